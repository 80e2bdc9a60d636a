"""Camera files for ``--camera FILE``: intrinsics, distortion, image size and depth scale.

Three layouts are read:

* **ROS ``camera_calibration`` YAML** (``.yaml`` / ``.yml``, as written by ``cameracalibrator`` and
  read by ``camera_info_manager``): ``image_width``, ``image_height``, ``camera_matrix``
  (``rows: 3, cols: 3, data: [fx 0 cx 0 fy cy 0 0 1]``), ``distortion_model`` (``plumb_bob``) and
  ``distortion_coefficients`` (``data: [k1 k2 p1 p2 k3]``); ``camera_name``,
  ``rectification_matrix`` and ``projection_matrix`` are accepted and not used. The optional
  ``depth_scale`` (raw depth units per metre) is not part of ROS's format; without it the run's
  configuration keeps its own (default 5000). Needs PyYAML.
* **OpenCV calibration YAML** (``.yaml`` / ``.yml`` as ``cv::FileStorage`` writes it, e.g. OpenCV's
  camera calibration sample: a first line ``%YAML:1.0`` or matrices tagged ``!!opencv-matrix``): ``image_width``, ``image_height``,
  ``camera_matrix`` (a 3x3 ``!!opencv-matrix``) and the optional ``distortion_coefficients``
  (4, 5 or 8 values, OpenCV's order) and ``depth_scale``, read with OpenCV's own reader; the
  calibration's other entries (views, reprojection errors, board) are not used. A
  ``fisheye_model`` other than 0 is not supported.
* **TOML** (``.toml``) or **JSON** (``.json``) with the keys ``fx fy cx cy`` (pixels), ``width
  height`` (pixels), ``depth_scale`` (raw depth units per metre of the depth images: 5000 for TUM
  RGB-D, 1000 for depth recorded in millimetres) and the optional distortion ``k1 k2 p1 p2 k3``
  (OpenCV's order; 0 when absent) and ``name``.

Pixel coordinates and distortion follow :class:`~covo_gtsam.camera.Camera` (OpenCV's model,
distortion of the colour image the depth is registered to). Missing or unknown keys and values
that are not numbers raise :class:`~covo_gtsam.errors.ConfigError` naming the file, as do:

* a principal point outside the image (``cx`` not in ``[0, width]``, ``cy`` not in ``[0, height]``);
* in YAML, a ``camera_matrix`` not of the form ``[fx 0 cx 0 fy cy 0 0 1]`` (skew, a third row other
  than ``0 0 1``, e.g. a transposed matrix) and ``rows``/``cols`` that do not match the data;
* a distortion that :meth:`~covo_gtsam.camera.Camera.undistort` cannot invert over the image: on a
  grid of pixels (edges and corners included, at most 16 px apart) undistorting and distorting
  again must come back within 0.01 px (a distortion that folds the image, or maps its corners to no
  undistorted point, fails this; so does one the iterative undistortion does not converge on).

YAML numbers such as ``1e-05`` or ``5.173E2`` (floats to ROS's reader, strings to YAML 1.1's) are
read as numbers; other strings, NaN and infinities are not.

A ROS bag's ``sensor_msgs/CameraInfo`` goes through the same checks
(:func:`check_camera_matrix`, :func:`plumb_bob`, :func:`checked_camera`; see
:mod:`covo_gtsam.datasets.rosbag`).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import ConfigError
from .io import read_settings_file

__all__ = ["check_camera_matrix", "checked_camera", "is_opencv_yaml", "load_camera_file", "plumb_bob",
           "resolve_camera"]

_REQUIRED = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
_DIST = ("k1", "k2", "p1", "p2", "k3")
#: A decimal number written as text: YAML 1.1 reads ``1e-05`` and ``5.173E2`` as strings.
_DECIMAL = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
#: Largest spacing (pixels) of the grid the distortion is checked on, and the round-trip tolerance (pixels).
_GRID_PX, _ROUND_TRIP_PX = 16, 0.01
_YAML_KEYS = {"image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
              "distortion_coefficients", "rectification_matrix", "projection_matrix", "depth_scale"}


def _read(p: Path) -> dict:
    if p.suffix.lower() not in (".yaml", ".yml", ".toml", ".json"):
        raise ConfigError(f"{p}: a camera file is .yaml/.yml (ROS camera_calibration), .toml or .json")
    return read_settings_file(p, "camera file", ("YAML", "TOML", "JSON"))


def _number(p: Path, key: str, value, text: bool = False) -> float:
    """``value`` as a finite float; with ``text``, a string holding a decimal number is one too."""
    x = value
    if text and isinstance(value, str) and _DECIMAL.fullmatch(value.strip()):
        x = float(value)
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ConfigError(f"{p}: {key} must be a finite number, got {value!r}")
    return float(x)


def _matrix_data(p: Path, data: dict, key: str, size: int | tuple[int, ...],
                 shape: tuple[int, int] | None = None) -> list[float]:
    """The numbers of a YAML matrix ``{rows, cols, data}``; ``rows``/``cols``, when given, must match the
    data (and ``shape``, if set)."""
    m = data.get(key)
    values = m.get("data") if isinstance(m, dict) else None
    sizes = (size,) if isinstance(size, int) else size
    if not isinstance(values, list) or len(values) not in sizes:
        raise ConfigError(f"{p}: {key} needs 'data' with {' or '.join(map(str, sizes))} numbers")
    dims = {d: m[d] for d in ("rows", "cols") if d in m}
    for d, v in dims.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ConfigError(f"{p}: {key}.{d} must be a non-negative integer, got {v!r}")
    if len(dims) == 2:
        if dims["rows"] * dims["cols"] != len(values):
            raise ConfigError(f"{p}: {key} has rows: {dims['rows']}, cols: {dims['cols']} but "
                              f"{len(values)} data values")
        if shape is not None and (dims["rows"], dims["cols"]) != shape:
            raise ConfigError(f"{p}: {key} must be {shape[0]}x{shape[1]}, got rows: {dims['rows']}, "
                              f"cols: {dims['cols']}")
    elif dims:
        raise ConfigError(f"{p}: {key} gives {next(iter(dims))} without {'cols' if 'rows' in dims else 'rows'}")
    return [_number(p, f"{key}.data", v, text=True) for v in values]


def check_camera_matrix(where: str | os.PathLike, K, key: str = "camera_matrix", item: str = "data") -> None:
    """``K`` (9 numbers, row-major) must be ``[fx 0 cx 0 fy cy 0 0 1]``: the camera model has no
    skew. Errors name ``where``, then the matrix ``key`` and its elements as ``item[i]``.

    Raises:
        ConfigError: another length, skew, a third row other than ``0 0 1`` (e.g. a transposed matrix),
            or a non-zero ``item[3]``.
    """
    K = [float(k) for k in K]
    if len(K) != 9:
        raise ConfigError(f"{where}: {key} needs 9 numbers (3x3), got {len(K)}")
    if K[6:] != [0.0, 0.0, 1.0]:
        hint = " (a transposed, column-major matrix?)" if K[2] == K[5] == 0.0 and K[8] == 1.0 else ""
        raise ConfigError(f"{where}: {key} third row must be [0, 0, 1], got [{K[6]:g}, {K[7]:g}, {K[8]:g}]"
                          f"{hint}")
    if K[1] != 0.0:
        raise ConfigError(f"{where}: {key} skew ({item}[1]) must be 0, got {K[1]:g}: the camera model has none")
    if K[3] != 0.0:
        lower_left = f"{item}[3]" if item == key else f"{key} {item}[3]"
        raise ConfigError(f"{where}: {lower_left} (row 2, column 1) must be 0, got {K[3]:g}")


def plumb_bob(where: str | os.PathLike, model: str, D) -> tuple[float, float, float, float, float]:
    """The distortion ``(k1, k2, p1, p2, k3)`` of ROS's ``distortion_model`` and coefficients ``D``
    (any length; missing ones are 0).

    Raises:
        ConfigError: a model other than ``plumb_bob`` or ``rational_polynomial`` with non-zero
            coefficients, or non-zero ``k4..k6``.
    """
    D = [float(d) for d in D]
    if model not in ("plumb_bob", "rational_polynomial") and any(D):
        raise ConfigError(f"{where}: distortion_model {model!r} is not supported (plumb_bob: k1 k2 p1 p2 k3)")
    if any(D[5:]):
        raise ConfigError(f"{where}: distortion k4..k6 are not supported (plumb_bob: k1 k2 p1 p2 k3)")
    return tuple(D[:5] + [0.0] * (5 - min(5, len(D))))


def _and_unknown(unknown: list[str]) -> str:
    """``"; unknown keys ..."`` for a file that also misses keys (a misspelt key is both), else ``""``."""
    return f"; unknown keys {', '.join(map(str, unknown))}" if unknown else ""


def _from_yaml(p: Path, data: dict) -> tuple[dict, float | None]:
    missing = [k for k in ("image_width", "image_height", "camera_matrix") if k not in data]
    unknown = sorted(set(data) - _YAML_KEYS)
    if missing:
        raise ConfigError(f"{p}: missing keys {', '.join(missing)} (ROS camera_calibration YAML)"
                          f"{_and_unknown(unknown)}")
    if unknown:
        raise ConfigError(f"{p}: unknown keys {', '.join(unknown)}")
    K = _matrix_data(p, data, "camera_matrix", 9, shape=(3, 3))
    check_camera_matrix(p, K)
    dist = (0.0,) * 5
    if "distortion_coefficients" in data:
        D = _matrix_data(p, data, "distortion_coefficients", (0, 4, 5, 8))
        dist = plumb_bob(p, data.get("distortion_model", "plumb_bob"), D)
    values = {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5], "dist": dist,
              "width": data["image_width"], "height": data["image_height"],
              "name": str(data.get("camera_name") or p.stem)}
    scale = data.get("depth_scale")
    return values, None if scale is None else _number(p, "depth_scale", scale, text=True)


def is_opencv_yaml(p: Path) -> bool:
    """True for a YAML file in OpenCV's ``FileStorage`` dialect, which YAML readers reject: a first
    line ``%YAML:1.0`` (OpenCV 3 and 4) or matrices tagged ``!!opencv-matrix`` (OpenCV 5 too)."""
    try:
        with open(p, "rb") as f:
            head = f.read(1 << 20)
    except OSError:
        return False
    return head.lstrip(b"\xef\xbb\xbf").startswith(b"%YAML:") or b"!!opencv-matrix" in head


def _from_opencv(p: Path) -> tuple[dict, float | None]:
    """An OpenCV calibration file's camera, read with ``cv2.FileStorage``."""
    import cv2

    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # a parse error comes as either, by OpenCV version
        text = str(exc.__cause__ or exc).strip()
        raise ConfigError(f"{p}: not a valid OpenCV calibration file ({text.splitlines()[-1] if text else 'unreadable'})"
                          ) from None
    try:
        if not fs.isOpened():
            raise ConfigError(f"{p}: cannot read the OpenCV calibration file")
        missing = [k for k in ("image_width", "image_height", "camera_matrix") if fs.getNode(k).empty()]
        if missing:
            raise ConfigError(f"{p}: missing keys {', '.join(missing)} (OpenCV calibration file)")

        def matrix(key: str) -> np.ndarray:
            m = fs.getNode(key).mat()
            if m is None:
                raise ConfigError(f"{p}: {key} must be an opencv-matrix")
            return np.asarray(m, dtype=float)

        def number(key: str):
            node = fs.getNode(key)
            if not (node.isInt() or node.isReal()):
                raise ConfigError(f"{p}: {key} must be a number")
            return node.real()

        K = matrix("camera_matrix")
        if K.shape != (3, 3):
            raise ConfigError(f"{p}: camera_matrix must be 3x3, got {K.shape[0]}x{K.shape[1]}")
        K = [_number(p, "camera_matrix", k) for k in K.ravel()]
        check_camera_matrix(p, K, item="camera_matrix")
        if not fs.getNode("fisheye_model").empty() and number("fisheye_model") != 0:
            raise ConfigError(f"{p}: fisheye_model is not supported (plumb_bob: k1 k2 p1 p2 k3)")
        dist = (0.0,) * 5
        if not fs.getNode("distortion_coefficients").empty():
            D = matrix("distortion_coefficients").ravel()
            if D.size not in (4, 5, 8):
                raise ConfigError(f"{p}: distortion_coefficients needs 4, 5 or 8 numbers, got {D.size}")
            dist = plumb_bob(p, "plumb_bob", [_number(p, "distortion_coefficients", d) for d in D])
        size = {}
        for k in ("image_width", "image_height"):
            v = number(k)
            size[k] = int(v) if float(v).is_integer() else v
        scale = None if fs.getNode("depth_scale").empty() else _number(p, "depth_scale", number("depth_scale"))
    finally:
        fs.release()
    return {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5], "dist": dist, "width": size["image_width"],
            "height": size["image_height"], "name": p.stem}, scale


