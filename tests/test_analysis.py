"""Noise analysis (covo_gtsam.analysis): unreadable frames are skipped, bugs are not."""

from __future__ import annotations

import pytest

from conftest import SMALL_SEQ_FRAMES as N_FRAMES
from conftest import corrupt_frame


def test_analysis_skips_unreadable_frames_but_not_bugs(small_seq, monkeypatch):
    from covo_gtsam import analysis
    from covo_gtsam.datasets.tum import TumSequence

    corrupt_frame(small_seq, 3, "truncated")
    summary = analysis.analyze_sequence(TumSequence(small_seq))
    assert summary["frame_pairs"] == N_FRAMES - 3  # the pairs 2-3 and 3-4 are gone

    def broken(*a, **k):
        raise RuntimeError("a bug, not a bad frame")

    monkeypatch.setattr(analysis, "prepare_frame", broken)
    with pytest.raises(RuntimeError, match="a bug"):
        analysis.analyze_sequence(TumSequence(small_seq))
