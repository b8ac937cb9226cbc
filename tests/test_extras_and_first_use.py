"""What a new user meets: every command on every install level works or says in one
line which extra to install; Python versions; docs that stand alone; honest progress; bench
runs outside docs/; a clean repo; inputs that are not 0/1 spikes refused. No test calls pip:
install levels are simulated by hiding the extras' modules from the import system."""

from __future__ import annotations

import argparse
import ast
import json
import re
import subprocess
import sys
import tomllib
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from spk2img.cli import build_parser, main
from spk2img.cli.bench import bench_options, out_dir
from spk2img.cli.extras import EXTRA_MODULES, missing_extra, required_extra
from spk2img.cli.progress import show_progress

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "examples" / "fast_motion_250x400.dat"

LEVELS = {
    "base": set(),
    "client": set(EXTRA_MODULES["client"]),
    "serve": set(EXTRA_MODULES["serve"]),
    "train": set(EXTRA_MODULES["train"]),
    "export": set(EXTRA_MODULES["export"]),
    "all": set().union(*EXTRA_MODULES.values()),
}
HEAVY = sorted(LEVELS["all"])

COMMANDS = {  # argv -> the extra it needs (None: the base install runs it)
    "reconstruct IN --out o.npz": "serve",
    "reconstruct IN --out o.npz --method tfp": None,
    "reconstruct IN --out o.npz --method tfi": None,
    "reconstruct IN --out o.npz --quality fast": None,
    "reconstruct IN --out o.npz --quality balanced": "serve",
    "reconstruct IN --out o.npz --backend torch": "train",
    "reconstruct IN --out o.npz --url http://127.0.0.1:9": "client",
    "simulate o.dat --frames 45 --height 8 --width 12": None,
    "fit-sensor IN": None,
    "models": "train",
    "train --steps 1": "train",
    "pack-data --data . --out o.pack": None,
    "export --random-weights --member tiny --out m.onnx": "export",
    "verify m.onnx": "export",
    "serve --port 8123": "serve",
    "bench --quick": "all",
    "bench --gpu-only --out-dir d": "export",  # the GPU machine's image has no fastapi or PyAV
}


def _args(argv: str) -> argparse.Namespace:
    return build_parser().parse_args(argv.split())


@pytest.mark.parametrize("argv, extra", COMMANDS.items())
@pytest.mark.parametrize("level", LEVELS)
def test_the_decision_on_every_install_level(argv, extra, level):
    need = required_extra(_args(argv))
    assert (need.extra if need else None) == extra
    message = missing_extra(_args(argv), available=LEVELS[level].__contains__)
    # the modules a command really imports (onnxruntime comes with serve and export, torch
    # with train and export)
    runs = need is None or set(need.modules) <= LEVELS[level]
    assert (message is None) == runs, message
    if message:
        assert "\n" not in message
        assert f'pip install -e ".[{extra}]"' in message


