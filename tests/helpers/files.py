"""Files as the tests see them: checksums of a folder (what a resumed command must leave byte-identical) and a
full disk."""

import hashlib
import os
import subprocess
from pathlib import Path

import pytest


class SmallDisk:
    """A folder on a tmpfs of its own, ``size`` bytes (64 kB: full after the first file of any size), and
    :meth:`grow`, the space freed."""

    def __init__(self, path: Path, size: str = "64k"):
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        try:
            res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                                 capture_output=True, text=True)
            why = (res.stderr.strip() or f"exit {res.returncode}") if res.returncode else None
        except OSError as exc:
            why = str(exc)
        if why:
            pytest.skip(f"a full disk needs a small tmpfs, and mounting one is not permitted here (uid "
                        f"{os.getuid()}: {why})")

    def grow(self, size: str = "256m") -> None:
        subprocess.run(["mount", "-o", f"remount,size={size}", str(self.path)], check=True)

    def unmount(self) -> None:
        subprocess.run(["umount", "--lazy", str(self.path)], check=True)


def checksums(root: Path) -> dict[str, str]:
    """SHA-256 of every file under ``root`` but dot files (locks, temporaries), by path relative to it."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(root).rglob("*")) if p.is_file() and not p.name.startswith(".")}


def checksums_but_timings(root: Path) -> dict[str, str]:
    """:func:`checksums` but the timings files (``timings.json``, one per folder that keeps seconds): what a
    resumed command must leave byte-identical to an uninterrupted one."""
    return {k: v for k, v in checksums(root).items() if Path(k).name != "timings.json"}
