"""Files split into parts and joined back with their checksums (spk2img.parts), and the
training-data pack that travels in such parts (spk2img pack-data)."""

import json
import math
import os
import shutil
import subprocess
import sys
import tarfile
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
from spk2img.evaluation.real_video import load_windows, training_windows
from spk2img.parts import PartsError, collect, join, missing, read_manifest, split
from spk2img.sim.sources import SourceIndex
from spk2img.training.pack import ARCHIVE_BYTES, ENTRY_BYTES, PACK_NAME, pack_training_data

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


def test_room_is_what_a_command_carries_beside_the_files_that_travel(tmp_path):
    """Tracked files and untracked ones git does not ignore travel; ignored ones do not."""
    repo = tmp_path / "repo"
    repo.mkdir()
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], cwd=repo, check=True)
    (repo / ".gitignore").write_text("pack/\n")
    (repo / "tracked.bin").write_bytes(bytes(3 * 2**20))
    subprocess.run([*git, "add", "."], cwd=repo, check=True)
    subprocess.run([*git, "commit", "-qm", "x"], cwd=repo, check=True)
    (repo / "new.bin").write_bytes(bytes(2**20))  # untracked, not ignored: travels
    (repo / "pack").mkdir()
    (repo / "pack" / "part").write_bytes(bytes(5 * 2**20))  # ignored: carried when named
    assert parts_module.travelling_bytes(repo) == 4 * 2**20 + len("pack/\n")
    assert parts_module.room_mib(repo) == pytest.approx(
        58.9
    )  # 64 - 1 - 4 MiB and 7 bytes, rounded down
    done = subprocess.run(
        [sys.executable, "-m", "spk2img.parts", "room", str(tmp_path)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "not a git checkout" in done.stderr


@pytest.mark.skipif(not (REPO / ".git").exists(), reason="not a git checkout")
def test_this_checkout_leaves_room_for_a_training_pack_in_one_command():
    """A lent GPU machine receives 64 MiB a command, this checkout included: the compact
    training pack (``pack-data --max-mib``, docs/gpu.md) needs 20 MiB of them."""
    assert parts_module.room_mib(REPO) >= 20


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
        main(
            [
                "pack-data",
                "--data",
                str(data_dir),
                "--out",
                str(pack),
                "--part-mib",
                "0.002",
                "--with-validation",
            ]
        )
        == 0
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
    clip = data_dir / "video" / "vid4_walk"  # a held-out real-video clip
    shutil.copytree(data_dir / "video" / "pan", clip)
    assert main(["pack-data", "--data", str(data_dir), "--out", str(pack)]) == 0
    assert "left out (held out): kodak24_kodim08.png, vid4_walk" in capsys.readouterr().out
    unpacked = unpack(pack, tmp_path)
    assert not list(unpacked.rglob("kodak24_kodim08.png")) and not list(unpacked.rglob("vid4*"))
    record = json.loads((unpacked / "PACK.json").read_text())
    assert record["real_video_windows"] == {"file": "real_video_windows.npz", "windows": 2}
    filmed = training_windows([data_dir])  # what the run elsewhere validates on: the same
    got = load_windows(unpacked / "real_video_windows.npz")
    assert [w.clip for w in got] == ["vid4_walk"] * 2
    assert all(np.array_equal(a.spikes, b.spikes) for a, b in zip(got, filmed, strict=True))
    assert not (pack / "real_video_windows.npz").exists()  # only the parts stay
    assert main(["pack-data", "--data", str(tmp_path / "nowhere")]) == 2
    assert main(["pack-data", "--data", str(data_dir), "--part-mib", "0"]) == 2
    assert main(["pack-data", "--data", str(data_dir), "--part-mib", "nan"]) == 2
    err = capsys.readouterr().err
    assert "not a folder" in err and "--part-mib 0" in err and "--part-mib nan" in err


@pytest.fixture(scope="module")
def collection(tmp_path_factory):
    """Nine photos of different sizes, three clips of 5, 8 and 12 frames, a held-out photo."""
    root = tmp_path_factory.mktemp("collection") / "train"
    rng = np.random.default_rng(2)
    (root / "photos").mkdir(parents=True)
    for k in range(9):
        pixels = rng.integers(0, 256, (40 + 4 * k, 48), np.uint8)
        Image.fromarray(pixels).save(root / "photos" / f"p{k}.png")
    Image.fromarray(rng.integers(0, 256, (40, 40), np.uint8)).save(
        root / "photos" / "kodak24_kodim08.png"
    )
    for name, frames in (("a", 5), ("b", 8), ("c", 12)):
        (root / "video" / name).mkdir(parents=True)
        for k in range(frames):
            pixels = rng.integers(0, 256, (36, 44), np.uint8)
            Image.fromarray(pixels).save(root / "video" / name / f"{k:05d}.png")
    (root / "MANIFEST.md").write_text("sources and licences\n")
    return root


@settings(max_examples=25, deadline=None)
@given(max_kib=st.floats(2, 80))
def test_a_pack_within_max_mib_keeps_whole_files_and_the_most_that_fits(
    collection, tmp_path_factory, max_kib
):
    """``--max-mib``: the archive is never larger; what it holds is byte for byte the source's;
    each clip keeps its first frames (3 at least: it stays a clip) or is left out, the photos
    are every k-th, and the next larger choice would not have fitted; the held-out photo and
    the manifest are always there. Too little room for any training source is refused."""
    out = tmp_path_factory.mktemp("compact")
    max_mib = max_kib / 1024

    def cost(files):
        return sum((collection.parent / f).stat().st_size + ENTRY_BYTES for f in files)

    room = max_mib * 2**20 - ARCHIVE_BYTES - cost(["train/photos/kodak24_kodim08.png"])
    room -= cost(["train/MANIFEST.md"])
    try:
        record = pack_training_data([collection], out, 1, validation=True, max_mib=max_mib)
    except ValueError as exc:
        assert "too little for any training source" in str(exc)
        assert min(cost([f"train/photos/p{k}.png"]) for k in range(9)) > room
        return
    assert record["bytes"] <= max_mib * 2**20
    assert record["validation"] == {"kodak24_kodim08.png": ["train/photos/kodak24_kodim08.png"]}
    archive = join(Path(record["manifest"]), out / "joined.zip")
    with zipfile.ZipFile(archive) as z:
        for name in z.namelist():
            if name != "PACK.json":
                assert z.read(name) == (collection.parent / name).read_bytes()
        assert "train/MANIFEST.md" in z.namelist()
    kept = record["compact"]
    photos = sorted(n for n in record["train"] if n.endswith(".png"))
    clips = {n: record["train"][n] for n in record["train"] if not n.endswith(".png")}
    every = kept["photos"]["every"]
    if every:
        assert photos == [f"p{k}.png" for k in range(0, 9, every)]
    if every != 1:  # one photo more in the spread would not have fitted beside the clips
        closer = range(0, 9, every - 1) if every else [0]  # p0: the smallest photo
        clip_bytes = cost(f for frames in record["train"].values() for f in frames if "video" in f)
        assert cost(f"train/photos/p{k}.png" for k in closer) > room - clip_bytes
    for name, frames in clips.items():
        expected = [f"train/video/{name}/{k:05d}.png" for k in range(len(frames))]
        assert frames == expected and len(frames) >= 3
    if kept["clip_frames"]:  # cut: one more frame each would not have fitted half the room
        assert all(len(f) <= kept["clip_frames"] for f in clips.values())
    assert kept["photos"]["kept"] == len(photos) and kept["clips"]["kept"] == len(clips)


def test_pack_data_says_what_a_compact_pack_kept(collection, tmp_path, capsys):
    pack = tmp_path / "pack"
    args = ["pack-data", "--data", str(collection), "--out", str(pack), "--max-mib", "0.05"]
    assert main(args) == 0
    said = capsys.readouterr().out
    assert "within 0.05 MiB: 3 of 3 clips (all, their first " in said and " of 9 photos (" in said
    assert sum(p["size"] for p in read_manifest(pack / f"{PACK_NAME}.parts.json")["parts"]) <= (
        0.05 * 2**20
    )
    assert main([*args[:-1], "0.001"]) == 2
    assert main([*args[:-1], "-1"]) == 2
    err = capsys.readouterr().err
    assert "too little for any training source" in err and "--max-mib -1: must be" in err


@pytest.mark.parametrize("kind", ["zip", "tar.xz"])
def test_the_receiving_script_gathers_a_part_per_command_and_unpacks_the_last(tmp_path, kind):
    """scripts/receive_parts.sh run once per command, each with one part beside the manifest
    (as a GPU machine receives them): it says what is missing until the last part, then joins
    and extracts the archive (the training-data pack's zip, slim onnxruntime-gpu's tar.xz)."""
    archive = tmp_path / f"data.{kind}"
    payload = np.random.default_rng(2).bytes(5000)
    if kind == "zip":
        with zipfile.ZipFile(archive, "w") as z:
            z.writestr("photos/a.bin", payload)
    else:
        (tmp_path / "photos").mkdir()
        (tmp_path / "photos" / "a.bin").write_bytes(payload)
        with tarfile.open(archive, "w:xz") as t:
            t.add(tmp_path / "photos", "photos")
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
    assert "still missing" in outputs[0] and f"data.{kind}.part-002" in outputs[1]
    assert f"received data.{kind}" in outputs[-1]
    assert (tmp_path / "dest" / "photos" / "a.bin").read_bytes() == payload
