"""The reference tool's camera files (``intrinsics0.yaml``): CentralGenericModel, CentralOpenCVModel
and CentralThinPrismFisheyeModel.

Both are written as the reference tool's ``io/calibration_io.cc`` writes them: one ``key : value``
line per field in a fixed order, numbers with 14 significant digits (C++ ``setprecision(14)``),
positions in its pixel-corner convention (the top-left pixel's centre at ``(0.5, 0.5)``).

``CentralGenericModel``::

    type : CentralGenericModel
    width : W
    height : H
    calibration_min_x : ..      (and min_y, max_x, max_y: the calibrated area, integers)
    grid_width : GW
    grid_height : GH
    # The grid is stored in row-major order, top to bottom. ...
    grid : [x, y, z, x, y, z, ...]                    (GH rows top to bottom, each left to right)

The loader accepts the type name ``CentralGenericBSplineModel`` too, needs at least 4 x 4 nodes
and renormalises every vector.

``CentralOpenCVModel``: ``type``, ``width``, ``height``,
``parameters : [fx, fy, cx, cy, k1, k2, k3, k4, k5, k6, p1, p2]`` (OpenCV's rational model in
another order; ``cx, cy`` pixel-corner, i.e. OpenCV's plus 0.5). blurcalib's Brown-Conrady
camera maps to ``[fx, fy, cx + .5, cy + .5, k1, k2, k3, 0, 0, 0, p1, p2]``.

``CentralThinPrismFisheyeModel``: ``type``, ``width``, ``height``,
``use_equidistant_projection : true`` (or ``false``),
``parameters : [fx, fy, cx, cy, k1, k2, k3, k4, p1, p2, sx1, sy1]`` (``cx, cy`` pixel-corner).
A Kannala-Brandt camera is this model with ``p1 = p2 = sx1 = sy1 = 0``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.generic import PIXEL_CORNER_OFFSET, CentralGeneric
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.rational import RationalCamera
from blurcalib.camera.thin_prism import ThinPrismFisheyeCamera
from blurcalib.io.atomic import atomic_write_text

__all__ = [
    "RefCameraError",
    "read_generic_yaml",
    "read_opencv_yaml",
    "read_parametric_yaml",
    "write_generic_yaml",
    "write_opencv_yaml",
    "write_parametric_yaml",
]

GENERIC_TYPES = ("CentralGenericModel", "CentralGenericBSplineModel")
OPENCV_TYPE = "CentralOpenCVModel"
THIN_PRISM_TYPE = "CentralThinPrismFisheyeModel"
_OPENCV_ORDER = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
_THIN_PRISM_ORDER = ThinPrismFisheyeCamera.PARAM_NAMES
GRID_COMMENT = ("# The grid is stored in row-major order, top to bottom. Each row is stored left to "
                "right. Each grid point is stored as x, y, z.")
_INT_FIELDS = ("width", "height", "calibration_min_x", "calibration_min_y", "calibration_max_x",
               "calibration_max_y", "grid_width", "grid_height")


class RefCameraError(ValueError):
    """A reference camera file is missing, malformed or holds an unsupported model.

    The message names the file and the field.
    """


def _num(value: float) -> str:
    """A number as C++ ``ostream << setprecision(14)`` writes it (``%.14g``)."""
    return f"{float(value):.14g}"


def write_generic_yaml(path: str | os.PathLike[str], model: CentralGeneric) -> Path:
    """Write ``model`` as the reference tool's ``CentralGenericModel`` file (atomically)."""
    lines = [
        "type : CentralGenericModel",
        f"width : {model.width}",
        f"height : {model.height}",
        f"calibration_min_x : {model.min_x}",
        f"calibration_min_y : {model.min_y}",
        f"calibration_max_x : {model.max_x}",
        f"calibration_max_y : {model.max_y}",
        f"grid_width : {model.grid_width}",
        f"grid_height : {model.grid_height}",
        GRID_COMMENT,
        "grid : [" + ", ".join(_num(v) for v in model.grid.reshape(-1)) + "]",
    ]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def write_opencv_yaml(path: str | os.PathLike[str], camera: BrownConrady) -> Path:
    """Write a Brown-Conrady camera as the reference tool's ``CentralOpenCVModel`` file."""
    return write_parametric_yaml(path, BrownConradyCamera.from_brown_conrady(camera))


