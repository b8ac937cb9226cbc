"""The viewer: a page at ``/`` (static HTML/JS/CSS shipped in the package, no build step, nothing
fetched from elsewhere) that uploads a spike stream to ``POST /v1/reconstruct`` and shows the
frames as they stream back (docs/viewer.md)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from starlette.types import Receive, Scope, Send

from ..errors import RequestError

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
"""``spk2img/service/static``: the page's files (package data)."""
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
}
"""The file types the viewer serves; any other name is 404."""
NO_CACHE = {"Cache-Control": "no-cache"}
"""Revalidate on each load (ETag/Last-Modified), so a new version of the page is seen at once."""

router = APIRouter(tags=["viewer"], include_in_schema=False)


class WholeFile(FileResponse):
    """A file sent whole: a ``Range`` header is ignored (as HTTP allows), so no range, valid or
    not, gets an answer outside the service's JSON errors; the page's files are small."""

    def __init__(self, path: Path, media_type: str, headers: dict[str, str]):
        super().__init__(path, media_type=media_type, headers=headers)
        del self.headers["accept-ranges"]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        ignored = (b"range", b"if-range")
        headers = [(name, value) for name, value in scope["headers"] if name not in ignored]
        await super().__call__({**scope, "headers": headers}, receive, send)


def _static(name: str) -> WholeFile:
    path = STATIC_DIR / name
    media_type = MEDIA_TYPES.get(Path(name).suffix)
    # the name is one path segment of the URL, never "..": only files directly in STATIC_DIR
    if media_type is None or "/" in name or name.startswith(".") or not path.is_file():
        raise RequestError(404, f"no viewer file {name!r}")
    return WholeFile(path, media_type, NO_CACHE)


@router.get("/")
def page() -> WholeFile:
    """The viewer page."""
    return _static("index.html")


@router.get("/docs")
def api_page() -> WholeFile:
    """The API reference, rendered from ``/openapi.json`` by the page's own script."""
    return _static("api.html")


@router.get("/static/{name}")
def static_file(name: str) -> WholeFile:
    """One of the page's scripts and style sheets."""
    return _static(name)
