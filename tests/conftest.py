import importlib.util
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

SERVICE_LIMITS = tuple(
    "--threads 2 --workers 2 --max-queue 6 --max-body-bytes 3000000 --max-frames 2000 "
    "--max-pixels 100000 --max-window 101 --max-tfi-pending 16 --max-request-seconds 60".split()
)
"""The limits of the shared test service (small, so that the limit tests stay cheap)."""

LONGEST_FIRST = (
    "test_export.py",
    "test_bench.py",
    "test_training.py",
    "test_shipped_model.py",
    "test_docs_examples.py",
    "test_natural_data.py",
    "test_model_geometry.py",
)
"""The test files that take a minute or more on 2 cores, longest first. ``--dist loadfile``
hands the workers whole files in collection order: these go first, so that the short files fill
in at the end (one long file last keeps one worker busy while the other waits)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run :data:`LONGEST_FIRST` first, in its order; every other file keeps its place."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="session")
def standin_model(tmp_path_factory):
    """A TFP-41 ONNX graph standing in for a trained model (tests/onnx_models.py)."""
    from onnx_models import write_tfp41_model

    return write_tfp41_model(tmp_path_factory.mktemp("models") / "tfp41.onnx")


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory, worker_id) -> Path:
    """A folder all the workers of this test run share (pytest-xdist's workers each have their
    own base folder inside the run's): what one worker builds there, the others reuse."""
    base = tmp_path_factory.getbasetemp()
    return base if worker_id == "master" else base.parent


def built_once(run_dir: Path, name: str, build) -> Path:
    """The folder ``run_dir / name``, filled by ``build(folder)`` by the first worker that asks
    for it; the others wait for it and reuse it."""
    from filelock import FileLock

    folder = run_dir / name
    with FileLock(str(run_dir / f"{name}.lock")):
        if not folder.is_dir():
            partial = run_dir / f"{name}.partial"
            shutil.rmtree(partial, ignore_errors=True)
            partial.mkdir()
            build(partial)
            partial.rename(folder)
    return folder


@pytest.fixture(scope="session")
def tiny_checkpoint(run_dir):
    """A ``tiny`` checkpoint with random weights (tests/onnx_models.py), shared by the run."""
    from onnx_models import write_tiny_checkpoint

    return built_once(run_dir, "ckpt", lambda d: write_tiny_checkpoint(d / "tiny.pt")) / "tiny.pt"


@pytest.fixture(scope="session")
def three_block_export(run_dir):
    """A random-weight :data:`~onnx_models.THREE_BLOCKS` member (27-frame window) exported
    (one-shot and block graphs, as ``spk2img export`` does) and verified, its checkpoint beside it
    (same stem, ``.pt``); built once a run (about half a minute), shared by the workers."""
    from onnx_models import THREE_BLOCKS, write_tiny_checkpoint, write_tiny_export

    def build(folder: Path) -> None:
        write_tiny_export(
            write_tiny_checkpoint(folder / "three.pt", THREE_BLOCKS, seed=2), folder / "three.onnx"
        )

    return built_once(run_dir, "three-blocks", build) / "three.onnx"


@pytest.fixture(scope="session")
def three_block_checkpoint(three_block_export):
    """The checkpoint that :func:`three_block_export` exported."""
    return three_block_export.with_suffix(".pt")


@pytest.fixture(scope="session")
def service(standin_model):
    """A real ``spk2img serve`` (uvicorn, subprocess) serving the stand-in model."""
    from service_support import run_server

    with run_server(standin_model, *SERVICE_LIMITS) as server:
        yield server


@pytest.fixture(scope="session")
def grey_photo() -> np.ndarray:
    """matplotlib's grace_hopper sample photograph (evaluation-only data) as ``(H, W)
    float64`` grey levels in [0, 255]; skips without matplotlib (the dev extra)."""
    spec = importlib.util.find_spec("matplotlib")
    if spec is None:
        pytest.skip("matplotlib (dev extra) holds the sample photograph")
    path = Path(spec.submodule_search_locations[0], "mpl-data", "sample_data", "grace_hopper.jpg")
    with Image.open(path) as im:
        return np.asarray(im.convert("L"), np.float64)
