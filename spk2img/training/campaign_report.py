"""The training campaign as a document: docs/training_campaign.md and its figure.

``python -m spk2img.training.campaign_report [--state-dir training_state] [--md
docs/training_campaign.md] [--figure docs/images/training_campaign.png]`` reads every run of
``--state-dir`` (:func:`spk2img.training.campaign.load_campaign`: the runs' metrics logs and
campaign.json) and writes, per member and hardware, the steps, windows, optimiser hours and
windows per second; per run, the same with what it started from and its first, last and best
validation; and the validation curves of every lineage against the windows its network has
seen. The sections (``## ...``) written below the generated ones in ``--md`` are kept.
"""

from __future__ import annotations

import argparse
import datetime
from collections import defaultdict
from pathlib import Path

from spk2img.markdown import table_head, table_row
from spk2img.model.config import MEMBERS

from .campaign import THEN, VALIDATIONS, Run, RunSettings, lineage, load_campaign, samples_before

GENERATED = ("# Training campaign", "## By member and hardware", "## Runs", "## Curves")
METRIC_LABELS = {name: f"{words} (dB)" for name, (_, _, words) in VALIDATIONS.items()}
MEMBER_ORDER = tuple(MEMBERS)  # largest first


def hardware_name(settings: RunSettings) -> str:
    """A short name of a run's hardware: the GPU's, or ``CPU, N thread(s)`` (and ``, bf16``
    for bf16 autocast on the CPU); each of a run resumed on other hardware, in order (once)."""
    return THEN.join(dict.fromkeys(map(_short_hardware, settings.hardware.split(THEN))))


def _short_hardware(words: str) -> str:
    """:func:`hardware_name` of one hardware as training describes it."""
    if "CUDA" in words:
        return words.split(" (")[0]
    threads = int(words.split(" torch thread")[0].rsplit(" ", 1)[1])
    bf16 = ", bf16" if words.endswith("bf16 autocast") else ""
    return f"CPU, {threads} thread{'s' if threads > 1 else ''}{bf16}"


def lineage_order(runs: dict[str, Run]) -> list[str]:
    """Runs grouped by member, each run after the run it started from and the runs that
    started from it before its next sibling (siblings in the order they started)."""

    def key(name: str) -> tuple:
        member = runs[name].settings.member
        return (MEMBER_ORDER.index(member), *(runs[r].started for r in lineage(runs, name)))

    return sorted(runs, key=key)


def summary_table(runs: dict[str, Run]) -> list[str]:
    groups: dict[tuple[str, str], list[Run]] = defaultdict(list)
    for run in runs.values():
        groups[(run.settings.member, hardware_name(run.settings))].append(run)
    lines = table_head(
        ["member", "hardware", "runs", "steps", "windows", "Mpx", "optimiser h", "windows/s"]
    )
    for (member, hardware), group in sorted(
        groups.items(), key=lambda item: (MEMBER_ORDER.index(item[0][0]), item[0][1])
    ):
        samples = sum(r.samples for r in group)
        hours = sum(r.wall_s for r in group) / 3600
        lines.append(
            table_row(
                [
                    member,
                    hardware,
                    len(group),
                    f"{sum(r.steps for r in group):,}",
                    f"{samples:,}",
                    f"{sum(megapixels(r) for r in group):,.0f}",
                    f"{hours:.2f}",
                    f"{samples / (hours * 3600):.1f}",
                ]
            )
        )
    return lines


def megapixels(run: Run) -> float:
    """Millions of training pixels: windows x patch side squared."""
    return run.samples * run.settings.patch**2 / 1e6


def curve_cell(run: Run, metric: str) -> str:
    """``first → last (best)`` of a validation metric of ``run``, or a dash."""
    values = [v.psnr[metric] for v in run.validations if metric in v.psnr]
    if not values:
        return "—"
    return f"{values[0]:.2f} → {values[-1]:.2f} ({max(values):.2f})"


def runs_table(runs: dict[str, Run]) -> list[str]:
    lines = table_head(
        [
            "run",
            "member",
            "hardware",
            "batch x patch",
            "started from",
            "steps",
            "windows",
            "optimiser h",
            "windows/s",
            *(f"{label}: first → last (best)" for label in METRIC_LABELS.values()),
            "shipped as",
        ]
    )
    for name in lineage_order(runs):
        run = runs[name]
        s = run.settings
        lines.append(
            table_row(
                [
                    f"`{name}`",
                    s.member,
                    hardware_name(s),
                    f"{s.batch_size} x {s.patch}²",
                    f"`{run.init[0]}` @ {run.init[1]:,}" if run.init else "scratch",
                    f"{run.steps:,}",
                    f"{run.samples:,}",
                    f"{run.wall_s / 3600:.2f}",
                    f"{run.samples_per_s:.1f}",
                    *(curve_cell(run, metric) for metric in METRIC_LABELS),
                    f"`{run.shipped}`" if run.shipped else "",
                ]
            )
        )
    return lines


