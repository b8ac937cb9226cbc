"""Files split into parts and joined back with their checksums (spk2img.parts), and the
training-data pack that travels in such parts (spk2img pack-data)."""

import json
import math
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from spk2img import parts as parts_module
from spk2img.cli import main
from spk2img.parts import PartsError, collect, join, missing, read_manifest, split
from spk2img.sim.sources import SourceIndex
from spk2img.training.pack import PACK_NAME

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "receive_parts.sh"


@settings(max_examples=30, deadline=None)
@given(
    payload=st.binary(min_size=0, max_size=3000),
    part_bytes=st.integers(1, 700),
    chunk=st.integers(1, 300),
)
def test_split_then_join_gives_the_file_back(tmp_path_factory, payload, part_bytes, chunk):
    """Whatever the part size and the size of the reads that copy a part (``chunk``)."""
    folder = tmp_path_factory.mktemp("parts")
    original = folder / "blob.bin"
    original.write_bytes(payload)
    with mock.patch.object(parts_module, "CHUNK", chunk):
        manifest = split(original, folder / "parts", part_bytes)
    parts = read_manifest(manifest)["parts"]
    assert len(parts) == max(1, math.ceil(len(payload) / part_bytes))  # empty: one empty part
    assert all(p["size"] <= part_bytes for p in parts)
    assert join(manifest, folder / "joined.bin").read_bytes() == payload


def test_a_missing_or_damaged_part_is_named_and_never_joined(tmp_path, capsys):
    original = tmp_path / "blob.bin"
    original.write_bytes(np.random.default_rng(0).bytes(10_000))
    manifest = split(original, tmp_path / "parts", 3000)
    received = tmp_path / "received"
    (tmp_path / "parts" / "blob.bin.part-002").rename(tmp_path / "held-back")
    assert collect(manifest, received) == ["blob.bin.part-002"]
    with pytest.raises(PartsError, match=r"1 of 4 parts missing: \['blob.bin.part-002'\]"):
        join(received / manifest.name, tmp_path / "out.bin")
    (tmp_path / "held-back").rename(tmp_path / "parts" / "blob.bin.part-002")
    assert collect(manifest, received) == []  # the next command brings the last part
    assert missing(received / manifest.name, received) == []
    part = received / "blob.bin.part-001"
    damaged = bytearray(part.read_bytes())
    damaged[10] ^= 1
    part.write_bytes(bytes(damaged))
    with pytest.raises(PartsError, match="blob.bin.part-001: damaged"):
        join(received / manifest.name, tmp_path / "out.bin")
    assert not (tmp_path / "out.bin").exists()
    part.write_bytes((tmp_path / "parts" / "blob.bin.part-001").read_bytes())
    assert join(received / manifest.name, tmp_path / "out.bin").read_bytes() == (
        original.read_bytes()
    )
    (tmp_path / "not.json").write_text("[1, 2]")
    command = [sys.executable, "-m", "spk2img.parts", "join", str(tmp_path / "not.json")]
    done = subprocess.run([*command, "--out", "x"], capture_output=True, text=True)
    assert done.returncode == 2 and "not a parts manifest" in done.stderr
    assert done.stderr.count("\n") == 1


@pytest.fixture
def data_dir(tmp_path):
    """Training data as spk2img train reads it: two photos (one held out), a clip, a small
    photo, licences."""
    root = tmp_path / "train"
    rng = np.random.default_rng(1)
    (root / "photos").mkdir(parents=True)
    for name in ("mine.png", "kodak24_kodim08.png", "tiny.png"):
        side = 8 if name == "tiny.png" else 40
        Image.fromarray(rng.integers(0, 256, (side, side + 3), np.uint8)).save(
            root / "photos" / name
        )
    (root / "video" / "pan").mkdir(parents=True)
    for k in range(4):
        frame = rng.integers(0, 256, (36, 44), np.uint8)
        Image.fromarray(frame).save(root / "video" / "pan" / f"{k:05d}.png")
    (root / "MANIFEST.md").write_text("sources and licences\n")
    (root / "licences").mkdir()
    (root / "licences" / "cc-by.txt").write_text("licence text\n")
    return root


