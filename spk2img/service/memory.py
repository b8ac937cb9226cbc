"""The process's memory: giving freed memory back to the system, and the container's limit.

glibc keeps what a job frees in its allocator's arenas (one per pool thread), so a replica's
resident memory stays at its largest job's even when idle: 72 MiB idle at start, 478 MiB after
four large model calls, 102 MiB after :func:`release_free_memory` (the shipped model,
onnxruntime without its arena, measured here). The pool calls it whenever it falls idle.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from pathlib import Path

CGROUP_LIMITS = (
    Path("/sys/fs/cgroup/memory.max"),  # cgroup v2
    Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"),  # cgroup v1
)
NO_LIMIT = 2**60
"""cgroup v1 reports "no limit" as a number near 2**63."""


@functools.cache
def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name) if name else None


M_MMAP_THRESHOLD = -3
"""glibc's ``mallopt`` parameter: allocations from this size on are mapped apart."""
MMAP_THRESHOLD_BYTES = 256 * 2**10


def map_large_allocations_apart() -> bool:
    """Have glibc map every allocation of :data:`MMAP_THRESHOLD_BYTES` or more on its own (and
    unmap it when freed), instead of raising that threshold after large frees and serving later
    large buffers from its heaps, where freed pages stay behind small live objects; False where
    the C library has no ``mallopt``."""
    library = _libc()
    mallopt = getattr(library, "mallopt", None)
    return bool(mallopt and mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))


def release_free_memory() -> bool:
    """Return the allocator's free memory to the system (glibc's ``malloc_trim(0)``, every
    arena); False where the C library has no such call."""
    trim = getattr(_libc(), "malloc_trim", None)  # glibc only (not musl, macOS, Windows)
    if trim is None:
        return False
    trim(0)
    return True


def resident_bytes() -> int:
    """This process's resident memory in bytes (0 where ``/proc`` is not there)."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return 0
    for line in status.splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def container_limit_bytes(files: tuple[Path, ...] = CGROUP_LIMITS) -> int | None:
    """The memory limit of the container (cgroup) this process runs in, None without one."""
    for path in files:
        try:
            text = path.read_text().strip()
        except OSError:
            continue
        if text == "max" or not text.isdigit() or int(text) >= NO_LIMIT:
            return None
        return int(text)
    return None


def budget_problem(budget: int, resident: int, limit: int | None) -> str | None:
    """Why a memory ``budget`` (bytes) on top of ``resident`` bytes cannot fit a container
    ``limit``, or None when it fits (or there is no limit or no budget)."""
    if limit is None or budget == 0 or budget + resident <= limit:
        return None
    return (
        f"memory_budget_bytes {budget >> 20} MiB plus the {resident >> 20} MiB this process "
        f"holds idle is over the container's memory limit of {limit >> 20} MiB: lower the "
        "budget or raise the limit"
    )
