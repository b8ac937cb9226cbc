"""The viewer page at ``/`` in a real headless browser (Playwright driving Debian's Chromium,
``/usr/bin/chromium``; ``.ci/run`` installs it): upload a stream through the page's file input,
wait for the frames, compare the pixels the page shows with the HTTP API's frames, and see the
service's error message on the page."""

from __future__ import annotations

import io
import shutil
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from service_support import OCTET, parse_frames, stream_bytes

from spk2img.protocol.framing import MEDIA_TYPE, encode_error, encode_frame

CHROMIUM = Path("/usr/bin/chromium")
H, W, T = 32, 48, 200
SPIKES, BODY = stream_bytes(T, H, W, seed=7)
WAIT_MS = 20_000

pytestmark = [
    pytest.mark.skipif(
        not CHROMIUM.is_file() and shutil.which("chromium") is None,
        reason="no Chromium at /usr/bin/chromium: `apt-get install chromium` (.ci/run does)",
    ),
]
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright (the dev extra) is not installed"
)


@pytest.fixture(scope="module")
def browser():
    executable = CHROMIUM if CHROMIUM.is_file() else Path(shutil.which("chromium"))
    with sync_api.sync_playwright() as playwright:
        # never Playwright's own browser download: the machine has Debian's Chromium
        browser = playwright.chromium.launch(
            executable_path=str(executable), args=["--no-sandbox", "--disable-dev-shm-usage"]
        )
        yield browser
        browser.close()


def test_the_pages_run_under_their_content_security_policy(browser, service):
    """The viewer and the API page with the service's policy enforced: the viewer reaches the
    service (ready), the API page renders every path, and the browser reports no violation."""
    context = browser.new_context()
    page = context.new_page()
    problems: list[str] = []
    page.on("pageerror", lambda error: problems.append(str(error)))
    page.on("console", lambda message: problems.append(message.text))
    try:
        page.goto(service.url + "/")
        page.wait_for_selector("#service-status:has-text('ready')", timeout=WAIT_MS)
        page.goto(service.url + "/docs")
        page.wait_for_selector("section h2:has-text('/v1/reconstruct')", timeout=WAIT_MS)
        assert page.locator("section").count() >= 5
    finally:
        context.close()
    assert not [p for p in problems if "Content Security Policy" in p or "Refused" in p], problems


def open_viewer(page, url: str) -> None:
    """Load the viewer and wait until it has heard the service ready (and its model's window)."""
    page.goto(url)
    page.wait_for_selector("#service-status:has-text('ready')", timeout=WAIT_MS)


@pytest.fixture
def page(browser, service):
    # the tests' own polling (wait_for_function) evaluates strings, which the page's policy
    # forbids; the test above runs the pages with the policy enforced
    context = browser.new_context(
        viewport={"width": 1280, "height": 900}, accept_downloads=True, bypass_csp=True
    )
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    open_viewer(page, service.url + "/")
    yield page
    context.close()
    assert not errors, errors  # no uncaught exception in the page's script


def api_frames(service, query: str, body: bytes = BODY) -> dict[int, np.ndarray]:
    """The uint8 frames the HTTP API answers, by centre."""
    response = httpx.post(
        f"{service.url}/v1/reconstruct?{query}&format=uint8&gamma=2.2",
        content=body,
        headers=OCTET,
        timeout=30,
    )
    assert response.status_code == 200, response.text
    frames, _ = parse_frames(response.content)
    return {frame.center: frame.image for frame in frames}


def shown(page, canvas: str) -> tuple[int, np.ndarray]:
    """The centre a canvas shows and its pixels, after the page's next draw (grey: the red
    channel, checked equal to the green and blue ones)."""
    centre, width, height, rgba = page.evaluate(
        """async id => {
            await new Promise(resolve => requestAnimationFrame(resolve));  // the page draws in one
            const c = document.getElementById(id);
            const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
            return [Number(c.dataset.centre), c.width, c.height, Array.from(d)];
        }""",
        canvas,
    )
    pixels = np.array(rgba, np.uint8).reshape(height, width, 4)
    assert (pixels[..., 0] == pixels[..., 1]).all() and (pixels[..., 0] == pixels[..., 2]).all()
    assert (pixels[..., 3] == 255).all()
    return centre, pixels[..., 0]


def choose(page, path: Path, **fields: str) -> None:
    page.set_input_files("#file", str(path))
    page.wait_for_function("!document.getElementById('run').disabled", timeout=WAIT_MS)
    for name, value in fields.items():
        selector = f"#{name}"
        if page.eval_on_selector(selector, "e => e.tagName") == "SELECT":
            page.select_option(selector, value)
        else:
            page.fill(selector, value)


def run_and_wait(page) -> None:
    page.click("#run")
    page.wait_for_function(
        "document.getElementById('status').textContent.startsWith('done')"
        " || !document.getElementById('error').hidden",
        timeout=WAIT_MS,
    )
    assert page.is_hidden("#error"), page.inner_text("#error")


