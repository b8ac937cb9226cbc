"""``python -m spk2img.service serve [FLAGS]``: ``spk2img serve`` with the connection-level
limits of :mod:`spk2img.service.server` (header timeout, connection cap, half-close, keep-alive
and head-size settings). The flags are ``spk2img serve``'s."""

from __future__ import annotations

import argparse
import sys

from spk2img.cli.serve import DEFAULT_MODEL_HINT, add_parser, settings_from_args
from spk2img.core.errors import InputError

from .server import run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m spk2img.service")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        settings = settings_from_args(args)
        if not settings.model_path.is_file():
            hint = DEFAULT_MODEL_HINT if settings.model is None else ""
            raise InputError(f"no model file at {settings.model_path}{hint}")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run(settings)
    return 0


if __name__ == "__main__":
    sys.exit(main())
