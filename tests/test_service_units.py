"""Service pieces without a server: settings and flags, readiness, the pool, the per-request job."""

from __future__ import annotations

import asyncio
import gc
import socket
import threading
import typing
import warnings
from pathlib import Path

import httpx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from service_support import OCTET, stream_bytes

from spk2img.cli import build_parser, main
from spk2img.cli.serve import flag_name, settings_from_args
from spk2img.errors import InputError
from spk2img.model.config import PUBLISHED_GEOMETRY
from spk2img.runtime.loader import LoadedNetwork
from spk2img.runtime.methods import method_plan
from spk2img.service import app as app_module
from spk2img.service import server as server_module
from spk2img.service.app import create_app
from spk2img.service.duplex import ClientGone, _Upload
from spk2img.service.inference import InferencePool
from spk2img.service.reconstruction import Cancelled, StreamJob
from spk2img.service.schemas import ReconstructQuery
from spk2img.service.settings import ServiceSettings


def _sample(name: str, field) -> tuple[str, object]:
    """A valid value of the setting other than its default: as a flag's text, and as parsed."""
    kinds = typing.get_args(field.annotation) or (field.annotation,)
    default = field.get_default(call_default_factory=True)
    if field.annotation is bool:
        return str(not default).lower(), not default
    if typing.get_origin(field.annotation) is typing.Literal:
        choice = next(value for value in kinds if value != default)
        return choice, choice
    if int in kinds:
        value = default + 1 if default else 3
        return str(value), value
    if float in kinds:
        return str(default * 2), default * 2
    if Path in kinds:  # a path, or also a name where str is accepted (--model)
        text = f"/elsewhere/{name}.onnx"
        return text, text if str in kinds else Path(text)
    assert str in kinds, f"no sample value for setting {name}: {field.annotation}"
    return "0.0.0.0", "0.0.0.0"


def test_every_setting_is_a_flag_that_reaches_the_settings():
    fields = ServiceSettings.model_fields
    samples = {name: _sample(name, field) for name, field in fields.items()}
    argv = ["serve"]
    for name, (text, _) in samples.items():
        argv += [flag_name(name), text]
    chosen = settings_from_args(build_parser().parse_args(argv))
    assert {name: getattr(chosen, name) for name in fields} == {
        name: value for name, (_, value) in samples.items()
    }
    assert all(
        value != fields[name].get_default(call_default_factory=True)
        for name, (_, value) in samples.items()
    )


