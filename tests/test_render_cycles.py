"""kpcn render-cycles (prep/render/cycles.py): the options checked, the Python with bpy found or refused in one line,
and the arguments the Blender side (prep/render/blender/cycles_set.py) reads back as the command's own."""
import ast
import importlib.util
import subprocess
import sys

import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.paths import REPO

from prep.render.cycles import BLENDER_PYTHON, BLENDER_SIDE, CATALOGUE, CyclesConfig, blender_command

NO_BPY = importlib.util.find_spec("bpy") is None  # the test environment's own Python, bpy-less as installed


def _blender_side():
    """The Blender side read by a Python without bpy (its argument parser alone)."""
    spec = importlib.util.spec_from_file_location("cycles_set", BLENDER_SIDE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_missing_blender_python_is_refused_in_one_line_naming_the_option(tmp_path):
    res = run_main("render-cycles", tmp_path / "cyc", "--blender-python", tmp_path / "no-python", cwd=tmp_path)
    assert_one_line_error(res, "kpcn render-cycles: error: --blender-python", str(tmp_path / "no-python"),
                          "no such Python", "make .venv-bpy/bin/python")
    assert not (tmp_path / "cyc").exists()


def test_the_default_blender_python_is_the_venv_make_makes_and_is_refused_where_there_is_none(tmp_path):
    assert CyclesConfig(out="o").blender_python == BLENDER_PYTHON == ".venv-bpy/bin/python"
    res = run_main("render-cycles", tmp_path / "cyc", cwd=tmp_path)  # tmp_path holds no .venv-bpy
    assert_one_line_error(res, "--blender-python", ".venv-bpy/bin/python")


@pytest.mark.skipif(not NO_BPY, reason="this Python has bpy")
def test_a_python_without_bpy_is_refused_in_one_line_naming_the_option(tmp_path):
    res = run_main("render-cycles", tmp_path / "cyc", "--blender-python", sys.executable, cwd=tmp_path)
    assert_one_line_error(res, "--blender-python", sys.executable, "without bpy")


@pytest.mark.parametrize("args, needle", [(("--scenes", "5:5"), "--scenes"), (("--scenes", "a:b"), "--scenes"),
                                          (("--scenes", "3"), "--scenes"), (("--spp", "4,4"), "--spp"),
                                          (("--spp", "8", "--ref-spp", "8"), "--ref-spp"), (("--res", "0"), "--res"),
                                          (("--res", "64,64"), "--res"), (("--seed", "-1"), "--seed")])
def test_bad_options_are_refused_in_one_line_before_any_python_is_looked_for(tmp_path, args, needle):
    res = run_main("render-cycles", tmp_path / "cyc", *args, "--blender-python", tmp_path / "none", cwd=tmp_path)
    assert_one_line_error(res, f"kpcn render-cycles: error: {needle}")


@pytest.mark.skipif(not NO_BPY, reason="the Blender side is read here without bpy")
def test_the_blender_side_reads_the_commands_arguments_back_as_its_options(tmp_path):
    cfg = CyclesConfig(out=str(tmp_path / "cyc"), scenes="3:7", res=(64, 96), spp=(2, 8), ref_spp=512, seed=5,
                       blender_python="/opt/py")
    command = blender_command(cfg)
    assert command[:2] == ["/opt/py", str(BLENDER_SIDE)]
    got = _blender_side().arguments(command[2:])
    assert (got.out, got.scenes, got.res, got.spp, got.ref_spp, got.seed) == (cfg.out, "3:7", "64,96", "2,8", 512, 5)
    # the defaults on both sides are one ladder
    default = _blender_side().arguments(blender_command(CyclesConfig(out="o"))[2:])
    assert vars(default) == vars(_blender_side().arguments(["o"]))


def _imports(path):
    tree = ast.parse(path.read_text())
    names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    return names | {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}


def test_the_blender_side_imports_nothing_but_the_standard_library_bpy_and_its_catalogue():
    # it runs in bpy's own venv, where kpcn is not installed; its catalogue is read by kpcn too, without bpy
    assert _imports(BLENDER_SIDE) - set(sys.stdlib_module_names) == {"bpy", "catalogue"}
    assert _imports(CATALOGUE) and _imports(CATALOGUE) <= set(sys.stdlib_module_names)


def test_a_blender_run_that_fails_is_one_line_that_says_the_same_command_resumes(tmp_path, monkeypatch):
    # a bpy that imports but is no Blender: the Blender side stops at its first call, as a crashed render would
    (tmp_path / "fake" / "bpy").mkdir(parents=True)
    (tmp_path / "fake" / "bpy" / "__init__.py").write_text("")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "fake"))
    res = run_main("render-cycles", tmp_path / "cyc", "--scenes", "0:1", "--blender-python", sys.executable,
                   cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    # Blender's Python says what it says (here a traceback); kpcn adds one line of its own
    ours = [line for line in res.stderr.splitlines() if line.startswith("kpcn render-cycles:")]
    assert len(ours) == 1 and ours[0].startswith(f"kpcn render-cycles: error: {tmp_path / 'cyc'}: Blender's Python")
    assert "exit status 1" in ours[0] and "resumes" in ours[0]


@pytest.mark.slow  # a fresh interpreter
def test_the_data_stages_commands_import_no_deep_learning():
    code = ("import sys; from kpcn_keras.parser import build_parser; build_parser(); "
            "import prep.imported, prep.render.cycles, kpcn_keras.studies.render_bench; "
            "bad = [m for m in ('keras', 'torch') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
