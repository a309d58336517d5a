"""Feature files to calibrate from (``blurcalib calibrate --features FILE``): the reference tool's
dataset ``.bin`` or blurcalib's own ``features.csv``, read and checked before any calibration runs.

Positions are in pixels, OpenCV convention (top-left pixel centre at ``(0, 0)``); a ``.bin`` holds
the reference tool's pixel-corner convention on disk and is converted on reading
(:mod:`blurcalib.io.refformat`).

Every check that the file alone decides is made here, each refusal one line naming the file and
the row (a ``features.csv``'s row, counted from 1 after the header) or the image (a ``.bin``'s):
the file's type and size (a regular file of at most :data:`MAX_FILE_BYTES`), the memory its table
would take (:data:`MAX_TABLE_BYTES`), the image size (:func:`blurcalib.io.frames.frame_size_problem`),
finite positions, weights in ``[0, MAX_WEIGHT]``, feature ids of the pattern at the feature
coordinates the pattern gives them, no feature observed twice in a frame, no two images of one
name, at least one sharp frame, at most :data:`MAX_FRAMES` frames and every position inside the
image.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from blurcalib.io.frames import frame_size_problem
from blurcalib.io.input_file import byte_size
from blurcalib.io.refformat import (
    RefDataset,
    RefFormatError,
    TargetFeatures,
    read_ref_dataset,
    ref_feature_table,
)
from blurcalib.io.results import (
    FeatureFlags,
    FeatureTable,
    ResultsFileError,
    read_feature_table,
    table_bytes,
)

MAX_FILE_BYTES: dict[str, int] = {".bin": 64_000_000, ".csv": 512_000_000}
"""Largest feature file read, per format (bytes): about 5 million observations either way (12
bytes each in a ``.bin``, about 100 in a ``features.csv``); a calibration of 2,000 frames of 250
features is 6 and 50 MB. A larger file is refused before it is read."""

MAX_TABLE_BYTES = 512_000_000
"""The most memory the features may take as a table (:func:`blurcalib.io.results.table_bytes`):
a ``features.csv`` is refused while it is read once its rows take more (long frame names make
every row wider)."""

MAX_FRAMES = 10_000
"""Most frames a feature file may hold; the calibration's memory grows with the frames."""

MAX_WEIGHT = 1e6
"""Largest feature weight accepted: weights are relative confidences (1 nominal; blurcalib writes
``1 / (1 + loss)`` in ``(0, 1]``); the bundle adjustment's normal equations sum weight times
squared residual, which a weight of 1e300 overflows."""

MIN_POSE_FEATURES = 6
"""Fewest features from which any calibration stage poses a frame."""


class FeatureInputError(ValueError):
    """A feature file cannot be calibrated from; the message names the file and the problem."""


