"""Files that are never half-written, folders that one process writes at a time, and records read back
with errors that name them.

- :func:`atomic_path` is the one atomic-write primitive: every EXR, HDF5 shard, ``.keras`` model and text
  record of the project is written under a temporary name beside its target (``.<name>.tmp-<pid>-<token>
  <suffix>``, unique per process, hidden from every reader), flushed to disk and renamed over the target
  in one step. A kill at any point leaves either the old file or the new one, never a mixture. A write
  the file system refuses (a full disk) is one error, ``<file>: cannot write (<reason>)``
  (:func:`write_failure`), and leaves no temporary file.
- :func:`exclusive_lock` serialises the writers of one folder (a render set, a shard set, a run): a
  second command on the same folder waits for the first, then finds its work done.
- :func:`check_writable` lets a command refuse an output it could not write *before* the work starts, and
  :func:`check_outputs` one that would replace a file it reads (every command that writes files checks all
  of them against all of its inputs, before any work);
  :func:`check_set_name` refuses a set name that is not one plain folder.
- :func:`read_json` turns a missing or broken record into one line naming the file and what it is.

Dot-files in a folder (``.lock``, temporaries) are this module's; no reader takes them for data.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import re
import secrets
import zlib
from contextlib import contextmanager
from pathlib import Path

from prep.errors import KpcnError, OptionError
from prep.processes import in_forked_children, lock_file, sync_file, sync_folder, unlock_file

log = logging.getLogger("kpcn")

LOCK_NAME = ".lock"
_TEMP_MARK = ".tmp-"


def is_temporary(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a temporary file of :func:`atomic_path`."""
    name = Path(path).name
    return name.startswith(".") and _TEMP_MARK in name


