"""Image decoding of the dataset readers: an image file to grey uint8 (:func:`load_grey`), a 16-bit
depth PNG to metres (:func:`load_depth`) and a colour array to grey (:func:`to_grey`). A missing,
unreadable, corrupt or wrong-sized file raises :class:`~covo_gtsam.errors.InputError` naming the file.
"""

from __future__ import annotations

import math
import os

import cv2
import numpy as np

from ..errors import InputError


def _check_file(path: str | os.PathLike, what: str) -> str:
    from ..io import file_problem

    p = os.fspath(path)
    problem = file_problem(p)
    if problem is not None:
        raise InputError(f"{p}: {what} file {problem}")
    return p


def load_grey(path: str | os.PathLike) -> np.ndarray:
    """Grey uint8 image (H, W) of an image file (``cv2.IMREAD_GRAYSCALE``).

    Raises:
        InputError: the file is missing, unreadable or corrupt.
    """
    p = _check_file(path, "image")
    img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{p}: image is unreadable or corrupt")
    return img


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
    raw = cv2.imread(p, cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"{p}: depth image is unreadable or corrupt")
    if raw.ndim != 2:
        raise InputError(f"{p}: depth image has {raw.shape[2]} channels, expected a single channel")
    if raw.dtype != np.uint16:
        bits = 8 * raw.dtype.itemsize
        raise InputError(
            f"{p}: depth image is {bits}-bit {raw.dtype}, expected 16-bit (uint16, value/{depth_scale:g} = metres)")
    if shape is not None and raw.shape != tuple(shape):
        raise InputError(
            f"{p}: depth image is {raw.shape[1]}x{raw.shape[0]}, expected {shape[1]}x{shape[0]}")
    return raw.astype(np.float32) * np.float32(1.0 / depth_scale)


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
