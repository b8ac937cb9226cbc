"""The training campaign: every run's settings, samples, optimiser time and validation curve.

Read from the runs' metrics logs (``training_state/NAME/metrics.jsonl``, or
``metrics.jsonl.gz`` for a finished run's, gzip-compressed to save room) and the campaign file
(``training_state/campaign.json``). A run logs its settings (member, batch, patch, hardware) and
what ``--init`` loaded (the run that wrote it and its step) in a ``run`` record at every
(re)start; the campaign file says the same for the runs logged before that record existed
(``settings``; ``init``: a run and its step, or ``null`` for a run from scratch), and what
shipped from a run (``shipped``: a shipped model's name). An entry's ``init`` overrides the
log's.

A run's samples are its steps times its batch; its time is the optimiser's (``wall_s``, the
training steps alone: validation and checkpoints left out). A lineage is a run with the runs it
started from: its samples before a run are the samples of its ancestors up to the step each
child started from.
"""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from pathlib import Path

from spk2img.errors import InputError

CAMPAIGN_FILE = "campaign.json"
LOG_NAMES = ("metrics.jsonl", "metrics.jsonl.gz")
"""A run's metrics log: as training writes it, or gzip-compressed once the run is finished."""


THEN = "; then "
"""What joins the hardware of a run resumed on other hardware (:class:`RunSettings`)."""


def run_hardware(starts: list[dict]) -> str:
    """The hardware of a run's ``run`` records (``metrics.jsonl``, in order): each distinct
    one once, in the order they trained, joined by :data:`THEN`."""
    return THEN.join(dict.fromkeys(r["hardware"] for r in starts))


@dataclass(frozen=True)
class RunSettings:
    """What trained a run: the family ``member``, windows per step, patch side (px), hardware
    (training's words for it; a run resumed on other hardware or in other arithmetic lists
    each, in order, joined by :data:`THEN`)."""

    member: str
    batch_size: int
    patch: int
    hardware: str

    @property
    def on_gpu(self) -> bool:
        """Whether a GPU trained the run (training's hardware words name CUDA)."""
        return "CUDA" in self.hardware


VALIDATIONS = {
    "natural_ideal": ("natural", "psnr_ideal", "natural validation, noise-free"),
    "natural_fitted": ("natural", "psnr_fitted", "natural validation, fitted sensor"),
    "real_video": ("real_video", "psnr", "real-video validation crops"),
}
"""The validations a campaign follows: name -> where a ``val`` record keeps its PSNR (dB)
(section, field) and what it is in words: the natural validation's noise-free and
fitted-sensor regimes, the real-video crops."""


@dataclass(frozen=True)
class Validation:
    """One validation of a run at ``step``: PSNR (dB) by the names of :data:`VALIDATIONS`, of
    those the run measured."""

    step: int
    psnr: dict[str, float]


@dataclass(frozen=True)
class Run:
    """One training run: its settings, when it started (Unix time of its first record), what it
    started from (``(run, step)`` or ``None``), the steps it reached, its optimiser time (s),
    its validations and what shipped from it."""

    name: str
    settings: RunSettings
    started: float
    init: tuple[str, int] | None
    steps: int
    wall_s: float
    validations: tuple[Validation, ...]
    shipped: str | None = None

    @property
    def samples(self) -> int:
        """Training windows seen: steps x batch."""
        return self.steps * self.settings.batch_size

    @property
    def samples_per_s(self) -> float:
        """Windows per second of optimiser time (0 for a run without a logged step)."""
        return self.samples / self.wall_s if self.wall_s else 0.0


