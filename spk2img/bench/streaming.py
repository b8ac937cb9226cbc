"""The streaming benchmark, written to ``bench_streaming.json`` and ``bench_streaming.md``:

- block reuse: a long simulated stream reconstructed at every 7th frame, each window run whole
  against each 13-frame block encoded once, side by side, each in its own fresh process;
- quality tiers: ``best``, ``balanced`` and ``fast`` (:mod:`spk2img.runtime.adaptive`) on every
  window of the benchmark set, time and PSNR/SSIM per scene class.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .cases import SCENE_CLASSES, BenchSet
from .scores import quality
from .worker import WorkerError, run_job

MD_NAME, JSON_NAME = "bench_streaming.md", "bench_streaming.json"
WORKER_TIMEOUT_S = 3600


def stream_benchmark(
    model: Path,
    stream: Path,
    threads: tuple[int, ...],
    work: Path,
    log: Callable[[str], None],
) -> dict:
    """Time the ONNX ``model`` (with its block graphs beside it) on the spike stream saved at
    ``stream`` (``(frames, h, w)`` uint8 .npy) at every ``block_stride``-th centre of its geometry
    (7 for the shipped models), whole and with block reuse, at each thread count; with the outputs'
    largest difference and the MAC ratio."""
    from spk2img.model.checkpoint import config_from_dict
    from spk2img.model.complexity import count_macs, count_stream_macs
    from spk2img.runtime.onnx_backend import graph_metadata

    frames, height, width = np.load(stream, mmap_mode="r").shape
    metadata = graph_metadata(model)
    name = metadata.get("name", model.stem)
    config = config_from_dict(json.loads(metadata["config"]))
    encoder, head = count_stream_macs(config, height, width)
    whole_macs = count_macs(config, height, width)
    rows = []
    for t in threads:
        runs, images = {}, {}
        for mode in ("whole", "reuse"):
            spec = {
                "job": "stream",
                "model": str(model),
                "mode": mode,
                "threads": [t],
                "spikes": str(stream),
                "stride": config.block_stride,
                "outputs": str(work / f"{mode}.npy"),
            }
            try:
                runs[mode] = run_job(spec, WORKER_TIMEOUT_S)
            except WorkerError as exc:
                runs[mode] = {"error": str(exc)}
                continue
            images[mode] = np.load(work / f"{mode}.npy")
            log(
                f"stream of {name}, {mode}, {t} thread(s): {runs[mode]['seconds']:.1f} s for "
                f"{runs[mode]['outputs']} frames"
            )
        row = {"threads": t, **{mode: run for mode, run in runs.items()}}
        if len(images) == 2:
            row["ratio"] = runs["reuse"]["seconds"] / runs["whole"]["seconds"]
            row["max_abs_diff"] = float(np.abs(images["reuse"] - images["whole"]).max())
        rows.append(row)
    return {
        "model": name,
        "member": metadata.get("member"),
        "graph": metadata.get("graph"),
        "frames": frames,
        "height": height,
        "width": width,
        "stride": config.block_stride,
        "macs": {"whole": whole_macs, "encoder": encoder, "head": head},
        "mac_ratio": (encoder + head) / whole_macs,
        "rows": rows,
    }


def tiers_benchmark(
    model: Path, cases: BenchSet, threads: tuple[int, ...], work: Path, log: Callable[[str], None]
) -> dict:
    """Each quality tier on every window of ``cases`` at each thread count (fresh processes):
    median ms per scene class, the balanced tier's network share, and PSNR/SSIM."""
    cases_dir = cases.save_spikes(work / "tier-cases")
    height, width = cases.truth.shape[1:]
    result: dict = {
        "threads": list(threads),
        "size": f"{height}x{width}",
        "per_class": len(cases) // len(SCENE_CLASSES),
        "tiers": {},
    }
    for t in threads:
        out = work / f"tiers-{t}"
        out.mkdir(exist_ok=True)
        spec = {
            "job": "tiers",
            "model": str(model),
            "threads": [t],
            "cases": str(cases_dir),
            "outputs": str(out),
        }
        try:
            run = run_job(spec, WORKER_TIMEOUT_S)
        except WorkerError as exc:
            return {"error": str(exc)}
        for tier, seconds in run["seconds"].items():
            entry = result["tiers"].setdefault(tier, {"ms": {}})
            per_class = by_class(seconds, cases.classes)
            entry["ms"][str(t)] = {name: 1000 * float(np.median(s)) for name, s in per_class}
            entry["quality"] = quality(np.load(out / f"{tier}.npy"), cases)
        shares = by_class(run["balanced_share"], cases.classes)
        result["balanced_share"] = {name: float(np.mean(s)) for name, s in shares}
        log(
            f"quality tiers, {t} thread(s): "
            + ", ".join(
                f"{tier} {np.median(s) * 1000:.0f} ms" for tier, s in run["seconds"].items()
            )
        )
    return result


def by_class(values: list[float], classes: list[str]) -> list[tuple[str, list[float]]]:
    """``(scene class, the values of its cases)`` for each class of :data:`SCENE_CLASSES`."""
    pairs = list(zip(values, classes, strict=True))
    return [(name, [v for v, c in pairs if c == name]) for name in SCENE_CLASSES]


