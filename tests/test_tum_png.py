"""The fast path for plain PNG files (covo_gtsam.datasets.images._png_bytes, with the optional isal):
the same images as OpenCV, and OpenCV for every file without isal. In a file of its own that runs
after the ROS bag tests (test_rosbag's streamed-memory test measures a tracemalloc peak)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from covo_gtsam.datasets import images
from covo_gtsam.datasets.images import load_depth, load_grey


def _png_file(path: Path, pixels: np.ndarray, colour_type: int, bit_depth: int, filter_type: int,
              extra: bytes = b"") -> Path:
    """A PNG with every row filtered with ``filter_type`` (0 None, 1 Sub): what the TUM files are."""
    h, w = pixels.shape[:2]
    data = pixels.astype(">u2" if bit_depth == 16 else np.uint8).reshape(h, -1).view(np.uint8)
    if filter_type == 1:
        step = data.shape[1] // w
        data = data.astype(np.int32)
        data[:, step:] -= data[:, :-step].copy()
        data = (data % 256).astype(np.uint8)
    rows = np.concatenate([np.full((h, 1), filter_type, np.uint8), data], axis=1)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + extra
                     + chunk(b"IDAT", zlib.compress(rows.tobytes())) + chunk(b"IEND", b""))
    return path


@pytest.mark.parametrize("filter_type", [0, 1])
def test_png_fast_path_reads_what_opencv_reads(tmp_path, filter_type):
    pytest.importorskip("isal")
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    rgb[:8] = rng.integers(0, 256, (8, 1, 1), dtype=np.uint8)  # grey pixels (R = G = B) too
    depth = rng.integers(0, 65536, (48, 64), dtype=np.uint16)
    grey8 = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    for name, pixels, ctype, bits in (("rgb", rgb, 2, 8), ("depth", depth, 0, 16), ("grey", grey8, 0, 8)):
        p = _png_file(tmp_path / f"{name}.png", pixels, ctype, bits, filter_type)
        assert images._png_bytes(str(p), ((ctype, bits),)) is not None  # the fast path is taken
    np.testing.assert_array_equal(load_grey(tmp_path / "rgb.png"),
                                  cv2.imread(str(tmp_path / "rgb.png"), cv2.IMREAD_GRAYSCALE))
    np.testing.assert_array_equal(load_grey(tmp_path / "grey.png"), grey8)
    got = load_depth(tmp_path / "depth.png", shape=None)
    np.testing.assert_array_equal(got, depth.astype(np.float32) * np.float32(1 / 5000.0))
    # anything else goes to OpenCV: another chunk, a broken checksum
    text = struct.pack(">I", 4) + b"tEXt" + b"a\x00bc" + struct.pack(">I", zlib.crc32(b"tEXta\x00bc"))
    p = _png_file(tmp_path / "text.png", rgb, 2, 8, filter_type, extra=text)
    assert images._png_bytes(str(p), ((2, 8),)) is None
    np.testing.assert_array_equal(load_grey(p), load_grey(tmp_path / "rgb.png"))
    broken = bytearray((tmp_path / "rgb.png").read_bytes())
    broken[-20] ^= 0xFF  # inside the IDAT data
    (tmp_path / "broken.png").write_bytes(bytes(broken))
    assert images._png_bytes(str(tmp_path / "broken.png"), ((2, 8),)) is None


def test_png_fast_path_on_the_tum_sample(sample_dir):
    pytest.importorskip("isal")
    rgb = sorted((sample_dir / "rgb").glob("*.png"))[:5]
    depth = sorted((sample_dir / "depth").glob("*.png"))[:5]
    assert rgb and depth
    kept = []
    for c, d in zip(rgb, depth):  # colour and depth in turn, as a frame loader reads them
        assert images._png_bytes(str(c), ((2, 8),)) is not None
        assert images._png_bytes(str(d), ((0, 16),)) is not None
        kept.append((load_grey(c), load_depth(d)))
    for (grey, depth_m), c, d in zip(kept, rgb, depth):  # the work arrays reused: no image shares them
        np.testing.assert_array_equal(grey, cv2.imread(str(c), cv2.IMREAD_GRAYSCALE))
        want = cv2.imread(str(d), cv2.IMREAD_UNCHANGED).astype(np.float32) * np.float32(1 / 5000.0)
        np.testing.assert_array_equal(depth_m, want)


def test_without_isal_opencv_decodes_the_same_images(sample_dir, tmp_path, monkeypatch):
    """The fast path is optional: without isal every file goes to OpenCV, with the same images."""
    rgb = sorted((sample_dir / "rgb").glob("*.png"))[:3]
    depth = sorted((sample_dir / "depth").glob("*.png"))[:3]
    sub = _png_file(tmp_path / "sub.png", np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8),
                    2, 8, 1)
    fast = [load_grey(p) for p in rgb + [sub]] + [load_depth(p, shape=None) for p in depth]
    monkeypatch.setattr(images, "_isal_zlib", None)
    assert images._png_bytes(str(rgb[0]), ((2, 8),)) is None and images._png_grey(str(rgb[0])) is None
    slow = [load_grey(p) for p in rgb + [sub]] + [load_depth(p, shape=None) for p in depth]
    for a, b in zip(fast, slow):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)

