"""prep/processes.py: what every command sets for the C allocator. Each case runs in a fresh interpreter: the
allocator's settings are per-process state that a test cannot undo."""

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

REALLOCATE = """
import resource, sys
import numpy as np
from prep.processes import keep_freed_memory
if sys.argv[1] == "kept":
    assert keep_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
block = np.ones(64 << 18, np.float32)  # 64 MB, written, then freed: what a layer's output is to torch
del block
before = faults()
for _ in range(5):
    block = np.ones(64 << 18, np.float32)
    del block
print(faults() - before)
"""


def _page_faults(mode: str) -> int:
    res = subprocess.run([sys.executable, "-c", REALLOCATE, mode], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    return int(res.stdout.split()[-1])


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_memory_is_reused_instead_of_faulted_in_again():
    kept, default = _page_faults("kept"), _page_faults("default")
    # 5 x 64 MB is 81920 pages of 4 KB (or 160 huge pages): kept, next to none fault in again
    assert kept < 50 < default, (kept, default)
