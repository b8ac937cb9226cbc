"""ONNX export: graph contract, metadata, torch/onnxruntime parity (hard cases included), the
DeformConv graph, reduced precision, and the CLI paths that use an export."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
import torch.nn.functional as F
from onnx import numpy_helper
from onnx_models import EXPORT_EXAMPLE_SIZE, THREE_BLOCKS, TINY_TRAIN_COMMIT

from spk2img import __version__
from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.export import hard_cases, pipeline
from spk2img.export.block_graphs import block_parity
from spk2img.export.metadata import weights_sha256
from spk2img.export.onnx_export import (
    ExportConfig,
    check_graph,
    graph_props,
    one_shot_io,
    operator_counts,
    random_source,
    weight_arrays,
    write_weights,
)
from spk2img.export.pipeline import export_verified
from spk2img.export.quantize import MIN_PSNR_VS_FP32, precision_report, reduce_precision
from spk2img.export.sampling_ops import sampling_as_custom_ops
from spk2img.export.verify import ATOL, reference_model, verify_onnx
from spk2img.model.checkpoint import (
    config_to_dict,
    load_checkpoint,
    load_model,
    save_checkpoint,
)
from spk2img.model.config import MEMBERS
from spk2img.model.deform_conv import ModulatedDeformConv2d
from spk2img.runtime.block_codec import block_graph_paths
from spk2img.runtime.onnx_backend import OnnxModel, shipped_models
from spk2img.runtime.torch_backend import TorchPredictor

torch.set_num_threads(1)
EXAMPLE = ExportConfig(example_height=EXPORT_EXAMPLE_SIZE, example_width=EXPORT_EXAMPLE_SIZE)


def _windows(seed: int, batch: int, height: int, width: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.concatenate([hard_cases.simulated_windows(rng, height, width) for _ in range(batch)])


def test_graph_contract(three_block_export):
    model = onnx.load(three_block_export)
    check_graph(model, one_shot_io(27))  # checker (full), standard domains, I/O names, dynamic dims
    ops = operator_counts(model)
    assert {domain for domain, _ in ops} == {""}
    assert ops[("", "GridSample")] == 3 and ("", "DeformConv") not in ops
    assert [(o.domain, o.version) for o in model.opset_import] == [("", 18)]
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in model.graph.initializer)
    # the one-shot graph, and the block encoder and head beside it: one file each
    files = sorted(p.name for p in three_block_export.parent.glob("*.onnx"))
    assert files == ["three.encoder.onnx", "three.head.onnx", "three.onnx"]


def _io_dims(model: onnx.ModelProto) -> dict[str, list[str | int]]:
    values = [*model.graph.input, *model.graph.output]
    return {
        v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim] for v in values
    }


def test_block_graph_contract(three_block_export):
    """The encoder's and head's I/O as docs/export.md states it, with named dims, and the same
    weights and metadata as the one-shot graph."""
    one_shot = {p.key: p.value for p in onnx.load(three_block_export).metadata_props}
    parts = {part: onnx.load(path) for part, path in block_graph_paths(three_block_export).items()}
    io = {part: _io_dims(model) for part, model in parts.items()}
    assert io["encoder"] == {
        "block": ["batch", 13, "height", "width"],
        **{
            f"{r}_l{i}": ["batch", 12, f"h_l{i}", f"w_l{i}"]
            for r in ("feat", "nbr", "key")
            for i in (1, 2)
        },
    }
    assert io["head"] == {
        **{f"feat_l{i}": ["batch", 3, 12, f"h_l{i}", f"w_l{i}"] for i in (1, 2)},
        **{f"nbr_l{i}": ["batch", 2, 12, f"h_l{i}", f"w_l{i}"] for i in (1, 2)},
        **{f"key_l{i}": ["batch", 12, f"h_l{i}", f"w_l{i}"] for i in (1, 2)},
        "image": ["batch", 1, "padded_height", "padded_width"],
    }
    for part, model in parts.items():
        meta = {p.key: p.value for p in model.metadata_props}
        assert meta == {**one_shot, "part": part}
        assert {domain for domain, _ in operator_counts(model)} == {""}


def test_metadata(three_block_export, three_block_checkpoint):
    meta = OnnxModel(three_block_export, threads=1).metadata
    state = load_checkpoint(three_block_checkpoint)
    assert meta["name"] == "spk2img-custom" and meta["member"] == "custom"
    assert meta["version"] == __version__
    assert json.loads(meta["config"]) == state["config"]
    assert (meta["window"], meta["rate"]) == ("27", "0.6")
    assert meta["weights_sha256"] == weights_sha256(state["model"])
    commit = (meta["training_commit"], meta["training_commit_source"])
    assert commit == (TINY_TRAIN_COMMIT, "checkpoint")
    random_meta = random_source("tiny").metadata  # no checkpoint: the exporting tree's commit
    assert random_meta["training_commit_source"] in ("git HEAD at export", "unknown")
    assert (meta["graph"], meta["opset"], meta["precision"]) == ("grid_sample", "18", "fp32")
    assert meta["source"] == "three.pt, step 0"


def test_weights_sha256_is_defined_by_names_and_values():
    state = random_source("tiny").model.state_dict()
    reordered = dict(reversed(list(state.items())))
    assert weights_sha256(reordered) == weights_sha256(state)
    changed = dict(state)
    changed["fusion.reconstruct.4.bias"] = state["fusion.reconstruct.4.bias"] + 1e-6
    assert weights_sha256(changed) != weights_sha256(state)


def test_verify_cli_quick_passes_on_hard_cases(
    three_block_export, three_block_checkpoint, tmp_path
):
    out = tmp_path / "verify.json"
    checkpoint = ["--checkpoint", str(three_block_checkpoint)]
    args = ["verify", str(three_block_export), *checkpoint, "--quick"]
    assert main([*args, "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["passed"] and report["atol"] == ATOL
    cases = {r["case"] for r in report["results"]}
    for name in (
        "dark (all 0)",
        "saturated (all 1)",
        "single spike",
        "checkerboard flicker",
        "far offsets (1e5 px)",
        "scene 17x23",
        "scene 250x250",
    ):
        assert name in cases
    assert {r["threads"] for r in report["results"]} == {1, 2}
    for r in report["results"]:
        assert r["nonfinite"] == 0 and r["max_abs"] <= ATOL


def test_verify_finds_its_weights_and_refuses_others(three_block_export, tmp_path):
    beside = reference_model(three_block_export)  # the checkpoint of the same stem
    expected = OnnxModel(three_block_export, 1).metadata["weights_sha256"]
    assert weights_sha256(beside.state_dict()) == expected
    alone = tmp_path / "alone.onnx"  # without the checkpoint beside it
    alone.write_bytes(three_block_export.read_bytes())
    with pytest.raises(InputError, match="--checkpoint"):
        reference_model(alone)
    other = random_source(THREE_BLOCKS, seed=4).model
    wrong = tmp_path / "wrong.pt"
    save_checkpoint(wrong, model=other.state_dict(), config=config_to_dict(other.config), step=0)
    with pytest.raises(InputError, match="weights_sha256"):
        reference_model(three_block_export, wrong)
    assert main(["verify", str(three_block_export), "--checkpoint", str(wrong)]) == 2
    # a mismatch the verifier must catch: the graph against a different network
    cases = hard_cases.size_cases(((17, 23),), threads=(1,))
    report = verify_onnx(three_block_export, other, cases)
    assert not report.passed and "FAIL" in report.table()


def test_rewritten_weights_give_the_graph_of_the_changed_network(
    three_block_export, three_block_checkpoint
):
    """The far-offset variant that verify checks: the graph with the variant's weights written
    over its own runs as the variant does in torch (every tap about 1e5 px outside the image),
    where the graph as exported does not. A graph whose named weight is not the one it was
    said to hold, or a constant two weights share whose new values differ, is left untouched."""
    model = load_model(three_block_checkpoint)
    far = hard_cases.far_offset_copy(model)
    own, new = weight_arrays(model.state_dict()), weight_arrays(far.state_dict())
    changed = {name for name in own if not np.array_equal(own[name], new[name])}
    assert changed and all("conv_offset_mask" in name for name in changed)
    graph = onnx.load(three_block_export)
    assert changed <= write_weights(graph, own, new)
    windows = model.config.geometry.crop(hard_cases.scene_cases()[0].spikes, axis=1)
    session = ort.InferenceSession(graph.SerializeToString(), providers=["CPUExecutionProvider"])
    rewritten = session.run(None, {"spikes": windows})[0][:, 0]
    with torch.inference_mode():
        expected = far(torch.from_numpy(windows))[0][:, 0].numpy()
    assert np.abs(rewritten - expected).max() <= ATOL
    unchanged = OnnxModel(three_block_export, 1)(windows)
    assert np.abs(unchanged - expected).max() > 10 * ATOL  # the graph as exported fails it
    before = graph.SerializeToString()
    assert write_weights(graph, own, new) is None  # it no longer holds `own`
    assert graph.SerializeToString() == before


def test_a_folded_weight_is_found_by_its_value_unless_two_weights_share_it():
    """An initializer not named after a weight but equal to one (the exporter's reshaped PReLU
    slopes) is rewritten with that weight's new value; one that two weights share is rewritten
    where their new values agree and refused where they differ; other constants stay."""
    slope = np.full((1,), 0.25, np.float32)

    def graph():
        folded = numpy_helper.from_array(slope.reshape(1, 1, 1, 1), "val_7")
        constant = numpy_helper.from_array(np.full((1,), 2.0, np.float32), "scale")
        return onnx.helper.make_model(
            onnx.helper.make_graph([], "g", [], [], initializer=[folded, constant])
        )

    def values(model):
        return {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}

    model = graph()
    written = write_weights(model, {"model.a": slope}, {"model.a": np.full((1,), 0.5, np.float32)})
    assert written == {"model.a"}
    assert values(model)["val_7"].shape == (1, 1, 1, 1) and values(model)["val_7"].item() == 0.5
    assert values(model)["scale"].item() == 2.0
    old = {"model.a": slope, "model.b": slope}
    agree = {name: np.full((1,), 0.5, np.float32) for name in old}
    assert write_weights(graph(), old, agree) == {"model.a", "model.b"}
    model = graph()
    differ = {"model.a": np.full((1,), 0.5, np.float32), "model.b": np.full((1,), 0.75, np.float32)}
    assert write_weights(model, old, differ) is None
    assert values(model)["val_7"].item() == 0.25


def test_a_checkpoint_of_a_shipped_architecture_takes_its_traced_graphs(
    tmp_path, capsys, monkeypatch
):
    """Exporting a fine-tuned ``default`` (every weight changed, the fusion's PReLU slopes, which
    the exporter folds into constants of other names, included) writes its weights into the
    shipped model's traced graphs instead of tracing: no written graph keeps a weight of the
    shipped model, and the graphs agree with the changed network in torch, one-shot and
    streamed, at sizes beside the export's own checks."""
    shipped = shipped_models()["default"]
    model = load_model(shipped.with_suffix(".pt"))
    generator = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for weight in model.parameters():
            weight.mul_(1 + 0.05 * torch.randn(weight.shape, generator=generator))
    tuned = tmp_path / "tuned.pt"
    save_checkpoint(tuned, config=config_to_dict(model.config), model=model.state_dict(), step=9)
    monkeypatch.setattr(pipeline, "export_onnx", None)  # tracing would fail
    monkeypatch.setattr(pipeline, "export_block_graphs", None)
    out = tmp_path / "tuned.onnx"
    assert main(["export", str(tuned), "--out", str(out), "--deform-conv"]) == 0
    assert "graphs: spk2img-default.onnx's trace" in capsys.readouterr().out
    shipped_weights = {
        array.tobytes()
        for array in weight_arrays(load_model(shipped.with_suffix(".pt")).state_dict()).values()
    }
    for path in [out, *block_graph_paths(out).values()]:
        graph = onnx.load(path)
        assert graph_props(graph)["weights_sha256"] == weights_sha256(model.state_dict())
        held = {numpy_helper.to_array(i).tobytes() for i in graph.graph.initializer}
        assert not held & shipped_weights, path.name
    cases = hard_cases.size_cases(((29, 41),), threads=(1,))
    assert verify_onnx(out, model, cases).passed
    assert block_parity(out, model, height=21, width=30) <= ATOL


