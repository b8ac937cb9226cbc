"""``spk2img reconstruct --url``: the CLI's work done by a running service, through the client."""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from spk2img.errors import InputError
from spk2img.io.spikes import DatStream
from spk2img.model.config import Geometry
from spk2img.runtime.methods import method_plan
from spk2img.runtime.stream import Frame

from .errors import Spk2ImgError
from .sync import Client


class RemoteError(InputError):
    """A failure of (or on the way to) the service, for the CLI to print as one line."""


@dataclass
class RemoteFrames:
    """The frames one ``spk2img reconstruct --url`` run asks the service for."""

    client: Client
    args: argparse.Namespace
    source: object
    """What is uploaded: the ``.dat`` file as it is, or the array."""
    shape: tuple[int, int, int]
    centers: np.ndarray
    """``(N,) int64``: every centre the run's arguments ask for, checked here."""
    stride: int | None

    @property
    def label(self) -> str:
        """What reconstructs, for the progress bar."""
        return f"{self.args.method} on {self.args.url}"

    def note(self) -> str:
        """Nothing to add to the closing message: the service did the work."""
        return ""

    def frames(self, centers: Sequence[int] | None = None) -> Iterator[Frame]:
        """``(centre, image)`` pairs as the service streams them back while the stream is
        uploaded: of every centre, or of ``centers`` only (a resumed run)."""
        everything = centers is None
        if everything:
            centers = None if self.args.centers is None else self.centers.tolist()
        yield from self.client.reconstruct(
            self.source,
            *self.shape[1:],
            centers=centers,
            stride=self.stride if everything else None,
            method=self.args.method,
            window=self.args.window,
            quality=self.args.quality,
            binning=self.args.binning,
        )


@contextmanager
def remote_frames(
    args: argparse.Namespace, spikes: np.ndarray | DatStream, stride: int | None
) -> Iterator[RemoteFrames]:
    """The service at ``args.url`` ready to reconstruct ``args.input``, already read as
    ``spikes`` (``(T, H, W)`` 0/1: an array, or a ``.dat`` memory-mapped), as the local CLI would.

    The centres are checked here first against the served model's geometry (``GET
    /v1/models``), with the local messages; without ``stride`` or centres, every
    ``block_stride``-th centre of that model. Raises :class:`RemoteError` for any failure the
    service reports or a connection that fails, also while the frames come back.
    """
    source = args.input if isinstance(spikes, DatStream) else np.asarray(spikes)
    try:
        with Client(args.url) as client:
            geometry = Geometry(**served_geometry(client.models()))
            if stride is None and args.centers is None:
                stride = geometry.block_stride
            plan = method_plan(
                args.method, args.centers, stride, args.window, args.binning, geometry, args.quality
            )
            centers = plan.centers_for(spikes.shape[0])
            yield RemoteFrames(client, args, source, spikes.shape, centers, stride)
    except Spk2ImgError as exc:
        raise RemoteError(f"{args.url}: {exc}") from exc


def served_geometry(models: dict) -> dict[str, int]:
    """The geometry of the served model, from ``GET /v1/models``'s answer, as
    :class:`~spk2img.model.config.Geometry`'s fields (``window_frames`` is derived there)."""
    (model,) = [m for m in models["models"] if m["method"] == "net"]
    return {k: v for k, v in model["geometry"].items() if k != "window_frames"}
