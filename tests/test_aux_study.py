"""``kpcn aux-study``: the shipped model on Cycles frames with each choice of auxiliaries beside Blender's frame;
its figures against the library's own calls and float64 numpy of the metrics, on two tiny frames."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.exr_layouts import cycles_channels, parts_of, write_channels
from helpers.paths import REPO

import kpcn
from kpcn_keras.studies import aux_study
from prep import auxiliary, exr, layouts, metrics

H, W = 20, 24
MODEL = REPO / "models" / "default"


def _rgb_channels(rgb: np.ndarray) -> dict:
    return {f"ViewLayer.Combined.{c}": rgb[..., i].astype(np.float32) for i, c in enumerate("RGB")}


def _combined(channels) -> np.ndarray:
    return np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1).astype(np.float64)


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    """One scene as the validation set lays it out: 4 and 16 spp, a 2048-spp reference, Blender's frame beside
    each (a stand-in: the reference mixed with the noisy frame)."""
    root = tmp_path_factory.mktemp("frames")
    ref = _combined(cycles_channels(H, W, seed=5))
    for j, spp in enumerate((4, 16)):
        ch = cycles_channels(H, W, seed=5, noise_seed=j)
        write_channels(root / exr.render_filename("fog", spp), ch, parts_of(ch))
        write_channels(root / f"fog-{spp:05d}spp-blender-oidn.exr", _rgb_channels(0.7 * ref + 0.3 * _combined(ch)))
    write_channels(root / exr.render_filename("fog", 2048), _rgb_channels(ref))
    return root


@pytest.mark.slow  # about 15 s of CPU: the shipped model loaded twice, four denoises of each frame
def test_the_study_scores_each_variant_as_the_library_and_numpy_do(frames, tmp_path):
    out = tmp_path / "reports"
    res = run_main("aux-study", frames, "--model", MODEL, "--out", out, "--blender-record", tmp_path / "none.json",
                   cwd=REPO)
    assert res.returncode == 0, res.stderr[-3000:]
    record = json.loads((out / "aux.json").read_text())
    assert (out / "aux.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "| 4 | nlm |" in (out / "aux.md").read_text()
    assert record["check"] is None and set(record["variants"]) >= {"raw", "oracle", "nlm"}
    rows = {r["spp"]: r for r in record["frames"]}
    ref = _combined(exr.read_image(frames / exr.render_filename("fog", 2048)).channels)
    clean = layouts.read(frames / exr.render_filename("fog", 16)).layers
    for spp, row in rows.items():
        frame = kpcn.read(frames / exr.render_filename("fog", spp))
        expected = {"raw": kpcn.denoise(frame, run=MODEL),
                    "oracle": kpcn.denoise(dataclasses.replace(
                        frame, layers=auxiliary.auxiliaries(frame.layers, "clean", clean=clean)), run=MODEL)}
        for variant, image in expected.items():
            x = np.asarray(image, np.float64)
            assert row["scores"][f"kpcn {variant}"]["relmse"] == pytest.approx(
                float(np.mean((x - ref) ** 2 / (ref * ref + metrics.RELMSE_EPS))), rel=1e-9)
        assert row["oracle_from"].endswith("fog-00016spp.exr")
    # at the scene's cleanest render the oracle is the raw frame
    assert rows[16]["scores"]["kpcn oracle"] == rows[16]["scores"]["kpcn raw"]
    block = record["summary"]["4"]["variants"]["raw"]
    ratio = rows[4]["scores"]["kpcn raw"]["relmse"] / rows[4]["scores"]["blender"]["relmse"]
    assert block["median_ratio_blender"] == pytest.approx(ratio) and block["below_blender"] == int(ratio < 1)


def test_the_check_reads_the_blender_reports_scores_of_the_same_model(frames, tmp_path):
    rows = [{"frame": str(frames / "fog-00004spp.exr"), "scores": {"kpcn raw": {"relmse": 0.5, "dssim": 0.25}}}]
    theirs = {"models": {"shipped": str(MODEL)},
              "frames": [{"frame": rows[0]["frame"], "scores": {"kpcn shipped": {"relmse": 0.5, "dssim": 0.375}}}]}
    path = tmp_path / "blender.json"
    path.write_text(json.dumps(theirs))
    check = aux_study.check_against(path, MODEL, rows)
    assert check["frames"] == 1 and check["max_abs_diff"] == {"relmse": 0.0, "dssim": 0.125}
    assert aux_study.check_against(path, tmp_path, rows) is None  # another model: nothing to check


def test_a_folder_without_frames_is_one_line(tmp_path):
    res = run_main("aux-study", tmp_path, "--out", tmp_path / "out", cwd=REPO)
    assert_one_line_error(res, str(tmp_path), "no noisy frame")
