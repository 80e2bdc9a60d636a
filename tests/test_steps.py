"""Step statuses, the history a caller keeps, and the deprecated history of VisualOdometry."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from covo_gtsam.datasets.images import load_depth, load_grey
from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.odometry import VisualOdometry
from covo_gtsam.steps import POSED_STATUSES, OdometryStep, StepHistory, StepStatus


def test_statuses_keep_their_strings_and_say_what_the_step_has():
    assert [s.value for s in StepStatus] == ["first", "tracked", "restart", "lost"]
    assert StepStatus.RELATIVE_POSE == "tracked" and f"{StepStatus.NEW_SEGMENT}" == "restart"
    assert set(POSED_STATUSES) == {"first", "tracked", "restart"}
    for status, has_pose, has_relative in (("first", True, False), ("tracked", True, True),
                                           ("restart", True, False), ("lost", False, False)):
        step = OdometryStep(0.0, status)
        assert step.status is StepStatus(status) and step.status == status
        assert (step.has_pose, step.has_relative_pose, step.tracked) == (has_pose, has_relative, has_pose)
    with pytest.raises(ValueError):
        OdometryStep(0.0, "tracking")


def test_history_keeps_slim_steps_and_gives_the_trajectory():
    posed = OdometryStep(1.0, "first", pose=gtsam.Pose3(), pose_covariance=np.zeros((6, 6)),
                         error_bases={"timing": np.eye(6)}, result=object())
    lost = OdometryStep(2.0, "lost", reason="no texture")
    history = StepHistory()
    assert history.add(posed) is posed and history.add(lost) is lost
    assert len(history) == 2 and history[0].result is None and history[0].error_bases is None
    assert posed.result is not None  # the caller's step is left as it was
    assert history.posed_steps == [history[0]] and history.lost_steps == [history[1]]
    stamps, poses = history.trajectory()
    assert stamps.tolist() == [1.0] and poses.shape == (1, 4, 4)
    keeping = StepHistory(keep_error_bases=True)
    keeping.add(posed)
    assert keeping[0].error_bases is posed.error_bases


def test_visual_odometry_history_is_deprecated_but_works(sample_dir):
    seq = TumSequence(sample_dir)
    vo = VisualOdometry(seq.camera)
    history = StepHistory()
    for i in range(3):
        history.add(vo.register_frame(load_grey(seq.rgb_paths[i]), load_depth(seq.depth_paths[i]), seq.timestamps[i]))
    history.add(vo.mark_lost(seq.timestamps[3], "unreadable"))
    with pytest.warns(DeprecationWarning, match="VisualOdometry.steps is deprecated"):
        assert [s.status for s in vo.steps] == [s.status for s in history] == ["first", "tracked", "tracked", "lost"]
    with pytest.warns(DeprecationWarning):
        assert len(vo.tracked_steps) == 3 and len(vo.lost_steps) == 1
    with pytest.warns(DeprecationWarning):
        np.testing.assert_array_equal(vo.trajectory()[1], history.trajectory()[1])
    with pytest.warns(DeprecationWarning):
        vo.keep_error_bases = True
