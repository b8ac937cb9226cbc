"""Score the shipped models and the classical methods on the spike-REDS streams that SpikeZoo's
PyPI package bundles (:mod:`spk2img.evaluation.spike_reds`): evaluation only, never trained,
tuned or chosen on.

``pip install --no-deps spikezoo==0.2.3.7``, then ``python scripts/spike_reds_benchmark.py
[--models default,real,tiny,tiny-real,cpu] [--self-ensemble] [--root FOLDER] [--add]
[--json docs/spike_reds.json] [--md docs/spike_reds.md]``: each method's PSNR / SSIM on each
stream's middle 41 frames against its truth, and their means. A model is a shipped model's
name or ``NAME=GRAPH.onnx``; ``--self-ensemble`` scores the models' self-ensembles (four mirrored
views averaged) as ``NAME, self-ensemble``; ``--add`` keeps the methods already in ``--json``
(the same streams) and scores only those given; ``--models ''`` scores the classical methods
alone. The notes written below the table in ``--md`` are kept.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import sys
from pathlib import Path

import numpy as np

from spk2img.evaluation.scoring import (
    commands_made,
    dates_made,
    image_scores,
    mean_scores,
    network_methods,
    tfi_window,
    tfp_window,
)
from spk2img.evaluation.spike_reds import (
    TOOLKIT,
    BenchmarkDataError,
    find_streams,
    load_window,
    toolkit_data_root,
)

CLASSICAL = {"TFP-41": tfp_window, "TFI": tfi_window}
NOTES = "## Reading it"
"""The heading from which ``--md``'s hand-written notes are kept."""


def score(method, windows: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict:
    """PSNR (dB) and SSIM of ``method`` on each window, and their means."""
    images = [np.clip(method(spikes, truth), 0.0, 1.0) for spikes, truth in windows.values()]
    scores = image_scores(images, [truth for _, truth in windows.values()])
    per_stream = {n: [round(p, 3), round(s, 4)] for n, (p, s) in zip(windows, scores, strict=True)}
    return {**mean_scores(list(per_stream.values())), "per_stream": per_stream}


def markdown(results: dict, notes: str) -> str:
    names = results["streams"]
    lines = [
        "# spike-REDS streams (SpikeZoo's bundled data): evaluation only",
        "",
        f"Made by `{results['command']}` on {results['date']}, from {results['source']}: "
        f"{len(names)} streams simulated from REDS video by the field's protocol, each scored on "
        "its middle 41 frames against its truth image (grey level / 255 as light, whole "
        "250x400 frames; `spk2img.evaluation.spike_reds`). Never trained, tuned or chosen on.",
        "",
        "| method | PSNR (dB) | SSIM | " + " | ".join(names) + " |",
        "|---" * (3 + len(names)) + "|",
    ]
    for method, row in results["methods"].items():
        cells = [f"{row['per_stream'][n][0]:.2f}" for n in names]
        lines.append(
            f"| {method} | {row['psnr']:.2f} | {row['ssim']:.3f} | " + " | ".join(cells) + " |"
        )
    return "\n".join(lines) + "\n" + (f"\n{notes}" if notes else "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", default="default,real,tiny,tiny-real,cpu")
    parser.add_argument("--self-ensemble", action="store_true")
    parser.add_argument("--root", type=Path, help="the streams' folder (default: SpikeZoo's)")
    parser.add_argument("--add", action="store_true", help="keep the methods in --json")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, default=Path("docs/spike_reds.json"))
    parser.add_argument("--md", type=Path, default=Path("docs/spike_reds.md"))
    args = parser.parse_args(argv)
    try:
        root = args.root or toolkit_data_root()
        streams = find_streams(root)
        windows = {s.name: load_window(s) for s in streams}
    except (BenchmarkDataError, OSError, ValueError) as exc:
        print(f"spike_reds_benchmark: error: {exc}", file=sys.stderr)
        return 2
    before = json.loads(args.json.read_text()) if args.add and args.json.is_file() else {}
    kept = before.get("methods", {})
    methods = CLASSICAL | network_methods(args.models, args.threads, args.self_ensemble)
    if args.add:
        methods = {name: m for name, m in methods.items() if name not in CLASSICAL or not kept}
    scored = dict(kept)
    for name, method in methods.items():
        scored[name] = score(method, windows)
        print(f"{name}: {scored[name]['psnr']:.2f} dB, SSIM {scored[name]['ssim']:.3f}", flush=True)
    source = str(root) if args.root else f"{TOOLKIT} {importlib.metadata.version(TOOLKIT)}"
    # what decides the rows, as real_video_validation.py records it (--threads changes the time)
    command = (
        f"python scripts/spike_reds_benchmark.py --models {args.models}"
        + (" --self-ensemble" if args.self_ensemble else "")
        + (f" --root {args.root}" if args.root else "")
        + (" --add" if args.add else "")
    )
    results = {
        "command": commands_made(before.get("command"), command),
        "date": dates_made(before.get("date")),
        "source": source,
        "streams": [s.name for s in streams],
        "methods": scored,
    }
    args.json.write_text(json.dumps(results, indent=1) + "\n")
    text = args.md.read_text() if args.md.is_file() else ""
    args.md.write_text(markdown(results, text[text.find(NOTES) :] if NOTES in text else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
