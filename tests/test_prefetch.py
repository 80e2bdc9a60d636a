"""Frames prepared ahead (:mod:`covo_gtsam.prefetch`): order, the arrays through shared memory,
errors and dead workers, and the same run whichever way the frames were prepared."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from covo_gtsam import pipeline, prefetch
from covo_gtsam.datasets.tum import TumSequence
from covo_gtsam.errors import CovoError, InputError
from covo_gtsam.prefetch import Prefetcher, can_fork

needs_fork = pytest.mark.skipif(not can_fork(), reason="fork is not safe here (no fork, no /proc, or other threads)")


def _arrays(i: int):
    """A result with arrays of several kinds: float and int, a view, a non-contiguous slice, empty."""
    base = np.arange(12.0 * (i + 1)).reshape(-1, 3) + i
    return {"i": i, "base": base, "view": base[:, 1], "ints": np.full((4, 5), i, np.int32),
            "empty": np.zeros((0, 3)), "bytes": np.frombuffer(bytes([i % 256]) * 7, np.uint8).copy()}


@pytest.mark.parametrize("mode", ["serial", "thread", pytest.param("process", marks=needs_fork)])
def test_frames_come_in_order_with_their_arrays(mode):
    with Prefetcher(_arrays, 9, mode=mode) as frames:
        assert frames.mode == mode
        for i in range(9):
            got, want = frames.get(i), _arrays(i)
            assert got["i"] == i
            for key in ("base", "view", "ints", "empty", "bytes"):
                assert got[key].dtype == want[key].dtype and got[key].shape == want[key].shape
                np.testing.assert_array_equal(got[key], want[key])
            got["base"][0, 0] = -1.0  # the odometry's arrays are its own: writable, not in a reused slot
        with pytest.raises(ValueError, match="in order"):
            frames.get(3)


def _big(i: int):
    return np.full(prefetch.SLOT_BYTES // 8 + 1, float(i))  # more than a slot: through the pipe


@needs_fork
def test_a_result_larger_than_a_slot_goes_through_the_pipe():
    with Prefetcher(_big, 3, mode="process") as frames:
        for i in range(3):
            out = frames.get(i)
            assert out.shape == (prefetch.SLOT_BYTES // 8 + 1,) and np.all(out == i)
            assert out.flags.writeable


def _fails_at_3(i: int):
    if i == 3:
        raise KeyError("boom")
    return i


def _frame_error_at_2(i: int):
    return InputError(f"frame {i} is unreadable") if i == 2 else i


@pytest.mark.parametrize("mode", ["serial", "thread", pytest.param("process", marks=needs_fork)])
def test_errors_arrive_in_order(mode):
    with Prefetcher(_frame_error_at_2, 5, mode=mode) as frames:
        got = [frames.get(i) for i in range(5)]
    assert got[:2] == [0, 1] and got[3:] == [3, 4]
    assert isinstance(got[2], InputError) and "frame 2 is unreadable" in str(got[2])
    with Prefetcher(_fails_at_3, 6, mode=mode) as frames:
        assert [frames.get(i) for i in range(3)] == [0, 1, 2]
        with pytest.raises(KeyError, match="boom"):
            frames.get(3)


class TwoArgError(Exception):
    def __init__(self, path, why):
        super().__init__(f"{path}: {why}")


def _raises_unpicklable(i: int):
    if i == 1:
        raise TwoArgError("/x", "bad")
    return i


@needs_fork
def test_a_worker_exception_keeps_its_message_and_traceback():
    with Prefetcher(_raises_unpicklable, 4, mode="process") as frames:
        assert frames.get(0) == 0
        with pytest.raises(RuntimeError, match="TwoArgError: /x: bad") as info:
            frames.get(1)
    assert "_raises_unpicklable" in str(info.value.__cause__)  # the worker's traceback
    with Prefetcher(_fails_at_3, 5, mode="process") as frames:
        for i in range(3):
            frames.get(i)
        with pytest.raises(KeyError) as info:
            frames.get(3)
    assert "_fails_at_3" in str(info.value.__cause__)


def _dies_at_2(i: int):
    if i == 2:
        os._exit(7)
    return i


@needs_fork
def test_a_worker_that_dies_is_a_clear_error():
    with Prefetcher(_dies_at_2, 6, mode="process") as frames:
        assert frames.get(0) == 0 and frames.get(1) == 1
        with pytest.raises(CovoError, match="stopped unexpectedly.*exit code 7"):
            frames.get(2)


def _slow(i: int):
    time.sleep(0.05)
    return np.zeros(1000)


@needs_fork
def test_closing_early_stops_the_workers():
    frames = Prefetcher(_slow, 1000, mode="process")
    frames.get(0)
    procs = list(frames._procs)
    start = time.perf_counter()
    frames.close()
    assert time.perf_counter() - start < 5.0
    assert procs and not any(p.is_alive() for p in procs)


@needs_fork
def test_a_forked_child_does_not_keep_the_folder_lock(tmp_path):
    from covo_gtsam.io import FolderLock

    lock = FolderLock(tmp_path).acquire()
    started, ready = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child (its fork handlers done) lives on while the parent releases the lock
        os.write(ready, b"1")
        time.sleep(1.0)
        os._exit(0)
    try:
        assert os.read(started, 1) == b"1"
        lock.release()
        FolderLock(tmp_path).acquire().release()  # a DatasetError if the child still held it
    finally:
        os.waitpid(pid, 0)
        os.close(started)
        os.close(ready)


def test_fork_is_not_taken_beside_other_threads():
    import threading

    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not can_fork()
        with Prefetcher(_arrays, 3) as frames:
            assert frames.mode == "thread"
            assert frames.get(0)["i"] == 0
    finally:
        stop.set()
        other.join()


@pytest.mark.slow
@needs_fork
def test_a_run_is_the_same_with_processes_and_threads(sample_dir, tmp_path, monkeypatch):
    modes = []
    forced = {"mode": "process"}

    class Forced(Prefetcher):  # earlier tests may have left idle threads (a progress bar's monitor)
        def __init__(self, prepare, n, **kwargs):
            super().__init__(prepare, n, **{**kwargs, "mode": forced["mode"]})
            modes.append(self.mode)

    monkeypatch.setattr(pipeline, "Prefetcher", Forced)
    seq = TumSequence(sample_dir)
    pipeline.run_sequence(seq, tmp_path / "p", plots=False, progress=False, max_frames=20)
    forced["mode"] = "thread"
    pipeline.run_sequence(seq, tmp_path / "t", plots=False, progress=False, max_frames=20)
    assert modes == ["process", "thread"]
    for name in ("relative.txt", "trajectory.txt", "graph.g2o"):
        assert (tmp_path / "p" / name).read_bytes() == (tmp_path / "t" / name).read_bytes(), name


def test_covo_run_takes_processes_where_a_fork_is_safe(monkeypatch):
    """The run's own choice (mode "auto"): processes where :func:`can_fork`, else threads."""
    if "fork" not in __import__("multiprocessing").get_all_start_methods():
        pytest.skip("no fork on this platform")
    monkeypatch.setattr(prefetch, "can_fork", lambda: True)
    with Prefetcher(_arrays, 2) as frames:
        assert frames.mode == "process" and frames.get(0)["i"] == 0
    monkeypatch.setattr(prefetch, "can_fork", lambda: False)
    with Prefetcher(_arrays, 2) as frames:
        assert frames.mode == "thread" and frames.get(0)["i"] == 0
    with Prefetcher(_arrays, 1) as frames:  # one frame: nothing to prepare ahead
        assert frames.mode == "thread"


def test_a_run_with_a_progress_bar_leaves_no_thread_behind(sample_dir, tmp_path, capsys):
    """tqdm's monitor thread would outlive the run by seconds and keep the next run in this process
    from forking its workers; the run's bar has none."""
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("threads are counted in /proc/self/task")

    def threads() -> int:
        return len(os.listdir("/proc/self/task"))

    before = threads()
    pipeline.run_sequence(TumSequence(sample_dir), tmp_path / "o", plots=False, progress=True, max_frames=3)
    deadline = time.monotonic() + 2.0  # threads that are ending get two seconds
    while threads() > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert threads() <= before
    assert "frame" in capsys.readouterr().err  # the bar was drawn
