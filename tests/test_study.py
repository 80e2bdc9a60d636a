"""covo evaluate and covo simulate on a local pool and on Dask: the same numbers as serially."""

from __future__ import annotations

import csv
import json

import pytest

from covo_gtsam.cli import main

NUMBERS = ("frames", "lost", "flagged", "weak_consensus", "rpe1_m", "rpe30_m", "ate_m", "anees_t", "anees_r",
           "above_9.35_t", "above_9.35_r",
           "chain_anees_t", "chain_anees_r", "chain_anees_r_axes_turned_back", "worst_60_t", "worst_60_r")


def _rows(out):
    with open(out / "summary.csv") as f:
        return {r["sequence"]: {k: r[k] for k in NUMBERS} for r in csv.DictReader(f)}


def _evaluate(seqs, out, *extra):
    assert main(["evaluate", *map(str, seqs), "--out", str(out), "--max-frames", "12", "--quiet", *extra]) == 0
    return _rows(out)


@pytest.mark.slow
@pytest.mark.realdata
def test_evaluate_serial_pool_and_dask_give_the_same_numbers(fr1_rpy_dir, fr1_desk_dir, tmp_path, capsys):
    seqs = [fr1_rpy_dir, fr1_desk_dir]
    serial = _evaluate(seqs, tmp_path / "serial", "--workers", "1")
    assert set(serial) == {fr1_rpy_dir.name, fr1_desk_dir.name}
    rpy = serial[fr1_rpy_dir.name]
    assert rpy["frames"] == "12" and float(rpy["rpe1_m"]) > 0 and float(rpy["anees_t"]) > 0
    assert serial[fr1_desk_dir.name]["frames"] == "9"
    # each row is that sequence's covo run
    m = json.loads((tmp_path / "serial" / fr1_rpy_dir.name / "metrics.json").read_text())
    assert float(rpy["rpe1_m"]) == m["rpe_1"]["trans_rmse"]
    assert rpy["worst_60_t"] == "" and m["nees_breakdown"]["windows"] is None  # 11 pairs: no window of 60
    assert (tmp_path / "serial" / "summary.md").read_text().count("\n") == 4
    assert (tmp_path / "serial" / "plots" / "summary.png").is_file()

    assert _evaluate(seqs, tmp_path / "pool", "--workers", "2", "--no-plots") == serial
    # the same folder again without plots: the earlier summary figure goes (a folder describes one study)
    assert _evaluate([fr1_desk_dir], tmp_path / "serial", "--workers", "1", "--no-plots").keys() == {fr1_desk_dir.name}
    assert not (tmp_path / "serial" / "plots" / "summary.png").exists()

    pytest.importorskip("dask.distributed")
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://", dashboard_address=":0",
                      host="127.0.0.1") as cluster:
        assert _evaluate(seqs, tmp_path / "dask", "--scheduler", cluster.scheduler_address, "--no-plots") == serial
    for name in serial:
        a = (tmp_path / "serial" / name / "relative.txt").read_text()
        assert a == (tmp_path / "dask" / name / "relative.txt").read_text()


@pytest.mark.slow
def test_simulate_on_workers_and_dask_same_seed_same_numbers(tmp_path):
    base = ["simulate", "--runs", "24", "--points", "60", "--seed", "5", "--no-plots", "--quiet"]
    assert main(base + ["--out", str(tmp_path / "serial")]) == 0
    serial = json.loads((tmp_path / "serial" / "metrics.json").read_text())
    assert main(base + ["--out", str(tmp_path / "pool"), "--workers", "2"]) == 0
    assert json.loads((tmp_path / "pool" / "metrics.json").read_text()) == serial
    pytest.importorskip("dask.distributed")
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://", dashboard_address=":0",
                      host="127.0.0.1") as cluster:
        assert main(base + ["--out", str(tmp_path / "dask"), "--scheduler", cluster.scheduler_address]) == 0
    assert json.loads((tmp_path / "dask" / "metrics.json").read_text()) == serial


