"""``python -m kpcn_keras.studies.blender_report``: kpcn's models on Cycles frames beside Blender's own denoised
frame; every figure of the report against float64 numpy of the metric definitions on the files themselves."""

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.exr_layouts import cycles_channels, parts_of, write_channels
from skimage.metrics import structural_similarity

import kpcn
from kpcn_keras.studies import blender_report as br
from prep import exr
from prep.colour import tonemap

H, W = 20, 24


def _combined(channels) -> np.ndarray:
    return np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1)


def _write_rgb(path: Path, rgb: np.ndarray) -> Path:
    return write_channels(path, {f"ViewLayer.Combined.{c}": rgb[..., i].astype(np.float32)
                                 for i, c in enumerate("RGB")})


def _folder(root: Path) -> Path:
    """Three scenes laid out as the validation set: ``fog`` (a recipe in the group ``media``) at 4 and 16 spp,
    ``room`` (no recipe) and ``hall`` (``media`` and ``interiors``) at 4 spp, each with a 2048-spp reference;
    Blender's own frame (a stand-in: the reference mixed with the noisy frame) beside each but ``fog`` at 16."""
    root.mkdir()
    for k, (scene, spps) in enumerate((("fog", (4, 16)), ("room", (4,)), ("hall", (4,)))):
        for j, spp in enumerate(spps):
            ch = cycles_channels(H, W, seed=k, noise_seed=10 * k + j)
            write_channels(root / exr.render_filename(scene, spp), ch, parts_of(ch))
            if (scene, spp) != ("fog", 16):
                ref = _combined(cycles_channels(H, W, seed=k))
                _write_rgb(root / f"{scene}-{spp:05d}spp-blender-oidn.exr", 0.7 * ref + 0.3 * _combined(ch))
        _write_rgb(root / exr.render_filename(scene, 2048), _combined(cycles_channels(H, W, seed=k)))
    (root / "fog.json").write_text(json.dumps({"effects": ["fog"], "groups": ["media"]}))
    (root / "hall.json").write_text(json.dumps({"effects": ["smoke", "window"], "groups": ["media", "interiors"]}))
    return root


def _rgb(path: Path) -> np.ndarray:
    return _combined(exr.read_image(path).channels).astype(np.float64)


def _relse_pixels(x, r):
    return ((x - r) ** 2 / (r * r + 0.01)).mean(axis=-1)


def _expected(x, r) -> dict:
    x, r = np.asarray(x, np.float64), np.asarray(r, np.float64)
    ssim = structural_similarity(tonemap(x), tonemap(r), channel_axis=-1, data_range=1.0, win_size=7)
    return {"relmse": float(np.mean((x - r) ** 2 / (r * r + 0.01))), "dssim": (1 - ssim) / 2,
            "relse_p999": float(np.percentile(_relse_pixels(x, r), 99.9))}


