"""The Blender add-on (blender/kpcn_addon, docs/blender.md): built into the extension zip by make addon, installed
from it into real headless Blender (bpy 5.0.1 in its own venv, .venv-bpy, as make .venv-bpy/bin/python makes it),
its checkbox turning on the passes kpcn reads, its operator denoising a real render into the same pixels as
``kpcn denoise`` of the same EXR, its pair operator rendering the frame's two halves (kpcn blend-pair's seeds and
samples) into the pixels ``kpcn denoise A --pair B --adapt-steps N`` gives, and kpcn's problems as one report
line. ``kpcn --version``, which its check
button runs, too. The tests needing bpy skip, saying so, only where .venv-bpy has no bpy (CI's .ci/run makes it)."""
import ast
import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import kpcn, run_main
from helpers.paths import REPO

from prep import exr
from prep.layouts import CYCLES_PASSES

sys.path.insert(0, str(REPO / "blender"))
import build as addon_build  # noqa: E402  blender/build.py: make addon's builder (the standard library alone)

ADDON = REPO / "blender" / "kpcn_addon"
BLENDER_SIDE = Path(__file__).parent / "helpers" / "blender_side.py"
BPY_PYTHON = REPO / ".venv-bpy" / "bin" / "python"
KPCN_EXE = Path(sys.executable).parent / "kpcn"  # this environment's kpcn, as a user's .venv/bin/kpcn


def _bpy_missing() -> str | None:
    if not BPY_PYTHON.exists():
        return f"no {BPY_PYTHON.relative_to(REPO)} (make .venv-bpy/bin/python installs bpy 5.0.1)"
    res = subprocess.run([BPY_PYTHON, "-c", "import bpy"], capture_output=True, timeout=120)
    return None if res.returncode == 0 else f"{BPY_PYTHON} cannot import bpy"


BPY_MISSING = _bpy_missing()
REQUIRE_BPY = "KPCN_REQUIRE_BPY"  # CI sets it (.ci/run makes .venv-bpy): there a missing bpy fails


def needs_bpy(test):
    """Skipped, with the reason, where bpy is missing; where CI requires it, run, to fail on that reason."""
    if BPY_MISSING is not None and os.environ.get(REQUIRE_BPY):
        def missing(*args, **kwargs):
            pytest.fail(f"{REQUIRE_BPY} is set: {BPY_MISSING}")
        missing.__name__ = test.__name__
        return missing
    return pytest.mark.skipif(BPY_MISSING is not None, reason=str(BPY_MISSING))(test)


def _tuple_of(path: Path, name: str) -> tuple:
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{path} has no {name}")


def test_the_checkbox_turns_on_the_passes_kpcn_render_cycles_does_each_one_kpcn_reads():
    passes = _tuple_of(ADDON / "passes.py", "PASSES")
    assert passes == _tuple_of(REPO / "prep" / "render" / "blender" / "cycles_set.py", "PASSES")
    roles = {"z": "depth", "emit": "emission"}  # Blender's property names where kpcn's role differs
    assert {roles.get(p, p) for p in passes} <= set(CYCLES_PASSES)
    # every light pass of kpcn's Cycles layout (the volumes and Denoising Data are the view layer's cycles ones)
    assert set(CYCLES_PASSES) - {roles.get(p, p) for p in passes} == {
        "volume_direct", "volume_indirect", "denoising_normal", "denoising_albedo", "denoising_depth"}
    assert _tuple_of(ADDON / "passes.py", "CYCLES_PASSES") == (
        "use_pass_volume_direct", "use_pass_volume_indirect", "denoising_store_passes")


def test_the_addon_imports_nothing_of_kpcn_only_the_standard_library_bpy_numpy_and_itself():
    for path in ADDON.glob("*.py"):
        tree = ast.parse(path.read_text())
        names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level == 0}
        assert names - set(sys.stdlib_module_names) <= {"bpy", "numpy"}, (path.name, names)  # Blender ships numpy


@pytest.mark.parametrize("half", [False, True])
def test_the_addon_reads_the_colour_of_kpcns_output_exr_as_openexr_does(tmp_path, half):
    # the add-on's own reader (Blender loads kpcn's layered output as a multilayer image, without pixels in Python)
    sys.path.insert(0, str(ADDON))
    try:
        import exr_colour
    finally:
        sys.path.remove(str(ADDON))
    rng = np.random.default_rng(0)
    colour, alpha = rng.random((37, 21, 3), np.float32) * 4, rng.random((37, 21), np.float32)
    path = exr.write_aovs(tmp_path / "out.exr", {"albedo": rng.random((37, 21, 3), np.float32), "default": colour,
                                                 "default.A": alpha, "depth": rng.random((37, 21))}, half=half)
    import OpenEXR

    expected = OpenEXR.File(str(path)).parts[0].channels["default"].pixels.astype(np.float32)
    np.testing.assert_array_equal(exr_colour.read_colour(str(path)), expected)
    with pytest.raises(exr_colour.ExrError, match="no layer nothing"):
        exr_colour.read_colour(str(path), "nothing")


