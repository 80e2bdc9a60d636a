"""Pose graphs in g2o's text format (``graph.g2o`` of ``covo run``).

One line per tracked frame and one per estimated frame pair::

    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT id_ref id_cur x y z qx qy qz qw I11 I12 ... I16 I22 ... I66

* ``id`` is the frame's index in the sequence (lost frames have no vertex, so ids have gaps);
  the vertex pose is ``T_world,cam`` (world = first tracked camera frame, as ``trajectory.txt``).
* The edge measurement is ``T_ref,cur`` (as ``relative.txt``); ``I..`` are the 21 upper-triangular
  entries, row by row, of its 6x6 information matrix (the inverse covariance).
* g2o orders the edge tangent **translation first**: ``[x y z rx ry rz]``; the package (GTSAM)
  orders it rotation first, ``[rx ry rz x y z]``. The information matrix is therefore
  ``P Sigma^-1 P`` with ``P`` swapping the two 3-blocks, cross blocks included.
* Rotation parameters: the information is over the rotation vector ``[rx ry rz]`` (radians) of the
  right perturbation ``T_true = T_est * Exp(xi)``, the convention GTSAM's ``readG2o`` and
  ``writeG2o`` use, so ``gtsam.readG2o(path, True)`` gives back exactly the covariances of
  ``relative.txt``. g2o's own ``EdgeSE3`` measures the rotation error by the vector part of the
  error quaternion, a half angle (``q_v ~ omega / 2``): read by g2o's optimiser as they are, these
  edges weigh rotation a quarter as much as they should (the rotation standard deviations count
  twice as large). Multiply the rotation block of the information by 4 and the cross blocks by 2
  to hand g2o the half-angle information.

Values are written with 17 significant digits (exact round trip of doubles).
"""

from __future__ import annotations

import os

import numpy as np

from .errors import InputError
from .geometry import pose_to_tum
from .io import _LineWriter

__all__ = ["G2oWriter", "g2o_information", "format_vertex", "format_edge"]

_SWAP = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
_UPPER = np.triu_indices(6)


def _num(v: float) -> str:
    return f"{float(v):.17g}"


def g2o_information(cov: np.ndarray) -> np.ndarray:
    """g2o information matrix (translation first) of a 6x6 GTSAM tangent covariance (rotation first).

    Raises:
        InputError: not a 6x6 finite, invertible matrix.
    """
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        raise InputError(f"a pose covariance must be a finite 6x6 matrix, got shape {cov.shape}")
    try:
        info = np.linalg.inv(cov)
    except np.linalg.LinAlgError as exc:
        raise InputError("the pose covariance is singular: no information matrix") from exc
    info = 0.5 * (info + info.T)
    return _SWAP @ info @ _SWAP


def format_vertex(index: int, T: np.ndarray) -> str:
    """``VERTEX_SE3:QUAT`` line (with newline) of a frame index and its 4x4 pose ``T_world,cam``."""
    row = pose_to_tum(np.asarray(T, dtype=float))
    return f"VERTEX_SE3:QUAT {int(index)} " + " ".join(_num(v) for v in row) + "\n"


def format_edge(index_ref: int, index_cur: int, T: np.ndarray, cov: np.ndarray) -> str:
    """``EDGE_SE3:QUAT`` line (with newline) of ``T_ref,cur`` (4x4) and its GTSAM tangent covariance."""
    row = pose_to_tum(np.asarray(T, dtype=float))
    info = g2o_information(cov)
    return (f"EDGE_SE3:QUAT {int(index_ref)} {int(index_cur)} " + " ".join(_num(v) for v in row) + " "
            + " ".join(_num(v) for v in info[_UPPER]) + "\n")


class G2oWriter(_LineWriter):
    """``graph.g2o`` written line by line (flushed): ``vertex(i, T_world_cam)`` and
    ``edge(i_ref, i_cur, T_ref_cur, cov)``; usable as a context manager."""

    header = ""

    def __init__(self, path: str | os.PathLike) -> None:
        super().__init__(path)

    def vertex(self, index: int, T: np.ndarray) -> None:
        self._write(format_vertex(index, T))

    def edge(self, index_ref: int, index_cur: int, T: np.ndarray, cov: np.ndarray) -> None:
        self._write(format_edge(index_ref, index_cur, T, cov))
