"""The spike-REDS streams that the SpikeZoo toolkit bundles in its PyPI package: the field's
benchmark protocol on real video, for evaluation only (never trained, tuned or chosen on).

SpikeZoo 0.2.3.7 (``pip install --no-deps spikezoo==0.2.3.7``: a 16 MB wheel, MIT licence; its
streams are simulated from REDS video, CC BY 4.0) keeps five streams under
``spikezoo/data/base/{train,test}/spike/NAME.dat`` (301 frames of 250x400 each, the format of
docs/format.md) with their truth images ``.../gt/NAME.png``. Its own protocol, followed here:
the middle 41 frames of a stream (``T // 2 - 20 .. T // 2 + 20``), the truth the image's grey
level / 255 as light (display-referred, no gamma undone: spike rate = 0.6 x value / 255), whole
frames. The package is only read (:func:`toolkit_data_root` locates it without importing it,
so none of its many dependencies is needed).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from spk2img.io.spikes import read_spikes

TOOLKIT = "spikezoo"
TOOLKIT_PIN = "spikezoo==0.2.3.7"
"""The release whose bundled streams were measured here (docs/spike_reds.md)."""
DATA_FOLDER = Path("data") / "base"
"""Where the package keeps the streams, under its folder."""
WINDOW = 41
"""Frames around the middle of a stream that a method sees (the toolkit's window)."""


class BenchmarkDataError(ValueError):
    """No benchmark streams where they were looked for (the message says how to get them)."""


@dataclass(frozen=True)
class BenchmarkStream:
    """One stream and its truth image."""

    name: str
    """The stream's file stem (``200_part1_key_id151``)."""
    split: str
    """The toolkit's folder it came from (``train`` or ``test``): both are scored."""
    spikes: Path
    truth: Path


def toolkit_data_root() -> Path:
    """The streams' folder of the installed SpikeZoo package (found, not imported);
    :class:`BenchmarkDataError` if it is not installed."""
    spec = importlib.util.find_spec(TOOLKIT)
    if spec is None or not spec.submodule_search_locations:
        raise BenchmarkDataError(
            f"{TOOLKIT} is not installed: pip install --no-deps {TOOLKIT_PIN} (its data only "
            "are read), or give --root FOLDER of <split>/spike/*.dat and <split>/gt/*.png"
        )
    return Path(list(spec.submodule_search_locations)[0]) / DATA_FOLDER


def find_streams(root: str | Path) -> list[BenchmarkStream]:
    """Every ``<split>/spike/NAME.dat`` under ``root`` that has a ``<split>/gt/NAME.png``,
    sorted by name; :class:`BenchmarkDataError` if there is none."""
    root = Path(root)
    streams = [
        BenchmarkStream(
            dat.stem, dat.parent.parent.name, dat, dat.parent.parent / "gt" / f"{dat.stem}.png"
        )
        for dat in root.glob("*/spike/*.dat")
    ]
    found = sorted((s for s in streams if s.truth.is_file()), key=lambda s: s.name)
    if not found:
        raise BenchmarkDataError(f"{root}: no <split>/spike/NAME.dat with a <split>/gt/NAME.png")
    return found


def load_window(stream: BenchmarkStream) -> tuple[np.ndarray, np.ndarray]:
    """The stream's middle :data:`WINDOW` frames ``(41, H, W) uint8`` and its truth
    ``(H, W) float32`` light in [0, 1] (grey level / 255); the truth's size is the frames'."""
    with Image.open(stream.truth) as image:
        grey = np.asarray(image.convert("L"))
    height, width = grey.shape
    frames = read_spikes(stream.spikes, height, width)
    middle = len(frames) // 2
    if middle < WINDOW // 2 or len(frames) - middle <= WINDOW // 2:
        raise BenchmarkDataError(f"{stream.spikes}: {len(frames)} frames, fewer than {WINDOW}")
    spikes = np.asarray(frames[middle - WINDOW // 2 : middle + WINDOW // 2 + 1], np.uint8)
    return spikes, grey.astype(np.float32) / 255
