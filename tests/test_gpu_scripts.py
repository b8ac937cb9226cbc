"""The scripts a lent GPU runs, checked on the CPU at small sizes (they name their device)."""

import dataclasses
import json
import os
import shlex
import shutil
import struct
import subprocess
import sys
import tarfile
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from isolation import without_modules
from PIL import Image
from script_loader import load_script

from spk2img.cli import build_parser, main
from spk2img.training.config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]


def test_torch_inference_speed_times_each_precision_and_batch_and_its_error(tmp_path):
    """``tiny`` at 24x32 on the CPU: a row per precision and batch, fp32 the reference (its
    batch rows agree to float rounding), bf16 and fp16 within 0.05 of it."""
    script = load_script("torch_inference_speed")
    out = tmp_path / "torch.json"
    argv = ["--device", "cpu", "--size", "24x32", "--batches", "1,2", "--models", "tiny"]
    result = script.main([*argv, "--repeats", "1", "--json", str(out)])
    assert json.loads(out.read_text()) == result and result["device"] == "cpu"
    rows = result["models"]["tiny"]
    assert [(r["precision"], r["batch"]) for r in rows] == [
        (p, b) for p in ("fp32", "bf16", "fp16") for b in (1, 2)
    ]
    assert all(r["ms_per_frame"] > 0 for r in rows)
    for row in rows:
        limit = 1e-5 if row["precision"] == "fp32" else 0.05
        assert row["max_abs_vs_fp32"] <= limit, row
    with pytest.raises(SystemExit):
        script.main(["--device", "cpu", "--precisions", "bf16"])
    table = load_script("gpu_results").inference_table(result).splitlines()
    assert table[0] == "# Torch inference on cpu" and len(table) == 6 + len(rows)
    assert table[-1].startswith("| tiny | fp16 | 2 | ") and table[6].endswith("| — |")


NOT_ON_THE_GPU_IMAGE = ("av", "fastapi", "uvicorn", "pydantic", "pydantic_settings", "starlette")
"""Modules of the project's extras that the lent GPU machines' image does not have (its package
list, as sessions there saw it): the session's steps must run without them."""


