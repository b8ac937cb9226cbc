"""``spk2img reconstruct`` keeps its frames as they come (spk2img.io.frame_store): a run
interrupted by Ctrl-C or SIGTERM keeps every finished frame (arrays and PNGs) and ``--resume``
continues it to the frames of an uninterrupted run; runs that would mix arguments are refused."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from spk2img.cli import main
from spk2img.clients import Client
from spk2img.io import frame_store
from spk2img.io.frame_store import FrameStore, partial_dir
from spk2img.io.spikes import write_spikes
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import SensorConfig, simulate

H, W = 24, 32


@pytest.fixture(scope="module")
def stream(tmp_path_factory):
    rng = np.random.default_rng(4)
    spikes = simulate(random_scene(rng, H, W, "fast", "normal"), 300, SensorConfig.real(), rng)
    path = tmp_path_factory.mktemp("stream") / "s.npy"
    write_spikes(path, spikes)
    return path


@pytest.fixture(autouse=True)
def ctrl_c_raises():
    """SIGINT raises ``KeyboardInterrupt``, as in a terminal, also where pytest started with it
    ignored (a script's background job, ``cmd &``, inherits SIGINT ignored and Python keeps it
    so: the interrupted runs below would then run to their end)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def interrupt_after(monkeypatch, frames: int, stop: signal.Signals = signal.SIGINT) -> None:
    """Make the run receive ``stop`` (Ctrl-C's SIGINT, or SIGTERM) once ``frames`` frames have
    been kept."""
    add = FrameStore.add

    def add_then_stop(self, center, image):
        add(self, center, image)
        if self.kept == frames:
            os.kill(os.getpid(), stop)

    monkeypatch.setattr(FrameStore, "add", add_then_stop)


@pytest.mark.parametrize(
    ("method", "stop"),
    [("tfp", signal.SIGTERM), ("net", signal.SIGINT)],
    ids=lambda value: getattr(value, "name", value),
)
def test_an_interrupted_run_keeps_its_frames_and_resumes_to_the_same_result(
    tmp_path, stream, monkeypatch, capsys, method, stop
):
    monkeypatch.setattr(frame_store, "CHUNK_FRAMES", 4)
    flags = ["--method", method, "--stride", "7", "--no-progress", "--threads", "1"]
    if method == "net":
        flags += ["--model", "tiny"]
    whole = tmp_path / "whole.npz"
    assert main(["reconstruct", str(stream), "--out", str(whole), *flags]) == 0
    expected = np.load(whole)
    assert len(expected["centers"]) == 38  # centres 20, 27, ... 279

    out, pngs = tmp_path / "run.npz", tmp_path / "png"
    args = ["reconstruct", str(stream), "--out", str(out), "--png-dir", str(pngs), *flags]
    with monkeypatch.context() as patched:
        interrupt_after(patched, 10, stop)
        assert main(args) == 128 + stop  # 130 for Ctrl-C, 143 for SIGTERM
    said = "terminated" if stop == signal.SIGTERM else "interrupted"
    assert f"{said}: 10 of 38 frames kept" in capsys.readouterr().err
    assert not out.exists() and len(list(pngs.glob("*.png"))) == 10
    chunks = sorted(partial_dir(out).glob("chunk_*.npz"))
    assert sum(len(np.load(c)["centers"]) for c in chunks) == 10  # all flushed on Ctrl-C

    assert main(args) == 2  # a kept run is never overwritten silently
    assert "add --resume" in capsys.readouterr().err
    assert main([*args, "--resume", "--stride", "14"]) == 2  # argparse: the last --stride wins
    assert "other arguments (stride)" in capsys.readouterr().err
    assert main([*args, "--resume"]) == 0
    resumed = np.load(out)
    np.testing.assert_array_equal(resumed["centers"], expected["centers"])
    np.testing.assert_array_equal(resumed["frames"], expected["frames"])
    assert not partial_dir(out).exists() and len(list(pngs.glob("*.png"))) == 38