def test_make_addon_builds_the_zip_named_after_the_manifest_version_the_same_bytes_each_time(tmp_path):
    res = subprocess.run(["make", "-s", "addon", f"ADDON_DIST={tmp_path}"], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    version = addon_build.manifest_version()
    built = tmp_path / f"kpcn-blender-{version}.zip"
    assert res.stdout.strip().endswith(str(built))
    with zipfile.ZipFile(built) as z:
        names = set(z.namelist())
        assert f'version = "{version}"' in z.read("blender_manifest.toml").decode()
    assert names == {p.name for p in ADDON.iterdir() if p.suffix in (".py", ".toml")}
    assert addon_build.build(tmp_path / "again").read_bytes() == built.read_bytes()


def test_kpcn_version_names_the_package_version_and_the_model_it_serves(tmp_path):
    from importlib.metadata import version

    from kpcn_keras.run import default_model

    res = run_main("--version", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    model = default_model()
    assert res.stdout.splitlines() == [f"kpcn {version('kpcn')}",
                                       f"model {model.dir} (quality modes: {', '.join(model.quality_modes())})"]


def _blender(tmp_path, mode: str, *args) -> dict:
    """The add-on built, installed and driven in bpy's Python (tests/helpers/blender_side.py), Blender's user
    folders and temporary files (the EXR the add-on writes) inside ``tmp_path``."""
    zip_path = addon_build.build(tmp_path / "dist")
    out, temp = tmp_path / "out", tmp_path / "temp"
    out.mkdir(), temp.mkdir()
    env = dict(os.environ, HOME=str(tmp_path / "home"), BLENDER_USER_RESOURCES=str(tmp_path / "blender"),
               TMPDIR=str(temp))
    res = subprocess.run([BPY_PYTHON, BLENDER_SIDE, zip_path, KPCN_EXE, out, mode, *map(str, args)], env=env,
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0 and (out / "result.json").exists(), (res.stdout + res.stderr)[-3000:]
    return json.loads((out / "result.json").read_text())


@needs_bpy
def test_blender_validates_the_zip_as_an_extension(tmp_path):
    validate = BPY_PYTHON.parents[1].glob("lib/python*/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/"
                                          "blender_ext.py")
    res = subprocess.run([BPY_PYTHON, next(validate), "validate", addon_build.build(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "Success" in res.stdout, res.stdout + res.stderr


@needs_bpy
def test_in_blender_the_checkbox_sets_the_passes_and_kpcn_problems_are_one_report_line(tmp_path):
    got = _blender(tmp_path, "checks")
    assert got["before"] == [False, False, True]
    assert all(got["on"].values()) and all(got["on_cycles"].values()), got
    assert got["denoiser_on"] is False and got["denoiser_off_again"] is True  # Blender's denoiser given back
    missing = str(tmp_path / "out" / "no-such-kpcn")
    for key in ("wrong_path", "wrong_path_check"):
        report = got[key]["report"].strip()
        assert got[key]["result"] == ["RuntimeError"] and len(report.splitlines()) == 1, got[key]
        assert report == f"Error: kpcn executable not found: {missing} (set it in the kpcn add-on's preferences)"
    assert "Traceback" not in json.dumps(got)


@pytest.mark.slow
@needs_bpy
def test_in_blender_the_button_loads_the_pixels_kpcn_denoise_gives_for_the_exr_it_wrote(tmp_path):
    got = _blender(tmp_path, "round_trip")
    assert got["denoise"]["result"] == ["FINISHED"], got
    assert got["check"]["result"] == ["FINISHED"] and got["found"].startswith("kpcn "), got
    assert "Scene frame 1 kpcn" in got["images"] and got["packed"]
    written = list((tmp_path / "temp").glob("kpcn-*/render.exr"))
    assert len(written) == 1  # the add-on's temporary EXR, which kpcn denoised
    res = kpcn("denoise", written[0], "-o", tmp_path / "cli.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    expected = exr.read_rgb(tmp_path / "cli.exr")
    loaded = np.load(tmp_path / "out" / "loaded.npy")
    assert loaded.shape[:2] == expected.shape[:2] == (32, 32)
    np.testing.assert_array_equal(loaded[..., :3], expected)
    shot = os.environ.get("KPCN_ADDON_PNG")  # docs/blender.md: how reports/blender_addon.png is made
    if shot:
        _picture(written[0], loaded, shot)


ADAPT_STEPS = 3  # the pair test's adaptation: a few exact steps, the same on any machine


@pytest.mark.slow
@needs_bpy
def test_in_blender_the_pair_button_renders_two_halves_and_loads_what_kpcn_denoise_pair_adapt_gives(tmp_path):
    from prep.layouts import read, read_header
    from prep.render.cycles import catalogue

    seeds = catalogue().half_seeds(7)  # kpcn blend-pair's seeds of the scene's seed, 7
    got = _blender(tmp_path, "pair", ADAPT_STEPS, *seeds)
    assert got["pair"]["result"] == ["FINISHED"], got
    # kpcn adapted for the steps the operator was given, and said what its guard decided
    assert re.fullmatch(rf"denoised into image 'Scene frame 1 kpcn pair'; adaptation (not )?kept: .* at steps "
                        rf"[\d and]+ of "
                        rf"{ADAPT_STEPS} in .*", got["message"]), got["message"]
    assert got["after"] == got["before"], got  # the scene's samples, seed, adaptive sampling, denoiser given back
    assert got["before"]["samples"] == 4 and got["before"]["use_denoising"], got
    assert "Scene frame 1 kpcn pair" in got["images"] and got["packed"]
    odd = got["odd"]["report"].strip()
    assert got["odd"]["result"] == ["RuntimeError"] and odd == (
        "Error: a pair renders the frame as two halves of half its samples: the scene's render samples must be even "
        "and 4 or more, got 5"), got["odd"]
    folders = list((tmp_path / "temp").glob("kpcn-*/render-a.exr"))
    assert len(folders) == 1, folders  # one pair written; the odd samples rendered nothing
    half_a, half_b = folders[0], folders[0].with_name("render-b.exr")
    assert [read_header(h).spp for h in (half_a, half_b)] == [2, 2]  # Cycles' header: half the scene's 4
    colours = [read(h).layers["default"] for h in (half_a, half_b)]
    assert not np.array_equal(*colours)
    for colour, seed in zip(colours, seeds):  # each half is Cycles' 2 spp frame of its seed, Blender's denoiser off
        np.testing.assert_array_equal(colour, read(tmp_path / "out" / f"seed-{seed}.exr").layers["default"])
    res = kpcn("denoise", half_a, "--pair", half_b, "--adapt-steps", ADAPT_STEPS, "-o", tmp_path / "cli.exr",
               cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    expected = exr.read_rgb(tmp_path / "cli.exr")
    loaded = np.load(tmp_path / "out" / "loaded.npy")
    assert loaded.shape[:2] == expected.shape[:2] == (32, 32)
    np.testing.assert_array_equal(loaded[..., :3], expected)


def test_the_addons_half_seeds_are_kpcn_blend_pairs_and_its_commands_pass_the_pair():
    from prep.render.cycles import catalogue

    sys.path.insert(0, str(ADDON))
    try:
        import halves
        import runner
    finally:
        sys.path.remove(str(ADDON))
    for seed in (0, 7, 2**28, 2**31 - 1, 1234567):
        assert halves.half_seeds(seed) == catalogue().half_seeds(seed)
    assert [halves.half_samples(n) for n in (4, 6, 128)] == [2, 3, 64]
    for bad in (2, 3, 5, 0):
        with pytest.raises(ValueError, match=f"must be even and 4 or more, got {bad}$"):
            halves.half_samples(bad)
    cmd = ["k", "denoise", "a.exr", "-o", "o.exr"]
    assert runner.denoise_command("k", "a.exr", "o.exr") == cmd
    assert runner.denoise_command("k", "a.exr", "o.exr", pair="b.exr") == cmd + ["--pair", "b.exr"]
    assert runner.denoise_command("k", "a.exr", "o.exr", "fast", 2, "b.exr", 12.5) == cmd + [
        "--quality", "fast", "--ensemble", "2", "--pair", "b.exr", "--adapt", "12.5"]
    assert runner.denoise_command("k", "a.exr", "o.exr", pair="b.exr", adapt_seconds=60, adapt_steps=3) == cmd + [
        "--pair", "b.exr", "--adapt-steps", "3"]
    assert runner.denoise_command("k", "a.exr", "o.exr", adapt_seconds=60) == cmd  # no pair: nothing to adapt to
    log = ("adapting: 100%| 3/3 step\rwrote o.exr\nadaptation not kept: estimated held-out error 0.1 -> 0.1 "
           "(+0.00%, 0.0 standard errors) at steps 0 and 0 of 3 in 1.5 s; no checkpoint did better\n"
           "peak memory 514 MiB\n")
    assert runner.adaptation_line(log) == ("adaptation not kept: estimated held-out error 0.1 -> 0.1 (+0.00%, 0.0 "
                                           "standard errors) at steps 0 and 0 of 3 in 1.5 s; no checkpoint did better")
    assert runner.adaptation_line("wrote o.exr\n") == ""


def _picture(noisy_exr: Path, loaded: np.ndarray, path: str) -> None:
    """The noisy render beside the image the add-on loaded, tonemapped, enlarged 8x (nearest)."""
    import matplotlib.pyplot as plt

    from prep.colour import tonemap
    from prep.files import save_png
    from prep.layouts import read

    noisy = read(noisy_exr).layers["default"]
    fig, axes = plt.subplots(1, 2, figsize=(6, 3.3))
    for ax, image, title in zip(axes, (noisy, loaded[..., :3]), ("Cycles, 4 spp (Render Result)",
                                                                  "kpcn add-on's image")):
        ax.imshow(np.repeat(np.repeat(tonemap(image), 8, 0), 8, 1), interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    save_png(fig, path)
    plt.close(fig)
