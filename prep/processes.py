"""What the operating system gives a process, in one module: a lock on an open file, files and folders made
durable, memory (what the machine has available, this process's peak), the process's age, a worker that dies with
its parent, the C library's stdio and allocator.

Linux is where kpcn is built and measured, and there each function does what it always did (``flock``,
``/proc``, ``prctl``, glibc's ``mallopt``). No module that some system lacks (``fcntl``, ``resource``,
``msvcrt``, ``psutil``) is imported at the top: each is imported by the function that needs it, so that this module,
and ``kpcn denoise``, import and run on macOS and Windows, where each function takes its portable path:

- a lock: ``flock`` on every POSIX system; on Windows ``msvcrt.locking`` of one byte (:func:`lock_file`);
- memory and age: ``psutil`` (a dependency off Linux) and, on macOS, ``getrusage``; None where a figure cannot be
  known, and every caller prints or records nothing then;
- a parent's death: Linux's kernel signal; elsewhere a thread that polls the parent (:func:`die_with_parent`);
- the allocator setting: nothing off glibc; the C stdio flush: Windows' universal C runtime.

Why each Linux call is there: a shard worker (``prep.shards``) or a training process started by torchrun
(``kpcn_keras.distributed``) left running by a killed parent would go on writing, or hold a folder's lock, or
wait for its peers forever; :func:`die_with_parent` makes the kernel end it instead. :func:`memory_shortfall` lets
render and denoise refuse a frame whose whole-frame arrays the machine cannot hold before any work starts.
:func:`keep_freed_memory` stops glibc's malloc from handing freed blocks back to the kernel (every command sets
it, ``kpcn_keras.cli.main``): torch allocates and frees a tile's activations, megabytes each, at every layer,
and glibc unmaps a freed block above its mmap threshold (at most 32 MB, adjusted as it goes) or trims its
heap's top, so the next allocation of that size faults its pages in again, zeroed by the kernel. Measured on
this 2-core machine (2026-12-03, ``kpcn_keras.studies.slope_map_costs``' 512 x 512 frame of a λ mixture run): a new λ
map 160-300 ms before, 90-120 ms after; the resident peak is the same, what is freed is reused.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
import time
from pathlib import Path

# Which path each function takes: module attributes, so that a test can play another system on this one
# (tests/test_processes.py)
LINUX = sys.platform.startswith("linux")
WINDOWS = sys.platform == "win32"
PROC = Path("/proc")  # Linux's process file system

# mallopt parameters (malloc.h) and their values: no block mmapped below 1 GB, the heap never trimmed, and each
# heap growth 256 MB beyond the request (address space: pages are resident only once written)
ALLOCATOR = {"M_MMAP_THRESHOLD": (-3, 1 << 30), "M_TRIM_THRESHOLD": (-1, 2**31 - 1), "M_TOP_PAD": (-2, 1 << 28)}

# Windows: the byte a lock holds, past what a lock file holds (its holder's pid), since a Windows lock is mandatory
# and a waiter must still read the pid; locking beyond the end of a file is allowed there
LOCK_BYTE = 1 << 20
LOCK_POLL_S = 0.1
PARENT_POLL_S = 0.5


def _psutil():
    """The ``psutil`` module, or None where it is not installed (a dependency off Linux only)."""
    try:
        import psutil
    except ImportError:
        return None
    return psutil


# ---------------------------------------------------------------- locks and durable files

def lock_file(fd: int, *, wait: bool) -> bool:
    """Take the exclusive lock of the open file ``fd``: True once taken; False if another process holds it and
    ``wait`` is False. The system releases it when the file is closed or its process ends, however it ends, so a
    killed holder never leaves a stale lock.

    POSIX (Linux, macOS): an advisory ``flock`` of the whole file; a forked child shares it through the open file.
    Windows: ``msvcrt.locking`` of :data:`LOCK_BYTE`, polled every :data:`LOCK_POLL_S` when waiting (its own
    waiting mode gives up after 10 s); ``filelock``'s Windows lock is the same call, not used because its lock
    owns its file (truncated when taken, deleted when released) where a folder's lock file also names its holder.
    """
    if WINDOWS:
        return _lock_byte(fd, wait)
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except OSError as exc:
        if wait or exc.errno not in (errno.EAGAIN, errno.EACCES):
            raise
        return False
    return True


def _lock_byte(fd: int, wait: bool) -> bool:
    import msvcrt

    while True:
        os.lseek(fd, LOCK_BYTE, os.SEEK_SET)
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
            return True
        except OSError as exc:
            if exc.errno not in (errno.EACCES, errno.EDEADLK):  # EDEADLK: Windows' EDEADLOCK, "held"
                raise
        if not wait:
            return False
        time.sleep(LOCK_POLL_S)


def unlock_file(fd: int) -> None:
    """Release the lock :func:`lock_file` took, before ``fd`` is closed. POSIX: nothing, closing releases it;
    Windows: unlocked here, since Windows releases a closed file's locks only when it gets to it."""
    if WINDOWS:
        import msvcrt

        os.lseek(fd, LOCK_BYTE, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def in_forked_children(call) -> None:
    """Have ``call`` run first thing in every child this process forks from now on; nothing where the system
    cannot fork (Windows)."""
    if hasattr(os, "register_at_fork"):
        os.register_at_fork(after_in_child=call)


def sync_file(path: str | os.PathLike) -> None:
    """Wait until the bytes of the file ``path`` are on the disk (fsync). Windows flushes only a file opened for
    writing."""
    fd = os.open(path, os.O_RDWR if WINDOWS else os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def sync_folder(path: str | os.PathLike) -> None:
    """Wait until the entries of the folder ``path`` (a file renamed into it) are on the disk: fsync of the folder
    on POSIX; nothing on Windows, which cannot open a folder as a file (NTFS journals its entries itself)."""
    if WINDOWS:
        return
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# ---------------------------------------------------------------- memory and age

def proc_megabytes(path: str | os.PathLike, keys) -> dict[str, float]:
    """The ``keys`` of a Linux ``/proc`` table of ``Key: N kB`` lines (``/proc/meminfo``,
    ``/proc/self/status``) in MiB; the keys not found, or every key off Linux, are left out."""
    found = {}
    try:
        for line in Path(path).read_text().splitlines():
            key, _, value = line.partition(":")
            if key in keys:
                found[key] = int(value.split()[0]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return found


def available_memory_mb() -> float | None:
    """The memory this machine has available for a new allocation without swapping, in MiB (Linux
    ``MemAvailable``; elsewhere ``psutil``'s figure), or None where it cannot be read."""
    if LINUX:
        return proc_megabytes(PROC / "meminfo", ("MemAvailable",)).get("MemAvailable")
    psutil = _psutil()
    return None if psutil is None else psutil.virtual_memory().available / 2**20


def memory_shortfall(needed_bytes: int, *, available_mb: float | None = None) -> str | None:
    """None where ``needed_bytes`` fit the memory this machine has available (:func:`available_memory_mb`;
    ``available_mb`` instead where given; taken to fit where it cannot be read), else the end of a message
    saying so: ``"needs 79.0 GiB, more than the 20.1 GiB this machine has available"``."""
    if available_mb is None:
        available_mb = available_memory_mb()
    if available_mb is None or needed_bytes <= available_mb * 2**20:
        return None
    return (f"needs {needed_bytes / 2**30:.1f} GiB, more than the {available_mb / 1024:.1f} GiB this machine has "
            "available")


def peak_memory_mb() -> float | None:
    """This process's peak resident memory in MiB, or None where it cannot be read. Linux: ``VmHWM``, not
    ``getrusage``, whose maxrss carries over the parent's resident size through fork and exec; elsewhere the peak
    working set where ``psutil`` reports one (Windows), else ``getrusage``'s maxrss (bytes on macOS, kB on the
    other POSIX systems)."""
    if LINUX:
        return proc_megabytes(PROC / "self" / "status", ("VmHWM",)).get("VmHWM")
    psutil = _psutil()
    peak = None if psutil is None else getattr(psutil.Process().memory_info(), "peak_wset", None)
    if peak is not None:
        return peak / 2**20
    try:
        import resource
    except ImportError:
        return None
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return maxrss / 2**20 if sys.platform == "darwin" else maxrss / 1024


def reset_peak_memory() -> bool:
    """Reset this process's peak resident memory (Linux: ``/proc/self/clear_refs``), so that the peak read after
    is what follows; False where it cannot be (every other system)."""
    if not LINUX:
        return False
    try:
        with open(PROC / "self" / "clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def process_age() -> float | None:
    """Seconds since this process started (Linux ``/proc``; elsewhere ``psutil``), or None where that cannot be
    read: the start-up (interpreter and imports) that precedes a call."""
    if not LINUX:
        psutil = _psutil()
        return None if psutil is None else max(time.time() - psutil.Process().create_time(), 0.0)
    try:
        start_ticks = int((PROC / "self" / "stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float((PROC / "uptime").read_text().split()[0])
        return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return None


# ---------------------------------------------------------------- the C library and the parent

def keep_freed_memory() -> bool:
    """Keep freed memory in this process for reuse (the module docstring); True where glibc took every setting,
    False elsewhere (another C library, another system: nothing is changed)."""
    if not LINUX:
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError):  # not glibc (musl has no mallopt)
        return False
    return all(mallopt(code, value) == 1 for code, value in ALLOCATOR.values())


def flush_c_stdio() -> bool:
    """Flush the C library's stdio buffers (what native code printed, buffered when fd 1 is not a tty): the
    process's own C library on POSIX, the universal C runtime (what extensions are built against) on Windows.
    False where it cannot be loaded."""
    import ctypes

    try:
        (ctypes.CDLL("ucrtbase") if WINDOWS else ctypes.CDLL(None)).fflush(None)
    except (AttributeError, OSError, TypeError):
        return False
    return True


def die_with_parent(parent: int) -> None:
    """End this process (SIGKILL on Linux, ``os._exit(1)`` elsewhere) when ``parent``, the process that started
    it, ends, however it ends. If ``parent`` is already gone, end now.

    Linux: the kernel's PR_SET_PDEATHSIG. Elsewhere a weaker stand-in: a daemon thread that looks every
    :data:`PARENT_POLL_S` s (POSIX: whether this process was handed to another parent; Windows: whether ``parent``
    runs, by ``psutil``), so the end comes up to that late, and only once native code lets Python's threads run."""
    if not LINUX:
        alive = _parent_check(parent)
        if alive is None:  # Windows without psutil: nothing is set
            return
        if not alive():
            os._exit(1)
        threading.Thread(target=_exit_when_gone, args=(alive,), name="kpcn-parent-watch", daemon=True).start()
        return
    import ctypes
    import signal

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # it ended before the request was made
        os._exit(1)


def _parent_check(parent: int):
    """A call that says whether ``parent`` still runs, or None where that cannot be known."""
    if not WINDOWS:
        return lambda: os.getppid() == parent
    psutil = _psutil()
    if psutil is None:
        return None
    try:
        watched = psutil.Process(parent)  # is_running also tells a new process that took the same pid
    except psutil.NoSuchProcess:
        return lambda: False
    return watched.is_running


def _exit_when_gone(alive) -> None:
    while alive():
        time.sleep(PARENT_POLL_S)
    os._exit(1)


__all__ = [
    "available_memory_mb", "die_with_parent", "flush_c_stdio", "in_forked_children", "keep_freed_memory",
    "lock_file", "memory_shortfall", "peak_memory_mb", "proc_megabytes", "process_age", "reset_peak_memory",
    "sync_file", "sync_folder", "unlock_file"
]
