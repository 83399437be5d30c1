"""prep/processes.py: what the operating system gives a process, on Linux and, played on this Linux machine, on
macOS and Windows. Each case that changes per-process state (the allocator's settings, a lock, a parent's death, a
played system) runs in a fresh interpreter: a test cannot undo them.

Playing a system (:data:`PLAY`) sets the module's own switches (``LINUX``, ``WINDOWS``) and takes away, from kpcn's
code, what that system lacks: ``ctypes.CDLL(None)`` (Windows raises TypeError), ``/proc`` (opened from a module of
kpcn), and on Windows the POSIX modules (``fcntl``, ``resource``) and ``os`` calls (``sysconf``, ``pread``,
``O_DIRECTORY``, ``fork``, ...). Windows' ``msvcrt.locking``, where a test needs it, is played by byte-range
``lockf`` locks, which keep its documented contract: the bytes from the file's position, OSError(EACCES) at once
(``LK_NBLCK``) where another process holds one of them."""

import ast
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest

from prep import processes

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


# ---------------------------------------------------------------- another system, played

PLAY = r'''
import builtins, ctypes, errno, fcntl, io, os, sys, types
import psutil  # imported as on Linux (its Linux half needs resource): this plays kpcn's calls, not psutil's
import prep.processes as processes

POSIX_MODULES = ("fcntl", "resource", "termios")
POSIX_CALLS = ("sysconf", "pread", "pwrite", "O_DIRECTORY", "sched_getaffinity", "register_at_fork", "fork")
_real = {"cdll": ctypes.CDLL, "open": builtins.open, "io.open": io.open, "modules": dict(sys.modules),
         "os": dict(vars(os)), "flags": (processes.LINUX, processes.WINDOWS)}


def _from_kpcn():
    frame = sys._getframe(2)
    while frame is not None and frame.f_globals.get("__name__") in ("pathlib", "io", "codecs"):
        frame = frame.f_back
    return frame is not None and frame.f_globals.get("__name__", "").split(".")[0] in ("prep", "kpcn_keras", "kpcn")


def _open(file, *args, **kwargs):
    if str(file).startswith("/proc") and _from_kpcn():
        raise FileNotFoundError(errno.ENOENT, "no /proc on this system", str(file))
    return _real["io.open"](file, *args, **kwargs)


def _cdll(name, *args, **kwargs):
    if name is None:
        raise TypeError("LoadLibrary() argument 1 must be str, not None")  # Windows' answer
    return _real["cdll"](name, *args, **kwargs)


def _locking(fd, mode, nbytes):
    start = os.lseek(fd, 0, os.SEEK_CUR)
    try:
        fcntl.lockf(fd, fcntl.LOCK_UN if mode == 0 else fcntl.LOCK_EX | fcntl.LOCK_NB, nbytes, start, os.SEEK_SET)
    except OSError as exc:
        raise OSError(errno.EACCES, os.strerror(errno.EACCES)) from exc


def play(system):
    """Look like ``system`` ("linux": as it is; "macos"; "windows") to kpcn's code from here on."""
    processes.LINUX, processes.WINDOWS = _real["flags"]
    ctypes.CDLL, builtins.open, io.open = _real["cdll"], _real["open"], _real["io.open"]
    for name in ("msvcrt",) + POSIX_MODULES:
        sys.modules.pop(name, None)
        if name in _real["modules"]:
            sys.modules[name] = _real["modules"][name]
    for name in POSIX_CALLS:
        if name in _real["os"]:
            setattr(os, name, _real["os"][name])
    if system == "linux":
        return
    processes.LINUX, processes.WINDOWS = False, system == "windows"
    ctypes.CDLL = _cdll
    builtins.open = io.open = _open
    if system == "windows":
        sys.modules["msvcrt"] = types.SimpleNamespace(LK_UNLCK=0, LK_NBLCK=2, locking=_locking)  # sys/locking.h
        for name in POSIX_MODULES:
            sys.modules[name] = None
        for name in POSIX_CALLS:
            if hasattr(os, name):
                delattr(os, name)
'''

# kpcn's modules are first imported while Windows is played (a module-level import of what Windows lacks fails);
# the libraries beneath them before, as on Linux: this plays kpcn's calls, not torch's
DENOISE = PLAY + r'''
import h5py, keras, matplotlib.pyplot, numba, OpenEXR, torch

play("windows")
from kpcn_keras.cli import main

frame, out = sys.argv[1:3]
for system in ("windows", "macos", "linux"):
    play(system)
    print("played", system, flush=True)
    assert main(["-q", "denoise", frame, "--png", "--output", f"{out}/{system}.exr"]) == 0
'''


