"""One request's reconstruction: ``.dat`` bytes in, encoded ``FRAM`` records out.

:class:`StreamJob` wraps the core pieces — :class:`~spk2img.io.spikes.SpikeDecoder`, a
:class:`~spk2img.runtime.stream.StreamingReconstructor` and the framing — and enforces the
per-request limits. Its :meth:`~StreamJob.feed` (decode a piece of the upload),
:meth:`~StreamJob.advance` (reconstruct until the next records are done: at most one model call
or classical step past them) and :meth:`~StreamJob.finish` run in the inference pool, one call
at a time; :meth:`~StreamJob.cancel` may be called from any thread.
"""

from __future__ import annotations

import io
import threading
from collections import deque

import numpy as np
from PIL import Image

from spk2img.io.light import to_display
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH, SpikeDecoder
from spk2img.model.config import Geometry
from spk2img.protocol.framing import encode_frame
from spk2img.runtime.loader import LoadedNetwork
from spk2img.runtime.methods import build_reconstructor, method_window
from spk2img.runtime.stream import Frame, TFIStream
from spk2img.runtime.windows import CenterPlan

from .errors import RequestError
from .schemas import ReconstructQuery
from .settings import ServiceSettings

STEP_PIXELS = 2**22
"""Classical methods push about this many spike pixels between checks for cancellation."""

NET_BYTES_PER_PIXEL = 14 * 2**10
"""Peak memory of one model call per window pixel of the frame as the network pads it (both
sides up to a multiple of its ``size_multiple``, :meth:`Geometry.padded_size`): measured with
the shipped model and
onnxruntime 1.32 (CPU, no arena) at 11.4 KiB (250x400), 12.7 KiB (125x200) and 13.2 KiB (64x64)
per pixel, whole graph or block encoder and head; rounded up. Thin frames pay for their padding:
one row of 20,000 pixels peaked at 36.7 KiB a pixel (9.2 KiB a padded pixel), one column at
43.7, two rows at 19.3 (tests/test_service_memory.py measures thin, square and wide)."""
SELF_ENSEMBLE_BYTES_PER_PIXEL = 8 * 2**10
"""What a self-ensemble (``self_ensemble``) holds beyond one model call, per padded pixel: the
block codes of its three more views (378 B a pixel a block for the shipped ``default`` and
``real``, 180 for ``tiny``, 48 for ``cpu``; at most six blocks held: 6.6 KiB) and the four
views' images; rounded up."""
WINDOW_BYTES_PER_PIXEL = 16
"""Per pixel and frame of the window: the spikes (uint8) and their float32 copy, with slack."""
JOB_BYTES = 16 * 2**20
"""Per request besides its frames: a decoded body piece, the upload and the encoded records."""
FRAME_RECORD_HEAD = 8 + 8 + 4 + 4 + 4
"""Bytes of a ``FRAM`` record before its data (tag, length, centre, height, width, format)."""


class Cancelled(Exception):
    """The request ended (client gone, time up) while its job was running."""


def check_upload_size(settings: ServiceSettings, n_bytes: int, n_frames: int) -> None:
    """Raise 413 when an upload of ``n_bytes`` bytes and ``n_frames`` frames is over the limits."""
    if n_bytes > settings.max_body_bytes:
        raise RequestError(413, f"the upload is over {settings.max_body_bytes} bytes")
    if n_frames > settings.max_frames:
        raise RequestError(413, f"the upload is over {settings.max_frames} frames")


def job_memory(
    query: ReconstructQuery, settings: ServiceSettings, response_bytes: int, geometry: Geometry
) -> int:
    """An upper estimate of the memory one request may use: the model's activations (``net``:
    :data:`NET_BYTES_PER_PIXEL` per padded pixel and window of a call, and
    :data:`SELF_ENSEMBLE_BYTES_PER_PIXEL` more for a self-ensemble), the window (``net``: the
    served network's ``geometry``), the upload read ahead (``read_ahead_bytes``), and the
    records waiting for the client (``response_bytes``, at most ``response_buffer_bytes``)."""
    pixels = query.height * query.width
    model = query.method == "net" and query.quality != "fast"
    window = method_window(query.method, query.window, query.binning, geometry=geometry)
    memory = JOB_BYTES + settings.read_ahead_bytes + pixels * window * WINDOW_BYTES_PER_PIXEL
    if model:
        padded_height, padded_width = geometry.padded_size(query.height, query.width)
        memory += padded_height * padded_width * NET_BYTES_PER_PIXEL * settings.batch
        if settings.self_ensemble:
            memory += padded_height * padded_width * SELF_ENSEMBLE_BYTES_PER_PIXEL * settings.batch
    return memory + min(response_bytes, settings.response_buffer_bytes)


