"""covo-gtsam: error-aware RGB-D visual odometry on GTSAM.

The public API, importable from the package itself (loaded on first use, so ``import covo_gtsam``
and ``covo --help`` stay quick)::

    from covo_gtsam import Camera, OdometryConfig, VisualOdometry, estimate_relative_pose
    from covo_gtsam import TumSequence, run_sequence, evaluate_run, RunEvaluation
"""

from importlib import import_module

from ._version import __version__

#: public name -> module that holds it
_PUBLIC = {
    "Camera": "camera",
    "OdometryConfig": "config",
    "OdometryStep": "steps",
    "StepStatus": "steps",
    "StepHistory": "steps",
    "VisualOdometry": "odometry",
    "FrontendConfig": "frontend",
    "estimate_relative_pose": "estimator",
    "RelativePoseResult": "estimator",
    "load_config": "config",
    "save_config": "config",
    "TumSequence": "datasets.tum",
    "run_sequence": "pipeline",
    "RunResult": "pipeline",
    "evaluate_run": "evaluation",
    "RunEvaluation": "evaluation",
    "ate": "metrics",
    "rpe": "metrics",
    "relative_pose_nees": "metrics",
    "chi2_quantile": "chi2",
    "CovoError": "errors",
    "CovoWarning": "errors",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(import_module(f".{_PUBLIC[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_PUBLIC})
