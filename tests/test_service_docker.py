"""docker/Dockerfile's install steps, replayed without Docker: its COPY lines into a scratch
"image", its ``pip install`` into a fresh virtual environment (no system site packages), then
``spk2img serve`` from that environment. The runtime must not pull in torch."""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from isolation import extra_closure, without_modules
from service_support import OCTET, parse_frames, run_server, stream_bytes

from spk2img.protocol.framing import DoneRecord

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "docker" / "Dockerfile"
NGINX = ROOT / "docker" / "nginx.conf"
COMPOSE = ROOT / "docker" / "compose.yaml"
IDLE_RSS_BYTES = 400 * 2**20
"""The service's footprint without requests, model loaded and warmed (measured: see
docs/service.md, "Memory"), with room for the interpreter's growth."""


def dockerfile_instructions(text: str) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` pairs, continuation lines joined, comments dropped."""
    joined = text.replace("\\\n", " ")
    lines = (line.strip() for line in joined.splitlines())
    return [tuple(line.split(None, 1)) for line in lines if line and not line.startswith("#")]


def install_steps(text: str) -> tuple[str, list[tuple[list[str], str]], list[str]]:
    """The WORKDIR, the COPY steps and the ``pip install`` arguments up to the install."""
    workdir, copies = "/", []
    for instruction, args in dockerfile_instructions(text):
        if instruction == "WORKDIR":
            workdir = args
        elif instruction == "COPY":
            *sources, dest = shlex.split(args)
            copies.append((sources, dest))
        elif instruction == "RUN" and "pip install" in args:
            (command,) = [c for c in args.split("&&") if c.strip().startswith("pip install")]
            return workdir, copies, shlex.split(command)[2:]
    raise AssertionError("docker/Dockerfile has no RUN pip install")


def test_dockerfile_runtime_is_slim():
    text = DOCKERFILE.read_text()
    instructions = dockerfile_instructions(text)
    assert instructions[0] == ("FROM", "python:3.11-slim")
    _, _, pip_args = install_steps(text)
    assert pip_args[-1] == ".[serve]"
    assert ("USER", "spk2img") in instructions
    health = dict(instructions)["HEALTHCHECK"]
    command = json.loads(dict(instructions)["CMD"])
    assert command[:6] == ["spk2img", "serve", "--host", "0.0.0.0", "--port", "8000"]
    assert command[6:] == ["--health-port", "8001"] and "127.0.0.1:8001/healthz" in health


@pytest.mark.slow
def test_the_serve_extra_pulls_in_no_torch():
    """The image's ``pip install ".[serve]"`` brings onnxruntime and fastapi, never torch."""
    closure = extra_closure("serve")
    assert {"onnxruntime", "fastapi", "uvicorn", "numpy"} <= closure
    assert "torch" not in closure


def test_dockerfile_copies_serve_without_torch(tmp_path, standin_model):
    """The Dockerfile's COPY lines into a scratch "image"; ``spk2img serve`` from those files
    alone (the package copied there comes first on the path) with torch impossible to import
    answers a reconstruction."""
    workdir, copies, pip_args = install_steps(DOCKERFILE.read_text())
    assert pip_args[-1] == ".[serve]"
    image = tmp_path / "image"
    cwd = image / workdir.lstrip("/")
    cwd.mkdir(parents=True)
    for sources, dest in copies:
        for source in sources:
            target = (cwd / dest) / Path(source).name if dest.endswith("/") else cwd / dest
            if (ROOT / source).is_dir():
                shutil.copytree(ROOT / source, target, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copy2(ROOT / source, target)
    env = without_modules(tmp_path / "block", {"torch"}, cwd)
    probe = "import spk2img; print(spk2img.__file__)"
    found = subprocess.run(  # run from tmp_path: the checkout must not come first on the path
        [sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=tmp_path
    )
    assert Path(found.stdout.strip()).is_relative_to(cwd), found.stdout
    with run_server(standin_model, env=env, cwd=tmp_path) as server:
        assert server.get("/healthz").json() == {"status": "ok"}
        _, body = stream_bytes(50, 8, 8)
        response = httpx.post(
            f"{server.url}/v1/reconstruct?height=8&width=8&centers=20,29",
            content=body,
            headers=OCTET,
            timeout=30,
        )
        frames, done = parse_frames(response.content)
        assert isinstance(done, DoneRecord) and [f.center for f in frames] == [20, 29]


def nginx_servers(text: str) -> dict[str, list[str]]:
    """Each ``server`` block's ``listen`` port and the ``location`` lines it holds."""
    servers: dict[str, list[str]] = {}
    for block in text.split("server {")[1:]:
        lines = [line.strip() for line in block.splitlines()]
        port = next(line.split()[1].rstrip(";") for line in lines if line.startswith("listen"))
        servers[port] = [
            line.removesuffix("{").strip() for line in lines if line.startswith("location")
        ]
    return servers


def test_nginx_publishes_only_the_api_health_and_viewer():
    servers = nginx_servers(NGINX.read_text())
    assert servers["80"] == [
        "location /v1/",
        "location = /healthz",
        "location = /readyz",
        "location = /",
        "location /static/",
        "location /",
    ]
    assert "metrics" in servers["8081"][0] and "docs" in servers["8081"][0]
    compose = COMPOSE.read_text()
    assert '"8000:80"' in compose and "8081:" not in compose  # 8081 is never published
    public_catch_all = NGINX.read_text().split("listen 80;")[1].split("server {")[0]
    assert "return 404" in public_catch_all


def test_compose_limits_match_the_memory_budget():
    """The container's memory limit holds the service's budget plus its idle footprint."""
    compose = COMPOSE.read_text()
    limit = int(compose.split("memory: ")[1].split("m")[0]) * 2**20
    budget = int(compose.split("SPK2IMG_MEMORY_BUDGET_BYTES: ")[1].split()[0].strip('"'))
    assert budget + IDLE_RSS_BYTES <= limit
