"""The bounds of every numeric option, and the one check of them (no numpy, no numba: ``kpcn --help`` reads it).

A config dataclass (``RenderConfig``, ``ShardConfig``, ``TrainConfig``, ...) declares a field's bound where it
declares its default, ``width: int = bounded(256, FRAME_SIDE)``, and calls :func:`check_fields` first thing
in its check: every bounded field is checked there, and nowhere else. A field whose value is a list (an spp
ladder, the seeds of a study) has each element checked, and ``distinct=True`` refuses a repeat, naming it
(``--families cornell,cornell`` would do the same work twice). ``kpcn --help`` states every bound from the
same :class:`Bound` (:meth:`Bound.text`), so what the help says is what the check does. A bound is closed at
both ends unless marked open; every bound is finite: a size or a count with no upper bound lets one typo
allocate the machine's memory or run for a year.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import operator
from dataclasses import dataclass
from typing import Any

from prep.errors import OptionError

BOUND = "kpcn.bound"  # field metadata keys
DISTINCT = "kpcn.distinct"


@dataclass(frozen=True)
class Bound:
    """The range of one option: ``low`` to ``high``, integers (``integer``; ``odd``: odd integers only) or
    numbers (a float; ``low_open``/``high_open`` exclude an end)."""

    low: float
    high: float
    integer: bool = True
    odd: bool = False
    low_open: bool = False
    high_open: bool = False

    def __post_init__(self):
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low <= self.high):
            raise ValueError(f"a bound is finite at both ends and low <= high, got {self}")

    def text(self) -> str:
        """The bound as ``--help`` and the error messages state it: ``an integer in [1, 16384]``."""
        if self.integer:
            kind = "an odd integer" if self.odd else "an integer"
            return f"{kind} in [{_num(self.low)}, {_num(self.high)}]"
        return (f"a number in {'(' if self.low_open else '['}{_num(self.low)}, "
                f"{_num(self.high)}{')' if self.high_open else ']'}")

    def contains(self, value) -> bool:
        if isinstance(value, bool):
            return False
        if self.integer:
            if not is_integer(value):  # ints and numpy integers; not floats, not strings
                return False
            return self.low <= value <= self.high and (not self.odd or value % 2 == 1)
        if not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
            return False
        try:
            value = float(value)
        except (TypeError, ValueError):
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below  # NaN is neither

    def check(self, name: str, value):
        """``value`` as an int (or a float), or OptionError ``name`` stating the bound and echoing ``value``."""
        if not self.contains(value):
            raise OptionError(name, f"must be {self.text()}, got {value!r}")
        return operator.index(value) if self.integer else float(value)


def is_integer(value) -> bool:
    """Whether ``value`` is an integer (an int or a numpy integer) and not a bool: ``True`` is an int to
    Python, but a flag typed where a count belongs is a mistake to refuse, not 1."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value) -> bool:
    """Whether ``value`` is a real number (int, float or a numpy number) and not a bool (see :func:`is_integer`)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _num(x: float) -> str:
    if float(x).is_integer() and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}"


# One seed range for the whole project: every seed reaches numpy's legacy seeding or Keras's
# ``set_random_seed`` (training), which take integers below 2**32 only; render and shards derive their own
# streams from it by SeedSequence, which would take more, but a seed that a set accepts must train too.
SEED = Bound(0, 2**32 - 1)
REPEATS = Bound(1, 1000)  # timed calls of a measurement (the benches, compare)
PATCH_COUNT = Bound(1, 65536)  # patches per image, per shard, per resampling round (shards are bounded in bytes too)


def bounded(default: Any = dataclasses.MISSING, bound: Bound | None = None, *, distinct: bool = False,
            default_factory: Any = dataclasses.MISSING, **kw) -> Any:
    """A dataclass field with a default and the bound of its value (or of each of its values); see the
    module docstring."""
    metadata = {BOUND: bound, DISTINCT: distinct}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=metadata, **kw)
    return dataclasses.field(default=default, metadata=metadata, **kw)


def bound_of(cls, name: str) -> Bound | None:
    """The bound of field ``name`` of the dataclass ``cls`` (None: unbounded or no such field)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f.metadata.get(BOUND)
    return None


def check_distinct(name: str, values) -> None:
    """OptionError ``name`` naming the values that ``values`` holds more than once."""
    values = list(values)
    repeated = [v for i, v in enumerate(values) if v in values[:i]]
    if repeated:
        shown = ", ".join(dict.fromkeys(str(v) for v in repeated))
        raise OptionError(name, f"names {shown} more than once, got {','.join(map(str, values))}")


def check_fields(obj) -> None:
    """Check every bounded (or ``distinct``) field of the dataclass instance ``obj``, in field order, and
    store each checked value back as an int or float (a list as a tuple). A field whose value is None is
    left alone when None is its default (an option not given)."""
    for f in dataclasses.fields(obj):
        bound, distinct = f.metadata.get(BOUND), f.metadata.get(DISTINCT, False)
        if bound is None and not distinct:
            continue
        value = getattr(obj, f.name)
        if value is None and f.default is None:
            continue
        if isinstance(value, (list, tuple)):
            if bound is not None:
                value = tuple(bound.check(f.name, v) for v in value)
            if distinct:
                check_distinct(f.name, value)
        elif bound is not None:
            value = bound.check(f.name, value)
        object.__setattr__(obj, f.name, value)  # frozen dataclasses too


__all__ = ["PATCH_COUNT", "REPEATS", "SEED", "Bound", "bound_of", "bounded", "check_distinct", "check_fields",
           "is_integer", "is_number"]
