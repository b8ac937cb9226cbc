"""The viewer's files as the service serves them (no browser needed): the page at ``/``, its
script and style sheet, nothing else from the static folder, and nothing fetched from elsewhere."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import httpx
import pytest

from spk2img.errors import InputError
from spk2img.runtime.adaptive import QUALITIES
from spk2img.runtime.methods import METHODS, method_window
from spk2img.runtime.windows import MAX_BINNING
from spk2img.service.routers.viewer import STATIC_DIR
from spk2img.service.schemas import ReconstructQuery

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
    names = {p.name for p in STATIC_DIR.iterdir()}
    assert names == {"index.html", "viewer.js", "viewer.css", "api.html", "api.js", "api.css"}


def test_the_binning_field_takes_what_the_api_takes():
    """The page's binning field: 1 .. MAX_BINNING, the API's default, and a hint that it is for
    dim streams (1 for normal light)."""
    html = (STATIC_DIR / "index.html").read_text()
    field = re.search(r'<input type="number" id="binning"([^>]*)>', html)
    assert field, "no binning field"
    attributes = dict(re.findall(r'(\w+)="([^"]*)"', field.group(1)))
    default = ReconstructQuery.model_fields["binning"].default
    assert (attributes["min"], attributes["max"], attributes["step"]) == (
        "1",
        str(MAX_BINNING),
        "1",
    )
    assert attributes["value"] == str(default) == "1"
    hint = re.search(r'<span id="binning-hint"[^>]*>([^<]*)</span>', html).group(1)
    assert "dim streams" in hint and "1 (none) for normal light" in hint
    assert re.search(r'<span id="binning-na"[^>]*hidden>n/a', html)


def test_the_script_sends_binning_only_where_it_applies():
    """The field is read only where binning applies (else 1), and ``binning`` goes in the query
    only when it is not 1: a request without it is the one the page always sent."""
    script = (STATIC_DIR / "viewer.js").read_text()
    assert "ui.binning.disabled = ui.binningHint.hidden = !binnable();" in script
    assert "ui.binningNa.hidden = binnable();" in script
    assert 'const binning = binnable() ? positiveInt(ui.binning, "binning") : 1;' in script
    assert "if (run.binning > 1) base.binning = run.binning;" in script
    assert "ui.quality, ui.compare" in script  # a change of quality updates the field too


@pytest.mark.parametrize("quality", QUALITIES)
@pytest.mark.parametrize("method", METHODS)
def test_binning_is_enabled_where_the_service_takes_it(method, quality):
    """The script's rule for enabling binning is the service's: every other combination of
    method and quality is refused (422)."""
    script = (STATIC_DIR / "viewer.js").read_text()
    rule = re.search(r"function binnable\(\) \{\s*return (.+?);\s*\}", script).group(1)
    wanted = re.fullmatch(r'ui\.method\.value === "(\w+)" && ui\.quality\.value === "(\w+)"', rule)
    assert wanted, rule
    if (method, quality) == wanted.groups():
        assert method_window(method, binning=2, quality=quality) == 83
    else:
        with pytest.raises(InputError, match="(binning|quality) is for"):
            method_window(method, binning=2, quality=quality)