def test_a_gpu_session_trains_its_runs_then_resumes_them_and_brings_them_back(tmp_path):
    """``gpu_session.sh session`` (on the CPU here: the last ``--device`` wins) unpacks the
    one-part training pack, trains the listed runs for the seconds given, stops them at a step
    they save and brings back their logs, metrics and checkpoints, under 8 files; a run
    started in the background with ``train-start`` (here: the same run, resumed) returns at
    once, and ``train-stop`` stops it with Ctrl-C and brings it back too. Its processes run
    without the modules the GPU machines' image lacks (:data:`NOT_ON_THE_GPU_IMAGE`)."""
    data = tmp_path / "collection"  # any name: the session reads it from PACK.json
    (data / "photos").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for name in ("leaf", "rock", "wall"):
        Image.fromarray(rng.integers(0, 256, (40, 48), np.uint8)).save(
            data / "photos" / f"{name}.png"
        )
    held_out = data / "video2" / "vid4_walk"  # a real-video clip: filmed into windows, not packed
    held_out.mkdir(parents=True)
    for k in range(4):
        frame = np.roll(rng.integers(0, 256, (40, 48), np.uint8), k, axis=1)
        Image.fromarray(frame).save(held_out / f"{k:05d}.png")
    pack = tmp_path / "pack"
    assert main(["pack-data", "--data", str(data), "--out", str(pack), "--max-mib", "1"]) == 0
    flags = "--member tiny --patch 16 --batch-size 2 --val-per-class 1 --log-every 1 --workers 0"
    flags += " --steps 100000 --val-every 100000 --checkpoint-every 100000 --device cpu"
    (tmp_path / "runs.txt").write_text(f"# the run of this test\nt {flags}\n")
    env = {
        **os.environ,
        "OUT": str(tmp_path / "out"),
        "SPK2IMG_RUNS": str(tmp_path / "runs"),
        "SPK2IMG_DATA": str(tmp_path / "data"),
        "SPK2IMG_PACK": str(pack),
        "SPK2IMG_SESSION_RUNS": str(tmp_path / "runs.txt"),
        "SPK2IMG_SESSION_MEASURE": "0",
        "PARTS_STORE": str(tmp_path / "parts"),
        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",  # its python3
        "PYTHONPATH": without_modules(tmp_path / "site", NOT_ON_THE_GPU_IMAGE)["PYTHONPATH"],
    }

    def session(*args: str) -> str:
        cmd = ["bash", str(ROOT / "scripts" / "gpu_session.sh"), *args]
        done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=180)
        assert done.returncode == 0, done.stderr
        return done.stdout

    def brought() -> list[dict]:
        with tarfile.open(tmp_path / "out" / "report.tar.gz") as report:
            names = report.getnames()
            assert "report/environment.txt" in names and "report/t/train.log" in names
            lines = report.extractfile("report/t/metrics.jsonl").read().decode().splitlines()
        return [json.loads(line) for line in lines]

    said = session("session", "8")
    records = brought()
    (logged,) = [r for r in records if r["kind"] == "data"]
    assert logged["real_video_windows"] == 2  # the clip's two speed bins, from the pack's file
    (stopped,) = [r for r in records if r["kind"] == "stopped"]
    assert stopped["signal"] == "SIGINT" and stopped["step"] >= 1
    assert f"stopped at step {stopped['step']} of 100000" in said
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["report.tar.gz", "t-last.pt"]
    last = torch.load(tmp_path / "out" / "t-last.pt", weights_only=True)
    assert last["step"] == stopped["step"]
    results, state = load_script("gpu_results"), tmp_path / "state"
    for older in ("a", "b"):  # two runs' states there already: one must go
        (state / older).mkdir(parents=True)
        (state / older / "last.pt").write_bytes(b"")
    said = results.take_results(tmp_path / "out", state, tmp_path / "back", tmp_path / "docs")
    assert said[0].startswith(f"t: step {stopped['step']}, ") and "fp16 weights" in said[0]
    assert "no torch inference rows came back" in said
    assert f"more than two states in {state}: drop the last.pt of a, b" in said
    assert (state / "t" / "metrics.jsonl").read_text().count('"kind": "stopped"') == 1
    kept = torch.load(state / "t" / "last.pt", weights_only=True)
    assert kept["step"] == stopped["step"] and "optimizer" not in kept
    assert {t.dtype for t in kept["model"].values() if t.is_floating_point()} == {torch.float16}
    assert (tmp_path / "docs" / "gpu_environment.txt").read_text().startswith("Python 3.")

    try:
        args = [
            "train-start",
            "t",
            "300",
            *flags.split(),
            "--data",
            str(tmp_path / "data/collection"),
        ]
        assert "in the background" in session(*args)
        metrics = tmp_path / "runs" / "t" / "metrics.jsonl"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and metrics.read_text().count('"kind": "train"') < (
            sum(r["kind"] == "train" for r in records) + 2
        ):
            time.sleep(0.2)
        said = session("train-stop", "t")
    finally:  # never leave the background run behind a failure
        subprocess.run(["pkill", "-KILL", "-f", f"--run-dir {tmp_path / 'runs' / 't'}"])
    resumed = json.loads(metrics.read_text().splitlines()[-1])
    assert resumed["kind"] == "stopped" and resumed["step"] > stopped["step"]
    assert torch.load(tmp_path / "out" / "t-last.pt", weights_only=True)["step"] == resumed["step"]
    assert "Traceback" not in (tmp_path / "out" / "report" / "t" / "train.log").read_text()
    assert "not running" in session("train-stop", "t")


def fake_cuda_library(containers: list[list[tuple[int, bytes]]]) -> tuple[bytes, int, int]:
    """A 64-bit ELF file whose ``.nv_fatbin`` section holds ``containers`` (fat binaries, each
    a list of ``(arch, cubin)`` entries, zero padding between them), with other bytes around
    it; the file and the section's offset and size."""
    slim = load_script("slim_onnxruntime_gpu")
    fatbin = b""
    for entries in containers:
        body = b"".join(
            slim.ENTRY_HEADER.pack(2, 0x0101, 64, len(cubin))
            + bytes(slim.ENTRY_ARCH_OFFSET - slim.ENTRY_HEADER.size)
            + arch.to_bytes(4, "little")
            + bytes(32)
            + cubin
            for arch, cubin in entries
        )
        fatbin += slim.CONTAINER_HEADER.pack(slim.FATBIN_MAGIC, 1, 16, len(body)) + body
        fatbin += bytes(8)
    names = b"\0.shstrtab\0.nv_fatbin\0"
    code = b"host code" * 10
    offset = 64 + len(code)
    shoff = offset + len(fatbin) + len(names)
    header = b"\x7fELF\x02\x01\x01" + bytes(33) + shoff.to_bytes(8, "little") + bytes(10)
    header += (64).to_bytes(2, "little") + (3).to_bytes(2, "little") + (1).to_bytes(2, "little")
    assert len(header) == 64

    def section(name_at: int, at: int, size: int) -> bytes:
        return name_at.to_bytes(4, "little") + bytes(20) + struct.pack("<QQ", at, size) + bytes(24)

    table = (
        bytes(64) + section(1, offset + len(fatbin), len(names)) + section(11, offset, len(fatbin))
    )
    return header + code + fatbin + names + table, offset, len(fatbin)


