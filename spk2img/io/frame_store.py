"""Reconstructed frames kept as they come, so that an interrupted run loses nothing done.

``spk2img reconstruct … --out OUT.npz`` writes its frames into ``OUT.npz.partial/`` while it
runs: ``run.json`` (the arguments that decide the frames) and chunks ``chunk_000000.npz`` …,
each a complete ``.npz`` (``frames (n, H, W) float32``, ``centers (n,) int64``) renamed into
place once written, so the folder is valid after every flush, whatever stops the run. At the
end the chunks become ``OUT.npz`` and the folder goes. A run with ``--resume`` and the same
arguments reads the chunks back and reconstructs only the centres still owed.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from spk2img.errors import InputError

CHUNK_FRAMES = 16
"""Frames held in memory before a chunk is written."""
FLUSH_SECONDS = 30.0
"""A chunk is also written when the oldest frame held is this old."""
RUN_FILE = "run.json"


def partial_dir(out: Path) -> Path:
    """Where the frames of a run writing ``out`` are kept until it ends: ``OUT.npz.partial``."""
    return out.with_name(out.name + ".partial")


def _write_npz(path: Path, frames: np.ndarray, centers: np.ndarray) -> None:
    """Write ``path`` whole or not at all (a temporary file renamed into place)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        np.savez_compressed(handle, frames=frames, centers=centers)
    os.replace(tmp, path)


class FrameStore:
    """The frames of one run writing ``out``, kept in :func:`partial_dir` as they come.

    Args:
        out: the ``.npz`` the run ends with.
        run: the arguments that decide the frames (JSON-able); a resumed run must match them.
        resume: continue the run kept in :func:`partial_dir` (:attr:`done` holds its centres).

    Raises :class:`InputError` when a kept run is there and ``resume`` is not asked for, when
    ``resume`` is asked for with other arguments than the kept run's, or with nothing kept.
    """

    def __init__(self, out: Path, run: dict, resume: bool = False):
        self.out, self.dir = out, partial_dir(out)
        self._frames: list[np.ndarray] = []
        self._centers: list[int] = []
        self._held_since: float | None = None
        self._chunks = 0
        if not resume:
            self.discard_if_empty()  # left by a run that failed before its first frame
        if self.dir.is_dir():
            if not resume:
                raise InputError(
                    f"{self.dir} holds the frames of an interrupted run: add --resume to "
                    "continue it, or delete the folder to start again"
                )
            try:
                kept = json.loads((self.dir / RUN_FILE).read_text())
            except (OSError, ValueError):
                raise InputError(
                    f"{self.dir / RUN_FILE} is missing or damaged, so the kept frames cannot be "
                    "matched to their arguments: delete the folder to start again"
                ) from None
            changed = sorted(k for k in {*kept, *run} if kept.get(k) != run.get(k))
            if changed:
                raise InputError(
                    f"{self.dir} was made with other arguments ({', '.join(changed)}): run it "
                    "again as it was, or delete the folder"
                )
            self._chunks = len(self._chunk_paths())
        elif resume:
            raise InputError(f"nothing to resume: no {self.dir}")
        else:
            self.dir.mkdir(parents=True)
            (self.dir / RUN_FILE).write_text(json.dumps(run, indent=1, sort_keys=True))
        self.done = {int(k) for _, centers in self._read_chunks() for k in centers}
        """Centres already kept (by an earlier, interrupted run)."""

    def discard_if_empty(self) -> None:
        """Remove :func:`partial_dir` when it keeps no frame (a run that failed before its
        first one leaves nothing behind)."""
        if not self._frames and not self._chunk_paths():
            shutil.rmtree(self.dir, ignore_errors=True)

    def _chunk_paths(self) -> list[Path]:
        return sorted(self.dir.glob("chunk_*.npz"))

    def _read_chunks(self):
        for path in self._chunk_paths():
            with np.load(path) as chunk:
                yield chunk["frames"], chunk["centers"]

    def add(self, center: int, image: np.ndarray) -> None:
        """Keep one frame; a chunk is written every :data:`CHUNK_FRAMES` frames or
        :data:`FLUSH_SECONDS` seconds."""
        self._frames.append(np.asarray(image, np.float32))
        self._centers.append(int(center))
        self._held_since = self._held_since or time.monotonic()
        if (
            len(self._frames) >= CHUNK_FRAMES
            or time.monotonic() - self._held_since >= FLUSH_SECONDS
        ):
            self.flush()

    def flush(self) -> None:
        """Write the frames held as the next chunk (nothing when none is held)."""
        if not self._frames:
            return
        path = self.dir / f"chunk_{self._chunks:06d}.npz"
        _write_npz(path, np.stack(self._frames), np.asarray(self._centers, np.int64))
        self._chunks += 1
        self.done.update(self._centers)
        self._frames, self._centers, self._held_since = [], [], None

    @property
    def kept(self) -> int:
        """Frames kept in chunks or held."""
        return len(self.done) + len(self._frames)

    def finish(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Write ``out`` from every chunk, in centre order, remove :func:`partial_dir`; return
        ``frames (N, H, W) float32`` and ``centers (N,) int64``."""
        self.flush()
        chunks = list(self._read_chunks())
        if chunks:
            frames = np.concatenate([f for f, _ in chunks])
            centers = np.concatenate([c for _, c in chunks]).astype(np.int64)
        else:
            frames, centers = np.zeros((0, height, width), np.float32), np.zeros(0, np.int64)
        order = np.argsort(centers, kind="stable")
        frames, centers = frames[order], centers[order]
        self.out.parent.mkdir(parents=True, exist_ok=True)
        _write_npz(self.out, frames, centers)
        shutil.rmtree(self.dir)
        return frames, centers
