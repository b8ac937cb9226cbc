"""Service settings, declared once: environment variables ``SPK2IMG_<NAME>`` and the flags of
``spk2img serve``.

Every field is both: ``max_body_bytes`` is ``SPK2IMG_MAX_BODY_BYTES`` and ``--max-body-bytes``
(:mod:`spk2img.cli.serve` builds the flags from the fields: name, type, default and the
description as help); flags win over the environment. A new field is a new flag.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from spk2img.hardware import available_cores

LogLevel = Literal["critical", "error", "warning", "info", "debug"]
Device = Literal["cpu", "auto", "cuda", "tensorrt"]


class ServiceSettings(BaseSettings):
    """What the service loads, where it listens and how much one request may use."""

    model_config = SettingsConfigDict(env_prefix="SPK2IMG_", extra="ignore")

    model: str | Path | None = Field(
        None,
        description="ONNX model file for method net, or a shipped model's name (`spk2img "
        "models` lists them; default: the shipped default)",
    )
    host: str = Field("127.0.0.1", description="interface to listen on")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0: any free port)")
    device: Device = Field(
        "cpu",
        description="where onnxruntime runs the model: cpu, auto (cuda when it can run here, "
        "else cpu; the log and /v1/models say which), cuda or tensorrt (the gpu extra, "
        "docs/gpu.md); a GPU device onnxruntime cannot run here stops the service at start",
    )
    threads: int = Field(
        default_factory=available_cores,
        ge=1,
        description="CPU threads for reconstruction in all (default: the cores available)",
    )
    workers: int | None = Field(
        None, ge=1, description="reconstruction jobs run at once (default: threads)"
    )
    max_queue: int = Field(
        8, ge=0, description="requests admitted beyond the workers; more get 503"
    )
    max_body_bytes: int = Field(256 * 2**20, ge=1, description="upload size limit in bytes")
    max_frames: int = Field(20_000, ge=1, description="spike frames per request")
    read_ahead_bytes: int = Field(
        4 * 2**20,
        ge=1,
        description="upload bytes read ahead of the reconstruction (reserved per request): a "
        "client that sends its body before reading and then leaves is noticed at once when "
        "the rest of its body fits here",
    )
    max_pixels: int = Field(512 * 512, ge=1, description="height*width limit in pixels")
    max_window: int = Field(
        401, ge=1, description="largest window in frames (TFP/TFI's, or the network's 41 x binning)"
    )
    max_tfi_pending: int = Field(
        64, ge=1, description="TFI centres waiting for a pixel's next spike"
    )
    max_request_seconds: float = Field(
        300.0, gt=0, description="wall time of one request in seconds, upload included"
    )
    batch: int = Field(1, ge=1, description="41-frame windows per model call")
    block_reuse: bool = Field(
        True,
        description="encode each 13-frame block once when centres share blocks (stride a "
        "multiple of 7), with the encoder and head graphs beside the model",
    )
    self_ensemble: bool = Field(
        False,
        description="run the model on each stream and its three mirror images and average "
        "the four images mirrored back: four times the time for a better image "
        "(docs/real_video.md)",
    )
    upload_read_timeout_seconds: float = Field(
        10.0,
        gt=0,
        description="longest wait for the next piece of an upload; longer is 408 (in-band "
        "after the first frame)",
    )
    min_upload_bytes_per_second: int = Field(
        1024,
        ge=0,
        description="slowest average upload: a request may wait for its body at most "
        "upload_read_timeout_seconds + bytes received / this rate in all (0: no minimum)",
    )
    header_timeout_seconds: float = Field(
        10.0,
        gt=0,
        description="time to send a whole request head, from connecting or from the end of "
        "the previous response on a kept-alive connection; the connection is closed after it",
    )
    keep_alive_seconds: int = Field(
        5, ge=1, description="an idle kept-alive connection is closed after this (uvicorn)"
    )
    max_connections: int = Field(
        256, ge=1, description="open connections; more are answered 503 and closed at once"
    )
    health_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="a second listener on the same host answering only /healthz and /readyz "
        "(0: any free port), for an orchestrator's probes: connections held on the main port "
        "never fail them; none by default",
    )
    max_head_bytes: int = Field(
        16384, ge=1024, description="request line and headers in bytes (h11); more is 400"
    )
    response_buffer_bytes: int = Field(
        32 * 2**20,
        ge=0,
        description="frames held for a client that is not reading yet; a Content-Length upload "
        "whose frames could exceed it needs the header X-Spk2img-Duplex: 1 (413 without)",
    )
    memory_budget_bytes: int = Field(
        1536 * 2**20,
        ge=0,
        description="memory all admitted reconstructions may use together (estimated per "
        "request); past it a request gets 503 with Retry-After",
    )
    retry_after_seconds: int = Field(1, ge=0, description="the Retry-After of a 503 in seconds")
    log_level: LogLevel = Field("info", description="uvicorn's log level")

    @field_validator("device")
    @classmethod
    def _device_runs_here(cls, device: str) -> str:
        """``cuda``/``tensorrt`` only where onnxruntime has the provider (the service refuses
        to start otherwise; whether the GPU itself starts is checked when the model loads)."""
        if device in ("cuda", "tensorrt"):
            from spk2img.runtime.onnx_backend import DeviceError, resolve_device

            try:
                resolve_device(device)
            except DeviceError as exc:
                raise ValueError(str(exc)) from None
        return device

    @property
    def model_path(self) -> Path:
        """The model file to serve: ``model`` (a file or a shipped model's name) or the shipped
        default; :class:`~spk2img.errors.InputError` when there is no such model."""
        from spk2img.runtime.onnx_backend import model_path

        return model_path(self.model)

    @property
    def job_workers(self) -> int:
        """Threads of the reconstruction pool."""
        return self.workers or self.threads

    @property
    def intra_op_threads(self) -> int:
        """onnxruntime intra-op threads per job, so that all jobs together use ``threads``."""
        return max(1, self.threads // self.job_workers)
