"""A gyroscope's angular velocities, for the rolling-shutter compensation.

The compensation moves each row of a frame to the frame's time with the camera's angular velocity
at that frame. Without a gyroscope that velocity is the mean of the two pairs' twists around the
frame, which misses the motion's change within the two intervals (docs/derivation.md, "A
gyroscope"); a gyroscope measures it at the frame, and its change over the readout too.

Conventions: samples ``(t, ω_g)`` are stamped on the camera's clock (seconds; ``time_offset_s`` is
added to them first) and give the body angular velocity in the gyroscope's own axes (rad/s).
``rotation`` is ``R_cam_gyro``, the gyroscope's axes in the camera's optical frame (x right, y down,
z forward), so ``ω_cam = R_cam_gyro ω_g``. Between samples the velocity is linear in time.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import DatasetError, InputError
from .geometry import quat_to_matrix

#: the angular acceleration is the slope of the angular velocity over this span (s) around a time:
#: wide enough to average a MEMS gyroscope's sample noise, short against a hand's motion
ACCELERATION_SPAN_S = 0.01
#: samples further apart than this (s) leave the time between them unmeasured (:meth:`Gyroscope.covers`)
MAX_GAP_S = 0.05


class Gyroscope:
    """Angular velocities of the camera (rad/s, camera frame) from gyroscope samples.

    Args:
        stamps: (N,) sample times (s, camera clock before ``time_offset_s``), strictly increasing.
        rates: (N, 3) angular velocities in the gyroscope's axes (rad/s).
        rotation: ``R_cam_gyro`` (3, 3), or a quaternion ``(qx, qy, qz, qw)``; identity by default.
        time_offset_s: added to ``stamps`` to put them on the camera's clock.

    Its error at a frame is the ``gyro`` term of the covariance (``sensor.gyro_sigma_rad_s``).
    """

    def __init__(self, stamps, rates, rotation=None, time_offset_s: float = 0.0) -> None:
        t = np.asarray(stamps, dtype=float).reshape(-1)
        w = np.asarray(rates, dtype=float)
        if w.shape != (len(t), 3):
            raise InputError(f"gyroscope: {len(t)} stamps need rates of shape ({len(t)}, 3), got {w.shape}")
        if len(t) < 2:
            raise InputError(f"gyroscope: at least 2 samples are needed, got {len(t)}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(w))):
            raise InputError("gyroscope: stamps and rates must be finite")
        if not np.all(np.diff(t) > 0):
            i = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise InputError(f"gyroscope: stamps must increase; sample {i + 1} ({t[i + 1]!r}) follows {t[i]!r}")
        if not (np.isfinite(time_offset_s) and abs(time_offset_s) <= 1.0):
            raise InputError(f"gyroscope: time_offset_s must be finite and within 1 s, got {time_offset_s!r}")
        R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=float)
        if R.shape == (4,):
            if not (np.all(np.isfinite(R)) and abs(np.linalg.norm(R) - 1.0) < 1e-3):
                raise InputError(f"gyroscope: the rotation quaternion (qx, qy, qz, qw) must be finite and of unit "
                                 f"norm, got {R} (norm {np.linalg.norm(R):.4g})")
            R = quat_to_matrix(R)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InputError("gyroscope: rotation must be a rotation matrix (3, 3) or a quaternion (qx, qy, qz, qw)")
        self.stamps = t + float(time_offset_s)
        self.rates = w @ R.T  # camera axes

    @classmethod
    def from_file(cls, path: str | os.PathLike, **kwargs) -> Gyroscope:
        """Samples from a text file, one ``t wx wy wz`` per line (s, rad/s; ``#`` comments; the
        layout of TUM RGB-D's ``accelerometer.txt``)."""
        from .io import _load_rows

        p = Path(path)
        rows, _ = _load_rows(p, 4, "t wx wy wz")
        if not len(rows):
            raise DatasetError(f"{p}: no gyroscope samples")
        try:
            return cls(rows[:, 0], rows[:, 1:], **kwargs)
        except InputError as exc:
            raise DatasetError(f"{p}: {exc}") from None

    @property
    def span(self) -> tuple[float, float]:
        return float(self.stamps[0]), float(self.stamps[-1])

    def covers(self, t: float, margin: float = 0.0) -> bool:
        """Whether samples surround ``t - margin`` to ``t + margin`` (s, on the frames' clock) with no gap
        over :data:`MAX_GAP_S`."""
        a, b = t - margin, t + margin
        if not (self.stamps[0] <= a and b <= self.stamps[-1]):
            return False
        i, j = np.searchsorted(self.stamps, [a, b])
        seg = self.stamps[max(i - 1, 0):min(j + 1, len(self.stamps))]
        return bool(np.all(np.diff(seg) <= MAX_GAP_S))

    def angular_velocity(self, t) -> np.ndarray:
        """The camera's angular velocity (..., 3) at times ``t`` (s, any shape; rad/s, camera frame),
        linear between samples."""
        return np.stack([np.interp(t, self.stamps, self.rates[:, i]) for i in range(3)], axis=-1)

    def angular_acceleration(self, t: float, span: float = ACCELERATION_SPAN_S) -> np.ndarray:
        """The camera's angular acceleration (3,) at ``t`` (rad/s^2, camera frame): the slope of a
        straight line fitted to the samples within ``span / 2`` of ``t`` (to the two around ``t``'s
        ends where fewer lie there)."""
        i, j = np.searchsorted(self.stamps, [t - 0.5 * span, t + 0.5 * span])
        i, j = max(min(i, len(self.stamps) - 2), 0), max(j, i + 2)
        ts, ws = self.stamps[i:j] - t, self.rates[i:j]
        tc = ts - ts.mean()
        return (tc @ (ws - ws.mean(axis=0))) / float(tc @ tc)


#: the shifts (s) :func:`clock_offset` tries, and its step
OFFSET_SEARCH_S, OFFSET_STEP_S = 0.05, 0.0005
#: nodes per interval for the gyroscope's mean over it (Simpson's rule)
_NODES = 9


def interval_means(gyro: Gyroscope, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """The gyroscope's mean angular velocity (N, 3; rad/s, camera axes) over each interval
    ``[starts, ends]`` (s), by Simpson's rule over :data:`_NODES` readings."""
    s = np.linspace(0.0, 1.0, _NODES)
    w = np.ones(_NODES)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    w /= w.sum()
    t = starts[:, None] + (ends - starts)[:, None] * s[None]
    return np.einsum("nkj,k->nj", gyro.angular_velocity(t), w)


def clock_offset(gyro: Gyroscope, starts, ends, rates) -> tuple[float, float] | None:
    """How far (s) the gyroscope's stamps lie behind the frames' clock, from the pairs' own turns: the
    shift ``τ`` under which its mean angular velocity over ``[start + τ, end + τ]`` best matches each
    pair's mean angular velocity ``rates`` (N, 3; rad/s, the pairs' ``Log(T)/dt``, camera axes), searched
    over ±:data:`OFFSET_SEARCH_S` in steps of :data:`OFFSET_STEP_S` and refined by a parabola; with its
    standard error from the residuals. ``--gyro-time-offset -τ`` aligns the clocks. None with fewer
    than 10 intervals the samples cover at every shift, or no turn to align on."""
    starts, ends, rates = (np.asarray(a, dtype=float) for a in (starts, ends, rates))
    ok = ((starts - OFFSET_SEARCH_S - 0.001 >= gyro.stamps[0]) & (ends + OFFSET_SEARCH_S + 0.001 <= gyro.stamps[-1])
          & (ends > starts))
    starts, ends, rates = starts[ok], ends[ok], rates[ok].reshape(-1, 3)
    if len(starts) < 10:
        return None
    shifts = np.arange(-OFFSET_SEARCH_S, OFFSET_SEARCH_S + 1e-12, OFFSET_STEP_S)
    cost = np.array([np.sum((interval_means(gyro, starts + d, ends + d) - rates) ** 2) for d in shifts])
    i = int(np.clip(np.argmin(cost), 1, len(shifts) - 2))
    c0, c1, c2 = cost[i - 1:i + 2]
    curve = c0 - 2 * c1 + c2
    tau = shifts[i] + (0.5 * OFFSET_STEP_S * (c0 - c2) / curve if curve > 0 else 0.0)
    # the mean's change with the shift: the change of the angular velocity over the interval, per its length
    slope = (gyro.angular_velocity(ends + tau) - gyro.angular_velocity(starts + tau)) / (ends - starts)[:, None]
    info = float(np.sum(slope**2))
    if not info > 0:
        return None
    residual = interval_means(gyro, starts + tau, ends + tau) - rates
    variance = float(np.sum(residual**2)) / max(residual.size - 1, 1)
    return float(tau), float(np.sqrt(variance / info))