def reconstruct_requests(page) -> list[str]:
    """The query strings of the page's ``v1/reconstruct`` requests from now on."""
    queries: list[str] = []

    def remember(request) -> None:
        if "/v1/reconstruct?" in request.url:
            queries.append(request.url.split("?", 1)[1])

    page.on("request", remember)
    return queries


def test_dat_upload_two_methods_pixels_and_downloads(page, service, tmp_path):
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    choose(page, path, height=str(H), width=str(W), method="net", stride="10", compare="tfp")
    assert "200 frames of 32×48" in page.inner_text("#file-info")
    run_and_wait(page)
    net = api_frames(service, f"height={H}&width={W}&method=net&quality=best&stride=10")
    tfp = api_frames(service, f"height={H}&width={W}&method=tfp&window=41&stride=10")
    assert sorted(net) == list(range(20, 180, 10))
    assert page.inner_text("#frame-label") == f"frame {len(net)} of {len(net)} · centre 170"
    centre, pixels = shown(page, "canvas-a")
    assert centre == 170
    np.testing.assert_array_equal(pixels, net[centre])
    page.click("#prev")  # step back: both panes follow
    page.click("#prev")
    centre, pixels = shown(page, "canvas-a")
    assert centre == 150
    np.testing.assert_array_equal(pixels, net[centre])
    centre_b, pixels_b = shown(page, "canvas-b")
    assert centre_b == 150
    np.testing.assert_array_equal(pixels_b, tfp[centre])
    page.fill("#slider", "0")
    page.get_by_text("40", exact=True).click()  # a filmstrip thumbnail
    assert shown(page, "canvas-a")[0] == 40
    assert "gamma 2.2" in page.inner_text("#gamma-note")

    with page.expect_download() as download:
        page.click("#download-png")
    with zipfile.ZipFile(download.value.path()) as archive:
        names = archive.namelist()
        assert len(names) == 2 * len(net) and "net-best/000020.png" in names
        for centre, image in tfp.items():
            png = Image.open(io.BytesIO(archive.read(f"tfp/{centre:06d}.png")))
            assert png.mode == "L"
            np.testing.assert_array_equal(np.asarray(png), image)
    with page.expect_download() as download:
        page.click("#download-npz")
    with np.load(download.value.path()) as npz:
        assert npz["centers"].tolist() == sorted(net) and npz["centers"].dtype == np.int64
        np.testing.assert_array_equal(npz["frames"], np.stack([net[k] for k in sorted(net)]))
        np.testing.assert_array_equal(npz["frames_b"][0], tfp[20])
        assert float(npz["gamma"]) == 2.2


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_npy_and_npz_uploads_are_packed_like_a_dat(page, service, tmp_path, suffix):
    path = tmp_path / f"rec{suffix}"
    if suffix == ".npy":
        np.save(path, SPIKES.astype(bool))
    else:  # deflated, beside another array: the page takes "spk"
        np.savez_compressed(path, spk=SPIKES, other=np.zeros(3))
    choose(page, path, method="tfi", window="21")
    page.check("#use-centers")
    page.fill("#centers", "15,60,150")
    assert page.input_value("#height") == str(H) and page.input_value("#width") == str(W)
    run_and_wait(page)
    tfi = api_frames(service, f"height={H}&width={W}&method=tfi&window=21&centers=15,60,150")
    centre, pixels = shown(page, "canvas-a")
    assert centre == 150
    np.testing.assert_array_equal(pixels, tfi[150])


def test_a_long_plan_is_split_into_requests(browser, service, tmp_path):
    """With a response budget of 12 frames a request (``?budget=``), stride 3 over 200 frames
    (54 frames) takes 5 requests, each uploading only the frames its windows need: the page
    shows the same frames as one request to the API."""
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    context = browser.new_context(bypass_csp=True)  # wait_for_function evaluates strings
    page = context.new_page()
    open_viewer(page, f"{service.url}/?budget={12 * (28 + H * W)}")
    requests = reconstruct_requests(page)
    choose(page, path, height=str(H), width=str(W), method="tfp", stride="3")
    run_and_wait(page)
    whole = api_frames(service, f"height={H}&width={W}&method=tfp&window=41&stride=3")
    assert len(requests) == 5
    label = f"frame {len(whole)} of {len(whole)} · centre {max(whole)}"
    assert len(whole) == 54 and page.inner_text("#frame-label") == label
    for step in range(len(whole) - 1, -1, -13):
        page.fill("#slider", str(step))
        centre, pixels = shown(page, "canvas-a")
        assert centre == sorted(whole)[step]
        np.testing.assert_array_equal(pixels, whole[centre])
    context.close()


def test_the_services_error_appears_on_the_page(page, service, tmp_path):
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    choose(page, path, height=str(H + 1), width=str(W), method="tfp", stride="10")
    assert "not a whole number of 33×48 frames" in page.inner_text("#file-info")
    query = f"height={H + 1}&width={W}&stride=10&method=tfp"
    run_and_expect_refusal(page, service, query, "not a whole number of 33x48 frames")


