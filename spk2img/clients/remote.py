"""``spk2img reconstruct --url``: the CLI's work done by a running service, through the client."""

from __future__ import annotations

import argparse
import sys

import numpy as np
from tqdm import tqdm

from spk2img.core.errors import InputError
from spk2img.core.methods import method_plan
from spk2img.core.spikes import DatStream
from spk2img.core.stream import collect

from .errors import Spk2ImgError
from .sync import Client

PROGRESS_DELAY_S = 1.0
"""The progress bar shows once a reconstruction has taken this long (seconds)."""


class RemoteError(InputError):
    """A failure of (or on the way to) the service, for the CLI to print as one line."""


def reconstruct_file_remote(
    args: argparse.Namespace, spikes: np.ndarray | DatStream, stride: int | None
) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruct ``args.input``, already read as ``spikes`` (``(T, H, W)`` 0/1: an array, or a
    ``.dat`` memory-mapped), on the service at ``args.url`` as the local CLI would.

    The centres are checked here first, with the local messages; then the
    stream is uploaded (a ``.dat`` as is, an array packed) while frames come back, with a
    progress bar on stderr (after :data:`PROGRESS_DELAY_S`) unless ``args.no_progress``.
    Returns ``frames (N, H, W) float32`` (linear intensity) and ``centers (N,) int64``.
    Raises :class:`RemoteError` for any failure the service reports or a connection that fails.
    """
    n_frames, height, width = spikes.shape
    plan = method_plan(args.method, args.centers, stride, args.window, args.binning)
    n_out = len(plan.centers_for(n_frames))
    source = args.input if isinstance(spikes, DatStream) else np.asarray(spikes)
    centers = None if plan.centers is None else plan.centers.tolist()
    try:
        with Client(args.url) as client:
            frames = client.reconstruct(
                source,
                height,
                width,
                centers=centers,
                stride=stride,
                method=args.method,
                window=args.window,
                quality=args.quality,
                binning=args.binning,
            )
            bar = tqdm(
                frames,
                total=n_out,
                unit="frame",
                disable=args.no_progress,
                file=sys.stderr,
                delay=PROGRESS_DELAY_S,
            )
            return collect(bar, height, width)
    except Spk2ImgError as exc:
        raise RemoteError(f"{args.url}: {exc}") from exc
