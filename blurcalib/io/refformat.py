"""The reference tool's binary feature dataset (``calib_data``, Schöps et al.'s ``dataset.bin``).

Layout (version 0, see ``docs/reference-format.md``; checked byte for byte against a file the
reference tool wrote). Integers are big-endian (the tool writes them with ``htonl``); floats are
written raw in the writing machine's byte order, little-endian in practice (x86, ARM):

* 10 bytes ``calib_data``; u32 version (0); u32 camera count C; per camera u32 width, u32 height;
* u32 image count; per image: u32 name length, the name's bytes, and per camera a u32 feature
  count followed by that many records ``(f32 x, f32 y, i32 feature id)`` (12 bytes);
* u32 geometry count; per geometry: f32 square length (metres), u32 count, and that many
  ``(i32 feature id, i32 fx, i32 fy)`` triples (feature coordinates, ``docs/conventions.md``).

Positions in the file use the tool's pixel-corner convention (top-left pixel centre at
``(0.5, 0.5)``); this module's dataclasses use OpenCV's (centre at ``(0, 0)``): reading subtracts
0.5 px, writing adds it. Only single-camera datasets are supported.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from blurcalib.io.atomic import atomic_write_bytes
from blurcalib.io.input_file import InputFileError, open_input, read_input
from blurcalib.io.results import FeatureFlags, FeatureTable

MAGIC = b"calib_data"
"""The file's first 10 bytes."""

VERSION = 0
"""The only format version the reference tool reads and writes."""

PIXEL_CORNER_OFFSET = 0.5
"""File position minus OpenCV position, in pixels."""

_FEATURE = np.dtype([("x", "<f4"), ("y", "<f4"), ("id", ">i4")])
_TRIPLE = np.dtype([("id", ">i4"), ("fx", ">i4"), ("fy", ">i4")])
_I32 = np.iinfo(np.int32)


class TargetFeatures(Protocol):
    """The target as this format needs it (:class:`blurcalib.target.pattern.StarPattern` is one).

    Attributes:
        features: ``(N, 2)`` int feature coordinates ``(fx, fy)`` of the feature ids ``0..N-1``.
        num_features: ``N``.
        square_length_m: the square length (m).
    """

    @property
    def features(self) -> np.ndarray: ...

    def points_3d(self) -> np.ndarray:
        """``(N, 3)`` target points ``(X, Y, 0)`` (m) of the feature ids ``0..N-1``."""
        ...

    @property
    def num_features(self) -> int: ...

    @property
    def square_length_m(self) -> float: ...


class RefFormatError(ValueError):
    """A reference dataset file is malformed; the message names the file and the problem."""


@dataclass
class RefImage:
    """The features of one image.

    Attributes:
        name: the image's file name as the reference tool stores it (usually without folder).
        features: ``(N,)`` int64 feature ids (the pattern's y-major ids).
        xy: ``(N, 2)`` float64 positions in pixels, OpenCV convention (top-left pixel centre at
            ``(0, 0)``), float32 precision when read from a file.
    """

    name: str
    features: np.ndarray
    xy: np.ndarray


@dataclass
class RefGeometry:
    """A known target geometry: the feature coordinates of every feature id.

    Attributes:
        square_length_m: square side in metres (float32 precision in the file).
        ids: ``(M,)`` int64 feature ids.
        fx, fy: ``(M,)`` int64 feature coordinates (squares) of those ids.
    """

    square_length_m: float
    ids: np.ndarray
    fx: np.ndarray
    fy: np.ndarray


@dataclass
class RefDataset:
    """A single-camera reference dataset.

    Attributes:
        image_size: ``(width, height)`` of the camera's images in pixels.
        images: the images, in file order.
        geometries: the known geometries (one per target; one for a single star target).
    """

    image_size: tuple[int, int]
    images: list[RefImage]
    geometries: list[RefGeometry]

    @property
    def geometry(self) -> RefGeometry:
        """The only geometry; ValueError if there is not exactly one."""
        if len(self.geometries) != 1:
            raise ValueError(f"dataset has {len(self.geometries)} geometries, expected exactly 1")
        return self.geometries[0]

    def image(self, name: str) -> RefImage:
        """The image called ``name``; KeyError if there is none."""
        for img in self.images:
            if img.name == name:
                return img
        raise KeyError(name)


