"""The packages show the flow spikes -> windows -> network -> frames: each imports only packages
of a lower layer (docs/architecture.md, "Packages"), and no module imports itself back through
others. Read from the source with ``ast``, every import counted, including those inside
functions."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "spk2img"

LAYERS: list[set[str]] = [
    {
        "errors",
        "provenance",
        "hardware",
        "parts",
        "io",
        "protocol",
        "markdown",
    },  # formats, transfer
    {"model"},  # the network and its geometry
    {"sim"},  # what a spike camera films
    {"runtime"},  # spikes -> windows -> network -> frames
    {"evaluation"},  # scores of frames
    {"export"},  # torch -> ONNX, verified
    {"training"},  # training runs and their model cards
    {"api", "service", "clients"},  # the in-process API, the HTTP service and its clients
    {"bench"},  # speed against error of all of the above
    {"cli", "__main__"},  # the command line
]
LEVEL = {package: level for level, packages in enumerate(LAYERS) for package in packages}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _package(module: str) -> str:
    """``spk2img.runtime.stream`` -> ``runtime``; ``spk2img.api`` -> ``api``."""
    return module.split(".")[1]


def _imports(path: Path) -> set[str]:
    """The spk2img modules ``path`` imports (relative imports resolved)."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found |= {f"{base}.{alias.name}" for alias in node.names}
    return {name for name in found if name.split(".")[0] == "spk2img"}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    """Module -> the spk2img modules it imports (names that are modules only). The root package
    ``spk2img`` (the version, and the public names it hands on lazily from the API) is the
    namespace every module imports, not a layer: it is left out."""
    files = {_module_name(path): path for path in ROOT.rglob("*.py")}
    files.pop("spk2img")
    return {name: _imports(path) & files.keys() - {name} for name, path in files.items()}


def test_every_package_has_a_layer(graph):
    assert {_package(module) for module in graph} == set(LEVEL)


def test_no_package_imports_a_higher_layer(graph):
    upward = [
        f"{module} -> {target}"
        for module, targets in graph.items()
        for target in targets
        if LEVEL[_package(target)] > LEVEL[_package(module)]
    ]
    assert not upward, "\n".join(sorted(upward))


def test_packages_import_each_other_without_cycles(graph):
    """Between packages of one layer too (api, service and clients): no two import each other,
    directly or through others."""
    edges = {(_package(m), _package(t)) for m, ts in graph.items() for t in ts}
    edges = {(a, b) for a, b in edges if a != b}
    reach = {package: {b for a, b in edges if a == package} for package in LEVEL}
    for _ in LEVEL:  # transitive closure
        reach = {p: targets.union(*(reach[t] for t in targets)) for p, targets in reach.items()}
    assert not [p for p, targets in reach.items() if p in targets]
