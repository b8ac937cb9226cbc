"""Browser hardening and strict queries, against a real ``spk2img serve``: security headers on
every response a browser may render, no redirect built from the Host header, ranges never
answered outside the JSON errors, an API page that loads nothing from elsewhere, and a
parameter repeated with different values refused by name."""

from __future__ import annotations

import re

import httpx
import pytest
from service_support import OCTET, parse_frames, stream_bytes

from spk2img.protocol.framing import DoneRecord
from spk2img.service.routers.viewer import STATIC_DIR
from spk2img.service.security import SECURITY_HEADERS


def _get(service, path: str, **headers) -> httpx.Response:
    return httpx.get(service.url + path, headers=headers, timeout=10)


def _post(service, target: str, body: bytes) -> httpx.Response:
    return httpx.post(service.url + target, content=body, headers=OCTET, timeout=10)


def _assert_hardened(answer: httpx.Response) -> None:
    for name, value in SECURITY_HEADERS.items():
        assert answer.headers.get(name) == value, (answer.request.url, name)


@pytest.mark.parametrize(
    "path", ["/", "/docs", "/static/viewer.js", "/healthz", "/readyz", "/v1/models", "/nope"]
)
def test_every_answer_carries_the_security_headers(service, path):
    _assert_hardened(service.get(path))


def test_the_frames_and_their_errors_carry_them_too(service):
    _, body = stream_bytes(45, 8, 12, seed=1)
    frames = _post(service, "/v1/reconstruct?height=8&width=12&centers=20", body)
    assert frames.status_code == 200 and isinstance(parse_frames(frames.content)[1], DoneRecord)
    _assert_hardened(frames)
    refused = _post(service, "/v1/reconstruct?height=8&width=12&centers=20", b"")
    assert refused.status_code == 422
    _assert_hardened(refused)


def test_the_policy_allows_what_the_pages_load_and_nothing_inline():
    """The policy's sources are the service's own: the pages hold no inline script or style,
    no style attribute and no handler attribute, which it would block."""
    policy = SECURITY_HEADERS["content-security-policy"]
    assert "script-src 'self'" in policy and "frame-ancestors 'none'" in policy
    assert "unsafe-inline" not in policy and "unsafe-eval" not in policy
    for page in ("index.html", "api.html"):
        html = (STATIC_DIR / page).read_text()
        assert not re.search(r"<script(?![^>]*\bsrc=)", html), page
        assert "<style" not in html and not re.search(r"\sstyle=|\son\w+=", html), page
    for script in ("viewer.js", "api.js"):
        text = (STATIC_DIR / script).read_text()
        assert ".innerHTML" not in text and "eval(" not in text and "new Function" not in text


@pytest.mark.parametrize("host", ["127.0.0.1", "evil.example"])
def test_a_trailing_slash_is_a_json_404_never_a_redirect(service, host):
    answer = _get(service, "/static/index.html/", Host=host)
    assert answer.status_code == 404 and "location" not in answer.headers
    assert answer.headers["content-type"] == "application/json" and "detail" in answer.json()


@pytest.mark.parametrize("value", ["bytes=5-1", "bytes=0-9", "bytes=abc", "items=1-2"])
def test_a_range_is_ignored_and_the_whole_file_sent(service, value):
    answer = _get(service, "/static/viewer.css", Range=value)
    assert answer.status_code == 200 and "accept-ranges" not in answer.headers
    assert answer.content == (STATIC_DIR / "viewer.css").read_bytes()


def test_the_api_page_is_served_by_the_service_itself(service):
    page = service.get("/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    linked = re.findall(r'(?:src|href)="(static/[^"]+)"', page.text)
    assert sorted(linked) == ["static/api.css", "static/api.js", "static/viewer.css"]
    assert all(service.get("/" + path).status_code == 200 for path in linked)
    script = (STATIC_DIR / "api.js").read_text()
    assert 'fetch("openapi.json")' in script
    assert service.get("/openapi.json").json()["paths"]
    assert service.get("/redoc").status_code == 404


@pytest.mark.parametrize(
    ("query", "named"),
    [
        ("method=tfp&method=tfi", "method (tfi, tfp)"),
        ("height=16&height=32", "height (16, 32)"),
        ("binning=2&binning=3", "binning (2, 3)"),
    ],
)
def test_a_parameter_given_twice_with_different_values_is_a_422_naming_it(service, query, named):
    answer = _post(service, f"/v1/reconstruct?width=12&centers=20&{query}", b"\0" * 600)
    assert answer.status_code == 422
    assert answer.json()["detail"].endswith(named), answer.json()


def test_a_parameter_repeated_with_the_same_value_is_taken(service):
    _, body = stream_bytes(45, 8, 12, seed=2)
    answer = _post(service, "/v1/reconstruct?height=8&height=8&width=12&centers=20", body)
    assert answer.status_code == 200
