"""``POST /v1/reconstruct``: a spike stream in, reconstructed frames streamed out.

The route checks everything knowable from the query and headers (JSON 4xx), takes a place in
the pool (503 when full) and returns a :class:`~spk2img.service.duplex.FramesResponse`, which
reads the body and streams the frames itself.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from spk2img.core.framing import MEDIA_TYPE
from spk2img.core.methods import method_plan
from spk2img.core.spikes import frame_nbytes
from spk2img.core.windows import CenterPlan

from ..duplex import FramesResponse
from ..errors import RequestError
from ..reconstruction import StreamJob, check_upload_size
from ..schemas import ErrorDetail, ReconstructQuery
from ..settings import ServiceSettings
from ..state import ReadyService, ServedModel

BODY_TYPE = "application/octet-stream"

router = APIRouter(prefix="/v1", tags=["reconstruct"])

ERROR_SCHEMA = ErrorDetail.model_json_schema()  # inline: "model" would take the frames' media type
_ERRORS = {
    408: "the request took over max_request_seconds",
    413: "the upload is over max_body_bytes or max_frames",
    415: f"Content-Type is not {BODY_TYPE}",
    422: "bad parameters or sizes, an empty body, a length that is not a whole number of frames, "
    "or a centre without a full window",
    503: "not ready, or busy (see Retry-After)",
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
    model: ServedModel,
) -> FramesResponse:
    """Reconstruct the uploaded stream at the requested centres, streaming each frame as soon as
    its window has arrived."""
    settings = service.settings
    _check_content_type(request.headers.get("content-type"))
    if query.quality != "best" and query.method != "net":
        raise RequestError(422, f"quality is for method net, not {query.method}")
    plan = _plan(query, settings)
    length = request.headers.get("content-length")
    if length is not None:
        plan.centers_for(_frames_in(int(length), query, settings))
    admission = service.pool.admit()
    if admission is None:
        raise RequestError(
            503,
            f"busy: {service.pool.capacity} reconstructions in flight; try again later",
            {"Retry-After": str(settings.retry_after_seconds)},
        )
    net = query.method == "net"
    job = StreamJob(query, plan, settings, model if net else None, service.codec if net else None)
    return FramesResponse(job, admission, settings.max_request_seconds, service.metrics)


def _check_content_type(content_type: str | None) -> None:
    media_type = (content_type or "").split(";")[0].strip().lower()
    if media_type != BODY_TYPE:
        raise RequestError(415, f"Content-Type must be {BODY_TYPE}, got {content_type!r}")


def _plan(query: ReconstructQuery, settings: ServiceSettings) -> CenterPlan:
    """The centre plan, after the size and window limits (raises 422)."""
    if query.height * query.width > settings.max_pixels:
        raise RequestError(
            422,
            f"{query.height}x{query.width} frames are over the limit of "
            f"{settings.max_pixels} pixels",
        )
    if query.method != "net" and query.window > settings.max_window:
        raise RequestError(422, f"window {query.window} is over the limit of {settings.max_window}")
    return method_plan(query.method, query.centers, query.stride, query.window)


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
