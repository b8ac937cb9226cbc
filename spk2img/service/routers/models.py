"""The served models."""

from __future__ import annotations

from fastapi import APIRouter

from spk2img.core.block_model import block_graph_paths
from spk2img.core.methods import METHODS
from spk2img.core.windows import NET_WINDOW

from ..schemas import ErrorDetail, ModelInfo, ModelsAnswer
from ..state import ServedModel, Service

router = APIRouter(prefix="/v1", tags=["models"])


@router.get("/models", responses={503: {"model": ErrorDetail, "description": "not loaded yet"}})
def list_models(model: ServedModel, service: Service) -> ModelsAnswer:
    """The model ``method=net`` runs, with its ONNX metadata, and every method."""
    parts = block_graph_paths(model.path).values() if service.codec is not None else []
    info = ModelInfo(
        name=model.metadata.get("name") or model.path.stem,
        file=model.path.name,
        window=NET_WINDOW,
        input_name=model.input_name,
        metadata=model.metadata,
        block_graphs=[path.name for path in parts],
        device=model.device,
        provider=model.provider,
    )
    return ModelsAnswer(models=[info], methods=list(METHODS))
