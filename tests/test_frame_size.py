"""A headerless .dat read at a wrong size (spk2img.io.frame_size): refused before any work, the
right size named, for simulated streams of several sizes and sensors, the shipped sample stream
and the real capture; ``--force-size`` reads it anyway; ``spk2img inspect`` lists the sizes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from spk2img.cli import main
from spk2img.io.frame_size import candidate_sizes, check_frame_size
from spk2img.io.spikes import SpikeFormatError, frame_nbytes, write_spikes
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import SensorConfig, simulate

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "examples" / "fast_motion_250x400.dat"
CAPTURE = ROOT.parent / "shared" / "data" / "real" / "uhsr_helicopter_250x250.npz"


def simulated(tmp_path: Path, height: int, width: int, sensor: SensorConfig) -> Path:
    rng = np.random.default_rng([height, width])
    scene = random_scene(rng, height, width, "slow", "normal")
    path = tmp_path / f"sim_{height}x{width}.dat"
    write_spikes(path, simulate(scene, 400, sensor, rng))
    return path


@pytest.mark.parametrize(
    ("size", "sensor", "wrong"),
    [
        ((128, 160), SensorConfig.ideal(), [(100, 160), (160, 128), (80, 256)]),
        ((96, 96), SensorConfig.real(), [(72, 128), (64, 144)]),
        ((120, 200), SensorConfig.ideal(), [(200, 120), (100, 240)]),
    ],
)
def test_a_wrong_size_of_a_simulated_stream_is_refused_naming_the_right_one(
    tmp_path, size, sensor, wrong
):
    path = simulated(tmp_path, *size, sensor)
    check_frame_size(path, *size)  # the right size passes
    for height, width in wrong:
        assert path.stat().st_size % frame_nbytes(height, width) == 0  # it decodes, as noise
        with pytest.raises(SpikeFormatError, match="look like noise") as refused:
            check_frame_size(path, height, width)
        likely = str(refused.value).split("likely sizes: ")[1]
        assert likely.startswith(f"{size[0]}x{size[1]} ")


def test_the_sample_stream():
    check_frame_size(SAMPLE, 250, 400)
    with pytest.raises(SpikeFormatError, match=r"likely sizes: 250x400 "):
        check_frame_size(SAMPLE, 200, 500)


def test_the_real_capture_as_a_dat(tmp_path):
    if not CAPTURE.is_file():
        pytest.skip(f"the real capture is not here ({CAPTURE})")
    with np.load(CAPTURE) as npz:
        spikes = npz[npz.files[0]].astype(np.uint8)
    path = tmp_path / "capture.dat"
    write_spikes(path, spikes)
    check_frame_size(path, 250, 250)  # dim (0.03 spikes a frame), still coherent
    with pytest.raises(SpikeFormatError, match=r"likely sizes: 250x250 "):
        check_frame_size(path, 200, 312)


def test_the_cli_refuses_it_force_size_reads_it_and_inspect_lists_the_sizes(tmp_path, capsys):
    path = simulated(tmp_path, 128, 160, SensorConfig.ideal())
    out = tmp_path / "o.npz"
    args = ["reconstruct", str(path), "--out", str(out), "--method", "tfp", "--no-progress"]
    assert main([*args, "--height", "100", "--width", "160"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "likely sizes: 128x160" in err and "--force-size" in err
    assert not out.exists()
    assert main([*args, "--height", "100", "--width", "160", "--force-size"]) == 0
    assert np.load(out)["frames"].shape[1:] == (100, 160)
    assert main(["inspect", str(path), "--height", "100", "--width", "160"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith("512 frames of 100x160")
    assert lines[2].startswith("  128x160: ") and any(line.endswith("as given") for line in lines)
    assert lines[-1].startswith("--binning auto would take ")


@given(height=st.integers(8, 64), width=st.integers(8, 64), frames=st.integers(16, 80))
def test_candidates_hold_the_given_size_and_all_divide_the_file(height, width, frames):
    n_bytes = frames * frame_nbytes(height, width)
    sizes = candidate_sizes(n_bytes, height, width)
    assert sizes[0] == (height, width) and len(set(sizes)) == len(sizes)
    assert all(n_bytes % frame_nbytes(h, w) == 0 for h, w in sizes)
