"""Mistakes any command can meet end in one line on stderr and exit 2, never a traceback: a
path where a file is and a folder must go, centres beyond any stream, a malformed service URL."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from spk2img.cli import main


@pytest.fixture()
def stream(tmp_path):
    path = tmp_path / "s.npy"
    np.save(path, (np.random.default_rng(2).random((60, 8, 8)) < 0.3).astype(np.uint8))
    return path


def _one_line(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"spk2img {command}: error:") and "\n" not in err, err
    return err


@pytest.mark.parametrize(
    "extra, says",
    [
        (["--centers", str(2**70)], "is beyond any stream"),
        (["--url", "notaurl"], "must look like http://HOST:PORT"),
        (["--url", "ftp://host:1"], "must look like http://HOST:PORT"),
        (["--method", "net", "--window", "21"], "--window is for --method tfp and tfi"),
        (["--method", "net", "--checkpoint", "c.pt"], "a checkpoint is for backend torch"),
    ],
)
def test_reconstruct_refuses_in_one_line(tmp_path, stream, capsys, extra, says):
    out = tmp_path / "o.npz"
    assert main(["reconstruct", str(stream), "--out", str(out), "--method", "tfp", *extra]) == 2
    assert says in _one_line(capsys, "reconstruct")
    assert not out.exists()


def test_a_file_where_a_folder_must_go_is_one_line(tmp_path, stream, capsys):
    (tmp_path / "afile").write_text("")
    out = tmp_path / "afile" / "o.npz"
    assert main(["reconstruct", str(stream), "--out", str(out), "--method", "tfp"]) == 2
    assert "afile" in _one_line(capsys, "reconstruct")
    data = tmp_path / "data"
    data.mkdir()
    assert main(["pack-data", "--data", str(data), "--out", str(tmp_path / "pack")]) == 2
    assert "no training sources" in _one_line(capsys, "pack-data")
    assert not (tmp_path / "pack").exists()
    Image.fromarray(np.full((64, 64), 128, np.uint8)).save(data / "photo.png")
    assert main(["pack-data", "--data", str(data), "--out", str(tmp_path / "afile")]) == 2
    assert "afile" in _one_line(capsys, "pack-data")


def test_sizes_beyond_any_camera_and_files_that_are_no_graph_are_refused_first(
    tmp_path, stream, capsys
):
    """Before any work: a side over 4096 (``models``, ``export``, ``verify``), a ``verify`` of
    a file that is no ONNX graph, and a ``--json`` that cannot be written."""
    huge = ["--height", "99999999", "--width", "9"]
    assert main(["models", *huge]) == 2
    assert "at most 4096" in _one_line(capsys, "models")
    out = tmp_path / "m.onnx"
    export = ["export", "--random-weights", "--member", "tiny", "--out", str(out)]
    assert main([*export, "--example-size", "99999x99999"]) == 2
    assert "at most 4096" in _one_line(capsys, "export") and not out.exists()
    assert main(["verify", str(stream)]) == 2
    assert "not an ONNX model" in _one_line(capsys, "verify")
    (tmp_path / "afile").write_text("")
    json_out = str(tmp_path / "afile" / "r.json")
    assert main(["verify", str(stream), "--json", json_out]) == 2
    assert "--json" in _one_line(capsys, "verify")
    for flag, value in (("--atol", "nan"), ("--atol", "-1"), ("--sizes", ",")):
        assert main(["verify", str(stream), flag, value]) == 2
        assert f"{flag} " in _one_line(capsys, "verify")


@pytest.mark.parametrize("command", ["inspect", "fit-sensor", "reconstruct"])
def test_a_folder_given_as_the_spike_file_is_named_as_one(tmp_path, capsys, command):
    extra = (
        ["--out", str(tmp_path / "o.npz"), "--method", "tfp"] if command == "reconstruct" else []
    )
    assert main([command, str(tmp_path), *extra]) == 2
    assert f"{tmp_path} is a folder, not a spike file" in _one_line(capsys, command)
