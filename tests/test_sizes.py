"""The size of the rooms, read from the source: every Python file of the repository under 800 lines, every
function (a method, a nested one) at most 80, with no list of exceptions.

Every ``.py`` file counts: the packages, their studies, ``tests/`` and any folder added later; only hidden
folders (``.venv``, ``.git``) and what a build or a run writes (the folders that ``.gitignore`` names) are left
out. A file grows past the line by taking a second job: split it by concept (the
owners are in docs/design.md), not by cutting it in two.
"""

import ast
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MAX_FILE_LINES = 799  # under 800
MAX_FUNCTION_LINES = 80
# what a build, an install, a run or the pipeline writes at the top of the repository (.gitignore): never source
OUTPUTS = frozenset({"build", "dist", "data", "runs", "shards"})


def _sources(root: Path) -> list[Path]:
    """Every .py file under ``root`` but in a hidden folder, an output folder, a __pycache__ or an egg-info."""
    found = []
    for folder, subfolders, files in os.walk(root):
        top = Path(folder) == root
        subfolders[:] = [s for s in subfolders if not (s.startswith(".") or s == "__pycache__"
                                                       or s.endswith(".egg-info") or (top and s in OUTPUTS))]
        found += [Path(folder) / f for f in files if f.endswith(".py")]
    return sorted(found)


def _functions(tree: ast.AST, prefix: str = ""):
    """(qualified name, lines) of every function in ``tree``, at any depth: ``Class.method``, ``outer.inner``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = prefix + node.name
            if not isinstance(node, ast.ClassDef):
                yield name, node.end_lineno - node.lineno + 1
            yield from _functions(node, name + ".")
        else:
            yield from _functions(node, prefix)


def oversized(root: Path) -> list[str]:
    """One line per file of ``root`` over :data:`MAX_FILE_LINES` lines and per function over
    :data:`MAX_FUNCTION_LINES`, each naming it and its size."""
    found = []
    for path in _sources(root):
        text = path.read_text(encoding="utf-8")
        where = path.relative_to(root).as_posix()
        lines = len(text.splitlines())
        if lines > MAX_FILE_LINES:
            found.append(f"{where}: {lines} lines (at most {MAX_FILE_LINES})")
        found += [f"{where}::{name}: {size} lines (at most {MAX_FUNCTION_LINES})"
                  for name, size in _functions(ast.parse(text, where)) if size > MAX_FUNCTION_LINES]
    return found


def _check(root: Path) -> None:
    found = oversized(root)
    assert not found, "split these by concept (docs/design.md names the owners):\n" + "\n".join(found)


def test_every_source_file_is_under_800_lines_and_every_function_at_most_80():
    assert {"prep", "kpcn_keras", "kpcn", "tests"} <= {p.relative_to(ROOT).parts[0] for p in _sources(ROOT)}
    _check(ROOT)


def _function(name: str, lines: int, indent: str = "") -> str:
    """Source of a function ``name`` of exactly ``lines`` lines."""
    return "".join([f"{indent}def {name}():\n", *(f"{indent}    x = {i}\n" for i in range(lines - 2)),
                    f"{indent}    return x\n"])


def test_the_checker_names_each_long_file_and_function_and_passes_those_at_the_limits(tmp_path):
    # at the limits: a file of 799 lines holding a function and a method of 80
    fits = tmp_path / "pkg" / "fits.py"
    fits.parent.mkdir()
    text = _function("fits", 80) + "class C:\n" + _function("method", 80, "    ")
    fits.write_text(text + "pass\n" * (799 - len(text.splitlines())))
    _check(tmp_path)
    # one over each: an 801-line file holding a function, a method and a nested function of 81 (whose outer
    # function is longer still)
    long = tmp_path / "scripts" / "long.py"
    long.parent.mkdir()
    text = _function("long", 81) + "class C:\n" + _function("method", 81, "    ")
    text += "def outer():\n" + _function("inner", 81, "    ") + "    return inner\n"
    long.write_text(text + "pass\n" * (801 - len(text.splitlines())))
    # what is not source is not read: a virtual environment, a run folder, an egg-info
    for folder in (".venv/lib", "runs/r", "kpcn.egg-info", "pkg/__pycache__"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "big.py").write_text(_function("big", 900))
    assert oversized(tmp_path) == [
        "scripts/long.py: 801 lines (at most 799)",
        "scripts/long.py::long: 81 lines (at most 80)",
        "scripts/long.py::C.method: 81 lines (at most 80)",
        "scripts/long.py::outer: 83 lines (at most 80)",
        "scripts/long.py::outer.inner: 81 lines (at most 80)",
    ]
    with pytest.raises(AssertionError, match=r"(?s)scripts/long\.py: 801 lines.*outer\.inner: 81 lines"):
        _check(tmp_path)
