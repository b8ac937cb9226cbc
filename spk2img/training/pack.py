"""The training data as one file that travels: ``spk2img pack-data``.

A pack is a zip archive (stored, not recompressed: the photos and frames keep their own files,
byte for byte, at full stored resolution) of every source the training index finds under the
``--data`` folders, laid out as there (so ``--data`` on the unpacked folder finds the same
photos and clips), with each folder's ``MANIFEST.*`` and ``licences/``:

- ``train``: the sources training may draw from;
- ``validation``: with ``--with-validation``, the held-out sources (:data:`~spk2img.evaluation.
  natural_validation.NEVER_TRAINED`: the natural validation's photos and clips, the real-video
  clips), which the training index skips by name, packed so that a run elsewhere validates as
  it does here (56 MiB of the project's collection);
- ``left_out``: otherwise, the held-out sources' names: never trained on, not packed. Their
  real-video clips' windows that training validates on are packed instead, filmed here
  (:data:`REAL_VIDEO_WINDOWS`, a few MiB against their clips' 56: ``spk2img train
  --real-video-windows`` reads them), so that a run elsewhere still validates on real video and
  chooses its ``best.pt`` as a run here does.

``PACK.json`` inside lists them, by name, with their files. The archive is then split into
parts of at most ``--part-mib`` (:mod:`spk2img.parts`) for a machine that receives 64 MiB a
command; docs/gpu.md gives the steps there.

``--max-mib`` packs a subset that fits, for a run that starts from one command: every
source's files stay byte for byte, and :func:`compact` chooses which (the training sources
only; the held-out ones, and the manifests and licences, are packed whole or not at all).
``PACK.json``'s ``compact`` says what was kept of what.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

from spk2img.evaluation.natural_validation import NEVER_TRAINED
from spk2img.evaluation.real_video import save_windows, training_windows
from spk2img.parts import DEFAULT_PART_MIB, MIB, split
from spk2img.sim.sources import MIN_CLIP_FRAMES, FrameFolder, Photo, SourceIndex, VideoFile

PACK_NAME = "training-data.zip"
REAL_VIDEO_WINDOWS = "real_video_windows.npz"
"""The archive's file of the real-video validation's training windows (module doc)."""
LICENCE_GLOBS = ("MANIFEST*", "licences/**/*", "LICENSE*")
ENTRY_BYTES = 640
"""An upper bound of what a file adds to the archive beside its bytes: its two zip headers
(76 bytes and its name twice) and its name in ``PACK.json`` (names are under 150 bytes)."""
ARCHIVE_BYTES = 4096
"""What the archive adds beside its files: the end record and ``PACK.json``'s other keys."""


@dataclass(frozen=True)
class Packed:
    """A source as packed: its name (what held-out lists use), whether it is a clip, and its
    files (in frame order)."""

    name: str
    clip: bool
    files: tuple[Path, ...]

    @classmethod
    def of(cls, source: Photo | FrameFolder | VideoFile) -> Packed:
        if isinstance(source, Photo):
            return cls(source.path.name, False, (source.path,))
        if isinstance(source, FrameFolder):
            return cls(source.name, True, source.frames)
        return cls(source.name, True, (source.path,))


def pack_training_data(
    folders: list[str | Path],
    out: Path,
    part_mib: float = DEFAULT_PART_MIB,
    validation: bool = False,
    max_mib: float | None = None,
) -> dict:
    """Pack the sources under ``folders`` into ``out/training-data.zip``, split it into parts
    there and remove the whole; returns the pack's record (``PACK.json``) with the parts'
    manifest path (module doc). With ``max_mib``, the training sources are cut
    (:func:`compact`) so that the archive is at most that many MiB; ``ValueError`` when the
    held-out sources, manifests and licences leave no room for any training source."""
    roots = [Path(folder).resolve() for folder in folders]
    names = [root.name for root in roots]
    if len(set(names)) != len(names):
        raise ValueError(f"--data folders need different names to pack them: {names}")
    record: dict = {"folders": names, "train": {}, "validation": {}, "left_out": []}
    training: list[tuple[Path, Packed]] = []
    kept: dict[str, Path] = {}  # arcname -> file: what is packed whatever the budget
    for root in roots:
        index = SourceIndex.scan([root], min_side=0)
        for source in index.photos + index.clips:
            packed = Packed.of(source)
            if packed.name not in NEVER_TRAINED:
                training.append((root, packed))
            elif validation:
                record["validation"][packed.name] = _add(kept, root, packed.files)
            else:
                record["left_out"].append(packed.name)
        for pattern in LICENCE_GLOBS:
            for path in sorted(root.glob(pattern)):
                if path.is_file():
                    _add(kept, root, (path,))
    if not training:
        raise ValueError(
            f"no training sources (photos or clips) under {', '.join(map(str, roots))}: "
            "nothing to pack"
        )
    out.mkdir(parents=True, exist_ok=True)
    windows_file = out / REAL_VIDEO_WINDOWS  # only while the archive is written
    try:
        if not validation and (windows := training_windows(roots)):
            save_windows(windows, windows_file)
            kept[REAL_VIDEO_WINDOWS] = windows_file
            record["real_video_windows"] = {"file": REAL_VIDEO_WINDOWS, "windows": len(windows)}
        if max_mib is not None:
            room = int(max_mib * MIB) - ARCHIVE_BYTES - _bytes(kept.values())
            training, record["compact"] = compact(training, room, max_mib)
        members = dict(kept)
        for root, packed in training:
            record["train"][packed.name] = _add(members, root, packed.files)
        archive = out / PACK_NAME
        with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as pack:
            pack.writestr("PACK.json", json.dumps(record, indent=1) + "\n")
            for arcname, path in sorted(members.items()):
                pack.write(path, arcname)
    finally:
        windows_file.unlink(missing_ok=True)
    record["bytes"] = archive.stat().st_size
    record["manifest"] = str(split(archive, out, int(part_mib * MIB)))
    archive.unlink()
    return record


