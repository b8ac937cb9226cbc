"""The served models."""

from __future__ import annotations

from fastapi import APIRouter

from spk2img.core.methods import METHODS
from spk2img.core.windows import NET_WINDOW

from ..schemas import ErrorDetail, ModelInfo, ModelsAnswer
from ..state import ServedModel

router = APIRouter(prefix="/v1", tags=["models"])


@router.get("/models", responses={503: {"model": ErrorDetail, "description": "not loaded yet"}})
def list_models(model: ServedModel) -> ModelsAnswer:
    """The model ``method=net`` runs, with its ONNX metadata, and every method."""
    info = ModelInfo(
        name=model.metadata.get("name") or model.path.stem,
        file=model.path.name,
        window=NET_WINDOW,
        input_name=model.input_name,
        metadata=model.metadata,
    )
    return ModelsAnswer(models=[info], methods=list(METHODS))
