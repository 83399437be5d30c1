"""``kpcn denoise A.exr --pair B.exr`` on every layout denoise reads, the refusal of a pair that is not a second
render of the input's frame (``prep.pairs``), alpha repaired as every layer is, and ``--albedo``/``--normal``
refused where the render has its own."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.exr_layouts import cycles_channels, modified_copy, parts_of, write_channels
from helpers.tiny import random_aovs

from kpcn_keras.batch import ReadOptions, read_frame
from prep import exr, layouts, pairs
from prep.errors import OptionError
from prep.inputs import InputSet, restrict

RENDERERS = Path(__file__).parent / "fixtures" / "renderers"
CYCLES45 = RENDERERS / "cycles45" / "studio-00016spp.exr"
H, W = 16, 12


def _rgb(seed: int, noise_seed: int) -> dict:
    """A plain colour file's channels: one scene (``seed``), one render of it (±10% noise from ``noise_seed``)."""
    base = np.random.default_rng(seed).uniform(0, 1, (H, W, 3))
    colour = base * np.random.default_rng(noise_seed).uniform(0.9, 1.1, base.shape)
    return {c: colour[..., i].astype(np.float32) for i, c in enumerate("RGB")}


def _colour(channels: dict, layer: str = "") -> np.ndarray:
    return np.stack([channels[f"{layer}{c}"] for c in "RGB"], axis=-1)


def _pair_of(kind: str, folder: Path, spp=(8, 8)) -> tuple[Path, Path, dict, np.ndarray, np.ndarray]:
    """Two renders of one frame in the layout ``kind`` (of :data:`NO_SPLIT`): (a, b, read options' extras, a's
    colour, b's colour as written)."""
    paths, colours, extra = [], [], {}
    for noise, n in zip((1, 2), spp):
        if kind.startswith("rgb"):
            ch, layer = _rgb(5, noise), ""
        else:
            ch, layer = cycles_channels(H, W, seed=5, noise_seed=noise), "ViewLayer.Combined."
            keep = ("ViewLayer.Combined.",) if kind == "cycles-combined" else ("ViewLayer.",)
            ch = {k: v for k, v in ch.items() if k.startswith(keep) and "Diffuse Color" not in k}
        paths.append(write_channels(folder / f"{'ab'[noise - 1]}-{n:05d}spp.exr", ch))
        colours.append(_colour(ch, layer))
    if kind == "rgb-albedo":
        albedo = np.random.default_rng(9).uniform(0, 1, (H, W, 3)).astype(np.float32)
        extra["albedo"] = write_channels(folder / "albedo.exr", {c: albedo[..., i] for i, c in enumerate("RGB")})
    return paths[0], paths[1], extra, colours[0], colours[1]


# every layout without a diffuse/specular split that denoise reads (the layout kpcn finds for each)
NO_SPLIT = {"rgb": "rgb", "cycles-combined": "rgb", "cycles-no-diffuse-color": "cycles", "rgb-albedo": "rgb"}


@pytest.mark.parametrize("kind", NO_SPLIT)
def test_a_pair_is_read_as_one_render_of_all_its_samples(tmp_path, kind):
    a, b, extra, ca, cb = _pair_of(kind, tmp_path)
    single = read_frame(a, ReadOptions(**extra))
    frame = read_frame(a, ReadOptions(pair=b, **extra))
    # what one render gives, no variance made from the two renders' difference
    assert frame.layout == NO_SPLIT[kind] and frame.inputs == single.inputs == InputSet(split=False, variance=False)
    assert frame.spp == 16 and not set(frame.layers) & set(exr.VARIANCE_LAYERS)
    np.testing.assert_allclose(frame.layers["default"], (ca.astype(np.float64) + cb) / 2, rtol=1e-6)
    served = restrict(frame.layers, frame.inputs)  # what the no-split network reads
    assert all(np.isfinite(v).all() for v in served.values())


