"""Self-ensemble: the network on a stream and its three mirror images, mirrored back and
averaged; mirror-equivariant where the network alone is not, the same through block reuse and
whole windows, and reachable from the API, the CLI and the service."""

import httpx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from service_support import OCTET, parse_frames, run_app_server

import spk2img
from spk2img.cli import main
from spk2img.errors import InputError
from spk2img.io.spikes import pack_frames
from spk2img.runtime.onnx_backend import OnnxModel
from spk2img.runtime.self_ensemble import MIRRORS, SelfEnsemblePredictor, mirror
from spk2img.sim.scenes import random_scene
from spk2img.sim.simulator import SensorConfig, simulate

HEIGHT, WIDTH = 26, 35  # odd and not a multiple of the pyramid's 4: padding differs per view


@pytest.fixture(scope="module")
def scene_stream():
    """A fast-moving simulated scene, real-like sensor: ``(90, 26, 35)`` uint8."""
    rng = np.random.default_rng(5151)
    return simulate(
        random_scene(rng, HEIGHT, WIDTH, "fast", "normal"), 90, SensorConfig.real(), rng
    )


def test_the_self_ensemble_is_mirror_equivariant_and_the_network_alone_is_not(scene_stream):
    network = OnnxModel("tiny", threads=1)
    ensemble = SelfEnsemblePredictor(network)
    window = scene_stream[None, 20:61].astype(np.float32)
    plain, averaged = network(window), ensemble(window)
    assert ensemble.geometry == network.geometry  # the wrapped predictor's attributes
    assert np.abs(averaged - plain).max() > 1e-3  # it is not the network alone
    # the four views as one batch (as on a GPU) give the four calls' image
    batched = SelfEnsemblePredictor(network, batch_views=True)
    np.testing.assert_allclose(batched(window), averaged, atol=1e-6)
    for axes in MIRRORS[1:]:
        mirrored = mirror(window, axes)
        np.testing.assert_allclose(ensemble(mirrored), mirror(averaged, axes), atol=2e-6)
        assert np.abs(network(mirrored) - mirror(plain, axes)).max() > 1e-3


@given(
    batch=st.integers(1, 3),
    height=st.integers(1, 9),
    width=st.integers(1, 9),
    seed=st.integers(0, 2**16),
    batch_views=st.booleans(),
)
@settings(max_examples=40, deadline=None)
def test_the_mean_of_views_is_equivariant_for_any_predictor(
    batch, height, width, seed, batch_views
):
    """A predictor that weighs every pixel by its place (no mirror symmetry of its own), called
    once a view or once with all four views as one batch."""
    rng = np.random.default_rng(seed)
    weights = rng.random((height, width)).astype(np.float32)
    calls: list[int] = []

    def weigh(windows: np.ndarray) -> np.ndarray:
        calls.append(len(windows))
        return windows.mean(axis=1, dtype=np.float32) * weights

    ensemble = SelfEnsemblePredictor(weigh, batch_views)
    windows = (rng.random((batch, 5, height, width)) < 0.4).astype(np.float32)
    expected = np.mean([mirror(weigh(mirror(windows, a)), a) for a in MIRRORS], axis=0)
    calls.clear()
    np.testing.assert_allclose(ensemble(windows), expected, atol=1e-6)
    assert calls == ([4 * batch] if batch_views else [batch] * 4)
    for axes in MIRRORS:
        np.testing.assert_allclose(
            ensemble(mirror(windows, axes)), mirror(ensemble(windows), axes), atol=1e-6
        )


def test_streams_average_the_mirrored_streams_and_keep_block_reuse(scene_stream):
    """The API's self-ensemble with block reuse equals it on whole windows, and the mean of the
    plain network on the four mirrored streams; every block is encoded once per view."""
    plain = spk2img.Reconstructor(model="tiny", threads=1)
    reused = spk2img.Reconstructor(model="tiny", threads=1, self_ensemble=True)
    whole = spk2img.Reconstructor(model="tiny", threads=1, self_ensemble=True, block_reuse=False)
    frames, centers = reused.reconstruct(scene_stream, stride=7)
    whole_frames, whole_centers = whole.reconstruct(scene_stream, stride=7)
    np.testing.assert_array_equal(centers, whole_centers)
    np.testing.assert_allclose(frames, whole_frames, atol=1e-5)
    views = []
    for axes in MIRRORS:
        view, _ = plain.reconstruct(mirror(scene_stream, axes), stride=7)
        views.append(mirror(view, axes))
    np.testing.assert_allclose(frames, np.mean(views, axis=0), atol=1e-5)
    assert reused.last_stream.blocks_encoded == plain.last_stream.blocks_encoded


def test_only_the_network_has_a_self_ensemble(tmp_path, capsys):
    with pytest.raises(InputError, match="self_ensemble is for method net"):
        spk2img.Reconstructor("tfp", self_ensemble=True)
    stream = tmp_path / "s.npz"
    spk2img.write_spikes(stream, np.zeros((50, 8, 8), np.uint8))
    argv = ["reconstruct", str(stream), "--out", str(tmp_path / "o.npz"), "--self-ensemble"]
    assert main([*argv, "--url", "http://127.0.0.1:9"]) != 0
    assert "drop --model/--checkpoint/--backend/--device/--self-ensemble" in capsys.readouterr().err
    assert main([*argv, "--method", "tfp"]) != 0
    assert "self_ensemble is for method net" in capsys.readouterr().err


def test_the_service_runs_and_reports_its_self_ensemble(standin_model, scene_stream):
    """The stand-in model (TFP-41) is mirror-symmetric: its self-ensemble gives its frames."""
    from spk2img.service.reconstruction import SELF_ENSEMBLE_BYTES_PER_PIXEL, job_memory
    from spk2img.service.schemas import ReconstructQuery

    with run_app_server(standin_model, self_ensemble=True) as server:
        (info,) = server.get("/v1/models").json()["models"]
        assert info["self_ensemble"] is True
        response = httpx.post(
            f"{server.url}/v1/reconstruct?height={HEIGHT}&width={WIDTH}&centers=20,40",
            content=pack_frames(scene_stream),
            headers=OCTET,
            timeout=30,
        )
        settings_ = server.state.settings
        geometry = server.state.network.geometry
    assert response.status_code == 200
    frames, centers = spk2img.Reconstructor("tfp").reconstruct(scene_stream, centers=[20, 40])
    got, _ = parse_frames(response.content)
    assert [f.center for f in got] == list(centers)
    np.testing.assert_allclose([f.image for f in got], frames, atol=1e-6)
    query = ReconstructQuery(height=HEIGHT, width=WIDTH, centers="20")
    alone = settings_.model_copy(update={"self_ensemble": False})
    padded = np.prod(geometry.padded_size(HEIGHT, WIDTH))
    assert (
        job_memory(query, settings_, 0, geometry) - job_memory(query, alone, 0, geometry)
        == padded * SELF_ENSEMBLE_BYTES_PER_PIXEL
    )
