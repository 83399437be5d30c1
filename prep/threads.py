"""The one owner of the process's thread count: what the user sets is what numba and torch use.

Contract: after :func:`set_threads` (``n`` threads, default :func:`default_threads`: every core, or this
process's share of them under a launcher), every later numba
parallel call of the calling thread and every torch op of the process run on ``n`` threads, whatever order
the two libraries are imported or first used in. ``kpcn --threads N`` calls it once, before any command.
This module never imports torch (prep stays free of the deep-learning stack): it sets torch's count only if
torch is already imported, and otherwise leaves ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` in the
environment, which torch reads when it starts its own thread pool. Child processes inherit them too.

Why the setting did not hold before: numba's OpenMP threading layer (``numba.threading_layer() == "omp"``,
the default where libgomp is present) and torch's ATen (``ATen parallel backend: OpenMP``) share one
libgomp. The first numba parallel call (or ``numba.get_num_threads``/``set_num_threads``) launches numba's
layer, whose ``launch_threads`` calls ``omp_set_num_threads(NUMBA_NUM_THREADS)`` (all cores) once per
process. torch's ``get_num_threads`` is ``omp_get_max_threads()``, and torch applies its own count to a
thread only once, lazily, at that thread's first parallel op: if torch had already run in the main thread
(a model loaded, a tile denoised) when numba first ran, its count silently became numba's pool size for
the rest of the process. :func:`set_threads` therefore launches numba's layer first
(``numba.set_num_threads``) and sets torch's count after it: the reset is behind us and never recurs.

numba's count is per thread (numba's design): threads other than the caller start at the pool size,
``numba.config.NUMBA_NUM_THREADS``. Nothing in kpcn calls numba from a second thread.
"""

from __future__ import annotations

import os
import sys

from prep.bounds import is_integer
from prep.errors import OptionError
from prep.parts import LOCAL_WORLD_SIZE, launcher_variables

_requested: int | None = None


def pool_size() -> int:
    """All the cores numba may use: the CPUs this process is allowed to run on (``os.sched_getaffinity``,
    which is ``os.cpu_count()`` outside a restricted container), or ``NUMBA_NUM_THREADS`` if set."""
    import numba

    return int(numba.config.NUMBA_NUM_THREADS)


def default_threads() -> int:
    """The threads of a process not told otherwise: every core of :func:`pool_size`, or, when a launcher
    started several processes on this machine (torchrun's ``LOCAL_WORLD_SIZE``), an even share of them,
    so that they do not fight over the cores."""
    local = launcher_variables((LOCAL_WORLD_SIZE,))
    if local is None or local[LOCAL_WORLD_SIZE] < 1:
        return pool_size()
    return max(1, pool_size() // local[LOCAL_WORLD_SIZE])


def requested() -> int | None:
    """The count of the last :func:`set_threads`, or None if it was never called."""
    return _requested


def set_threads(n: int | None = None) -> int:
    """Use ``n`` threads (None: :func:`default_threads`) in numba and torch from now on; returns ``n``.

    OptionError ``threads`` for anything but an integer from 1 to numba's pool size (numba cannot grow its
    pool once started, and more threads than cores only slow the convolutions down).
    """
    global _requested
    import numba

    most = pool_size()
    if n is None:
        n = default_threads()
    if not is_integer(n) or not 1 <= n <= most:
        raise OptionError("threads", f"must be an integer from 1 to {most} (the cores this process may use), got {n!r}")
    # for a torch imported later (it sizes its OpenMP and MKL pools from these) and for child processes
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(n)
    # launches numba's threading layer now, so its one-time omp_set_num_threads(pool size) is behind us
    numba.set_num_threads(n)
    _requested = n
    apply_to_torch()
    return n


def apply_to_torch() -> None:
    """Set torch's intra-op count to the requested one, if torch is imported and a count was requested.
    Safe to call any number of times. :func:`set_threads` calls it; a torch imported afterwards starts at
    the count through ``OMP_NUM_THREADS``, so nothing needs to call it again."""
    torch = sys.modules.get("torch")
    if torch is not None and _requested is not None and torch.get_num_threads() != _requested:
        torch.set_num_threads(_requested)
