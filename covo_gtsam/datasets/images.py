"""Image decoding of the dataset readers: an image file to grey uint8 (:func:`load_grey`), a 16-bit
depth PNG to metres (:func:`load_depth`) and a colour array to grey (:func:`to_grey`). A missing,
unreadable, corrupt or wrong-sized file raises :class:`~covo_gtsam.errors.InputError` naming the file.

Plain PNG files (as the TUM files are) take a fast path when the optional ``isal`` package is
installed (``pip install "covo-gtsam[fast]"``, :func:`_png_bytes`): the same images in about two
thirds of the time. Any other file, or any file without ``isal``, is decoded by OpenCV.
"""

from __future__ import annotations

import math
import os
import sys
import threading

import cv2
import numpy as np

from ..errors import InputError

try:  # optional ("fast" extra): a faster inflate for plain PNG files (see _png_bytes)
    from isal import isal_zlib as _isal_zlib
except ImportError:  # OpenCV then decodes every image
    _isal_zlib = None


def _check_file(path: str | os.PathLike, what: str) -> str:
    from ..io import file_problem

    p = os.fspath(path)
    problem = file_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {what} file {problem}")
    return p


def _png_size(path: str) -> tuple[int, int] | None:
    """``(height, width)`` from a PNG file's header (IHDR), None for any other file."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")


def _wrong_size(path: str, what: str, size: tuple[int, ...], shape: tuple[int, int], expected: str) -> InputError:
    """The error of an image of ``size`` (height, width) where ``shape`` was expected."""
    return InputError(f"{path}: {what} is {size[1]}x{size[0]}, {expected} {shape[1]}x{shape[0]}")


def _check_size(path: str, shape: tuple[int, int] | None, what: str, expected: str) -> None:
    """A PNG's pixel count from its header against the expected ``(height, width)``, before any
    decoding (a small file can declare a huge image; the exact shape is checked after decoding, as
    an orientation tag may turn the image)."""
    size = None if shape is None else _png_size(path)
    if size is not None and size[0] * size[1] != shape[0] * shape[1]:
        raise _wrong_size(path, what, size, shape, expected)


def load_grey(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Grey uint8 image (H, W) of an image file (``cv2.IMREAD_GRAYSCALE``; plain PNG files through
    :func:`_png_grey` when ``isal`` is installed, the same image). ``shape``: the camera's
    ``(height, width)``, checked from a PNG's header before decoding (None: any size).

    Raises:
        InputError: the file is missing, unreadable or corrupt, or (a PNG) not of ``shape``.
    """
    p = _check_file(path, "image")
    _check_size(p, shape, "image", "the camera's is")
    img = _png_grey(p)
    if img is None:
        img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{p}: image is unreadable or corrupt")
    if shape is not None and img.shape != tuple(shape):
        raise _wrong_size(p, "image", img.shape, shape, "the camera's is")
    return img


#: libpng's grey of an RGB pixel, as OpenCV asks for it (``png_set_rgb_to_gray(.., 0.299, 0.587)``):
#: ``(9797 R + 19234 G + 3737 B) >> 15``, as ``cv2.transform`` of int32 pixels computes it: the
#: weights over 2^15 and an offset of ``2^-16 - 1/2`` (all exact in double precision), rounded to
#: the nearest integer, which is the floor of the weighted sum (its fraction, a multiple of 2^-15,
#: never rounds as a tie). Checked against the shift for every 8-bit RGB value.
_PNG_GREY_WEIGHTS = np.array([[9797.0, 19234.0, 3737.0, 0.5 - 16384.0]]) / 32768.0


