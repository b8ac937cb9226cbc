"""The viewer's files as the service serves them (no browser needed): the page at ``/``, its
script and style sheet, nothing else from the static folder, and nothing fetched from elsewhere."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import httpx
import pytest

from spk2img.service.routers.viewer import STATIC_DIR

ROOT = Path(__file__).resolve().parents[1]


def test_the_page_and_its_files(service):
    page = service.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "spk2img viewer" in page.text
    linked = re.findall(r'(?:src|href)="(static/[^"]+)"', page.text)
    assert sorted(linked) == ["static/viewer.css", "static/viewer.js"]
    types = {"static/viewer.js": "text/javascript", "static/viewer.css": "text/css"}
    for path in linked:
        answer = service.get("/" + path)
        assert answer.status_code == 200, path
        assert answer.headers["content-type"].startswith(types[path])
        assert answer.content == (STATIC_DIR / Path(path).name).read_bytes()
    assert "/" not in service.get("/openapi.json").json()["paths"]  # not part of the API


@pytest.mark.parametrize(
    "path", ["/static/nope.js", "/static/..%2Fapp.py", "/static/../app.py", "/static/.hidden.js"]
)
def test_nothing_else_is_served(service, path):
    answer = httpx.get(service.url + path, timeout=10)
    assert answer.status_code == 404
    assert "detail" in answer.json()


def test_nothing_is_fetched_from_elsewhere():
    """No CDN, no font or script from the internet: the page works offline. Every URL in the
    files is relative (the service's own API) or a link in a comment."""
    for path in STATIC_DIR.iterdir():
        text = path.read_text()
        assert not re.search(r"https?://", text), path.name
        assert "import(" not in text and "@import" not in text, path.name


def test_the_files_ship_in_the_package():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "service/static/*" in config["tool"]["setuptools"]["package-data"]["spk2img"]
    assert {p.name for p in STATIC_DIR.iterdir()} == {"index.html", "viewer.js", "viewer.css"}
