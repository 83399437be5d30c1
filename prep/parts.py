"""Splitting an offline stage (``kpcn render``, ``kpcn shards``) over processes or machines, each writing the
files one process would.

A :class:`Part` is "part i of N" of a stage's work. Every part plans the whole work from the same options,
takes its own share (:meth:`Part.block` for items of even cost, :meth:`Part.balanced` for items of uneven
cost), writes each of its files atomically under its own lock, and the part that finishes last merges what
the parts recorded into the one record a single-process run writes. What a file holds never depends on
which part wrote it, so N parts write the same files (checksums equal) as one process.

The part comes from ``--part i/N`` (1-based: ``--part 1/2`` and ``--part 2/2`` split a stage in two), else
from a launcher's variables: ``torchrun`` sets ``RANK`` (0-based) and ``WORLD_SIZE`` for each process it
starts (:func:`launcher_variables`, shared with ``kpcn_keras.distributed``, so that training and the
offline stages read them one way). prep never imports torch: these are only environment variables.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

from prep.bounds import is_integer
from prep.errors import KpcnError, OptionError
from prep.files import LOCK_NAME

# what torchrun sets for each process it starts
RANK, WORLD_SIZE, LOCAL_RANK, LOCAL_WORLD_SIZE = "RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE"
_PART_RE = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")


class LaunchError(KpcnError, ValueError):
    """A launcher's environment variable that is malformed, or set without the others it needs."""


def launcher_variables(names: tuple[str, ...], environ=None) -> dict[str, int] | None:
    """The integer values of the launcher's variables ``names`` (from ``os.environ`` by default), or None
    when none is set. LaunchError naming the variable when one is not an integer, or some are set and
    others not."""
    environ = os.environ if environ is None else environ
    given = {name: environ.get(name) for name in names}
    if all(v is None for v in given.values()):
        return None
    missing = [name for name, v in given.items() if v is None]
    if missing:
        raise LaunchError(f"{', '.join(missing)} not set while {', '.join(n for n in names if n not in missing)} "
                          "is: start the processes with torchrun, which sets all of them")
    values = {}
    for name, text in given.items():
        try:
            values[name] = int(text)
        except ValueError:
            raise LaunchError(f"{name} must be an integer, got {text!r}") from None
    return values


@dataclass(frozen=True)
class Part:
    """Part ``index`` (0-based) of ``count``; ``Part()`` is the whole work."""

    index: int = 0
    count: int = 1

    def __post_init__(self):
        if not is_integer(self.count) or self.count < 1:
            raise OptionError("part", f"must be i/N with N >= 1, got {self.count!r} parts")
        if not is_integer(self.index) or not 0 <= self.index < self.count:
            raise OptionError("part", f"must be i/N with 1 <= i <= N, got {self}")

    @classmethod
    def parse(cls, text: str) -> Part:
        """``"i/N"`` (1-based i), as ``--part`` takes it."""
        match = _PART_RE.match(str(text))
        if not match:
            raise OptionError("part", f"must be i/N (part i of N, 1 <= i <= N), got {text!r}")
        index, count = int(match.group(1)), int(match.group(2))
        if count < 1 or not 1 <= index <= count:
            raise OptionError("part", f"must be i/N with 1 <= i <= N, got {text!r}")
        return cls(index - 1, count)

    @classmethod
    def from_environment(cls, environ=None) -> Part:
        """The part ``torchrun`` gives this process (``RANK`` of ``WORLD_SIZE``); the whole work without it."""
        values = launcher_variables((RANK, WORLD_SIZE), environ)
        if values is None:
            return cls()
        if values[WORLD_SIZE] < 1 or not 0 <= values[RANK] < values[WORLD_SIZE]:
            raise LaunchError(f"{RANK}={values[RANK]} and {WORLD_SIZE}={values[WORLD_SIZE]} name no process")
        return cls(values[RANK], values[WORLD_SIZE])

    @classmethod
    def chosen(cls, text: str | None = None, environ=None) -> Part:
        """``--part`` when given, else the launcher's."""
        return cls.from_environment(environ) if text is None else cls.parse(text)

    def __str__(self) -> str:
        return f"{self.index + 1}/{self.count}"

    @property
    def whole(self) -> bool:
        return self.count == 1

    @property
    def label(self) -> str:
        """For file names: ``part-1-of-2``."""
        return f"part-{self.index + 1}-of-{self.count}"

    @property
    def lock_name(self) -> str:
        """The lock a part holds while it writes its own files (``prep.files.exclusive_lock``'s ``name``):
        the folder's own lock for the whole work."""
        return LOCK_NAME if self.whole else f"{LOCK_NAME}-{self.label}"

    def block(self, n: int) -> range:
        """This part's share of ``n`` items of even cost, in order: a contiguous run of them, the shares
        differing by at most one item (neighbours stay together: a shard's input often spans the next)."""
        return range(self.index * n // self.count, (self.index + 1) * n // self.count)

    def balanced(self, costs: list[float]) -> list[int]:
        """This part's share of items of uneven ``costs``: their indices, ascending. The dearest item goes
        to the part with the least so far (ties to the lower part), which keeps the parts within one item's
        cost of each other; every part computes the same assignment from the same costs."""
        loads = [0.0] * self.count
        mine = []
        for i in sorted(range(len(costs)), key=lambda i: (-costs[i], i)):
            p = min(range(self.count), key=lambda p: (loads[p], p))
            loads[p] += costs[i]
            if p == self.index:
                mine.append(i)
        return sorted(mine)
