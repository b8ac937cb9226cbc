"""Argument types that several subcommands share (argparse ``type=`` callables: a bad value is
argparse's one-line error and exit 2)."""

from __future__ import annotations

import argparse
import os

THREADS_PER_CORE = 4
"""The most threads a command may ask for per core available: more only slow the runtime down
(a thousand threads on a few cores turn a second's work into minutes)."""


def cores_available() -> int:
    """The CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def thread_count(text: str) -> int:
    """``--threads``: a whole number from 1 to :data:`THREADS_PER_CORE` x the cores here."""
    cores = cores_available()
    most = THREADS_PER_CORE * cores
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= most:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a whole number from 1 to {most} ({THREADS_PER_CORE}x the {cores} "
            "cores here; more threads only slow inference down)"
        )
    return value
