"""Named choices of the settings. Each is a ``str`` enum: a member equals its value
(``Weighting.CONSISTENT == "consistent"``), prints as its value and is written as its value to
configuration and results files, so the plain strings keep working wherever a choice is passed
or compared."""

from __future__ import annotations

from enum import Enum


class Choice(str, Enum):
    """Base of the choices: a ``str`` whose ``str()`` and format are its value."""

    __str__ = str.__str__
    __format__ = str.__format__


class Weighting(Choice):
    """Weighting of the two-way point-transfer residuals (:mod:`covo_gtsam.factors`)."""

    CONSISTENT = "consistent"  #: each pair once, with the transferred covariance (docs/derivation.md)
    THESIS = "thesis"  #: the thesis's (4.16): overconfident by a scene-dependent factor


class RobustKernel(Choice):
    """Robust re-weighting of the estimator (no kernel: ``None``, written ``"none"``)."""

    HUBER = "huber"
    CAUCHY = "cauchy"


class MotionModel(Choice):
    """Prediction of the relative pose of the next frame."""

    CONSTANT_VELOCITY = "constant_velocity"  #: the motion of the last two posed frames, scaled by time
    NONE = "none"  #: no prediction


class OutlierRejection(Choice):
    """Outlier rejection of the matched point pairs (:func:`covo_gtsam.frontend.associate_frames`)."""

    RIGID3D = "rigid3d"  #: RANSAC of a rigid transform with a Mahalanobis inlier test
    HOMOGRAPHY = "homography"  #: the thesis's code: ``cv2.findHomography`` RANSAC
    NONE = "none"  #: every match is kept