def _ran(op: str, function, *args, **kwargs) -> tuple[bool, torch.Tensor]:
    """Whether ``function(*args, **kwargs)`` ran the custom op ``op``, and its result."""
    with torch.autograd.profiler.profile() as prof:
        result = function(*args, **kwargs)
    return op in {e.name for e in prof.function_events}, result


def test_bilinear_sampling_is_traced_as_one_op_and_nothing_else_is():
    """While exporting, bilinear F.grid_sample without aligned corners and F.interpolate by
    an integer factor are custom ops whose results are exactly the F functions' (every padding
    mode, factors 2 and 4); other modes, conventions and sizes are left to F; afterwards F's
    functions are themselves again."""
    original = F.grid_sample, F.interpolate
    rng = torch.Generator().manual_seed(0)
    x, grid = torch.rand(2, 3, 5, 7, generator=rng), torch.rand(2, 4, 6, 2, generator=rng) * 3 - 1.5
    sample, upsample = "spk2img::grid_sample_bilinear", "spk2img::upsample_bilinear"
    with sampling_as_custom_ops():
        assert (F.grid_sample, F.interpolate) != original
        for padding in ("zeros", "border", "reflection"):
            kwargs = {"padding_mode": padding, "align_corners": False}
            routed, result = _ran(sample, F.grid_sample, x, grid, **kwargs)
            assert routed and torch.equal(result, original[0](x, grid, **kwargs))
        for kwargs in ({"mode": "nearest", "align_corners": False}, {"align_corners": True}):
            routed, result = _ran(sample, F.grid_sample, x, grid, **kwargs)
            assert not routed and torch.equal(result, original[0](x, grid, **kwargs))
        for factor in (2, 4):
            kwargs = {"scale_factor": factor, "mode": "bilinear", "align_corners": False}
            routed, result = _ran(upsample, F.interpolate, x, **kwargs)
            assert routed and torch.equal(result, original[1](x, **kwargs))
        for kwargs in (
            {"scale_factor": 2.5, "mode": "bilinear", "align_corners": False},
            {"scale_factor": 2, "mode": "bilinear", "align_corners": True},
            {"size": (9, 9), "mode": "bilinear", "align_corners": False},
            {"scale_factor": 2, "mode": "nearest"},
        ):
            routed, result = _ran(upsample, F.interpolate, x, **kwargs)
            assert not routed and torch.equal(result, original[1](x, **kwargs))
    assert (F.grid_sample, F.interpolate) == original