def test_a_bad_flag_value_is_one_line_and_exit_2(capsys):
    assert main(["serve", "--port", "eighty"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--port (SPK2IMG_PORT)" in err, err


def test_flags_win_over_the_environment(monkeypatch):
    monkeypatch.setenv("SPK2IMG_MAX_QUEUE", "3")
    monkeypatch.setenv("SPK2IMG_MAX_FRAMES", "77")
    args = build_parser().parse_args(["serve", "--max-queue", "5", "--threads", "4"])
    chosen = settings_from_args(args)
    assert (chosen.max_queue, chosen.max_frames, chosen.threads) == (5, 77, 4)
    assert chosen.job_workers == 4 and chosen.intra_op_threads == 1
    assert ServiceSettings(threads=4, workers=1).intra_op_threads == 4


def test_bad_settings_are_input_errors(monkeypatch):
    monkeypatch.setenv("SPK2IMG_THREADS", "0")
    with pytest.raises(InputError, match=r"--threads \(SPK2IMG_THREADS\)"):
        settings_from_args(build_parser().parse_args(["serve"]))


def test_serve_without_the_model_file_fails_clearly(tmp_path, capsys):
    assert main(["serve", "--model", str(tmp_path / "missing.onnx")]) == 2
    assert "no model file" in capsys.readouterr().err


def test_serve_on_a_file_that_is_no_model_or_a_busy_port_is_one_line(tmp_path, capsys):
    """Found before the server starts: exit 2 and one line, not the server's traceback."""
    (tmp_path / "not.onnx").write_bytes(b"not a graph")
    assert main(["serve", "--model", str(tmp_path / "not.onnx"), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "not a loadable ONNX model" in err and err.count("\n") == 1
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        assert main(["serve", "--port", port]) == 2
        assert main(["serve", "--port", "0", "--health-port", port]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [
        f"spk2img serve: error: --port {port}: cannot listen on 127.0.0.1:{port} "
        "(Address already in use)",
        f"spk2img serve: error: --health-port {port}: cannot listen on 127.0.0.1:{port} "
        "(Address already in use)",
    ]


def test_serve_loads_the_model_once_and_the_app_serves_that_network(monkeypatch, standin_model):
    """The CLI loads the network before the server starts; the app's start-up keeps it."""
    loads = []
    real_load = app_module.load_network
    monkeypatch.setattr(
        app_module, "load_network", lambda *a, **k: loads.append(a) or real_load(*a, **k)
    )
    served = []
    monkeypatch.setattr(server_module.Listeners, "run", lambda self: served.append(self.app))
    assert main(["serve", "--model", str(standin_model), "--port", "0"]) == 0
    (app,) = served
    network = app.state.service.network
    assert len(loads) == 1 and network.predict.path == standin_model

    async def start_and_stop():
        async with app.router.lifespan_context(app):
            assert app.state.service.network is network

    asyncio.run(start_and_stop())
    assert len(loads) == 1


def test_not_ready_before_the_model_is_loaded(standin_model):
    """Before the lifespan has run: alive, not ready, reconstruct and models answer 503."""
    app = create_app(ServiceSettings(model=standin_model, retry_after_seconds=7))

    async def ask():
        transport = httpx.ASGITransport(app=app)  # runs no lifespan
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return (
                await client.get("/healthz"),
                await client.get("/readyz"),
                await client.get("/v1/models"),
                await client.post("/v1/reconstruct?centers=20", content=b"x", headers=OCTET),
            )

    health, ready, models, reconstruct = asyncio.run(ask())
    assert health.status_code == 200
    for response in (ready, models, reconstruct):
        assert response.status_code == 503 and response.headers["retry-after"] == "7"
        assert "not ready" in response.json()["detail"]


def test_pool_admits_workers_plus_queue_and_releases_after_the_last_job():
    pool = InferencePool(workers=1, max_queue=1)
    first, second = pool.admit(), pool.admit()
    assert not isinstance(first, str) and not isinstance(second, str)
    assert pool.admit() == "busy" and pool.full()
    release = threading.Event()

    async def scenario():
        job = asyncio.ensure_future(first.run(release.wait, 10))
        await asyncio.sleep(0.05)
        job.cancel()  # the request gave up while its job runs
        first.close()
        assert pool.admitted == 2 and pool.jobs == 1  # the place is held until the job ends
        release.set()
        for _ in range(100):
            if pool.admitted == 1:
                break
            await asyncio.sleep(0.01)

    asyncio.run(scenario())
    assert pool.admitted == 1 and pool.jobs == 0
    second.close()
    second.close()  # closing twice gives back one place
    assert pool.admitted == 0 and not isinstance(pool.admit(), str)
    pool.shutdown()


H, W = 8, 12
_, BODY = stream_bytes(60, H, W, seed=11)


def _job(method: str, **query) -> StreamJob:
    q = ReconstructQuery(height=H, width=W, method=method, **query)
    plan = method_plan(q.method, q.centers, q.stride, q.window)
    tfp41 = LoadedNetwork(lambda w: w.mean(axis=1) / 0.6, PUBLISHED_GEOMETRY)
    return StreamJob(q, plan, ServiceSettings(), tfp41)


@settings(max_examples=60, deadline=None)
@given(
    method=st.sampled_from(["net", "tfp", "tfi"]),
    cuts=st.lists(st.integers(0, len(BODY)), max_size=12),
)
def test_the_job_gives_the_same_records_for_any_split(method, cuts):
    whole = _job(method, stride=3, window=5)
    expected = _advance_all(whole, BODY) + whole.finish()
    job = _job(method, stride=3, window=5)
    bounds = [0, *sorted(cuts), len(BODY)]
    records = []
    for a, b in zip(bounds, bounds[1:], strict=False):
        records += _advance_all(job, BODY[a:b])
    assert records + job.finish() == expected


def _advance_all(job: StreamJob, chunk: bytes) -> list[bytes]:
    """Feed ``chunk`` and advance until nothing is pending (as the response does)."""
    job.feed(chunk)
    records = []
    while job.pending:
        step = job.advance()
        assert step or not job.pending  # a call returns records, or has used every frame
        records += step
    return records


def test_each_advance_returns_the_records_of_one_step_as_soon_as_their_window_is_in():
    """A whole body taken at once comes back a step at a time: every call to advance returns
    the frames of one model call (batch 1: one centre), not the body's all at the end."""
    job = _job("net", stride=3)
    job.feed(BODY)
    sizes = []
    while job.pending:
        sizes.append(len(job.advance()))
    centres = len(range(20, 60 - 20, 3))
    assert sum(sizes) == centres and set(sizes) <= {0, 1} and sizes.count(1) == centres


def test_a_cancelled_job_stops():
    job = _job("tfp", stride=1, window=3)
    job.feed(BODY)
    job.cancel()
    with pytest.raises(Cancelled):
        job.advance()


def test_a_read_after_the_client_left_is_refused_without_a_dangling_coroutine():
    """The upload asked for its next piece after the client has gone raises ``ClientGone`` and
    leaves no coroutine that was never awaited (the log's "coroutine 'Queue.get' was never
    awaited" under resets)."""

    async def scenario():
        messages = asyncio.Queue()
        messages.put_nowait({"type": "http.disconnect"})
        upload = _Upload(messages.get, 1.0, 0, lambda: None, 1024)
        await asyncio.sleep(0)  # the reader task sees the disconnect
        await asyncio.sleep(0)
        with pytest.raises(ClientGone):
            await upload.next()

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        asyncio.run(scenario())
        gc.collect()
    assert not [w for w in seen if "never awaited" in str(w.message)]
