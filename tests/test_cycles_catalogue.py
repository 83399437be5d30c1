"""The Cycles scene catalogue (prep/render/blender/catalogue.py): a scene drawn from (seed, index) is the same
recipe in any process, records the effects it drew and holds what each of them builds; the manifest counts a
folder as it is; and, where a Python with bpy is at hand, a medium's frame carries Cycles' volume passes."""
import json
import math
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.paths import REPO

from prep.render.cycles import BLENDER_SIDE, CATALOGUE, catalogue

cat = catalogue()
SCENES = [cat.draw(0, i, (128, 192), (4, 64, 1024)) for i in range(240)]
BPY = os.environ.get("KPCN_BLENDER_PYTHON", str(REPO / ".venv-bpy" / "bin" / "python"))


def _materials(r):
    return [s["material"] for s in r["surfaces"]] + [o["material"] for o in r["objects"]]


def _textures(r):
    return [m["texture"]["kind"] for m in _materials(r) if "texture" in m]


# what each effect must have put into the scene, read from the recipe alone
HOLDS = {
    "fog": lambda r: any("noise" not in v for v in r["media"]),
    "smoke": lambda r: any("noise" in v for v in r["media"]),
    "shafts": lambda r: r["window"] is not None and r["media"] and any(li["type"] in ("sun", "spot")
                                                                        for li in r["lights"]),
    "glass_medium": lambda r: any("volume" in m and m.get("transmission") == 1.0 for m in _materials(r)),
    "subsurface": lambda r: any(m.get("subsurface", 0) > 0 for m in _materials(r)),
    "brick_far": lambda r: any(m.get("texture", {}).get("kind") == "brick" and m["texture"]["scale"] >= 20
                               for m in _materials(r)),
    "fine_tiles": lambda r: any(m.get("texture", {}).get("scale", 0) >= 40 for m in _materials(r))
    and r["camera"]["location"][2] < 0.5,
    "text": lambda r: len(r["texts"]) > 0,
    "dof": lambda r: r["camera"].get("dof", {}).get("fstop", 99) <= 2.0,
    "motion_blur": lambda r: "shutter" in r["camera"] and any("motion" in o for o in r["objects"]),
    "hair": lambda r: any("hair" in o for o in r["objects"]),
    "sun_sky": lambda r: r["world"]["type"] == "sky" and any(li["type"] == "sun" for li in r["lights"]),
    "hdri": lambda r: r["world"]["type"] == "hdri",
    "window": lambda r: r["window"] is not None and r["world"]["type"] == "sky",
    "emissive_mesh": lambda r: any(o["material"]["kind"] == "emission" for o in r["objects"]),
    "glass_caustics": lambda r: any(o["material"]["kind"] == "glass" for o in r["objects"])
    and any(li["type"] == "point" and li["size"] <= 0.05 for li in r["lights"]),
    "water_caustics": lambda r: any("waves" in s and s["material"]["ior"] == 1.33 for s in r["surfaces"]),
    "coat": lambda r: any(m.get("coat", 0) > 0 for m in _materials(r)),
    "sheen": lambda r: any(m.get("sheen", 0) > 0 for m in _materials(r)),
}


def test_the_same_seed_draws_the_same_scene_in_another_process():
    # a string seed hashes by SHA-512, not by Python's per-process hash: another PYTHONHASHSEED, the same scenes
    code = (f"import importlib.util, json; s = importlib.util.spec_from_file_location('c', {str(CATALOGUE)!r}); "
            "m = importlib.util.module_from_spec(s); s.loader.exec_module(m); "
            "print(json.dumps([m.draw(0, i, (128, 192), (4, 64, 1024)) for i in range(240)]))")
    env = dict(os.environ, PYTHONHASHSEED="12345")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert json.loads(out) == json.loads(json.dumps(SCENES))


def test_other_seeds_and_indices_draw_other_scenes():
    assert cat.draw(1, 7) != cat.draw(0, 7) != cat.draw(0, 8)
    assert len({json.dumps(cat.draw(seed, 3)) for seed in range(20)}) == 20


def test_each_scene_records_effects_of_the_catalogue_and_holds_what_each_builds():
    for r in SCENES:
        assert 1 <= len(r["effects"]) <= 3 and len(set(r["effects"])) == len(r["effects"])
        assert set(r["effects"]) <= set(cat.BY_NAME)
        assert r["groups"] == sorted({cat.BY_NAME[e].group for e in r["effects"]}, key=cat.GROUPS.index)
        assert sum(cat.BY_NAME[e].group == "lighting" for e in r["effects"]) <= 1
        for e in r["effects"]:
            assert HOLDS[e](r), (r["name"], e)
        assert r["name"] == f"{r['kind']}-{r['index']:03d}" and r["frames"] == [4, 64, 1024]


def test_scenes_without_an_effect_lack_its_distinctive_parts():
    # the recording is not a label stuck on any scene: the parts come with the effect only
    for r in SCENES:
        assert bool(r["media"]) == bool({"fog", "smoke", "shafts"} & set(r["effects"]))
        assert any("hair" in o for o in r["objects"]) == ("hair" in r["effects"])
        assert bool(r["texts"]) == ("text" in r["effects"])
        assert ("shutter" in r["camera"]) == ("motion_blur" in r["effects"])
        assert (r["world"]["type"] == "hdri") == ("hdri" in r["effects"])


