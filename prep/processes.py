"""Processes: a worker never outlives the process that started it; what the kernel says of memory.

A shard worker (``prep.shards``) or a training process started by torchrun (``kpcn_keras.distributed``)
left running by a killed parent would go on writing, or hold a folder's lock, or wait for its peers
forever; :func:`die_with_parent` makes the kernel end it instead.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


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


__all__ = ["die_with_parent", "proc_megabytes"]
