"""The ``spk2img`` command line (SPEC §6). Each subcommand is a module with ``add_parser`` and
``run``; heavy imports (torch, onnxruntime, fastapi) happen inside ``run`` only."""

from __future__ import annotations

import argparse
import importlib
import sys

from spk2img import __version__
from spk2img.core.errors import InputError

SUBCOMMANDS = [
    "reconstruct",
    "simulate",
    "fit-sensor",
    "models",
    "train",
    "export",
    "verify",
    "serve",
    "bench",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="spk2img", description="Spike-camera streams to images (Spk2ImgNet, TFP, TFI)."
    )
    parser.add_argument("--version", action="version", version=f"spk2img {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        module = importlib.import_module(f"spk2img.cli.{name.replace('-', '_')}")
        module.add_parser(sub)
        sub.choices[name].set_defaults(run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse ``argv`` and run the subcommand; input errors exit 2 with one line."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (InputError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        print(f"spk2img {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("spk2img: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
