"""``spk2img reconstruct --url``: the CLI's work done by a running service, through the client."""

from __future__ import annotations

import argparse
import sys

import numpy as np
from tqdm import tqdm

from spk2img.errors import InputError
from spk2img.io.spikes import DatStream
from spk2img.model.config import Geometry
from spk2img.runtime.methods import method_plan
from spk2img.runtime.stream import collect

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

    The centres are checked here first against the served model's geometry (``GET
    /v1/models``), with the local messages; without ``stride`` or centres, every
    ``block_stride``-th centre of that model; then the stream is uploaded (a ``.dat`` as is, an
    array packed) while frames come back, with a progress bar on stderr (after
    :data:`PROGRESS_DELAY_S`) unless ``args.no_progress``. Returns ``frames (N, H, W) float32``
    (linear intensity) and ``centers (N,) int64``.
    Raises :class:`RemoteError` for any failure the service reports or a connection that fails.
    """
    n_frames, height, width = spikes.shape
    source = args.input if isinstance(spikes, DatStream) else np.asarray(spikes)
    try:
        with Client(args.url) as client:
            geometry = Geometry(**served_geometry(client.models()))
            if stride is None and args.centers is None:
                stride = geometry.block_stride
            plan = method_plan(
                args.method, args.centers, stride, args.window, args.binning, geometry, args.quality
            )
            n_out = len(plan.centers_for(n_frames))
            centers = None if plan.centers is None else plan.centers.tolist()
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


def served_geometry(models: dict) -> dict[str, int]:
    """The geometry of the served model, from ``GET /v1/models``'s answer, as
    :class:`~spk2img.model.config.Geometry`'s fields (``window_frames`` is derived there)."""
    (model,) = [m for m in models["models"] if m["method"] == "net"]
    return {k: v for k, v in model["geometry"].items() if k != "window_frames"}