@pytest.mark.slow
def test_the_report_scores_every_frame_group_and_model_as_numpy_does(tiny_run_of_every_input_set, tmp_path):
    run = tiny_run_of_every_input_set
    frames, out = _folder(tmp_path / "frames"), tmp_path / "reports"
    assert br.main([str(frames), "--model", f"before={run}", "--model", f"after={run}", "--out", str(out),
                    "--note", "A tiny synthetic set."]) == 0
    record = json.loads((out / "blender.json").read_text())
    assert (out / "blender.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = {(r["scene"], r["spp"]): r for r in record["frames"]}
    assert sorted(rows) == [("fog", 4), ("fog", 16), ("hall", 4), ("room", 4)]
    assert rows["hall", 4]["groups"] == ["interiors", "media"]
    assert rows["fog", 4]["groups"] == ["media"] and rows["room", 4]["groups"] == ["unknown"]
    for (scene, spp), row in rows.items():
        noisy, ref = frames / exr.render_filename(scene, spp), _rgb(frames / exr.render_filename(scene, 2048))
        own = frames / f"{scene}-{spp:05d}spp-blender-oidn.exr"
        denoised = kpcn.denoise(kpcn.read(noisy), run=run)
        expected = {"raw": _expected(_rgb(noisy), ref), "kpcn before": _expected(denoised, ref),
                    "kpcn after": _expected(denoised, ref)}
        if own.exists():
            expected["blender"] = _expected(_rgb(own), ref)
        assert set(row["scores"]) == set(expected) | set(record["oidn_modes"])
        for method, want in expected.items():
            for score, value in want.items():
                assert row["scores"][method][score] == pytest.approx(value, rel=1e-6, abs=1e-12), (scene, method)
    # the anchors at 4 spp, from the per-frame relMSE of numpy above
    four = [rows["fog", 4], rows["room", 4], rows["hall", 4]]
    kp = [r["scores"]["kpcn before"]["relmse"] for r in four]
    bl = [r["scores"]["blender"]["relmse"] for r in four]
    against = record["summary"]["by_spp"]["4"]["models"]["before"]
    assert against["below_blender"] == sum(k < b for k, b in zip(kp, bl)) and against["with_blender"] == 3
    assert against["median_ratio_blender"] == pytest.approx(np.median(np.divide(kp, bl)), rel=1e-12)
    assert record["summary"]["by_spp"]["4"]["means"]["kpcn after"]["relmse"] == pytest.approx(np.mean(kp))
    # fog at 16 spp has no Blender frame: its block counts none and has no ratio
    assert record["summary"]["by_spp"]["16"]["models"]["after"]["with_blender"] == 0
    assert record["summary"]["by_spp"]["16"]["models"]["after"]["median_ratio_blender"] is None
    media = record["summary"]["by_group"]["media"]
    assert sorted(media) == ["16", "4"] and media["4"]["frames"] == 2 and media["16"]["frames"] == 1
    assert media["4"]["means"]["blender"]["dssim"] == pytest.approx(
        np.mean([rows[s, 4]["scores"]["blender"]["dssim"] for s in ("fog", "hall")]), rel=1e-12)
    assert [(p["group"], Path(p["frame"]).name) for p in record["panels"]] == [
        ("interiors", "hall-00004spp.exr"), ("media", "fog-00004spp.exr"), ("media", "fog-00016spp.exr"),
        ("unknown", "room-00004spp.exr")]
    md = (out / "blender.md").read_text()
    assert "A tiny synthetic set." in md
    assert f"| room | 4 | unknown | {rows['room', 4]['scores']['raw']['relmse']:.4f} |" in md
    # the title names Blender's denoiser only where a frame has its denoised frame
    assert md.startswith("# kpcn on Blender Cycles frames, beside Blender's own denoiser (")
    for row in record["frames"]:
        row["scores"].pop("blender", None)
    assert br.format_report(record).startswith("# kpcn beside OIDN, on frames without Blender's own denoised frame (")


def test_a_scenes_groups_come_from_its_recipe(tmp_path):
    noisy = tmp_path / "a-00004spp.exr"
    assert br.effect_groups(noisy) == ["unknown"]
    (tmp_path / "a.json").write_text(json.dumps({"effects": ["smoke", "fog"]}))
    assert br.effect_groups(noisy) == ["fog", "smoke"]
    (tmp_path / "a.json").write_text(json.dumps({"effects": ["fog"], "groups": ["media", "media"]}))
    assert br.effect_groups(noisy) == ["media"]
    (tmp_path / "a.json").write_text(json.dumps({"effects": []}))
    assert br.effect_groups(noisy) == ["none"]


@pytest.mark.parametrize("args, says", [
    (["{empty}"], "no noisy frame"),
    (["{empty}", "--model", "=x"], "--model '=x': give NAME=RUN"),
    (["{empty}", "--model", "a={empty}/nothing"], "no such run or model folder"),
    (["{frames}"], "fog.json: not a readable JSON recipe"),
])
def test_bad_input_is_one_line_and_status_2(tmp_path, capsys, args, says):
    (tmp_path / "empty").mkdir()
    frames = tmp_path / "frames"
    frames.mkdir()
    ch = cycles_channels(4, 4)
    write_channels(frames / "fog-00004spp.exr", ch)
    _write_rgb(frames / "fog-02048spp.exr", _combined(ch))
    (frames / "fog.json").write_text("{not json")
    argv = [a.format(empty=tmp_path / "empty", frames=frames) for a in args] + ["--out", str(tmp_path / "r")]
    assert br.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("blender-report: error: ") and says in err and err.count("\n") == 1, err
