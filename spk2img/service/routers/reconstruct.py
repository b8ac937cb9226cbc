"""``POST /v1/reconstruct``: a spike stream in, reconstructed frames streamed out.

The route checks everything knowable from the query and headers (JSON 4xx), takes a place in
the pool (503 when full) and returns a :class:`~spk2img.service.duplex.FramesResponse`, which
reads the body and streams the frames itself.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from spk2img.io.spikes import frame_nbytes
from spk2img.model.config import Geometry
from spk2img.protocol.framing import MEDIA_TYPE
from spk2img.runtime.methods import method_window
from spk2img.runtime.windows import CenterPlan

from ..duplex import FramesResponse
from ..errors import RequestError
from ..inference import InferencePool
from ..reconstruction import StreamJob, check_upload_size, frame_record_bytes, job_memory
from ..schemas import ErrorDetail, ReconstructQuery
from ..settings import ServiceSettings
from ..state import ReadyService, ServedNetwork

BODY_TYPE = "application/octet-stream"
DUPLEX_HEADER = "X-Spk2img-Duplex"
"""``X-Spk2img-Duplex: 1``: the client reads the frames while it uploads (no response limit)."""
RECORD_SLACK = 1024
"""Bytes of the last record (``DONE`` or ``ERRO``) in a response-size bound."""

router = APIRouter(prefix="/v1", tags=["reconstruct"])

ERROR_SCHEMA = ErrorDetail.model_json_schema()  # inline: "model" would take the frames' media type
_ERRORS = {
    408: "the request took over max_request_seconds, or the upload stalled "
    "(upload_read_timeout_seconds) or was slower than min_upload_bytes_per_second",
    413: "the upload is over max_body_bytes or max_frames, or its frames are over "
    "response_buffer_bytes without X-Spk2img-Duplex: 1",
    415: f"Content-Type is not {BODY_TYPE}",
    422: "bad parameters or sizes, an empty body, a length that is not a whole number of frames, "
    "a centre without a full window, or frames too large for the whole memory budget",
    503: "not ready, or busy: every place or the memory budget taken (see Retry-After)",
}


@router.post(
    "/reconstruct",
    status_code=200,
    response_class=FramesResponse,
    responses={
        200: {
            "description": "FRAM records, then DONE or ERRO (see docs/service.md)",
            "content": {MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        },
        **{
            status: {"description": text, "content": {"application/json": {"schema": ERROR_SCHEMA}}}
            for status, text in _ERRORS.items()
        },
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": "the .dat spike stream (docs/format.md); Content-Length or chunked",
            "content": {BODY_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        }
    },
)
async def reconstruct(
    query: Annotated[ReconstructQuery, Query()],
    request: Request,
    service: ReadyService,
    network: ServedNetwork,
) -> FramesResponse:
    """Reconstruct the uploaded stream at the requested centres, streaming each frame as soon as
    its window has arrived."""
    settings = service.settings
    _check_content_type(request.headers.get("content-type"))
    plan = _plan(query, settings, network.geometry)
    length = request.headers.get("content-length")
    response_bytes = settings.response_buffer_bytes  # unknown before a chunked upload ends
    if length is not None:
        centres = plan.centers_for(_frames_in(int(length), query, settings))
        response_bytes = len(centres) * frame_record_bytes(query) + RECORD_SLACK
        duplex = request.headers.get(DUPLEX_HEADER, "").strip() == "1"
        if response_bytes > settings.response_buffer_bytes and not duplex:
            raise RequestError(413, _over_buffer(response_bytes, settings))
    cost = job_memory(query, settings, response_bytes, network.geometry)
    if settings.memory_budget_bytes and cost > settings.memory_budget_bytes:
        raise RequestError(
            422,
            f"{query.height}x{query.width} frames with method {query.method} need about "
            f"{cost >> 20} MiB, over the whole memory budget of "
            f"{settings.memory_budget_bytes >> 20} MiB (memory_budget_bytes): send smaller frames",
        )
    admission = service.pool.admit(cost)
    if isinstance(admission, str):
        service.metrics.refused.labels(admission).inc()
        raise RequestError(
            503,
            _refusal(admission, service.pool),
            {"Retry-After": str(settings.retry_after_seconds)},
        )
    job = StreamJob(query, plan, settings, network if query.method == "net" else None)
    return FramesResponse(job, admission, settings, service.metrics)


def _refusal(reason: str, pool: InferencePool) -> str:
    if reason == "busy":
        return f"busy: {pool.capacity} reconstructions in flight; try again later"
    return (
        f"busy: {pool.reserved >> 20} MiB of the {pool.budget >> 20} MiB memory budget are "
        "reserved by the reconstructions in flight; try again later"
    )


def _over_buffer(response_bytes: int, settings: ServiceSettings) -> str:
    return (
        f"the frames of this upload take up to {response_bytes} bytes, over the "
        f"{settings.response_buffer_bytes}-byte response buffer (response_buffer_bytes) that "
        "keeps a client that sends its whole body before reading from deadlocking: read the "
        f"response while uploading and send '{DUPLEX_HEADER}: 1', or ask for fewer centres or "
        "for uint8/png frames"
    )


def _check_content_type(content_type: str | None) -> None:
    media_type = (content_type or "").split(";")[0].strip().lower()
    if media_type != BODY_TYPE:
        raise RequestError(415, f"Content-Type must be {BODY_TYPE}, got {content_type!r}")


def _plan(query: ReconstructQuery, settings: ServiceSettings, geometry: Geometry) -> CenterPlan:
    """The centre plan (``net``: the served network's ``geometry``), after the size and window
    limits (raises 422)."""
    if query.height * query.width > settings.max_pixels:
        raise RequestError(
            422,
            f"{query.height}x{query.width} frames are over the limit of "
            f"{settings.max_pixels} pixels",
        )
    window = method_window(query.method, query.window, query.binning, query.quality, geometry)
    if window > settings.max_window:
        raise RequestError(422, f"window {window} is over the limit of {settings.max_window}")
    return CenterPlan.parse(window, query.centers, query.stride)


def _frames_in(length: int, query: ReconstructQuery, settings: ServiceSettings) -> int:
    """Frames in a body of ``length`` bytes, after the body limits (raises 413/422)."""
    nbytes = frame_nbytes(query.height, query.width)
    if length == 0:
        raise RequestError(422, "empty body: no frames")
    check_upload_size(settings, length, length // nbytes)
    if length % nbytes:
        raise RequestError(
            422,
            f"Content-Length {length} is not a whole number of {query.height}x{query.width} "
            f"frames ({nbytes} bytes each)",
        )
    return length // nbytes