def test_paper_width_exports_as_deform_conv_nodes_and_verifies(tmp_path, monkeypatch):
    """The published width (64 channels, 8 deformable groups, the three-level pyramid; two of
    its ten residual blocks: the others add more of the same convs) traced with each deformable
    conv as one standard ``DeformConv`` node (opset 19, where the other tests trace the
    ``GridSample`` graph, the same code for every member), verified against torch like every
    export: on the hard cases, then at two more sizes. Offered a reused graph that computes
    another network (here the shipped ``default``'s), the export traces after all."""
    shipped = shipped_models()["default"]

    def wrong_reuse(template, source, out, config, block_graphs):
        shutil.copy(shipped, out)
        return True

    monkeypatch.setattr(pipeline, "find_template", lambda *args: shipped)
    monkeypatch.setattr(pipeline, "reuse_graphs", wrong_reuse)
    source = random_source(dataclasses.replace(MEMBERS["paper"], residual_blocks=2), seed=0)
    config = dataclasses.replace(EXAMPLE, graph="deform_conv")
    result = export_verified(source, tmp_path / "paper.onnx", config, block_graphs=False)
    assert result.reused is None
    model = onnx.load(result.path)
    ops = operator_counts(model)
    deform_convs = sum(isinstance(m, ModulatedDeformConv2d) for m in source.model.modules())
    assert ops[("", "DeformConv")] == deform_convs == source.model.config.pyramid_levels + 1
    assert ("", "GridSample") not in ops and {domain for domain, _ in ops} == {""}
    assert [(o.domain, o.version) for o in model.opset_import] == [("", 19)]
    cases = hard_cases.size_cases(((17, 23), (24, 32)), threads=(1,))
    report = verify_onnx(result.path, source.model, cases)
    assert result.parity.passed and report.passed, report.table()
    assert OnnxModel(result.path, 1).metadata["weights_sha256"] == weights_sha256(
        source.model.state_dict()
    )


