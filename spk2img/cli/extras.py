"""Which optional dependencies ("extras") a command needs, decided in one place.

:func:`required_extra` reads the parsed arguments and names the extra the command will need (or
None); :func:`missing_extra` says whether its modules are importable, without importing them.
``spk2img`` calls it before it runs a command and prints one line naming the extra to install
(exit :data:`EXIT_MISSING_EXTRA`), never a traceback. An ``ImportError`` of one of these
modules that still escapes a command is turned into the same line (:func:`extra_for_module`).
"""

from __future__ import annotations

import argparse
import importlib.util
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from spk2img.errors import InputError

EXIT_MISSING_EXTRA = 3
"""The exit code of a command whose optional dependencies are not installed."""

EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "serve": (
        "onnxruntime",
        "fastapi",
        "uvicorn",
        "pydantic",
        "pydantic_settings",
        "prometheus_client",
    ),
    "client": ("httpx", "h11"),
    "train": ("torch", "av", "cv2"),
    "export": ("torch", "onnx", "onnxscript", "onnxruntime"),
    "all": (
        "onnxruntime",
        "fastapi",
        "uvicorn",
        "pydantic_settings",
        "prometheus_client",
        "httpx",
        "torch",
        "onnx",
        "onnxscript",
        "av",
        "cv2",
        "matplotlib",
    ),
}
"""The top-level modules each extra of pyproject.toml installs (``all`` with ``dev``'s
matplotlib, which ``bench`` plots with)."""
TRAINING_MODULES = tuple(m for m in EXTRA_MODULES["train"] if m != "av")
"""What ``spk2img train`` cannot run without (PyAV only decodes video files)."""


@dataclass(frozen=True)
class Need:
    """What a command needs: ``modules`` importable, from ``extra``, for ``what``."""

    extra: str
    what: str
    modules: tuple[str, ...]


def required_extra(args: argparse.Namespace) -> Need | None:
    """The extra the parsed command needs, or None when the base install runs it.

    - ``reconstruct``: ``--url`` the client extra; ``--method net`` (quality best or balanced)
      onnxruntime from the serve extra, or torch from the train extra with ``--backend torch``;
      ``tfp``, ``tfi`` and ``--quality fast`` nothing.
    - ``models``: torch (train extra); ``train``: the train extra's torch and OpenCV (PyAV only
      decodes video files, which a run without it skips and names, as any unreadable source:
      the GPU machines' image has no PyAV); ``export`` and ``verify``: the
      export extra; ``serve``: the serve extra; ``bench``: every extra (``all``), but with
      ``--gpu-only`` the export extra (its service rows say so when the serve extra is absent).
    - ``simulate``, ``fit-sensor``: nothing.
    """
    command = args.command
    if command == "reconstruct":
        if getattr(args, "url", None):
            return Need("client", "--url", EXTRA_MODULES["client"])
        if args.method != "net" or args.quality == "fast":
            return None
        if args.backend == "torch":
            return Need("train", "--backend torch", ("torch",))
        return Need("serve", "--method net", ("onnxruntime",))
    if command == "models":
        return Need("train", "models", ("torch",))
    if command == "train":
        return Need("train", "training", TRAINING_MODULES)
    if command in ("export", "verify"):
        return Need("export", command, EXTRA_MODULES["export"])
    if command == "serve":
        return Need("serve", "serving", EXTRA_MODULES["serve"])
    if command == "bench" and getattr(args, "gpu_only", False):
        return Need("export", "bench --gpu-only", EXTRA_MODULES["export"])
    if command == "bench":
        return Need("all", "bench", EXTRA_MODULES["all"])
    return None


def module_available(name: str) -> bool:
    """Whether ``name`` can be imported (found on the path; it is not imported)."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def missing_extra(
    args: argparse.Namespace, available: Callable[[str], bool] | None = None
) -> str | None:
    """The one-line message for a command whose extra is not installed, or None.

    ``available(module)`` says whether a module is installed (default :func:`module_available`).
    """
    need = required_extra(args)
    if need is None:
        return None
    available = available or module_available
    absent = [m for m in need.modules if not available(m)]
    return extra_message(need.extra, need.what, absent) if absent else None


def extra_message(extra: str, what: str, absent: list[str]) -> str:
    """``--method net needs the serve extra (not installed: onnxruntime): pip install -e
    ".[serve]" in a checkout, or pip install "spk2img[serve]"``."""
    return (
        f"{what} needs the {extra} extra (not installed: {', '.join(absent)}): "
        f'pip install -e ".[{extra}]" in a checkout, or pip install "spk2img[{extra}]"'
    )


def extra_for_module(name: str | None) -> str | None:
    """The extra that installs the top-level module of ``name`` (``torch.nn`` -> ``train``)."""
    top = (name or "").partition(".")[0]
    for extra, modules in EXTRA_MODULES.items():
        if top in modules:
            return extra
    return None


class MissingExtra(InputError):
    """A command's optional dependencies are not installed; the message names the extra."""


@contextmanager
def needs_extra(extra: str, what: str) -> Iterator[None]:
    """Turn an ``ImportError`` inside the block into :class:`MissingExtra` naming ``extra``."""
    try:
        yield
    except ImportError as exc:
        raise MissingExtra(extra_message(extra, what, [exc.name or str(exc)])) from exc
