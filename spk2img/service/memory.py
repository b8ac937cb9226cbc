"""The process's memory and the container's limit. Giving freed memory back to the system is
:mod:`spk2img.runtime.allocator`'s (the pool calls it whenever it falls idle)."""

from __future__ import annotations

from pathlib import Path

CGROUP_LIMITS = (
    Path("/sys/fs/cgroup/memory.max"),  # cgroup v2
    Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"),  # cgroup v1
)
NO_LIMIT = 2**60
"""cgroup v1 reports "no limit" as a number near 2**63."""


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
