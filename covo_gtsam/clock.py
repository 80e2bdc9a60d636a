"""The camera's frame clock, learnt from the timestamps alone.

A camera captures its frames on a regular clock (period ``P``, 33.3 ms at 30 Hz), but the stamps a
driver writes carry the time the frame reached it: in the TUM freiburg1 sequences they scatter by
up to +-3.7 ms (s.d. 1.9 ms) around a regular clock, in a repeating pattern. A pose estimated
from the images belongs to the capture time; a back end that takes the stamp at its word sees the
difference as an error ``Exp(r xi)`` (``r`` the stamp's offset, ``xi`` the camera's twist), which
grows with the camera's speed.

:class:`FrameClock` fits ``t_k = t_0 + P k`` by least squares to the stamps of the last ``window``
frames (the frame count ``k`` advancing by ``round(dt / P)`` across dropped frames) and reports
each new stamp's offset ``r = t - (t_0 + P k)`` from that fit, causally, as frames arrive. Stamps
that do not follow a regular clock (scattering by more than 15 % of the period, or off it by more
than a quarter period) get no offset, and neither do the first 20 frames of a run: their stamps
keep their full jitter (the ``stamp_jitter`` term of the covariance).

:func:`check_stamp` and :func:`check_depth_offset` check the stamps a caller passes.
"""

from __future__ import annotations

from collections import deque

import gtsam
import numpy as np

from .errors import InputError


def seconds(value, what: str = "timestamp") -> float:
    """``value`` as float seconds; InputError naming ``what`` for anything but a real number."""
    if isinstance(value, (str, bytes, bool, np.bool_)):
        raise InputError(f"{what} must be a number (seconds), got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number (seconds), got {value!r}") from None


def check_depth_offset(offset) -> float:
    """``offset`` (depth minus colour time, s) as float; InputError unless finite and at most 1 s."""
    d = seconds(offset, "depth time offset")
    if not (np.isfinite(d) and abs(d) <= 1.0):
        raise InputError(f"the depth image is {d!r} s from its colour image; at most 1 s is usable")
    return d


def check_stamp(timestamp, previous: float | None = None) -> float:
    """``timestamp`` as float seconds; InputError unless finite and not earlier than ``previous``
    (the previous frame's stamp, None for the first frame)."""
    t = seconds(timestamp)
    if not np.isfinite(t):
        raise InputError(f"timestamp must be finite, got {t!r}")
    if previous is not None and t < previous:
        raise InputError(
            f"timestamp {t!r} is earlier than the previous frame's {previous!r}; "
            "frames must be registered in time order")
    return t


class FrameClock:
    """Causal least-squares fit of a regular frame clock to the stamps seen so far.

    ``nominal_period_s``: the camera's nominal frame period (s), used to count frames across gaps
    (the fitted period once there is one). ``window``: how many recent frames the fit uses.
    ``min_frames``: no offsets until this many stamps were seen (at most ``window``): a fit of
    phase and period to fewer stamps, or of the phase alone with the nominal period, invents
    offsets when the camera's period differs from the nominal.
    """

    def __init__(self, nominal_period_s: float, window: int = 60, min_frames: int = 20) -> None:
        self.nominal = float(nominal_period_s)
        self._k: deque[float] = deque(maxlen=window)
        self._t: deque[float] = deque(maxlen=window)
        self._count = 0.0
        self._min = min(min_frames, window)
        self.period_s: float | None = None  # fitted period, once fitted
        self.samples = 0  # stamps in the last fit (0: none)

    def offset(self, timestamp: float) -> float | None:
        """Add ``timestamp`` (s, not earlier than the previous one) and return its offset from the
        fitted clock (s; positive: stamped after the clock's tick); None while the fit is not
        ready and when the stamps follow no regular clock (offsets beyond a quarter period)."""
        if self._t:
            steps = (timestamp - self._t[-1]) / (self.period_s or self.nominal)
            if not 0 <= steps <= 1000:  # a gap far beyond the window (or none to count): start over
                self._k.clear()
                self._t.clear()
            else:
                self._count += round(steps)
        self._k.append(self._count)
        self._t.append(float(timestamp))
        self.samples = 0
        if len(self._t) < self._min:
            return None
        k = np.asarray(self._k) - self._k[0]
        t = np.asarray(self._t) - self._t[0]
        A = np.stack([np.ones_like(k), k], axis=1)
        phase, period = np.linalg.lstsq(A, t, rcond=None)[0]
        if not (0.5 * self.nominal < period < 2.0 * self.nominal):
            return None  # no regular clock in these stamps
        self.period_s = float(period)
        resid = t - (phase + period * k)
        r = float(resid[-1])
        # stamps that scatter by more than 15 % of the period (5 ms at 30 Hz) follow no regular clock
        if not (abs(r) < 0.25 * period and np.std(resid) < 0.15 * period):
            return None
        self.samples = len(t)
        return r


def restamp(T: gtsam.Pose3, shift_ref: np.ndarray, shift_cur: np.ndarray) -> tuple[gtsam.Pose3, np.ndarray]:
    """A relative pose between two capture times moved to the frames' stamps.

    ``T`` is ``T_ref,cur`` between the captures; ``shift_ref``/``shift_cur`` are ``r xi`` of each
    frame (its stamp's offset from the capture, s, times the camera's body twist there, rad/s and
    m/s). The camera at the stamp is ``T_capture Exp(r xi)``, so the result is
    ``Exp(shift_ref)^-1 T Exp(shift_cur)``, returned with the 6x6 matrix ``Ad`` that carries a
    covariance of ``T`` (tangent ``[omega, v]``, right perturbation) to it: ``Ad C Ad^T`` (the
    shifts taken as exact; their uncertainty is the timing term's)."""
    A = gtsam.Pose3.Expmap(np.asarray(shift_ref, dtype=float))
    B = gtsam.Pose3.Expmap(np.asarray(shift_cur, dtype=float))
    return A.inverse().compose(T).compose(B), B.inverse().AdjointMap()
