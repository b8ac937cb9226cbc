"""Natural training content from folders: photographs and video clips, indexed once per run.

``--data DIR`` may hold, at any depth:

- photographs: ``*.png``, ``*.jpg``, ``*.jpeg``, ``*.webp``, ``*.bmp``, ``*.tif`` files that are
  not frames of a clip;
- clips as folders of consecutively numbered frames (``clip/00000.png, 00001.png ...``, the REDS
  layout ``train_sharp/000/00000000.png`` among them): a folder whose image files, sorted by
  the number in their names, are at least :data:`MIN_CLIP_FRAMES` frames numbered consecutively;
- clips as video files (``*.mp4``, ``*.avi``, ``*.mkv``, ``*.mov``, ``*.webm``), decoded with
  PyAV.

Colour becomes luminance (ITU-R BT.601 weights, as Pillow's ``convert("L")``), and its 8-bit
values become light by one of two conventions (:data:`LIGHT_CONVENTIONS`): ``linear`` undoes the
display gamma, ``I = (v / 255) ** 2.2`` (docs/format.md); ``display`` takes the value itself as
the light, ``I = v / 255``, as the field's simulated datasets (spike-REDS) and its real-video
benchmark do.
A file that cannot be read, or is smaller than the training patch, is skipped and counted
(:attr:`SourceIndex.skipped`); it never stops a run.
"""

from __future__ import annotations

import functools
import os
import re
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from spk2img.io.light import DISPLAY_GAMMA

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".webm"}
MIN_CLIP_FRAMES = 3
"""A folder of at least this many consecutively numbered images is a clip."""
MAX_VIDEO_FRAMES = 250
"""Frames read from the start of a video file (a clip's motion needs only a few)."""
LIGHT_CONVENTIONS = ("linear", "display")
"""How 8-bit grey levels become light (module doc)."""


def to_light(grey: np.ndarray, convention: str = "linear") -> np.ndarray:
    """``(H, W) uint8`` grey levels -> ``(H, W) float32`` light in [0, 1]: ``(v / 255) ** 2.2``
    for the ``linear`` convention, ``v / 255`` for ``display`` (module doc)."""
    if convention not in LIGHT_CONVENTIONS:
        raise ValueError(f"light convention {convention!r}: use one of {LIGHT_CONVENTIONS}")
    light = np.asarray(grey, np.float32) / 255
    return light**DISPLAY_GAMMA if convention == "linear" else light


def read_grey(path: str | Path) -> np.ndarray:
    """An image file as ``(H, W) uint8`` luminance (display-encoded, not yet linear)."""
    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def read_video(path: str | Path, max_frames: int = MAX_VIDEO_FRAMES) -> list[np.ndarray]:
    """The first ``max_frames`` frames of a video file as ``(H, W) uint8`` luminance each."""
    import av  # the train extra

    frames = []
    with av.open(str(path)) as container:
        for frame in container.decode(video=0):
            frames.append(frame.to_ndarray(format="gray"))
            if len(frames) == max_frames:
                break
    return frames


@dataclass(frozen=True)
class Photo:
    path: Path


@dataclass(frozen=True)
class FrameFolder:
    """A clip stored as numbered image files, in frame order."""

    frames: tuple[Path, ...]

    @property
    def name(self) -> str:
        return self.frames[0].parent.name


@dataclass(frozen=True)
class VideoFile:
    path: Path

    @property
    def name(self) -> str:
        return self.path.stem


Clip = FrameFolder | VideoFile


