import dataclasses
import gzip
import json
from pathlib import Path

import pytest

from spk2img.errors import InputError
from spk2img.runtime.onnx_backend import graph_metadata, shipped_models
from spk2img.training.campaign import lineage, load_campaign, samples_before
from spk2img.training.campaign_report import curves_plot, hardware_name, markdown

REPO = Path(__file__).resolve().parents[1]
CPU = "a 2-core x86_64 CPU, 1 torch thread(s)"


def _write(state: Path, runs: dict[str, list[dict]], entries: dict) -> None:
    """A campaign folder: one metrics log per run and the campaign file."""
    state.mkdir(exist_ok=True)
    for name, records in runs.items():
        (state / name).mkdir()
        lines = [json.dumps(r | {"time": 1000.0 + i}) for i, r in enumerate(records)]
        (state / name / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    (state / "campaign.json").write_text(json.dumps({"runs": entries}))


def _train(step, wall_s):
    return {"kind": "train", "step": step, "wall_s": wall_s, "loss": 0.1}


def _val(step, ideal=None, real_video=None):
    record = {"kind": "val", "step": step, "psnr": 30.0}
    if ideal is not None:
        record["natural"] = {"psnr_ideal": ideal, "psnr_fitted": ideal - 8}
    if real_video is not None:
        record["real_video"] = {"psnr": real_video}
    return record


def _run_record(step, batch_size, patch=64, init=None):
    """A ``run`` record as training writes it; ``init``: ``(run, step)`` that --init loaded."""
    config = {"member": "tiny", "batch_size": batch_size, "patch": patch}
    init_from = (
        {"path": f"runs/{init[0]}/last.pt", "run": init[0], "step": init[1]} if init else None
    )
    return {
        "kind": "run",
        "step": step,
        "train_config": config,
        "hardware": CPU,
        "init_from": init_from,
    }


@pytest.fixture
def campaign(tmp_path):
    """root (settings and start in the campaign file, batch 8) -> child (its own run record,
    batch 16; resumed once) -> grandchild (batch 4, no entry in the campaign file)."""
    runs = {
        "root": [_train(100, 50.0), _val(100, ideal=30.0), _train(200, 100.0), _val(200, 31.0)],
        "child": [
            _run_record(0, 16, init=("root", 150)),
            _train(30, 20.0),
            _run_record(30, 16, init=("root", 150)),  # resumed: the steps and wall time go on
            _train(60, 40.0),
            _val(60, ideal=32.0, real_video=28.0),
        ],
        "grandchild": [_run_record(0, 4, patch=32, init=("child", 50)), _train(10, 1.0)],
    }
    entries = {
        "root": {
            "init": None,
            "settings": {"member": "tiny", "batch_size": 8, "patch": 48, "hardware": CPU},
        },
        "child": {"shipped": "tiny"},
    }
    _write(tmp_path, runs, entries)
    return tmp_path


def test_runs_count_their_steps_windows_and_optimiser_time(campaign):
    runs = load_campaign(campaign)
    root, child, grandchild = runs["root"], runs["child"], runs["grandchild"]
    assert (root.steps, root.samples, root.wall_s) == (200, 1600, 100.0)
    assert root.samples_per_s == pytest.approx(16.0)
    # a resumed run: its last train record holds the steps and the optimiser time in all
    assert (child.steps, child.samples, child.wall_s) == (60, 960, 40.0)
    assert child.settings.batch_size == 16 and child.shipped == "tiny"
    assert grandchild.settings.patch == 32 and grandchild.init == ("child", 50)
    expected = {"natural_ideal": 32.0, "natural_fitted": 24.0, "real_video": 28.0}
    assert [(v.step, v.psnr) for v in child.validations] == [(60, expected)]
    assert root.validations[0].psnr == {"natural_ideal": 30.0, "natural_fitted": 22.0}


def test_a_finished_runs_compressed_log_reads_as_the_log_itself_and_two_logs_are_refused(campaign):
    """gzip -9n on a finished run's metrics.jsonl (to save room) changes nothing the campaign
    reads; a run with both logs is an input error naming them, not one of them picked."""
    before = load_campaign(campaign)
    log = campaign / "child" / "metrics.jsonl"
    compressed = gzip.compress(log.read_bytes(), 9, mtime=0)
    (campaign / "child" / "metrics.jsonl.gz").write_bytes(compressed)
    with pytest.raises(InputError, match="child has two metrics logs: metrics.jsonl and metrics"):
        load_campaign(campaign)
    log.unlink()
    assert load_campaign(campaign) == before


def test_a_run_resumed_in_other_arithmetic_or_on_a_gpu_names_each_hardware_in_order(tmp_path):
    """The settings come from the first run record, the hardware from every one (repeats once):
    the report's short names say fp32 CPU, then bf16 CPU (once, with or without the CPU's model
    in its words), then the GPU."""
    bf16 = f"{CPU}, bf16 autocast"
    gpu = "NVIDIA H200 (CUDA, bf16 autocast)"
    records = [_run_record(0, 8), _train(10, 5.0), _run_record(10, 8), _train(20, 9.0)]
    records += [_run_record(20, 8) | {"hardware": bf16}, _train(30, 11.0)]
    named = "a 2-core Intel(R) Xeon(R) Processor (AMX bf16) CPU, 1 torch thread(s), bf16 autocast"
    records += [_run_record(25, 8) | {"hardware": named}, _train(30, 11.0)]  # the same, named
    records += [_run_record(30, 8) | {"hardware": gpu}, _train(40, 11.5)]
    _write(tmp_path, {"r": records}, {})
    (run,) = load_campaign(tmp_path).values()
    assert run.settings.on_gpu and (run.steps, run.wall_s) == (40, 11.5)
    expected = "CPU, 1 thread; then CPU, 1 thread, bf16; then NVIDIA H200"
    assert hardware_name(run.settings) == expected
    two = "a 2-core x86_64 CPU, 2 torch thread(s), bf16 autocast"
    assert hardware_name(dataclasses.replace(run.settings, hardware=two)) == "CPU, 2 threads, bf16"


def test_a_lineage_counts_the_windows_its_ancestors_saw_up_to_where_each_child_started(campaign):
    runs = load_campaign(campaign)
    assert lineage(runs, "grandchild") == ["root", "child", "grandchild"]
    assert samples_before(runs, "root") == 0
    assert samples_before(runs, "child") == 150 * 8
    assert samples_before(runs, "grandchild") == 150 * 8 + 50 * 16


def test_the_report_sums_each_member_and_hardware_and_keeps_hand_written_sections(campaign):
    runs = load_campaign(campaign)
    md, figure = campaign / "campaign.md", campaign / "images" / "curves.png"
    md.write_text("# Training campaign\n\nold\n\n## Runs\n\nold table\n\n## Notes\n\nkept\n")
    text = markdown(runs, campaign, figure, md, "the command")
    lines = text.splitlines()
    # one member on one hardware: 3 runs, 200 + 60 + 10 steps, 1600 + 960 + 40 windows
    assert "| tiny | CPU, 1 thread | 3 | 270 | 2,600 |" in text
    child = next(line for line in lines if line.startswith("| `child`"))
    assert "`root` @ 150" in child and "| 960 |" in child and "32.00 → 32.00 (32.00)" in child
    assert "`tiny`" in child  # what shipped from it
    order = [line.split("`")[1] for line in lines if line.startswith("| `")]
    assert order == ["root", "child", "grandchild"]
    assert "old table" not in text and text.rstrip().endswith("## Notes\n\nkept")
    assert "](images/curves.png)" in text
    curves_plot(runs, figure)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_every_run_must_say_how_it_trained_and_what_it_started_from(tmp_path):
    entry = {
        "init": None,
        "settings": {"member": "tiny", "batch_size": 8, "patch": 48, "hardware": CPU},
    }
    _write(tmp_path / "a", {"r1": [_train(1, 1.0)], "r2": [_train(1, 1.0)]}, {"r1": entry})
    with pytest.raises(InputError, match="r2: no run record in its log and no settings"):
        load_campaign(tmp_path / "a")
    older = _run_record(0, 8) | {"init_from": {"path": "x.pt", "step": 3}}  # no run named
    _write(tmp_path / "f", {"r1": [older, _train(1, 1.0)]}, {})
    with pytest.raises(InputError, match="r1: neither its log nor"):
        load_campaign(tmp_path / "f")
    _write(tmp_path / "b", {"r1": [_train(1, 1.0)]}, {"r1": entry, "gone": entry})
    with pytest.raises(InputError, match="without a metrics log: gone"):
        load_campaign(tmp_path / "b")
    orphan = entry | {"init": {"run": "nowhere", "step": 5}}
    _write(tmp_path / "c", {"r1": [_train(1, 1.0)]}, {"r1": orphan})
    with pytest.raises(InputError, match="starts from nowhere"):
        load_campaign(tmp_path / "c")
    _write(tmp_path / "d", {"r1": [_train(1, 1.0)]}, {"r1": {"init": None}})
    with pytest.raises(InputError, match="no settings"):
        load_campaign(tmp_path / "d")
    circle = {
        "r1": entry | {"init": {"run": "r2", "step": 1}},
        "r2": entry | {"init": {"run": "r1", "step": 1}},
    }
    _write(tmp_path / "e", {"r1": [_train(1, 1.0)], "r2": [_train(1, 1.0)]}, circle)
    with pytest.raises(InputError, match="circle"):
        lineage(load_campaign(tmp_path / "e"), "r1")


def test_the_committed_campaign_covers_every_kept_run_and_names_shipped_models():
    """Every run in training_state/ has its settings and its start; each lineage begins with a
    run from scratch; what the campaign says shipped is a shipped model of the same member."""
    runs = load_campaign(REPO / "training_state")
    members = {name: graph_metadata(path)["member"] for name, path in shipped_models().items()}
    for name, run in runs.items():
        assert run.settings.batch_size > 0 and run.steps > 0, name
        assert runs[lineage(runs, name)[0]].init is None
        if run.shipped:
            assert members[run.shipped] == run.settings.member, name
        if run.init:
            parent = runs[run.init[0]]
            assert run.init[1] <= parent.steps, name  # started from a step its parent reached
    assert {run.shipped for run in runs.values() if run.shipped} == set(members)