def compact(
    training: list[tuple[Path, Packed]], room: int, max_mib: float
) -> tuple[list[tuple[Path, Packed]], dict]:
    """The training sources cut to ``room`` bytes (files and their share of the archive), and
    what was kept of what.

    Half the room is the clips' (their real motion is what photos lack), the rest and what the
    clips leave is the photos'. Clips: each keeps its first frames, as many as let every clip
    fit (at least :data:`~spk2img.sim.sources.MIN_CLIP_FRAMES`, so that it stays a clip); where
    not even that fits, every k-th clip, the smallest k that fits. Photos: every k-th, the
    smallest k that fits (spread over every collection: they are indexed by name).
    ``ValueError`` when no training source fits."""
    clips = [(root, s) for root, s in training if s.clip]
    photos = [(root, s) for root, s in training if not s.clip]
    kept_clips, frames, clip_every = _cut_clips(clips, room // 2 if photos else room)
    kept_photos, photo_every = _every_kth(photos, room - _cost(kept_clips))
    if not kept_clips and not kept_photos:
        raise ValueError(
            f"--max-mib {max_mib:g}: the held-out sources, manifests and licences leave "
            f"{max(room, 0) / MIB:.1f} MiB, too little for any training source (give more, or "
            "leave the held-out sources out)"
        )
    summary = {
        "max_mib": max_mib,
        "photos": {"kept": len(kept_photos), "of": len(photos), "every": photo_every},
        "clips": {"kept": len(kept_clips), "of": len(clips), "every": clip_every},
        "clip_frames": frames,
    }
    return kept_photos + kept_clips, summary


def describe_compact(summary: dict) -> str:
    """What :func:`compact` kept, in words: ``31 of 31 clips (all, their first 4 frames), 100
    of 793 photos (one in 8)``."""
    frames = summary["clip_frames"]
    words = []
    for kind in ("clips", "photos"):
        kept = summary[kind]
        how = {None: "none fit", 1: "all"}.get(kept["every"], f"one in {kept['every']}")
        if kind == "clips" and frames and kept["kept"]:
            how += f", their first {frames} frames"
        words.append(f"{kept['kept']} of {kept['of']} {kind} ({how})")
    return ", ".join(words)


def _cut_clips(
    clips: list[tuple[Path, Packed]], room: int
) -> tuple[list[tuple[Path, Packed]], int | None, int | None]:
    """Clips within ``room`` bytes, the frames each keeps at most (None: all of every clip)
    and the k of every k-th clip kept (None: none fit)."""
    longest = max((len(s.files) for _, s in clips), default=MIN_CLIP_FRAMES)
    for frames in range(longest, MIN_CLIP_FRAMES, -1):
        cut = [(root, _first(s, frames)) for root, s in clips]
        if _cost(cut) <= room:
            return cut, (None if frames == longest else frames), 1
    kept, every = _every_kth([(root, _first(s, MIN_CLIP_FRAMES)) for root, s in clips], room)
    return kept, MIN_CLIP_FRAMES, every


def _every_kth(
    sources: list[tuple[Path, Packed]], room: int
) -> tuple[list[tuple[Path, Packed]], int | None]:
    """Every k-th of ``sources`` for the smallest k whose files fit ``room`` bytes, and k
    (None where not even one fits)."""
    for every in range(1, len(sources) + 1):
        if _cost(sources[::every]) <= room:
            return sources[::every], every
    return [], None


def _first(source: Packed, frames: int) -> Packed:
    return Packed(source.name, source.clip, source.files[:frames])


def _add(members: dict[str, Path], root: Path, files: tuple[Path, ...]) -> list[str]:
    """Add ``files`` (under ``root``) to ``members`` by their names in the archive; the names."""
    arcnames = [f"{root.name}/{path.relative_to(root).as_posix()}" for path in files]
    members |= dict(zip(arcnames, files, strict=True))
    return arcnames


def _bytes(files) -> int:
    """The bytes ``files`` take in the archive: their own and :data:`ENTRY_BYTES` each."""
    return sum(Path(f).stat().st_size + ENTRY_BYTES for f in files)


def _cost(sources: list[tuple[Path, Packed]]) -> int:
    return sum(_bytes(s.files) for _, s in sources)
