"""Where an artefact came from: the commit of the code that made it."""

from __future__ import annotations

import subprocess
from pathlib import Path


def git_commit() -> str:
    """``git rev-parse HEAD`` of the tree this package lives in, or ``unknown``."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"