def _from_table(p: Path, data: dict) -> tuple[dict, float]:
    missing = [k for k in _REQUIRED if k not in data]
    unknown = sorted(set(data) - set(_REQUIRED) - set(_DIST) - {"name"})
    if missing:
        raise ConfigError(f"{p}: missing keys {', '.join(missing)} (a camera file has {' '.join(_REQUIRED)}, "
                          f"optional {' '.join(_DIST)} name){_and_unknown(unknown)}")
    if unknown:
        raise ConfigError(f"{p}: unknown keys {', '.join(unknown)}")
    values = {k: _number(p, k, data[k]) for k in ("fx", "fy", "cx", "cy")}
    values["dist"] = tuple(_number(p, k, data.get(k, 0.0)) for k in _DIST)
    values["width"], values["height"] = data["width"], data["height"]
    values["name"] = str(data.get("name") or p.stem)
    return values, _number(p, "depth_scale", data["depth_scale"])


def _check_distortion(p: str | os.PathLike, cam: Camera) -> None:
    """Undistorting a grid of pixels over the image (edges and corners included) and distorting them
    again must give them back within ``_ROUND_TRIP_PX``: otherwise the run's undistorted pixels are wrong."""
    if not cam.has_distortion:
        return
    nu, nv = (int(np.ceil((size - 1) / _GRID_PX)) + 1 for size in (cam.width, cam.height))
    u, v = np.meshgrid(np.linspace(0.0, cam.width - 1, nu), np.linspace(0.0, cam.height - 1, nv))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    err = np.linalg.norm(cam.distort(cam.undistort(uv)) - uv, axis=1)
    bad = np.flatnonzero(~(err <= _ROUND_TRIP_PX))  # NaN is bad too
    if bad.size:
        i = bad[np.argmax(np.nan_to_num(err[bad], nan=np.inf))]
        coeffs = " ".join(f"{d:g}" for d in cam.dist)
        raise ConfigError(f"{p}: distortion k1 k2 p1 p2 k3 = {coeffs} cannot be undistorted over the "
                          f"{cam.width}x{cam.height} image: pixel ({uv[i, 0]:.0f}, {uv[i, 1]:.0f}) undistorted and "
                          f"distorted again is {err[i]:.3g} px away")


