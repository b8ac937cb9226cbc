"""The code keeps the project's lint and format rules (``[tool.ruff]`` in pyproject.toml) and
holds no dead code (``[tool.vulture]``)."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff: the dev extra")
@pytest.mark.parametrize("command", [["check"], ["format", "--check"]])
def test_ruff(command):
    done = subprocess.run(
        [sys.executable, "-m", "ruff", *command, "spk2img", "tests", "scripts"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stdout + done.stderr


@pytest.mark.skipif(importlib.util.find_spec("vulture") is None, reason="vulture: the dev extra")
def test_no_dead_code():
    """vulture over spk2img/ with the paths, confidence and whitelist of ``[tool.vulture]``."""
    done = subprocess.run(
        [sys.executable, "-m", "vulture"], cwd=ROOT, capture_output=True, text=True
    )
    assert done.returncode == 0, (
        "vulture found code nothing uses: remove it, or, for a genuine false positive (a name "
        f"a framework calls), add it to vulture_whitelist.py\n{done.stdout}{done.stderr}"
    )