# in the fast suite (make test) although it starts an interpreter (about 15 s): it is what keeps kpcn denoise
# working off Linux
def test_kpcn_denoise_runs_and_writes_the_same_bytes_without_what_linux_alone_gives(fixture_noisy, tmp_path):
    """``kpcn denoise`` with the shipped model, in one process: playing Windows, then macOS, then as it is."""
    res = subprocess.run([sys.executable, "-c", DENOISE, str(fixture_noisy), str(tmp_path)], cwd=REPO,
                         capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    printed = res.stdout.split("played ")
    assert [part.split()[0] for part in printed[1:]] == ["windows", "macos", "linux"]
    # the peak as each system gives it: this Linux's psutil has no Windows peak; macOS's maxrss; Linux's VmHWM
    assert ["peak memory" in part for part in printed[1:]] == [False, True, True], res.stdout
    linux = (tmp_path / "linux.exr").read_bytes()
    for system in ("macos", "windows"):
        assert (tmp_path / f"{system}.exr").read_bytes() == linux
        assert (tmp_path / f"{system}.png").read_bytes() == (tmp_path / "linux.png").read_bytes()


HOLD = PLAY + r'''
import logging
from prep.files import exclusive_lock

logging.basicConfig(level=logging.INFO, format="%(message)s")
play(sys.argv[1])
with exclusive_lock(sys.argv[2], "test folder"):
    print("held", flush=True)
    sys.stdin.readline()  # until told to let go
'''


def _line(stream, timeout: float = 60.0) -> str:
    """The next line of ``stream``, or what says that none came within ``timeout`` s (a test fails, not hangs)."""
    got = []
    reader = threading.Thread(target=lambda: got.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return got[0] if got else f"(no line within {timeout:.0f} s)"


def _holder(system: str, folder: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", HOLD, system, str(folder)], cwd=REPO, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONPATH": str(REPO)})


@pytest.mark.slow
@pytest.mark.parametrize("system", ["linux", "macos", "windows"])
def test_a_folder_lock_is_held_by_one_process_at_a_time_and_a_second_waits_naming_the_first(system, tmp_path):
    first = _holder(system, tmp_path)
    second = None
    try:
        assert _line(first.stdout) == "held\n"
        second = _holder(system, tmp_path)
        waiting = _line(second.stderr)
        assert f"test folder {tmp_path} is being written by another process (pid {first.pid})" in waiting
        time.sleep(1.0)
        assert second.poll() is None  # still waiting: nothing printed yet, and it is alive
        first.stdin.write("\n")
        first.stdin.flush()
        assert first.wait(timeout=30) == 0
        assert _line(second.stdout) == "held\n"  # taken once the first let go
        assert (tmp_path / ".lock").read_text() == f"{second.pid}\n"
        second.stdin.write("\n")
        second.stdin.flush()
        assert second.wait(timeout=30) == 0
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.kill()


ORPHAN = PLAY + r'''
import subprocess
child = subprocess.Popen([sys.executable, "-c", sys.argv[2], sys.argv[1]])
print(child.pid, flush=True)
child.wait()
'''

WATCHED = PLAY + r'''
import time
play(sys.argv[1])
processes.die_with_parent(os.getppid())
print("watching", flush=True)
time.sleep(120)
'''


@pytest.mark.slow
@pytest.mark.parametrize("system", ["linux", "macos", "windows"])
def test_a_worker_ends_when_the_process_that_started_it_is_killed(system):
    parent = subprocess.Popen([sys.executable, "-c", ORPHAN, system, WATCHED], cwd=REPO, text=True,
                              stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)})
    pid = None
    try:
        pid = int(_line(parent.stdout))
        assert _line(parent.stdout) == "watching\n"
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        deadline = time.monotonic() + 10 * processes.PARENT_POLL_S + 5
        while _runs(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _runs(pid), "the worker outlived its parent"
    finally:
        if parent.poll() is None:
            parent.kill()
        if pid is not None and _runs(pid):
            os.kill(pid, signal.SIGKILL)


def _runs(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


# ---------------------------------------------------------------- figures of memory and age

def _proc_status_mb(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


def _proc_available_mb() -> float:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) / 1024
    raise KeyError("MemAvailable")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="checked against Linux's /proc")
@pytest.mark.parametrize("linux", [True, False])
def test_memory_and_age_agree_with_the_kernels_own_figures_on_each_path(monkeypatch, linux):
    monkeypatch.setattr(processes, "LINUX", linux)
    # the peak resident size is at least what this process holds now, and at most what it ever held
    # (maxrss, the macOS path here, carries the parent's over exec: an upper bound, not Linux's VmHWM)
    assert processes.peak_memory_mb() >= _proc_status_mb("VmRSS") * 0.99
    if linux:
        assert processes.peak_memory_mb() == pytest.approx(_proc_status_mb("VmHWM"), abs=1)
    assert processes.available_memory_mb() == pytest.approx(_proc_available_mb(), rel=0.05, abs=64)
    # this test process has lived as long as pytest has (the kernel's start time of this process)
    started = psutil.Process().create_time()
    assert processes.process_age() == pytest.approx(time.time() - started, abs=1.5)  # btime: whole seconds
    if not linux:
        assert processes.reset_peak_memory() is False
    elif processes.reset_peak_memory():  # where the kernel lets a process reset it: the peak is now what it holds
        assert processes.peak_memory_mb() <= _proc_status_mb("VmRSS") + 16


def test_where_a_figure_cannot_be_known_it_is_none_and_a_frame_is_taken_to_fit(monkeypatch):
    monkeypatch.setattr(processes, "LINUX", False)
    monkeypatch.setitem(sys.modules, "psutil", None)  # Windows without psutil: neither /proc nor getrusage
    monkeypatch.setitem(sys.modules, "resource", None)
    assert processes.peak_memory_mb() is None
    assert processes.available_memory_mb() is None
    assert processes.process_age() is None
    assert processes.reset_peak_memory() is False
    assert processes.memory_shortfall(1 << 50) is None
    assert processes.memory_shortfall(1 << 30, available_mb=512.0) == (
        "needs 1.0 GiB, more than the 0.5 GiB this machine has available")


# ---------------------------------------------------------------- one module answers for the system

LIBRARY = [p for pkg in ("prep", "kpcn_keras", "kpcn") for p in sorted((REPO / pkg).rglob("*.py"))
           if "studies" not in p.relative_to(REPO).parts]  # the lab measures this machine; the library runs anywhere
SYSTEM_ONLY_MODULES = {"fcntl", "resource", "msvcrt", "termios", "pwd", "grp", "psutil"}
SYSTEM_ONLY_CALLS = {"CDLL", "prctl", "flock", "lockf", "sysconf", "pread", "pwrite", "O_DIRECTORY",
                     "sched_getaffinity", "getrusage", "killpg", "setsid", "register_at_fork"}


def system_calls(path: Path) -> list[str]:
    """What ``path`` uses that some system lacks: an import of a module some system lacks, an attribute of one such
    call, a string naming ``/proc``; as ``line: what``. In ``prep/processes.py``, only an import outside a function
    (one that would fail where the module is missing)."""
    tree = ast.parse(path.read_text())
    found = []
    own = path == REPO / "prep" / "processes.py"
    allowed = {id(n) for f in ast.walk(tree) if isinstance(f, ast.FunctionDef) for n in ast.walk(f)} if own else set()
    docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                  if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and n.body
                  and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    for node in ast.walk(tree):
        if id(node) in allowed:
            continue
        if isinstance(node, ast.Import):
            names = [a.name.split(".")[0] for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [(node.module or "").split(".")[0]]
        elif own:
            names = []
        elif isinstance(node, ast.Attribute):
            names = [node.attr] if node.attr in SYSTEM_ONLY_CALLS else []
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            names = ["/proc"] if node.value.startswith("/proc") else []
        else:
            names = []
        found += [(node.lineno, n) for n in names if n in SYSTEM_ONLY_MODULES | SYSTEM_ONLY_CALLS | {"/proc"}]
    return [f"{line}: {what}" for line, what in sorted(found)]


def test_only_prep_processes_calls_what_some_system_lacks_and_only_inside_its_functions():
    assert len(LIBRARY) > 40 and REPO / "prep" / "processes.py" in LIBRARY
    found = {str(p.relative_to(REPO)): calls for p in LIBRARY if (calls := system_calls(p))}
    assert found == {}, found


def test_the_guard_finds_each_kind_of_call_planted(tmp_path, monkeypatch):
    planted = tmp_path / "planted.py"
    planted.write_text('"""/proc in a docstring is prose."""\nimport fcntl\nfrom resource import getrusage\n'
                       'import ctypes\n\ndef f():\n    ctypes.CDLL(None)\n    return open("/proc/self/status")\n')
    assert system_calls(planted) == ["2: fcntl", "3: resource", "7: CDLL", "8: /proc"]
    # prep/processes.py itself: allowed inside a function, not at its top
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    (tmp_path / "prep").mkdir()
    (tmp_path / "prep" / "processes.py").write_text(planted.read_text())
    assert system_calls(tmp_path / "prep" / "processes.py") == ["2: fcntl", "3: resource"]
