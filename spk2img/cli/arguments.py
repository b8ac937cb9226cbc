"""Checks of arguments that several subcommands share: argparse ``type=`` callables (a bad value
is argparse's one-line error and exit 2) and output paths checked before any work."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from spk2img.errors import InputError
from spk2img.hardware import available_cores

THREADS_PER_CORE = 4
"""The most threads a command may ask for per core available: more only slow the runtime down
(a thousand threads on a few cores turn a second's work into minutes)."""


def thread_count(text: str) -> int:
    """``--threads``: a whole number from 1 to :data:`THREADS_PER_CORE` x the cores here."""
    cores = available_cores()
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


def check_output_folder(directory: Path, flag: str) -> None:
    """Make output folder ``directory`` before any work, so that a run does not end with its
    work lost to a path it cannot write (:class:`InputError`, naming ``flag``)."""
    if directory.exists() and not directory.is_dir():
        raise InputError(f"{flag} {directory}: a file is there, not a folder")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{flag} {directory}: cannot make it ({exc.strerror})") from None
    if not os.access(directory, os.W_OK):
        raise InputError(f"{flag} {directory}: this user cannot write there")


def check_output_file(path: Path, flag: str) -> None:
    """:func:`check_output_folder` for the folder of output file ``path``."""
    if path.is_dir():
        raise InputError(f"{flag} {path}: a folder is there, not a file")
    check_output_folder(path.parent, flag)
