"""The served models."""

from __future__ import annotations

from fastapi import APIRouter

from spk2img.runtime.block_codec import block_graph_paths
from spk2img.runtime.methods import METHODS
from spk2img.runtime.self_ensemble import SelfEnsemblePredictor

from ..schemas import ErrorDetail, ModelInfo, ModelsAnswer
from ..state import ServedNetwork

router = APIRouter(prefix="/v1", tags=["models"])


@router.get("/models", responses={503: {"model": ErrorDetail, "description": "not loaded yet"}})
def list_models(network: ServedNetwork) -> ModelsAnswer:
    """The model ``method=net`` runs, with its geometry and ONNX metadata, and every method."""
    model = network.predict
    parts = block_graph_paths(model.path).values() if network.codec is not None else []
    info = ModelInfo(
        name=model.metadata.get("name") or model.path.stem,
        file=model.path.name,
        window=network.geometry.window_frames,
        geometry=network.geometry.as_dict(),
        input_name=model.input_name,
        metadata=model.metadata,
        block_graphs=[path.name for path in parts],
        device=model.device,
        provider=model.provider,
        self_ensemble=isinstance(model, SelfEnsemblePredictor),
    )
    return ModelsAnswer(models=[info], methods=list(METHODS))
