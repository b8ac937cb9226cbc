"""What this machine's CPU is: its model and whether it has bf16 matrix units (Intel AMX), which
decide whether training in bf16 on it pays (docs/training_data.md, "bf16 on the CPU")."""

from __future__ import annotations

import os
import platform
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")


def _cpuinfo_field(name: str) -> str:
    """The first ``name : value`` of /proc/cpuinfo (empty where there is none)."""
    if not CPUINFO.is_file():
        return ""
    for line in CPUINFO.read_text().splitlines():
        key, _, value = line.partition(":")
        if key.strip() == name:
            return value.strip()
    return ""


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :mod:`platform` knows of it."""
    return _cpuinfo_field("model name") or platform.processor() or platform.machine()


def has_amx_bf16() -> bool:
    """Whether the CPU has Intel AMX's bf16 tiles (the ``amx_bf16`` flag of /proc/cpuinfo)."""
    return "amx_bf16" in _cpuinfo_field("flags").split()


def cpu_words() -> str:
    """The CPU's model and its bf16 matrix units, e.g. ``Intel(R) Xeon(R) Processor (AMX
    bf16)`` or ``AMD EPYC 7B13 (no AMX)``."""
    return f"{cpu_model()} ({'AMX bf16' if has_amx_bf16() else 'no AMX'})"


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1
