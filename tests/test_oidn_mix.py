"""A run's frame mixed with OIDN's (``kpcn_keras.oidn_mix``, ``kpcn mix-oidn``): the fit finds the weight that two
independent errors' variances give, a mixed frame is the weighted mean of the networks' frame and OIDN's (float64
numpy) whether tiled or not, the weight travels in each variant's record to every command that denoises, and a
damaged entry is refused in one line."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import run_main

from prep import baselines

CYCLES = "tests/fixtures/renderers/cycles5/studio-00016spp.exr"  # has Blender's Denoising Albedo and Normal

needs_oidn = pytest.mark.skipif(not baselines.oidn_available(), reason="pyoidn (the optional extra oidn) is missing")


def test_the_fit_finds_the_weight_two_independent_errors_call_for():
    from kpcn_keras.oidn_mix_fit import GRID, fit_weight

    # errors of variance 4 s² and s²: the mean w a + (1 - w) b has error variance 4 s² w² + s² (1 - w)², least at
    # w = 1 / 5; with a constant reference relMSE is that variance over (0.5² + 0.01)
    rng = np.random.default_rng(0)
    ref = np.full((96, 96, 3), 0.5, np.float32)
    frames = [(ref + rng.normal(0, 0.02, ref.shape).astype(np.float32),
               ref + rng.normal(0, 0.01, ref.shape).astype(np.float32), ref) for _ in range(6)]
    weight, objective = fit_weight(frames)
    assert weight in GRID and abs(weight - 0.2) <= 0.05 + 1e-9
    analytic = {w: np.log((4 * w ** 2 + (1 - w) ** 2) * 0.01 ** 2 / (0.25 + 0.01)) for w in GRID}
    for w in GRID:  # the objective itself, against the analytic variance (a statistical bound: 6 x 27648 draws)
        assert objective[w] == pytest.approx(analytic[w], abs=0.03)
    by_hand = np.mean([np.log(np.mean(((0.2 * f[0] + 0.8 * f[1]) - f[2]) ** 2 / (f[2] ** 2 + 0.01)))
                       for f in [tuple(x.astype(np.float64) for x in t) for t in frames]])
    assert objective[0.2] == pytest.approx(by_hand, rel=1e-5)


@pytest.fixture(scope="module")
def mixed_run(tiny_run_of_every_input_set, tmp_path_factory):
    """A copy of the tiny run of every input set (beside it: its records' shard paths hold) with its mix fit."""
    src = Path(tiny_run_of_every_input_set)
    dest = src.with_name("mixed")
    if not dest.exists():
        shutil.copytree(src, dest)
    res = run_main("mix-oidn", "--run", dest, str(Path.cwd() / CYCLES), cwd=dest.parent)
    assert res.returncode == 0, res.stderr
    return dest, res


@needs_oidn
def test_mix_oidn_writes_the_weight_into_each_variant_that_serves_the_frames(mixed_run):
    from kpcn_keras.oidn_mix import KEY
    from kpcn_keras.oidn_mix_fit import GRID

    run, res = mixed_run
    written = {}
    for name in ("full", "no-variance", "no-split", "no-split-no-variance"):
        folder = run if name == "full" else run / "inputs" / name
        written[name] = json.loads((folder / "config.json").read_text()).get(KEY)
    # a Cycles frame has a split and no variance: the no-variance networks serve it, the others are left unmixed
    assert written["full"] is None and written["no-split"] is None and written["no-split-no-variance"] is None
    for name in ("no-variance",):
        entry = written[name]
        assert entry["weight"] in GRID and entry["oidn_mode"] == "prefiltered" and entry["oidn_quality"] == "high"
        assert entry["fit"]["frames"] == [str(Path.cwd() / CYCLES)]
        best = min(entry["fit"]["by_weight"].values())
        assert entry["fit"]["by_weight"][f"{entry['weight']:g}"] == best
    assert res.stdout.count("weight") == 1


@needs_oidn
def test_a_mixed_frame_is_the_weighted_mean_of_the_networks_and_oidn_tiled_or_not(mixed_run):
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.oidn_mix import KEY
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from kpcn_keras.settings import InferenceSettings
    from prep import layouts

    fitted, _ = mixed_run
    run = fitted.with_name("mixed-at-0.35")  # a weight of neither end, so that both frames count
    if not run.exists():
        shutil.copytree(fitted, run)
    frame = layouts.read(CYCLES)
    variant = Run(run).serving(frame.inputs)
    data = variant.read_record()
    weight = data[KEY]["weight"] = 0.35
    variant.write_record(data)
    networks = Denoiser.from_run(variant)(frame.layers)["default"].astype(np.float64)
    oidn = baselines.oidn_denoise(baselines.oidn_inputs(frame)).astype(np.float64)  # Blender's guides
    expected = weight * networks + (1 - weight) * oidn
    for tile in (16, 256):
        out = Serving(Run(run), InferenceSettings(tile=tile)).denoiser(frame.inputs)(frame.served_layers())
        np.testing.assert_allclose(out["default"], expected, rtol=1e-5, atol=1e-6)
    # the guides matter: OIDN with the Diffuse Color in place of the Denoising Albedo gives another frame
    assert np.abs(baselines.oidn_denoise(frame.layers) - oidn).max() > 1e-4


@needs_oidn
def test_kpcn_denoise_and_the_api_serve_the_mix(mixed_run, tmp_path):
    import kpcn
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from prep import exr, layouts

    run, _ = mixed_run
    frame = layouts.read(CYCLES)
    served = Serving(Run(run)).denoiser(frame.inputs)(frame.served_layers())["default"]
    out = tmp_path / "out.exr"
    res = run_main("denoise", str(Path.cwd() / CYCLES), "--run", run, "-o", out, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    np.testing.assert_array_equal(exr.read_aovs(out, variances=False)["default"], served)
    np.testing.assert_array_equal(kpcn.denoise(kpcn.read(CYCLES), run=run), served)


@needs_oidn
def test_the_card_gives_each_mixed_input_sets_weight(mixed_run, tiny_run_of_every_input_set):
    from kpcn_keras.card import quality_lines
    from kpcn_keras.oidn_mix import KEY
    from kpcn_keras.run import Run

    run, _ = mixed_run
    weights = {name: json.loads((run / "inputs" / name / "config.json").read_text())[KEY]["weight"]
               for name in ("no-variance",)}
    lines = quality_lines({"balanced": Run(tiny_run_of_every_input_set), "high": Run(run)})
    balanced, high = (line.split(" | ") for line in lines if line.startswith(("| balanced", "| high")))
    assert balanced[3] == "–"
    assert high[3] == ", ".join(f"{name} {weight:g}" for name, weight in weights.items())


def test_an_onnx_export_says_which_graphs_are_mixed_and_at_what_weight(mixed_run, tmp_path):
    pytest.importorskip("onnx", reason="onnx not installed (the optional extra onnx; CI: .[test])")
    pytest.importorskip("onnxruntime", reason="onnxruntime not installed (the optional extra onnx; CI: .[test])")
    from kpcn_keras.onnx_export import MANIFEST, export
    from kpcn_keras.run import Run

    run, _ = mixed_run
    out = export(Run(run), tmp_path / "exported")
    entries = json.loads((out / MANIFEST).read_text())["networks"]
    weight = json.loads((run / "inputs" / "no-variance" / "config.json").read_text())["oidn_mix"]["weight"]
    for entry in entries:
        expected = ({"weight": weight, "oidn_mode": "prefiltered", "oidn_quality": "high"}
                    if entry["inputs"] == "no-variance" else None)
        assert entry["oidn_mix"] == expected, entry["file"]


def test_a_damaged_mix_entry_is_refused_in_one_line_naming_it():
    from kpcn_keras.oidn_mix import KEY, of_record
    from prep.errors import KpcnError

    assert of_record({}) is None
    assert of_record({KEY: {"weight": 0.25, "oidn_mode": "prefiltered", "oidn_quality": "high"}}).weight == 0.25
    for bad in ({"weight": 2, "oidn_mode": "prefiltered", "oidn_quality": "high"},
                {"weight": 0.5, "oidn_mode": "sharp", "oidn_quality": "high"}, {"oidn_mode": "plain"}):
        with pytest.raises(KpcnError, match=f"^runs/r/config.json: entry '{KEY}'") as info:
            of_record({KEY: bad}, "runs/r/config.json")
        assert "\n" not in str(info.value)
