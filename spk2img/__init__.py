"""spk2img: spike-camera streams to images.

The public API (:mod:`spk2img.api`, loaded on first use so that ``import spk2img`` stays light)::

    import spk2img

    spikes = spk2img.read_spikes("rec.dat", 250, 400)      # (T, H, W) 0/1
    frames, centers = spk2img.reconstruct(spikes, stride=7)  # (N, H, W) float32 linear [0, 1]
    recon = spk2img.Reconstructor("net")                    # one loaded model, many streams
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = [
    "Reconstruction",
    "Reconstructor",
    "__version__",
    "read_spikes",
    "reconstruct",
    "suggest_binning",
    "write_spikes",
]

if TYPE_CHECKING:
    from spk2img.api import (
        Reconstruction,
        Reconstructor,
        read_spikes,
        reconstruct,
        suggest_binning,
        write_spikes,
    )


def __getattr__(name: str) -> Any:
    if name in __all__:
        from spk2img import api

        return getattr(api, name)
    raise AttributeError(f"module 'spk2img' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
