"""Run independent tasks serially, on a local process pool, or on a Dask distributed cluster.

:func:`map_tasks` is the one place that chooses: ``scheduler`` (``tcp://HOST:PORT`` of a running
``dask scheduler``; optional extra ``dask``) sends the tasks to that cluster; otherwise ``workers``
processes on this machine run them (``workers=1``: in this process, one after the other). Tasks
are module-level functions with plain arguments, so they pickle to any worker; each result is
returned in the order of the arguments, so a study gives the same numbers whichever way it ran.
"""

from __future__ import annotations

import os
from typing import Any, Callable, Sequence

from .errors import ConfigError

__all__ = ["CONNECT_TIMEOUT", "default_workers", "map_tasks"]

#: Seconds to wait for a Dask scheduler before giving up.
CONNECT_TIMEOUT = 10.0


def default_workers(tasks: int) -> int:
    """One process per task, at most one per CPU core of this machine."""
    return max(1, min(tasks, os.cpu_count() or 1))


def _check_address(address: str) -> str:
    """The transport of a scheduler address Dask can connect to: ``[scheme://]host:port``, the scheme
    one of Dask's registered network transports (tcp if none; not ``inproc``, which is within one
    process), checked before connecting.

    Raises:
        ConfigError: it is not such an address.
    """
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port
    from distributed.comm.registry import backends

    schemes = sorted(set(backends) - {"inproc"})
    try:
        scheme, location = parse_address(address)
        if scheme not in schemes:
            raise ValueError(f"the transport must be one of {', '.join(schemes)}, got {scheme!r}")
        parse_host_port(location)
        return scheme
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"--scheduler {address}: not a scheduler address such as tcp://HOST:PORT "
                          f"({' '.join(str(exc).split())})") from None


def _dask_client(address: str, timeout: float):
    try:
        from dask.distributed import Client
    except ImportError:
        raise ConfigError('--scheduler needs Dask: pip install "covo-gtsam[dask]" '
                          '(or pip install "dask[distributed]")') from None
    scheme = _check_address(address)
    client = None
    try:
        # created, then connected: a client whose connection failed is closed here, at once (left
        # to the garbage collector, it waits for its event loop and prints a traceback at exit)
        client = Client.__new__(Client)
        client.__init__(address, timeout=timeout, set_as_default=False)
        return client
    except Exception as exc:  # any transport's failure: Dask raises no common type
        _discard(client, timeout)
        msg = " ".join(str(exc).split()) or type(exc).__name__
        if isinstance(exc, (OSError, TimeoutError)):
            raise ConfigError(f"--scheduler {address}: cannot reach the Dask scheduler within {timeout:g} s "
                              f"({msg})") from exc
        raise ConfigError(f"--scheduler {address}: cannot connect to the Dask scheduler ({type(exc).__name__}: "
                          f"{msg}; is Dask's {scheme} transport set up here?)") from exc


def _discard(client, timeout: float) -> None:
    """Close a client whose connection failed (its event loop is still running), whatever it says."""
    if client is None:
        return
    try:
        client.close(timeout=timeout)
    except Exception:  # a half-built client may lack what close() expects
        pass


def map_tasks(func: Callable, args: Sequence[tuple], workers: int | None = None, scheduler: str | None = None,
              timeout: float = CONNECT_TIMEOUT, progress: Callable[[int], Any] | None = None) -> list:
    """``[func(*a) for a in args]``, run serially, on ``workers`` local processes or on the Dask
    scheduler at ``scheduler``. ``progress(k)`` is called as tasks finish (k = tasks done).

    Raises:
        ConfigError: Dask is missing or the scheduler cannot be reached (any failure to connect,
            e.g. a transport that is not set up here, such as ``tls`` without certificates).
        CovoError: a task raised one (the first, in argument order).
    """
    args = [tuple(a) for a in args]
    if not args:
        return []
    if scheduler:
        client = _dask_client(scheduler, timeout)
        try:
            futures = client.map(func, *zip(*args), pure=False)
            out = []
            for k, f in enumerate(futures, 1):  # in order; the cluster runs them concurrently
                out.append(f.result())
                if progress:
                    progress(k)
            return out
        finally:
            client.close()
    workers = default_workers(len(args)) if workers is None else workers
    if workers <= 1 or len(args) == 1:
        out = []
        for k, a in enumerate(args, 1):
            out.append(func(*a))
            if progress:
                progress(k)
        return out
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    # spawn: a fresh interpreter per worker (no fork of GTSAM's or OpenCV's threads)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(workers, len(args)), mp_context=ctx) as pool:
        futures = [pool.submit(func, *a) for a in args]
        for k, _ in enumerate(as_completed(futures), 1):
            if progress:
                progress(k)
        return [f.result() for f in futures]

