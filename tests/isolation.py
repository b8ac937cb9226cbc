"""Running spk2img as a smaller installation would, without installing anything: a subprocess in
which some packages cannot be imported, and what an extra of pyproject.toml pulls in.

Tests run offline and never call pip: what a fresh ``pip install ".[client]"`` or the Docker
image's ``pip install ".[serve]"`` would give is checked as (1) the extra's dependency closure
among the installed distributions and (2) the program run with every other package blocked."""

from __future__ import annotations

import os
import re
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

BLOCKER = '''"""Test-only: importing any of BLOCKED fails as if it were not installed."""
import importlib.abc
import sys

BLOCKED = {blocked!r}


class _NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None


sys.meta_path.insert(0, _NotInstalled())
'''


def without_modules(folder: Path, modules, *paths: Path) -> dict[str, str]:
    """The environment of a subprocess in which importing any of ``modules`` (top-level names)
    raises ``ModuleNotFoundError``; ``paths`` come first on its ``sys.path``."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(BLOCKER.format(blocked=set(modules)))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(str(p) for p in (folder, *paths))
    return env


def _name(requirement: str) -> str:
    return re.sub(r"[-_.]+", "-", Requirement(requirement).name).lower()


def extra_closure(extra: str | None, package: str = "spk2img") -> set[str]:
    """The normalised names of every distribution ``package[extra]`` needs, transitively, as the
    installed distributions' metadata declare them (``extra`` None: the base install)."""
    seen: set[str] = set()
    todo = [(package, extra)]
    while todo:
        dist, wanted = todo.pop()
        for text in metadata.requires(dist) or []:
            requirement = Requirement(text)
            marker = requirement.marker
            if marker is not None and not marker.evaluate({"extra": wanted or ""}):
                continue
            name = _name(text)
            if name in seen or name == package:
                continue
            seen.add(name)
            try:
                metadata.distribution(name)
            except metadata.PackageNotFoundError:
                continue  # not installed here: its own needs are unknown, it is still named
            todo.append((name, None))
    return seen
