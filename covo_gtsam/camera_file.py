"""Camera files for ``--camera FILE``: intrinsics, distortion, image size and depth scale.

Two layouts are read:

* **ROS ``camera_calibration`` YAML** (``.yaml`` / ``.yml``, as written by ``cameracalibrator`` and
  read by ``camera_info_manager``): ``image_width``, ``image_height``, ``camera_matrix``
  (``rows: 3, cols: 3, data: [fx 0 cx 0 fy cy 0 0 1]``), ``distortion_model`` (``plumb_bob``) and
  ``distortion_coefficients`` (``data: [k1 k2 p1 p2 k3]``); ``camera_name``,
  ``rectification_matrix`` and ``projection_matrix`` are accepted and not used. The optional
  ``depth_scale`` (raw depth units per metre) is not part of ROS's format; without it the run's
  configuration keeps its own (default 5000). Needs PyYAML.
* **TOML** (``.toml``) or **JSON** (``.json``) with the keys ``fx fy cx cy`` (pixels), ``width
  height`` (pixels), ``depth_scale`` (raw depth units per metre of the depth images: 5000 for TUM
  RGB-D, 1000 for depth recorded in millimetres) and the optional distortion ``k1 k2 p1 p2 k3``
  (OpenCV's order; 0 when absent) and ``name``.

Pixel coordinates and distortion follow :class:`~covo_gtsam.camera.Camera` (OpenCV's model,
distortion of the colour image the depth is registered to). Missing or unknown keys and values
that are not numbers raise :class:`~covo_gtsam.errors.ConfigError` naming the file.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from .camera import Camera
from .errors import ConfigError
from .io import read_settings_file

__all__ = ["load_camera_file", "resolve_camera"]

_REQUIRED = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")
_DIST = ("k1", "k2", "p1", "p2", "k3")
_YAML_KEYS = {"image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
              "distortion_coefficients", "rectification_matrix", "projection_matrix", "depth_scale"}


def _read(p: Path) -> dict:
    if p.suffix.lower() not in (".yaml", ".yml", ".toml", ".json"):
        raise ConfigError(f"{p}: a camera file is .yaml/.yml (ROS camera_calibration), .toml or .json")
    return read_settings_file(p, "camera file", ("YAML", "TOML", "JSON"))


def _number(p: Path, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{p}: {key} must be a finite number, got {value!r}")
    return float(value)


def _matrix_data(p: Path, data: dict, key: str, size: int | tuple[int, ...]) -> list[float]:
    m = data.get(key)
    values = m.get("data") if isinstance(m, dict) else None
    sizes = (size,) if isinstance(size, int) else size
    if not isinstance(values, list) or len(values) not in sizes:
        raise ConfigError(f"{p}: {key} needs 'data' with {' or '.join(map(str, sizes))} numbers")
    return [_number(p, f"{key}.data", v) for v in values]


def _from_yaml(p: Path, data: dict) -> tuple[dict, float | None]:
    missing = [k for k in ("image_width", "image_height", "camera_matrix") if k not in data]
    if missing:
        raise ConfigError(f"{p}: missing keys {', '.join(missing)} (ROS camera_calibration YAML)")
    unknown = sorted(set(data) - _YAML_KEYS)
    if unknown:
        raise ConfigError(f"{p}: unknown keys {', '.join(unknown)}")
    K = _matrix_data(p, data, "camera_matrix", 9)
    dist = [0.0] * 5
    if "distortion_coefficients" in data:
        model = data.get("distortion_model", "plumb_bob")
        D = _matrix_data(p, data, "distortion_coefficients", (0, 4, 5, 8))
        if model not in ("plumb_bob", "rational_polynomial") and any(D):
            raise ConfigError(f"{p}: distortion_model {model!r} is not supported (plumb_bob: k1 k2 p1 p2 k3)")
        if any(D[5:]):
            raise ConfigError(f"{p}: distortion k4..k6 are not supported (plumb_bob: k1 k2 p1 p2 k3)")
        dist[: min(5, len(D))] = D[:5]
    values = {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5], "dist": tuple(dist),
              "width": data["image_width"], "height": data["image_height"],
              "name": str(data.get("camera_name") or p.stem)}
    scale = data.get("depth_scale")
    return values, None if scale is None else _number(p, "depth_scale", scale)


def _from_table(p: Path, data: dict) -> tuple[dict, float]:
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise ConfigError(f"{p}: missing keys {', '.join(missing)} (a camera file has {' '.join(_REQUIRED)}, "
                          f"optional {' '.join(_DIST)} name)")
    unknown = sorted(set(data) - set(_REQUIRED) - set(_DIST) - {"name"})
    if unknown:
        raise ConfigError(f"{p}: unknown keys {', '.join(unknown)}")
    values = {k: _number(p, k, data[k]) for k in ("fx", "fy", "cx", "cy")}
    values["dist"] = tuple(_number(p, k, data.get(k, 0.0)) for k in _DIST)
    values["width"], values["height"] = data["width"], data["height"]
    values["name"] = str(data.get("name") or p.stem)
    return values, _number(p, "depth_scale", data["depth_scale"])


def load_camera_file(path: str | os.PathLike) -> tuple[Camera, float | None]:
    """The camera of a camera file and its depth scale (raw units per metre; None when a ROS YAML
    file gives none). See the module docstring for the layouts.

    Raises:
        ConfigError: unreadable file, missing or unknown keys, invalid values.
    """
    p = Path(path)
    data = _read(p)
    is_yaml = p.suffix.lower() in (".yaml", ".yml")
    values, scale = _from_yaml(p, data) if is_yaml else _from_table(p, data)
    for k in ("width", "height"):
        v = values[k]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"{p}: {'image_' if is_yaml else ''}{k} must be a positive integer, got {v!r}")
    if scale is not None and not scale > 0:
        raise ConfigError(f"{p}: depth_scale must be positive, got {scale:g}")
    try:
        return Camera(**values), scale
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from exc


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
