"""Type and range checks of configuration values; each failure is a :class:`ConfigError` naming the setting.

Booleans are not numbers here (``True`` is no pixel sigma) and numbers are not booleans (the
string ``"false"`` is no ``False``); numpy scalars count as the Python type they stand for.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from .errors import ConfigError

#: Sanity limits shared by the configurations and the command line: beyond them the models are
#: meaningless and float arithmetic overflows. Pixel noise in pixels, covariance scale phi.
MIN_PIXEL_SIGMA, MAX_PIXEL_SIGMA = 0.01, 1e4
MAX_SCALE = 1e6


def is_int(value) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def is_real(value) -> bool:
    """A real number (Python or numpy int/float), not a bool; may be NaN or inf."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def check_bool(name: str, value) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(f"{name} must be true or false, got {value!r}")


def check_int(name: str, value, minimum: int, maximum: int | None = None) -> None:
    """An integer in ``[minimum, maximum]`` (no upper limit if None)."""
    if is_int(value) and value >= minimum and (maximum is None or value <= maximum):
        return
    if maximum is None:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    raise ConfigError(f"{name} must be an integer from {minimum} to {maximum}, got {value!r}")


def check_real(name: str, value, kind: str, minimum: float | None = None, maximum: float | None = None,
               finite: bool = True) -> None:
    """A real number; ``kind`` is ``"positive"`` (> 0), ``"non-negative"`` (>= 0) or ``"any"``;
    optionally within ``[minimum, maximum]``; NaN never, inf only if not ``finite``."""
    ok = is_real(value) and not math.isnan(value) and (math.isfinite(value) or not finite)
    if ok:
        ok = {"positive": value > 0, "non-negative": value >= 0, "any": True}[kind]
        ok = ok and (minimum is None or value >= minimum) and (maximum is None or value <= maximum)
    if ok:
        return
    what = "a finite" if finite and kind == "any" else ("a" if kind == "any" else f"a {kind}")
    what += " number"
    if minimum is not None and maximum is not None:
        what += f" from {minimum:g} to {maximum:g}"
    elif minimum is not None:
        what += f" >= {minimum:g}"
    elif maximum is not None:
        what += f" <= {maximum:g}"
    raise ConfigError(f"{name} must be {what}, got {value!r}")


def check_choice(name: str, value, allowed: tuple) -> None:
    if not any(value is a or (isinstance(value, str) and value == a) for a in allowed):
        raise ConfigError(f"unknown {name} {value!r}; choose one of {allowed}")