@contextmanager
def atomic_path(path: str | os.PathLike, *, durable: bool = True):
    """Yield a temporary path beside ``path``; when the block ends normally it replaces ``path``.

    The temporary name keeps ``path``'s suffix (Keras and OpenEXR look at it). If the block raises, the
    temporary file is removed and ``path`` is left as it was. Failures of the file system (no space, no
    permission, a parent that is a file) become a KpcnError naming ``path`` (:func:`write_failure`),
    whether Python raised them or a library writing in the block (OpenEXR, HDF5) reported them.

    ``durable``: the file's bytes reach the disk (fsync) before the rename, so a power cut leaves the old
    file or the whole new one. Without it the rename is still atomic for every process, but after a power
    cut the new name may hold a torn file: only for files whose checksum a manifest lists and every reader
    checks (shards), where a torn file is found and written again.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}{_TEMP_MARK}{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        if durable:
            sync_file(tmp)
        os.replace(tmp, path)
        if durable:
            sync_folder(path.parent)
    except (OSError, RuntimeError) as exc:
        failure = write_failure(path, exc)
        if failure is None:
            raise
        raise failure from exc
    finally:
        if tmp.exists():
            tmp.unlink()


# what the file system answers a write it refuses: the errors a user can fix (space, rights, a path)
_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO,
                 errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG)
_HDF5_ERRNO = re.compile(r"\berrno = (\d+)")


def write_failure(path: str | os.PathLike, exc: BaseException) -> KpcnError | None:
    """The one error of a failed write of ``path``: ``<path>: cannot write (<the system's reason>)``.

    An OSError gives its errno's reason. The libraries that write files report the system's refusal in
    their own words: OpenEXR raises a RuntimeError ending in the reason ("... No space left on device."),
    HDF5 (through h5py) an OSError or RuntimeError whose text holds ``errno = 28``; the reason is found in
    the text. None for a RuntimeError that names no reason of the file system (a bug, not the disk).
    """
    code = getattr(exc, "errno", None) if isinstance(exc, OSError) else None
    text = str(exc)
    found = _HDF5_ERRNO.search(text)
    if found and int(found.group(1)) in errno.errorcode:
        code = int(found.group(1))  # h5py's OSError carries HDF5's long message as its strerror
    if code is None:
        code = next((c for c in _WRITE_ERRNOS if os.strerror(c) in text), None)
    if code is not None:
        return KpcnError(f"{path}: cannot write ({os.strerror(code)})")
    if isinstance(exc, OSError):
        return KpcnError(f"{path}: cannot write ({exc.strerror or exc})")
    return None


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Replace ``path`` with ``text`` in one step; an interrupted write leaves the old file as it was."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def atomic_write_json(path: str | os.PathLike, value) -> Path:
    """``value`` as indented JSON, written with :func:`atomic_write_text`."""
    return atomic_write_text(path, json.dumps(value, indent=2) + "\n")


def read_input(path: str | os.PathLike, expected: str, error=KpcnError) -> bytes:
    """The bytes of an input file; ``error`` (a KpcnError class) naming ``path`` if it is missing, a folder
    (``expected`` says what should be there: "an OBJ file") or unreadable."""
    path = Path(path)
    if not path.exists():
        raise error(f"{path}: no such file")
    if path.is_dir():
        raise error(f"{path}: is a folder, expected {expected}")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_json(path: str | os.PathLike, what: str, keys: tuple[str, ...] = ()):
    """The JSON value in ``path``, a ``what`` (for messages: "run record", "shard manifest", ...).

    KpcnError naming the file and ``what`` if it is missing, unreadable, not JSON, or (with ``keys``)
    not an object holding every key of ``keys``.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise KpcnError(f"{path}: no such {what}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise KpcnError(f"{path}: cannot read the {what} ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise KpcnError(
            f"{path}: the {what} is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None
    if keys:
        missing = [k for k in keys if not isinstance(value, dict) or k not in value]
        if missing:
            raise KpcnError(f"{path}: the {what} lacks {', '.join(repr(k) for k in missing)}")
    return value


def _blocks(path: str | os.PathLike, size: int = 1 << 22):
    """The bytes of the file ``path`` in blocks of ``size``: a checksum of a file of any size in bounded memory."""
    with open(path, "rb") as f:
        yield from iter(lambda: f.read(size), b"")


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    for block in _blocks(path):
        h.update(block)
    return h.hexdigest()


def crc32_file(path: str | os.PathLike) -> str:
    """The file's CRC-32 (zlib's), 8 hex digits: finds torn and damaged files, not tampering."""
    crc = 0
    for block in _blocks(path):
        crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def check_set_name(name) -> str:
    """``name`` if it can name a set's folder under a root (one plain path component), else OptionError
    ``set_name`` echoing it: a render set, a shard set and every command that reads one share this rule."""
    if not name or not isinstance(name, str) or "/" in name or name in (".", ".."):
        raise OptionError("set_name", f"must be a plain folder name, got {name!r}")
    return name


def check_writable(path: str | os.PathLike, what: str, *, directory: bool = False) -> Path:
    """Refuse now an output that could not be written later; returns ``path``.

    ``what`` names the option or output in the message (``"--output"``, ``"run folder"``). ``path`` may
    not exist yet: its nearest existing ancestor must be a folder in which a file can be created (tried
    for real, so read-only mounts and permissions count as they will). An existing ``path`` must be a
    folder when ``directory`` is set and must not be one otherwise.
    """
    path = Path(path)
    if path.exists() and path.is_dir() != directory:
        found = "a folder" if path.is_dir() else "a file"
        raise KpcnError(f"{what} {path}: is {found}, expected {'a folder' if directory else 'a file'}")
    ancestor = path if directory and path.is_dir() else path.parent
    while not ancestor.exists() and not ancestor.is_symlink():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise KpcnError(f"{what} {path}: {ancestor} is a file, not a folder")
    try:
        with open(ancestor / f".probe{_TEMP_MARK}{os.getpid()}-{secrets.token_hex(4)}", "x") as probe:
            pass
        os.unlink(probe.name)
    except OSError as exc:
        raise KpcnError(f"{what} {path}: cannot write in {ancestor} ({exc.strerror or exc})") from None
    return path


def _identity(path: str | os.PathLike):
    """What names one file: its device and inode where it exists (every link to it, any spelling of its path),
    else its path with every symlink resolved."""
    try:
        st = os.stat(path)
    except OSError:
        return "path", os.path.realpath(path)
    return "file", st.st_dev, st.st_ino


def check_outputs(outputs, inputs, fix: str = "choose another output") -> None:
    """Refuse, before any work, a command that would write a file over one it reads or write one file twice.

    ``outputs`` and ``inputs``: ``(what, path)`` pairs, every file the command writes (its EXRs, PNGs,
    reports) and every file it reads (inputs, references, models, a scene's textures), ``what`` naming each
    in the message (``"--output"``, ``"side-by-side PNG"``; ``"input"``, ``"reference"``). Two paths are one
    file when they resolve to it: the same inode (hard links, a symlink, ``./x`` and ``x``) or, for a file
    not written yet, the same path once symlinks are resolved. ``fix`` ends the message (what to change).
    """
    outputs = [(what, Path(path)) for what, path in outputs]
    read = {}
    for what, path in inputs:
        read.setdefault(_identity(path), (what, Path(path)))
    written = {}
    for what, path in outputs:
        key = _identity(path)
        if key in read:
            label, src = read[key]
            raise KpcnError(f"{what} {path} is the {label} file {src} itself; {fix}")
        if key in written:
            other_what, other = written[key]
            raise KpcnError(f"{what} {path} and {other_what} {other} are the same file; {fix}")
        written[key] = (what, path)


def temporary_target(path: str | os.PathLike) -> str | None:
    """The name of the file that the temporary ``path`` of :func:`atomic_path` was to replace (None if
    ``path`` is not one)."""
    name = Path(path).name
    return name[1:name.index(_TEMP_MARK)] if is_temporary(name) else None


def remove_temporaries(folder: str | os.PathLike, targets=None) -> int:
    """Remove the temporary files that killed writers left in ``folder``; returns how many.

    Call only while holding the lock of every writer of ``folder`` whose temporaries it removes: then no
    live writer owns one. ``targets``: only the temporaries of these file names (a part of a stage removes
    those of its own files while other parts write theirs); None: all of them.
    """
    count = 0
    for path in Path(folder).iterdir():
        if (is_temporary(path) and path.is_file()
                and (targets is None or temporary_target(path) in targets)):
            path.unlink()
            count += 1
    return count


@contextmanager
def exclusive_lock(folder: str | os.PathLike, what: str, name: str = LOCK_NAME):
    """Hold the lock of ``folder`` (created if needed) for the block; ``what`` names it in messages.
    ``name``: another lock of the same folder (``.lock-part-1-of-2``: a part of a split stage, which writes
    its own files while the other parts write theirs); it must start with ``.lock``.

    A second holder waits, saying for whom. The lock is the system's lock of ``folder/.lock``
    (``prep.processes.lock_file``: an advisory ``flock`` on POSIX): the system releases it when its process dies,
    so a killed command never leaves a stale lock. A flock belongs to the open file, which a forked child shares:
    a child (a shard worker) left behind by a killed parent would hold the lock on, so every forked child closes
    its copy first thing (``_held_locks``).
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not name.startswith(LOCK_NAME):
            raise ValueError(f"a lock's name starts with {LOCK_NAME!r}, got {name!r}")
        fd = os.open(folder / name, os.O_RDWR | os.O_CREAT | getattr(os, "O_BINARY", 0), 0o644)
    except OSError as exc:
        raise KpcnError(f"{what} {folder}: cannot lock ({exc.strerror or exc})") from None
    try:
        if not lock_file(fd, wait=False):
            os.lseek(fd, 0, os.SEEK_SET)
            holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
            log.info("%s %s is being written by another process (pid %s); waiting for it", what, folder, holder)
            lock_file(fd, wait=True)
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, f"{os.getpid()}\n".encode())
        _held_locks.add(fd)
        yield folder
    finally:
        if fd in _held_locks:
            _held_locks.discard(fd)
            unlock_file(fd)
        os.close(fd)


_held_locks: set[int] = set()


def _close_held_locks_in_child() -> None:
    for fd in _held_locks:
        os.close(fd)
    _held_locks.clear()


in_forked_children(_close_held_locks_in_child)


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display needed), imported only when a figure is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Write the matplotlib figure ``fig`` to ``path`` as PNG through :func:`atomic_path` and close it. No
    "Software" stamp: the same figure gives the same bytes whatever matplotlib version drew it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", metadata={"Software": None})
    pyplot().close(fig)
    return path