def read_feature_input(path: str | os.PathLike[str], pattern: TargetFeatures,
                       image_size: tuple[int, int] | None = None) -> tuple[FeatureTable, tuple[int, int]]:
    """Features to calibrate from, and the image size: the reference tool's dataset ``.bin``
    (pixel-corner convention on disk; every frame sharp) or blurcalib's ``features.csv`` (rows
    flagged ``BLURRY_FRAME`` are blurry frames, those flagged ``FILTERED_OUT`` are left out; the
    size must be given, the file does not hold it), checked as the module docstring says.

    Raises:
        FeatureInputError: an unknown suffix, a file that is not a regular file or is too large, an
            unreadable or malformed file, a ``features.csv`` without ``image_size``, or a check
            that fails (the message names the file and the row or image).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in MAX_FILE_BYTES:
        raise FeatureInputError(f"{p}: features must be a reference dataset (.bin) or a blurcalib "
                                f"features.csv")
    if suffix == ".csv" and image_size is None:
        raise FeatureInputError(f"{p}: a features.csv does not hold the image size: give --image-size WxH")
    try:
        if suffix == ".bin":
            dataset = read_ref_dataset(p, MAX_FILE_BYTES[suffix])
            size = image_size or dataset.image_size
            _check_bin(p, dataset)
            table = ref_feature_table(dataset, pattern)
            where = _image_rows(dataset)
        else:
            if os.path.getsize(p) > MAX_FILE_BYTES[suffix]:
                raise FeatureInputError(f"{p}: {byte_size(os.path.getsize(p))}, more than the "
                                        f"{byte_size(MAX_FILE_BYTES[suffix])} a features file may have")
            assert image_size is not None  # a features.csv without one is refused above
            table, size = read_feature_table(p, MAX_TABLE_BYTES), image_size
            where = _csv_rows
            _check_ids(p, table, pattern, where)
    except (FileNotFoundError, RefFormatError, ResultsFileError) as exc:
        text = str(exc)
        raise FeatureInputError(text if text.startswith(f"{p}:") else f"{p}: {text}") from None
    except OSError as exc:
        raise FeatureInputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    _check_size(p, size)
    _check_values(p, table, where)
    _check_repeats(p, table, where)
    table = table.select((table.flags & int(FeatureFlags.FILTERED_OUT)) == 0)
    _check_frames(p, table)
    _check_inside(p, table, size)
    return table, size


def _csv_rows(i: int) -> str:
    """Row ``i`` (from 0) of a ``features.csv`` as its messages name it (rows from 1)."""
    return f"row {i + 1}"


def _image_rows(dataset: RefDataset) -> Callable[[int], str]:
    """Names of a ``.bin``'s table rows: the image and the feature record's place in it (from 0)."""
    ends = np.cumsum([len(img.features) for img in dataset.images])

    def where(i: int) -> str:
        j = int(np.searchsorted(ends, i, side="right"))
        k = i - (int(ends[j - 1]) if j else 0)
        return f"image {dataset.images[j].name!r} record {k}"

    return where


def _number(value: float) -> str:
    """A value for a message: short whatever its size (1e300 is not written as 300 digits)."""
    return f"{value:.1f}" if abs(value) < 1e6 else f"{value:.3g}"


def _check_bin(path: Path, dataset: RefDataset) -> None:
    """Two images of one name, or a table too large for memory (:data:`MAX_TABLE_BYTES`)."""
    seen: dict[str, int] = {}
    for j, img in enumerate(dataset.images):
        if img.name in seen:
            raise FeatureInputError(f"{path}: images {seen[img.name]} and {j} are both named {img.name!r}: "
                                    f"each image of a dataset needs a name of its own")
        seen[img.name] = j
    rows = sum(len(img.features) for img in dataset.images)
    longest = max((len(img.name) for img in dataset.images), default=0)
    if table_bytes(rows, longest) > MAX_TABLE_BYTES:
        raise FeatureInputError(f"{path}: too large: its {rows} features (image names of up to {longest} "
                                f"characters) take {byte_size(table_bytes(rows, longest))} in memory, more "
                                f"than the {byte_size(MAX_TABLE_BYTES)} a features file may fill")


def _check_size(path: Path, size: tuple[int, int]) -> None:
    """An image size that no frame may have (:func:`blurcalib.io.frames.frame_size_problem`)."""
    problem = frame_size_problem(*size)
    if problem is not None:
        raise FeatureInputError(f"{path}: the image size {problem.removeprefix('is ')}")


def _check_ids(path: Path, table: FeatureTable, pattern: TargetFeatures,
               where: Callable[[int], str]) -> None:
    """Feature ids outside the pattern's, or feature coordinates ``(fx, fy)`` other than the
    pattern gives the id (a file of another pattern)."""
    bad = np.flatnonzero((table.feature_id < 0) | (table.feature_id >= pattern.num_features))
    if len(bad):
        raise FeatureInputError(f"{path}: {where(int(bad[0]))}: feature id {int(table.feature_id[bad[0]])} "
                                f"is not one of the pattern's ids 0 to {pattern.num_features - 1}")
    expected = np.asarray(pattern.features)[table.feature_id] if len(table) else np.zeros((0, 2))
    bad = np.flatnonzero((expected[:, 0] != table.fx) | (expected[:, 1] != table.fy))
    if len(bad):
        i = int(bad[0])
        raise FeatureInputError(f"{path}: {where(i)}: feature {int(table.feature_id[i])} is at feature "
                                f"coordinates ({int(expected[i, 0])}, {int(expected[i, 1])}) in the pattern, "
                                f"the file says ({int(table.fx[i])}, {int(table.fy[i])}): features of "
                                f"another pattern?")


def _check_values(path: Path, table: FeatureTable, where: Callable[[int], str]) -> None:
    """Positions that are not finite, and weights outside ``[0, MAX_WEIGHT]``."""
    for name in ("x", "y", "X", "Y"):
        values = getattr(table, name)
        bad = np.flatnonzero(~np.isfinite(values))
        if len(bad):
            raise FeatureInputError(f"{path}: {where(int(bad[0]))}: {name} is {values[bad[0]]}; positions "
                                    f"must be finite numbers")
    w = table.weight
    bad = np.flatnonzero(~((w >= 0) & (w <= MAX_WEIGHT)))
    if len(bad):
        raise FeatureInputError(f"{path}: {where(int(bad[0]))}: weight {w[bad[0]]:.3g} is outside 0 to "
                                f"{MAX_WEIGHT:.0e} (a relative confidence, 1 nominal)")


def _check_repeats(path: Path, table: FeatureTable, where: Callable[[int], str]) -> None:
    """A feature observed twice in one frame."""
    if not len(table):
        return
    _, frame_code = np.unique(table.frame, return_inverse=True)
    key = frame_code.reshape(-1).astype(np.int64) * (int(table.feature_id.max()) + 1) + table.feature_id
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    first_of = first[inverse.reshape(-1)]
    repeats = np.flatnonzero(first_of != np.arange(len(table)))
    if len(repeats):
        i = int(repeats[0])
        raise FeatureInputError(f"{path}: {where(i)} repeats {where(int(first_of[i]))}: feature "
                                f"{int(table.feature_id[i])} observed twice in frame {str(table.frame[i])!r}")


def _check_frames(path: Path, table: FeatureTable) -> None:
    """No features, no sharp frame, or more than :data:`MAX_FRAMES` frames."""
    if not len(table):
        raise FeatureInputError(f"{path}: no features to calibrate from (every row flagged FILTERED_OUT, "
                                f"or none)")
    blurry = int(FeatureFlags.BLURRY_FRAME)
    if np.all((table.flags & blurry) != 0):
        raise FeatureInputError(f"{path}: every row is flagged BLURRY_FRAME ({blurry}): the parametric "
                                f"camera is calibrated on sharp frames, rows without that flag")
    names, counts = np.unique(table.frame, return_counts=True)
    if len(names) > MAX_FRAMES:
        few = int(np.count_nonzero(counts < MIN_POSE_FEATURES))
        raise FeatureInputError(f"{path}: {len(names)} frames, more than the {MAX_FRAMES} a calibration takes"
                                + (f"; {few} of them have fewer than {MIN_POSE_FEATURES} features, which no "
                                   f"calibration can use" if few else "")
                                + ": select the frames to calibrate from")


def _check_inside(path: Path, table: FeatureTable, size: tuple[int, int]) -> None:
    """Raise :class:`FeatureInputError` when a feature lies outside the image ``size`` (px, OpenCV
    convention: the image spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``): a wrong ``--image-size``."""
    width, height = size
    x_max, y_max = float(table.x.max()), float(table.y.max())
    x_min, y_min = float(table.x.min()), float(table.y.min())
    if x_min < -0.5 or y_min < -0.5 or x_max > width - 0.5 or y_max > height - 0.5:
        raise FeatureInputError(f"{path}: features span x {_number(x_min)} to {_number(x_max)} px, y "
                                f"{_number(y_min)} to {_number(y_max)} px, outside the {width} x {height} "
                                f"image: is the image size right (--image-size WxH)?")
