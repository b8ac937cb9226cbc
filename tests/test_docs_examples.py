"""Every code block of README.md and docs/*.md runs as written, on the shipped files.

A block is code when its fence names ``python``, ``bash`` or ``sh``; the others are text
(synopses, outputs, file trees, grammars). Each code block runs in a scratch folder that holds
the checkout's ``examples/``, ``spk2img/`` and ``scripts/`` (python blocks with this
interpreter, shell blocks with bash, ``-e``), with ``http://127.0.0.1:8000`` pointing at the
tests' service. A block that cannot run here says why in :data:`NOT_RUN` (a GPU, Docker, pip,
the training data, a capture that is not shipped), one that another test runs as written is in
:data:`RUN_ELSEWHERE`; a long one is shortened by the replacements in :data:`SHORTENED`; a
fragment that continues the text before it gets the :data:`CONTEXT` that text describes. A new
block is run unless it is listed, so the docs stay runnable.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
CODE_LANGUAGES = {"python", "bash", "sh"}
SAMPLE = "examples/fast_motion_250x400.dat"
DOCS_URL = "http://127.0.0.1:8000"


@dataclass(frozen=True)
class Block:
    """A fenced code block: its file (relative to the checkout), line, language and text."""

    file: str
    line: int
    language: str
    text: str

    @property
    def key(self) -> tuple[str, str]:
        """The file and the block's first line: how the tables below name it."""
        return self.file, self.text.splitlines()[0].strip()

    def __str__(self) -> str:
        return f"{self.file}:{self.line}"


def doc_blocks() -> list[Block]:
    found = []
    for path in DOC_FILES:
        text = path.read_text()
        for match in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.M | re.S):
            line = text[: match.start()].count("\n") + 1
            name = str(path.relative_to(ROOT))
            found.append(Block(name, line, match.group(1), match.group(2)))
    return found


NOT_RUN = {
    ("README.md", 'pip install -e ".[all]"'): "installs (CI runs it first; tests never call pip)",
    ("README.md", "python -m pytest -q"): "the test suite itself",
    ("README.md", "spk2img train --member lite --run-dir runs/lite --data PHOTOS_AND_CLIPS/ \\"): (
        "needs the training photos and clips, which are not shipped"
    ),
    (
        "docs/binning.md",
        "python scripts/real_capture_quality.py CAPTURE.npz --binning auto --step 5 \\",
    ): "needs a real capture, which is not shipped",
    (
        "docs/client.md",
        'pip install "spk2img[client]"     # numpy, tqdm, pillow + httpx; no '
        "fastapi, onnxruntime or torch",
    ): "installs",
    (
        "docs/gpu.md",
        'pip install -e ".[gpu]"        # the serve extra with onnxruntime-gpu '
        "instead of onnxruntime",
    ): "installs",
    ("docs/gpu.md", "pip uninstall -y onnxruntime onnxruntime-gpu"): "installs",
    ("docs/gpu.md", 'python -c "import onnxruntime as o; print(o.get_available_providers())"'): (
        "meant after installing onnxruntime-gpu"
    ),
    ("docs/gpu.md", f"spk2img reconstruct {SAMPLE} --out out.npz --device cuda"): "needs a GPU",
    (
        "docs/gpu.md",
        'pip install -e ".[all]" && pip uninstall -y onnxruntime && pip install '
        "onnxruntime-gpu==1.31.1",
    ): "installs, then needs a GPU",
    (
        "docs/gpu.md",
        "# here: split",
    ): "needs the package registry and a GPU machine",
    (
        "docs/gpu.md",
        "scripts/gpu_session.sh prepare-onnx        # here, 90 s: download, slim, split into "
        "pack-onnx/",
    ): "downloads the 256 MB onnxruntime-gpu wheel (tests run offline; "
    "tests/test_gpu_scripts.py slims a synthetic one)",
    (
        "docs/sensor.md",
        "spk2img fit-sensor CAPTURE [--height 250 --width 400] [--out PRESET.json]",
    ): "a synopsis (placeholders)",
    (
        "docs/sensor.md",
        "spk2img fit-sensor uhsr_helicopter_250x250.npz --out "
        "spk2img/assets/sensors/vidar-fitted.json",
    ): "needs the real capture, which is not shipped",
    ("docs/service.md", 'pip install -e ".[serve]"'): "installs, then serves until stopped",
    ("docs/service.md", "docker compose -f docker/compose.yaml up --build --scale spk2img=3"): (
        "needs Docker"
    ),
    (
        "docs/training_data.md",
        "spk2img train --member lite --run-dir runs/lite --data "
        "PHOTOS_AND_CLIPS/ [--data MORE/] \\",
    ): "a synopsis (placeholders)",
    ("docs/viewer.md", 'pip install -e ".[serve]"'): "installs, then serves until stopped",
}
"""Blocks that cannot run here, and why."""

