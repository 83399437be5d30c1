"""prep/threads.py: the thread count a user sets is the one numba and torch use, whatever runs first.

Each case runs in a fresh interpreter: thread pools are per-process state that a test cannot undo.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

PRANGE = """
import numba, numpy as np
@numba.njit(parallel=True)
def total(x):
    s = 0.0
    for i in numba.prange(x.shape[0]):
        s += x[i]
    return s
"""

CHECK = """
total(np.ones(1000))          # numba's first parallel call launches its threading layer
torch.ones(300, 300) @ torch.ones(300, 300)
total(np.ones(1000))
print(torch.get_num_threads(), numba.get_num_threads())
"""


def _run(code: str, **extra) -> tuple[int, int]:
    leave = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS", "LOCAL_WORLD_SIZE")
    env = {**{k: v for k, v in os.environ.items() if k not in leave}, **extra}
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    torch_n, numba_n = map(int, res.stdout.split()[-2:])
    return torch_n, numba_n


@pytest.mark.slow
def test_one_thread_holds_when_torch_is_imported_first():
    # a torch op first: torch has then initialised its threads and will not redo it after numba's reset
    code = ("import torch\ntorch.ones(300, 300) @ torch.ones(300, 300)\n" + PRANGE
            + "from prep import threads\nthreads.set_threads(1)\n" + CHECK)
    assert _run(code) == (1, 1)


@pytest.mark.slow
def test_one_thread_holds_when_torch_is_imported_after():
    code = PRANGE + "from prep import threads\nthreads.set_threads(1)\nimport torch\n" + CHECK
    assert _run(code) == (1, 1)


@pytest.mark.slow
def test_the_default_is_every_core():
    code = ("import torch\ntorch.ones(300, 300) @ torch.ones(300, 300)\n" + PRANGE
            + "from prep import threads\nthreads.set_threads()\n" + CHECK)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert cores == os.cpu_count()  # no restricted affinity on the machines this runs on
    assert _run(code) == (cores, cores)


@pytest.mark.slow
@pytest.mark.parametrize("local", [2, 64])
def test_the_default_under_a_launcher_is_this_processs_share_of_the_cores(local):
    """torchrun's LOCAL_WORLD_SIZE processes on one machine each take an even share, at least one core."""
    code = PRANGE + "from prep import threads\nthreads.set_threads()\nimport torch\n" + CHECK
    share = max(1, os.cpu_count() // local)
    assert _run(code, LOCAL_WORLD_SIZE=str(local)) == (share, share)


@pytest.mark.slow
@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: numba's reset cannot be seen")
def test_without_the_module_numba_resets_torch():
    # guards the tests above: the defect they would catch is real here (numba's OpenMP layer calls
    # omp_set_num_threads(pool size) when it starts; torch reads omp_get_max_threads and, having run an op
    # in this thread already, does not apply its own count again)
    code = ("import torch\ntorch.set_num_threads(1)\ntorch.ones(300, 300) @ torch.ones(300, 300)\n" + PRANGE
            + "total(np.ones(10))\n")
    res = subprocess.run([sys.executable, "-c", code + "print(numba.threading_layer(), torch.get_num_threads())"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    layer, torch_n = res.stdout.split()[-2:]
    if layer != "omp":
        pytest.skip(f"numba's threading layer is {layer} here, not OpenMP")
    assert int(torch_n) > 1


def test_prep_threads_does_not_import_torch():
    code = "import sys\nfrom prep import threads\nthreads.set_threads(1)\nprint(int('torch' in sys.modules), 0)"
    assert _run(code) == (0, 0)


@pytest.mark.parametrize("bad", [0, -1, 10_000, 1.5, "2", True])
def test_a_bad_count_names_the_option(bad):
    from prep import threads
    from prep.errors import OptionError

    with pytest.raises(OptionError, match=r"threads must be an integer from 1 to \d+.*got"):
        threads.set_threads(bad)
