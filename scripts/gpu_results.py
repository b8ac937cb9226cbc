"""What a GPU session brought back, put where the project keeps it (docs/gpu.md, "A GPU session").

``python scripts/gpu_results.py FILES_AT [--state-dir training_state] [--runs runs] [--docs
docs]`` reads the folder a command's files came back to: ``report.tar.gz``, ``NAME-last.pt``,
``NAME-best.pt`` from ``scripts/gpu_session.sh session`` and ``more``; ``bench/``,
``verify_fp16_cuda.txt``, ``onnxruntime.txt`` and ``tensorrt.txt`` from its ``onnx`` step:

- each run's ``metrics.jsonl`` into ``STATE_DIR/NAME/`` (its whole log: a later ``more``
  brings the log again, longer), and its ``last.pt`` there as its weights alone in fp16 (what
  the next run starts from with ``--init``; the machine's full state does not outlive the
  machine, and the room beside the checkout that the next session's data needs stays);
- both checkpoints as they came into ``RUNS/NAME/`` (git-ignored), to score them here;
- the torch inference rows (``torch_inference.json``) into ``DOCS/gpu_torch_inference.json``
  and, as a table, ``DOCS/gpu_torch_inference.md``; the synthesis speed
  (``synthesis_speed_gpu.json``) and ``environment.txt`` into ``DOCS/`` as they are;
- the bench's GPU section (``bench/bench.json``) into ``DOCS/bench.json``, with
  ``DOCS/bench.md`` rewritten from it (the CPU rows stay as they were measured), and the fp16
  parity on the GPU, onnxruntime's providers and TensorRT's probe into ``DOCS/`` (prefixed
  ``gpu_``).

It prints, per run, the steps it reached, its median steps a second and samples a second, and
its last validation, then the commands that score its checkpoints on the real-video
validation. Whatever the session did not bring back is named, not an error.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import statistics
import sys
import tarfile
from pathlib import Path

import torch

from spk2img.model.checkpoint import release_checkpoint

REPORT = "report.tar.gz"


def read_report(files_at: Path) -> dict[str, bytes]:
    """The files of ``report.tar.gz`` by their path under ``report/`` (``NAME/metrics.jsonl``)."""
    with tarfile.open(files_at / REPORT) as tar:
        return {
            member.name.removeprefix("report/"): tar.extractfile(member).read()
            for member in tar.getmembers()
            if member.isfile() and member.name.startswith("report/")
        }


def run_summary(metrics: bytes) -> dict:
    """Steps, median steps and samples a second, and the last validation of a run's log (with
    its alignment probe, where it has one)."""
    records = [json.loads(line) for line in io.BytesIO(metrics).read().decode().splitlines()]
    train = [r for r in records if r["kind"] == "train"]
    start = next((r for r in records if r["kind"] == "run"), {})
    batch = start.get("train_config", {}).get("batch_size")
    rates = [r["steps_per_s"] for r in train[1:]] or [r["steps_per_s"] for r in train]
    vals = [r for r in records if r["kind"] == "val"]
    steps_per_s = statistics.median(rates) if rates else None
    return {
        "step": train[-1]["step"] if train else 0,
        "steps_per_s": steps_per_s,
        "samples_per_s": steps_per_s * batch if steps_per_s and batch else None,
        "val_psnr": vals[-1].get("psnr") if vals else None,
        "val_step": vals[-1]["step"] if vals else None,
        "alignment_slopes": vals[-1].get("alignment_slopes") if vals else None,
    }


def inference_table(result: dict) -> str:
    """``torch_inference.json`` as a markdown table: ms a frame per network, precision, batch."""
    lines = [
        f"# Torch inference on {result['device']}",
        "",
        f"torch {result['torch']}, {result['size']} windows, median of the script's repeats "
        "(`scripts/torch_inference_speed.py`; brought back by `scripts/gpu_results.py`).",
        "",
        "| network | precision | batch | ms a frame | max abs vs fp32 | PSNR vs fp32 (dB) |",
        "|---|---|---|---|---|---|",
    ]
    for name, rows in result["models"].items():
        for row in rows:
            psnr = row["psnr_vs_fp32_db"]
            lines.append(
                f"| {name} | {row['precision']} | {row['batch']} | {row['ms_per_frame']:.2f} | "
                f"{row['max_abs_vs_fp32']:.1e} | {'—' if psnr is None else f'{psnr:.1f}'} |"
            )
    return "\n".join(lines) + "\n"


ONNX_FILES = ("verify_fp16_cuda.txt", "onnxruntime.txt", "tensorrt.txt")
"""What the ``onnx`` step writes beside ``bench/``, filed in docs/ as ``gpu_NAME``."""


def take_onnx_results(files_at: Path, docs: Path) -> list[str]:
    """The ``onnx`` step's bench section and files into ``docs`` (module doc)."""
    from spk2img.cli.bench import add_gpu_rows

    section = json.loads((files_at / "bench" / "bench.json").read_text())["gpu"]
    add_gpu_rows(docs, section)
    measured = [row for row in section["rows"] if row.get("ms_per_frame")]
    said = [f"GPU bench rows: {len(measured)} of {len(section['rows'])} measured, into {docs}"]
    for name in ONNX_FILES:
        if (files_at / name).is_file():
            shutil.copyfile(files_at / name, docs / f"gpu_{name}")
        else:
            said.append(f"no {name} came back")
    return said


