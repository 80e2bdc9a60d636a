"""Frames decoded and prepared ahead of the odometry, in order.

``prepare(i)`` decodes frame i and computes its features, 3-D points and covariances (it returns a
:class:`~covo_gtsam.frontend.FrameData`, or the :class:`~covo_gtsam.errors.CovoError` that makes
the frame lost); :meth:`Prefetcher.get` hands the results to the odometry in index order while the
next :data:`PREFETCH` frames are prepared beside it. Two ways:

* ``"process"``: forked worker processes, worker k preparing the frames ``k, k + W, ...``. A
  result is pickled (protocol 5) with its arrays' data out of band: the data goes into one of
  :data:`SLOTS` slots of anonymous shared memory per worker, the rest (a few kilobytes) through a
  pipe; the odometry copies the arrays out and acknowledges the slot through a second pipe. A
  worker ends with its parent (``PR_SET_PDEATHSIG``; else it notices within a second). The odometry's thread and the workers share
  no interpreter lock, which on two cores made threads cost about 6 ms of CPU per frame more than
  the same work done one after the other (benchmarks/README.md). Only where ``fork`` is safe:
  the platform has it and this process runs one thread (checked in ``/proc/self/task``), as
  ``covo run`` does; the workers inherit ``prepare`` and its data without pickling.
* ``"thread"``: a thread pool in this process (OpenCV releases the interpreter lock while it
  detects); everywhere else, and for readers that are not safe to fork (a bag streamed by one
  reader).
* ``"serial"``: each frame prepared when it is asked for, on the calling thread (no overlap; for
  debugging and for benchmarks that time the work alone).
"""

from __future__ import annotations

import mmap
import multiprocessing
import os
import pickle
import sys
import traceback
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

from .errors import CovoError

__all__ = ["PREFETCH", "Prefetcher", "can_fork"]

#: Frames prepared ahead of the one the odometry registers (worker threads or processes).
PREFETCH = 2


def can_fork() -> bool:
    """Whether worker processes may be forked here: ``fork`` exists and this process runs a single
    thread (a fork copies only the calling thread, so locks held by others would stay locked in the
    child). False where the thread count cannot be read (no ``/proc``)."""
    if "fork" not in multiprocessing.get_all_start_methods():
        return False
    try:
        return len(os.listdir("/proc/self/task")) == 1
    except OSError:
        return False


#: Bytes of one slot of a worker's shared memory; a result whose arrays need more goes through the pipe.
SLOT_BYTES = 8 << 20
#: Slots per worker: a worker may be this many results ahead of the odometry.
SLOTS = 2
_ALIGN = 64


