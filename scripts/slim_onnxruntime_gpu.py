"""onnxruntime-gpu for one GPU architecture: its wheel as a ``.tar.xz`` of the package, with the
CUDA provider's kernels for the other architectures left out (docs/gpu.md, "onnxruntime-gpu
in three commands").

``python scripts/slim_onnxruntime_gpu.py WHEEL --arch 90 --out FILE.tar.xz`` reads the wheel
(``pip download onnxruntime-gpu==1.31.1 ...``), keeps every file as it is except
``libonnxruntime_providers_cuda.so``: in its ``.nv_fatbin`` section each fat binary (the
kernels of one compilation unit, one cubin per architecture) keeps only its entries for
``sm_ARCH``; the bytes freed are zeroed in place, so no address in the library moves, and
xz takes them to nothing. The 1.31.1 wheel (255.6 MB; that library 284 MB, 231 MB compressed,
with cubins for sm_75, 80, 86, 89, 90 and 120) becomes a 66.7 MiB archive that three commands
carry, where the wheel needed ten. The CUDA driver loads the cubin of the device's own
architecture from a fat binary, so the result runs on that architecture only (sm_90: H100,
H200); a fat binary without an entry for it is left whole. A ``.json`` beside the archive
records the wheel's SHA-256 and the bytes per architecture before and after.

The archive unpacks into a folder for ``PYTHONPATH`` (``scripts/receive_parts.sh``); it is
not a wheel and not for pip.
"""

from __future__ import annotations

import argparse
import io
import json
import lzma
import struct
import sys
import tarfile
import zipfile
from collections import Counter
from pathlib import Path

from spk2img.parts import sha256_of

CUDA_LIBRARY = "libonnxruntime_providers_cuda.so"
SECTION = ".nv_fatbin"
FATBIN_MAGIC = 0xBA55ED50
"""The first four bytes (little-endian) of a fat binary's header."""
CONTAINER_HEADER = struct.Struct("<IHHQ")
"""magic, version, header size, payload size: a fat binary's header."""
ENTRY_HEADER = struct.Struct("<HHIQ")
"""kind (1 PTX, 2 cubin), version, header size, payload size: an entry's header."""
ENTRY_ARCH_OFFSET = 28
"""Where an entry's header holds its architecture (``90`` for sm_90), a uint32."""


class SlimError(ValueError):
    """A library or wheel that is not laid out as this tool reads it (the message says how)."""


def elf_section(data: bytes, name: str) -> tuple[int, int]:
    """File offset and size of section ``name`` of the 64-bit little-endian ELF ``data``."""
    if data[:6] != b"\x7fELF\x02\x01":
        raise SlimError("not a 64-bit little-endian ELF file")
    (shoff,) = struct.unpack_from("<Q", data, 0x28)
    entsize, count, names_index = struct.unpack_from("<HHH", data, 0x3A)

    def header(i: int) -> tuple[int, int, int]:
        (name_at,) = struct.unpack_from("<I", data, shoff + i * entsize)
        offset, size = struct.unpack_from("<QQ", data, shoff + i * entsize + 24)
        return name_at, offset, size

    _, names, _ = header(names_index)
    for i in range(count):
        name_at, offset, size = header(i)
        end = data.index(b"\0", names + name_at)
        if data[names + name_at : end].decode() == name:
            return offset, size
    raise SlimError(f"no {name} section")


def entries(data: bytes, start: int, end: int) -> list[tuple[int, int, int]]:
    """``(offset, length, arch)`` of each entry (header and payload) between ``start`` and
    ``end``, the payload of one fat binary."""
    found, at = [], start
    while at < end:
        _, _, header, payload = ENTRY_HEADER.unpack_from(data, at)
        (arch,) = struct.unpack_from("<I", data, at + ENTRY_ARCH_OFFSET)
        found.append((at, header + payload, arch))
        at += header + payload
    if at != end:
        raise SlimError(f"fat binary entries overrun their container at {start:#x}")
    return found


def keep_architecture(data: bytearray, start: int, size: int, arch: int) -> dict:
    """Keep only the ``arch`` entries of every fat binary in ``data[start:start + size]``, in
    place (each container keeps its place and length; what its dropped entries held is zeroed);
    the bytes per architecture before and kept, and the containers left whole for having no
    ``arch`` entry."""
    before, kept, whole, at, end = Counter(), Counter(), 0, start, start + size
    while at < end:
        magic, version, header, payload = CONTAINER_HEADER.unpack_from(data, at)
        if magic != FATBIN_MAGIC:
            if any(data[at : at + 8]):
                raise SlimError(f"neither a fat binary nor padding at {at:#x}")
            at += 8
            continue
        body = at + header
        listed = entries(data, body, body + payload)
        for _, length, entry_arch in listed:
            before[entry_arch] += length
        chosen = b"".join(bytes(data[o : o + n]) for o, n, a in listed if a == arch)
        if chosen:
            CONTAINER_HEADER.pack_into(data, at, magic, version, header, len(chosen))
            data[body : body + payload] = chosen + bytes(payload - len(chosen))
            kept[arch] += len(chosen)
        else:
            whole += 1
            for _, length, entry_arch in listed:
                kept[entry_arch] += length
        at = body + payload
    return {"before": dict(before), "kept": dict(kept), "containers_left_whole": whole}


def slim(wheel: Path, out: Path, arch: int) -> dict:
    """Write the package of ``wheel`` to the ``.tar.xz`` ``out`` with the CUDA provider kept
    for ``sm_ARCH`` only (module doc); the summary it writes beside (``OUT.json``)."""
    summary: dict = {"wheel": wheel.name, "wheel_sha256": sha256_of(wheel), "arch": f"sm_{arch}"}
    with zipfile.ZipFile(wheel) as source, tarfile.open(out, "w:xz", preset=6) as target:
        for member in source.infolist():
            if member.is_dir() or member.filename.endswith(".dist-info/RECORD"):
                continue  # RECORD's hashes no longer hold; nothing installs from it
            data = source.read(member)
            if member.filename.endswith("/" + CUDA_LIBRARY):
                data = bytearray(data)
                summary["fatbin"] = keep_architecture(data, *elf_section(data, SECTION), arch)
                if not summary["fatbin"]["kept"].get(arch):
                    raise SlimError(f"{CUDA_LIBRARY} holds no cubin for sm_{arch}")
            info = tarfile.TarInfo(member.filename)
            info.size, info.mode = len(data), (member.external_attr >> 16) & 0o777 or 0o644
            target.addfile(info, io.BytesIO(data))
    if "fatbin" not in summary:
        raise SlimError(f"{wheel.name} holds no {CUDA_LIBRARY}")
    summary["archive_bytes"] = out.stat().st_size
    Path(f"{out}.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("wheel", type=Path, help="an onnxruntime-gpu wheel")
    parser.add_argument("--arch", type=int, default=90, help="compute capability, 90 for sm_90")
    parser.add_argument("--out", type=Path, required=True, help="the .tar.xz to write")
    args = parser.parse_args(argv)
    try:
        summary = slim(args.wheel, args.out, args.arch)
    except (SlimError, OSError, zipfile.BadZipFile, lzma.LZMAError) as exc:
        print(f"slim_onnxruntime_gpu: error: {exc}", file=sys.stderr)
        return 2
    mib = {a: round(n / 2**20, 1) for a, n in sorted(summary["fatbin"]["before"].items())}
    print(f"cubins before (MiB per sm): {mib}; kept sm_{args.arch}")
    print(f"{args.out}: {summary['archive_bytes'] / 2**20:.1f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
