"""Image decoding of the dataset readers (covo_gtsam.datasets.images) and the decoded frames of a
TUM sequence (TumSequence.load, loader, images); the PNG fast path in test_tum_png.py."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from covo_gtsam.camera import Camera
from covo_gtsam.datasets.images import load_depth, load_grey, to_grey
from covo_gtsam.datasets.tum import DEPTH_SCALE, TumSequence
from covo_gtsam.errors import ConfigError, InputError


def _write_png(path: Path, array: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), array)
    return path


def test_load_depth_reads_metres(tmp_path):
    raw = np.zeros((480, 640), np.uint16)
    raw[10, 20] = 5000
    raw[11, 21] = 12345
    depth = load_depth(_write_png(tmp_path / "d.png", raw))
    assert depth.dtype == np.float32 and depth.shape == (480, 640)
    assert depth[10, 20] == pytest.approx(1.0) and depth[11, 21] == pytest.approx(12345 / 5000)
    assert depth[0, 0] == 0.0
    assert load_depth(tmp_path / "d.png", depth_scale=1000.0)[10, 20] == pytest.approx(5.0)


def test_load_depth_rejects_8bit(tmp_path):
    p = _write_png(tmp_path / "depth8.png", np.full((480, 640), 7, np.uint8))
    with pytest.raises(InputError, match=r"depth8\.png.*8-bit"):
        load_depth(p)


def test_load_depth_rejects_wrong_size(tmp_path):
    p = _write_png(tmp_path / "small.png", np.zeros((240, 320), np.uint16))
    with pytest.raises(InputError, match=r"small\.png.*320x240.*expected 640x480"):
        load_depth(p)
    assert load_depth(p, shape=None).shape == (240, 320)
    assert load_depth(p, shape=(240, 320)).shape == (240, 320)


def test_load_depth_rejects_colour(tmp_path):
    p = _write_png(tmp_path / "rgb16.png", np.zeros((480, 640, 3), np.uint16))
    with pytest.raises(InputError, match="3 channels"):
        load_depth(p)


def test_load_depth_rejects_truncated_and_missing(tmp_path):
    noise = np.random.default_rng(0).integers(0, 60000, (480, 640)).astype(np.uint16)
    full = _write_png(tmp_path / "full.png", noise)
    cut = tmp_path / "cut.png"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    with pytest.raises(InputError, match=r"cut\.png.*unreadable or corrupt"):
        load_depth(cut)
    with pytest.raises(InputError, match="does not exist"):
        load_depth(tmp_path / "nope.png")
    with pytest.raises(InputError, match="unreadable or corrupt"):
        load_grey(cut)


def test_load_grey_and_to_grey(tmp_path):
    rng = np.random.default_rng(2)
    bgr = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    grey = load_grey(_write_png(tmp_path / "c.png", bgr))
    assert grey.shape == (48, 64) and grey.dtype == np.uint8
    np.testing.assert_array_equal(to_grey(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    np.testing.assert_array_equal(to_grey(bgr[:, :, ::-1], bgr=False), to_grey(bgr))
    np.testing.assert_array_equal(to_grey(np.dstack([bgr, np.full((48, 64), 255, np.uint8)])), to_grey(bgr))
    np.testing.assert_array_equal(to_grey(grey[:, :, None]), grey)
    assert to_grey(grey) is not None
    with pytest.raises(InputError, match="uint8"):
        to_grey(bgr.astype(np.float32))
    with pytest.raises(InputError, match="shape"):
        to_grey(np.zeros((4, 4, 2), np.uint8))


# ------------------------------------------------------------------------------------------
# decoded frames of a TUM sequence
# ------------------------------------------------------------------------------------------
def test_tum_sequence_returns_decoded_frames(small_sample):
    seq = TumSequence(small_sample(3))
    assert seq.depth_scale == DEPTH_SCALE == 5000.0
    grey, depth = seq.load(1)
    np.testing.assert_array_equal(grey, load_grey(seq.rgb_paths[1]))
    np.testing.assert_array_equal(depth, load_depth(seq.depth_paths[1], 5000.0))
    assert grey.dtype == np.uint8 and depth.dtype == np.float32 and grey.shape == depth.shape == (480, 640)
    load = seq.loader()
    for i, frame in enumerate(seq.images()):
        for a, b in zip(frame, load(i)):
            np.testing.assert_array_equal(a, b)
    assert len(list(seq.images(2))) == 2


def test_tum_sequence_owns_its_depth_scale(small_sample):
    path = small_sample(2)
    raw = cv2.imread(TumSequence(path).depth_paths[0], cv2.IMREAD_UNCHANGED)
    _, depth = TumSequence(path, depth_scale=1000.0).load(0)
    np.testing.assert_array_equal(depth, raw.astype(np.float32) * np.float32(1 / 1000.0))
    _, depth = TumSequence(path).load(0, depth_scale=2500.0)
    np.testing.assert_array_equal(depth, raw.astype(np.float32) * np.float32(1 / 2500.0))
    for bad in (0.0, -5000.0, float("nan"), "5000"):
        with pytest.raises(ConfigError, match="depth_scale"):
            TumSequence(path, depth_scale=bad)


def test_tum_sequence_decoding_errors_name_the_file(small_sample):
    seq = TumSequence(small_sample(3))
    with pytest.raises(InputError, match=r"\.png: image is 640x480, the camera's is 320x240"):
        seq.load(0, camera=Camera(258.65, 258.1, 159.75, 127.65, width=320, height=240))
    Path(seq.depth_paths[1]).write_bytes(b"not a png")
    frames = list(seq.images())
    assert isinstance(frames[1], InputError) and Path(seq.depth_paths[1]).name in str(frames[1])
    assert not isinstance(frames[0], InputError) and not isinstance(frames[2], InputError)
    Path(seq.rgb_paths[2]).unlink()
    with pytest.raises(InputError, match="does not exist"):
        seq.loader()(2)


@pytest.mark.parametrize("what", ["rgb", "depth"])
def test_a_png_declaring_a_huge_image_is_refused_before_decoding(small_sample, monkeypatch, what):
    import zlib

    seq = TumSequence(small_sample(2))
    w = h = 16000  # 768 MB of RGB pixels declared in a file of a few hundred kB
    kind, step = (2, 3) if what == "rgb" else (0, 2)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + tag + data + zlib.crc32(tag + data).to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8 if what == "rgb" else 16, kind, 0, 0, 0])
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(50 * (1 + w * step)), 9))
           + chunk(b"IEND", b""))
    Path(seq.rgb_paths[1] if what == "rgb" else seq.depth_paths[1]).write_bytes(png)
    decoded = []
    monkeypatch.setattr(cv2, "imread", lambda *a, **k: decoded.append(a) or None)
    with pytest.raises(InputError, match=r"is 16000x16000, (expected|the camera's is) 640x480"):
        seq.load(1)
    assert not decoded


def test_load_grey_holds_the_camera_shape_after_decoding(tmp_path):
    wide = tmp_path / "wide.png"  # as many pixels as 640x480, another shape: passes the header's count
    cv2.imwrite(str(wide), np.zeros((160, 1920), np.uint8))
    with pytest.raises(InputError, match=r"image is 1920x160, the camera's is 640x480"):
        load_grey(wide, shape=(480, 640))
    assert load_grey(wide).shape == (160, 1920)
