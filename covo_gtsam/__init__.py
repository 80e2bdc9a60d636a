"""covo-gtsam: error-aware RGB-D visual odometry on GTSAM."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("covo-gtsam")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without installing
    __version__ = "unknown"
