"""What the hardware does well (whether bf16 autocast pays on a device) and how much memory is free."""

from __future__ import annotations

import functools
import os
import sys

import torch

__all__ = ["available_memory_bytes", "bf16_is_fast", "cpu_flags"]


@functools.lru_cache(maxsize=1)
def cpu_flags() -> frozenset[str]:
    """The CPU feature flags of ``/proc/cpuinfo`` (empty where there is none, e.g. macOS)."""
    if not sys.platform.startswith("linux"):
        return frozenset()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.partition(":")[2].split())
    except OSError:
        pass
    return frozenset()


def bf16_is_fast(device: str | torch.device) -> bool:
    """True where bf16 matrix products run natively: CUDA GPUs that support bf16, and CPUs with
    ``avx512_bf16`` or AMX (``amx_bf16``); elsewhere bf16 autocast is emulated and slower."""
    device = torch.device(device)
    if device.type == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    if device.type == "cpu":
        return bool({"avx512_bf16", "amx_bf16"} & cpu_flags())
    return False


def available_memory_bytes(device: str | torch.device = "cpu") -> int | None:
    """Memory a new allocation can take on ``device`` without swapping: ``MemAvailable`` of
    ``/proc/meminfo`` for the CPU (Linux; else free physical pages), free memory for a CUDA GPU;
    None where it cannot be told."""
    device = torch.device(device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            return None
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None
