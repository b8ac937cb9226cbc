"""Files split into parts that each fit a size limit, and joined back with their checksums.

A GPU machine that receives at most 64 MiB a command (the repository included) gets a larger
file (the training-data pack, an onnxruntime-gpu wheel) a part per command into a folder that
lasts between commands; the last command joins it. docs/gpu.md gives the steps. Standard library
only, so the receiving machine needs nothing installed::

    python -m spk2img.parts split FILE --out DIR [--part-mib 40]
    python -m spk2img.parts collect DIR/FILE.parts.json --into /tmp/parts
    python -m spk2img.parts join /tmp/parts/FILE.parts.json --out FILE
    python -m spk2img.parts room [CHECKOUT]   # MiB a command carries beside the checkout

``split`` writes ``FILE.part-000``, ``FILE.part-001`` ... and ``FILE.parts.json`` (the name,
size and SHA-256 of the file and of every part). ``collect`` copies the manifest and the parts
found beside it into a folder and lists what is still missing there; ``join`` checks every part
and the whole against the manifest. A missing or damaged part is named, never joined.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

MIB = 2**20
DEFAULT_PART_MIB = 40
"""Part size where none is given (``room`` says what fits beside a checkout)."""
COMMAND_MIB = 64
"""What a lent GPU machine receives a command: the working tree, and the files carried."""
MARGIN_MIB = 1
"""Kept free of a command by ``room``: a part's manifest, files the session writes."""
CHUNK = 4 * MIB


class PartsError(ValueError):
    """A manifest, part or joined file that does not match (the message says which)."""


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(CHUNK):
            digest.update(block)
    return digest.hexdigest()


def manifest_path(file: Path, folder: Path) -> Path:
    """Where :func:`split` writes the manifest of ``file`` in ``folder``."""
    return folder / f"{file.name}.parts.json"


def _copy_part(source, part: Path, limit: int, whole) -> tuple[int, str]:
    """Copy up to ``limit`` bytes of the open ``source`` into file ``part``, :data:`CHUNK` at a
    time (never a whole part in memory), adding them to the ``whole`` file's hash too; the
    bytes copied and the part's SHA-256."""
    digest, size = hashlib.sha256(), 0
    with open(part, "wb") as sink:
        while size < limit and (block := source.read(min(CHUNK, limit - size))):
            sink.write(block)
            digest.update(block)
            whole.update(block)
            size += len(block)
    return size, digest.hexdigest()


def split(file: Path, out: Path, part_bytes: int = DEFAULT_PART_MIB * MIB) -> Path:
    """Split ``file`` into parts of at most ``part_bytes`` in folder ``out``; returns the
    manifest's path (module doc)."""
    if part_bytes < 1:
        raise PartsError(f"part size {part_bytes} bytes: must be at least 1")
    out.mkdir(parents=True, exist_ok=True)
    parts, whole = [], hashlib.sha256()
    with open(file, "rb") as source:
        while True:  # an empty file is one empty part
            part = out / f"{file.name}.part-{len(parts):03d}"
            size, digest = _copy_part(source, part, part_bytes, whole)
            if size == 0 and parts:
                part.unlink()
                break
            parts.append({"file": part.name, "size": size, "sha256": digest})
            if size < part_bytes:
                break
    manifest = {
        "name": file.name,
        "size": sum(p["size"] for p in parts),
        "sha256": whole.hexdigest(),
        "parts": parts,
    }
    path = manifest_path(file, out)
    path.write_text(json.dumps(manifest, indent=1) + "\n")
    return path


def read_manifest(path: Path) -> dict:
    """The manifest ``path`` holds; :class:`PartsError` if it is not one."""
    try:
        manifest = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise PartsError(f"{path}: not a parts manifest ({exc})") from None
    keys = {"name", "size", "sha256", "parts"}
    if not (isinstance(manifest, dict) and keys <= manifest.keys() and manifest["parts"]):
        raise PartsError(f"{path}: not a parts manifest (it needs {', '.join(sorted(keys))})")
    return manifest


def missing(manifest_file: Path, folder: Path) -> list[str]:
    """The parts of ``manifest_file`` not in ``folder`` with their size (checksums are checked
    by :func:`join`)."""
    manifest = read_manifest(manifest_file)
    return [
        p["file"]
        for p in manifest["parts"]
        if not (folder / p["file"]).is_file() or (folder / p["file"]).stat().st_size != p["size"]
    ]


