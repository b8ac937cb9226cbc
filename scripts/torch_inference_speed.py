"""The shipped networks in torch: ms per frame at one size, per precision and batch, and the
error of each precision against fp32 — the torch side of the GPU rows (issue: GPU inference).

``python scripts/torch_inference_speed.py [--device cuda] [--size 250x400] [--batches 1,8,32]
[--precisions fp32,bf16,fp16] [--compile] [--repeats 5] [--json OUT.json]`` loads every shipped
checkpoint (``spk2img/assets/models/spk2img-*.pt``), runs a simulated window batch of the size
through it under each precision (autocast for bf16/fp16), warm-up first, and reports the median
ms per frame (per window) and, per precision, the largest absolute difference from fp32 and its
PSNR on the same windows. ``--compile`` adds the ``torch.compile``d fp32 rows. Runs anywhere;
on the CPU use small sizes (the tests do).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from spk2img.evaluation.metrics import psnr
from spk2img.export.hard_cases import simulated_windows
from spk2img.model.checkpoint import load_model

MODELS = Path(__file__).resolve().parents[1] / "spk2img" / "assets" / "models"
DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(run, device: torch.device, repeats: int) -> tuple[float, torch.Tensor]:
    """Median seconds of ``run()`` over ``repeats`` calls after one warm-up, and its output."""
    out = run()
    synchronize(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = run()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def measure(model, windows, device, precisions, batches, repeats, compiled) -> list[dict]:
    """Rows of one network: every precision and batch (and the compiled fp32 ones)."""
    rows, reference = [], None
    variants = [(p, model) for p in precisions]
    if compiled:
        variants.append(("fp32 compiled", torch.compile(model)))
    for precision, net in variants:
        dtype = DTYPES.get(precision)
        for batch in batches:
            x = windows[:1].expand(batch, -1, -1, -1).contiguous()

            def run(net=net, x=x, dtype=dtype):
                with (
                    torch.inference_mode(),
                    torch.autocast(device.type, dtype or torch.float32, enabled=dtype is not None),
                ):
                    return net(x)[0][:, 0].float()

            seconds, out = timed(run, device, repeats)
            row = {"precision": precision, "batch": batch, "ms_per_frame": 1000 * seconds / batch}
            image = out[0].cpu().numpy()
            if precision == "fp32" and reference is None:
                reference = image
            row["max_abs_vs_fp32"] = float(np.abs(image - reference).max())
            row["psnr_vs_fp32_db"] = psnr(image, reference) if row["max_abs_vs_fp32"] else None
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", default="250x400")
    parser.add_argument("--batches", default="1,8,32")
    parser.add_argument("--precisions", default="fp32,bf16,fp16")
    parser.add_argument("--models", default="", help="names, e.g. default,tiny (default: all)")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    height, width = (int(v) for v in args.size.split("x"))
    batches = [int(b) for b in args.batches.split(",")]
    precisions = args.precisions.split(",")
    if precisions[0] != "fp32":
        raise SystemExit("--precisions must start with fp32 (the reference)")
    windows = torch.from_numpy(simulated_windows(np.random.default_rng(0), height, width))
    windows = windows.to(device)
    wanted = set(filter(None, args.models.split(",")))
    result = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "size": args.size,
        "models": {},
    }
    for path in sorted(MODELS.glob("spk2img-*.pt")):
        name = path.stem.removeprefix("spk2img-")
        if wanted and name not in wanted:
            continue
        model = load_model(path).to(device)
        rows = measure(model, windows, device, precisions, batches, args.repeats, args.compile)
        result["models"][name] = rows
        for row in rows:
            print(name, json.dumps(row), flush=True)
        if args.json:  # after each network: a run stopped by its time limit keeps what it timed
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
