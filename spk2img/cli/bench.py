"""``spk2img bench``: every method's speed, memory and error in one table and one plot
(``bench.md``, ``bench.json``, ``images/pareto.png``), written into a fresh run folder
``bench-runs/<UTC time>/`` (git-ignored) by default; only ``--update-docs`` rewrites the
committed ``docs/`` copies."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

from spk2img.errors import InputError
from spk2img.runtime.onnx_backend import DEVICES

RUNS_DIR = Path("bench-runs")
"""Where runs go by default, one folder each (git-ignored)."""
DOCS_DIR = Path("docs")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="benchmark every method: speed, memory and error; tables and a Pareto plot",
        description="Time TFP, TFI and each network (family members with random weights, the "
        "shipped model, --trained checkpoints) on every backend, each in a fresh process; score "
        "them on a fixed simulated benchmark set; load-test the HTTP service; write bench.md, "
        "bench.json and images/pareto.png into a new run folder bench-runs/<UTC time>/ (or "
        "--out-dir); --update-docs writes them over the committed copies in docs/. Needs every "
        'extra: pip install -e ".[all]". Run it on an otherwise idle machine.',
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="CI smoke run: 48x64 frames, 2 repeats, the tiny member only, a short "
        "service run (under 2 minutes on 2 cores)",
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--out-dir",
        type=Path,
        help=f"write the files here (default: a new folder {RUNS_DIR}/<UTC time>/)",
    )
    where.add_argument(
        "--update-docs",
        action="store_true",
        help=f"write them into {DOCS_DIR}/, replacing the committed results",
    )
    p.add_argument("--threads", default="1,2", help="thread counts to time, e.g. 1,2 (default)")
    p.add_argument("--repeats", type=int, help="timed calls per row (default 5; --quick: 2)")
    p.add_argument(
        "--members",
        help="family members with random weights (default: every member, paper,small,lite,cpu,"
        "tiny; --quick: tiny; '' for none)",
    )
    p.add_argument(
        "--trained",
        action="append",
        default=[],
        metavar="NAME=CHECKPOINT",
        help="also benchmark and score a trained checkpoint (repeatable)",
    )
    p.add_argument(
        "--data",
        action="append",
        default=[],
        type=Path,
        metavar="DIR",
        help="also score every scored row on the natural validation: training's held-out photos "
        "and clips found under DIR (e.g. the training data folder; only the held-out sources "
        "are read), per sensor regime, at training's validation size (repeatable)",
    )
    p.add_argument("--skip-service", action="store_true", help="skip the HTTP load test")
    p.add_argument(
        "--stream-models",
        default="default",
        metavar="NAMES",
        help="shipped models (comma-separated names, as spk2img models lists them) that the "
        "streaming benchmark streams (default: default)",
    )
    p.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where the GPU rows run (docs/gpu.md): auto (default: CUDA where onnxruntime can "
        "run it, else they are written as not yet measured), cuda or tensorrt (an error at "
        "start where it cannot run), cpu (skip them); the CPU rows always run on the CPU",
    )
    sections = p.add_mutually_exclusive_group()
    sections.add_argument(
        "--skip-streaming", action="store_true", help="skip the streaming benchmark (block reuse)"
    )
    sections.add_argument(
        "--streaming-only",
        action="store_true",
        help="run only the streaming benchmark: bench_streaming.md and .json "
        "(the other files are left as they are)",
    )
    sections.add_argument(
        "--gpu-only",
        action="store_true",
        help="run only the GPU rows and write them into the bench.json and bench.md already in "
        "the output folder (use with --update-docs or --out-dir of an earlier run)",
    )


def run(args: argparse.Namespace) -> int:
    args.out_dir = out_dir(args)
    options = bench_options(args)
    from spk2img.bench.report import write_report  # every extra: spk2img.cli.extras checked
    from spk2img.bench.runner import run_benchmark, run_gpu_only, run_streaming_only
    from spk2img.bench.streaming import write_streaming_report

    start = time.monotonic()

    def log(message: str) -> None:
        print(f"bench [{time.monotonic() - start:5.0f} s] {message}", file=sys.stderr, flush=True)

    if args.gpu_only:
        if not (args.out_dir / "bench.json").is_file():
            raise InputError(f"--gpu-only: no bench.json in {args.out_dir} to add the rows to")

        def write(section: dict) -> Path:  # after every row too: a run cut short keeps them
            return add_gpu_rows(args.out_dir, section | {"command": options.command})

        log(f"wrote {write(run_gpu_only(options, log, write))}")
        return 0
    if args.streaming_only:
        results = run_streaming_only(options, log)
        paths = []
    else:
        results = run_benchmark(options, log)
        paths = write_report(results, args.out_dir)
    for streamed in results["streaming"] or []:
        if "error" in streamed:
            log(f"streaming benchmark of {streamed['model']} not run: {streamed['error']}")
    if any("error" not in streamed for streamed in results["streaming"] or []):
        paths += write_streaming_report(results, args.out_dir)
    for path in paths:
        log(f"wrote {path}")
    return 0


def add_gpu_rows(directory: Path, section: dict) -> Path:
    """Put the GPU ``section`` into ``directory``'s bench.json and its table into bench.md in
    place of the GPU section there (the rest of bench.md, notes added by hand included, stays;
    a bench.md without one is rewritten from bench.json); the bench.md path."""
    import json

    from spk2img.bench.report import JSON_NAME, MD_NAME, gpu_table, markdown

    path = directory / JSON_NAME
    results = json.loads(path.read_text())
    results["gpu"] = section
    md = directory / MD_NAME
    text = md.read_text() if md.is_file() else ""
    # each file whole or not at all: a run stopped while writing keeps the last rows written
    for target, content in (
        (path, json.dumps(results, indent=1) + "\n"),
        (md, replace_gpu_section(text, gpu_table(results)) or markdown(results)),
    ):
        partial = target.with_name(target.name + ".writing")
        partial.write_text(content)
        partial.replace(target)
    return md


def replace_gpu_section(text: str, table: str) -> str | None:
    """``text`` (a bench.md) with its GPU section, from its heading to the end of its table,
    replaced by ``table``; ``None`` when it has none."""
    from spk2img.bench.report import GPU_HEADING

    start = text.find(GPU_HEADING + "\n")
    if start < 0:
        return None
    lines = text[start:].split("\n")
    first = next((i for i, line in enumerate(lines) if line.startswith("|")), len(lines))
    last = next((i for i in range(first, len(lines)) if not lines[i].startswith("|")), len(lines))
    end = start + len("\n".join(lines[:last]))
    return text[:start] + table.rstrip("\n") + text[end:]


def out_dir(args: argparse.Namespace, now: datetime | None = None) -> Path:
    """Where a run writes: ``--out-dir``, ``docs/`` with ``--update-docs``, else a new folder
    ``bench-runs/YYYYmmdd-HHMMSS/`` (UTC; ``-2``, ``-3`` … if it exists already)."""
    if args.out_dir is not None:
        return args.out_dir
    if args.update_docs:
        return DOCS_DIR
    if args.gpu_only:
        raise InputError("--gpu-only adds to an earlier run: give --update-docs or --out-dir DIR")
    stamp = (now or datetime.now(UTC)).strftime("%Y%m%d-%H%M%S")
    path, n = RUNS_DIR / stamp, 1
    while path.exists():
        n += 1
        path = RUNS_DIR / f"{stamp}-{n}"
    return path


def bench_options(args: argparse.Namespace):
    """:class:`~spk2img.bench.runner.BenchOptions` from the arguments (:class:`InputError` for
    bad ones), with the command line that reproduces them."""
    from spk2img.bench.runner import FULL, QUICK, BenchOptions
    from spk2img.model.config import MEMBERS

    scale = QUICK if args.quick else FULL
    threads = _positive_ints(args.threads, "--threads")
    repeats = scale.repeats if args.repeats is None else args.repeats
    if repeats < 1:
        raise InputError(f"--repeats must be >= 1, got {repeats}")
    members = (
        scale.members if args.members is None else tuple(filter(None, args.members.split(",")))
    )
    unknown = [m for m in members if m not in MEMBERS]
    if unknown:
        raise InputError(
            f"unknown member(s) {', '.join(unknown)}: choose from {', '.join(MEMBERS)}"
        )
    trained = tuple(_named_checkpoint(text) for text in args.trained)
    for folder in args.data:
        if not folder.is_dir():
            raise InputError(f"--data: no such folder {folder}")
    stream_models = _stream_models(args.stream_models)
    names = [*members, "shipped", *(name for name, _ in trained)]
    if len(set(names)) < len(names):
        raise InputError("--trained names must be unique and differ from the members and 'shipped'")
    command = [
        "spk2img bench",
        "--quick" if args.quick else "",
        "--update-docs" if args.out_dir == DOCS_DIR else f"--out-dir {args.out_dir}",
        f"--threads {','.join(map(str, threads))}",
    ]
    if args.gpu_only:
        command += [
            "--gpu-only",
            f"--repeats {repeats}",
            f"--device {args.device}",
            "--skip-service" if args.skip_service else "",
        ]
    elif args.streaming_only:  # the rows' options do not apply
        command.append("--streaming-only")
    else:
        command += [
            f"--repeats {repeats}",
            f"--members {','.join(members) or repr('')}",
            *(f"--trained {n}={p}" for n, p in trained),
            *(f"--data {folder}" for folder in args.data),
            "--skip-service" if args.skip_service else "",
            "--skip-streaming" if args.skip_streaming else "",
            "" if args.device == "auto" else f"--device {args.device}",
        ]
    if not args.gpu_only and not args.skip_streaming and stream_models != ("default",):
        command.append(f"--stream-models {','.join(stream_models)}")
    return BenchOptions(
        replace(scale, repeats=repeats, members=members),
        threads,
        trained,
        natural_data=tuple(args.data),
        service=not args.skip_service and not args.streaming_only,
        streaming=not args.skip_streaming,
        stream_models=stream_models,
        command=" ".join(part for part in command if part),
        device=args.device,
    )


def _stream_models(text: str) -> tuple[str, ...]:
    """The shipped models ``--stream-models`` names; :class:`InputError` for a name given that is
    not installed (the default, ``default``, is reported as not installed in the results)."""
    from spk2img.runtime.onnx_backend import shipped_models

    names = tuple(filter(None, text.split(",")))
    installed = shipped_models()
    unknown = [] if text == "default" else [name for name in names if name not in installed]
    if not names or unknown:
        raise InputError(
            f"--stream-models: no shipped model {', '.join(unknown) or repr(text)} "
            f"(installed: {', '.join(installed) or 'none'})"
        )
    return names


def _positive_ints(text: str, flag: str) -> tuple[int, ...]:
    try:
        values = tuple(int(part) for part in text.split(","))
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise InputError(f"{flag} must be comma-separated positive integers, got {text!r}")
    return values


def _named_checkpoint(text: str) -> tuple[str, Path]:
    name, sep, path = text.partition("=")
    if not (sep and name and path):
        raise InputError(f"--trained takes NAME=CHECKPOINT, got {text!r}")
    if not Path(path).is_file():
        raise InputError(f"--trained {name}: no such checkpoint {path}")
    return name, Path(path)
