"""Results of feature and PSF extraction, and their one on-disk format.

Conventions (see ``docs/results-format.md``):

* Pixel coordinates follow OpenCV: the centre of the top-left pixel is ``(0, 0)``, x right,
  y down.
* Feature ``(fx, fy)`` sits at the metric target point ``(fx L, fy L, 0)`` metres.
* A *block* is the star square around one feature; its homography ``H`` (3 x 3) maps block
  coordinates ``q in [-1, 1]^2`` (star centre at 0, square corners at ``(+-1, +-1)``, i.e.
  feature coordinates ``p = (fx, fy) + q / 2``) to pixels.
* PSF pixel ``(i, j)`` (row, column) of a ``K x K`` kernel sits at offset ``(j - c, i - c)``
  px from the kernel centre, ``c = (K - 1) / 2``.

One output folder holds ``features.csv`` (one row per feature observation), ``blocks.csv`` (one
row per fitted block) and ``psfs.npz`` (the blocks' kernels and homographies, in the rows' order).
Floats are written with ``repr`` so that float64 values round-trip exactly. Resumable runs write
the same files per frame (:mod:`blurcalib.io.frame_files`). Every file is written atomically.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum, IntFlag
from pathlib import Path
from typing import cast

import numpy as np

from blurcalib.geometry.homography import homography_centre
from blurcalib.io.atomic import (
    atomic_path,
    atomic_write_text,
    ensure_writable_dir,
    read_csv_columns,
)
from blurcalib.io.csv_reader import csv_chunks
from blurcalib.io.input_file import byte_size
from blurcalib.psf.kernel import blur_per_square

FEATURES_FILE = "features.csv"
BLOCKS_FILE = "blocks.csv"
PSFS_FILE = "psfs.npz"
CORNERS_FILE = "corners.csv"
FRAMES_DIR = "frames"

FEATURE_COLUMNS: tuple[str, ...] = ("frame", "feature_id", "fx", "fy", "X", "Y", "x", "y", "weight",
                                    "flags")
"""Columns of ``features.csv``, in order."""

H_COLUMNS: tuple[str, ...] = tuple(f"h{r}{c}" for r in range(3) for c in range(3))
COEFF_COLUMNS: tuple[str, ...] = ("a1", "a2", "a3", "b1", "b2", "b3")
BLOCK_COLUMNS: tuple[str, ...] = (
    "frame", "feature_id", "fx", "fy", "status", "loss", "boundary_energy", "sigma_major",
    "sigma_minor", "eccentricity", "orientation", "centroid_x", "centroid_y",
    *H_COLUMNS, *COEFF_COLUMNS, "loss_extent", "noise_var")
"""Columns of ``blocks.csv``, in order (a file without the last two reads ``loss_extent`` as 1 and
``noise_var`` as NaN)."""

BLUR_PER_SQUARE_LIMIT = 1.25
""":attr:`BlockTable.blur_per_square` from which fewer blocks are found, and those found are poorer,
even with the frame's path-PSF field (``scripts/bench_yield.py`` prints the share returned by
class of blur per square; docs/decisions/path-psf-field.md)."""

CORNER_COLUMNS: tuple[str, ...] = ("frame", "cx2", "cy2", "X", "Y", "x", "y", "blocks")
"""Columns of ``corners.csv``: the corner's feature coordinates doubled (``cx2 = 2 fx + 1`` for
the corner half a square right of feature ``fx``), its metric point ``(cx2 L / 2, cy2 L / 2)``
(m), its image position (px, OpenCV convention) and the number of blocks that share it."""


class ResultsFileError(ValueError):
    """A results file is missing or malformed; the message names the file and the column/row."""


class BlockStatus(str, Enum):
    """Outcome of fitting one block: ``accepted`` or the reason it was rejected."""

    ACCEPTED = "accepted"
    HIGH_LOSS = "high_loss"
    OUTSIDE_IMAGE = "outside_image"
    DEGENERATE_HOMOGRAPHY = "degenerate_homography"
    PSF_TRUNCATED = "psf_truncated"
    NOT_CONVERGED = "not_converged"
    FILTERED_BOUNDARY_ENERGY = "filtered_boundary_energy"
    FILTERED_LOSS = "filtered_loss"
    DISCONNECTED = "disconnected"


class FeatureFlags(IntFlag):
    """Bit mask describing how a feature observation was obtained."""

    NONE = 0
    STAR_CENTRE = 1
    """The observation is a star centre (the only kind of feature so far)."""
    SHARP_FRAME = 2
    """Extracted from a sharp frame (PSF close to a delta)."""
    BLURRY_FRAME = 4
    """Extracted from a motion-blurred frame with a fitted PSF."""
    LOCALLY_ALIGNED = 8
    """Position refined by the per-block (local) alignment."""
    GLOBALLY_ALIGNED = 16
    """Position refined by the frame-wide (global) alignment."""
    FILTERED_OUT = 32
    """Rejected by a later filter; kept for diagnostics, not to be used for calibration."""
    LENS_CORRECTED = 64
    """Moved by minus the bias of its block homography under the calibrated lens's distortion
    (:mod:`blurcalib.calib.lens_bias`)."""


@dataclass(frozen=True)
class FeatureObservation:
    """One observed feature: a star centre's pixel position in one frame.

    Attributes:
        frame: frame name.
        feature_id: id of the feature in :attr:`StarPattern.features`.
        fx, fy: integer feature coordinates (squares).
        X, Y: metric target point ``(fx L, fy L)`` in metres (Z = 0).
        x, y: pixel position, OpenCV convention (top-left pixel centre at (0, 0)).
        weight: relative confidence, >= 0 (1 nominal).
        flags: :class:`FeatureFlags` bit mask.
    """

    frame: str
    feature_id: int
    fx: int
    fy: int
    X: float
    Y: float
    x: float
    y: float
    weight: float
    flags: int


# -------------------------------------------------------------------------------- column tables
def _column(values: Sequence[object] | np.ndarray, dtype: type, n: int | None = None) -> np.ndarray:
    out: np.ndarray = np.asarray(values, dtype=dtype)
    if out.ndim != 1 or (n is not None and len(out) != n):
        raise ValueError(f"column must be 1-D of length {n}, got shape {out.shape}")
    return out


@dataclass(eq=False)
class FeatureTable:
    """Feature observations as numpy columns (N rows); the fast form for large sets.

    Columns (all ``(N,)``): ``frame`` str, ``feature_id, fx, fy, flags`` int64,
    ``X, Y`` metres and ``x, y`` px (OpenCV convention) and ``weight``, float64.
    """

    frame: np.ndarray
    feature_id: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    x: np.ndarray
    y: np.ndarray
    weight: np.ndarray
    flags: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.frame)
        self.frame = _column(self.frame, np.str_, n)
        for name in ("feature_id", "fx", "fy", "flags"):
            setattr(self, name, _column(getattr(self, name), np.int64, n))
        for name in ("X", "Y", "x", "y", "weight"):
            setattr(self, name, _column(getattr(self, name), np.float64, n))

    def __len__(self) -> int:
        return len(self.frame)

    @classmethod
    def empty(cls) -> FeatureTable:
        """A table with no rows."""
        return cls(np.array([], dtype=np.str_), *(np.zeros(0) for _ in FEATURE_COLUMNS[1:]))

    @classmethod
    def from_observations(cls, features: Sequence[FeatureObservation]) -> FeatureTable:
        """Columns of a list of observations (row order kept)."""
        if not features:
            return cls.empty()
        return cls(*(np.asarray(col) for col in zip(*((f.frame, f.feature_id, f.fx, f.fy, f.X, f.Y, f.x, f.y,
                                                 f.weight, f.flags) for f in features), strict=True)))

    def to_observations(self) -> list[FeatureObservation]:
        """One :class:`FeatureObservation` per row, with plain Python values."""
        cols = [getattr(self, name).tolist() for name in FEATURE_COLUMNS]
        return [FeatureObservation(*row) for row in zip(*cols, strict=True)]

    def select(self, rows: np.ndarray) -> FeatureTable:
        """The rows chosen by a boolean mask or an index array."""
        return FeatureTable(*(getattr(self, name)[rows] for name in FEATURE_COLUMNS))

    @classmethod
    def concat(cls, tables: Sequence[FeatureTable]) -> FeatureTable:
        """Rows of several tables, in order."""
        if not tables:
            return cls.empty()
        return cls(*(np.concatenate([getattr(t, name) for t in tables]) for name in FEATURE_COLUMNS))


@dataclass(eq=False)
class BlockTable:
    """The fitted blocks (star squares) of one or more frames as numpy columns (B rows, one
    kernel size K): what extraction returns, the files hold and the pipeline and the app use.

    Columns:
        frame: ``(B,)`` str, frame name.
        feature_id, fx, fy: ``(B,)`` int64, the block's feature (:attr:`StarPattern.features`)
            and its integer feature coordinates (squares).
        status: ``(B,)`` str, a :class:`BlockStatus` value: accepted, or why it was rejected.
        loss: ``(B,)`` mean squared residual (8-bit grey levels squared).
        boundary_energy: ``(B,)`` share of PSF energy in the kernel's outer two-pixel ring.
        sigma_major, sigma_minor: ``(B,)`` px, square roots of the PSF second-moment eigenvalues.
        eccentricity: ``(B,)`` ``sqrt(1 - sigma_minor^2 / sigma_major^2)`` (0 round, 1 a line).
        orientation: ``(B,)`` rad in ``(-pi/2, pi/2]``, major axis from +x towards +y.
        centroid: ``(B, 2)`` px, PSF intensity centroid relative to the kernel centre.
        H: ``(B, 3, 3)`` float64 homographies, block coordinates ``q`` -> pixels.
        coeffs: ``(B, 6)`` float64 ``a1, a2, a3, b1, b2, b3`` of the paper's affine intensity
            model ``A(p) = a1 u + a2 v + a3``, ``B(p) = b1 u + b2 v + b3`` (grey levels).
        psf: ``(B, K, K)`` float32 kernels, each summing to 1; pixel ``(i, j)`` at offset
            ``(j - c, i - c)`` px, ``c = (K - 1) / 2``.
        loss_extent: ``(B,)`` the area the block was fitted over, ``|q|_inf <= loss_extent``
            (1: its square; :attr:`blurcalib.deconv.settings.DeconvSettings.loss_extent`); 1 when not given.
        noise_var: ``(B,)`` the frame's noise variance at the block's brightness (grey levels^2,
            :meth:`blurcalib.growth.noise.NoiseModel.block_variance`): the unit of the noise-relative
            loss threshold; NaN when not known.
    """

    frame: np.ndarray
    feature_id: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    status: np.ndarray
    loss: np.ndarray
    boundary_energy: np.ndarray
    sigma_major: np.ndarray
    sigma_minor: np.ndarray
    eccentricity: np.ndarray
    orientation: np.ndarray
    centroid: np.ndarray
    H: np.ndarray
    coeffs: np.ndarray
    psf: np.ndarray
    loss_extent: np.ndarray | None = None
    noise_var: np.ndarray | None = None

    _SCALARS = ("loss", "boundary_energy", "sigma_major", "sigma_minor", "eccentricity", "orientation")
    _FIELDS = ("frame", "feature_id", "fx", "fy", "status", *_SCALARS, "centroid", "H", "coeffs", "psf",
               "loss_extent", "noise_var")

    def __post_init__(self) -> None:
        n = len(self.frame)
        self.frame = _column(self.frame, np.str_, n)
        statuses = self.status.tolist() if isinstance(self.status, np.ndarray) else list(self.status)
        self.status = _column([BlockStatus(s).value for s in statuses], np.str_, n)
        for name in ("feature_id", "fx", "fy"):
            setattr(self, name, _column(getattr(self, name), np.int64, n))
        for name in self._SCALARS:
            setattr(self, name, _column(getattr(self, name), np.float64, n))
        self.centroid = np.asarray(self.centroid, dtype=np.float64).reshape(n, 2)
        self.H = np.asarray(self.H, dtype=np.float64).reshape(n, 3, 3)
        self.coeffs = np.asarray(self.coeffs, dtype=np.float64).reshape(n, 6)
        self.loss_extent = _column(np.ones(n) if self.loss_extent is None else self.loss_extent,
                                   np.float64, n)
        self.noise_var = _column(np.full(n, np.nan) if self.noise_var is None else self.noise_var,
                                 np.float64, n)
        self.psf = np.asarray(self.psf, dtype=np.float32)
        if self.psf.ndim != 3 or self.psf.shape[0] != n or self.psf.shape[1] != self.psf.shape[2]:
            raise ValueError(f"psf must be ({n}, K, K), got {self.psf.shape}")

    def __len__(self) -> int:
        return len(self.frame)

    @classmethod
    def empty(cls, kernel_size: int = 0) -> BlockTable:
        """A table with no rows and kernels of ``kernel_size``."""
        return cls(np.array([], dtype=np.str_),
                   **{n: np.zeros(0) for n in cls._FIELDS[1:5 + len(cls._SCALARS)]},
                   centroid=np.zeros((0, 2)), H=np.zeros((0, 3, 3)), coeffs=np.zeros((0, 6)),
                   psf=np.zeros((0, kernel_size, kernel_size)))

    @property
    def centre(self) -> np.ndarray:
        """``(B, 2)`` px star centres ``H(0, 0)``; NaN for a degenerate ``H``."""
        return homography_centre(self.H)

    @property
    def accepted(self) -> np.ndarray:
        """``(B,)`` bool, the blocks whose status is ``accepted``."""
        return cast(np.ndarray, self.status == BlockStatus.ACCEPTED.value)

    @property
    def blur_per_square(self) -> np.ndarray:
        """``(B,)`` blur extent over the star square's side (:func:`blurcalib.psf.kernel.blur_per_square`).
        From :data:`BLUR_PER_SQUARE_LIMIT` even the frame's path-PSF field locates few stars
        (docs/deconvolution.md); NaN where not fitted."""
        return blur_per_square(self.sigma_major, self.H)

    def features(self, square_length_m: float, flags: int) -> FeatureTable:
        """One star-centre observation per row: ``(x, y)`` the star centre, ``(X, Y) = (fx L,
        fy L)`` m, weight ``1 / (1 + loss)``, every row with the :class:`FeatureFlags` ``flags``."""
        centre = self.centre
        return FeatureTable(self.frame, self.feature_id, self.fx, self.fy, self.fx * square_length_m,
                            self.fy * square_length_m, centre[:, 0], centre[:, 1], 1.0 / (1.0 + self.loss),
                            np.full(len(self), int(flags)))

    def select(self, rows: np.ndarray) -> BlockTable:
        """The rows chosen by a boolean mask or an index array."""
        return BlockTable(*(getattr(self, name)[rows] for name in self._FIELDS))

    @classmethod
    def concat(cls, tables: Sequence[BlockTable]) -> BlockTable:
        """Rows of several tables, in order; kernels are zero-padded (centred) to the largest
        size, which leaves them unchanged as kernels (the PSF window adapts to each frame's blur)."""
        nonempty = [t for t in tables if len(t)]
        if not nonempty:
            return tables[0] if tables else cls.empty()
        size = max(t.psf.shape[1] for t in nonempty)
        if any((size - t.psf.shape[1]) % 2 for t in nonempty):
            raise ValueError(f"cannot centre PSFs of sizes {sorted({t.psf.shape[1] for t in nonempty})}")

        def column(t: BlockTable, name: str) -> np.ndarray:
            if name != "psf":
                return cast(np.ndarray, getattr(t, name))
            p = (size - t.psf.shape[1]) // 2
            return np.pad(t.psf, ((0, 0), (p, p), (p, p)))

        return cls(*(np.concatenate([column(t, name) for t in nonempty]) for name in cls._FIELDS))


# ------------------------------------------------------------------------------------- writing
def _float_strings(values: np.ndarray) -> list[str]:
    return list(map(repr, np.asarray(values, dtype=np.float64).tolist()))


def _int_strings(values: np.ndarray) -> list[str]:
    return list(map(str, np.asarray(values, dtype=np.int64).tolist()))


def _csv_field(text: str) -> str:
    """A CSV field as the ``csv`` module writes it (quoted only when it must be)."""
    if any(ch in text for ch in ',"\r\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def _str_strings(values: np.ndarray) -> list[str]:
    names = np.asarray(values).tolist()
    quoted = {name: _csv_field(name) for name in set(names)}
    return [quoted[name] for name in names]


def _csv_text(header: Sequence[str], columns: Sequence[list[str]]) -> str:
    lines = [",".join(header), *map(",".join, zip(*columns, strict=True))]
    return "\n".join(lines) + "\n"


def as_feature_table(features: Sequence[FeatureObservation] | FeatureTable) -> FeatureTable:
    """``features`` as a :class:`FeatureTable`."""
    return features if isinstance(features, FeatureTable) else FeatureTable.from_observations(features)


def write_features(path: str | os.PathLike[str],
                   features: Sequence[FeatureObservation] | FeatureTable) -> Path:
    """Write ``features.csv`` (columns :data:`FEATURE_COLUMNS`) atomically; return its path."""
    t = as_feature_table(features)
    cols = [_str_strings(t.frame), *(_int_strings(getattr(t, n)) for n in ("feature_id", "fx", "fy")),
            *(_float_strings(getattr(t, n)) for n in ("X", "Y", "x", "y", "weight")),
            _int_strings(t.flags)]
    return atomic_write_text(path, _csv_text(FEATURE_COLUMNS, cols))


def write_blocks(csv_path: str | os.PathLike[str], npz_path: str | os.PathLike[str],
                 t: BlockTable) -> tuple[Path, Path]:
    """Write ``blocks.csv`` and ``psfs.npz`` atomically (each on its own); return their paths."""
    assert t.loss_extent is not None and t.noise_var is not None  # filled in by BlockTable
    cols = [_str_strings(t.frame), *(_int_strings(getattr(t, n)) for n in ("feature_id", "fx", "fy")),
            _str_strings(t.status), *(_float_strings(getattr(t, n)) for n in BlockTable._SCALARS),
            *(_float_strings(t.centroid[:, i]) for i in range(2)),
            *(_float_strings(t.H[:, r, c]) for r in range(3) for c in range(3)),
            *(_float_strings(t.coeffs[:, i]) for i in range(6)), _float_strings(t.loss_extent),
            _float_strings(t.noise_var)]
    atomic_write_text(csv_path, _csv_text(BLOCK_COLUMNS, cols))
    with atomic_path(npz_path) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, frame=t.frame, feature_id=t.feature_id, psf=t.psf, H=t.H)
    return Path(csv_path), Path(npz_path)


def write_results(folder: str | os.PathLike[str], features: Sequence[FeatureObservation] | FeatureTable,
                  blocks: BlockTable) -> dict[str, Path]:
    """Write ``features.csv``, ``blocks.csv`` and ``psfs.npz`` into ``folder`` (created if needed).

    The inputs are validated before anything is written; each file is replaced atomically.

    Returns:
        ``{"features": ..., "blocks": ..., "psfs": ...}`` paths.
    Raises:
        OutputError: the folder cannot be created or written.
    """
    feature_table = as_feature_table(features)
    out = ensure_writable_dir(folder)
    paths = {"features": write_features(out / FEATURES_FILE, feature_table)}
    paths["blocks"], paths["psfs"] = write_blocks(out / BLOCKS_FILE, out / PSFS_FILE, blocks)
    return paths


# ------------------------------------------------------------------------------------- reading
def _quoted(value: str, limit: int = 40) -> str:
    """A field's text for a message, shortened to ``limit`` characters."""
    return repr(value) if len(value) <= limit else repr(value[:limit - 3]) + "..."


def _parse(path: Path, name: str, values: list[str], convert: Callable[[str], object],
           dtype: type, kind: str, first_row: int = 1) -> np.ndarray:
    try:
        return np.array(list(map(convert, values)), dtype=dtype)
    except (ValueError, OverflowError):
        for row, value in enumerate(values, start=first_row):
            try:
                np.array(convert(value), dtype=dtype)
            except (ValueError, OverflowError):
                raise ResultsFileError(f"{path}: column '{name}', row {row}: cannot parse {_quoted(value)} "
                                       f"as {kind}") from None
        raise


def _floats(path: Path, cols: dict[str, list[str]], name: str, first_row: int = 1) -> np.ndarray:
    return _parse(path, name, cols[name], float, np.float64, "a float", first_row)


def _ints(path: Path, cols: dict[str, list[str]], name: str, first_row: int = 1) -> np.ndarray:
    return _parse(path, name, cols[name], int, np.int64, "a 64-bit integer", first_row)


def table_bytes(rows: int, longest_name: int) -> int:
    """Memory (bytes) of a :class:`FeatureTable` of ``rows`` rows whose longest frame name has
    ``longest_name`` characters: nine 8-byte columns and the frame column, 4 bytes per character
    of its longest name in every row."""
    return rows * (9 * 8 + 4 * longest_name)


def read_feature_table(path: str | os.PathLike[str], max_bytes: int | None = None) -> FeatureTable:
    """Read a ``features.csv`` into columns, a chunk of rows at a time.

    Args:
        path: the file.
        max_bytes: the most memory the table may take (:func:`table_bytes`; None: any); the
            file is refused as soon as the rows read so far take more.
    Raises:
        ResultsFileError: missing file, not a regular file, missing column, wrong field count, an
            unparsable value or a value beyond 64 bits, or more rows than ``max_bytes`` allows
            (the message names the file and the column/row; rows count from 1 after the header).
    """
    p = Path(path)
    parts, rows, longest = [], 0, 0
    for first, cols in csv_chunks(p, FEATURE_COLUMNS, ResultsFileError, "results file"):
        part = FeatureTable(
            np.array(cols["frame"], dtype=np.str_),
            **{n: _ints(p, cols, n, first) for n in ("feature_id", "fx", "fy")},
            **{n: _floats(p, cols, n, first) for n in ("X", "Y", "x", "y", "weight")},
            flags=_ints(p, cols, "flags", first))
        parts.append(part)
        rows, longest = rows + len(part), max(longest, part.frame.dtype.itemsize // 4)
        if max_bytes is not None and table_bytes(rows, longest) > max_bytes:
            raise ResultsFileError(
                f"{p}: too large: its first {rows} rows (frame names of up to {longest} characters) "
                f"take {byte_size(table_bytes(rows, longest))} in memory, more than the "
                f"{byte_size(max_bytes)} a features file may fill")
    return parts[0] if len(parts) == 1 else FeatureTable.concat(parts)


def read_features(path: str | os.PathLike[str]) -> list[FeatureObservation]:
    """Read a ``features.csv`` into observations (see :func:`read_feature_table`)."""
    return read_feature_table(path).to_observations()


def _status(path: Path, values: list[str]) -> np.ndarray:
    valid = {s.value for s in BlockStatus}
    for row, value in enumerate(values, start=1):
        if value not in valid:
            raise ResultsFileError(f"{path}: column 'status', row {row}: {value!r} is not one of "
                                   f"{', '.join(sorted(valid))}")
    return np.array(values, dtype=np.str_)


def _read_psfs(path: Path, n: int) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise ResultsFileError(f"{path}: results file not found") from None
    except (OSError, ValueError, EOFError) as exc:
        raise ResultsFileError(f"{path}: not a readable npz archive ({exc})") from None
    shapes = {"frame": (n,), "feature_id": (n,), "H": (n, 3, 3)}
    for key in ("frame", "feature_id", "psf", "H"):
        if key not in arrays:
            raise ResultsFileError(f"{path}: missing array '{key}'")
    for key, shape in shapes.items():
        if arrays[key].shape != shape:
            raise ResultsFileError(f"{path}: array '{key}' has shape {arrays[key].shape}, expected {shape}")
    psf = arrays["psf"]
    if psf.ndim != 3 or psf.shape[0] != n or psf.shape[1] != psf.shape[2]:
        raise ResultsFileError(f"{path}: array 'psf' has shape {psf.shape}, expected ({n}, K, K)")
    return arrays


def read_block_table(folder: str | os.PathLike[str]) -> BlockTable:
    """Read ``blocks.csv`` and ``psfs.npz`` of a results folder into columns.

    The npz rows must match the CSV rows (same frame, feature id and homography).

    Raises:
        ResultsFileError: a missing file, column or array, an unparsable value or a mismatch
            between the two files (the message names the file and the column/row).
    """
    return read_block_files(Path(folder) / BLOCKS_FILE, Path(folder) / PSFS_FILE)


def read_block_files(csv_path: Path, npz_path: Path) -> BlockTable:
    """The block table of the files ``csv_path`` (``blocks.csv``'s columns) and ``npz_path``
    (``psfs.npz``'s arrays): :func:`read_block_table` of any pair of them.

    Raises:
        ResultsFileError: a missing or malformed file, or files that do not match.
    """
    cols, n = read_csv_columns(csv_path, BLOCK_COLUMNS[:-2], ResultsFileError, "results file",
                               optional=BLOCK_COLUMNS[-2:])
    frame = np.array(cols["frame"], dtype=np.str_)
    feature_id = _ints(csv_path, cols, "feature_id")
    H = np.stack([_floats(csv_path, cols, c) for c in H_COLUMNS], axis=1).reshape(n, 3, 3)
    arrays = _read_psfs(npz_path, n)
    for key, ours in (("frame", frame), ("feature_id", feature_id), ("H", H)):
        differs = arrays[key] != ours
        if key == "H":
            differs &= ~(np.isnan(arrays[key]) & np.isnan(ours))
        bad: Sequence[int] | np.ndarray = np.flatnonzero(differs.reshape(n, -1).any(axis=1)) if n else []
        if len(bad):
            raise ResultsFileError(f"{npz_path}: array '{key}' differs from {csv_path.name} at row "
                                   f"{bad[0] + 1}")
    return BlockTable(
        frame, feature_id, _ints(csv_path, cols, "fx"), _ints(csv_path, cols, "fy"),
        _status(csv_path, cols["status"]), **{c: _floats(csv_path, cols, c) for c in BlockTable._SCALARS},
        centroid=np.stack([_floats(csv_path, cols, c) for c in ("centroid_x", "centroid_y")], axis=1), H=H,
        coeffs=np.stack([_floats(csv_path, cols, c) for c in COEFF_COLUMNS], axis=1), psf=arrays["psf"],
        loss_extent=_floats(csv_path, cols, "loss_extent") if "loss_extent" in cols else None,
        noise_var=_floats(csv_path, cols, "noise_var") if "noise_var" in cols else None)
