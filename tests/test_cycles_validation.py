"""The held-out Cycles validation set (kpcn cycles-validation, prep/render/cycles.py and the catalogue's
validation split): training draws are what they were, no validation draw can be a training one, every effect
group has two scenes, the manifest's checksums catch a changed byte, and where a Python with bpy is at hand a
tiny set renders the input, Blender's own denoised frame of the same noise, the input's two halves (two other
seeds, half its samples each) and a reference that verify."""
import hashlib
import importlib.util
import json
import os
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.paths import REPO
from test_cycles_catalogue import HOLDS

from prep.render.cycles import BLENDER_SIDE, ValidationConfig, catalogue, validation_command

cat = catalogue()
BPY = os.environ.get("KPCN_BLENDER_PYTHON", str(REPO / ".venv-bpy" / "bin" / "python"))
TRAIN = [cat.draw(seed, i, (128,), (4, 16, 64, 1024)) for seed in range(3) for i in range(300)]
VALID = [cat.draw(seed, i, (128,), (4, 16, 64, 2048), "validation") for seed in range(3) for i in range(40)]
# sha256 of json.dumps([draw(seed, i, (128, 192), (4, 64, 1024)) for i in range(300)]) before splits existed:
# the training scenes rendered then (data/cycles/...) keep resuming under the same recipes
TRAIN_DRAWS = {0: "561eb45a7d98e6d5dee28ad830f1321ca8fae2fadf94f7e45067f23afe6b2ddb",
               1: "fca7b60d867569b60afdcad786461b986c1d9c0e9fd0c1918340f3d515260ac1"}


def _random_textures(r):
    """The kinds of the textures a recipe's materials drew at random (not the effects' brick wall and tiles)."""
    extras = sum(e in r["effects"] for e in ("brick_far", "fine_tiles", "water_caustics"))  # the last surfaces
    kept = r["surfaces"][:len(r["surfaces"]) - extras] + r["objects"]
    return {s["material"]["texture"]["kind"] for s in kept if "texture" in s["material"]}


def test_training_draws_are_bit_identical_to_those_before_the_split():
    for seed, digest in TRAIN_DRAWS.items():
        drawn = json.dumps([cat.draw(seed, i, (128, 192), (4, 64, 1024)) for i in range(300)])
        assert hashlib.sha256(drawn.encode()).hexdigest() == digest
    assert all("split" not in r and not r["name"].startswith("val-") for r in TRAIN)


def test_no_validation_draw_can_equal_a_training_one():
    # the camera's azimuth alone tells the split: each scene has a camera, and the splits' azimuths are disjoint
    assert {cat.camera_split(r) for r in TRAIN} == {"train"}
    assert {cat.camera_split(r) for r in VALID} == {"validation"}
    for lo, hi in cat.VALIDATION.azimuths:
        assert all(hi < a or lo > b for a, b in cat.TRAIN.azimuths)
    # and the materials' textures, the lines of text and the brick walls' proportions come from other lists
    assert set(cat.VALIDATION.textures).isdisjoint(cat.TRAIN.textures)
    assert set(cat.VALIDATION.texts).isdisjoint(cat.TRAIN.texts)
    assert set().union(*map(_random_textures, TRAIN)) <= set(cat.TRAIN.textures)
    assert set().union(*map(_random_textures, VALID)) == set(cat.VALIDATION.textures)
    assert {t["body"] for r in VALID for t in r["texts"]} <= set(cat.VALIDATION.texts)
    bricks = [s["material"]["texture"] for r in VALID if "brick_far" in r["effects"] for s in r["surfaces"][-3:]
              if s["material"].get("texture", {}).get("kind") == "brick"]
    assert bricks and all("brick_width" in b for b in bricks)
    assert not any("brick_width" in json.dumps(r) for r in TRAIN)
    # what stays the same between the two would not make them equal: the whole scenes differ
    strip = ("seed", "index", "name", "split", "frames", "res", "exposure")
    train = {json.dumps({k: v for k, v in r.items() if k not in strip}, sort_keys=True) for r in TRAIN}
    assert not train & {json.dumps({k: v for k, v in r.items() if k not in strip}, sort_keys=True) for r in VALID}