def take_results(files_at: Path, state_dir: Path, runs: Path, docs: Path) -> list[str]:
    """Put what came back in its places (module doc); returns what was said, a line each."""
    said = []
    if (files_at / "bench" / "bench.json").is_file():
        said += take_onnx_results(files_at, docs)
    if not (files_at / REPORT).is_file():
        return [*said, f"{files_at}: no {REPORT}: this command brought back no training report"]
    report = read_report(files_at)
    docs.mkdir(parents=True, exist_ok=True)
    written = sorted({path.split("/")[0] for path in report if path.endswith("metrics.jsonl")})
    for name in written:
        metrics = report[f"{name}/metrics.jsonl"]
        (state_dir / name).mkdir(parents=True, exist_ok=True)
        (state_dir / name / "metrics.jsonl").write_bytes(metrics)
        (runs / name).mkdir(parents=True, exist_ok=True)
        for kind in ("last", "best"):
            came = files_at / f"{name}-{kind}.pt"
            if came.is_file():
                shutil.copyfile(came, runs / name / f"{kind}.pt")
        last = runs / name / "last.pt"
        if last.is_file():
            release_checkpoint(last, state_dir / name / "last.pt", torch.float16)
        summary = run_summary(metrics)
        rate = (
            f"{summary['steps_per_s']:.2f} steps/s ({summary['samples_per_s']:.0f} samples/s)"
            if summary["samples_per_s"]
            else "no timed steps"
        )
        val = (
            f"validation {summary['val_psnr']:.2f} dB at step {summary['val_step']}"
            if summary["val_psnr"] is not None
            else "no validation yet"
        )
        if summary["alignment_slopes"]:  # docs/motion_study.md: 1 follows motion, 0 ignores it
            slopes = ", ".join(f"{k} {v:.3f}" for k, v in summary["alignment_slopes"].items())
            val += f" (alignment slopes: {slopes})"
        kept = "last.pt kept (fp16 weights)" if last.is_file() else "no last.pt"
        said.append(f"{name}: step {summary['step']}, {rate}, {val}; {kept}")
    if "torch_inference.json" in report:
        result = json.loads(report["torch_inference.json"])
        (docs / "gpu_torch_inference.json").write_bytes(report["torch_inference.json"])
        (docs / "gpu_torch_inference.md").write_text(inference_table(result))
        said.append(f"torch inference rows of {len(result['models'])} networks: {docs}")
    else:
        said.append("no torch inference rows came back")
    others = sorted(
        p.parent.name for p in state_dir.glob("*/last.pt") if p.parent.name not in written
    )
    if others and len(written) + len(others) > 2:  # the repository keeps two runs' states
        said.append(f"more than two states in {state_dir}: drop the last.pt of {', '.join(others)}")
    for name in ("synthesis_speed_gpu.json", "environment.txt"):
        if name in report:
            (docs / ("gpu_" + name if name == "environment.txt" else name)).write_bytes(
                report[name]
            )
        else:
            said.append(f"no {name} came back")
    return said


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files_at", type=Path, help="the folder the session's files came to")
    parser.add_argument("--state-dir", type=Path, default=Path("training_state"))
    parser.add_argument("--runs", type=Path, default=Path("runs"))
    parser.add_argument("--docs", type=Path, default=Path("docs"))
    args = parser.parse_args(argv)
    try:
        said = take_results(args.files_at, args.state_dir, args.runs, args.docs)
    except (OSError, tarfile.TarError, ValueError, KeyError) as exc:
        print(f"gpu_results: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(said))
    print(
        "next: for each run, the whole-frame real-video score beside the shipped models "
        "(training_state/README.md: release_checkpoint, spk2img export, "
        "scripts/real_video_validation.py --add), then its row in training_state/README.md "
        "and python -m spk2img.training.campaign_report"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
