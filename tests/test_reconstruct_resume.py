"""``spk2img reconstruct`` keeps its frames as they come (spk2img.io.frame_store): a run
interrupted by Ctrl-C keeps every finished frame (arrays and PNGs) and ``--resume`` continues it
to the frames of an uninterrupted run; runs that would mix arguments are refused."""

from __future__ import annotations

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


def interrupt_after(monkeypatch, frames: int) -> None:
    """Make the run stop with Ctrl-C once ``frames`` frames have been kept."""
    add = FrameStore.add

    def add_then_stop(self, center, image):
        add(self, center, image)
        if self.kept >= frames:
            raise KeyboardInterrupt

    monkeypatch.setattr(FrameStore, "add", add_then_stop)


@pytest.mark.parametrize("method", ["tfp", "net"])
def test_an_interrupted_run_keeps_its_frames_and_resumes_to_the_same_result(
    tmp_path, stream, monkeypatch, capsys, method
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
        interrupt_after(patched, 10)
        assert main(args) == 130
    assert "interrupted: 10 of 38 frames kept" in capsys.readouterr().err
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