def _layout(sizes: list[int]) -> list[int]:
    """Offsets of buffers of ``sizes`` bytes in a slot, each aligned to :data:`_ALIGN` bytes."""
    offsets, at = [], 0
    for n in sizes:
        offsets.append(at)
        at += -(-n // _ALIGN) * _ALIGN
    return offsets + [at]


class _RemoteTraceback(Exception):
    """The traceback of an exception raised in a worker process (its ``__cause__`` in the parent)."""

    def __str__(self) -> str:
        return self.args[0]


def _die_with_parent(parent: int) -> bool:
    """In a worker: ask Linux to end this process when its parent ends (``PR_SET_PDEATHSIG``);
    False if the parent has already gone."""
    try:
        import ctypes
        import signal

        ctypes.CDLL(None).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux's C library: the ack wait checks the parent
        pass
    return os.getppid() == parent


def _error_result(i: int, exc: BaseException) -> tuple[bytes, list]:
    """``(False, exc)`` pickled with the worker's traceback; an exception that does not survive a
    pickle round trip is replaced by a RuntimeError naming it."""
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    try:
        head = pickle.dumps((False, exc, tb), protocol=5)
        pickle.loads(head)
    except Exception:  # noqa: BLE001 - any failure to pickle or unpickle it
        head = pickle.dumps((False, RuntimeError(f"frame {i}: {type(exc).__name__}: {exc}"), tb), protocol=5)
    return head, []


def _serve(prepare: Callable[[int], object], indices: range, conn, acks, shared: mmap.mmap, parent: int) -> None:
    """Worker process: prepare ``indices`` in order and hand over each result, pickled (protocol 5):
    its arrays' data written into the next slot of ``shared`` (once the parent has acknowledged
    through ``acks`` that it copied that slot out), the rest sent through ``conn``. An exception
    that is not a frame's error is sent with its traceback and ends the worker."""
    if not _die_with_parent(parent):
        return
    slot, free = 0, SLOTS
    try:
        for i in indices:
            buffers: list[pickle.PickleBuffer] = []
            try:
                ok, head = True, pickle.dumps((True, prepare(i), ""), protocol=5, buffer_callback=buffers.append)
            except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
                ok, (head, buffers) = False, _error_result(i, exc)
            raws = [b.raw() for b in buffers]
            offsets = _layout([r.nbytes for r in raws])
            if offsets[-1] > SLOT_BYTES:  # too large for a slot: the data through the pipe
                conn.send((head, None, [r.nbytes for r in raws]))
                for r in raws:
                    conn.send_bytes(r)
            else:
                while free == 0:  # wait until the parent has copied out the oldest slot
                    if acks.poll(1.0):
                        free += len(acks.recv_bytes())
                    elif os.getppid() != parent:  # the parent died without stopping this worker
                        return
                free -= 1
                base = slot * SLOT_BYTES
                for r, at in zip(raws, offsets):
                    shared[base + at:base + at + r.nbytes] = r
                conn.send((head, slot, [r.nbytes for r in raws]))
                slot = (slot + 1) % SLOTS
            if not ok:
                return
    except (BrokenPipeError, KeyboardInterrupt, EOFError, OSError):  # the parent stopped reading
        pass
    finally:
        conn.close()


class Prefetcher:
    """``get(i)`` for i = 0, 1, ..., n - 1 in turn returns ``prepare(i)``, computed ahead on
    :data:`PREFETCH` worker processes (``mode="process"``, where :func:`can_fork`) or threads.
    Use as a context manager; leaving it stops the workers. Arrays in the results are writable
    and the caller's own.

    ``mode``: ``"process"``, ``"thread"``, ``"serial"`` or ``"auto"`` (processes where they can
    be forked, else threads; also threads when the workers cannot be started).
    """

    def __init__(self, prepare: Callable[[int], object], n: int, mode: str = "auto", workers: int = PREFETCH):
        if mode not in ("auto", "process", "thread", "serial"):
            raise ValueError(f"mode must be 'auto', 'process', 'thread' or 'serial', got {mode!r}")
        self.n, self.workers = n, max(1, workers)
        if mode == "process" and "fork" not in multiprocessing.get_all_start_methods():
            raise ValueError("worker processes need fork, which this platform does not have")
        self.mode = mode if mode != "auto" else "process" if n > 1 and can_fork() else "thread"
        self._next = 0
        self._procs: list = []
        self._conns: list = []
        self._pool = None
        self._pending: deque = deque()
        self._prepare = prepare
        if self.mode == "process":
            try:
                self._start_processes()
            except OSError:
                self.close()
                if mode == "process":
                    raise
                self.mode = "thread"  # e.g. no memory or processes left to start them
        if self.mode == "thread":
            self._pool = ThreadPoolExecutor(max_workers=self.workers)
            self._pending.extend(self._pool.submit(prepare, i) for i in range(min(self.workers, n)))

    def _start_processes(self) -> None:
        ctx = multiprocessing.get_context("fork")
        for stream in (sys.stdout, sys.stderr):  # else a child's exit could write their buffers again
            if stream is not None:
                stream.flush()
        try:
            for k in range(min(self.workers, self.n)):
                recv, send = ctx.Pipe(duplex=False)
                ack_recv, ack_send = ctx.Pipe(duplex=False)
                shared = mmap.mmap(-1, SLOTS * SLOT_BYTES)
                self._conns.append((recv, ack_send, shared))
                proc = ctx.Process(target=_serve, name=f"covo-prepare-{k}", daemon=True,
                                   args=(self._prepare, range(k, self.n, self.workers), send, ack_recv, shared,
                                         os.getpid()))
                proc.start()
                self._procs.append(proc)
                send.close()
                ack_recv.close()
        except BaseException:
            self.close()
            raise

    def _receive(self, i: int):
        """Frame ``i``'s result from its worker process."""
        k = i % self.workers
        conn, acks, shared = self._conns[k]
        try:
            head, slot, sizes = conn.recv()
            if slot is None:  # through the pipe, into writable buffers
                buffers = [bytearray(n) for n in sizes]
                for b in buffers:
                    conn.recv_bytes_into(b)
            else:  # copy the arrays out of the slot (writable), then hand the slot back
                with memoryview(shared) as view:
                    base = slot * SLOT_BYTES
                    buffers = [bytearray(view[base + at:base + at + n]) for at, n in zip(_layout(sizes), sizes)]
                try:
                    acks.send_bytes(b"1")
                except BrokenPipeError:  # the worker has sent its last frame and ended
                    pass
        except EOFError:
            proc = self._procs[k]
            proc.join(1.0)
            raise CovoError(f"frame {i}: the process preparing frames stopped unexpectedly "
                            f"(exit code {proc.exitcode})") from None
        ok, out, tb = pickle.loads(head, buffers=buffers)
        if not ok:
            raise out from _RemoteTraceback(f"\n(in the worker process)\n{tb}")
        return out

    def get(self, i: int):
        """``prepare(i)``; ``i`` must be the next index. Raises what ``prepare`` raised (other than
        a returned frame error), or :class:`CovoError` if a worker process died."""
        if i != self._next or not 0 <= i < self.n:
            raise ValueError(f"frames are handed out in order: expected {self._next}, got {i}")
        self._next += 1
        if self.mode == "serial":
            return self._prepare(i)
        if self._pool is None:
            return self._receive(i)
        out = self._pending.popleft().result()
        if i + self.workers < self.n:
            self._pending.append(self._pool.submit(self._prepare, i + self.workers))
        return out

    def close(self) -> None:
        """Stop the workers (those still preparing frames nobody will ask for are terminated)."""
        if self._pool is not None:
            for f in self._pending:
                f.cancel()
            self._pool.shutdown(wait=True)
            self._pool = None
        for conn, acks, _ in self._conns:
            conn.close()
            acks.close()
        for proc in self._procs:
            proc.join(0.0 if self._next < self.n else 1.0)
            if proc.is_alive():
                proc.terminate()
                proc.join()
        for *_, shared in self._conns:
            try:
                shared.close()
            except BufferError:  # a view of it is still alive (an interrupted copy): freed with it
                pass
        self._conns, self._procs = [], []

    def __enter__(self) -> Prefetcher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
