"""The one message for a command whose optional dependencies are not installed."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from spk2img.core.errors import InputError


@contextmanager
def needs_extra(extra: str, what: str) -> Iterator[None]:
    """Turn an ``ImportError`` inside the block into an :class:`InputError` naming the extra."""
    try:
        yield
    except ImportError as exc:
        raise InputError(
            f"{what} needs the {extra} extra: pip install 'spk2img[{extra}]' ({exc})"
        ) from exc