def test_main_says_one_line_and_exits_3(monkeypatch, capsys):
    monkeypatch.setattr("spk2img.cli.extras.module_available", lambda name: False)
    assert main(["models"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert 'models needs the train extra (not installed: torch): pip install -e ".[train]"' in err


_LIGHT_RUN = r"""
import contextlib, io, json, sys
BLOCKED = set(sys.argv[1].split(","))

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, Block())  # import X: ModuleNotFoundError, as when X is not installed
import importlib.util

_find_spec = importlib.util.find_spec
importlib.util.find_spec = lambda name, package=None: (  # find_spec(X): None, as then
    None if name.partition(".")[0] in BLOCKED else _find_spec(name, package)
)
from spk2img.cli import main

results = {}
for argv in json.loads(sys.argv[2]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code
        except BaseException as exc:
            import traceback
            traceback.print_exc(file=err)
            code = "raised"
    results[" ".join(argv)] = [code, err.getvalue()]
print(json.dumps(results))
"""


@pytest.mark.parametrize("level", ["base", "client"])
def test_light_installs_never_show_a_traceback(level, tmp_path):
    """The real commands in a process where the modules of the missing extras cannot be
    imported (as after ``pip install -e .`` or ``pip install -e ".[client]"``)."""
    spikes = tmp_path / "in.npy"
    np.save(spikes, (np.random.default_rng(0).random((50, 8, 12)) < 0.3).astype(np.uint8))
    blocked = [m for m in HEAVY if m not in LEVELS[level]]
    runs = {
        argv.replace("IN", str(spikes))
        .replace("o.", f"{tmp_path}/o.")
        .replace("m.onnx", f"{tmp_path}/m.onnx"): extra
        for argv, extra in COMMANDS.items()
    }
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            _LIGHT_RUN,
            ",".join(blocked),
            json.dumps([argv.split() for argv in runs]),
        ],
        capture_output=True,
        text=True,
        check=True,
        cwd=tmp_path,
    )
    results = json.loads(out.stdout)
    for argv, extra in runs.items():
        code, err = results[argv]
        assert "Traceback" not in err, (argv, err)
        if extra is not None and not set(EXTRA_MODULES[extra]) <= LEVELS[level]:
            assert code == 3, (argv, err)
            assert err.count("\n") == 1 and f'pip install -e ".[{extra}]"' in err, (argv, err)
        else:  # works, or fails on its input in one line (fit-sensor on 50 frames of 8x12, a
            # service that is not there)
            assert code in (0, 2), (argv, err)
            assert code == 0 or err.count("\n") == 1, (argv, err)
    ok = [argv for argv, (code, _) in results.items() if code == 0]
    assert any("--method tfp" in argv and "--url" not in argv for argv in ok)
    assert any(argv.startswith("simulate") for argv in ok)


def test_python_versions():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["requires-python"] == ">=3.11"
    for version in ("3.11", "3.12", "3.13"):
        assert f"Programming Language :: Python :: {version}" in project["classifiers"]
    assert "3.11" in (REPO / "README.md").read_text()


REMOVED_STDLIB = {  # gone in 3.12 (PEP 632, PEP 594 part) and 3.13 (PEP 594)
    "distutils", "imp", "asynchat", "asyncore", "smtpd", "aifc", "audioop", "cgi", "cgitb",
    "chunk", "crypt", "imghdr", "mailcap", "msilib", "nis", "nntplib", "ossaudiodev", "pipes",
    "sndhdr", "spwd", "sunau", "telnetlib", "uu", "xdrlib", "lib2to3",
}  # fmt: skip