def run_and_expect_refusal(page, service, query: str, fragment: str) -> None:
    """Run the page's form and check that it shows the service's own 422 message for the same
    request (``query``), which names ``fragment``, and is ready for the next try."""
    expected = httpx.post(f"{service.url}/v1/reconstruct?{query}", content=BODY, headers=OCTET)
    assert expected.status_code == 422
    page.click("#run")
    page.wait_for_selector("#error:not([hidden])", timeout=WAIT_MS)
    message = page.inner_text("#error")
    assert message == f"The service answered 422: {expected.json()['detail']}"
    assert fragment in message
    assert page.is_enabled("#run")


def test_run_before_the_service_answers_says_so_on_the_page(browser, service, tmp_path):
    """Until ``v1/models`` has answered the page does not know the network's window: Run with
    method net shows that on the page (no uncaught error, no request), and works once it has."""
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    context = browser.new_context(bypass_csp=True)  # wait_for_function evaluates strings
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    held = []
    page.route("**/v1/models", lambda route: held.append(route))  # its answer held back
    page.goto(service.url + "/")
    queries = reconstruct_requests(page)
    choose(page, path, height=str(H), width=str(W), method="net", stride="10")
    page.click("#run")
    page.wait_for_selector("#error:not([hidden])", timeout=WAIT_MS)
    assert "has not said its model's window yet" in page.inner_text("#error")
    assert not queries and not errors
    held[0].continue_()
    page.wait_for_selector("#service-status:has-text('ready')", timeout=WAIT_MS)
    run_and_wait(page)
    assert len(queries) == 1 and not errors
    context.close()


def test_binning_is_sent_for_net_best_only(page, service, tmp_path):
    """``binning=2`` goes with every request of a split plan (a budget of 5 frames: 12 centres
    of 83-frame windows in 3 requests), and the page shows the frames of one API request; for
    tfp, or quality fast, the field is disabled and no request carries it."""
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    open_viewer(page, f"{service.url}/?budget={5 * (28 + H * W)}")
    queries = reconstruct_requests(page)
    assert page.is_enabled("#binning") and page.is_visible("#binning-hint")
    choose(page, path, height=str(H), width=str(W), method="net", binning="2", stride="10")
    run_and_wait(page)
    whole = api_frames(service, f"height={H}&width={W}&method=net&binning=2&stride=10")
    assert sorted(whole) == list(range(41, 160, 10))
    assert len(queries) == 3 and all("&binning=2&" in query for query in queries)
    assert page.inner_text("#caption-a") == "net (best, binning 2), centre 151"
    for step in (0, 6, 11):
        page.fill("#slider", str(step))
        centre, pixels = shown(page, "canvas-a")
        np.testing.assert_array_equal(pixels, whole[centre])

    page.select_option("#quality", "fast")
    assert page.is_disabled("#binning") and page.is_visible("#binning-na")
    page.select_option("#quality", "best")
    page.select_option("#method", "tfp")
    assert page.is_disabled("#binning") and page.is_hidden("#binning-hint")
    queries.clear()
    run_and_wait(page)
    assert queries and not any("binning" in query for query in queries)


def test_a_refused_binning_shows_the_services_message(page, service, tmp_path):
    """Binning 3 makes the network's window 123 frames, over the test service's max_window of
    101: the page shows the service's 422 message."""
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    queries = reconstruct_requests(page)
    choose(page, path, height=str(H), width=str(W), method="net", binning="3", stride="10")
    query = f"height={H}&width={W}&stride=10&binning=3"
    run_and_expect_refusal(page, service, query, "window 123 is over the limit of 101")
    assert len(queries) == 1 and "&binning=3&" in queries[0]


@pytest.mark.parametrize(
    ("ending", "message"),
    [
        (encode_error("the request took over 60 s (max_request_seconds)", 408), "answered 408"),
        (b"", "the response was cut"),
    ],
)
def test_an_error_after_frames_keeps_them(page, tmp_path, ending, message):
    """An ``ERRO`` record after some frames (or a response cut short) is shown, and the frames
    that came stay on the page (the service's answer is stood in for by the browser)."""
    image = np.arange(H * W, dtype=np.uint32).reshape(H, W).astype(np.uint8)
    body = encode_frame(20, image, "uint8") + encode_frame(30, image[::-1], "uint8") + ending
    page.route(
        "**/v1/reconstruct?*",
        lambda route: route.fulfill(status=200, body=body, content_type=MEDIA_TYPE),
    )
    path = tmp_path / "rec.dat"
    path.write_bytes(BODY)
    choose(page, path, height=str(H), width=str(W), method="tfp", stride="10")
    page.click("#run")
    page.wait_for_selector("#error:not([hidden])", timeout=WAIT_MS)
    assert message in page.inner_text("#error")
    assert page.inner_text("#frame-label").startswith("frame 2 of 2")
    centre, pixels = shown(page, "canvas-a")
    assert centre == 30
    np.testing.assert_array_equal(pixels, image[::-1])
    assert page.is_enabled("#download-npz")