def test_a_member_guided_by_its_blocks_motion_exports_with_block_graphs_that_agree(tmp_path):
    """A full-size member whose alignment its blocks' Lucas-Kanade motion guides, found at 1/4
    size over two levels (so it pads to 8, past its pyramid's 4), and whose offset convs read
    that motion too (random convs, where training starts them at zero): the one-shot graph and
    the block graphs, whose code now carries the SALI estimates the head finds the motion from,
    agree with torch (streams with block reuse at 17x23 and at 16x24, a multiple of 8; one
    Gauss-Newton step a level, for a shorter trace)."""
    config = dataclasses.replace(
        THREE_BLOCKS,
        flow_guided=True,
        offsets_read_motion=True,
        motion_stride=4,
        motion_levels=2,
        motion_window=7,
        motion_iterations=1,
    )
    assert config.size_multiple == 8
    source = random_source(config, seed=2)
    assert all(conv.weight.abs().max() > 0 for conv in source.model.align.motion_conv.values())
    result = export_verified(source, tmp_path / "guided.onnx", EXAMPLE, reuse=False)
    assert result.parity.passed and result.block_parity <= ATOL
    names = [o.name for o in onnx.load(block_graph_paths(result.path)["encoder"]).graph.output]
    assert names[-1] == "sali"
    assert block_parity(result.path, source.model, 16, 24, frames=40) <= ATOL


