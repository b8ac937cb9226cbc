"""``spk2img serve``: the streaming reconstruction service (docs/service.md).

The flags are built from the fields of :class:`spk2img.service.settings.ServiceSettings`, the
one declaration of the service's settings: ``--max-body-bytes`` is the field ``max_body_bytes``,
its help is the field's description. Flags take text and the settings model checks it, so a bad
value (from a flag or the environment) is one line naming the flag and the variable, exit 2.
"""

from __future__ import annotations

import argparse
import socket
import typing
from typing import Any

from spk2img.errors import InputError

DEFAULT_MODEL_HINT = (
    " (the shipped default model is not installed: pass --model MODEL.onnx or set SPK2IMG_MODEL)"
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the HTTP reconstruction service",
        description="Serve POST /v1/reconstruct, GET /v1/models, /healthz, /readyz and /metrics "
        "(docs/service.md). Each flag is also an environment variable SPK2IMG_<NAME>; flags win.",
    )
    try:
        from spk2img.service.settings import ServiceSettings
    except ImportError:  # no serve extra: main() names it, whatever the flags
        p.description += ' The flags need the serve extra: pip install -e ".[serve]".'
        return
    for name, field in ServiceSettings.model_fields.items():
        p.add_argument(
            flag_name(name),
            dest=name,
            default=None,  # absent: the environment or the field's default
            metavar=_metavar(name, field.annotation),
            help=_help(name, field).replace("%", "%%"),
        )


def run(args: argparse.Namespace) -> int:
    from spk2img.service.app import load_served_network  # the serve extra (cli.extras)
    from spk2img.service.server import run as serve

    settings = settings_from_args(args)
    if not settings.model_path.is_file():  # a --model that is no model raised already
        raise InputError(f"no model file at {settings.model_path}{DEFAULT_MODEL_HINT}")
    for flag, port in (("--port", settings.port), ("--health-port", settings.health_port)):
        check_port_free(settings.host, port, flag)
    # loaded before the server starts: a model or device that cannot run is one line, not a
    # server's traceback
    serve(settings, load_served_network(settings))
    return 0


def check_port_free(host: str, port: int | None, flag: str) -> None:
    """:class:`InputError` when ``host:port`` cannot be listened on now (in use, or a host that
    is not this machine's); None and 0 (any free port) always can."""
    if not port:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise InputError(
                f"{flag} {port}: cannot listen on {host}:{port} ({exc.strerror})"
            ) from None


def settings_from_args(args: argparse.Namespace):
    """:class:`~spk2img.service.settings.ServiceSettings` from the environment, overridden by
    the flags given (raises :class:`InputError` for a bad value)."""
    from pydantic import ValidationError

    from spk2img.service.settings import ServiceSettings

    given = {
        name: value
        for name in ServiceSettings.model_fields
        if (value := getattr(args, name, None)) is not None
    }
    try:
        return ServiceSettings(**given)
    except ValidationError as exc:
        problems = "; ".join(_setting_problem(error) for error in exc.errors())
        raise InputError(f"bad settings: {problems}") from exc


def flag_name(name: str) -> str:
    """The flag of the setting ``name``: ``max_queue`` -> ``--max-queue``."""
    return "--" + name.replace("_", "-")


def env_name(name: str) -> str:
    """The environment variable of the setting ``name``: ``max_queue`` -> ``SPK2IMG_MAX_QUEUE``."""
    from spk2img.service.settings import ServiceSettings

    return ServiceSettings.model_config["env_prefix"] + name.upper()


def _metavar(name: str, annotation: Any) -> str:
    """``{a,b}`` for a choice or a bool, else the name in capitals."""
    choices: tuple = ()
    if annotation is bool:
        choices = ("true", "false")
    elif typing.get_origin(annotation) is typing.Literal:
        choices = typing.get_args(annotation)
    return "{" + ",".join(map(str, choices)) + "}" if choices else name.upper()


def _help(name: str, field) -> str:
    """The field's description, its default unless the description says it, and its variable."""
    text = field.description or name.replace("_", " ")
    default = field.get_default(call_default_factory=False)
    if "default" not in text and field.default_factory is None and default is not None:
        shown = str(default).lower() if isinstance(default, bool) else default
        text += f" (default {shown})"
    return f"{text}; env {env_name(name)}"


def _setting_problem(error: dict) -> str:
    name = "_".join(str(part) for part in error["loc"])
    return f"{flag_name(name)} ({env_name(name)}): {error['msg']}"
