"""The printable target: a vector PDF of the page, its PNG render and its pattern YAML.

The PDF is drawn with matplotlib's PDF backend as filled polygons at the page's exact physical
size: every black star sector and every black tag cell, in page millimetres (origin top-left,
y down), all in one compound path so that neighbouring polygons abut without seams. The black
areas are exactly those of :meth:`StarPattern.intensity` (``pattern.py`` defines the
coordinate systems and the colour convention).
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import cv2
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path as MplPath
from matplotlib.transforms import Affine2D

from blurcalib.io.atomic import OutputError, atomic_path, atomic_write_bytes, ensure_writable_dir
from blurcalib.target.pattern import TAG_CELLS, StarPattern

PRINTABLE_FORMATS = ("pdf", "png", "yaml")
MM_PER_INCH = 25.4

MAX_PNG_PIXELS = 150_000_000
"""Largest PNG render (width x height px): an A4 page at 1200 dpi is 139 MP, an A0 poster at
300 dpi 139 MP. The render holds the 8-bit image and row chunks of 2 M samples, so 150 MP stays
near 0.2 GB; larger renders are refused before any file is written."""


def sector_polygons(num_segments: int) -> list[np.ndarray]:
    """The black sectors of one star, as polygons in feature units around the star centre.

    Sector ``s`` spans ``theta in [2 pi s / N, 2 pi (s + 1) / N)`` with ``theta = atan2(u, v)``
    (from +y towards +x, i.e. direction ``(sin theta, cos theta)``); even sectors are black. Each
    polygon runs from the centre along the sector's first ray to the star square's border
    (``max(|u|, |v|) = 1/2``), through any square corner the sector spans, and back along its
    second ray.

    Returns:
        ``N / 2`` arrays of shape ``(V, 2)`` (``V`` = 3 or 4), ``(u, v)`` offsets in squares.
    """
    def border(theta: float) -> np.ndarray:
        d = np.array([math.sin(theta), math.cos(theta)])
        return cast(np.ndarray, 0.5 * d / np.abs(d).max())

    corner_angles = [math.pi / 4 + k * math.pi / 2 for k in range(4)]
    step = 2.0 * math.pi / num_segments
    polygons = []
    for s in range(0, num_segments, 2):
        t0, t1 = s * step, (s + 1) * step
        corners = [border(t) for t in corner_angles if t0 + 1e-12 < t < t1 - 1e-12]
        polygons.append(np.array([[0.0, 0.0], border(t0), *corners, border(t1)]))
    return polygons


def black_polygons(pattern: StarPattern) -> list[np.ndarray]:
    """Every black area of the page as a polygon in page millimetres (origin top-left, y down).

    Stars are centred on every grid corner, feature coordinates ``-1 .. squares_x - 1`` by
    ``-1 .. squares_y - 1``. The patterned area's border and the tags' boxes lie on integer
    feature coordinates, i.e. on star centres along sector rays (N is a multiple of 4), so
    clipping a star to the patterned area and cutting out the tags keeps or drops whole sectors;
    a sector is kept when its interior point lies inside the patterned area and outside every
    tag. Each tag adds its black cells (10 x 10 cells over its feature box).

    Returns:
        Arrays of shape ``(V, 2)``, each a closed polygon (first vertex not repeated).
    """
    n = pattern.num_star_segments
    templates = sector_polygons(n)
    step = 2.0 * math.pi / n
    mids = np.array([[math.sin((s + 0.5) * step), math.cos((s + 0.5) * step)]
                     for s in range(0, n, 2)]) * 0.25
    fy, fx = np.mgrid[-1:pattern.squares_y, -1:pattern.squares_x]
    centres = np.stack([fx.ravel(), fy.ravel()], axis=1).astype(np.float64)  # (S, 2)
    probe = centres[:, None, :] + mids[None, :, :]  # (S, N/2, 2)
    px, py = probe[..., 0], probe[..., 1]
    keep = (px > -1) & (py > -1) & (px < pattern.squares_x - 1) & (py < pattern.squares_y - 1)
    for tag in pattern.apriltags:
        x0, y0, x1, y1 = tag.feature_box
        keep &= ~((px > x0) & (py > y0) & (px < x1) & (py < y1))
    polygons = [pattern.feature_to_page_mm(centres[i] + templates[k]) for i, k in zip(*np.nonzero(keep),
                                                                                      strict=True)]
    for tag in pattern.apriltags:
        x0, y0, _, _ = tag.feature_box
        cw, ch = tag.width / TAG_CELLS, tag.height / TAG_CELLS
        for r, c in zip(*np.nonzero(pattern.tag_cells(tag) == 0), strict=True):
            left, top = x0 + c * cw, y0 + r * ch
            rect = [[left, top], [left + cw, top], [left + cw, top + ch], [left, top + ch]]
            polygons.append(pattern.feature_to_page_mm(np.array(rect)))
    return polygons


def page_figure(pattern: StarPattern) -> Figure:
    """A matplotlib figure of the whole page at its physical size (white page, black polygons).

    The figure is ``page.width_mm x page.height_mm`` (in inches, ``/ 25.4``), without axes; all
    black polygons form one compound path, filled without edge lines or antialiasing. Render it
    with any backend (``savefig(..., format="pdf")`` gives a vector PDF).
    """
    width, height = pattern.page.width_mm, pattern.page.height_mm
    fig = Figure(figsize=(width / MM_PER_INCH, height / MM_PER_INCH), facecolor="white")
    polygons = black_polygons(pattern)
    vertices = np.concatenate([np.vstack([poly, poly[:1]]) for poly in polygons])
    codes = np.concatenate([[MplPath.MOVETO, *[MplPath.LINETO] * (len(poly) - 1), MplPath.CLOSEPOLY]
                            for poly in polygons]).astype(MplPath.code_type)
    mm_to_figure = Affine2D().scale(1.0 / width, -1.0 / height).translate(0.0, 1.0) + fig.transFigure
    fig.add_artist(PathPatch(MplPath(vertices, codes), transform=mm_to_figure, facecolor="black",
                             edgecolor="none", linewidth=0.0, antialiased=False))
    return fig


def png_with_dpi(image: np.ndarray, dpi: float) -> bytes:
    """Encode an image as PNG with OpenCV and record its resolution (a ``pHYs`` chunk)."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode an image of shape {image.shape} as PNG")
    data = encoded.tobytes()
    ppm = round(dpi / MM_PER_INCH * 1000.0)  # pixels per metre
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body))
    ihdr_end = 8 + 8 + 13 + 4  # signature, IHDR length + type, IHDR data, CRC
    return data[:ihdr_end] + chunk + data[ihdr_end:]


