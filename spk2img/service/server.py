"""Running the app under uvicorn with the connection-level limits of the settings.

uvicorn's h11 protocol, with what it lacks (:func:`protocol_class`):

* a **header timeout**: a connection must send a whole request head within
  ``header_timeout_seconds`` of connecting (or of the end of its previous response), else it
  is closed — half-sent request lines hold nothing for long;
* a **connection cap**: past ``max_connections`` open connections a new one is answered 503 and
  closed at once;
* **half-close**: a client that has sent its whole request and shut down its write side still
  gets every frame and the end record (uvicorn would close the connection at the EOF).

and uvicorn's own settings: ``timeout_keep_alive`` (``keep_alive_seconds``) and
``h11_max_incomplete_event_size`` (``max_head_bytes``).
"""

from __future__ import annotations

import asyncio
import json

import uvicorn
from fastapi import FastAPI
from uvicorn.protocols.http.h11_impl import H11Protocol

from .app import create_app
from .metrics import ServiceMetrics
from .settings import ServiceSettings

GRACEFUL_SHUTDOWN_SECONDS = 5


def protocol_class(settings: ServiceSettings, metrics: ServiceMetrics) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a header timeout, a connection cap and half-close."""
    header_timeout = settings.header_timeout_seconds
    max_connections = settings.max_connections
    refusal = json.dumps({"detail": f"busy: over {max_connections} open connections"}).encode()
    busy = (
        b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n"
        + f"retry-after: {settings.retry_after_seconds}\r\n".encode()
        + f"connection: close\r\ncontent-length: {len(refusal)}\r\n\r\n".encode()
        + refusal
    )

    class GuardedH11Protocol(H11Protocol):
        _head_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            connections = self.connections
            metrics.connections.set_function(lambda: len(connections))
            if len(connections) > max_connections:
                metrics.refused.labels("connections").inc()
                transport.write(busy)
                transport.close()
                return
            self._arm_head_timer()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm_head_timer()
            super().connection_lost(exc)

        def eof_received(self) -> bool | None:
            """Keep writing after the client's EOF when its request is whole and unanswered
            (half-close); else close as uvicorn does."""
            cycle = self.cycle
            if cycle is not None and not cycle.response_complete and not cycle.more_body:
                cycle.keep_alive = False  # close once the response is sent
                self._disarm_head_timer()
                return True
            return None

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm_head_timer()

        def _arm_head_timer(self) -> None:
            self._disarm_head_timer()
            self._head_timer = self.loop.call_later(header_timeout, self._head_late, self.cycle)

        def _disarm_head_timer(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_late(self, cycle) -> None:
            """No new request head since the timer was armed: close the connection."""
            self._head_timer = None
            if self.cycle is cycle and not self.transport.is_closing():
                if cycle is None or cycle.response_complete:
                    metrics.refused.labels("header_timeout").inc()
                    self.transport.close()

    return GuardedH11Protocol


def server_config(settings: ServiceSettings, app: FastAPI | None = None) -> uvicorn.Config:
    """The uvicorn configuration serving ``app`` (default: ``create_app(settings)``)."""
    app = app if app is not None else create_app(settings)
    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        http=protocol_class(settings, app.state.service.metrics),
        timeout_keep_alive=settings.keep_alive_seconds,
        h11_max_incomplete_event_size=settings.max_head_bytes,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_SECONDS,
    )


def run(settings: ServiceSettings) -> None:
    """Serve until stopped (SIGINT/SIGTERM)."""
    uvicorn.Server(server_config(settings)).run()