@pytest.mark.realdata
@pytest.mark.slow  # waits for the connection to the unreachable scheduler to fail
def test_unreachable_scheduler_and_bad_sequence_are_one_line_exit_2(fr1_desk_dir, tmp_path, capsys):
    pytest.importorskip("dask.distributed")
    assert main(["evaluate", str(fr1_desk_dir), "--out", str(tmp_path / "a"), "--scheduler", "tcp://127.0.0.1:1",
                 "--connect-timeout", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tcp://127.0.0.1:1" in err
    assert main(["simulate", "--runs", "4", "--out", str(tmp_path / "b"), "--scheduler", "tcp://127.0.0.1:1",
                 "--connect-timeout", "1", "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "scheduler" in err
    assert main(["evaluate", str(fr1_desk_dir), str(tmp_path), "--out", str(tmp_path / "c"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "neither a TUM sequence folder" in err


@pytest.mark.parametrize("address", ["notaurl", "http://host:8786", "inproc://x", "tcp://[::1", "tcp://host:port"])
def test_malformed_scheduler_address_is_refused_before_connecting(sample_dir, tmp_path, capsys, monkeypatch,
                                                                   address):
    distributed = pytest.importorskip("dask.distributed")
    tried = []
    monkeypatch.setattr(distributed, "Client", lambda *a, **k: tried.append(a))
    assert main(["evaluate", str(sample_dir), "--out", str(tmp_path / "a"), "--scheduler", address,
                 "--connect-timeout", "5", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a scheduler address" in err and "Traceback" not in err
    assert not tried  # refused before any connection attempt


def test_transport_not_set_up_is_one_line_and_its_client_closed(tmp_path, capsys, monkeypatch):
    """tls:// without Dask's TLS configuration fails inside the client's constructor, before any
    network traffic: one line, and the half-built client is closed at once (left open, it prints a
    traceback when the interpreter exits)."""
    distributed = pytest.importorskip("dask.distributed")
    made = []

    class Recorded(distributed.Client):
        def __init__(self, *args, **kwargs):
            made.append(self)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(distributed, "Client", Recorded)
    assert main(["simulate", "--runs", "2", "--out", str(tmp_path / "s"), "--scheduler", "tls://127.0.0.1:1",
                 "--connect-timeout", "1", "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tls://127.0.0.1:1" in err and "TLS" in err and "Traceback" not in err
    assert made and all(client.status == "closed" for client in made)


def test_any_failure_to_connect_is_one_line_naming_the_address_and_reason(sample_dir, tmp_path, capsys,
                                                                         monkeypatch):
    distributed = pytest.importorskip("dask.distributed")

    class Failing(distributed.Client):
        def __init__(self, *args, **kwargs):
            raise RuntimeError("comm layer unavailable")

    monkeypatch.setattr(distributed, "Client", Failing)
    assert main(["evaluate", str(sample_dir), "--out", str(tmp_path / "e"), "--scheduler", "ucx://127.0.0.1:1",
                 "--connect-timeout", "1", "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ucx://127.0.0.1:1" in err and "RuntimeError: comm layer unavailable" in err


def test_evaluate_ends_with_exit_code_3_when_a_sequence_lost_every_frame(small_sample, tmp_path, capsys):
    import shutil

    import cv2
    import numpy as np

    good, bad = small_sample(3), tmp_path / "rgbd_dataset_freiburg1_blind"
    shutil.copytree(good, bad)
    for png in (bad / "depth").glob("*.png"):
        cv2.imwrite(str(png), np.zeros((480, 640), np.uint16))
    assert main(["evaluate", str(good), str(bad), "--out", str(tmp_path / "e"), "--quiet", "--no-plots",
                 "--workers", "1"]) == 3
    captured = capsys.readouterr()
    assert "no frame could be tracked in rgbd_dataset_freiburg1_blind" in captured.err
    assert (tmp_path / "e" / "summary.csv").is_file()  # the summary is written all the same


def test_evaluate_ends_with_exit_code_3_when_a_sequence_gave_no_relative_pose(small_sample, tmp_path, capsys):
    """Its first frame tracked, every later one lost: no relative pose, as covo run reports with exit code 3."""
    import shutil

    import cv2
    import numpy as np

    good, bad = small_sample(3), tmp_path / "rgbd_dataset_freiburg1_first_only"
    shutil.copytree(good, bad)
    for png in sorted((bad / "depth").glob("*.png"))[1:]:  # only the first frame has depth
        cv2.imwrite(str(png), np.zeros((480, 640), np.uint16))
    out = tmp_path / "e"
    assert main(["evaluate", str(good), str(bad), "--out", str(out), "--quiet", "--no-plots", "--workers", "1"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and good.name not in err
    assert "no relative pose could be estimated between any two frames of rgbd_dataset_freiburg1_first_only" in err
    rows = _rows(out)  # the summary is written all the same
    assert (rows[bad.name]["frames"], rows[bad.name]["lost"]) == ("3", "2") and rows[good.name]["lost"] == "0"
    assert main(["run", str(bad), "--out", str(tmp_path / "r"), "--quiet", "--no-plots"]) == 3


def test_summary_row_takes_the_worst_window_from_the_breakdown():
    from covo_gtsam.study import COLUMNS, summary_row

    windows = {"anees_translation": {"highest": 4.2}, "anees_rotation": {"highest": 2.9}}
    row = summary_row("s", {"frames": 300, "nees_breakdown": {"windows": windows}})
    assert (row["worst_60_t"], row["worst_60_r"]) == (4.2, 2.9) and set(COLUMNS) <= set(row)
    assert summary_row("s", {"nees_breakdown": {"windows": None}})["worst_60_t"] is None
    assert summary_row("s", {})["worst_60_r"] is None  # no ground truth
    axes = {"rotation_vector_deg": [-1.4, -0.5, 0.1], "standard_error_deg": [0.3] * 3, "chains_anees_rotation": 1.8}
    assert summary_row("s", {"reference_axes": axes})["chain_anees_r_axes_turned_back"] == 1.8
    row = summary_row("s", {"flagged_pairs": 3, "weak_consensus_pairs": 2})
    assert (row["flagged"], row["weak_consensus"]) == (3, 2)
    assert summary_row("s", {"reference_axes": None})["chain_anees_r_axes_turned_back"] is None
    assert summary_row("s", {"twist_change_response": {"delay_ms": 9.0}})["twist_change_delay_ms"] == 9.0
    assert summary_row("s", {"twist_change_response": None})["twist_change_delay_ms"] is None


def test_evaluate_into_a_folder_used_before_names_the_earlier_sequences_left(small_sample, tmp_path, capsys):
    """The earlier study's results folders of sequences not in this one stay (they are the user's
    results), and one warning line says so: the new summary lists this study's sequences only."""
    import csv
    import shutil

    first = small_sample(3)
    second = tmp_path / "rgbd_dataset_freiburg1_copy"
    shutil.copytree(first, second)
    out = tmp_path / "e"
    args = ["--out", str(out), "--quiet", "--no-plots", "--workers", "1"]
    assert main(["evaluate", str(first), str(second), *args]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(first), *args]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert err == [f"covo: warning: {out}: the results folders of an earlier study's sequences stay "
                   f"({second.name}); the summary lists this study's only"], err
    with open(out / "summary.csv") as f:
        assert [row["sequence"] for row in csv.DictReader(f)] == [first.name]
    assert (out / second.name / "metrics.json").is_file()
    assert main(["evaluate", str(first), *args]) == 0  # the summary before listed only this study's
    assert not capsys.readouterr().err.strip()


def test_evaluate_checks_every_sequence_before_the_first_run(small_sample, tmp_path, capsys):
    """A sequence that exists but cannot be used (no frame with both images; a folder name without
    the camera) stops the study before any run, not after the runs before it."""
    import shutil

    good = small_sample(3)
    for name, damage in (("rgbd_dataset_freiburg1_emptyrgb", lambda s: (s / "rgb.txt").write_text("# none\n")),
                         ("no_camera_in_this_name", lambda s: None)):
        bad = tmp_path / name
        shutil.copytree(good, bad)
        damage(bad)
        out = tmp_path / f"e_{name}"
        assert main(["evaluate", str(good), str(bad), "--out", str(out), "--quiet", "--no-plots",
                     "--workers", "1"]) == 2
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert len(err) == 1 and err[0].startswith(f"covo: error: {bad}"), err
        assert not out.exists() or not any(out.iterdir())  # no run was started


def test_evaluate_refuses_a_results_folder_that_is_a_sequence_before_writing(small_sample, tmp_path, capsys):
    """``OUT/<name>`` holding a sequence (the input itself when OUT is its parent, or another with
    the same name) is refused before any run and before an earlier summary is replaced."""
    import shutil

    first, second = small_sample(3), small_sample(3)
    out = tmp_path / "e"
    shutil.copytree(second, out / second.name)  # another sequence where second's results would go
    (out / "summary.csv").write_text("sequence\nearlier\n")
    for args in ([str(first), str(second)], [str(first), str(second.parent / second.name)]):
        assert main(["evaluate", *args, "--out", str(out), "--quiet", "--no-plots", "--workers", "1"]) == 2
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert err == [f"covo: error: {out / second.name}: is a sequence's folder (it holds a TUM sequence's "
                       "rgb.txt); write the results into another one (--out)"], err
        assert sorted(p.name for p in out.iterdir()) == sorted([second.name, "summary.csv"])
        assert (out / "summary.csv").read_text() == "sequence\nearlier\n"
    assert main(["evaluate", str(second), "--out", str(second.parent), "--quiet", "--no-plots", "--workers", "1"]) == 2
    assert "is a sequence's folder" in capsys.readouterr().err


def test_evaluate_goes_on_past_a_sequence_whose_run_fails(small_sample, tmp_path, capsys):
    """A bag is opened by its own run: one that cannot be read gets an empty row and one error line,
    the other sequences' results and the summary are written, and the exit code is 2."""
    import csv

    import numpy as np

    good, bad = small_sample(3), tmp_path / "broken.bag"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    out = tmp_path / "e"
    assert main(["evaluate", str(bad), str(good), "--out", str(out), "--quiet", "--no-plots", "--workers", "1"]) == 2
    captured = capsys.readouterr()
    err = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith(f"covo: error: {bad}"), err
    assert "broken: failed" in captured.out
    with open(out / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["sequence"] for r in rows] == ["broken", good.name]
    assert rows[0]["frames"] == "" and rows[1]["frames"] == "3"
    assert (out / good.name / "metrics.json").is_file()
