"""``spk2img serve``: the streaming reconstruction service (docs/service.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from spk2img.cli.extras import needs_extra
from spk2img.core.errors import InputError

DEFAULT_MODEL_HINT = (
    " (the shipped default model is not installed: pass --model MODEL.onnx or set SPK2IMG_MODEL)"
)
LOG_LEVELS = ("critical", "error", "warning", "info", "debug")


def _parse_bool(text: str) -> bool:
    value = text.strip().lower()
    if value not in ("true", "false", "1", "0", "yes", "no"):
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")
    return value in ("true", "1", "yes")


# one flag per field of spk2img.service.settings.ServiceSettings (a test keeps them in step);
# absent flags leave the environment or the default, so the parser needs no pydantic import
FLAGS = [
    ("model", Path, "ONNX model for method net (default: the shipped model)"),
    ("host", str, "interface to listen on (default 127.0.0.1)"),
    ("port", int, "TCP port (default 8000)"),
    ("threads", int, "CPU threads for reconstruction in all (default: the cores available)"),
    ("workers", int, "reconstruction jobs run at once (default: threads)"),
    ("max_queue", int, "requests admitted beyond the workers; more get 503 (default 8)"),
    ("max_body_bytes", int, "upload size limit in bytes (default 256 MiB)"),
    ("max_frames", int, "spike frames per request (default 20000)"),
    ("max_pixels", int, "height*width limit (default 262144)"),
    ("max_window", int, "largest TFP/TFI window (default 401)"),
    ("max_tfi_pending", int, "TFI centres waiting for a pixel's next spike (default 64)"),
    ("max_request_seconds", float, "wall time of one request, upload included (default 300)"),
    ("batch", int, "41-frame windows per model call (default 1)"),
    (
        "block_reuse",
        _parse_bool,
        "encode each 13-frame block once when centres share blocks, with the encoder and head "
        "graphs beside the model: true or false (default true)",
    ),  # fmt: skip
    ("retry_after_seconds", int, "the Retry-After of a 503 (default 1)"),
    ("log_level", str, "uvicorn's log level (default info)"),
]


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the HTTP reconstruction service",
        description="Serve POST /v1/reconstruct, GET /v1/models, /healthz, /readyz and /metrics "
        "(docs/service.md). Each flag is also an environment variable SPK2IMG_<NAME>; flags win.",
    )
    for name, kind, text in FLAGS:
        p.add_argument(
            f"--{name.replace('_', '-')}",
            type=kind,
            default=None,
            choices=LOG_LEVELS if name == "log_level" else None,
            help=f"{text}; env SPK2IMG_{name.upper()}",
        )


def run(args: argparse.Namespace) -> int:
    with needs_extra("serve", "serving"):
        import uvicorn

        from spk2img.service.app import create_app

    settings = settings_from_args(args)
    if not settings.model_path.is_file():
        hint = DEFAULT_MODEL_HINT if settings.model is None else ""
        raise InputError(f"no model file at {settings.model_path}{hint}")
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=5,
    )
    return 0


def settings_from_args(args: argparse.Namespace):
    """:class:`~spk2img.service.settings.ServiceSettings` from the environment, overridden by
    the flags given (raises :class:`InputError` for a bad value)."""
    from pydantic import ValidationError

    from spk2img.service.settings import ServiceSettings

    given = {name: getattr(args, name) for name, _, _ in FLAGS if getattr(args, name) is not None}
    try:
        return ServiceSettings(**given)
    except ValidationError as exc:
        problems = "; ".join(_setting_problem(error) for error in exc.errors())
        raise InputError(f"bad settings: {problems}") from exc


def _setting_problem(error: dict) -> str:
    name = "_".join(str(part) for part in error["loc"])
    return f"--{name.replace('_', '-')} (SPK2IMG_{name.upper()}): {error['msg']}"
