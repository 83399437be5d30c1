"""The suite's numba warm-up (helpers.compiled, run by tests/conftest.py before the workers start) leaves what a
later process needs in numba's disk cache: a fresh process calling the library's functions the same way
compiles none of them again, so the suite's workers and the kpcn processes its tests start do not either."""

import json
import os
import subprocess
import sys

from helpers.paths import REPO

# every module-level numba function of the library outside the renderer (whose kernel the slow tests warm)
NUMBA_FUNCTIONS = {"prep.albedo._nlm", "prep.features._buffers_kernel", "prep.features._depth_max",
                   "prep.sampling._window_sums", "prep.sampling._error_pixels", "prep.colour.relative_variance",
                   "prep.colour.variance_of", "kpcn_keras.layers._contract_rows"}

_PROBE = """
import json, sys
sys.path.insert(0, "tests")
from helpers.compiled import STEPS, compiled
for step in STEPS:
    step()
print(json.dumps(compiled()))
"""


def test_a_fresh_process_loads_every_specialisation_of_the_warm_up_from_numbas_disk_cache():
    from helpers.compiled import compile_all

    compile_all(render=False)  # already done by conftest.py where the session started: loaded, then
    res = subprocess.run([sys.executable, "-c", _PROBE], cwd=REPO, capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert res.returncode == 0, res.stderr[-3000:]
    stats = json.loads(res.stdout.strip().splitlines()[-1])
    assert NUMBA_FUNCTIONS <= set(stats), sorted(NUMBA_FUNCTIONS - set(stats))
    compiled_again = {name: s for name, s in stats.items() if s["misses"]}
    assert not compiled_again, f"compiled again rather than loaded from the disk cache: {compiled_again}"
    assert all(stats[name]["hits"] >= 1 for name in NUMBA_FUNCTIONS)


def test_the_list_names_every_numba_function_of_the_library():
    """A numba function added to the library is added to the warm-up (helpers.compiled) and to this list."""
    import re

    found = set()
    for path in [*REPO.glob("prep/**/*.py"), *REPO.glob("kpcn_keras/*.py")]:
        if path.parent.name == "render":
            continue  # the render kernel's modules: warmed through the kernel (helpers.compiled._render)
        text = path.read_text()
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        for name in re.findall(r"^@numba\.njit\([^\n]*\n(?:@[^\n]*\n)*def (\w+)", text, re.M):
            found.add(f"{module}.{name}")
    assert found - {"prep.features._relative_variance"} == NUMBA_FUNCTIONS  # inlined into _buffers_kernel