def png_size(pattern: StarPattern, dpi: float) -> tuple[int, int]:
    """``(width, height)`` px of the page rendered at ``dpi`` (:meth:`StarPattern.render_page`)."""
    mm_per_px = MM_PER_INCH / dpi
    return round(pattern.page.width_mm / mm_per_px), round(pattern.page.height_mm / mm_per_px)


def write_printable(pattern: StarPattern, out_base: str | os.PathLike[str], dpi: float = 300,
                    formats: Sequence[str] = PRINTABLE_FORMATS, overwrite: bool = False
                    ) -> dict[str, Path]:
    """Write the printable target: ``<out_base>.pdf``, ``<out_base>.png``, ``<out_base>.yaml``.

    Args:
        pattern: the target.
        out_base: output path without extension; its folder is created if needed.
        dpi: resolution of the PNG (dots per inch); the PDF is vector and has none.
        formats: any of ``"pdf"`` (vector page at its physical size, see :func:`page_figure`),
            ``"png"`` (``pattern.render_page(dpi)``, 8-bit grey, resolution recorded) and
            ``"yaml"`` (the pattern YAML).
        overwrite: replace files that exist; without it an existing file is refused before
            anything is written.
    Returns:
        ``{format: path}`` of the files written. Each file is written atomically.
    Raises:
        ValueError: no format, an unknown format, a dpi that is not a positive number, or a PNG
            over :data:`MAX_PNG_PIXELS` (all checked before any file is written).
        OutputError: a file exists (without ``overwrite``), or the output folder cannot be
            created or written (the message names it).
    """
    unknown = sorted(set(formats) - set(PRINTABLE_FORMATS))
    if unknown:
        raise ValueError(f"unknown printable format(s) {unknown}; choose from {list(PRINTABLE_FORMATS)}")
    if not formats:
        raise ValueError(f"no format to write; choose from {', '.join(PRINTABLE_FORMATS)}")
    if not (math.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    if "png" in formats:
        w, h = png_size(pattern, dpi)
        if w * h > MAX_PNG_PIXELS:
            raise ValueError(f"dpi {dpi:g}: the PNG of the {pattern.page.width_mm:g} x "
                             f"{pattern.page.height_mm:g} mm page would be {w} x {h} px "
                             f"({w * h / 1e6:.0f} MP), more than the {MAX_PNG_PIXELS / 1e6:.0f} MP limit; "
                             f"lower the dpi or leave png out of the formats")
    base = Path(out_base)
    targets = {kind: base.with_name(f"{base.name}.{kind}") for kind in PRINTABLE_FORMATS if kind in formats}
    existing = [str(path) for path in targets.values() if path.exists()]
    if existing and not overwrite:
        raise OutputError(f"{', '.join(existing)}: already exists; use --overwrite to replace")
    ensure_writable_dir(base.parent)
    paths: dict[str, Path] = {}
    if "pdf" in formats:
        paths["pdf"] = targets["pdf"]
        fig = page_figure(pattern)
        with atomic_path(paths["pdf"]) as tmp:
            fig.savefig(tmp, format="pdf", facecolor="white",
                        metadata={"Creator": "blurcalib", "Title": base.name})
    if "png" in formats:
        paths["png"] = atomic_write_bytes(targets["png"],
                                          png_with_dpi(pattern.render_page(dpi), dpi))
    if "yaml" in formats:
        paths["yaml"] = pattern.save_yaml(targets["yaml"])
    return paths