def load_camera_file(path: str | os.PathLike) -> tuple[Camera, float | None]:
    """The camera of a camera file and its depth scale (raw units per metre; None when a ROS YAML
    file gives none). See the module docstring for the layouts.

    Raises:
        ConfigError: unreadable file, missing or unknown keys, invalid values (a principal point
            outside the image, a YAML camera matrix with skew or another third row than 0 0 1, a
            distortion that cannot be undistorted over the image).
    """
    p = Path(path)
    is_yaml = p.suffix.lower() in (".yaml", ".yml")
    if is_yaml and is_opencv_yaml(p):
        values, scale = _from_opencv(p)
    else:
        data = _read(p)
        values, scale = _from_yaml(p, data) if is_yaml else _from_table(p, data)
    if scale is not None and not scale > 0:
        raise ConfigError(f"{p}: depth_scale must be positive, got {scale:g}")
    return checked_camera(p, values, size_prefix="image_" if is_yaml else ""), scale


def checked_camera(where: str | os.PathLike, values: dict, size_prefix: str = "") -> Camera:
    """The :class:`Camera` of ``values`` (``fx fy cx cy`` px, ``dist`` k1 k2 p1 p2 k3, ``width height``
    px, ``name``) after the checks every camera source goes through: the image size positive
    integers (named ``size_prefix + "width"``, ...), the principal point inside the image, the focal
    lengths in range, the distortion invertible over the image.

    Raises:
        ConfigError: a check fails; the message starts with ``where``.
    """
    for k in ("width", "height"):
        v = values[k]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"{where}: {size_prefix}{k} must be a positive integer, got {v!r}")
    for k, n in (("cx", values["width"]), ("cy", values["height"])):
        if not 0 <= values[k] <= n:
            raise ConfigError(f"{where}: principal point {k}={values[k]:g} px is outside the image (0 to {n} px)")
    try:
        cam = Camera(**values)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc
    _check_distortion(where, cam)
    return cam


def resolve_camera(value: str | None) -> tuple[Camera | None, float | None]:
    """``--camera``: None, a preset name (``fr1``, ``fr2``, ``fr3``) or a camera file.

    Returns ``(camera or None, depth scale or None)``.
    """
    if value is None:
        return None, None
    from .camera import PRESETS

    if value.lower().replace("freiburg", "fr") in PRESETS:
        return Camera.preset(value), None
    p = Path(value)
    if not p.is_file():
        raise ConfigError(f"--camera {value}: neither a camera preset ({', '.join(sorted(PRESETS))}) "
                          "nor an existing camera file")
    return load_camera_file(p)