def unpack(pack: Path, tmp_path) -> Path:
    received = tmp_path / "received"
    assert collect(pack / f"{PACK_NAME}.parts.json", received) == []
    archive = join(received / f"{PACK_NAME}.parts.json", tmp_path / PACK_NAME)
    with zipfile.ZipFile(archive) as z:
        z.extractall(tmp_path / "unpacked")
    return tmp_path / "unpacked"


def test_the_pack_travels_in_parts_and_unpacks_to_the_same_training_data(
    data_dir, tmp_path, capsys
):
    """Every source byte for byte in parts of at most --part-mib; training finds the same
    photos and clips in the unpacked folder; the held-out photo is there for validation only,
    listed; the licences travel."""
    pack = tmp_path / "pack"
    assert (
        main(["pack-data", "--data", str(data_dir), "--out", str(pack), "--part-mib", "0.002"]) == 0
    )
    out = capsys.readouterr().out
    assert "packed 3 training and 1 validation sources (7 files" in out
    assert not (pack / PACK_NAME).exists()  # only the parts stay
    parts = read_manifest(pack / f"{PACK_NAME}.parts.json")["parts"]
    assert len(parts) > 3 and all(p["size"] <= 0.002 * 2**20 for p in parts)
    unpacked = unpack(pack, tmp_path) / "train"
    for path in data_dir.rglob("*"):
        if path.is_file():
            assert (unpacked / path.relative_to(data_dir)).read_bytes() == path.read_bytes()
    record = json.loads((unpacked.parent / "PACK.json").read_text())
    assert sorted(record["validation"]) == ["kodak24_kodim08.png"]
    assert sorted(record["train"]) == ["mine.png", "pan", "tiny.png"]
    held_out = frozenset(record["validation"])
    for folder in (data_dir, unpacked):
        index = SourceIndex.scan([folder], min_side=16, held_out=held_out)
        assert [p.path.name for p in index.photos] == ["mine.png"]
        assert [c.name for c in index.clips] == ["pan"]


def test_the_pack_can_leave_the_held_out_sources_out_and_refuses_bad_input(
    data_dir, tmp_path, capsys
):
    pack = tmp_path / "pack"
    assert main(["pack-data", "--data", str(data_dir), "--out", str(pack), "--no-validation"]) == 0
    assert "left out (held out): kodak24_kodim08.png" in capsys.readouterr().out
    unpacked = unpack(pack, tmp_path)
    assert not list(unpacked.rglob("kodak24_kodim08.png"))
    assert main(["pack-data", "--data", str(tmp_path / "nowhere")]) == 2
    assert main(["pack-data", "--data", str(data_dir), "--part-mib", "0"]) == 2
    assert main(["pack-data", "--data", str(data_dir), "--part-mib", "nan"]) == 2
    err = capsys.readouterr().err
    assert "not a folder" in err and "--part-mib 0" in err and "--part-mib nan" in err


def test_the_receiving_script_gathers_a_part_per_command_and_unpacks_the_last(tmp_path):
    """scripts/receive_parts.sh run once per command, each with one part beside the manifest
    (as a GPU machine receives them): it says what is missing until the last part, then joins
    and extracts the archive."""
    archive = tmp_path / "data.zip"
    payload = np.random.default_rng(2).bytes(5000)
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("photos/a.bin", payload)
    manifest = split(archive, tmp_path / "parts", 2000)
    env = {**os.environ, "PARTS_STORE": str(tmp_path / "store"), "PYTHON": sys.executable}
    outputs = []
    for part in read_manifest(manifest)["parts"]:
        call = tmp_path / "call"
        shutil.rmtree(call, ignore_errors=True)
        call.mkdir()
        shutil.copy(manifest, call)
        shutil.copy(tmp_path / "parts" / part["file"], call)
        done = subprocess.run(
            ["bash", str(SCRIPT), str(call / manifest.name), str(tmp_path / "dest")],
            capture_output=True,
            text=True,
            env=env,
            cwd=REPO,
            check=True,
        )
        outputs.append(done.stdout)
    assert "still missing" in outputs[0] and "data.zip.part-002" in outputs[1]
    assert "received data.zip" in outputs[-1]
    assert (tmp_path / "dest" / "photos" / "a.bin").read_bytes() == payload