def _png_bytes(path: str, formats: tuple[tuple[int, int], ...]) -> tuple[np.ndarray, int] | None:
    """Pixel bytes (H, W, bytes per pixel) and colour type of a PNG file that is plain enough for a
    fast path: only IHDR, IDAT and IEND chunks (valid CRCs), a ``(colour type, bit depth)``
    of ``formats`` (colour type 0 grey or 2 RGB; bit depth 8 or 16), no interlacing, and every row
    filtered with "None" or every row with "Sub" (as the TUM RGB-D files are). The compressed data
    is inflated with ISA-L (``isal``, about three times as fast as zlib) and the "Sub" filter
    undone by a running sum along the rows (``cv2.integral``). The bytes are the file's (uint8) when
    no row is filtered, else int32 running sums whose low byte (the sum mod 256) is the pixel byte
    (:func:`_low_bytes`). None for any other file, or without ``isal``: OpenCV decodes those."""
    if _isal_zlib is None:
        return None
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return None
    view, pos, idat, header = memoryview(data), 8, [], None
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    while True:
        if pos + 12 > len(data):
            return None
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind, end = data[pos + 4:pos + 8], pos + 12 + length
        if end > len(data) or _isal_zlib.crc32(view[pos + 4:end - 4]) != int.from_bytes(data[end - 4:end], "big"):
            return None
        if kind == b"IHDR" and header is None and length == 13:
            header = data[pos + 8:pos + 21]
        elif kind == b"IDAT" and header is not None:
            idat.append(view[pos + 8:end - 4])
        elif kind == b"IEND" and idat and end == len(data):
            break
        else:
            return None
        pos = end
    width, height = int.from_bytes(header[:4], "big"), int.from_bytes(header[4:8], "big")
    bit_depth, colour_type = header[8], header[9]
    if (colour_type, bit_depth) not in formats or tuple(header[10:]) != (0, 0, 0) or width == 0 or height == 0:
        return None
    channels = {0: 1, 2: 3}[colour_type]
    step = channels * bit_depth // 8
    try:  # the output's size given: one allocation, not a growing buffer
        raw = _isal_zlib.decompress(idat[0] if len(idat) == 1 else b"".join(idat), bufsize=height * (1 + width * step))
    except Exception:  # isal's own error for corrupt data: let OpenCV report the file
        return None
    if len(raw) != height * (1 + width * step):
        return None
    rows = np.frombuffer(raw, np.uint8).reshape(height, 1 + width * step)
    filters = rows[:, 0]
    pixels = rows[:, 1:].reshape(height, width, step)
    if not filters.any():
        return pixels, colour_type
    if not np.all(filters == 1) or height * width * 255 >= 1 << 31:  # int32 sums below
        return None
    # "Sub": each byte adds the one a pixel to its left; the running sum of each row (mod 256). OpenCV
    # reads the rows where they are (no copy without the filter bytes) and subtracts about three
    # times as fast as numpy on these strided views (its saturation never acts: the differences are
    # the rows' running sums, 0 to width * 255)
    total = cv2.integral(pixels, sum=_png_scratch("a", (height + 1, width + 1, step), np.int32))
    row_sum = cv2.subtract(total[1:, 1:], total[:-1, 1:], dst=_png_scratch("b", pixels.shape, np.int32))
    return row_sum, colour_type


#: Index of an int32's lowest byte among its four.
_LOW_BYTE = 0 if sys.byteorder == "little" else 3


def _low_bytes(pixels: np.ndarray) -> np.ndarray:
    """The pixel bytes (H, W, bytes per pixel) uint8 of what :func:`_png_bytes` returns."""
    return pixels if pixels.dtype == np.uint8 else np.ascontiguousarray(pixels.view(np.uint8)[..., _LOW_BYTE::4])


_png_local = threading.local()