def test_each_validation_scene_carries_its_two_groups_and_nine_cover_every_group_twice():
    for r in VALID:
        i, groups = r["index"], cat.GROUPS
        assert {groups[i % 9], groups[(i + cat.PAIR_STEP) % 9]} <= set(r["groups"]) and len(r["effects"]) <= 3
        assert sum(cat.BY_NAME[e].group == "lighting" for e in r["effects"]) <= 1
        for e in r["effects"]:
            assert HOLDS[e](r), (r["name"], e)
        assert r["split"] == "validation" and r["name"] == f"val-{r['kind']}-{i:03d}"
    for seed in range(3):
        for first in (0, 5, 20):  # any nine consecutive scenes
            count = Counter(g for r in VALID if r["seed"] == seed and first <= r["index"] < first + 9
                            for g in r["groups"])
            assert set(count) == set(cat.GROUPS) and min(count.values()) >= 2


def test_a_validation_camera_in_a_room_stands_inside_it():
    rooms = [r for r in VALID if r["kind"] == "room"]
    assert rooms
    for r in rooms:
        half = r["surfaces"][0]["size"][0] / 2
        assert max(map(abs, r["camera"]["location"][:2])) < half


def test_the_blender_side_reads_the_validation_command_back():
    spec = importlib.util.spec_from_file_location("cycles_set", BLENDER_SIDE)
    side = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(side)
    cfg = ValidationConfig(out="o", scenes=14, res=96, spp=(2, 8), ref_spp=512, seed=3, blender_python="/py")
    got = side.arguments(validation_command(cfg)[2:])
    assert (got.out, got.split, got.scenes, got.res, got.spp, got.ref_spp, got.seed) == \
        ("o", "validation", "0:14", "96", "2,8", 512, 3)
    default = side.arguments(validation_command(ValidationConfig(out="o"))[2:])
    assert (default.scenes, default.res, default.spp, default.ref_spp) == ("0:12", "128", "4,16,64", 2048)
    # the validation inputs and their denoised twins share their Cycles seed; each input's two halves (half its
    # spp, every pass) have two seeds of their own; the training ones have others
    recipe = cat.draw(0, 3, (128,), (4, 16, 64, 2048), "validation")
    plan = side.planned_renders(got, recipe, [4, 16, 64, 2048])
    rows = []
    for n in (4, 16, 64):
        rows += [(f"val-studio-003-{n:05d}spp.exr", n, False, True),
                 (f"val-studio-003-{n:05d}spp-blender-oidn.exr", n, True, False),
                 (f"val-studio-003-{n // 2:05d}spp-pair-a.exr", n // 2, False, True),
                 (f"val-studio-003-{n // 2:05d}spp-pair-b.exr", n // 2, False, True)]
    assert [(n, spp, dn, ps) for n, spp, _, dn, ps in plan] == rows + [("val-studio-003-02048spp.exr", 2048, False,
                                                                        False)]
    seeds = {n: s for n, _, s, _, _ in plan}
    for n in (4, 16, 64):
        full, a, b = seeds[cat.frame_name(recipe["name"], n)], *(seeds[p] for p in cat.pair_names(recipe["name"], n))
        assert seeds[cat.denoised_name(recipe["name"], n)] == full
        assert len({full, a, b}) == 3
    # no two frames of the set share a seed but an input and its denoised twin (the halves' noise is their own)
    every = [s for i in range(12) for n, _, s, dn, _ in side.planned_renders(
        side.arguments(validation_command(ValidationConfig(out="o"))[2:]),
        cat.draw(0, i, (128,), (4, 16, 64, 2048), "validation"), [4, 16, 64, 2048]) if not dn]
    assert len(set(every)) == len(every) == 12 * 10
    assert cat.pair_names("s", 64) == ("s-00032spp-pair-a.exr", "s-00032spp-pair-b.exr")
    with pytest.raises(ValueError, match="5 spp"):
        cat.pair_names("s", 5)
    train = side.arguments(["o", "--seed", "3"])
    assert side.cycles_seed(got, 3, 1) != side.cycles_seed(train, 3, 1)


def _fake_set(out: Path, scenes=2):
    """A validation folder as the render leaves it, its frames a few bytes each; returns the recipes."""
    out.mkdir()
    recipes = [cat.draw(0, i, (128,), (4, 16, 64, 2048), "validation") for i in range(scenes)]
    for r in recipes:
        (out / f"{r['name']}.json").write_text(json.dumps(r, indent=1))
        for name in cat.planned_files(r):
            (out / name).write_bytes(name.encode() * 3)
    cat.write_manifest(str(out))
    return recipes


def test_verify_passes_a_folder_as_written_and_names_a_file_with_one_changed_byte(tmp_path):
    recipes = _fake_set(tmp_path / "val")
    m = json.loads((tmp_path / "val" / "manifest.json").read_text())
    # a scene: its recipe, 3 inputs, their 3 denoised frames, their 6 halves and a reference
    assert len(m["sha256"]) == 2 * 14 and (m["frames_done"], m["frames_planned"]) == (26, 26)
    name = cat.denoised_name(recipes[1]["name"], 16)
    assert m["sha256"][name] == hashlib.sha256((tmp_path / "val" / name).read_bytes()).hexdigest()
    res = run_main("cycles-validation", tmp_path / "val", "--verify", cwd=tmp_path)
    assert res.returncode == 0 and "28 files match" in res.stdout, res.stderr
    data = bytearray((tmp_path / "val" / name).read_bytes())
    data[5] ^= 1
    (tmp_path / "val" / name).write_bytes(bytes(data))
    cat.write_manifest(str(tmp_path / "val"))  # a resumed run counting again keeps the checksum first recorded
    res = run_main("cycles-validation", tmp_path / "val", "--verify", cwd=tmp_path)
    assert_one_line_error(res, "kpcn cycles-validation: error:", str(tmp_path / "val" / name), "differs")


def test_verify_names_a_missing_file_and_a_frame_not_rendered(tmp_path):
    recipes = _fake_set(tmp_path / "val")
    gone = tmp_path / "val" / cat.frame_name(recipes[0]["name"], 2048)
    gone.unlink()
    res = run_main("cycles-validation", tmp_path / "val", "--verify", cwd=tmp_path)
    assert_one_line_error(res, str(gone), "missing")
    cat.write_manifest(str(tmp_path / "val"))  # counted again without it: planned, not rendered
    res = run_main("cycles-validation", tmp_path / "val", "--verify", cwd=tmp_path)
    assert_one_line_error(res, str(gone), "not rendered")
    res = run_main("cycles-validation", tmp_path / "nothing", "--verify", cwd=tmp_path)
    assert_one_line_error(res, "manifest.json", "no manifest")


def test_a_folder_of_other_scenes_is_refused_in_one_line_before_blender_starts(tmp_path):
    _fake_set(tmp_path / "val")
    res = run_main("cycles-validation", tmp_path / "val", "--seed", "1", "--blender-python", tmp_path / "none",
                   cwd=tmp_path)
    assert_one_line_error(res, "kpcn cycles-validation: error:", "records another scene", "--seed 1")
    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "room-000.json").write_text(json.dumps(cat.draw(0, 0)))
    res = run_main("cycles-validation", tmp_path / "train", "--blender-python", tmp_path / "none", cwd=tmp_path)
    assert_one_line_error(res, "room-000.json", "not a validation scene")


@pytest.mark.parametrize("args, needle", [(("--scenes", "0"), "--scenes"), (("--spp", "4,4"), "--spp"),
                                          (("--spp", "4,5"), "--spp"),
                                          (("--spp", "8", "--ref-spp", "8"), "--ref-spp"), (("--res", "0"), "--res")])
def test_bad_options_are_refused_in_one_line(tmp_path, args, needle):
    res = run_main("cycles-validation", tmp_path / "val", *args, "--blender-python", tmp_path / "none", cwd=tmp_path)
    assert_one_line_error(res, f"kpcn cycles-validation: error: {needle}")


def _pixels(path):
    import OpenEXR

    f = OpenEXR.File(str(path), separate_channels=True)
    return {c: p.channels[c].pixels for p in f.parts for c in p.channels}


@pytest.mark.slow  # three runs of Blender's Python, about 12 renders of 16 x 16
@pytest.mark.skipif(not Path(BPY).exists(), reason="no Python with bpy (make .venv-bpy/bin/python)")
def test_a_tiny_set_renders_the_input_its_denoised_frame_its_two_halves_and_a_reference(tmp_path):
    from kpcn_keras.studies.blender_report import effect_groups
    from kpcn_keras.studies.frames import renderer_pairs

    out, recipe = tmp_path / "val", cat.draw(0, 0, (16,), (2, 4), "validation")
    args = ("cycles-validation", out, "--scenes", "1", "--res", "16", "--spp", "2", "--ref-spp", "4",
            "--blender-python", BPY)
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    noisy = _pixels(out / cat.frame_name(recipe["name"], 2))
    own = _pixels(out / cat.denoised_name(recipe["name"], 2))
    ref = _pixels(out / cat.frame_name(recipe["name"], 4))
    assert {"ViewLayer.Denoising Albedo.R", "ViewLayer.Diffuse Direct.R"} <= set(noisy)
    assert {c.rsplit(".", 1)[0] for c in ref} == {"ViewLayer.Combined"}
    assert {c.rsplit(".", 1)[0] for c in own} == {"ViewLayer.Combined", "ViewLayer.Noisy Image"}
    # Blender keeps the noisy frame it denoised: the input's own noise (threads may reorder a sum: 1e-5)
    np.testing.assert_allclose(own["ViewLayer.Noisy Image.R"], noisy["ViewLayer.Combined.R"], rtol=1e-5, atol=1e-6)
    assert np.abs(own["ViewLayer.Combined.R"] - noisy["ViewLayer.Combined.R"]).max() > 1e-2  # and denoised it
    assert "files match their sha256" in res.stdout
    m = json.loads((out / "manifest.json").read_text())
    assert set(m["sha256"]) == {f"{recipe['name']}.json", *cat.planned_files(recipe)}
    assert renderer_pairs([out]) == [(out / cat.frame_name(recipe["name"], 2), out / cat.frame_name(recipe["name"],
                                                                                                      4))]
    assert effect_groups(out / cat.frame_name(recipe["name"], 2)) == sorted(recipe["groups"])
    # the input's two halves: 1 spp each (name and header), every pass the input has, each its own noise
    halves = [out / n for n in cat.pair_names(recipe["name"], 2)]
    assert [h.name for h in halves] == ["val-studio-000-00001spp-pair-a.exr", "val-studio-000-00001spp-pair-b.exr"]
    a, b = (_pixels(h) for h in halves)
    assert set(a) == set(b) == set(noisy)
    assert [_samples(h) for h in halves] == [1, 1] and _samples(out / cat.frame_name(recipe["name"], 2)) == 2
    combined = [x["ViewLayer.Combined.R"] for x in (a, b, noisy)]
    assert min(np.abs(x - y).max() for i, x in enumerate(combined) for y in combined[i + 1:]) > 1e-3
    # a killed run resumes: the file it lacks is rendered again, recorded anew, and the folder verifies
    (out / cat.denoised_name(recipe["name"], 2)).unlink()
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0 and "files match" in res.stdout, res.stderr[-3000:]
    assert (out / cat.denoised_name(recipe["name"], 2)).exists()
    # a folder rendered before halves were planned (its manifest without them) gains them when run again
    for h in halves:
        h.unlink()
    m = json.loads((out / "manifest.json").read_text())
    (out / "manifest.json").write_text(json.dumps({**m, "sha256": {k: v for k, v in m["sha256"].items()
                                                                   if "-pair-" not in k}}))
    res = run_main("cycles-validation", out, "--verify", cwd=tmp_path)
    assert_one_line_error(res, str(halves[0]), "not rendered (run it again)")
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0 and "files match" in res.stdout, res.stderr[-3000:]
    # the same seed: the same render (its header's render time aside; threads may reorder a sum: 1e-5)
    np.testing.assert_allclose(_pixels(halves[0])["ViewLayer.Combined.R"], combined[0], rtol=1e-5, atol=1e-6)
    assert set(json.loads((out / "manifest.json").read_text())["sha256"]) >= {h.name for h in halves}


def _samples(path):
    """The samples per pixel Cycles wrote in the frame's header."""
    import OpenEXR

    header = OpenEXR.File(str(path), header_only=True).header()
    return int(next(v for k, v in header.items() if k.startswith("cycles.") and k.endswith(".samples")))