def typical_request_bytes(settings: ServiceSettings, geometry: Geometry) -> int:
    """What a typical request reserves: one ``net`` frame of the camera's 250x400 as float32,
    at most the whole budget (so an idle service is ready even with a smaller budget)."""
    query = ReconstructQuery(height=DEFAULT_HEIGHT, width=DEFAULT_WIDTH, centers=str(geometry.half))
    cost = job_memory(query, settings, frame_record_bytes(query), geometry)
    return min(cost, settings.memory_budget_bytes) if settings.memory_budget_bytes else cost


def frame_record_bytes(query: ReconstructQuery) -> int:
    """The most bytes one ``FRAM`` record of ``query``'s frames takes (a PNG: stored blocks at
    worst, one filter byte a row)."""
    pixels = query.height * query.width
    if query.format == "float32":
        return FRAME_RECORD_HEAD + 4 * pixels
    if query.format == "uint8":
        return FRAME_RECORD_HEAD + pixels
    raw = pixels + query.height
    return FRAME_RECORD_HEAD + raw + 5 * (raw // 16_000 + 1) + 1024


class StreamJob:
    """Decode, reconstruct and encode one uploaded stream of ``query.height x query.width`` frames.

    The ``network`` (``method=net``) runs ``settings.batch`` windows per model call, or, with
    its block codec and centres that share blocks, encodes each block once and runs the head per
    centre (:meth:`~spk2img.runtime.loader.LoadedNetwork.reconstructor`); classical methods push
    :data:`STEP_PIXELS` at a time. Between steps the job checks for :meth:`cancel`.
    """

    def __init__(
        self,
        query: ReconstructQuery,
        plan: CenterPlan,
        settings: ServiceSettings,
        network: LoadedNetwork | None = None,
    ):
        self.query, self.settings = query, settings
        self.decoder = SpikeDecoder(query.height, query.width)
        size = (query.height, query.width)
        if query.method == "net":
            if network is None:
                raise ValueError("method net needs the served network")
            self.recon = network.reconstructor(*size, plan, query.quality, query.binning)
        else:
            self.recon = build_reconstructor(query.method, *size, plan)
        pixels = query.height * query.width
        self.step = settings.batch if query.method == "net" else max(1, STEP_PIXELS // pixels)
        self.bytes_received = 0
        self._frames: deque[np.ndarray] = deque()  # decoded, not yet reconstructed
        self._cancelled = threading.Event()

    @property
    def pending(self) -> bool:
        """Whether decoded frames wait for :meth:`advance`."""
        return bool(self._frames)

    def feed(self, chunk: bytes) -> None:
        """Take (decode) the next bytes of the upload; :meth:`advance` reconstructs them."""
        self.bytes_received += len(chunk)
        frames = self.decoder.feed(chunk)
        check_upload_size(self.settings, self.bytes_received, self.decoder.frames_decoded)
        if len(frames):
            self._frames.append(frames)

    def advance(self) -> list[bytes]:
        """Reconstruct the frames taken, step by step, until a step completes ``FRAM`` records
        (return them) or none are left (return ``[]``): so each frame goes out as soon as its
        window is in, and a cancelled job stops within one step."""
        while self._frames:
            if self._cancelled.is_set():
                raise Cancelled
            frames = self._frames[0]
            if len(frames) > self.step:
                self._frames[0] = frames[self.step :]
            else:
                self._frames.popleft()
            records = self._encode(self.recon.push(frames[: self.step]))
            self._check_pending()
            if records:
                return records
        return []

    def finish(self) -> list[bytes]:
        """The upload ended: check it and return the records still owed.

        Raises :class:`~spk2img.errors.InputError` for a partial last frame, an empty
        stream or a centre without a full window.
        """
        self.decoder.finish()
        return self._encode(self.recon.close())

    def cancel(self) -> None:
        """Stop at the next step (from any thread)."""
        self._cancelled.set()

    def _check_pending(self) -> None:
        limit = self.settings.max_tfi_pending
        if isinstance(self.recon, TFIStream) and self.recon.pending_centres > limit:
            raise RequestError(
                413,
                f"TFI holds over {limit} centres waiting for a pixel's next spike "
                "(dark pixels): ask for fewer or sparser centres, or use tfp",
            )

    def _encode(self, frames: list[Frame]) -> list[bytes]:
        return [self._encode_one(k, image) for k, image in frames]

    def _encode_one(self, center: int, image: np.ndarray) -> bytes:
        fmt = self.query.format
        if fmt == "float32":
            return encode_frame(center, image)
        display = to_display(image, self.query.gamma)
        if fmt == "uint8":
            return encode_frame(center, display, "uint8")
        png = io.BytesIO()
        Image.fromarray(display).save(png, format="PNG")
        return encode_frame(center, display, "png", png.getvalue())
