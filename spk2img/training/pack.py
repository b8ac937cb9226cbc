"""The training data as one file that travels: ``spk2img pack-data``.

A pack is a zip archive (stored, not recompressed: the photos and frames keep their own files,
byte for byte, at full stored resolution) of every source the training index finds under the
``--data`` folders, laid out as there (so ``--data`` on the unpacked folder finds the same
photos and clips), with each folder's ``MANIFEST.*`` and ``licences/``:

- ``train``: the sources training may draw from;
- ``validation``: the held-out sources (:data:`~spk2img.evaluation.natural_validation.
  NEVER_TRAINED`: the natural validation's photos and clips, the real-video clips), which the
  training index skips by name, packed so that a run elsewhere validates as it does here;
  ``--no-validation`` leaves them out.

``PACK.json`` inside lists both, by name, with their files. The archive is then split into
parts of at most ``--part-mib`` (:mod:`spk2img.parts`) for a machine that receives 64 MiB a
command; docs/gpu.md gives the steps there.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

from spk2img.evaluation.natural_validation import NEVER_TRAINED
from spk2img.parts import DEFAULT_PART_MIB, MIB, split
from spk2img.sim.sources import FrameFolder, Photo, SourceIndex, VideoFile

PACK_NAME = "training-data.zip"
LICENCE_GLOBS = ("MANIFEST*", "licences/**/*", "LICENSE*")


def source_files(source: Photo | FrameFolder | VideoFile) -> tuple[str, list[Path]]:
    """A source's name (what held-out lists use) and its files."""
    if isinstance(source, Photo):
        return source.path.name, [source.path]
    if isinstance(source, FrameFolder):
        return source.name, list(source.frames)
    return source.name, [source.path]


def pack_training_data(
    folders: list[str | Path],
    out: Path,
    part_mib: float = DEFAULT_PART_MIB,
    validation: bool = True,
) -> dict:
    """Pack the sources under ``folders`` into ``out/training-data.zip``, split it into parts
    there and remove the whole; returns the pack's record (``PACK.json``) with the parts'
    manifest path (module doc)."""
    roots = [Path(folder).resolve() for folder in folders]
    names = [root.name for root in roots]
    if len(set(names)) != len(names):
        raise ValueError(f"--data folders need different names to pack them: {names}")
    record: dict = {"folders": names, "train": {}, "validation": {}, "left_out": []}
    members: dict[str, Path] = {}
    for root in roots:
        index = SourceIndex.scan([root], min_side=0)
        for source in index.photos + index.clips:
            name, files = source_files(source)
            held_out = name in NEVER_TRAINED
            if held_out and not validation:
                record["left_out"].append(name)
                continue
            arcnames = [f"{root.name}/{path.relative_to(root).as_posix()}" for path in files]
            record["validation" if held_out else "train"][name] = arcnames
            members |= dict(zip(arcnames, files, strict=True))
        for pattern in LICENCE_GLOBS:
            for path in sorted(root.glob(pattern)):
                if path.is_file():
                    members[f"{root.name}/{path.relative_to(root).as_posix()}"] = path
    if not record["train"]:
        raise ValueError(
            f"no training sources (photos or clips) under {', '.join(map(str, roots))}: "
            "nothing to pack"
        )
    out.mkdir(parents=True, exist_ok=True)
    archive = out / PACK_NAME
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as pack:
        pack.writestr("PACK.json", json.dumps(record, indent=1) + "\n")
        for arcname, path in sorted(members.items()):
            pack.write(path, arcname)
    record["bytes"] = archive.stat().st_size
    record["manifest"] = str(split(archive, out, int(part_mib * MIB)))
    archive.unlink()
    return record
