"""The parametric camera family by name: every model of :mod:`blurcalib.camera.lens` and the
conversions between a camera description (``to_dict``) and a camera."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.rational import RationalCamera
from blurcalib.camera.thin_prism import ThinPrismFisheyeCamera

__all__ = ["MODELS", "as_family", "camera_from_dict", "model_class"]

MODELS: dict[str, type[ParametricCamera]] = {
    cls.MODEL: cls for cls in (BrownConradyCamera, RationalCamera, KannalaBrandtCamera,
                               ThinPrismFisheyeCamera)}
"""Every model of the family by its name (``to_dict``'s ``model``)."""


def model_class(name: str) -> type[ParametricCamera]:
    """The model called ``name``; ValueError listing the known ones otherwise."""
    if name not in MODELS:
        raise ValueError(f"unknown camera model {name!r}; known: {', '.join(MODELS)}")
    return MODELS[name]


def camera_from_dict(data: Mapping[str, Any]) -> ParametricCamera:
    """The camera a ``to_dict`` describes (also :meth:`BrownConrady.to_dict`'s flat form)."""
    if not isinstance(data, Mapping):
        raise ValueError(f"camera description must be a mapping, got {type(data).__name__}")
    if "parameters" not in data and data.get("model", BrownConradyCamera.MODEL) == BrownConradyCamera.MODEL:
        return BrownConradyCamera.from_brown_conrady(BrownConrady.from_dict(data))
    return model_class(str(data.get("model"))).from_dict(data)


def as_family(camera: BrownConrady | ParametricCamera) -> ParametricCamera:
    """``camera`` behind the family's interface (a :class:`BrownConrady` becomes a
    :class:`BrownConradyCamera`)."""
    if isinstance(camera, BrownConrady):
        return BrownConradyCamera.from_brown_conrady(camera)
    return camera
