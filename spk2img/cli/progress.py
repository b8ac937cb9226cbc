"""Progress on stderr that tells the truth: shown only on a terminal and without ``--quiet`` or
``--no-progress``, and advanced frame by frame as the work is done."""

from __future__ import annotations

import argparse
import sys

from tqdm import tqdm


def add_progress_flags(parser: argparse.ArgumentParser) -> None:
    """``-q/--quiet`` (no progress bar, no closing summary) and ``--no-progress``."""
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="print nothing but errors on stderr"
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def show_progress(args: argparse.Namespace, stream=None) -> bool:
    """Whether to draw a progress bar: not with ``--quiet``/``--no-progress``, and only when
    ``stream`` (default stderr) is a terminal (a log file or a pipe gets no bar)."""
    stream = sys.stderr if stream is None else stream
    if getattr(args, "quiet", False) or getattr(args, "no_progress", False):
        return False
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


def progress_bar(args: argparse.Namespace, total: int, unit: str = "frame") -> tqdm:
    """A tqdm bar on stderr over ``total`` ``unit``s, disabled when :func:`show_progress` says.
    It redraws at most every 0.1 s, and at once after a slow step."""
    return tqdm(total=total, unit=unit, disable=not show_progress(args), file=sys.stderr)


def say(args: argparse.Namespace, message: str) -> None:
    """A closing summary line on stderr, unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr)