def _png_scratch(slot: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """A work array in one of this thread's two memory slots ("a", "b"), kept for the next image
    (fresh arrays of megabytes cost more in page faults than the arithmetic on them). What
    :func:`_png_bytes` returns lives in slot "b" until the thread's next image."""
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buffer = getattr(_png_local, slot, None)
    if buffer is None or buffer.shape[0] < nbytes:
        buffer = np.empty(nbytes, np.uint8)
        setattr(_png_local, slot, buffer)
    return buffer[:nbytes].view(dtype).reshape(shape)


def _png_grey(path: str) -> np.ndarray | None:
    """``cv2.imread(path, cv2.IMREAD_GRAYSCALE)`` of an 8-bit grey or RGB PNG through
    :func:`_png_bytes` (the same image: libpng's grey, :data:`_PNG_GREY_WEIGHTS`), None when the
    fast path does not apply."""
    found = _png_bytes(path, ((2, 8), (0, 8)))
    if found is None:
        return None
    pixels, colour_type = found
    if colour_type == 0:
        return np.ascontiguousarray(_low_bytes(pixels)[:, :, 0])
    if pixels.dtype == np.int32:  # "Sub" rows undone: int32 running sums in slot "b"; "a" is free again
        rgb, out = np.bitwise_and(pixels, 255, out=pixels), "a"
    else:  # unfiltered rows: the file's bytes
        rgb, out = _png_scratch("a", pixels.shape, np.int32), "b"
        np.copyto(rgb, pixels)
    grey = cv2.transform(rgb, _PNG_GREY_WEIGHTS, dst=_png_scratch(out, pixels.shape[:2], np.int32))
    return grey.astype(np.uint8)  # 0-255: libpng's ">> 15"


def load_depth(
    path: str | os.PathLike, depth_scale: float = 5000.0, shape: tuple[int, int] | None = (480, 640)
) -> np.ndarray:
    """Depth image in metres (float32, 0 = no measurement) of a 16-bit PNG: ``value / depth_scale``.

    ``shape`` is the expected ``(height, width)``; None accepts any size.

    Raises:
        InputError: the file is missing, unreadable or corrupt, not a single-channel 16-bit
            image (e.g. an 8-bit PNG), or not of the expected size.
    """
    if not (depth_scale > 0 and math.isfinite(depth_scale)):
        raise InputError(f"depth_scale must be a positive number, got {depth_scale!r}")
    p = _check_file(path, "depth")
    _check_size(p, shape, "depth image", "expected")
    found = _png_bytes(p, ((0, 16),))
    if found is None:
        raw = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    else:  # big-endian 16-bit samples
        raw = _low_bytes(found[0]).view(">u2")[:, :, 0].astype(np.uint16)
    if raw is None:
        raise InputError(f"{p}: depth image is unreadable or corrupt")
    if raw.ndim != 2:
        raise InputError(f"{p}: depth image has {raw.shape[2]} channels, expected a single channel")
    if raw.dtype != np.uint16:
        bits = 8 * raw.dtype.itemsize
        raise InputError(
            f"{p}: depth image is {bits}-bit {raw.dtype}, expected 16-bit (uint16, value/{depth_scale:g} = metres)")
    if shape is not None and raw.shape != tuple(shape):
        raise _wrong_size(p, "depth image", raw.shape, shape, "expected")
    return np.multiply(raw, np.float32(1.0 / depth_scale), dtype=np.float32)  # one pass: the same values


def to_grey(image: np.ndarray, bgr: bool = True) -> np.ndarray:
    """Grey uint8 (H, W) of a grey (H, W) / (H, W, 1), colour (H, W, 3) or (H, W, 4) uint8 image.

    Colour channels are in OpenCV's BGR(A) order unless ``bgr`` is False (RGB(A)).
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise InputError(f"image must be 8-bit (uint8), got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        return np.ascontiguousarray(img)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        code = {
            (3, True): cv2.COLOR_BGR2GRAY, (3, False): cv2.COLOR_RGB2GRAY,
            (4, True): cv2.COLOR_BGRA2GRAY, (4, False): cv2.COLOR_RGBA2GRAY,
        }[(img.shape[2], bool(bgr))]
        return cv2.cvtColor(np.ascontiguousarray(img), code)
    raise InputError(f"image must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {img.shape}")