@pytest.mark.slow
@pytest.mark.parametrize("kind", NO_SPLIT)
def test_kpcn_denoise_takes_a_pair_of_every_layout_without_a_split(tiny_run_of_every_input_set, tmp_path, kind):
    a, b, extra, _, _ = _pair_of(kind, tmp_path)
    run = tiny_run_of_every_input_set
    args = [f"--{k}={v}" for k, v in extra.items()]
    res = run_main("denoise", a, "--pair", b, *args, "--run", run, "-o", tmp_path / "o.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    served = "no-split-no-variance"
    assert f"({NO_SPLIT[kind]} layout, {served}, model {run / 'inputs' / served};" in res.stdout, res.stdout
    colour = np.stack([exr.read_image(tmp_path / "o.exr").channels[f"default.{c}"] for c in "RGB"], axis=-1)
    assert colour.shape == (H, W, 3) and np.isfinite(colour).all()


# ---------------------------------------------------------------- a pair that is not a second render of the frame

def _cycles_pair(folder: Path, seeds=(5, 5), spp=(8, 8), header=None) -> tuple[Path, Path]:
    """Two Cycles renders with a split (the full model serves their pair): scenes ``seeds``, noise 1 and 2."""
    out = []
    for i, (seed, n) in enumerate(zip(seeds, spp)):
        ch = cycles_channels(H, W, seed=seed, noise_seed=i + 1)
        out.append(write_channels(folder / f"{'ab'[i]}-{n:05d}spp.exr", ch, parts_of(ch),
                                  header=header if i == 1 else None))
    return out[0], out[1]


def test_a_pair_that_is_the_input_itself_is_refused_in_one_line_before_any_work(tmp_path, tiny_run):
    a, _ = _cycles_pair(tmp_path)
    os.symlink(a, tmp_path / "link-00008spp.exr")
    for same in (a, "./a-00008spp.exr", tmp_path / "link-00008spp.exr"):
        res = run_main("denoise", a, "--pair", same, "--run", tiny_run, "-o", tmp_path / "o.exr", cwd=tmp_path)
        assert_one_line_error(res, f"--pair {Path(same)} is the input {a} itself")
    assert not (tmp_path / "o.exr").exists()


def test_a_copy_of_the_input_as_its_pair_is_refused_as_the_same_render(tmp_path, tiny_run_of_every_input_set):
    a, _ = _cycles_pair(tmp_path)
    shutil.copy(a, tmp_path / "copy-00008spp.exr")
    res = run_main("denoise", a, "--pair", "copy-00008spp.exr", "--run", tiny_run_of_every_input_set, "-o", "o.exr",
                   cwd=tmp_path)
    assert_one_line_error(res, f"--pair copy-00008spp.exr has the same pixels as {a}: the same render twice")
    assert not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("differs, needle", [
    ("spp", "differs in spp (16, the input's 8)"),
    ("window", "differs in data window (((4, 2), (15, 17)), the input's ((0, 0), (11, 15)))"),
    ("size", "differs in size (12x15, the input's 12x16)"),
    ("layout", "differs in layout (rgb, the input's cycles), diffuse/specular split (False, the input's True)"),
])
def test_a_pair_of_another_header_is_refused_in_one_line_before_any_work(tmp_path, tiny_run, differs, needle):
    a, b = _cycles_pair(tmp_path, spp=(8, 16) if differs == "spp" else (8, 8), header={
        "dataWindow": (np.array([4, 2], np.int32), np.array([15, 17], np.int32))} if differs == "window" else None)
    if differs == "size":
        ch = cycles_channels(H - 1, W, seed=5, noise_seed=2)
        b = write_channels(tmp_path / "b-00008spp.exr", ch, parts_of(ch))
    elif differs == "layout":
        b = write_channels(tmp_path / "b-00008spp.exr", _rgb(5, 2))
    res = run_main("denoise", a, "--pair", b, "--run", tiny_run, "-o", tmp_path / "o.exr", cwd=tmp_path)
    assert_one_line_error(res, f"--pair {b} is not a second render of {a}: it {needle}")
    assert not (tmp_path / "o.exr").exists()


def test_a_pair_of_another_scene_of_the_same_size_and_spp_is_refused_in_one_line(tmp_path,
                                                                               tiny_run_of_every_input_set):
    a, b = _cycles_pair(tmp_path, seeds=(5, 6))
    r = pairs.correlation(layouts.read(a).layers["default"], layouts.read(b).layers["default"])
    assert r < pairs.MIN_CORRELATION
    res = run_main("denoise", a, "--pair", b, "--run", tiny_run_of_every_input_set, "-o", tmp_path / "o.exr",
                   cwd=tmp_path)
    assert_one_line_error(res, f"--pair {b} is not a render of the frame {a}: their smoothed log luminance "
                               f"correlates at {r:.3f}, below 0.6")
    assert not (tmp_path / "o.exr").exists()
    (tmp_path / "same").mkdir()
    same_scene = _cycles_pair(tmp_path / "same")
    assert pairs.correlation(*(layouts.read(p).layers["default"] for p in same_scene)) > 0.9


def test_the_correlation_of_a_pair_is_pearsons_of_the_smoothed_log_luminance():
    rng = np.random.default_rng(3)
    a, b = rng.gamma(0.5, 2.0, (2, 9, 11, 3))
    b[..., 1] *= -1  # negative luminance counts as 0

    def smoothed(c):
        lum = np.log1p(np.maximum(c @ np.array([0.2126, 0.7152, 0.0722]), 0.0))
        return np.array([[lum[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3].mean() for x in range(11)]
                         for y in range(9)])

    np.testing.assert_allclose(pairs.correlation(a, b), np.corrcoef(smoothed(a).ravel(), smoothed(b).ravel())[0, 1],
                               rtol=1e-12)
    assert pairs.correlation(a, a * 2) > 0.99 and pairs.correlation(a, np.ones_like(a)) is None
    ramp = np.broadcast_to(np.linspace(0, 1, 11)[None, :, None], (9, 11, 3))
    assert pairs.correlation(ramp, ramp[:, ::-1]) < -0.99  # a mirrored frame: not the same picture


def test_the_measure_of_the_threshold_takes_every_two_frames_of_one_size(tmp_path):
    for name, seed, noise in (("s-00004spp", 5, 1), ("s-00016spp", 5, 2), ("t-00004spp", 6, 1)):
        write_channels(tmp_path / f"{name}.exr", _rgb(seed, noise))
    write_channels(tmp_path / "u-00004spp.exr", {c: np.ones((3, 3), np.float32) for c in "RGB"})  # another size
    rows = pairs.measure(sorted(tmp_path.glob("*.exr")))
    assert [(r["a"], r["b"], r["same_scene"]) for r in rows] == [
        ("s-00004spp.exr", "s-00016spp.exr", True), ("s-00004spp.exr", "t-00004spp.exr", False),
        ("s-00016spp.exr", "t-00004spp.exr", False)]
    colour = {n: _colour(_rgb(seed, noise)) for n, seed, noise in (("s4", 5, 1), ("s16", 5, 2), ("t4", 6, 1))}
    assert [r["correlation"] for r in rows] == [pairs.correlation(colour["s4"], colour["s16"]),
                                                pairs.correlation(colour["s4"], colour["t4"]),
                                                pairs.correlation(colour["s16"], colour["t4"])]


# ---------------------------------------------------------------- alpha, repaired as every layer is

def _alpha_with_faults(seed: int, value=np.nan, count: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A 64x64 half alpha (a ramp) with ``count`` pixels of NaN, +inf, -inf and 3e38 (inf in half) in turn (or all
    ``value``), and the mask of those pixels."""
    rng = np.random.default_rng(seed)
    alpha = np.linspace(0.1, 0.9, 64 * 64).reshape(64, 64)
    bad = np.zeros((64, 64), bool)
    bad.ravel()[rng.choice(64 * 64, count, replace=False)] = True
    with np.errstate(over="ignore"):
        faults = np.array([np.nan, np.inf, -np.inf, 3e38]).astype(np.float16)
        alpha = alpha.astype(np.float16)
        alpha[bad] = np.resize(faults, count)
    return alpha, bad


def _repair(alpha: np.ndarray) -> np.ndarray:
    """NaN -> 0, +inf -> the largest finite value, -inf -> the smallest, float64."""
    a = alpha.astype(np.float64)
    finite = a[np.isfinite(a)]
    hi, lo = (finite.max(), finite.min()) if finite.size else (0.0, 0.0)
    return np.where(np.isnan(a), 0.0, np.where(np.isposinf(a), hi, np.where(np.isneginf(a), lo, a)))


def test_non_finite_alpha_is_repaired_by_the_rule_of_every_layer_and_counted(tmp_path):
    alpha, bad = _alpha_with_faults(1)
    path = modified_copy(CYCLES45, tmp_path / "studio-00016spp.exr", {"ViewLayer.Combined.A": alpha})
    frame = layouts.read(path)
    assert np.isfinite(frame.alpha).all() and frame.alpha.dtype == np.float32
    np.testing.assert_array_equal(frame.alpha, _repair(alpha))
    np.testing.assert_array_equal(frame.alpha[~bad], alpha[~bad].astype(np.float32))
    assert any("alpha: 16" in note for note in frame.notes), frame.notes
    everywhere = modified_copy(CYCLES45, tmp_path / "nan-00016spp.exr",
                               {"ViewLayer.Combined.A": np.full((64, 64), np.nan, np.float16)})
    np.testing.assert_array_equal(layouts.read(everywhere).alpha, 0)


def test_a_pairs_alpha_is_the_mean_of_its_two_repaired_alphas(tmp_path):
    (alpha_a, _), (alpha_b, _) = _alpha_with_faults(1), _alpha_with_faults(2)
    source = exr.read_image(CYCLES45).channels
    noise = np.random.default_rng(4).uniform(0.9, 1.1, (64, 64))
    brighter = {f"ViewLayer.Combined.{c}": (source[f"ViewLayer.Combined.{c}"] * noise).astype(np.float16)
                for c in "RGB"}
    a = modified_copy(CYCLES45, tmp_path / "a-00016spp.exr", {"ViewLayer.Combined.A": alpha_a})
    b = modified_copy(CYCLES45, tmp_path / "b-00016spp.exr", {"ViewLayer.Combined.A": alpha_b, **brighter})
    frame = read_frame(a, ReadOptions(pair=b))
    np.testing.assert_allclose(frame.alpha, (_repair(alpha_a) + _repair(alpha_b)) / 2, rtol=1e-7)


@pytest.mark.slow
def test_kpcn_denoise_writes_a_finite_alpha_for_non_finite_input_alpha(tiny_run_of_every_input_set, tmp_path):
    alpha, bad = _alpha_with_faults(1)
    src = modified_copy(CYCLES45, tmp_path / "studio-00016spp.exr", {"ViewLayer.Combined.A": alpha})
    res = run_main("denoise", src, "--run", tiny_run_of_every_input_set, "-o", tmp_path / "o.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    written = exr.read_image(tmp_path / "o.exr").channels["default.A"]
    assert np.isfinite(written).all()
    np.testing.assert_array_equal(written[~bad], alpha[~bad].astype(np.float32))


# ---------------------------------------------------------------- auxiliary files beside a render's own

def test_an_albedo_or_normal_file_for_a_render_that_has_its_own_is_refused_in_one_line(tmp_path, tiny_run):
    src = exr.write_aovs(tmp_path / "k-00008spp.exr", random_aovs(H, W))
    aux = write_channels(tmp_path / "aux.exr", _rgb(5, 1))
    for option in ("albedo", "normal"):
        res = run_main("denoise", src, f"--{option}", aux, "--run", tiny_run, "-o", tmp_path / "o.exr", cwd=tmp_path)
        assert_one_line_error(res, f"--{option} {aux} is for a frame without its own {option}, and {src} (kpcn "
                                   "layout) has one")
    assert not (tmp_path / "o.exr").exists()
    ch = cycles_channels(H, W)
    cycles = write_channels(tmp_path / "c-00008spp.exr", ch)
    with pytest.raises(OptionError, match=r"albedo .* without its own albedo, and .* \(cycles layout\) has one"):
        layouts.read(cycles, albedo=aux)
    rgb = write_channels(tmp_path / "p.exr", _rgb(5, 1))
    np.testing.assert_array_equal(layouts.read(rgb, albedo=aux).layers["albedo"], _colour(_rgb(5, 1)))