def test_onnx_backend_agrees_with_torch_predictor(three_block_export, three_block_checkpoint):
    windows = THREE_BLOCKS.geometry.crop(_windows(6, 3, 21, 30), axis=1)
    torch_out = TorchPredictor(three_block_checkpoint, threads=1)(windows)
    onnx_out = OnnxModel(three_block_export, threads=1)(windows)
    assert onnx_out.shape == torch_out.shape == (3, 21, 30)
    assert torch_out.std() > 1e-3  # an image, not the 0 that a random network can give
    assert np.abs(onnx_out - torch_out).max() <= ATOL


def test_reconstruct_cli_onnx_and_torch_backends_agree(
    three_block_export, three_block_checkpoint, tmp_path
):
    spikes = (np.random.default_rng(7).uniform(size=(60, 19, 26)) < 0.3).astype(np.uint8)
    np.save(tmp_path / "x.npy", spikes)
    common = ["reconstruct", str(tmp_path / "x.npy"), "--method", "net", "--centers", "20,30,39"]
    common += ["--no-progress", "--threads", "1"]
    onnx_args = ["--model", str(three_block_export)]
    assert main([*common, "--out", str(tmp_path / "o.npz"), *onnx_args]) == 0
    torch_args = ["--backend", "torch", "--checkpoint", str(three_block_checkpoint)]
    assert main([*common, "--out", str(tmp_path / "t.npz"), *torch_args]) == 0
    onnx_run, torch_run = np.load(tmp_path / "o.npz"), np.load(tmp_path / "t.npz")
    assert onnx_run["frames"].shape == (3, 19, 26)
    assert list(onnx_run["centers"]) == list(torch_run["centers"]) == [20, 30, 39]
    assert np.abs(onnx_run["frames"] - torch_run["frames"]).max() <= ATOL


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_reduced_precision_variants_run_close_to_fp32(three_block_export, tmp_path, precision):
    out = tmp_path / f"{precision}.onnx"
    model = reduce_precision(three_block_export, out, precision)  # includes check_graph
    assert {p.key: p.value for p in model.metadata_props}["precision"] == precision
    report = precision_report(three_block_export, out)
    assert report["nonfinite"] == 0 and report["psnr_vs_fp32_db"] >= MIN_PSNR_VS_FP32


@pytest.mark.parametrize(
    "argv",
    [
        "export --out m.onnx",  # neither a checkpoint nor --random-weights
        "export --out m.onnx --random-weights",  # no member
        "export --out m.onnx --random-weights --member huge",
        "export c.pt --out m.onnx --member tiny",
        "export --out m.txt --random-weights --member tiny",
        "export --out m.onnx --random-weights --member tiny --example-size x",
    ],
)
def test_export_cli_rejects_bad_arguments(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(argv.split()) == 2
    assert "error" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_verify_stops_at_a_camera_frame_unless_asked_for_the_full_set(capsys):
    from spk2img.export.hard_cases import DEFAULT_SIZES, FULL_SIZES, QUICK_SIZES

    assert max(DEFAULT_SIZES) == (250, 400) and (1000, 1000) in FULL_SIZES
    assert set(QUICK_SIZES) < set(DEFAULT_SIZES) < set(FULL_SIZES)
    with pytest.raises(SystemExit):
        main(["verify", "m.onnx", "--quick", "--full"])
    assert "not allowed with argument" in capsys.readouterr().err
