"""Processes: a worker never outlives the process that started it; what the kernel says of memory; how the C
allocator keeps what is freed.

A shard worker (``prep.shards``) or a training process started by torchrun (``kpcn_keras.distributed``)
left running by a killed parent would go on writing, or hold a folder's lock, or wait for its peers
forever; :func:`die_with_parent` makes the kernel end it instead. :func:`memory_shortfall` lets render and denoise
refuse a frame whose whole-frame arrays the machine cannot hold before any work starts.
:func:`keep_freed_memory` stops glibc's malloc from handing freed blocks back to the kernel (every command sets
it, ``kpcn_keras.cli.main``): torch allocates and frees a tile's activations, megabytes each, at every layer,
and glibc unmaps a freed block above its mmap threshold (at most 32 MB, adjusted as it goes) or trims its
heap's top, so the next allocation of that size faults its pages in again, zeroed by the kernel. Measured on
this 2-core machine (2026-12-03, ``kpcn_keras.studies.slope_map_costs``' 512 x 512 frame of a λ mixture run): a new λ
map 160-300 ms before, 90-120 ms after; the resident peak is the same, what is freed is reused.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

# mallopt parameters (malloc.h) and their values: no block mmapped below 1 GB, the heap never trimmed, and each
# heap growth 256 MB beyond the request (address space: pages are resident only once written)
ALLOCATOR = {"M_MMAP_THRESHOLD": (-3, 1 << 30), "M_TRIM_THRESHOLD": (-1, 2**31 - 1), "M_TOP_PAD": (-2, 1 << 28)}


def keep_freed_memory() -> bool:
    """Keep freed memory in this process for reuse (the module docstring); True where glibc took every setting,
    False elsewhere (another C library, another system: nothing is changed)."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except AttributeError:  # not glibc (musl has no mallopt)
        return False
    return all(mallopt(code, value) == 1 for code, value in ALLOCATOR.values())


def die_with_parent(parent: int) -> None:
    """End this process (SIGKILL) when ``parent``, the process that started it, ends, however it ends
    (Linux's PR_SET_PDEATHSIG; elsewhere nothing is set). If ``parent`` is already gone, end now."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # it ended before the request was made
        os._exit(1)


def proc_megabytes(path: str, keys) -> dict[str, float]:
    """The ``keys`` of a Linux ``/proc`` table of ``Key: N kB`` lines (``/proc/meminfo``,
    ``/proc/self/status``) in MB; the keys not found, or every key off Linux, are left out."""
    found = {}
    try:
        for line in Path(path).read_text().splitlines():
            key, _, value = line.partition(":")
            if key in keys:
                found[key] = int(value.split()[0]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return found


def memory_shortfall(needed_bytes: int, *, available_mb: float | None = None) -> str | None:
    """None where ``needed_bytes`` fit the memory this machine has available (Linux ``MemAvailable``;
    ``available_mb`` instead where given; taken to fit where it cannot be read), else the end of a message
    saying so: ``"needs 79.0 GiB, more than the 20.1 GiB this machine has available"``."""
    if available_mb is None:
        available_mb = proc_megabytes("/proc/meminfo", ("MemAvailable",)).get("MemAvailable")
    if available_mb is None or needed_bytes <= available_mb * 2**20:
        return None
    return (f"needs {needed_bytes / 2**30:.1f} GiB, more than the {available_mb / 1024:.1f} GiB this machine has "
            "available")


__all__ = ["memory_shortfall", "die_with_parent", "proc_megabytes"]