def test_no_module_removed_in_python_3_12_or_3_13_is_imported():
    for path in [*(REPO / "spk2img").rglob("*.py"), *(REPO / "tests").glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            for name in names:
                assert name.partition(".")[0] not in REMOVED_STDLIB, (path, name)


def _tracked() -> list[str]:
    try:
        out = subprocess.run(
            ["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True
        )
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return out.stdout.splitlines()


def test_docs_stand_alone():
    """No reference to a specification users do not have; every docs/*.md the code and the
    docs point to exists."""
    pointed = set()
    for name in _tracked():
        path = REPO / name
        if path.suffix not in (".py", ".md", ".toml", ".txt", ".json", ".yaml", "") or (
            not path.is_file()
        ):
            continue
        text = path.read_text(errors="replace")
        assert "SPEC" + " §" not in text, name  # (split: this file must not match itself)
        pointed |= set(re.findall(r"docs/([a-z_]+\.md)", text))
    assert {"format.md", "http.md", "cli.md"} <= pointed
    missing = [name for name in pointed if not (REPO / "docs" / name).is_file()]
    assert not missing


def test_no_caches_in_git_and_tool_output_ignored():
    tracked = _tracked()
    caches = (".schemathesis/", "__pycache__/", ".pytest_cache/", ".hypothesis/", ".ruff_cache/")
    assert not [name for name in tracked if any(c in name for c in caches)]
    written = ["bench-runs/20260101-000000/bench.md", ".schemathesis/x.json", "out/frames.npz",
               "runs/tiny/last.pt", ".venv/bin/python", "spk2img/__pycache__/a.pyc",
               ".coverage", "onnxruntime_profile__1.json"]  # fmt: skip
    out = subprocess.run(
        ["git", "check-ignore", "--no-index", *written], cwd=REPO, capture_output=True, text=True
    )
    assert sorted(out.stdout.split()) == sorted(written)
    # binaries: the shipped model, the sample stream, docs figures and small fixtures only
    # (training_state/, the resumable training runs, is dealt with on its own)
    big = [
        name
        for name in tracked
        if (REPO / name).is_file()
        and (REPO / name).stat().st_size > 1_000_000
        and not name.startswith(("spk2img/assets/", "examples/", "docs/images/", "training_state/"))
    ]
    assert not big


def test_bench_writes_a_run_folder_unless_told_to_update_docs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    now = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    args = _args("bench --quick")
    assert out_dir(args, now) == Path("bench-runs/20260102-030405")
    Path("bench-runs/20260102-030405").mkdir(parents=True)
    assert out_dir(args, now) == Path("bench-runs/20260102-030405-2")
    assert out_dir(_args("bench --quick --update-docs"), now) == Path("docs")
    assert out_dir(_args("bench --quick --out-dir elsewhere"), now) == Path("elsewhere")
    with pytest.raises(SystemExit):
        _args("bench --update-docs --out-dir docs")
    args = _args("bench --quick --update-docs")
    args.out_dir = out_dir(args)
    assert "--update-docs" in bench_options(args).command


class _Stream:
    def __init__(self, tty: bool):
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def test_progress_only_on_a_terminal_and_never_with_quiet():
    assert show_progress(_args("reconstruct x --out o.npz"), _Stream(True))
    assert not show_progress(_args("reconstruct x --out o.npz"), _Stream(False))
    assert not show_progress(_args("reconstruct x --out o.npz --quiet"), _Stream(True))
    assert not show_progress(_args("simulate o.dat -q"), _Stream(True))
    assert not show_progress(_args("simulate o.dat --no-progress"), _Stream(True))


def test_progress_is_per_frame_and_each_centre_comes_when_done():
    """On a stream of 47 frames with two centres, progress moves on every frame and each
    centre is handed over right after the last frame of its window, not at the end."""
    from spk2img import Reconstructor

    spikes = (np.random.default_rng(1).random((47, 6, 7)) < 0.4).astype(np.uint8)
    events: list = []
    recon = Reconstructor("tfp")
    for k, _ in recon.frames(spikes, centers=[20, 26], progress=events.append):
        events.append(("centre", k))
    assert [e for e in events if isinstance(e, int)] == list(range(1, 48))
    assert events.index(("centre", 20)) == events.index(40) + 1
    assert events.index(("centre", 26)) == events.index(46) + 1


def test_cli_not_on_a_terminal_prints_no_bar(tmp_path, capsys):
    out = tmp_path / "o.npz"
    assert main(["reconstruct", str(SAMPLE), "--out", str(out), "--method", "tfp"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("wrote ") and err.count("\n") == 1  # no bar: stderr is not a tty
    assert main(["reconstruct", str(SAMPLE), "--out", str(out), "--method", "tfp", "-q"]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "values, words",
    [
        (np.array([0, 1, 2], np.uint8), "found 2 at frame"),
        (np.array([0.0, 1.0, 0.5]), "found 0.5 at frame"),
        (np.array([0, 1, -1], np.int16), "found -1 at frame"),
    ],
)
@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_not_spikes_is_one_line_and_exit_2(tmp_path, capsys, values, words, suffix):
    spikes = np.zeros((45, 4, 5), values.dtype)
    spikes[30, 2, 3] = values[-1]
    spikes[::2, 0, 0] = values[1]
    path = tmp_path / f"bad{suffix}"
    if suffix == ".npy":
        np.save(path, spikes)
    else:
        np.savez(path, spk=spikes)
    argv = ["reconstruct", str(path), "--out", str(tmp_path / "o.npz"), "--method", "tfp"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and "frame 30 (row 2, column 3)" in err
    assert not (tmp_path / "o.npz").exists()
