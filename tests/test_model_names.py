"""Models by name: ``--model`` of reconstruct and serve, and the service's ``SPK2IMG_MODEL``,
take a shipped model's name (``spk2img-<name>.onnx`` in the package's models folder) or a file;
``spk2img models`` lists the names with the sensors each was trained on."""

import shutil

import numpy as np
import pytest

from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.export.metadata import trained_sensors
from spk2img.io.light import SPIKE_RATE
from spk2img.runtime import onnx_backend
from spk2img.runtime.onnx_backend import model_path, shipped_models
from spk2img.service.settings import ServiceSettings


@pytest.fixture
def models_dir(tmp_path, monkeypatch, standin_model):
    """A models folder holding ``default`` and ``real`` (the TFP-41 stand-in graph), with the
    block-graph parts of ``default`` beside it."""
    folder = tmp_path / "models"
    folder.mkdir()
    for name in ("default", "default.encoder", "default.head", "real"):
        shutil.copy(standin_model, folder / f"spk2img-{name}.onnx")
    monkeypatch.setattr(onnx_backend, "shipped_models_dir", lambda: folder)
    return folder


def test_names_are_the_shipped_files_and_a_file_wins(models_dir, tmp_path, monkeypatch):
    assert shipped_models() == {
        "default": models_dir / "spk2img-default.onnx",
        "real": models_dir / "spk2img-real.onnx",
    }
    assert model_path(None) == model_path("default") == models_dir / "spk2img-default.onnx"
    assert model_path("real") == models_dir / "spk2img-real.onnx"
    own = tmp_path / "mine.onnx"
    own.write_bytes(b"")
    assert model_path(str(own)) == model_path(own) == own
    monkeypatch.chdir(tmp_path)
    (tmp_path / "real").write_bytes(b"")  # a file in the working folder named like a model
    assert model_path("real").resolve() == (tmp_path / "real").resolve()
    with pytest.raises(InputError, match=r"no model file 'nope'.*\(default, real\)"):
        model_path("nope")


def test_reconstruct_runs_the_named_model(models_dir, tmp_path, capsys):
    """``--model real`` runs that graph: here TFP-41, so the frame is the window's mean / 0.6."""
    spikes = (np.random.default_rng(0).uniform(size=(60, 16, 24)) < 0.3).astype(np.uint8)
    np.save(tmp_path / "s.npy", spikes)
    out = tmp_path / "out.npz"
    args = ["reconstruct", str(tmp_path / "s.npy"), "--out", str(out), "--centers", "30"]
    assert main([*args, "--model", "real", "--no-progress", "--no-block-reuse"]) == 0
    expected = np.clip(spikes[10:51].mean(axis=0) / SPIKE_RATE, 0, 1)
    np.testing.assert_allclose(np.load(out)["frames"][0], expected, atol=1e-6)
    capsys.readouterr()
    assert main([*args, "--model", "nope", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "shipped model's name (default, real)" in err


def test_the_service_takes_a_name_and_refuses_an_unknown_one(models_dir, capsys):
    assert ServiceSettings(model="real").model_path == models_dir / "spk2img-real.onnx"
    assert ServiceSettings().model_path == models_dir / "spk2img-default.onnx"
    assert main(["serve", "--model", "nope"]) == 2
    assert "no model file 'nope'" in capsys.readouterr().err


def test_models_lists_the_shipped_names(models_dir, capsys):
    assert main(["models"]) == 0
    listed = capsys.readouterr().out.split("shipped model")[1].splitlines()
    assert [line.split()[0] for line in listed[1:3]] == ["default", "real"]


def test_trained_sensors_say_which_streams_a_model_is_for():
    assert trained_sensors({"train_config": {"data": []}}) == "random (procedural scenes only)"
    natural = {"data": ["photos"]}
    assert trained_sensors({"train_config": natural | {"ideal_share": 1.0}}) == "noise-free"
    assert trained_sensors({"train_config": natural | {"ideal_share": 0}}) == "fitted real camera"
    assert trained_sensors({"train_config": natural}) == "noise-free 50%, fitted real camera 50%"


def test_the_torch_backend_runs_the_checkpoint_shipped_beside_the_named_model(
    models_dir, tiny_checkpoint, tmp_path, capsys
):
    """``--model real --backend torch`` runs ``spk2img-real.pt``, never the default's weights;
    a model with no checkpoint beside it, or a model and a checkpoint at once, is refused."""
    import torch

    from spk2img.model.checkpoint import load_model

    shutil.copy(tiny_checkpoint, models_dir / "spk2img-real.pt")
    spikes = (np.random.default_rng(1).uniform(size=(41, 16, 24)) < 0.3).astype(np.uint8)
    np.save(tmp_path / "s.npy", spikes)
    out = tmp_path / "out.npz"
    args = ["reconstruct", str(tmp_path / "s.npy"), "--out", str(out), "--centers", "20"]
    assert main([*args, "--model", "real", "--backend", "torch", "--no-progress"]) == 0
    with torch.inference_mode():
        expected = load_model(tiny_checkpoint)(torch.from_numpy(spikes[None].astype("f4")))[0]
    np.testing.assert_allclose(np.load(out)["frames"][0], expected[0, 0].numpy(), atol=1e-5)
    capsys.readouterr()
    assert main([*args, "--model", "default", "--backend", "torch", "--no-progress"]) == 2
    assert "no checkpoint spk2img-default.pt beside model 'default'" in capsys.readouterr().err
    both = ["--model", "real", "--checkpoint", str(tiny_checkpoint), "--backend", "torch"]
    assert main([*args, *both, "--no-progress"]) == 2
    assert "give a model or a checkpoint" in capsys.readouterr().err


def test_models_piped_into_a_reader_that_left_ends_quietly():
    """``spk2img models | head -1``: the reader leaves, the command stops without a traceback
    (exit 141, as a shell's own tools end on a closed pipe)."""
    import subprocess
    import sys

    command = [sys.executable, "-c", "import sys; from spk2img.cli import main; sys.exit(main())"]
    process = subprocess.Popen([*command, "models"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # the reader leaves before anything is written
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) == 141 and err == ""