def write_streaming_report(results: dict, out_dir: Path) -> list[Path]:
    """Write ``bench_streaming.json`` and ``bench_streaming.md`` into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / JSON_NAME, out_dir / MD_NAME]
    paths[0].write_text(json.dumps(results, indent=1) + "\n")
    paths[1].write_text(streaming_markdown(results))
    return paths


def streaming_markdown(results: dict) -> str:
    """``bench_streaming.md``: the command, the machine and the block-reuse table of every
    streamed model."""
    streamed = [s for s in results["streaming"] if "error" not in s]
    first = streamed[0]
    lines = [
        "# Benchmarks: streaming with block-feature reuse",
        "",
        f"Generated by `{results['command']}` on {results['date']}. Machine: "
        f"{results['machine']['cpu']}, {results['machine']['cores_available']} cores.",
        "",
        f"A {first['frames']}-frame {first['height']}x{first['width']} simulated stream (fast "
        f"motion, real-like sensor) reconstructed at every {first['stride']}th centre by each "
        "shipped model below through onnxruntime, two ways, each in a fresh process after one "
        "warm-up call: **whole** runs the one-shot graph on every 41-frame window; **reuse** "
        "encodes each 13-frame block once with the encoder graph and runs only the "
        "align-and-fuse head per centre (`spk2img.runtime.block_stream`). Times are the wall "
        "time of the whole stream (one run each, side by side in one bench run); **ms per "
        "output** is that time over the frames out, the cost of one frame of a long stream "
        "(docs/bench.md times one window alone).",
        "",
        "| model | threads | frames out | whole (s) | reuse (s) | ms per output whole / reuse "
        "| reuse / whole | blocks encoded | max abs diff | peak RSS whole / reuse (MiB) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in streamed:
        model = f"`{s['model']}` (`{s['member']}`, {s['graph']})"
        for row in s["rows"]:
            if "ratio" not in row:
                errors = "; ".join(row[m].get("error", "") for m in ("whole", "reuse") if m in row)
                lines.append(f"| {model} | {row['threads']} | failed: {errors} | | | | | | | |")
                continue
            whole, reuse = row["whole"], row["reuse"]
            per_output = [1000 * r["seconds"] / r["outputs"] for r in (whole, reuse)]
            lines.append(
                f"| {model} | {row['threads']} | {whole['outputs']} | {whole['seconds']:.1f} | "
                f"{reuse['seconds']:.1f} | {' / '.join(_ms(ms) for ms in per_output)} | "
                f"**{row['ratio']:.2f}** | {reuse['blocks_encoded']} "
                f"(vs {5 * whole['outputs']} whole) | {row['max_abs_diff']:.1e} | "
                f"{whole['peak_rss_mib']:.0f} / {reuse['peak_rss_mib']:.0f} |"
            )
    lines += ["", f"Multiply-accumulates per output at {first['height']}x{first['width']}:", ""]
    for s in streamed:
        macs = s["macs"]
        lines.append(
            f"- `{s['model']}`: whole {macs['whole'] / 1e9:.1f} G; reuse "
            f"{macs['encoder'] / 1e9:.1f} G (one block encoded) + {macs['head'] / 1e9:.1f} G "
            f"(align and fuse) = {s['mac_ratio']:.2f} of whole."
        )
    lines += [
        "",
        "The head — pyramid deformable alignment of four neighbours to a key that changes with "
        "every output, and the fusion — cannot be shared between outputs with equal results, "
        "so it bounds what reuse can save (`spk2img models` lists that ratio for every "
        "member); the time ratio also counts the bilinear sampling of the deformable convs, "
        "which sits in the head and which the MAC count leaves out.",
        "",
        *(
            f"Not streamed: `{s['model']}`: {s['error']}."
            for s in results["streaming"]
            if "error" in s
        ),
        "",
        tiers_markdown(results.get("tiers")),
    ]
    return "\n".join(lines)


def tiers_markdown(tiers: dict | None) -> str:
    """The quality tiers' table: ms/frame and PSNR/SSIM per scene class."""
    if tiers is None:
        return ""
    if "error" in tiers:
        return f"## Quality tiers\n\nNot measured: {tiers['error']}\n"
    classes = list(SCENE_CLASSES)
    threads = [str(t) for t in tiers["threads"]]
    lines = [
        "## Quality tiers (`quality=best|balanced|fast`)",
        "",
        f"Every 41-frame window of the benchmark set of `docs/bench.md` ({tiers['size']}, "
        f"{tiers['per_class']} per scene class, ideal and real-like sensors) through the "
        "shipped default's ONNX graph, one "
        "window at a time, each tier timed on each window in one process per thread count "
        "(after a warm-up call). Cells: median ms/frame at "
        f"{' / '.join(threads)} thread(s); PSNR dB / SSIM against the ground truth. "
        "`balanced` runs the network only on the bounding box of the 16x16 tiles whose light "
        "moves or is dim (plus 16 px of context) and TFP-41 elsewhere; `fast` is TFP-41.",
        "",
        "| tier | " + " | ".join(classes) + " | all: PSNR / SSIM |",
        "| --- | " + " | ".join("---" for _ in classes) + " | --- |",
    ]
    for tier, entry in tiers["tiers"].items():
        q = entry["quality"]
        cells = [
            " / ".join(_ms(entry["ms"][t][name]) for t in threads)
            + f" ms; {q['classes'][name]['psnr']:.2f} / {q['classes'][name]['ssim']:.3f}"
            for name in classes
        ]
        lines.append(f"| {tier} | " + " | ".join(cells) + f" | {q['psnr']:.2f} / {q['ssim']:.3f} |")
    share = tiers["balanced_share"]
    lines += [
        "",
        "Share of the pixels the `balanced` tier ran the network on (context included): "
        + ", ".join(f"{name} {share[name]:.0%}" for name in classes)
        + ".",
        "",
    ]
    return "\n".join(lines)


def _ms(value: float) -> str:
    return f"{value:,.0f}" if value >= 10 else f"{value:.2f}"