def test_slim_onnxruntime_gpu_keeps_one_architectures_cubins_in_place(tmp_path, capsys):
    """Each fat binary keeps its sm_90 entries byte for byte at its own address; the others'
    bytes are zeroed; one without sm_90 stays whole; every other file of the wheel is as it was
    (RECORD, whose hashes no longer hold, is left out); bad input is one line and exit 2."""
    slim = load_script("slim_onnxruntime_gpu")
    rng = np.random.default_rng(0)
    cubin = {arch: [rng.bytes(40 + 8 * i) for i in range(3)] for arch in (80, 90, 120)}
    containers = [
        [(80, cubin[80][0]), (90, cubin[90][0]), (120, cubin[120][0])],
        [(120, cubin[120][1])],  # no sm_90: left whole
        [(90, cubin[90][1]), (80, cubin[80][1]), (90, cubin[90][2])],
    ]
    library, offset, size = fake_cuda_library(containers)
    wheel = tmp_path / "onnxruntime_gpu-9.9-cp312-cp312-manylinux_2_28_x86_64.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        z.writestr("onnxruntime/__init__.py", "version = 9.9\n")
        z.writestr("onnxruntime/capi/libonnxruntime_providers_cuda.so", library)
        z.writestr("onnxruntime_gpu-9.9.dist-info/RECORD", "hashes\n")
    out = tmp_path / "ort.tar.xz"
    assert slim.main([str(wheel), "--arch", "90", "--out", str(out)]) == 0
    with tarfile.open(out) as t:
        assert sorted(t.getnames()) == [
            "onnxruntime/__init__.py",
            "onnxruntime/capi/libonnxruntime_providers_cuda.so",
        ]
        assert t.extractfile("onnxruntime/__init__.py").read() == b"version = 9.9\n"
        slimmed = t.extractfile("onnxruntime/capi/libonnxruntime_providers_cuda.so").read()
    assert len(slimmed) == len(library) and slim.elf_section(slimmed, ".nv_fatbin") == (
        offset,
        size,
    )
    assert (
        slimmed[:offset] == library[:offset]
        and slimmed[offset + size :] == library[offset + size :]
    )
    seen, at = [], offset
    while at < offset + size:  # the containers where they were, with what they keep
        magic, _, header, payload = slim.CONTAINER_HEADER.unpack_from(slimmed, at)
        if magic != slim.FATBIN_MAGIC:
            at += 8
            continue
        found = slim.entries(slimmed, at + header, at + header + payload)
        seen.append([(arch, slimmed[o + 64 : o + n]) for o, n, arch in found])
        (start,) = slim.CONTAINER_HEADER.unpack_from(library, at)[:1]
        assert start == slim.FATBIN_MAGIC  # a container starts where one started before
        at += header + slim.CONTAINER_HEADER.unpack_from(library, at)[3]
    assert seen == [
        [(90, cubin[90][0])],
        [(120, cubin[120][1])],
        [(90, cubin[90][1]), (90, cubin[90][2])],
    ]
    summary = json.loads(Path(f"{out}.json").read_text())
    assert summary["fatbin"]["containers_left_whole"] == 1
    assert summary["fatbin"]["kept"] == {
        "90": sum(len(c) + 64 for c in cubin[90]),
        "120": len(cubin[120][1]) + 64,
    }
    assert "kept sm_90" in capsys.readouterr().out

    assert slim.main([str(wheel), "--arch", "75", "--out", str(out)]) == 2
    assert "holds no cubin for sm_75" in capsys.readouterr().err
    not_elf = tmp_path / "not_elf.whl"
    with zipfile.ZipFile(not_elf, "w") as z:
        z.writestr("onnxruntime/capi/libonnxruntime_providers_cuda.so", b"text")
    assert slim.main([str(not_elf), "--out", str(out)]) == 2
    assert "not a 64-bit little-endian ELF file" in capsys.readouterr().err