class _Reader:
    """Sequential reader over a file's bytes with errors that name the file and the byte."""

    def __init__(self, data: bytes, path: str) -> None:
        self.data = data
        self.path = path
        self.pos = 0

    def take(self, size: int, what: str) -> bytes:
        end = self.pos + size
        if end > len(self.data):
            raise RefFormatError(
                f"{self.path}: truncated at byte {len(self.data)} while reading {what} "
                f"(needs {size} bytes from byte {self.pos})")
        chunk = self.data[self.pos:end]
        self.pos = end
        return chunk

    def u32(self, what: str) -> int:
        return int(struct.unpack(">I", self.take(4, what))[0])

    def array(self, dtype: np.dtype, count: int, what: str) -> np.ndarray:
        return np.frombuffer(self.take(count * dtype.itemsize, what), dtype=dtype)


def read_ref_dataset(path: str | os.PathLike[str], max_bytes: int | None = None) -> RefDataset:
    """Read a reference dataset file, converting positions to the OpenCV convention.

    Args:
        path: the binary file (``calib_data`` format, version 0, one camera).
        max_bytes: the largest file read (None: any size).
    Returns:
        The dataset; positions have 0.5 px subtracted.
    Raises:
        RefFormatError: the file is missing, not a regular file (a device, a FIFO), larger than
            ``max_bytes``, unreadable or empty, has a bad magic or version, more than one camera,
            is truncated, has bytes after its end, or a name that is not UTF-8 (the message names
            the file and the byte where the problem is).
    """
    path_s = str(path)
    try:
        data = read_input(path, max_bytes, "reference dataset")
    except FileNotFoundError:
        raise RefFormatError(f"{path_s}: no such file") from None
    except InputFileError as exc:
        raise RefFormatError(str(exc)) from None
    except OSError as exc:
        raise RefFormatError(f"{path_s}: cannot read ({exc.strerror or exc})") from None
    if not data:
        raise RefFormatError(f"{path_s}: empty file")
    r = _Reader(data, path_s)
    if data[:len(MAGIC)] != MAGIC[:len(data)]:
        raise RefFormatError(f"{path_s}: bad magic {data[:len(MAGIC)]!r}, expected {MAGIC!r} "
                             "(not a reference feature dataset)")
    r.take(len(MAGIC), "the magic")
    version = r.u32("the version")
    if version != VERSION:
        raise RefFormatError(f"{path_s}: unsupported format version {version} (only {VERSION})")
    num_cameras = r.u32("the camera count")
    if num_cameras != 1:
        raise RefFormatError(f"{path_s}: has {num_cameras} cameras; only single-camera datasets "
                             "are supported")
    image_size = (r.u32("the image width"), r.u32("the image height"))
    num_images = r.u32("the image count")
    images = []
    for i in range(num_images):
        start = r.pos
        raw_name = r.take(r.u32(f"the name length of image {i}"), f"the name of image {i}")
        try:
            name = raw_name.decode("utf-8")
        except UnicodeDecodeError:
            raise RefFormatError(f"{path_s}: the name of image {i} at byte {start + 4} is not "
                                 f"UTF-8: {raw_name[:40]!r}") from None
        count = r.u32(f"the feature count of image {name!r}")
        rec = r.array(_FEATURE, count, f"the features of image {name!r}")
        xy = np.stack([rec["x"], rec["y"]], axis=1).astype(np.float64) - PIXEL_CORNER_OFFSET
        images.append(RefImage(name=name, features=rec["id"].astype(np.int64), xy=xy))
    geometries = []
    for g in range(r.u32("the geometry count")):
        square = float(np.frombuffer(r.take(4, f"the square length of geometry {g}"), "<f4")[0])
        count = r.u32(f"the feature count of geometry {g}")
        rec = r.array(_TRIPLE, count, f"the features of geometry {g}")
        geometries.append(RefGeometry(square_length_m=square, ids=rec["id"].astype(np.int64),
                                      fx=rec["fx"].astype(np.int64), fy=rec["fy"].astype(np.int64)))
    if r.pos != len(data):
        raise RefFormatError(f"{path_s}: {len(data) - r.pos} unexpected bytes after the dataset's "
                             f"end at byte {r.pos}")
    return RefDataset(image_size=image_size, images=images, geometries=geometries)


