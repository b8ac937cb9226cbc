"""SIGTERM stops a command as Ctrl-C does: an exception in the main thread, so every
``finally`` and ``with`` block runs (temporary folders go, a reconstruction keeps its frames for
``--resume``) and the command exits 128 + the signal's number.

Without this, SIGTERM (what ``timeout``, ``kill`` and schedulers send) ended the process at once
and left what the command was writing behind.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


class Terminated(KeyboardInterrupt):
    """SIGTERM received: raised where the main thread is, handled as Ctrl-C."""


def exit_code(interrupt: KeyboardInterrupt) -> int:
    """128 + the signal's number: 143 for SIGTERM, 130 for Ctrl-C (SIGINT)."""
    number = signal.SIGTERM if isinstance(interrupt, Terminated) else signal.SIGINT
    return 128 + number


def interrupt_message(interrupt: KeyboardInterrupt) -> str:
    """``interrupted`` or ``terminated``: what stopped the command, for its last line."""
    return "terminated" if isinstance(interrupt, Terminated) else "interrupted"


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While entered (in the main thread; elsewhere nothing changes), SIGTERM raises
    :class:`Terminated`. Code that handles signals itself (``train``, ``serve``) sets its own
    handlers inside and restores this one when it is done."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _raise_terminated(number: int, frame) -> None:
    raise Terminated
