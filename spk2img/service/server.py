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

With ``health_port``, :class:`Listeners` runs a second, plain listener in the same event loop
that answers only ``/healthz`` and ``/readyz`` from the same app (:class:`HealthOnly`), so an
orchestrator's probes are never refused for connections held on the main port.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Iterator

import uvicorn
from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from spk2img.runtime.loader import LoadedNetwork

from .app import create_app
from .metrics import ServiceMetrics
from .settings import ServiceSettings

GRACEFUL_SHUTDOWN_SECONDS = 5
HEALTH_PATHS = frozenset({"/healthz", "/readyz"})
_NOT_A_PROBE = json.dumps({"detail": "this port answers /healthz and /readyz only"}).encode()


class HealthOnly:
    """``app`` for the health paths only; anything else is a JSON 404."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in HEALTH_PATHS:
            await self.app(scope, receive, send)
            return
        headers = [(b"content-type", b"application/json")]
        await send({"type": "http.response.start", "status": 404, "headers": headers})
        await send({"type": "http.response.body", "body": _NOT_A_PROBE})


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


class _ProbeServer(uvicorn.Server):
    """A uvicorn server that leaves the signals to the main one (which stops it)."""

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield


class Listeners:
    """The main listener and, with ``settings.health_port``, the probes' listener serving the
    same app in one event loop; the probes' one stops when the main one does."""

    def __init__(self, settings: ServiceSettings, app: FastAPI | None = None):
        self.app = app if app is not None else create_app(settings)
        self.main = uvicorn.Server(server_config(settings, self.app))
        self.probes = None
        if settings.health_port is not None:
            probes = uvicorn.Config(
                HealthOnly(self.app),
                host=settings.host,
                port=settings.health_port,
                lifespan="off",  # the main listener runs the app's lifespan
                log_level=settings.log_level,
                access_log=False,
            )
            self.probes = _ProbeServer(probes)

    @property
    def health_port(self) -> int | None:
        """The probes' port once listening (``health_port`` 0 picks a free one)."""
        if self.probes is None or not self.probes.started:
            return None
        return self.probes.servers[0].sockets[0].getsockname()[1]

    async def serve(self) -> None:
        probes = asyncio.ensure_future(self.probes.serve()) if self.probes else None
        try:
            await self.main.serve()
        finally:
            if probes is not None:
                self.probes.should_exit = True
                await probes

    def stop(self) -> None:
        """Stop both at once (no grace)."""
        self.main.should_exit = self.main.force_exit = True

    def run(self) -> None:
        asyncio.run(self.serve())


def run(settings: ServiceSettings, network: LoadedNetwork | None = None) -> None:
    """Serve ``network`` (default: loaded by the app's start-up) until stopped
    (SIGINT/SIGTERM)."""
    Listeners(settings, create_app(settings, network)).run()
