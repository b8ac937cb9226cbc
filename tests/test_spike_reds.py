"""The spike-REDS streams of SpikeZoo's package (spk2img.evaluation.spike_reds) and the script
that scores the shipped models on them: found by layout, read by the toolkit's protocol (the
middle 41 frames, truth = grey level / 255), scored like any window; on the real streams where
that package is installed."""

from __future__ import annotations

import importlib.util
import json
from datetime import date

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image
from script_loader import load_script

from spk2img.evaluation import spike_reds
from spk2img.evaluation.metrics import psnr
from spk2img.evaluation.scoring import commands_made, dates_made
from spk2img.evaluation.spike_reds import BenchmarkDataError, find_streams, load_window
from spk2img.io.spikes import read_spikes, write_spikes
from spk2img.runtime.classical import tfp

HEIGHT, WIDTH = 16, 24


def add_stream(root, split, name, frames, truth=True, seed=0):
    """``frames`` random spike frames of a scene at ``root/split/spike/name.dat`` and (with
    ``truth``) its 8-bit truth image beside, as the toolkit lays them out; the grey levels."""
    rng = np.random.default_rng(seed)
    grey = rng.integers(0, 256, (HEIGHT, WIDTH), np.uint8)
    spikes = (rng.random((frames, HEIGHT, WIDTH)) < 0.6 * grey / 255).astype(np.uint8)
    (root / split / "spike").mkdir(parents=True, exist_ok=True)
    write_spikes(root / split / "spike" / f"{name}.dat", spikes)
    if truth:
        (root / split / "gt").mkdir(parents=True, exist_ok=True)
        Image.fromarray(grey).save(root / split / "gt" / f"{name}.png")
    return grey


def test_streams_are_found_by_layout_and_read_by_the_toolkits_protocol(tmp_path):
    grey = add_stream(tmp_path, "test", "b_scene", 61)
    add_stream(tmp_path, "train", "a_scene", 45, seed=1)
    add_stream(tmp_path, "test", "no_truth", 61, truth=False)
    streams = find_streams(tmp_path)
    assert [(s.name, s.split) for s in streams] == [("a_scene", "train"), ("b_scene", "test")]
    spikes, truth = load_window(streams[1])
    whole = np.asarray(read_spikes(streams[1].spikes, HEIGHT, WIDTH))
    assert spikes.shape == (41, HEIGHT, WIDTH) and spikes.dtype == np.uint8
    assert np.array_equal(spikes, whole[30 - 20 : 30 + 21])  # the middle of 61 frames
    assert truth.dtype == np.float32 and np.array_equal(truth, grey / np.float32(255))
    add_stream(tmp_path, "test", "short", 40)
    with pytest.raises(BenchmarkDataError, match="40 frames, fewer than 41"):
        load_window(next(s for s in find_streams(tmp_path) if s.name == "short"))
    with pytest.raises(BenchmarkDataError, match="no <split>/spike/NAME.dat"):
        find_streams(tmp_path / "train" / "gt")


def test_the_script_scores_each_method_per_stream_and_keeps_what_it_is_asked_to(tmp_path, capsys):
    root = tmp_path / "data"
    add_stream(root, "test", "s1", 61, seed=2)
    add_stream(root, "train", "s2", 61, seed=3)
    out = {"json": tmp_path / "r.json", "md": tmp_path / "r.md"}
    files = ["--json", str(out["json"]), "--md", str(out["md"])]
    script = load_script("spike_reds_benchmark")
    assert script.main(["--root", str(root), "--models", "tiny", *files]) == 0
    results = json.loads(out["json"].read_text())
    assert results["streams"] == ["s1", "s2"] and list(results["methods"]) == [
        "TFP-41",
        "TFI",
        "tiny",
    ]
    spikes, truth = load_window(find_streams(root)[0])
    expected = psnr(np.clip(tfp(spikes, [20], 41)[0], 0, 1), truth)
    assert results["methods"]["TFP-41"]["per_stream"]["s1"][0] == pytest.approx(expected, abs=1e-3)
    tiny = results["methods"]["tiny"]
    assert tiny["psnr"] == pytest.approx(np.mean([v[0] for v in tiny["per_stream"].values()]))
    out["md"].write_text(out["md"].read_text() + "\n## Reading it\n\nA note.\n")
    out["json"].write_text(json.dumps(results | {"date": "2026-12-02 and 2026-12-04"}))
    args = ["--root", str(root), "--models", "", "--add", *files]
    assert script.main(args) == 0  # the classical rows again, tiny's kept, the note kept
    again = json.loads(out["json"].read_text())
    assert again["methods"]["tiny"] == tiny and "A note." in out["md"].read_text()
    assert again["date"] == dates_made("2026-12-02 and 2026-12-04")  # the earlier runs' dates kept
    assert again["date"].startswith("2026-12-02 and 2026-12-04")
    assert "| tiny |" in out["md"].read_text()
    assert script.main([*args, "--threads", "1"]) == 0  # the same command again: recorded once
    made_by = json.loads(out["json"].read_text())["command"].split(" && ")
    assert [c.split("--models ")[1].split(" ")[0] for c in made_by] == ["tiny", ""]
    assert script.main(["--root", str(tmp_path / "nothing"), *files]) == 2
    assert "no <split>/spike/NAME.dat" in capsys.readouterr().err


COMMANDS = ["a --add", "b --add", "c --x 1 --add", "a --add --x 2"]


@given(st.lists(st.sampled_from(COMMANDS), min_size=1))
def test_a_results_file_lists_each_command_it_was_made_by_once_in_the_order_first_run(runs):
    made_by = None
    for command in runs:
        made_by = commands_made(made_by, command)
    assert made_by.split(" && ") == list(dict.fromkeys(runs))


def test_a_results_file_lists_each_date_it_was_made_on_once_in_order():
    assert dates_made(None, date(2026, 12, 6)) == "2026-12-06"
    assert dates_made("2026-12-02 and 2026-12-04", date(2026, 12, 6)) == (
        "2026-12-02 and 2026-12-04 and 2026-12-06"
    )
    assert dates_made("2026-12-02 and 2026-12-04", date(2026, 12, 4)) == (
        "2026-12-02 and 2026-12-04"
    )


def test_without_the_toolkit_it_says_how_to_get_it(monkeypatch):
    monkeypatch.setattr(spike_reds.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(BenchmarkDataError, match="pip install --no-deps spikezoo==0.2.3.7"):
        spike_reds.toolkit_data_root()


@pytest.mark.skipif(
    importlib.util.find_spec("spikezoo") is None, reason="spikezoo (its data) not installed"
)
def test_the_toolkits_streams_fire_at_0_6_of_their_truths_grey_level():
    """The light convention of spike-REDS that docs/format.md states: the spike rate is
    0.6 x value / 255, no gamma undone (over each stream's whole length)."""
    for stream in find_streams(spike_reds.toolkit_data_root()):
        frames = np.asarray(read_spikes(stream.spikes, 250, 400))
        _, truth = load_window(stream)
        rate = frames.mean(0)
        assert len(frames) == 301
        assert rate.mean() == pytest.approx(0.6 * truth.mean(), rel=0.02)
