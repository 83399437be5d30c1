"""kpcn blend-pair (prep/render/blendpair.py, prep/render/blender/blend_pair.py): a .blend file's frame rendered
as two halves for kpcn denoise --pair, bad input refused in one line before Blender starts, and where a Python
with bpy is at hand, a tiny .blend rendered: two Cycles renders of half the samples each (the header says so),
every pass kpcn reads, different noise, read by kpcn as the Cycles layout; a half there is kept."""
import ast
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.paths import REPO

from prep import layouts
from prep.render.blendpair import BLENDER_SIDE, BlendPairConfig, blender_command
from prep.render.cycles import catalogue

cat = catalogue()
BPY = os.environ.get("KPCN_BLENDER_PYTHON", str(REPO / ".venv-bpy" / "bin" / "python"))
# a .blend of Blender's start-up scene (cube, camera, lamp; EEVEE, which the halves replace by Cycles) at 16 x 12
MAKE_BLEND = """import sys, bpy
bpy.ops.wm.read_factory_settings()
s = bpy.context.scene
s.render.resolution_x, s.render.resolution_y, s.render.resolution_percentage = 16, 12, 100
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])
"""


@pytest.mark.parametrize("name, args, needles", [
    ("none.blend", (), ("blend", "none.blend", "no such file")),
    ("scene.txt", (), ("blend", "scene.txt", "not a .blend file")),
    ("a.blend", ("--spp", "6", "--spp", "7"), ("--spp", "even", "7")),
    ("a.blend", ("--spp", "2"), ("--spp", "4 or more"))])
def test_bad_input_is_refused_in_one_line_before_blender_starts(tmp_path, name, args, needles):
    for there in ("scene.txt", "a.blend"):
        (tmp_path / there).write_text("")
    res = run_main("blend-pair", tmp_path / name, *args, "--blender-python", tmp_path / "none", cwd=tmp_path)
    assert_one_line_error(res, "kpcn blend-pair: error:", *needles)


def test_the_blender_side_reads_the_commands_arguments_and_imports_no_kpcn(tmp_path):
    (tmp_path / "shot.blend").write_text("")
    cfg = BlendPairConfig(blend=str(tmp_path / "shot.blend"), spp=32, frame=7, blender_python="/py")
    command = blender_command(cfg)
    assert command[:2] == ["/py", str(BLENDER_SIDE)] and cfg.out == str(tmp_path)
    assert [p.name for p in cfg.outputs()] == ["shot-00016spp-pair-a.exr", "shot-00016spp-pair-b.exr"]
    tree = ast.parse(BLENDER_SIDE.read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert names - set(sys.stdlib_module_names) == {"bpy", "catalogue", "cycles_set"}
    assert "--frame" in command and command[command.index("--spp") + 1] == "32"
    assert cat.half_seeds(0) == (2**28, 2**29) and cat.half_seeds(2**31 - 1) == (2**28 - 1, 2**29 - 1)


def _channels(path):
    import OpenEXR

    f = OpenEXR.File(str(path), separate_channels=True)
    return {c: p.channels[c].pixels for p in f.parts for c in p.channels}, f.header()


@pytest.mark.slow  # two runs of Blender's Python, two renders of 16 x 12
@pytest.mark.skipif(not Path(BPY).exists(), reason="no Python with bpy (make .venv-bpy/bin/python)")
def test_a_tiny_blend_renders_as_two_halves_with_every_pass(tmp_path):
    blend = tmp_path / "cube.blend"
    subprocess.run([BPY, "-c", MAKE_BLEND, str(blend)], check=True, capture_output=True)
    res = run_main("blend-pair", blend, "--spp", "4", "--out", tmp_path / "out", "--blender-python", BPY,
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    halves = [tmp_path / "out" / n for n in cat.pair_names("cube", 4)]
    (a, ha), (b, hb) = (_channels(h) for h in halves)
    assert ha["cycles.ViewLayer.samples"] == hb["cycles.ViewLayer.samples"] == "2"
    # every pass kpcn reads, as the validation inputs have them
    assert {"ViewLayer.Denoising Albedo.R", "ViewLayer.Diffuse Direct.R", "ViewLayer.Glossy Color.R",
            "ViewLayer.Volume Direct.R", "ViewLayer.Depth.Z", "ViewLayer.Normal.X"} <= set(a) and set(a) == set(b)
    assert np.abs(a["ViewLayer.Combined.R"] - b["ViewLayer.Combined.R"]).max() > 1e-3  # two seeds
    frames = [layouts.read(h) for h in halves]
    assert [(f.layout, f.spp, f.inputs.split) for f in frames] == [("cycles", 2, True)] * 2
    assert f"kpcn denoise {halves[0]} --pair {halves[1]}" in res.stdout
    stamp = halves[0].stat().st_mtime_ns
    halves[1].unlink()  # a killed run: the half there is kept, the other rendered again with its own seed
    res = run_main("blend-pair", blend, "--spp", "4", "--out", tmp_path / "out", "--blender-python", BPY,
                   cwd=tmp_path)
    assert res.returncode == 0 and halves[0].stat().st_mtime_ns == stamp, res.stderr[-3000:]
    np.testing.assert_allclose(_channels(halves[1])[0]["ViewLayer.Combined.R"], b["ViewLayer.Combined.R"],
                               rtol=1e-5, atol=1e-6)
