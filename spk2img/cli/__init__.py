"""The ``spk2img`` command line (docs/cli.md). Each subcommand is a module with ``add_parser`` and
``run``; heavy imports (torch, onnxruntime, fastapi) happen inside ``run`` only, and
:mod:`spk2img.cli.extras` decides before ``run`` whether the extra a command needs is there."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from spk2img import __version__
from spk2img.cli.extras import (
    EXIT_MISSING_EXTRA,
    MissingExtra,
    extra_for_module,
    extra_message,
    missing_extra,
)
from spk2img.cli.interrupts import exit_code, interrupt_message, sigterm_as_interrupt
from spk2img.errors import InputError

SUBCOMMANDS = [
    "reconstruct",
    "inspect",
    "simulate",
    "fit-sensor",
    "models",
    "train",
    "pack-data",
    "export",
    "verify",
    "serve",
    "bench",
]


PATH_ERRORS = (
    FileNotFoundError,
    FileExistsError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
)
"""OS errors that a path the user gave causes (a missing input, a file where a folder must go):
one line and exit 2, like an :class:`InputError`."""


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
    """Entry point: parse ``argv`` and run the subcommand. Input errors exit 2 and a missing
    extra exits 3, each with one line on stderr (docs/cli.md)."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    problem = missing_extra(args)  # before unknown flags: without its extra, a command may
    if problem:  # lack flags (serve builds them from the serve extra's settings)
        return _fail(args, problem, EXIT_MISSING_EXTRA)
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        with sigterm_as_interrupt():
            code = int(args.run(args) or 0)
        sys.stdout.flush()  # a reader that left is found here, not at exit
        return code
    except MissingExtra as exc:
        return _fail(args, str(exc), EXIT_MISSING_EXTRA)
    except (InputError, *PATH_ERRORS) as exc:
        return _fail(args, str(exc), 2)
    except ModuleNotFoundError as exc:
        extra = extra_for_module(exc.name)
        if extra is None:
            raise
        return _fail(args, extra_message(extra, args.command, [exc.name]), EXIT_MISSING_EXTRA)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (cli.interrupts)
        print(f"spk2img: {interrupt_message(exc)}", file=sys.stderr)
        return exit_code(exc)
    except BrokenPipeError:  # the reader left (`spk2img models | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no error at exit
        return 141


def _fail(args: argparse.Namespace, message: str, code: int) -> int:
    print(f"spk2img {args.command}: error: {message}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
