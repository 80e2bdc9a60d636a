"""Ctrl-C that is not lost.

Python's SIGINT handler raises KeyboardInterrupt wherever the main thread is; where that is a
finalizer (``__del__``) or a callback whose exceptions are ignored, the interrupt is printed as
ignored and the run goes on. :func:`recorded_sigint` installs a handler that also records it, and
the frame loops call :func:`check` once per frame, so such an interrupt stops the run at the next
frame all the same.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager

_ASKED = threading.Event()


def _on_sigint(signum, frame) -> None:
    _ASKED.set()
    raise KeyboardInterrupt


@contextmanager
def recorded_sigint():
    """Within the block, SIGINT also records the interrupt (:func:`check`); installed only in the
    main thread and over Python's own handler, which is put back afterwards, the record cleared."""
    install = (threading.current_thread() is threading.main_thread()
               and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    _ASKED.clear()
    if install:
        signal.signal(signal.SIGINT, _on_sigint)
    try:
        yield
    finally:
        if install:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        _ASKED.clear()


def check() -> None:
    """KeyboardInterrupt if an interrupt was recorded (and swallowed on its way)."""
    if _ASKED.is_set():
        raise KeyboardInterrupt