def write_parametric_yaml(path: str | os.PathLike[str], camera: ParametricCamera) -> Path:
    """Write a parametric camera as the reference tool's file (atomically): Brown-Conrady and
    the rational model as ``CentralOpenCVModel``, Kannala-Brandt and the thin-prism fisheye as
    ``CentralThinPrismFisheyeModel``."""
    values = {name: 0.0 for name in _OPENCV_ORDER + _THIN_PRISM_ORDER} | camera.named()
    values["cx"] += PIXEL_CORNER_OFFSET
    values["cy"] += PIXEL_CORNER_OFFSET
    order: tuple[str, ...]
    if isinstance(camera, BrownConradyCamera | RationalCamera):
        kind, order, extra = OPENCV_TYPE, _OPENCV_ORDER, []
    else:
        equidistant = camera.angular
        kind, order = THIN_PRISM_TYPE, _THIN_PRISM_ORDER
        extra = [f"use_equidistant_projection : {'true' if equidistant else 'false'}"]
    lines = [f"type : {kind}", f"width : {camera.width}", f"height : {camera.height}", *extra,
             "parameters : [" + ", ".join(_num(values[n]) for n in order) + "]"]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def _read_fields(path: Path) -> dict[str, str]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise RefCameraError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    fields: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        key, sep, value = stripped.partition(":")
        if not sep:
            raise RefCameraError(f"{path}: line {number} is not 'key : value': {stripped[:60]!r}")
        fields[key.strip()] = value.strip()
    return fields


def _field(path: Path, fields: dict[str, str], name: str) -> str:
    if name not in fields:
        raise RefCameraError(f"{path}: missing field {name!r}")
    return fields[name]


def _int_field(path: Path, fields: dict[str, str], name: str) -> int:
    raw = _field(path, fields, name)
    try:
        return int(raw)
    except ValueError:
        raise RefCameraError(f"{path}: field {name!r} must be an integer, got {raw[:40]!r}") from None


def _list_field(path: Path, fields: dict[str, str], name: str) -> np.ndarray:
    raw = _field(path, fields, name)
    if not (raw.startswith("[") and raw.endswith("]")):
        raise RefCameraError(f"{path}: field {name!r} must be a list [a, b, ...]")
    body = raw[1:-1].strip()
    try:
        values = np.array([float(v) for v in body.split(",")] if body else [], dtype=np.float64)
    except ValueError:
        raise RefCameraError(f"{path}: field {name!r} holds a value that is not a number") from None
    if not np.all(np.isfinite(values)):
        raise RefCameraError(f"{path}: field {name!r} holds a non-finite value")
    return values


def _type(path: Path, fields: dict[str, str], allowed: tuple[str, ...]) -> str:
    kind = _field(path, fields, "type")
    if kind not in allowed:
        raise RefCameraError(f"{path}: field 'type' is {kind!r}, expected {' or '.join(allowed)}")
    return kind


def read_generic_yaml(path: str | os.PathLike[str]) -> CentralGeneric:
    """Read a ``CentralGenericModel`` (or ``CentralGenericBSplineModel``) file.

    Raises:
        RefCameraError: naming the file and the missing or malformed field.
    """
    path = Path(path)
    fields = _read_fields(path)
    _type(path, fields, GENERIC_TYPES)
    ints = {name: _int_field(path, fields, name) for name in _INT_FIELDS}
    gw, gh = ints["grid_width"], ints["grid_height"]
    if gw < 4 or gh < 4:
        raise RefCameraError(f"{path}: field 'grid_width'/'grid_height' must be at least 4, got {gw} x {gh}")
    for name in ("width", "height"):
        if ints[name] <= 0:
            raise RefCameraError(f"{path}: field {name!r} must be positive, got {ints[name]}")
    grid = _list_field(path, fields, "grid")
    if grid.size != gw * gh * 3:
        raise RefCameraError(f"{path}: field 'grid' has {grid.size} numbers, expected "
                             f"grid_width x grid_height x 3 = {gw * gh * 3}")
    grid = grid.reshape(gh, gw, 3)
    if np.any(np.linalg.norm(grid, axis=-1) == 0):
        raise RefCameraError(f"{path}: field 'grid' holds a zero vector")
    try:
        return CentralGeneric(ints["width"], ints["height"], ints["calibration_min_x"],
                              ints["calibration_min_y"], ints["calibration_max_x"],
                              ints["calibration_max_y"], grid)
    except ValueError as exc:
        raise RefCameraError(f"{path}: field 'calibration_*': {exc}") from None


