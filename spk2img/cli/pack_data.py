"""``spk2img pack-data``: the training data as parts of one archive that travel to a machine
receiving 64 MiB a command (:mod:`spk2img.training.pack`; the steps there: docs/gpu.md)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from spk2img.errors import InputError
from spk2img.parts import DEFAULT_PART_MIB, read_manifest


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "pack-data",
        help="pack the training data into parts that travel (never commit them)",
        description=__doc__,
    )
    p.add_argument(
        "--data",
        action="append",
        required=True,
        metavar="DIR",
        help="a folder of photographs and clips, as spk2img train reads it (once per folder)",
    )
    p.add_argument("--out", type=Path, default=Path("pack"), help="folder of the parts")
    p.add_argument("--part-mib", type=float, default=DEFAULT_PART_MIB, help="largest part, in MiB")
    p.add_argument(
        "--max-mib",
        type=float,
        metavar="MIB",
        help="pack a subset of the training sources (each file whole) so that the pack is at "
        "most MIB: the first frames of every clip and every k-th photo (docs/gpu.md)",
    )
    p.add_argument(
        "--with-validation",
        dest="validation",
        action="store_true",
        help="also pack the held-out validation sources, apart (never trained on; left out and "
        "listed by default)",
    )


def run(args: argparse.Namespace) -> int:
    from spk2img.training.pack import describe_compact, pack_training_data

    for folder in args.data:
        if not Path(folder).is_dir():
            raise InputError(f"--data {folder}: not a folder")
    for flag, value in (("--part-mib", args.part_mib), ("--max-mib", args.max_mib)):
        if value is not None and not 0 < value < math.inf:
            raise InputError(f"{flag} {value:g}: must be a number > 0")
    try:
        record = pack_training_data(
            args.data, args.out, args.part_mib, args.validation, args.max_mib
        )
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    files = sum(len(f) for kind in ("train", "validation") for f in record[kind].values())
    parts = read_manifest(Path(record["manifest"]))["parts"]
    print(
        f"packed {len(record['train'])} training and {len(record['validation'])} validation "
        f"sources ({files} files, {record['bytes'] / 2**20:.1f} MiB) into {len(parts)} parts; "
        f"manifest {record['manifest']}"
    )
    if "compact" in record:
        print(f"within {args.max_mib:g} MiB: {describe_compact(record['compact'])}")
    if record["left_out"]:
        print(f"left out (held out): {', '.join(record['left_out'])}")
    return 0
