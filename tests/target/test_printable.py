"""The printable target: vector PDF at the page size, PNG render, YAML, output errors."""

from __future__ import annotations

import os
import re
import shutil
import struct
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.path import Path as MplPath
from scipy.ndimage import maximum_filter, minimum_filter

from blurcalib.io.atomic import OutputError
from blurcalib.target.pattern import StarPattern, layout_pattern, load_pattern
from blurcalib.target.printable import black_polygons, page_figure, sector_polygons, write_printable

DPI = 100


@pytest.fixture(scope="module")
def pattern() -> StarPattern:
    return layout_pattern()  # A4, 17 x 24 squares, 16 segments, tag 0


@pytest.fixture(scope="module")
def written(pattern: StarPattern, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return write_printable(pattern, tmp_path_factory.mktemp("printable") / "target", dpi=DPI)


@pytest.fixture(scope="module")
def reference(pattern: StarPattern) -> np.ndarray:
    return pattern.render_page(DPI)


def test_writes_all_formats_atomically(written: dict[str, Path]) -> None:
    assert set(written) == {"pdf", "png", "yaml"}
    folder = written["pdf"].parent
    assert sorted(p.name for p in folder.iterdir()) == ["target.pdf", "target.png", "target.yaml"]


def test_pdf_is_vector_page_of_exact_size(pattern: StarPattern, written: dict[str, Path]) -> None:
    data = written["pdf"].read_bytes()
    assert data.startswith(b"%PDF")
    boxes = re.findall(rb"/MediaBox\s*\[\s*([-\d.\s]+)\]", data)
    assert len(boxes) == 1
    x0, y0, x1, y1 = map(float, boxes[0].split())
    pt_per_mm = 72.0 / 25.4
    assert (x0, y0) == (0.0, 0.0)
    assert x1 == pytest.approx(pattern.page.width_mm * pt_per_mm, abs=1e-6)
    assert y1 == pytest.approx(pattern.page.height_mm * pt_per_mm, abs=1e-6)
    assert re.search(rb"/Subtype\s*/Image", data) is None  # no embedded raster image


def _rasterise(pattern: StarPattern, pdf: Path, tmp_path: Path) -> np.ndarray:
    """The PDF at DPI with pdftoppm, or else the same figure through matplotlib's Agg backend."""
    if shutil.which("pdftoppm"):
        subprocess.run(["pdftoppm", "-r", str(DPI), "-gray", "-png", "-singlefile", str(pdf),
                        str(tmp_path / "raster")], check=True)
        return cv2.imread(str(tmp_path / "raster.png"), cv2.IMREAD_GRAYSCALE)
    fig = page_figure(pattern)
    fig.set_dpi(DPI)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., 0].copy()


def test_pdf_raster_matches_render(pattern: StarPattern, written: dict[str, Path], reference: np.ndarray,
                                   tmp_path: Path) -> None:
    raster = _rasterise(pattern, written["pdf"], tmp_path)
    exact = pattern.render_page(DPI, supersample=1)
    h, w = min(raster.shape[0], exact.shape[0]), min(raster.shape[1], exact.shape[1])
    assert abs(raster.shape[0] - exact.shape[0]) <= 1 and abs(raster.shape[1] - exact.shape[1]) <= 1
    exact, raster, ref = exact[:h, :w], raster[:h, :w].astype(np.int32), reference[:h, :w].astype(np.int32)
    away = maximum_filter(exact, size=3) == minimum_filter(exact, size=3)
    assert away.mean() > 0.4
    agree = np.abs(raster - ref)[away] <= 64
    assert agree.mean() >= 0.99
    black = exact[away] == 0
    assert black.mean() > 0.2  # the comparison covers black areas too, not only paper


def test_polygons_cover_exactly_the_black_areas(pattern: StarPattern) -> None:
    polygons = black_polygons(pattern)
    rng = np.random.default_rng(0)
    points = rng.random((4000, 2)) * [pattern.page.width_mm, pattern.page.height_mm]
    inside = np.zeros(len(points), dtype=bool)
    for poly in polygons:
        near = np.all((points >= poly.min(axis=0)) & (points <= poly.max(axis=0)), axis=1)
        if near.any():
            inside[near] |= MplPath(poly).contains_points(points[near])
    black = pattern.intensity(pattern.page_mm_to_feature(points)) < 0.5
    assert black.mean() > 0.2
    assert np.array_equal(inside, black)


@pytest.mark.parametrize("segments", [4, 8, 16, 20])
def test_sector_polygons_cover_half_the_square(segments: int) -> None:
    polygons = sector_polygons(segments)
    assert len(polygons) == segments // 2
    assert np.abs(np.concatenate(polygons)).max() == pytest.approx(0.5)

    def area(poly: np.ndarray) -> float:
        px, py = poly.T
        return 0.5 * abs(float(np.dot(px, np.roll(py, -1)) - np.dot(py, np.roll(px, -1))))

    assert sum(area(p) for p in polygons) == pytest.approx(0.5)


def test_png_equals_render_with_dpi(written: dict[str, Path], reference: np.ndarray) -> None:
    png = cv2.imread(str(written["png"]), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint8 and png.ndim == 2
    assert np.array_equal(png, reference)
    data = written["png"].read_bytes()
    at = data.index(b"pHYs")
    ppm_x, ppm_y, unit = struct.unpack(">IIB", data[at + 4:at + 13])
    assert (ppm_x, ppm_y, unit) == (round(DPI / 0.0254), round(DPI / 0.0254), 1)


def test_yaml_reloads_equal(pattern: StarPattern, written: dict[str, Path]) -> None:
    assert load_pattern(written["yaml"]) == pattern


def test_folder_under_a_file_raises_output_error(pattern: StarPattern, tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match=re.escape(str(blocker / "sub"))):
        write_printable(pattern, blocker / "sub" / "target", formats=("yaml",))


def test_read_only_folder_raises_output_error(pattern: StarPattern, tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    if os.access(locked, os.W_OK):
        pytest.skip("running with privileges that ignore folder permissions")
    with pytest.raises(OutputError, match=re.escape(str(locked))):
        write_printable(pattern, locked / "target", formats=("yaml",))


def test_unknown_format_rejected(pattern: StarPattern, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="svg"):
        write_printable(pattern, tmp_path / "target", formats=("pdf", "svg"))
    assert list(tmp_path.iterdir()) == []
