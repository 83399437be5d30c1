"""The small pieces the command line's option builders share: comma-separated values, a dataclass field's
default for a help text, and the folders of a command that trains runs of its own."""

from __future__ import annotations

import argparse
import dataclasses


def csv(text: str) -> tuple[str, ...]:
    return tuple(t for t in (s.strip() for s in text.split(",")) if t)


def csv_ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(t) for t in csv(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def csv_floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(t) for t in csv(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def default(cls, name: str) -> str:
    """A dataclass field's default, for help texts."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    value = f.default_factory() if f.default is dataclasses.MISSING else f.default
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def experiment_folders(p: argparse.ArgumentParser, d, runs: str) -> None:
    """--set, --shards, --runs and --out of a command that trains runs of its own (compare, resample-study);
    ``d(name)`` is the help text of a field's default."""
    p.add_argument("--set", dest="set_name", help=f"shard set {d('set_name')}")
    p.add_argument("--shards", dest="shards_root", help=f"folder holding shard sets {d('shards_root')}")
    p.add_argument("--runs", dest="runs_root", help=f"folder of {runs}, reused when run again {d('runs_root')}")
    p.add_argument("--out", dest="out_dir", help=f"report folder {d('out_dir')}")


def defaults(cls):
    """``d(name)``: the help text of the default of field ``name`` of the dataclass ``cls``."""
    return lambda name: f"(default: {default(cls, name)})"