RUN_ELSEWHERE = {
    (
        "README.md",
        f"spk2img reconstruct {SAMPLE} --out out/frames.npz --png-dir out/png --stride 7",
    ): "tests/test_shipped_model.py runs it as written, on the whole sample stream",
}
"""Blocks another test runs as written, and which."""

SHORTENED = {
    ("README.md", "import spk2img"): [("stride=7)", "centers=[20])")],
    ("docs/export.md", "import time, numpy as np"): [
        ("range(7)", "range(1)"),
        ("(1, 2)", "(2,)"),
        ("spk2img-default.onnx", "spk2img-tiny.onnx"),
        ("250, 400)", "64, 96)"),
    ],
    ("docs/binning.md", "k = spk2img.suggest_binning(spikes)  # 1 for a normally lit stream"): [
        ("stride=20", "centers=[60]")
    ],
}
"""Replacements that shorten long blocks (fewer frames or repeats, the same calls)."""

CONTEXT = {
    (
        "docs/binning.md",
        "spk2img reconstruct dim.npz --out out.npz --binning auto      # or --binning 3",
    ): (
        "before",
        "spk2img simulate dim.dat --frames 200 --height 48 --width 64 --brightness dim -q\n"
        "python -c \"import spk2img; s = spk2img.read_spikes('dim.dat', 48, 64); "
        "spk2img.write_spikes('dim.npz', s[0:200])\"\n",
    ),
    ("docs/binning.md", "k = spk2img.suggest_binning(spikes)  # 1 for a normally lit stream"): (
        "before",
        f'import spk2img\nspikes = spk2img.read_spikes("{SAMPLE}", 250, 400)\n',
    ),
    (
        "docs/service.md",
        "from spk2img.protocol.framing import DoneRecord, ErrorRecord, FrameRecord, RecordParser",
    ): (
        "wrap",
        "import httpx\n"
        f'body = open("{SAMPLE}", "rb").read()\n'
        f'url = "{DOCS_URL}/v1/reconstruct?stride=20&method=tfp"\n'
        "headers = {'Content-Type': 'application/octet-stream'}\n"
        "with httpx.stream('POST', url, content=body, headers=headers) as response:\n",
    ),
    ("docs/client.md", "import asyncio"): (
        "after",
        "import numpy as np\n"
        f'camera = spk2img.read_spikes("{SAMPLE}", 250, 400)[0:80]\n'
        "show = lambda image: print(image.shape)\n"
        "asyncio.run(main(iter(np.asarray(camera))))\n",
    ),
}
"""What a fragment continues: code run before it (a capture the text calls ``dim.npz``, the
``spikes`` it talks of), around it (the ``response`` it reads) or after it (calling the
``main`` it defines, with the ``show`` it leaves to the reader)."""

BLOCKS = doc_blocks()
CODE = [b for b in BLOCKS if b.language in CODE_LANGUAGES]
RUN = [b for b in CODE if b.key not in NOT_RUN and b.key not in RUN_ELSEWHERE]


def test_every_listed_block_is_in_the_docs_and_most_code_runs():
    keys = {b.key for b in CODE}
    listed = (*NOT_RUN, *RUN_ELSEWHERE, *SHORTENED, *CONTEXT)
    stale = [key for key in listed if key not in keys]
    assert not stale, f"listed blocks no longer in the docs: {stale}"
    run = len(RUN) + len(RUN_ELSEWHERE)
    print(f"\n{len(BLOCKS)} blocks, {len(CODE)} code, {run} run, {len(CODE) - run} not")
    assert run >= 12


def script_of(block: Block, url: str) -> str:
    text = block.text
    for old, new in SHORTENED.get(block.key, []):
        assert old in text, (str(block), old)
        text = text.replace(old, new)
    where, extra = CONTEXT.get(block.key, ("", ""))
    if where == "before":
        text = extra + text
    elif where == "after":
        text = text + "\nimport spk2img\n" + extra
    elif where == "wrap":
        text = extra + "".join(f"    {line}\n" for line in text.splitlines())
    return text.replace(DOCS_URL, url)


@pytest.fixture
def scratch(tmp_path) -> Path:
    for name in ("examples", "spk2img", "scripts"):
        (tmp_path / name).symlink_to(ROOT / name)
    return tmp_path


@pytest.mark.parametrize("block", RUN, ids=str)
def test_the_block_runs_as_written(block, scratch, service):
    script = script_of(block, service.url)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    if block.language == "python":
        command = [sys.executable, "-c", script]
    else:
        command = ["bash", "-e", "-o", "pipefail", "-c", script]
    done = subprocess.run(
        command, cwd=scratch, env=env, capture_output=True, text=True, timeout=300
    )
    output = f"--- stdout\n{done.stdout}\n--- stderr\n{done.stderr}"
    assert done.returncode == 0, f"{block}:\n{script}\n{output}"