def test_nothing_to_resume_is_an_error(tmp_path, stream, capsys):
    out = tmp_path / "o.npz"
    assert main(["reconstruct", str(stream), "--out", str(out), "--method", "tfp", "--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err


def test_a_run_that_fails_before_its_first_frame_leaves_nothing_that_blocks_the_next(
    tmp_path, stream, capsys
):
    """A bad input found after the run began keeps no folder; a folder with no frames (left by
    an older version) does not ask for --resume; a damaged run.json is named, not a traceback."""
    out, bad = tmp_path / "o.npz", tmp_path / "complex.npy"
    np.save(bad, np.zeros((50, 8, 8), np.complex64))
    assert main(["reconstruct", str(bad), "--out", str(out), "--method", "tfp"]) == 2
    assert "complex64" in capsys.readouterr().err and not partial_dir(out).exists()
    args = ["reconstruct", str(stream), "--out", str(out), "--method", "tfp", "--centers", "50"]
    partial_dir(out).mkdir()
    (partial_dir(out) / frame_store.RUN_FILE).write_text("{damaged")
    assert main([*args, "--resume"]) == 2
    err = capsys.readouterr().err
    assert "run.json is missing or damaged" in err and "Traceback" not in err
    assert main(args) == 0 and not partial_dir(out).exists()
    assert np.load(out)["centers"].tolist() == [50]


@pytest.mark.parametrize("png_dir, says", [("a_file", "a file is there"), ("/proc/x", "cannot")])
def test_a_png_dir_that_cannot_be_made_is_refused_before_any_work(
    tmp_path, stream, capsys, png_dir, says
):
    out = tmp_path / "o.npz"
    (tmp_path / "a_file").write_text("")
    folder = png_dir if png_dir.startswith("/") else str(tmp_path / png_dir)
    cmd = ["reconstruct", str(stream), "--out", str(out), "--method", "tfp", "--png-dir", folder]
    assert main(cmd) == 2
    assert says in capsys.readouterr().err and not partial_dir(out).exists()


@pytest.mark.parametrize("threads", ["-1", "0", "x", "100000"])
def test_threads_outside_one_to_a_few_per_core_is_a_usage_error(tmp_path, stream, capsys, threads):
    out = tmp_path / "o.npz"
    with pytest.raises(SystemExit) as exc:
        main(["reconstruct", str(stream), "--out", str(out), "--threads", threads])
    assert exc.value.code == 2 and "give a whole number from 1 to" in capsys.readouterr().err


def test_a_remote_run_resumes_through_the_service_too(
    tmp_path, stream, monkeypatch, capsys, service
):
    """``--url``: interrupted after 10 of 38 frames, resumed with ``--resume``: the service is
    asked for the 28 owed centres only, and the result equals an uninterrupted remote run."""
    flags = ["--method", "net", "--stride", "7", "--no-progress", "--url", service.url]
    whole = tmp_path / "whole.npz"
    assert main(["reconstruct", str(stream), "--out", str(whole), *flags]) == 0
    expected = np.load(whole)
    out = tmp_path / "run.npz"
    args = ["reconstruct", str(stream), "--out", str(out), *flags]
    with monkeypatch.context() as patched:
        interrupt_after(patched, 10)
        assert main(args) == 130
    assert "interrupted: 10 of 38 frames kept" in capsys.readouterr().err
    asked = []
    reconstruct = Client.reconstruct

    def recording(self, source, *rest, **options):
        asked.append(options.get("centers"))
        return reconstruct(self, source, *rest, **options)

    monkeypatch.setattr(Client, "reconstruct", recording)
    assert main([*args, "--resume"]) == 0
    assert asked == [expected["centers"][10:].tolist()]
    resumed = np.load(out)
    np.testing.assert_array_equal(resumed["centers"], expected["centers"])
    np.testing.assert_array_equal(resumed["frames"], expected["frames"])
