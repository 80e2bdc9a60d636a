"""Frames decoded and prepared ahead of the odometry, in order.

``prepare(i)`` decodes frame i and computes its features, 3-D points and covariances (it returns a
:class:`~covo_gtsam.frontend.FrameData`, or the :class:`~covo_gtsam.errors.CovoError` that makes
the frame lost); :meth:`Prefetcher.get` hands the results to the odometry in index order while the
next :data:`PREFETCH` frames are prepared beside it. Two ways:

* ``"process"``: forked worker processes, worker k preparing the frames ``k, k + W, ...``. A
  result is pickled (protocol 5) with its arrays' data out of band: the data goes into one of
  :data:`SLOTS` slots of shared memory per worker, the rest (a few kilobytes) through a pipe; the
  odometry copies the arrays out and frees the slot. The odometry's thread and the workers share
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


def _serve(prepare: Callable[[int], object], indices: range, conn, shared: mmap.mmap, free) -> None:
    """Worker process: prepare ``indices`` in order and hand over each result: pickled (protocol 5)
    with its arrays' data written into a free slot of ``shared`` (``free`` counts the free slots;
    the parent releases one when it has copied it out) and the rest sent through ``conn``. An
    exception that is not a frame's error ends the worker after it is sent (the parent raises it)."""
    slot, parent = 0, os.getppid()
    try:
        for i in indices:
            try:
                out = (True, prepare(i))
            except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
                out = (False, exc)
            buffers: list[pickle.PickleBuffer] = []
            try:
                head = pickle.dumps(out, protocol=5, buffer_callback=buffers.append)
            except (TypeError, AttributeError, ValueError, pickle.PicklingError) as exc:  # does not pickle
                out, buffers = (False, RuntimeError(f"frame {i}: {out[1]!r} ({exc})")), []
                head = pickle.dumps(out, protocol=5)
            raws = [b.raw() for b in buffers]
            offsets = _layout([r.nbytes for r in raws])
            if offsets[-1] <= SLOT_BYTES:
                while not free.acquire(timeout=1.0):
                    if os.getppid() != parent:  # the parent died without stopping this worker
                        return
                base = slot * SLOT_BYTES
                for r, at in zip(raws, offsets):
                    shared[base + at:base + at + r.nbytes] = r
                conn.send((head, slot, [r.nbytes for r in raws]))
                slot = (slot + 1) % SLOTS
            else:
                conn.send((head, None, [bytes(r) for r in raws]))
            if not out[0]:
                return
    except (BrokenPipeError, KeyboardInterrupt, EOFError):  # the parent stopped reading
        pass
    finally:
        conn.close()


class Prefetcher:
    """``get(i)`` for i = 0, 1, ..., n - 1 in turn returns ``prepare(i)``, computed ahead on
    :data:`PREFETCH` worker processes (``mode="process"``, where :func:`can_fork`) or threads.
    Use as a context manager; leaving it stops the workers.

    ``mode``: ``"process"``, ``"thread"``, ``"serial"`` or ``"auto"`` (processes where they can
    be forked, else threads).
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
        self._shared: list = []
        self._pool = None
        self._pending: deque = deque()
        self._prepare = prepare
        if self.mode == "process":
            self._start_processes()
        elif self.mode == "thread":
            self._pool = ThreadPoolExecutor(max_workers=self.workers)
            self._pending.extend(self._pool.submit(prepare, i) for i in range(min(self.workers, n)))

    def _start_processes(self) -> None:
        ctx = multiprocessing.get_context("fork")
        for stream in (sys.stdout, sys.stderr):  # else a child's exit could write their buffers again
            if stream is not None:
                stream.flush()
        for k in range(min(self.workers, self.n)):
            recv, send = ctx.Pipe(duplex=False)
            shared, free = mmap.mmap(-1, SLOTS * SLOT_BYTES), ctx.Semaphore(SLOTS)
            proc = ctx.Process(target=_serve, args=(self._prepare, range(k, self.n, self.workers), send, shared, free),
                               name=f"covo-prepare-{k}", daemon=True)
            proc.start()
            send.close()
            self._procs.append(proc)
            self._conns.append(recv)
            self._shared.append((shared, free))

    def get(self, i: int):
        """``prepare(i)``; ``i`` must be the next index. Raises what ``prepare`` raised (other than
        a returned frame error), or :class:`CovoError` if a worker process died."""
        if i != self._next or not 0 <= i < self.n:
            raise ValueError(f"frames are handed out in order: expected {self._next}, got {i}")
        self._next += 1
        if self.mode == "serial":
            return self._prepare(i)
        if self._pool is not None:
            out = self._pending.popleft().result()
            if i + self.workers < self.n:
                self._pending.append(self._pool.submit(self._prepare, i + self.workers))
            return out
        k = i % self.workers
        try:
            head, slot, buffers = self._conns[k].recv()
        except EOFError:
            proc = self._procs[k]
            proc.join(1.0)
            raise CovoError(f"frame {i}: the process preparing frames stopped unexpectedly "
                            f"(exit code {proc.exitcode})") from None
        if slot is not None:  # copy the arrays out of the slot (writable), then free it for the worker
            shared, free = self._shared[k]
            view = memoryview(shared)[slot * SLOT_BYTES:(slot + 1) * SLOT_BYTES]
            offsets = _layout(buffers)
            buffers = [bytearray(view[at:at + n]) for at, n in zip(offsets, buffers)]
            view.release()
            free.release()
        ok, out = pickle.loads(head, buffers=buffers)
        if not ok:
            raise out
        return out

    def close(self) -> None:
        """Stop the workers (those still preparing frames nobody will ask for are terminated)."""
        if self._pool is not None:
            for f in self._pending:
                f.cancel()
            self._pool.shutdown(wait=True)
            self._pool = None
        for conn in self._conns:
            conn.close()
        for proc in self._procs:
            proc.join(0.0 if self._next < self.n else 1.0)
            if proc.is_alive():
                proc.terminate()
                proc.join()
        for shared, _ in self._shared:
            shared.close()
        self._conns, self._procs, self._shared = [], [], []

    def __enter__(self) -> Prefetcher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
