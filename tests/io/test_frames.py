"""Frame listing and decoding: depths, colour, natural order, and clear errors for bad files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from blurcalib.io.frames import (
    MAX_FRAME_PIXELS,
    MIN_FRAME_SIDE,
    FrameError,
    FrameSizeError,
    frame_size,
    list_frames,
    load_frame,
)


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _write(path: Path, image: np.ndarray) -> Path:
    ok, buf = cv2.imencode(path.suffix, image)
    assert ok
    path.write_bytes(buf.tobytes())
    return path


def test_8bit_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    image = rng.integers(0, 256, (34, 40), dtype=np.uint8)
    for ext in (".png", ".bmp", ".tif"):
        out = load_frame(_write(tmp_path / f"a{ext}", image))
        assert out.dtype == np.float32 and out.shape == (34, 40)
        np.testing.assert_array_equal(out, image.astype(np.float32))


def test_16bit_scaled_to_8bit_range(tmp_path: Path, rng: np.random.Generator) -> None:
    image = rng.integers(0, 65536, (33, 35), dtype=np.uint16)
    image[0, 0], image[0, 1] = 0, 65535
    for ext in (".png", ".tiff"):
        out = load_frame(_write(tmp_path / f"a{ext}", image))
        np.testing.assert_allclose(out, image / 65535.0 * 255.0, rtol=1e-6, atol=1e-4)
        assert out[0, 0] == 0.0 and out[0, 1] == pytest.approx(255.0)


def test_colour_to_grey_with_standard_weights(tmp_path: Path, rng: np.random.Generator) -> None:
    bgr = rng.integers(0, 256, (300, 33, 3), dtype=np.uint8)  # more rows than one conversion chunk
    expected = 0.114 * bgr[..., 0] + 0.587 * bgr[..., 1] + 0.299 * bgr[..., 2]
    np.testing.assert_allclose(load_frame(_write(tmp_path / "c.png", bgr)), expected, atol=1e-3)
    bgra = np.concatenate([bgr, rng.integers(0, 256, (300, 33, 1), dtype=np.uint8)], axis=2)
    np.testing.assert_allclose(load_frame(_write(tmp_path / "d.png", bgra)), expected, atol=1e-3)
    bgr16 = bgr.astype(np.uint16) * 257
    np.testing.assert_allclose(load_frame(_write(tmp_path / "e.png", bgr16)), expected, atol=1e-3)


def test_odd_characters_in_path(tmp_path: Path) -> None:
    folder = tmp_path / "Bilder äöü #1"
    folder.mkdir()
    image = np.full((32, 36), 77, dtype=np.uint8)
    path = _write(folder / "frame 01 (ß).png", image)
    np.testing.assert_array_equal(load_frame(path), 77.0)


def test_expected_size(tmp_path: Path) -> None:
    path = _write(tmp_path / "small.png", np.zeros((480, 640), dtype=np.uint8))
    assert load_frame(path, expected_size=(640, 480)).shape == (480, 640)
    with pytest.raises(FrameSizeError, match=r"small\.png: is 640x480, expected 1280x720"):
        load_frame(path, expected_size=(1280, 720))


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_image(tmp_path: Path, rng: np.random.Generator, ext: str) -> None:
    path = _write(tmp_path / f"cut{ext}", rng.integers(0, 256, (64, 64), dtype=np.uint8))
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])
    with pytest.raises(FrameError, match=rf"cut\{ext}: truncated"):
        load_frame(path)


def test_unreadable_files(tmp_path: Path) -> None:
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(FrameError, match=r"empty\.png: empty file"):
        load_frame(empty)
    text = tmp_path / "notes.png"
    text.write_text("this is not an image\n")
    with pytest.raises(FrameError, match=r"notes\.png: cannot decode image"):
        load_frame(text)
    with pytest.raises(FrameError, match=r"missing\.png: no such file"):
        load_frame(tmp_path / "missing.png")
    with pytest.raises(FrameError, match="is a folder"):
        load_frame(tmp_path)


def test_list_frames_natural_order(tmp_path: Path) -> None:
    names = ["10.png", "2.png", "1.PNG", "frame_9.jpg", "frame_10.jpeg", "b.TIF", "a.bmp"]
    for name in [*names, "notes.txt", ".hidden.png"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "0.png").write_bytes(b"x")
    got = [p.name for p in list_frames([tmp_path])]
    assert got == ["1.PNG", "2.png", "10.png", "a.bmp", "b.TIF", "frame_9.jpg", "frame_10.jpeg"]


def test_list_frames_files_and_folders_in_order(tmp_path: Path) -> None:
    folder = tmp_path / "f"
    folder.mkdir()
    for name in ("3.png", "20.png"):
        (folder / name).write_bytes(b"x")
    single = tmp_path / "first.png"
    single.write_bytes(b"x")
    got = list_frames([str(single), folder, folder / "20.png"])
    assert got == [single, folder / "3.png", folder / "20.png"]


def test_list_frames_errors(tmp_path: Path) -> None:
    with pytest.raises(FrameError, match=r"nowhere: no such file or folder"):
        list_frames([tmp_path / "nowhere"])
    empty = tmp_path / "empty_dir"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images here")
    with pytest.raises(FrameError, match=r"empty_dir: folder contains no image files"):
        list_frames([empty])
    text = tmp_path / "list.txt"
    text.write_text("x")
    with pytest.raises(FrameError, match=r"list\.txt: not an image file"):
        list_frames([text])
    with pytest.raises(FrameError, match="no frames given"):
        list_frames([])


def test_colour_conversion_in_chunks_is_exact(tmp_path: Path, rng: np.random.Generator) -> None:
    bgr = rng.integers(0, 256, (700, 40, 3), dtype=np.uint8)
    whole = cv2.cvtColor(bgr.astype(np.float32), cv2.COLOR_BGR2GRAY)
    assert load_frame(_write(tmp_path / "c.png", bgr)).tobytes() == whole.tobytes()


def test_tiny_frames_are_unreadable(tmp_path: Path) -> None:
    for h, w in ((1, 1), (MIN_FRAME_SIDE - 1, 400), (400, 3)):
        path = _write(tmp_path / f"tiny_{h}x{w}.png", np.full((h, w), 90, np.uint8))
        with pytest.raises(FrameError, match=rf"tiny_{h}x{w}\.png: is {w}x{h} px, smaller than"):
            load_frame(path)
    assert load_frame(_write(tmp_path / "ok.png", np.zeros((MIN_FRAME_SIDE, MIN_FRAME_SIDE),
                                                           np.uint8))).shape == (32, 32)


def test_oversized_frame_is_refused_from_its_header(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    w, h = 9000, MAX_FRAME_PIXELS // 9000 + 1
    path = _write(tmp_path / "huge.png", np.zeros((h, w), np.uint8))
    decoded = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a: decoded.append(a))
    with pytest.raises(FrameError, match=rf"huge\.png: is {w}x{h} px .* more than the 50 MP"):
        load_frame(path)
    assert decoded == []  # refused before decoding


def test_frame_size_from_header_matches_decoded(tmp_path: Path, rng: np.random.Generator) -> None:
    image = rng.integers(0, 256, (37, 51, 3), dtype=np.uint8)
    for ext in (".png", ".jpg", ".bmp", ".tif"):
        assert frame_size(_write(tmp_path / f"a{ext}", image)) == (51, 37)
    exif = tmp_path / "exif.jpg"  # an APP1 block before the frame header
    data = _write(tmp_path / "plain.jpg", image).read_bytes()
    exif.write_bytes(data[:2] + b"\xff\xe1" + (2 + 5000).to_bytes(2, "big") + bytes(5000) + data[2:])
    assert frame_size(exif) == (51, 37) and load_frame(exif).shape == (37, 51)
    (tmp_path / "text.png").write_text("not an image")
    assert frame_size(tmp_path / "text.png") is None
    assert frame_size(tmp_path / "missing.png") is None
