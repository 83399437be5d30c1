"""The floor plan of the packages, read from their source: who may import whom.

Every import of a module counts, at any depth (one inside a function too: it closes a circle as soon as
that function runs). Three floors (:data:`FLOORS`): ``prep``, the offline stage, on the ground; the library
(``kpcn_keras`` and ``kpcn``, the public API) above it; the lab and the command line (which runs the lab's
studies, and whose parser the lab uses to spell a command) on top; no import runs up a floor. No circle
anywhere; ``prep`` never imports the deep-learning stack nor ``kpcn_keras``;
the library never imports a study (only the command line does, inside a study's command), and every study
lives in ``kpcn_keras.studies``; ``kpcn_keras.config`` imports nothing else of its package.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("prep", "kpcn_keras", "kpcn")
DEEP_LEARNING = ("keras", "torch")
# the one way in to the studies
COMMAND_LINE = ("kpcn_keras.cli", "kpcn_keras.parser", "kpcn_keras.options", "kpcn_keras.study_options",
                "kpcn_keras.helpdoc")
STUDIES = ("kpcn_keras.studies",)  # the lab: every study and cost probe, and nothing else
FLOORS = (("prep",), ("kpcn_keras", "kpcn"), (*STUDIES, *COMMAND_LINE))  # the ground first


def _modules() -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the packages (a package is its __init__)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _imported(name: str, path: Path) -> set[str]:
    """Every module ``name`` imports, anywhere in it, as dotted names (``from a import b`` names both ``a``
    and ``a.b``, since ``b`` may be a module)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                package = package[: len(package) - node.level + 1]
                base = ".".join(package + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def _graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(module -> the project's modules it imports, module -> every name it imports)."""
    modules = _modules()
    every = {m: _imported(m, p) for m, p in modules.items()}
    return {m: {d for d in names if d in modules and d != m} for m, names in every.items()}, every


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iteratively)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            child = next(successors, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _inside(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def test_no_module_of_the_project_is_in_an_import_circle():
    graph, _ = _graph()
    assert _cycles(graph) == []


def test_the_circle_finder_finds_a_circle_through_a_package_init():
    # the finder itself can fail: prep.render's __init__ importing a submodule that imports the package
    graph = {"p": {"p.a"}, "p.a": {"p.b"}, "p.b": {"p"}, "q": {"p.a"}}
    assert _cycles(graph) == [["p", "p.a", "p.b"]]


def test_prep_never_imports_the_deep_learning_stack_or_kpcn_keras():
    _, every = _graph()
    bad = {m: sorted(d for d in names if any(_inside(d, p) for p in (*DEEP_LEARNING, "kpcn_keras")))
           for m, names in every.items() if _inside(m, "prep")}
    assert {m: d for m, d in bad.items() if d} == {}


def _floor(name: str, floors=FLOORS) -> int:
    """The floor of module ``name``: that of the longest package or module of :data:`FLOORS` it is inside."""
    found = [(len(p), i) for i, names in enumerate(floors) for p in names if _inside(name, p)]
    return max(found)[1]


def _up_arrows(graph: dict[str, set[str]], floors=FLOORS) -> list[str]:
    return sorted(f"{m} (floor {_floor(m, floors)}) -> {d} (floor {_floor(d, floors)})"
                  for m, deps in graph.items() for d in deps if _floor(d, floors) > _floor(m, floors))


def test_no_import_runs_up_a_floor():
    graph, _ = _graph()
    assert {_floor(m) for m in graph} == set(range(len(FLOORS)))  # every floor has rooms
    assert _up_arrows(graph) == []


def test_the_floor_check_finds_an_import_running_up():
    # the library reaching up to the parser to spell a flag: what the check exists to refuse
    graph = {"kpcn_keras.run": {"kpcn_keras.parser", "prep.files"}, "kpcn_keras.parser": {"kpcn_keras.config"},
             "prep.files": {"kpcn_keras.config"}, "kpcn_keras.config": set()}
    assert _up_arrows(graph) == ["kpcn_keras.run (floor 1) -> kpcn_keras.parser (floor 2)",
                                 "prep.files (floor 0) -> kpcn_keras.config (floor 1)"]


def test_the_library_never_imports_a_study():
    graph, _ = _graph()

    def study(name):
        return any(_inside(name, s) for s in STUDIES)

    bad = {m: sorted(d for d in deps if study(d)) for m, deps in graph.items()
           if not study(m) and m not in COMMAND_LINE}
    assert {m: d for m, d in bad.items() if d} == {}


def test_the_training_config_imports_nothing_else_of_its_package():
    graph, _ = _graph()
    assert sorted(d for d in graph["kpcn_keras.config"] if _inside(d, "kpcn_keras")) == []


def test_every_python_file_outside_the_tests_is_in_a_package():
    # the lab has one home: a study or a probe is a module of kpcn_keras.studies, never a loose script
    # (scripts/, reports/*.py) beside the packages; kpcn is the public API's package
    # blender/: the Blender add-on and its zip's builder (docs/blender.md), code of Blender's Python that kpcn never
    # imports (tests/test_blender_addon.py holds that it imports nothing of kpcn)
    homes = (*PACKAGES, "blender")
    loose = sorted(p.relative_to(ROOT).as_posix() for top in ROOT.iterdir()
                   if top.is_dir() and not top.name.startswith(".") and top.name not in (*homes, "tests")
                   for p in top.rglob("*.py"))
    assert loose == []
