"""Without the optional extras, the commands that need them end with one line naming the install."""

from __future__ import annotations

import sys

from covo_gtsam.cli import main


def test_bag_without_rosbags_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rosbags", None)  # import rosbags raises ImportError
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"")
    assert main(["run", str(bag), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "covo-gtsam[ros]" in err


def test_scheduler_without_dask_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    assert main(["simulate", "--runs", "2", "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:1",
                 "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "covo-gtsam[dask]" in err