def collect(manifest_file: Path, into: Path) -> list[str]:
    """Copy ``manifest_file`` and its parts found beside it into folder ``into`` (parts already
    there are kept); returns the parts still missing there."""
    manifest = read_manifest(manifest_file)
    into.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(manifest_file, into / manifest_file.name)
    for part in manifest["parts"]:
        found = manifest_file.parent / part["file"]
        if found.is_file() and found.resolve() != (into / part["file"]).resolve():
            shutil.copyfile(found, into / part["file"])
    return missing(manifest_file, into)


def join(manifest_file: Path, out: Path, folder: Path | None = None) -> Path:
    """Join the parts of ``manifest_file`` (in ``folder``, default beside it) into ``out`` after
    checking each part's checksum, and the whole's after joining; returns ``out``."""
    manifest = read_manifest(manifest_file)
    folder = folder or manifest_file.parent
    absent = missing(manifest_file, folder)
    if absent:
        raise PartsError(f"{len(absent)} of {len(manifest['parts'])} parts missing: {absent}")
    for part in manifest["parts"]:
        if sha256_of(folder / part["file"]) != part["sha256"]:
            raise PartsError(f"{part['file']}: damaged (its SHA-256 differs from the manifest)")
    partial = out.with_name(out.name + ".joining")
    with open(partial, "wb") as target:
        for part in manifest["parts"]:
            with open(folder / part["file"], "rb") as source:
                shutil.copyfileobj(source, target, CHUNK)
    if sha256_of(partial) != manifest["sha256"]:
        partial.unlink()
        raise PartsError(f"{manifest['name']}: the joined file's SHA-256 differs")
    partial.replace(out)
    return out


def travelling_bytes(checkout: Path) -> int:
    """The bytes of git checkout ``checkout`` that travel with every command to a lent
    machine: its tracked files and the untracked ones git does not ignore (a link as a link);
    :class:`PartsError` where it is not a checkout."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=checkout,
        capture_output=True,
    )
    if listed.returncode:
        raise PartsError(f"{checkout}: not a git checkout ({os.fsdecode(listed.stderr).strip()})")
    files = {Path(checkout, name) for name in os.fsdecode(listed.stdout).split("\0") if name}
    return sum(f.lstat().st_size for f in files if f.is_file() or f.is_symlink())


def room_mib(checkout: Path) -> float:
    """MiB a command can carry beside the checkout (:data:`COMMAND_MIB` less what travels
    with it and :data:`MARGIN_MIB`), rounded down to a tenth."""
    free = COMMAND_MIB - MARGIN_MIB - travelling_bytes(checkout) / MIB
    return max(0.0, math.floor(free * 10) / 10)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m spk2img.parts", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    cut = sub.add_parser("split", help="split a file into parts and write their manifest")
    cut.add_argument("file", type=Path)
    cut.add_argument("--out", type=Path, required=True, help="folder of the parts")
    cut.add_argument("--part-mib", type=float, default=DEFAULT_PART_MIB)
    gather = sub.add_parser("collect", help="copy the parts beside a manifest into a folder")
    gather.add_argument("manifest", type=Path)
    gather.add_argument("--into", type=Path, required=True)
    whole = sub.add_parser("join", help="check the parts and join them")
    whole.add_argument("manifest", type=Path)
    whole.add_argument("--out", type=Path, required=True)
    free = sub.add_parser("room", help=f"MiB a {COMMAND_MIB} MiB command carries beside a checkout")
    free.add_argument("checkout", type=Path, nargs="?", default=Path("."))
    args = parser.parse_args(argv)
    try:
        if args.command == "room":
            print(f"{room_mib(args.checkout):.1f}")
        elif args.command == "split":
            path = split(args.file, args.out, int(args.part_mib * MIB))
            count = len(read_manifest(path)["parts"])
            print(f"{args.file} -> {count} parts, manifest {path}")
        elif args.command == "collect":
            absent = collect(args.manifest, args.into)
            print(f"still missing in {args.into}: {', '.join(absent)}" if absent else "complete")
        else:
            print(f"joined {join(args.manifest, args.out)}")
    except (PartsError, OSError) as exc:
        print(f"spk2img.parts {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