def test_gpu_results_files_the_onnx_steps_rows_into_the_bench(tmp_path):
    """The ``onnx`` step's GPU section replaces docs' (the CPU rows stay), bench.md's GPU table
    is replaced by its rows (the rest, notes written by hand included, stays), and its text
    files are kept beside; what did not come back is named."""
    from spk2img.bench import gpu

    came, docs = tmp_path / "came", tmp_path / "docs"
    (came / "bench").mkdir(parents=True)
    docs.mkdir()
    shutil.copy(ROOT / "docs" / "bench.json", docs / "bench.json")
    before = (ROOT / "docs" / "bench.md").read_text()
    (docs / "bench.md").write_text(
        before.replace("## Speed and error", "A note.\n\n## Speed and error")
    )
    section = gpu.measured_section("cuda") | {"gpu": "NVIDIA H200"}
    section["rows"] = [{**r, "ms_per_frame": 4.0, "error": None} for r in gpu.planned_rows()[:3]]
    bench = json.loads((docs / "bench.json").read_text()) | {"gpu": section}
    (came / "bench" / "bench.json").write_text(json.dumps(bench))
    (came / "verify_fp16_cuda.txt").write_text("every case passed\n")
    said = load_script("gpu_results").take_results(came, tmp_path / "s", tmp_path / "r", docs)
    assert said[0] == f"GPU bench rows: 3 of 3 measured, into {docs}"
    assert "no onnxruntime.txt came back" in said and "no tensorrt.txt came back" in said
    assert said[-1].endswith("this command brought back no training report")
    filed = json.loads((docs / "bench.json").read_text())
    assert filed["gpu"]["rows"] == section["rows"]
    assert filed["rows"] == json.loads((ROOT / "docs" / "bench.json").read_text())["rows"]
    after = (docs / "bench.md").read_text()
    assert after.count("NVIDIA H200 (cuda) | 4.00 | 250 |") == 3 and "A note.\n" in after
    assert after.count(gpu.NO_GPU) == 0 and "not run" in after  # the service's rows
    heading = after.index("## On a GPU")
    assert after[:heading] == before[: before.index("## On a GPU")].replace(
        "## Speed and error", "A note.\n\n## Speed and error"
    )
    assert after[after.index("![PSNR") :] == before[before.index("![PSNR") :]
    assert (docs / "gpu_verify_fp16_cuda.txt").read_text() == "every case passed\n"


def test_a_runs_summary_carries_its_last_alignment_probe():
    records = [
        {"kind": "run", "train_config": {"batch_size": 64}},
        {"kind": "train", "step": 1, "steps_per_s": 2.0},
        {"kind": "train", "step": 2, "steps_per_s": 4.0},
        {"kind": "val", "step": 2, "psnr": 33.0, "alignment_slopes": {"align.dcn_pack.l1": 0.4}},
    ]
    metrics = "\n".join(json.dumps(r) for r in records).encode()
    summary = load_script("gpu_results").run_summary(metrics)
    assert summary["samples_per_s"] == 256 and summary["val_psnr"] == 33.0
    assert summary["alignment_slopes"] == {"align.dcn_pack.l1": 0.4}
    records[-1].pop("alignment_slopes")
    metrics = "\n".join(json.dumps(r) for r in records).encode()
    assert load_script("gpu_results").run_summary(metrics)["alignment_slopes"] is None


def test_every_listed_gpu_run_is_a_valid_training_run_of_this_tree():
    """Each run of scripts/gpu_runs.txt, with the flags the session adds, makes a valid
    ``TrainConfig`` (a bad flag would waste the GPU session it is found in), starts from a
    checkpoint this tree holds, and has a name of its own."""
    names = []
    for line in (ROOT / "scripts" / "gpu_runs.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, *flags = shlex.split(line)
        session = ["--device", "cuda", "--synthesis", "torch", "--run-dir", f"runs/{name}"]
        args = build_parser().parse_args(["train", *session, *flags])
        fields = {f.name for f in dataclasses.fields(TrainConfig)}
        values = {k: v for k, v in vars(args).items() if k in fields and v is not None}
        config = TrainConfig(**values)
        assert (ROOT / config.init).is_file(), config.init
        names.append(name)
    assert len(names) == len(set(names)) >= 2
