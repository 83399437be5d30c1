"""kpcn render --pair (prep/render/renderset.py, prep/render/scenefile.py): each input also rendered as two halves
of half its samples (catalogue.pair_names), seeds of their own, their spp in their header; the halves are
independent renders, so their mean's squared error against the reference is about half a single half's
(a statistical bound below); kpcn shards passes them over."""
import shutil

import numpy as np
from helpers.commands import assert_one_line_error, run_main
from helpers.paths import REPO

from prep import layouts
from prep.render import RenderConfig, render_set
from prep.render.cycles import catalogue
from prep.render.renderset import _renders, render_seed
from prep.shards.renders import discover_renders

cat = catalogue()
H, REF = 8, 1024  # a half's spp, the reference's


def _colour(path):
    return layouts.read(path).layers["default"].astype(np.float64)


def test_every_half_has_a_seed_of_its_own_and_odd_inputs_are_refused(tmp_path):
    cfg = RenderConfig(set_name="p", families=("cornell", "spheres"), per_family=2, input_spp=(4, 16), pair=True)
    renders = _renders(cfg)
    halves = [r for r in renders if r.half]
    assert len(halves) == 2 * 2 * 2 * 2 and all(r.spp in (2, 8) for r in halves)
    assert len({r.seed for r in renders}) == len(renders)  # no two renders of the set share noise
    plain = _renders(RenderConfig(set_name="p", families=("cornell", "spheres"), per_family=2, input_spp=(4, 16)))
    assert [r for r in renders if not r.half] == plain  # the inputs and references are the set without --pair's
    assert render_seed(0, "cornell", 0, 16) == plain[1].seed  # ... with the seeds they had before halves existed
    res = run_main("render", "--set", "odd", "--input-spp", "4,6,9", "--pair", "--out", tmp_path, cwd=tmp_path)
    assert_one_line_error(res, "kpcn render: error: --input-spp", "[9]")


def test_the_halves_are_independent_and_their_mean_has_half_the_squared_error(tmp_path):
    # the boxes family: its noise has light tails at 8 spp (no caustics, no small bright lights), so the standard
    # error estimated from the pixels is an honest one (over seeds 0-7 the statistic below stayed within 1.5 of them)
    cfg = RenderConfig(set_name="p", families=("boxes",), per_family=1, width=64, height=64, input_spp=(2 * H,),
                       reference_spp=REF, out_root=str(tmp_path), pair=True)
    render_set(cfg, progress=False)
    folder = tmp_path / "p"
    scene = _renders(cfg)[0].name.rsplit("-", 1)[0]
    a_path, b_path = (folder / n for n in cat.pair_names(scene, 2 * H))
    assert a_path.name == f"{scene}-00008spp-pair-a.exr"
    a, b = (layouts.read(p) for p in (a_path, b_path))
    assert a.spp == b.spp == H and layouts.read(folder / f"{scene}-00016spp.exr").spp == 2 * H  # header, name
    ref = _colour(folder / f"{scene}-{REF:05d}spp.exr")
    ea, eb = a.layers["default"] - ref, b.layers["default"] - ref
    assert np.abs(ea - eb).max() > 0  # two renders, not one twice
    # Each half's error is its own noise (variance s2/H per pixel) minus the reference's (s2/REF), the one
    # noise both share: E[ea eb] = s2/REF = q E[ea^2] per pixel with q = (H/REF) / (1 + H/REF), so the mean's
    # squared error, (ea^2 + eb^2)/4 + ea eb/2, is (1 + q)/2 of a half's on average; the ratio's fluctuation is
    # that of mean(ea eb)/(2 avg), its standard error estimated from the pixels: 4 of them bound it.
    avg = (np.mean(ea**2) + np.mean(eb**2)) / 2
    ratio = np.mean(((ea + eb) / 2) ** 2) / avg
    q = (H / REF) / (1 + H / REF)
    se = np.std(ea * eb) / np.sqrt(ea.size) / (2 * avg)
    assert abs(ratio - (1 + q) / 2) < 4 * se, (ratio, (1 + q) / 2, se)
    assert (1 + q) / 2 + 4 * se < 0.6  # the bound tells 1/2 from 1 (one render twice): the test can fail
    full = _colour(folder / f"{scene}-00016spp.exr") - ref  # and the mean is as noisy as the 2H-spp input
    assert 0.5 < np.mean(full**2) / np.mean(((ea + eb) / 2) ** 2) < 2.0
    # kpcn shards reads the inputs and reference, not the halves
    found = discover_renders(folder)
    assert [s.spp for s in found[scene]["inputs"]] == [2 * H] and found[scene]["reference"].spp == REF


def test_a_scene_files_pair_is_two_halves_beside_it(tmp_path):
    shutil.copy(REPO / "scenes" / "example.toml", tmp_path / "example.toml")
    args = ("render", "--scene", tmp_path / "example.toml", "--spp", "8", "--width", "16", "--height", "12",
            "--pair", "--no-png")
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    a, b = (layouts.read(tmp_path / n) for n in cat.pair_names("example", 8))
    assert a.spp == b.spp == 4 and a.layers["default"].shape == (12, 16, 3)
    assert np.abs(a.layers["default"] - b.layers["default"]).max() > 0
    assert not (tmp_path / "example-00008spp.exr").exists()  # the halves instead of the frame
    res = run_main(*args[:4], "7", *args[5:], cwd=tmp_path)
    assert_one_line_error(res, "kpcn render: error: --spp", "even", "7")