def read_run(name: str, records: list[dict], entry: dict) -> Run:
    """The :class:`Run` ``name`` from its metrics ``records`` (``metrics.jsonl``, in order) and
    its ``entry`` of the campaign file (``{}`` for none); settings from its first ``run``
    record (the hardware from all of them), else from the entry; its start from the entry,
    else from that record (an input error where neither says)."""
    starts = [r for r in records if r["kind"] == "run"]
    logged = starts[0] if starts else None
    if logged is not None:
        tc = logged["train_config"]
        settings = RunSettings(tc["member"], tc["batch_size"], tc["patch"], run_hardware(starts))
    elif "settings" in entry:
        settings = RunSettings(**entry["settings"])
    else:
        raise InputError(f"run {name}: no run record in its log and no settings in {CAMPAIGN_FILE}")
    if "init" in entry:
        init = entry["init"]
    elif logged is not None and (logged["init_from"] is None or logged["init_from"].get("run")):
        init = logged["init_from"]
    else:
        raise InputError(
            f"run {name}: neither its log nor {CAMPAIGN_FILE} says what it started from"
        )
    trained = [r for r in records if r["kind"] == "train"]
    validations = tuple(
        Validation(
            r["step"],
            {
                key: r[section][field]
                for key, (section, field, _) in VALIDATIONS.items()
                if field in r.get(section, {})
            },
        )
        for r in records
        if r["kind"] == "val"
    )
    return Run(
        name=name,
        settings=settings,
        started=next((r["time"] for r in records if "time" in r), 0.0),
        init=(init["run"], int(init["step"])) if init else None,
        steps=trained[-1]["step"] if trained else 0,
        wall_s=trained[-1]["wall_s"] if trained else 0.0,
        validations=validations,
        shipped=entry.get("shipped"),
    )


def run_log(run_dir: Path) -> Path | None:
    """The metrics log in ``run_dir`` (one of :data:`LOG_NAMES`), ``None`` where it has none; an
    input error for a run with both, which would say two things."""
    found = [run_dir / name for name in LOG_NAMES if (run_dir / name).is_file()]
    if len(found) > 1:
        names = " and ".join(path.name for path in found)
        raise InputError(f"run {run_dir.name} has two metrics logs: {names}")
    return found[0] if found else None


def metrics_logs(state_dir: Path) -> dict[str, Path]:
    """Each run's metrics log in ``state_dir`` (:func:`run_log` of ``state_dir/NAME/``), by run
    name, for the runs that have one."""
    logs = {d.name: run_log(d) for d in sorted(state_dir.iterdir()) if d.is_dir()}
    return {name: log for name, log in logs.items() if log is not None}


def read_records(path: Path) -> list[dict]:
    """The records of a metrics log (``.jsonl``, or ``.jsonl.gz`` compressed), in order."""
    data = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
    return [json.loads(line) for line in data.decode().splitlines() if line.strip()]


def load_campaign(state_dir: Path) -> dict[str, Run]:
    """Every run of ``state_dir`` (a folder holding ``campaign.json`` and one folder with a
    ``metrics.jsonl`` per run), by name; an input error for a run whose settings or start
    neither its log nor the campaign file gives, an entry without a log, or a start naming no
    run."""
    entries = json.loads((state_dir / CAMPAIGN_FILE).read_text())["runs"]
    logs = metrics_logs(state_dir)
    unlogged = sorted(set(entries) - set(logs))
    if unlogged:
        raise InputError(f"{CAMPAIGN_FILE} lists runs without a metrics log: {', '.join(unlogged)}")
    runs = {}
    for name, path in logs.items():
        runs[name] = read_run(name, read_records(path), entries.get(name, {}))
    for run in runs.values():
        if run.init and run.init[0] not in runs:
            raise InputError(f"run {run.name} starts from {run.init[0]}, which is not a run")
    return runs


def lineage(runs: dict[str, Run], name: str) -> list[str]:
    """``name`` and the runs it started from, the first (from scratch) first."""
    chain = [name]
    while (init := runs[chain[-1]].init) is not None:
        if init[0] in chain:
            raise InputError(f"runs {' -> '.join(chain)} start from each other in a circle")
        chain.append(init[0])
    return chain[::-1]


def samples_before(runs: dict[str, Run], name: str) -> int:
    """Training windows the network of run ``name`` had seen before its step 0: its ancestors'
    steps up to where each child started, times their batch."""
    chain = lineage(runs, name)
    total = 0
    for parent, child in zip(chain, chain[1:], strict=False):
        total += runs[child].init[1] * runs[parent].settings.batch_size
    return total
