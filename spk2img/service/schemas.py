"""Pydantic models of the HTTP API: query parameters, JSON answers, errors (OpenAPI shows them)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from spk2img.io.light import DISPLAY_GAMMA
from spk2img.io.spikes import DEFAULT_HEIGHT, DEFAULT_WIDTH
from spk2img.protocol.framing import FORMATS
from spk2img.runtime.adaptive import QUALITIES
from spk2img.runtime.methods import DEFAULT_TFP_WINDOW, METHODS
from spk2img.runtime.windows import MAX_BINNING

Method = Literal[METHODS]  # type: ignore[valid-type]
FrameFormat = Literal[tuple(FORMATS)]  # type: ignore[valid-type]
Quality = Literal[QUALITIES]  # type: ignore[valid-type]

CENTERS_PATTERN = r"^[0-9]{1,12}(,[0-9]{1,12})*$"


class ReconstructQuery(BaseModel):
    """Query parameters of ``POST /v1/reconstruct``; exactly one of ``centers`` and ``stride``."""

    model_config = ConfigDict(extra="forbid")

    height: int = Field(DEFAULT_HEIGHT, ge=1, le=1_000_000, description="frame height (pixels)")
    width: int = Field(DEFAULT_WIDTH, ge=1, le=1_000_000, description="frame width (pixels)")
    centers: str | None = Field(
        None,
        pattern=CENTERS_PATTERN,
        max_length=8192,  # the request line must fit uvicorn's 16 KiB header limit
        description="comma-separated centre frames, e.g. 40,80,120",
        examples=["40,80,120"],
    )
    stride: int | None = Field(
        None, ge=1, le=1_000_000_000, description="every stride-th frame with a full window"
    )
    method: Method = Field("net", description="net (the model), tfp or tfi")
    window: int = Field(
        DEFAULT_TFP_WINDOW,
        ge=1,
        le=1_000_000,
        description="TFP/TFI window (odd; net uses the model's window)",
    )
    quality: Quality = Field(
        "best",
        description="for net: best (the network everywhere), balanced (the network only on "
        "tiles that move or are dim, TFP elsewhere) or fast (TFP over the 41 frames)",
    )
    binning: int = Field(
        1,
        ge=1,
        le=MAX_BINNING,
        description="for net with quality best, on dim streams: stream frames merged into each "
        "of the network's frames (a window spans its window x binning frames; 1: none)",
    )
    format: FrameFormat = Field(
        "float32", description="float32 linear intensity, or uint8/png display values"
    )
    gamma: float = Field(
        DISPLAY_GAMMA, gt=0, le=100, description="display gamma for uint8/png (1: linear)"
    )

    @model_validator(mode="after")
    def _one_selector(self) -> ReconstructQuery:
        if (self.centers is None) == (self.stride is None):
            raise ValueError("give exactly one of centers and stride")
        return self


class ErrorDetail(BaseModel):
    """Every error answer: one line saying what was wrong."""

    detail: str


class Status(BaseModel):
    """A health or readiness answer."""

    status: str


class Ready(Status):
    """``GET /readyz`` when ready: also where the model runs."""

    device: str = Field(description="where the model runs: cpu, cuda or tensorrt")
    provider: str = Field(description="the onnxruntime execution provider in use")


class ModelInfo(BaseModel):
    """A served model: what ``method=net`` runs."""

    name: str = Field(description="the model's name (metadata 'name', else the file's stem)")
    method: Method = "net"
    file: str = Field(description="the ONNX file's name")
    window: int = Field(
        description="spike frames per reconstruction (the geometry's window_frames)"
    )
    geometry: dict[str, int] = Field(
        description="the frames the network reads and their blocks: window_frames, block_frames, "
        "block_stride (the stride at which centres share blocks), num_blocks, size_multiple"
    )
    input_name: str = Field(description="the graph's input")
    metadata: dict[str, str] = Field(description="the ONNX metadata_props")
    block_graphs: list[str] = Field(
        description="the block encoder and head files in use (empty: every window runs whole)"
    )
    device: str = Field(description="where the model runs: cpu, cuda or tensorrt")
    provider: str = Field(
        description="the onnxruntime execution provider in use, e.g. CUDAExecutionProvider"
    )
    self_ensemble: bool = Field(
        description="whether each image is the mean of the model on the stream and its three "
        "mirror images (the service's self_ensemble setting)"
    )


class ModelsAnswer(BaseModel):
    """``GET /v1/models``: the served models and every method."""

    models: list[ModelInfo]
    methods: list[Method]
