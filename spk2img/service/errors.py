"""Errors as the API answers them: ``{"detail": "<one line>"}`` with a 4xx/5xx status."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from spk2img.errors import InputError

logger = logging.getLogger("spk2img.service")


class RequestError(Exception):
    """An error to answer with ``status``: a JSON error before the first frame, an ``ERRO``
    record after it. ``headers`` go with a JSON error (``Retry-After`` of a 503)."""

    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None):
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


def as_request_error(exc: Exception) -> RequestError:
    """The status and message for any exception: input errors are 422, bugs 500."""
    if isinstance(exc, RequestError):
        return exc
    if isinstance(exc, InputError):
        return RequestError(422, str(exc))
    logger.exception("unexpected error while reconstructing", exc_info=exc)
    return RequestError(500, f"internal error: {type(exc).__name__}")


def error_response(error: RequestError) -> JSONResponse:
    return JSONResponse({"detail": error.detail}, error.status, headers=error.headers)


def validation_message(exc: RequestValidationError) -> str:
    """FastAPI's list of validation errors as one line: ``query.height: msg; ...``."""
    parts = []
    for error in exc.errors():
        where = ".".join(str(part) for part in error.get("loc", ()))
        parts.append(f"{where}: {error['msg']}" if where else error["msg"])
    return "; ".join(parts)


def install_error_handlers(app: FastAPI) -> None:
    """Answer validation, input, request and unexpected errors as ``{"detail": str}``."""

    async def on_validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        return error_response(RequestError(422, validation_message(exc)))

    async def on_input(_: Request, exc: InputError) -> JSONResponse:
        return error_response(as_request_error(exc))

    async def on_request(_: Request, exc: RequestError) -> JSONResponse:
        return error_response(exc)

    async def on_unexpected(_: Request, exc: Exception) -> JSONResponse:
        return error_response(as_request_error(exc))

    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(InputError, on_input)
    app.add_exception_handler(RequestError, on_request)
    app.add_exception_handler(Exception, on_unexpected)
