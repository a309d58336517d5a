"""Feature files to calibrate from (``blurcalib calibrate --features FILE``): the reference tool's
dataset ``.bin`` or blurcalib's own ``features.csv``, read and checked before any calibration runs.

Positions are in pixels, OpenCV convention (top-left pixel centre at ``(0, 0)``); a ``.bin`` holds
the reference tool's pixel-corner convention on disk and is converted on reading
(:mod:`blurcalib.io.refformat`).
"""

from __future__ import annotations

import os
from pathlib import Path

from blurcalib.io.refformat import RefFormatError, TargetFeatures, read_ref_dataset, ref_feature_table
from blurcalib.io.results import FeatureFlags, FeatureTable, ResultsFileError, read_feature_table


class FeatureInputError(ValueError):
    """A feature file cannot be calibrated from; the message names the file and the problem."""


def read_feature_input(path: str | os.PathLike, pattern: TargetFeatures,
                       image_size: tuple[int, int] | None = None) -> tuple[FeatureTable, tuple[int, int]]:
    """Features to calibrate from, and the image size: the reference tool's dataset ``.bin``
    (pixel-corner convention on disk; every frame sharp) or blurcalib's ``features.csv`` (rows
    flagged ``BLURRY_FRAME`` are blurry frames, those flagged ``FILTERED_OUT`` are left out; the
    size must be given, the file does not hold it).

    Raises:
        FeatureInputError: an unknown suffix, an unreadable or malformed file, or a ``features.csv``
            without ``image_size``.
    """
    p = Path(path)
    try:
        if p.suffix.lower() == ".bin":
            dataset = read_ref_dataset(p)
            table, size = ref_feature_table(dataset, pattern), image_size or dataset.image_size
        elif p.suffix.lower() == ".csv":
            if image_size is None:
                raise FeatureInputError(f"{p}: a features.csv does not hold the image size: give "
                                        f"--image-size WxH")
            table, size = read_feature_table(p), image_size
            table = table.select((table.flags & int(FeatureFlags.FILTERED_OUT)) == 0)
            if len(table) and int(table.feature_id.max()) >= pattern.num_features:
                raise FeatureInputError(f"{p}: feature id {int(table.feature_id.max())} is not one of the "
                                        f"pattern's {pattern.num_features} features")
        else:
            raise FeatureInputError(f"{p}: features must be a reference dataset (.bin) or a blurcalib "
                                    f"features.csv")
    except FeatureInputError:
        raise
    except (OSError, RefFormatError, ResultsFileError, ValueError) as exc:
        raise FeatureInputError(f"{p}: {exc}") from None
    _check_inside(p, table, size)
    return table, size


def _check_inside(path: Path, table: FeatureTable, size: tuple[int, int]) -> None:
    """Raise :class:`FeatureInputError` when a feature lies outside the image ``size`` (px, OpenCV
    convention: the image spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``): a wrong ``--image-size``."""
    if not len(table):
        return
    width, height = size
    x_max, y_max = float(table.x.max()), float(table.y.max())
    x_min, y_min = float(table.x.min()), float(table.y.min())
    if x_min < -0.5 or y_min < -0.5 or x_max > width - 0.5 or y_max > height - 0.5:
        raise FeatureInputError(f"{path}: features span x {x_min:.1f} to {x_max:.1f} px, y {y_min:.1f} to "
                                f"{y_max:.1f} px, outside the {width} x {height} image: is the image size "
                                f"right (--image-size WxH)?")
