"""The star calibration target of the reference generic-calibration tool (Schöps et al.).

Coordinate systems (see ``docs/conventions.md``):

* **Feature coordinates** ``p = (x, y)``, in squares, x right and y down the page. Stars are
  centred on every grid corner; integer points are star centres. Feature ``(0, 0)`` is the first
  *interior* corner, at page position ``pattern_start + 1 square``. The patterned area covers
  ``[-1, squares_x - 1] x [-1, squares_y - 1]``. This is the reference tool's feature system.
* **Metric target coordinates**: feature ``(fx, fy)`` sits at ``(fx L, fy L, 0)`` metres, with
  ``L = square_length_in_meters``.
* **Block coordinates** ``q`` of the block (star square) around feature ``(fx, fy)``:
  ``p = (fx, fy) + q / 2``, so ``q in [-1, 1]^2`` with the star centre at 0 and the square's
  corners at ``(+-1, +-1)`` (the paper's block coordinates, used in its local alignment).

Colour convention: 1 is white paper, 0 black ink. In each star of ``N`` segments the angle
``theta = atan2(q_x, q_y)`` (from the +y axis, which points down the page, turning towards +x)
splits into ``N`` sectors ``s = floor(N theta / 2 pi)``; odd sectors are white, as in the paper's
supplement (``eq:hard``). Neighbouring stars have opposite colours along their shared square
border.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import yaml

from blurcalib.io.atomic import atomic_write_text
from blurcalib.io.input_file import InputFileError, open_input
from blurcalib.target.star import star_sector_white

TAG_CELLS = 10
"""A tag36h11 marker drawn by the reference tool is 10 x 10 cells: a white ring, a black ring
and 6 x 6 data bits."""


MAX_SQUARES = 1000
"""Most squares along one side of a target (a 2 m poster of 2 mm squares); larger counts are
refused before anything is allocated from them."""

MAX_STAR_SEGMENTS = 128
"""Most segments in a star: at 128 a 12 mm square's sectors are 0.3 mm wide at its border, at
the edge of what prints and what a camera resolves; larger counts are refused before anything
is computed from them."""

MAX_PATTERN_BYTES = 1 << 20
"""Largest pattern YAML read (bytes); the reference tool's files are under 1 kB."""

MAX_YAML_DEPTH = 16
"""Deepest nesting of mappings and lists in a pattern YAML (a pattern file nests 3 deep); checked
on the parser's event stream before any object is built from it."""

_SHOWN_CHARS = 60
"""Longest part of a field's value quoted in an error message."""

PAGE_TOLERANCE_MM = 0.01
"""How far (mm) the pattern area may reach past the page edge (rounding in written YAMLs)."""


class PatternFileError(ValueError):
    """A pattern YAML is missing, unreadable or malformed; the message names file and field.

    Attributes:
        summary: the message without anything quoted from the file (no field's value, no line
            of it): what a server shows a client that named a file it cannot read itself.
    """

    def __init__(self, message: str, summary: str | None = None) -> None:
        super().__init__(message)
        self.summary = message if summary is None else summary


@dataclass(frozen=True)
class AprilTagPlacement:
    """One AprilTag (tag36h11) on the target.

    ``tag_x, tag_y`` index the first square covered by the tag (page squares, 0-based);
    the tag covers ``width x height`` squares, i.e. feature coordinates
    ``[tag_x - 1, tag_x - 1 + width] x [tag_y - 1, tag_y - 1 + height]``.
    """

    tag_x: int
    tag_y: int
    width: int
    height: int
    index: int

    @property
    def feature_box(self) -> tuple[int, int, int, int]:
        """``(x0, y0, x1, y1)``: the tag's extent in feature coordinates (squares)."""
        return (self.tag_x - 1, self.tag_y - 1, self.tag_x - 1 + self.width,
                self.tag_y - 1 + self.height)


@dataclass(frozen=True)
class PageLayout:
    """Page size and the patterned area's corners, in millimetres from the top-left corner."""

    width_mm: float
    height_mm: float
    pattern_start_x_mm: float
    pattern_start_y_mm: float
    pattern_end_x_mm: float
    pattern_end_y_mm: float