@dataclass
class SourceIndex:
    """The photographs and clips under some folders (module doc), minus held-out names."""

    photos: list[Photo] = field(default_factory=list)
    clips: list[Clip] = field(default_factory=list)
    skipped: Counter = field(default_factory=Counter)
    """Files left out, by reason (``unreadable``, ``too small``, ``held out``)."""

    @classmethod
    def scan(
        cls, folders: list[str | Path], min_side: int, held_out: frozenset[str] = frozenset()
    ) -> SourceIndex:
        """Index ``folders``: every photo and clip whose shorter side is at least ``min_side``
        pixels and whose name (photo file name, clip folder or video stem) is not in
        ``held_out``. Reads each photo's and clip's size once (headers only where the format
        allows); warns once with the counts of what it skipped."""
        index = cls()
        for folder in folders:
            folder = Path(folder)
            if not folder.is_dir():
                raise FileNotFoundError(f"--data {folder}: not a folder")
            index._scan_folder(folder, min_side, held_out)
        index.photos.sort(key=lambda p: str(p.path))
        index.clips.sort(key=_clip_key)
        if index.skipped:
            counts = ", ".join(f"{n} {why}" for why, n in sorted(index.skipped.items()))
            warnings.warn(f"training data: skipped {counts}", stacklevel=2)
        return index

    def _scan_folder(self, folder: Path, min_side: int, held_out: frozenset[str]) -> None:
        for root, _, names in sorted(os.walk(folder)):
            directory = Path(root)
            images = sorted(
                (directory / n for n in names if Path(n).suffix.lower() in IMAGE_SUFFIXES),
                key=_frame_number_key,
            )
            clip_frames = _consecutive_frames(images)
            if clip_frames is not None:
                self._add(FrameFolder(tuple(clip_frames)), directory.name, min_side, held_out)
            else:
                for path in images:
                    self._add(Photo(path), path.name, min_side, held_out)
            for n in sorted(names):
                if Path(n).suffix.lower() in VIDEO_SUFFIXES:
                    path = directory / n
                    self._add(VideoFile(path), path.stem, min_side, held_out)

    def _add(self, source: Photo | Clip, name: str, min_side: int, held_out) -> None:
        if name in held_out:
            self.skipped["held out"] += 1
            return
        try:
            height, width = _size(source)
        except (OSError, UnidentifiedImageError, ValueError, ImportError) as exc:
            self.skipped["unreadable"] += 1
            hint = (
                " (video files need PyAV, the train extra)" if isinstance(exc, ImportError) else ""
            )
            warnings.warn(f"training data: cannot read {_where(source)}: {exc}{hint}", stacklevel=3)
            return
        if min(height, width) < min_side:
            self.skipped["too small"] += 1
            return
        (self.photos if isinstance(source, Photo) else self.clips).append(source)

    def summary(self) -> dict:
        """Counts for the run's log: photos, clips, frame folders, video files, skipped."""
        return {
            "photos": len(self.photos),
            "clips": len(self.clips),
            "video_files": sum(isinstance(c, VideoFile) for c in self.clips),
            "skipped": dict(self.skipped),
        }


def _frame_number_key(path: Path) -> tuple[int, str]:
    numbers = re.findall(r"\d+", path.stem)
    return (int(numbers[-1]) if numbers else -1, path.name)


def _consecutive_frames(images: list[Path]) -> list[Path] | None:
    """``images`` (sorted by number) if they are :data:`MIN_CLIP_FRAMES` or more consecutively
    numbered frames whose names differ only in that number, else None."""
    if len(images) < MIN_CLIP_FRAMES:
        return None
    stems = [re.sub(r"\d+(?=\D*$)", "#", p.stem) for p in images]
    numbers = [_frame_number_key(p)[0] for p in images]
    if len(set(stems)) != 1 or numbers[0] < 0:
        return None
    if numbers != list(range(numbers[0], numbers[0] + len(numbers))):
        return None
    return images


def _clip_key(clip: Clip) -> str:
    return str(clip.frames[0] if isinstance(clip, FrameFolder) else clip.path)


def _where(source: Photo | Clip) -> str:
    return str(source.frames[0].parent if isinstance(source, FrameFolder) else source.path)


def _size(source: Photo | Clip) -> tuple[int, int]:
    """``(height, width)`` of a photo or of a clip's frames; raises if unreadable."""
    if isinstance(source, VideoFile):
        frames = read_video(source.path, max_frames=MIN_CLIP_FRAMES)
        if len(frames) < MIN_CLIP_FRAMES:
            raise ValueError(f"fewer than {MIN_CLIP_FRAMES} frames")
        return frames[0].shape
    path = source.path if isinstance(source, Photo) else source.frames[0]
    with Image.open(path) as im:
        width, height = im.size
    return height, width


@functools.lru_cache(maxsize=1024)
def load_photo(path: Path, light: str = "linear") -> np.ndarray:
    """A photo as ``(H, W) float32`` light in [0, 1] by the ``light`` convention (cached per
    process and convention)."""
    return to_light(read_grey(path), light)


@functools.lru_cache(maxsize=64)
def load_clip(clip: Clip) -> tuple[np.ndarray, ...]:
    """A clip's frames as ``(H, W) uint8`` grey levels (cached per process; made light with
    :func:`to_light` after cropping)."""
    if isinstance(clip, VideoFile):
        frames = read_video(clip.path)
    else:
        frames = [read_grey(path) for path in clip.frames]
    if len({f.shape for f in frames}) != 1:
        raise ValueError(f"{_where(clip)}: frames of different sizes")
    return tuple(frames)