def read_opencv_yaml(path: str | os.PathLike[str]) -> BrownConrady:
    """Read a ``CentralOpenCVModel`` file as a Brown-Conrady camera (OpenCV pixels).

    Raises:
        RefCameraError: naming the file and the field; also when ``k4..k6`` are non-zero
            (a rational model blurcalib's Brown-Conrady camera cannot hold).
    """
    camera = _read_parametric(Path(path), (OPENCV_TYPE,))
    if not isinstance(camera, BrownConradyCamera):
        raise RefCameraError(f"{path}: field 'parameters' has non-zero k4..k6 (rational model); "
                             "only Brown-Conrady (k1, k2, k3, p1, p2) is supported")
    return camera.to_brown_conrady()


def read_parametric_yaml(path: str | os.PathLike[str]) -> ParametricCamera:
    """Read a ``CentralOpenCVModel`` or ``CentralThinPrismFisheyeModel`` file as the smallest
    model of the family that holds it: Brown-Conrady when ``k4..k6`` are 0, else the rational
    model; Kannala-Brandt for an equidistant thin-prism fisheye without ``p1, p2, sx1, sy1``.

    Raises:
        RefCameraError: naming the file and the missing or malformed field.
    """
    return _read_parametric(Path(path), (OPENCV_TYPE, THIN_PRISM_TYPE))


def _read_parametric(path: Path, allowed: tuple[str, ...]) -> ParametricCamera:
    fields = _read_fields(path)
    kind = _type(path, fields, allowed)
    width = _int_field(path, fields, "width")
    height = _int_field(path, fields, "height")
    params = _list_field(path, fields, "parameters")
    order = _OPENCV_ORDER if kind == OPENCV_TYPE else _THIN_PRISM_ORDER
    if params.size != len(order):
        raise RefCameraError(f"{path}: field 'parameters' has {params.size} numbers, expected {len(order)} "
                             f"[{', '.join(order)}]")
    values = dict(zip(order, (float(v) for v in params), strict=True))
    values["cx"] -= PIXEL_CORNER_OFFSET
    values["cy"] -= PIXEL_CORNER_OFFSET
    equidistant = True
    if kind == THIN_PRISM_TYPE:
        flag = _field(path, fields, "use_equidistant_projection")
        if flag not in ("true", "false"):
            raise RefCameraError(f"{path}: field 'use_equidistant_projection' must be true or false, "
                                 f"got {flag[:20]!r}")
        equidistant = flag == "true"
    try:
        return _smallest_model(kind, values, width, height, equidistant)
    except ValueError as exc:
        raise RefCameraError(f"{path}: field 'parameters': {exc}") from None


def _smallest_model(kind: str, values: dict[str, float], width: int, height: int, equidistant: bool
                    ) -> ParametricCamera:
    """The smallest model of the family holding a reference file's parameters."""
    if kind == OPENCV_TYPE:
        rational = any(values[k] != 0 for k in ("k4", "k5", "k6"))
        cls = RationalCamera if rational else BrownConradyCamera
        return cls.from_values(width, height, **{n: values[n] for n in cls.PARAM_NAMES})
    if equidistant and all(values[k] == 0 for k in ("p1", "p2", "sx1", "sy1")):
        return KannalaBrandtCamera.from_values(
            width, height, **{n: values[n] for n in KannalaBrandtCamera.PARAM_NAMES})
    return ThinPrismFisheyeCamera(np.array([values[n] for n in _THIN_PRISM_ORDER]), width, height,
                                  equidistant=equidistant)