@dataclass(frozen=True)
class StarPattern:
    """A star target: its grid, square length, tags and page layout (the reference YAML)."""

    num_star_segments: int
    squares_x: int
    squares_y: int
    square_length_m: float
    page: PageLayout
    apriltags: tuple[AprilTagPlacement, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        """Check the geometry before anything is allocated from it; messages name the YAML
        field."""
        n = self.num_star_segments
        if n < 4 or n % 4 != 0 or n > MAX_STAR_SEGMENTS:
            raise ValueError(f"num_star_segments must be a multiple of 4 from 4 to {MAX_STAR_SEGMENTS}, "
                             f"got {n}")
        for name in ("squares_x", "squares_y"):
            count = getattr(self, name)
            if not 3 <= count <= MAX_SQUARES:
                raise ValueError(f"field '{name}' must be between 3 and {MAX_SQUARES} squares, "
                                 f"got {count}")
        if not (math.isfinite(self.square_length_m) and self.square_length_m > 0):
            raise ValueError(f"field 'square_length_in_meters' must be a finite positive length, "
                             f"got {self.square_length_m}")
        pg = self.page
        for name in ("width_mm", "height_mm"):
            value = getattr(pg, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"field 'page.{name}' must be a finite positive length, got {value}")
        for axis, squares, page_len in (("x", self.squares_x, pg.width_mm),
                                        ("y", self.squares_y, pg.height_mm)):
            start = getattr(pg, f"pattern_start_{axis}_mm")
            end = getattr(pg, f"pattern_end_{axis}_mm")
            if not (math.isfinite(start) and math.isfinite(end) and start < end):
                raise ValueError(f"fields 'page.pattern_start_{axis}_mm' and "
                                 f"'page.pattern_end_{axis}_mm' must be finite with start < end, "
                                 f"got {start} and {end}")
            slack = PAGE_TOLERANCE_MM
            if start < -slack or end > page_len + slack:
                raise ValueError(f"fields 'page.pattern_start_{axis}_mm' and "
                                 f"'page.pattern_end_{axis}_mm' ({start}, {end}) must lie on the "
                                 f"page (0 to {page_len} mm)")
            fits = (end - start) / self.square_length_mm
            if abs(fits - squares) > 0.5:
                raise ValueError(f"field 'squares_{axis}' is {squares}, but the page's pattern area "
                                 f"({end - start:.6g} mm from 'page.pattern_start_{axis}_mm' to "
                                 f"'page.pattern_end_{axis}_mm') holds {fits:.6g} squares of "
                                 f"{self.square_length_mm:.6g} mm")
        for i, tag in enumerate(self.apriltags):
            if (tag.width < 1 or tag.height < 1 or tag.tag_x < 0 or tag.tag_y < 0
                    or tag.tag_x + tag.width > self.squares_x
                    or tag.tag_y + tag.height > self.squares_y):
                raise ValueError(f"field 'apriltags[{i}]' (tag_x {tag.tag_x}, tag_y {tag.tag_y}, "
                                 f"width {tag.width}, height {tag.height}) must lie inside the "
                                 f"{self.squares_x} x {self.squares_y} squares")

    # ----------------------------------------------------------------------------- features
    @property
    def square_length_mm(self) -> float:
        """Square side on the page (mm)."""
        return self.square_length_m * 1000.0

    def is_valid_feature(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """Whether integer feature coordinates are features: interior corners not on a tag.

        Args:
            fx, fy: integer arrays of any (equal) shape.
        Returns:
            Boolean array of the same shape.
        """
        fx = np.asarray(fx)
        fy = np.asarray(fy)
        ok = (fx >= 0) & (fy >= 0) & (fx <= self.squares_x - 2) & (fy <= self.squares_y - 2)
        for tag in self.apriltags:
            x0, y0, x1, y1 = tag.feature_box
            ok &= ~((fx >= x0) & (fy >= y0) & (fx <= x1) & (fy <= y1))
        return ok

    @cached_property
    def features(self) -> np.ndarray:
        """``(M, 2)`` int: ``(fx, fy)`` of every valid feature, in id order (y-major)."""
        fy, fx = np.mgrid[0:self.squares_y - 1, 0:self.squares_x - 1]
        ok = self.is_valid_feature(fx, fy)
        return np.stack([fx[ok], fy[ok]], axis=1).astype(np.int64)

    @property
    def num_features(self) -> int:
        """Number of valid features M."""
        return int(self.features.shape[0])

    @cached_property
    def id_grid(self) -> np.ndarray:
        """``(squares_y - 1, squares_x - 1)`` int: feature id at ``[fy, fx]``, -1 if invalid."""
        grid = np.full((self.squares_y - 1, self.squares_x - 1), -1, dtype=np.int64)
        f = self.features
        grid[f[:, 1], f[:, 0]] = np.arange(len(f))
        return grid

    def feature_ids(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """Feature ids of integer coordinates (``-1`` where not a valid feature)."""
        fx = np.asarray(fx, dtype=np.int64)
        fy = np.asarray(fy, dtype=np.int64)
        inside = (fx >= 0) & (fy >= 0) & (fx <= self.squares_x - 2) & (fy <= self.squares_y - 2)
        out = np.full(np.broadcast(fx, fy).shape, -1, dtype=np.int64)
        out[inside] = self.id_grid[np.broadcast_to(fy, out.shape)[inside],
                                   np.broadcast_to(fx, out.shape)[inside]]
        return out

    def points_3d(self, ids: np.ndarray | None = None) -> np.ndarray:
        """``(M, 3)`` metric target points ``(fx L, fy L, 0)`` in metres of ``ids`` (all if None)."""
        f = self.features if ids is None else self.features[np.asarray(ids)]
        out = np.zeros((len(f), 3))
        out[:, :2] = f * self.square_length_m
        return out

    def neighbours(self, feature_id: int) -> list[int]:
        """Ids of the valid 4-neighbours (right, left, down, up) of a feature."""
        fx, fy = self.features[feature_id]
        cand = np.array([[fx + 1, fy], [fx - 1, fy], [fx, fy + 1], [fx, fy - 1]])
        ids = self.feature_ids(cand[:, 0], cand[:, 1])
        return [int(i) for i in ids if i >= 0]

    # ------------------------------------------------------------------------- page mapping
    def feature_to_page_mm(self, p: np.ndarray) -> np.ndarray:
        """Feature coordinates ``(..., 2)`` to page millimetres ``(..., 2)`` (top-left origin)."""
        start = np.array([self.page.pattern_start_x_mm, self.page.pattern_start_y_mm])
        return start + (np.asarray(p, dtype=np.float64) + 1.0) * self.square_length_mm

    def page_mm_to_feature(self, mm: np.ndarray) -> np.ndarray:
        """Page millimetres ``(..., 2)`` to feature coordinates ``(..., 2)``."""
        start = np.array([self.page.pattern_start_x_mm, self.page.pattern_start_y_mm])
        return cast(np.ndarray, (np.asarray(mm, dtype=np.float64) - start) / self.square_length_mm - 1.0)

    def tag_corners(self, tag: AprilTagPlacement) -> np.ndarray:
        """``(4, 2)`` feature coordinates of the tag's black square, in OpenCV aruco corner order.

        aruco reports the outer corners of the marker's black ring starting at the marker's own
        top-left; the reference page shows the marker turned by 180 degrees, so corner 0 is the
        page's bottom-right one: (right, bottom), (left, bottom), (left, top), (right, top).
        """
        x0, y0, x1, y1 = tag.feature_box
        cw = tag.width / TAG_CELLS
        ch = tag.height / TAG_CELLS
        left, right, top, bottom = x0 + cw, x1 - cw, y0 + ch, y1 - ch
        return np.array([[right, bottom], [left, bottom], [left, top], [right, top]])

    # --------------------------------------------------------------------- exact intensity
    def tag_cells(self, tag: AprilTagPlacement) -> np.ndarray:
        """``(10, 10)`` uint8 cells of a tag, 1 white and 0 black (white ring included)."""
        return tag36h11_cells(tag.index)

    def intensity(self, p: np.ndarray) -> np.ndarray:
        """Exact target intensity at feature coordinates ``p`` ``(..., 2)``.

        1 white, 0 black, 0.5 exactly on a star centre; the page outside the patterned area is
        white; tags are drawn from their 10 x 10 cells. Returns float32 of shape ``p[..., 0]``.
        """
        p = np.asarray(p, dtype=np.float64)
        x, y = p[..., 0], p[..., 1]
        u = x - np.round(x)
        v = y - np.round(y)
        out = star_sector_white(u, v, self.num_star_segments).astype(np.float32)
        out[(u == 0) & (v == 0)] = 0.5
        outside = (x < -1) | (y < -1) | (x > self.squares_x - 1) | (y > self.squares_y - 1)
        out[outside] = 1.0
        for tag in self.apriltags:
            x0, y0, x1, y1 = tag.feature_box
            in_tag = (x >= x0) & (y >= y0) & (x < x1) & (y < y1)
            if not in_tag.any():
                continue
            cells = self.tag_cells(tag)
            cx = np.clip(((x[in_tag] - x0) / tag.width * TAG_CELLS).astype(np.int64), 0, 9)
            cy = np.clip(((y[in_tag] - y0) / tag.height * TAG_CELLS).astype(np.int64), 0, 9)
            out[in_tag] = cells[cy, cx]
        return out

    def render_page(self, dpi: float, supersample: int = 4,
                    size_px: tuple[int, int] | None = None) -> np.ndarray:
        """Render the whole page as 8-bit grey, box-filtered over ``supersample^2`` samples.

        Pixel ``(i, j)`` (row, column) covers page millimetres
        ``[j, j + 1] x [i, i + 1] * 25.4 / dpi``; its centre is at ``(j + 0.5) * 25.4 / dpi``.

        Args:
            dpi: resolution in dots per inch.
            supersample: samples per pixel side.
            size_px: ``(width, height)``; default rounds the page size at ``dpi``.
        Returns:
            ``(H, W)`` uint8.
        """
        mm_per_px = 25.4 / dpi
        if size_px is None:
            size_px = (round(self.page.width_mm / mm_per_px), round(self.page.height_mm / mm_per_px))
        w, h = size_px
        offs = (np.arange(supersample) + 0.5) / supersample
        out = np.empty((h, w), dtype=np.uint8)
        xs = np.arange(w, dtype=np.float64)
        rows_per_chunk = max(1, 2_000_000 // max(w, 1))
        for r0 in range(0, h, rows_per_chunk):  # memory: a few chunks of 2 M samples, and the image
            r1 = min(h, r0 + rows_per_chunk)
            ys = np.arange(r0, r1, dtype=np.float64)
            acc = np.zeros((r1 - r0, w), dtype=np.float64)
            for oy in offs:
                for ox in offs:
                    mm = np.stack(np.broadcast_arrays((xs[None, :] + ox) * mm_per_px,
                                                      (ys[:, None] + oy) * mm_per_px), axis=-1)
                    acc += self.intensity(self.page_mm_to_feature(mm))
            out[r0:r1] = np.clip(np.round(acc / supersample**2 * 255.0), 0, 255)
        return out

    # ------------------------------------------------------------------------------- YAML
    def to_yaml_text(self) -> str:
        """The pattern in the reference tool's YAML layout."""
        lines = [
            f"num_star_segments: {self.num_star_segments}",
            f"squares_x: {self.squares_x}",
            f"squares_y: {self.squares_y}",
            f"square_length_in_meters: {self.square_length_m!r}",
            "page:",
            f"    width_mm: {self.page.width_mm!r}",
            f"    height_mm: {self.page.height_mm!r}",
            f"    pattern_start_x_mm: {self.page.pattern_start_x_mm!r}",
            f"    pattern_start_y_mm: {self.page.pattern_start_y_mm!r}",
            f"    pattern_end_x_mm: {self.page.pattern_end_x_mm!r}",
            f"    pattern_end_y_mm: {self.page.pattern_end_y_mm!r}",
            "apriltags:",
        ]
        for tag in self.apriltags:
            lines += [f"  - tag_x: {tag.tag_x}", f"    tag_y: {tag.tag_y}",
                      f"    width: {tag.width}", f"    height: {tag.height}",
                      f"    index: {tag.index}"]
        return "\n".join(lines) + "\n"

    def save_yaml(self, path: str | os.PathLike[str]) -> Path:
        """Write the pattern YAML atomically."""
        return atomic_write_text(path, self.to_yaml_text())


def _shown(value: object) -> str:
    """A field's value for an error message, at most :data:`_SHOWN_CHARS` characters: a mapping
    or a list is named by its type and length (never expanded: YAML aliases can make a 1 kB
    file a structure of 10^9 leaves), other values by their ``repr``, shortened."""
    if isinstance(value, dict):
        return f"a mapping of {len(value)} key(s)"
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)} item(s)"
    plain = isinstance(value, (str, int, float, bool)) or value is None
    text = repr(value) if plain else type(value).__name__
    return text if len(text) <= _SHOWN_CHARS else text[:_SHOWN_CHARS - 3] + "..."


def _check_depth(text: str, path: str) -> None:
    """Refuse YAML nested deeper than :data:`MAX_YAML_DEPTH`, from the parser's event stream
    (the parser is iterative; the composer that builds objects is recursive and would run out
    of stack on a file nested 20,000 deep)."""
    depth = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise PatternFileError(f"{path}: YAML nested more than {MAX_YAML_DEPTH} levels deep at "
                                       f"line {event.start_mark.line + 1} (a pattern file nests 3)")
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1


def _field(node: dict[str, Any], key: str, kind: type, path: str, where: str = "") -> Any:
    name = f"{where}{key}"
    if not isinstance(node, dict) or key not in node:
        raise PatternFileError(f"{path}: missing field '{name}'")
    value = node[key]
    try:
        if kind is int:
            if isinstance(value, bool) or float(value) != int(value):
                raise ValueError
            return int(value)
        return kind(value)
    except (TypeError, ValueError, OverflowError):
        problem = f"{path}: field '{name}' must be {kind.__name__}"
        raise PatternFileError(f"{problem}, got {_shown(value)}", problem) from None


def load_pattern(path: str | os.PathLike[str]) -> StarPattern:
    """Read a pattern YAML in the reference tool's format.

    Raises:
        PatternFileError: missing or unreadable file, invalid YAML, a missing or mistyped field,
            or an unsupported value (the message names the file and the field).
    """
    path_s = str(path)
    try:
        with open_input(path, what="pattern file") as handle:  # a regular file: a FIFO would block
            data = handle.read(MAX_PATTERN_BYTES + 1)
    except FileNotFoundError:
        raise PatternFileError(f"{path_s}: pattern file not found") from None
    except InputFileError as exc:
        raise PatternFileError(str(exc)) from None
    except OSError as exc:
        raise PatternFileError(f"{path_s}: cannot read pattern file ({exc})",
                               f"{path_s}: cannot read pattern file ({exc.strerror or exc})") from None
    if len(data) > MAX_PATTERN_BYTES:
        raise PatternFileError(f"{path_s}: more than {MAX_PATTERN_BYTES} bytes, the largest pattern file "
                               f"read (a pattern YAML is under 1 kB)")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise PatternFileError(f"{path_s}: cannot read pattern file ({exc})",
                               f"{path_s}: not a pattern file (not UTF-8 text)") from None
    try:
        _check_depth(text, path_s)
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise PatternFileError(f"{path_s}: not valid YAML ({exc})".replace("\n", " "),
                               f"{path_s}: not valid YAML" + (f" (line {mark.line + 1})" if mark else "")
                               ) from None
    except PatternFileError:
        raise
    except ValueError as exc:  # a value the YAML constructors refuse (an integer of 5,000 digits)
        raise PatternFileError(f"{path_s}: unreadable value in the YAML ({exc})") from None
    if not isinstance(doc, dict):
        raise PatternFileError(f"{path_s}: not a pattern YAML (expected a mapping at top level)")
    segments = _field(doc, "num_star_segments", int, path_s)
    if segments < 4 or segments % 4 or segments > MAX_STAR_SEGMENTS:
        problem = f"{path_s}: field 'num_star_segments' must be a multiple of 4 from 4 to {MAX_STAR_SEGMENTS}"
        raise PatternFileError(f"{problem}, got {segments}", problem)
    squares_x = _field(doc, "squares_x", int, path_s)
    squares_y = _field(doc, "squares_y", int, path_s)
    square_length = _field(doc, "square_length_in_meters", float, path_s)
    page = doc.get("page")
    if not isinstance(page, dict):
        raise PatternFileError(f"{path_s}: missing field 'page'")
    layout = PageLayout(*(
        _field(page, k, float, path_s, "page.")
        for k in ("width_mm", "height_mm", "pattern_start_x_mm", "pattern_start_y_mm",
                  "pattern_end_x_mm", "pattern_end_y_mm")))
    tags_node = doc.get("apriltags", [])
    if not isinstance(tags_node, list):
        raise PatternFileError(f"{path_s}: field 'apriltags' must be a list")
    tags = tuple(
        AprilTagPlacement(*(_field(t, k, int, path_s, f"apriltags[{i}].")
                            for k in ("tag_x", "tag_y", "width", "height", "index")))
        for i, t in enumerate(tags_node))
    for i, tag in enumerate(tags):
        if not 0 <= tag.index < 587:
            problem = f"{path_s}: field 'apriltags[{i}].index' must be a tag36h11 id in [0, 586]"
            raise PatternFileError(f"{problem}, got {tag.index}", problem)
    try:
        return StarPattern(
            num_star_segments=segments, squares_x=squares_x, squares_y=squares_y,
            square_length_m=square_length, page=layout, apriltags=tags)
    except ValueError as exc:
        fields = ", ".join(dict.fromkeys(re.findall(r"'([\w.\[\]]+)'", str(exc)))) or "the fields"
        raise PatternFileError(f"{path_s}: {exc}", f"{path_s}: {fields}: not a valid star target") from None


def tag36h11_cells(index: int) -> np.ndarray:
    """``(10, 10)`` uint8 cells of tag36h11 marker ``index``: 1 white, 0 black.

    Drawn with OpenCV's aruco ``DICT_APRILTAG_36h11`` (8 x 8 cells: black ring and 6 x 6 bits),
    turned by 180 degrees to match the reference tool's tag images (checked against its page
    render), and padded with the white ring that those images carry.
    """
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, int(index), 8, borderBits=1)
    cells = np.ones((TAG_CELLS, TAG_CELLS), dtype=np.uint8)
    cells[1:9, 1:9] = np.rot90(marker > 127, 2).astype(np.uint8)
    return cells


PAGE_SIZES_MM: dict[str, tuple[float, float]] = {
    "A4": (210.0, 297.0),
    "letter": (215.9, 279.4),
}
"""Named page sizes (width, height) in millimetres."""


def layout_pattern(page_size_mm: tuple[float, float] = PAGE_SIZES_MM["A4"],
                   approx_square_length_mm: float = 12.0, tag_index: int = 0,
                   num_star_segments: int = 16, margin_mm: float = 4.0,
                   tag_length_in_squares: int = 4) -> StarPattern:
    """Lay out a target on a page as the reference generator does.

    The square length is chosen so that a whole number of squares fits the printable area
    (page minus ``margin_mm`` on each side) in the direction that needs the smaller square; the
    pattern is centred in the printable area and the tag is placed in its middle. With the
    defaults this reproduces ``pattern_resolution_17x24_segments_16_apriltag_0.yaml``.

    Raises:
        ValueError: unsupported segment count, a page too small for 3 x 3 squares plus the tag,
            or a tag id outside tag36h11.
    """
    if num_star_segments < 4 or num_star_segments % 4 or num_star_segments > MAX_STAR_SEGMENTS:
        raise ValueError(f"num_star_segments must be a multiple of 4 from 4 to {MAX_STAR_SEGMENTS}, "
                         f"got {num_star_segments}")
    if not 0 <= tag_index < 587:
        raise ValueError(f"tag index must be a tag36h11 id in [0, 586], got {tag_index}")
    # Computed in PDF points exactly as the reference generator does, so that the YAML it
    # writes is reproduced to the last digit.
    cm = 72.0 / 2.54
    mm = cm * 0.1
    width, height = page_size_mm[0] * mm, page_size_mm[1] * mm
    margin = margin_mm / 10.0 * cm
    area_w = (width - margin) - margin
    area_h = (height - margin) - margin
    approx = approx_square_length_mm / 10.0 * cm
    if area_w <= 0 or area_h <= 0 or approx <= 0:
        raise ValueError(f"page {page_size_mm[0]} x {page_size_mm[1]} mm leaves no printable area")
    length = min(area_w / max(1, round(area_w / approx)), area_h / max(1, round(area_h / approx)))
    squares_x = math.floor(area_w / length)
    squares_y = math.floor(area_h / length)
    if min(squares_x, squares_y) < tag_length_in_squares + 2:
        raise ValueError(f"page {page_size_mm[0]} x {page_size_mm[1]} mm fits only {squares_x} x "
                         f"{squares_y} squares of {length / mm:.2f} mm: too few for a "
                         f"{tag_length_in_squares}-square tag")
    unused_x = area_w - squares_x * length
    unused_y = area_h - squares_y * length
    start_x = margin + 0.5 * unused_x
    start_y_up = height - margin - 0.5 * unused_y  # PDF y axis points up
    end_x = width - margin - 0.5 * unused_x
    end_y_up = margin + 0.5 * unused_y
    tag = AprilTagPlacement(tag_x=squares_x // 2 - tag_length_in_squares // 2,
                            tag_y=squares_y // 2 - tag_length_in_squares // 2,
                            width=tag_length_in_squares, height=tag_length_in_squares,
                            index=tag_index)
    page = PageLayout(width / mm, height / mm, start_x / mm, (height - start_y_up) / mm,
                      end_x / mm, (height - end_y_up) / mm)
    return StarPattern(num_star_segments, squares_x, squares_y, 0.01 * length / cm, page, (tag,))