def ref_dataset_image_size(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    """``(width, height)`` of a reference dataset's camera, read from its first 26 bytes (nothing
    else is read); None when the file cannot be read or does not start as a single-camera dataset
    of version 0 (:func:`read_ref_dataset` then says why)."""
    head_size = len(MAGIC) + 4 * 4
    try:
        with open_input(path, what="reference dataset") as handle:
            head = handle.read(head_size)
    except (OSError, InputFileError):
        return None
    if len(head) < head_size or head[:len(MAGIC)] != MAGIC:
        return None
    version, cameras, width, height = struct.unpack(">IIII", head[len(MAGIC):])
    return (width, height) if version == VERSION and cameras == 1 else None


def _int32(values: np.ndarray, what: str) -> np.ndarray:
    values = np.asarray(values)
    if values.size and (values.min() < _I32.min or values.max() > _I32.max):
        raise ValueError(f"{what} do not fit in 32-bit integers")
    return values


def encode_ref_dataset(dataset: RefDataset) -> bytes:
    """The file bytes of ``dataset`` (positions converted to the pixel-corner convention).

    Raises:
        ValueError: inconsistent array shapes, values that do not fit the file's types, or
            non-finite positions.
    """
    w, h = dataset.image_size
    parts = [MAGIC, struct.pack(">IIIII", VERSION, 1, w, h, len(dataset.images))]
    for img in dataset.images:
        ids = _int32(np.asarray(img.features).reshape(-1), f"feature ids of image {img.name!r}")
        xy = np.asarray(img.xy, dtype=np.float64)
        if xy.shape != (len(ids), 2):
            raise ValueError(f"image {img.name!r}: xy has shape {xy.shape}, expected ({len(ids)}, 2)")
        if not np.all(np.isfinite(xy)):
            raise ValueError(f"image {img.name!r}: positions must be finite")
        name = img.name.encode("utf-8")
        rec = np.empty(len(ids), dtype=_FEATURE)
        rec["x"] = xy[:, 0] + PIXEL_CORNER_OFFSET
        rec["y"] = xy[:, 1] + PIXEL_CORNER_OFFSET
        rec["id"] = ids
        parts += [struct.pack(">I", len(name)), name, struct.pack(">I", len(ids)), rec.tobytes()]
    parts.append(struct.pack(">I", len(dataset.geometries)))
    for g, geo in enumerate(dataset.geometries):
        cols = [_int32(np.asarray(a).reshape(-1), f"geometry {g} {label}")
                for a, label in ((geo.ids, "ids"), (geo.fx, "fx"), (geo.fy, "fy"))]
        if not len(cols[0]) == len(cols[1]) == len(cols[2]):
            raise ValueError(f"geometry {g}: ids, fx and fy differ in length")
        rec = np.empty(len(cols[0]), dtype=_TRIPLE)
        rec["id"], rec["fx"], rec["fy"] = cols
        parts += [np.array([geo.square_length_m], dtype="<f4").tobytes(),
                  struct.pack(">I", len(rec)), rec.tobytes()]
    return b"".join(parts)


def write_ref_dataset(path: str | os.PathLike[str], dataset: RefDataset) -> Path:
    """Write ``dataset`` atomically in the reference format (adds 0.5 px to positions).

    Reading the file back gives the same dataset to float32 precision; writing a dataset that
    was read from a file reproduces that file byte for byte (for files whose floats are
    little-endian and that have a single camera).

    Raises:
        ValueError: see ``encode_ref_dataset``.
        OutputError: the file cannot be written.
    """
    return atomic_write_bytes(path, encode_ref_dataset(dataset))


def to_ref_dataset(image_size: tuple[int, int], frames: Sequence[str], frame_of_obs: np.ndarray,
                   feature_id: np.ndarray, x: np.ndarray, y: np.ndarray,
                   pattern: TargetFeatures) -> RefDataset:
    """Build a reference dataset from blurcalib observations.

    Every frame becomes an image (in ``frames`` order, also those without observations), its
    features sorted by id. The geometry lists all of the pattern's features with their
    feature coordinates and the pattern's square length.

    Args:
        image_size: ``(width, height)`` in pixels.
        frames: ``F`` image names as the reference tool should see them (usually file names).
        frame_of_obs: ``(K,)`` int index into ``frames`` of each observation.
        feature_id: ``(K,)`` int pattern feature ids (y-major, ``StarPattern.features``).
        x, y: ``(K,)`` positions in pixels, OpenCV convention.
        pattern: the target.
    Returns:
        The dataset (positions in the OpenCV convention, as everywhere in blurcalib).
    Raises:
        ValueError: arrays of different lengths, an index outside ``frames``, an id that is not
            a feature of ``pattern``, a feature observed twice in a frame, or non-finite
            positions.
    """
    frame_of_obs = np.asarray(frame_of_obs).reshape(-1).astype(np.int64)
    feature_id = np.asarray(feature_id).reshape(-1).astype(np.int64)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    if not len(frame_of_obs) == len(feature_id) == len(x) == len(y):
        raise ValueError("frame_of_obs, feature_id, x and y must have the same length")
    xy = np.stack([x, y], axis=1)
    if len(frame_of_obs) and (frame_of_obs.min() < 0 or frame_of_obs.max() >= len(frames)):
        raise ValueError(f"frame_of_obs must index the {len(frames)} frames")
    if len(feature_id) and (feature_id.min() < 0 or feature_id.max() >= pattern.num_features):
        raise ValueError(f"feature ids must lie in [0, {pattern.num_features - 1}]")
    if not np.all(np.isfinite(xy)):
        raise ValueError("positions must be finite")
    order = np.lexsort((feature_id, frame_of_obs))
    fo, fi, xy = frame_of_obs[order], feature_id[order], xy[order]
    repeated = (fo[1:] == fo[:-1]) & (fi[1:] == fi[:-1])
    if np.any(repeated):
        k = int(np.argmax(repeated))
        raise ValueError(f"feature {fi[k]} is observed more than once in frame {frames[fo[k]]!r}")
    bounds = np.searchsorted(fo, np.arange(len(frames) + 1))
    images = [RefImage(name=str(name), features=fi[bounds[f]:bounds[f + 1]].copy(),
                       xy=xy[bounds[f]:bounds[f + 1]].copy())
              for f, name in enumerate(frames)]
    feats = pattern.features
    geometry = RefGeometry(square_length_m=float(pattern.square_length_m),
                           ids=np.arange(len(feats), dtype=np.int64),
                           fx=feats[:, 0].copy(), fy=feats[:, 1].copy())
    return RefDataset(image_size=(int(image_size[0]), int(image_size[1])), images=images,
                      geometries=[geometry])


def ref_feature_table(dataset: RefDataset, pattern: TargetFeatures) -> FeatureTable:
    """The dataset's features as a :class:`blurcalib.io.results.FeatureTable` of ``pattern``'s
    feature ids (matched by feature coordinates ``(fx, fy)``), every frame a sharp frame, named
    as the dataset names its images; positions stay in the OpenCV convention.

    Raises:
        RefFormatError: a feature whose coordinates are not one of ``pattern``'s features, or a
            geometry whose square length differs from the pattern's by more than 1e-6 m.
    """
    geo = dataset.geometry
    if abs(geo.square_length_m - pattern.square_length_m) > 1e-6:
        raise RefFormatError(f"the dataset's square length {geo.square_length_m:.6g} m differs from "
                             f"the pattern's {pattern.square_length_m:.6g} m")
    ids = {(int(fx), int(fy)): i for i, (fx, fy) in enumerate(pattern.features.tolist())}
    coords = {int(i): (int(fx), int(fy)) for i, fx, fy in zip(geo.ids, geo.fx, geo.fy, strict=True)}
    counts = [len(img.features) for img in dataset.images]
    observed = (np.concatenate([img.features for img in dataset.images]).astype(np.int64)
                if dataset.images else np.zeros(0, dtype=np.int64))
    known, where = np.unique(observed, return_inverse=True)
    mapped = []
    for i in known.tolist():
        if i in coords and coords[i] in ids:
            mapped.append(ids[coords[i]])
            continue
        name = next(img.name for img in dataset.images if np.any(img.features == i))
        if i not in coords:
            raise RefFormatError(f"feature {i} of image {name!r} is not in the dataset's geometry (which "
                                 f"lists {len(coords)} feature ids)")
        raise RefFormatError(f"feature {i} of image {name!r}, at feature coordinates {coords[i]}, is not "
                             f"a feature of the pattern")
    fid_a = np.asarray(mapped, dtype=np.int64)[where] if len(known) else np.zeros(0, dtype=np.int64)
    frame = np.repeat(np.array([img.name for img in dataset.images], dtype=np.str_), counts)
    xy = np.concatenate([img.xy for img in dataset.images]) if dataset.images else np.zeros((0, 2))
    feats = pattern.features[fid_a] if len(fid_a) else np.zeros((0, 2), dtype=np.int64)
    points = pattern.points_3d()[fid_a] if len(fid_a) else np.zeros((0, 3))
    flags = int(FeatureFlags.STAR_CENTRE | FeatureFlags.SHARP_FRAME)
    return FeatureTable(frame=frame, feature_id=fid_a, fx=feats[:, 0],
                        fy=feats[:, 1], X=points[:, 0], Y=points[:, 1], x=xy[:, 0], y=xy[:, 1],
                        weight=np.ones(len(fid_a)), flags=np.full(len(fid_a), flags, dtype=np.int64))