def test_the_catalogue_covers_the_groups_and_every_effect_is_drawn():
    assert set(cat.GROUPS) == {"media", "subsurface", "texture", "camera", "hair", "lighting", "emission",
                               "caustics", "layered"}
    assert set(HOLDS) == set(cat.BY_NAME) and all(e.weight > 0 and e.builds for e in cat.EFFECTS)
    drawn = Counter(e for r in SCENES for e in r["effects"])
    assert set(drawn) == set(cat.BY_NAME) and min(drawn.values()) >= 5
    groups = Counter(g for r in SCENES for g in r["groups"])
    assert min(groups.values()) >= 10


def test_each_scene_draws_one_of_the_resolutions_and_the_rest_does_not_depend_on_them():
    assert Counter(r["res"] for r in SCENES).keys() == {128, 192}
    for i in range(20):
        a, b = cat.draw(0, i, (128, 192)), cat.draw(0, i, (64,))
        assert b["res"] == 64 and {**a, "res": 64} == b


def _fake_folder(out: Path):
    """Four scenes' recipes, some frames (empty files), a render log; returns the counts made by hand."""
    out.mkdir()
    recipes = [cat.draw(0, i, (128, 192), (4, 16, 256)) for i in range(4)]
    present = {0: (4, 16, 256), 1: (4,), 2: (), 3: (4, 16, 256)}
    log = {"renders": {}, "cpu": {}, "threads": 2}
    for r in recipes:
        (out / f"{r['name']}.json").write_text(json.dumps(r))
        for spp in present[r["index"]]:
            name = f"{r['name']}-{spp:05d}spp.exr"
            (out / name).write_bytes(b"")
            log["renders"][name] = 10.0 * spp
            if r["index"] != 3:  # scene 3 logged before CPU time was: wall x threads
                log["cpu"][name] = 15.0 * spp
    (out / "render_log.json").write_text(json.dumps(log))
    cpu = sum(15.0 * s for i in (0, 1) for s in present[i]) + sum(10.0 * 2 * s for s in present[3])
    return recipes, cpu


def test_the_manifest_counts_a_folder_as_it_is(tmp_path):
    recipes, cpu = _fake_folder(tmp_path / "cyc")
    m = cat.write_manifest(str(tmp_path / "cyc"))
    assert json.loads((tmp_path / "cyc" / "manifest.json").read_text()) == m
    assert (m["scenes"], m["scenes_complete"], m["frames_done"], m["frames_planned"]) == (4, 2, 7, 12)
    assert math.isclose(m["cpu_hours"], round(cpu / 3600, 4))
    for e in cat.BY_NAME:
        assert m["effects"][e] == sum(e in r["effects"] for r in recipes)
    for g in cat.GROUPS:
        assert m["groups"][g] == sum(g in r["groups"] for r in recipes)
    assert sum(m["resolutions"].values()) == 4
    text = cat.summary(m)
    assert "4 scenes (2 complete), frames 7 of 12" in text and "media" in text


def test_a_folder_recording_another_scene_under_a_name_is_refused_in_one_line(tmp_path):
    _fake_folder(tmp_path / "cyc")  # drawn with --res 128,192, seed 0
    res = run_main("render-cycles", tmp_path / "cyc", "--scenes", "0:2", "--seed", "3", "--res", "128,192",
                   "--blender-python", tmp_path / "none", cwd=tmp_path)
    assert_one_line_error(res, f"kpcn render-cycles: error: {tmp_path / 'cyc'}", "records another scene", "--seed 3")


@pytest.mark.skipif(not Path(BPY).exists(), reason="no Python with bpy (make .venv-bpy/bin/python)")
def test_a_medium_scene_renders_a_frame_with_cycles_volume_passes(tmp_path):
    import OpenEXR

    index = next(r["index"] for r in SCENES if "fog" in r["effects"] and r["kind"] != "room")
    args = [BPY, str(BLENDER_SIDE), str(tmp_path), "--scenes", f"{index}:{index + 1}", "--res", "16", "--spp", "1",
            "--ref-spp", "2"]
    res = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    name = cat.draw(0, index)["name"]
    frame = OpenEXR.File(str(tmp_path / f"{name}-00001spp.exr"), separate_channels=True)
    channels = {c for part in frame.parts for c in part.channels}
    for layer in ("Volume Direct", "Volume Indirect", "Combined", "Denoising Albedo"):
        assert f"ViewLayer.{layer}.R" in channels or f"ViewLayer.{layer}.X" in channels, layer
    pixels = {c: p.channels[c].pixels for p in frame.parts for c in p.channels}
    assert pixels["ViewLayer.Volume Direct.R"].max() > 0  # the fog scatters light, it is no empty black box
    assert pixels["ViewLayer.Combined.R"].mean() > 0
    assert json.loads((tmp_path / f"{name}.json").read_text())["effects"] == cat.draw(0, index)["effects"]
    m = json.loads((tmp_path / "manifest.json").read_text())
    assert (m["frames_done"], m["frames_planned"], m["effects"]["fog"]) == (2, 2, 1) and m["cpu_hours"] > 0


def test_a_folder_of_frames_without_recipes_is_refused_in_one_line(tmp_path):
    # an earlier generator's frames: kept frames of another scene would be mixed into this one's
    (tmp_path / "cyc").mkdir()
    (tmp_path / "cyc" / "studio-001-00004spp.exr").write_bytes(b"")
    res = run_main("render-cycles", tmp_path / "cyc", "--scenes", "0:2", "--blender-python", tmp_path / "none",
                   cwd=tmp_path)
    assert_one_line_error(res, "studio-001-00004spp.exr", "without its recipe")