def curves_plot(runs: dict[str, Run], path: Path) -> None:
    """Each metric of :data:`METRIC_LABELS` (one panel each) of every run against the windows its
    network had seen (its ancestors' included), coloured by member; GPU runs drawn thicker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRIC_LABELS), figsize=(19, 5.5), dpi=120, squeeze=False)
    colours = {member: f"C{i}" for i, member in enumerate(MEMBER_ORDER)}
    order = lineage_order(runs)
    for ax, (metric, label) in zip(axes[0], METRIC_LABELS.items(), strict=True):
        for name in order:
            run = runs[name]
            before = samples_before(runs, name)
            points = [
                (before + v.step * run.settings.batch_size, v.psnr[metric])
                for v in run.validations
                if metric in v.psnr
            ]
            if not points:
                continue
            gpu = run.settings.on_gpu
            ax.plot(
                *zip(*points, strict=True),
                color=colours[run.settings.member],
                linewidth=2.5 if gpu else 1.0,
                marker="o" if gpu else ".",
                markersize=4,
            )
            if run.shipped:
                x, y = max(points, key=lambda p: p[1])
                ax.annotate(run.shipped, (x, y), textcoords="offset points", xytext=(4, 4))
        ax.set_xlabel("training windows seen by the network (its ancestors' included)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    for member, colour in colours.items():
        if any(r.settings.member == member for r in runs.values()):
            axes[0][0].plot([], [], color=colour, label=member)
    axes[0][0].plot([], [], color="0.3", linewidth=2.5, marker="o", label="on a GPU")
    axes[0][0].legend(loc="lower right", fontsize=8)
    axes[0][0].set_title("Validation along every lineage of runs", loc="left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def kept_sections(md: Path) -> list[str]:
    """The ``## ...`` sections of an existing ``md`` that this script does not write."""
    if not md.is_file():
        return []
    sections, current = [], None
    for line in md.read_text().splitlines():
        if line.startswith("#"):
            current = None if line.startswith(GENERATED) else [line]
            if current is not None:
                sections.append(current)
        elif current is not None:
            current.append(line)
    return ["\n".join(s).rstrip() for s in sections]


def markdown(runs: dict[str, Run], state_dir: Path, figure: Path, md: Path, command: str) -> str:
    gpu = [r for r in runs.values() if r.settings.on_gpu]
    lines = [
        "# Training campaign",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()} from the metrics logs of "
        f"the {len(runs)} runs in `{state_dir}/` and its `campaign.json` (what each run started "
        "from). Windows: training windows seen (steps x batch); Mpx: windows x patch side²; "
        "optimiser h: the time of the training steps alone (validations and checkpoints left "
        "out). The CPU runs ran on one or two cores of a 2-core machine, most of them beside "
        f"other work; the {len(gpu)} GPU runs on lent GPUs, 15 minutes a lease. Every run's "
        "command and what it showed: training_state/README.md.",
        "",
        "## By member and hardware",
        "",
        *summary_table(runs),
        "",
        "## Runs",
        "",
        "Grouped by member and by the run from scratch each descends from. Validation: the "
        "natural validation (66 held-out scenes) filmed noise-free and by the fitted sensor, "
        "and the real-video "
        "validation's 96x128 crops (38 windows of 19 held-out real clips; runs from before it "
        "existed show a dash); the best of each is the highest logged, not always the "
        "checkpoint chosen.",
        "",
        *runs_table(runs),
        "",
        "## Curves",
        "",
        f"![validation along every lineage]({figure.relative_to(md.parent).as_posix()})",
        "",
        "Each line is a run, starting where the run it started from had got to. Thick lines "
        "with round markers: runs on a GPU.",
        "",
    ]
    return "\n".join(lines + [s + "\n" for s in kept_sections(md)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--state-dir", type=Path, default=Path("training_state"))
    parser.add_argument("--md", type=Path, default=Path("docs/training_campaign.md"))
    parser.add_argument("--figure", type=Path, default=Path("docs/images/training_campaign.png"))
    args = parser.parse_args()
    runs = load_campaign(args.state_dir)
    curves_plot(runs, args.figure)
    command = "python -m spk2img.training.campaign_report"
    args.md.write_text(markdown(runs, args.state_dir, args.figure, args.md, command))
    print(f"wrote {args.md} and {args.figure} ({len(runs)} runs)")


if __name__ == "__main__":
    main()
