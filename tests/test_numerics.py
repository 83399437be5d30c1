"""Hard numerical cases end to end: every stage stays finite and agrees with a float64 computation.

Every hard case is a synthetic render (``helpers.tiny.random_aovs`` with the case applied) that goes through
the whole pipeline: written with ``prep.exr.write_aovs`` and read back (the repair rule), the features of
both branches (finite, inside the ranges of the table in ``prep/features.py``, equal to a float64 numpy
evaluation of that table), the variance PDF (a distribution equal to explicit window sums), shards, real
training steps of the three architectures (losses and gradients finite) and tiled denoising (finite,
non-negative, equal to an untiled run). Figures are checked against independent float64 references
(``helpers.references``); the property-based tests (hypothesis) of the feature transforms, the PDF, the kernel
application and the losses are in the files of their modules (test_features, test_sampling, test_layers,
test_losses, test_models).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.networks import finite_loss_and_gradients, randomise
from helpers.numerics import F32_EPS, F32_MAX, F32_TINY, FEATURE_RANGES, HALF_MAX, RELVAR_BOUND
from helpers.references import (
    assert_features_in_documented_ranges,
    assert_features_match_reference,
    assert_pdf_is_a_distribution,
    assert_read_features_close,
    assert_variance_pdf_matches,
    reference_features,
    reference_importance,
    reference_log_colour,
    reference_pdf,
)
from helpers.tiny import random_aovs

from kpcn_keras.denoise import Denoiser
from kpcn_keras.models import ARCHS
from kpcn_keras.run import Run, load_model
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.train import TrainConfig, train
from prep import exr, features, sampling, shards
from prep.albedo import prefilter
from prep.colour import ALBEDO_EPS, LOG_COLOUR_MAX
from prep.errors import KpcnError, OptionError
from prep.features import NUM_FEATURES

TINY = {"width": 4, "depth": 2, "kernel_size": 3}
PATCH = 8
SIZE = (16, 18)


def to_np(x):
    """Tensor -> numpy without keras.ops.convert_to_numpy, whose np.array(torch_tensor) warns on numpy 2."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@pytest.fixture(scope="module", autouse=True)
def _one_torch_thread():
    """This module runs hundreds of tiny forward passes; on a loaded 2-core machine torch's two OpenMP
    threads wait on each other (about 70 ms per 12x12 pass instead of 1 ms). Restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---------------------------------------------------------------- the hard cases

COLOUR_LAYERS = ("diffuse", "specular", "default")


def _variances(aovs):
    return [name for name in exr.VARIANCE_LAYERS if name in aovs]


def _firefly(value):
    def apply(aovs, reference):
        for name in COLOUR_LAYERS:
            aovs[name] *= np.float32(1e-3)  # a dim image
        aovs["diffuse"][5, 7] = aovs["specular"][5, 7] = value
        aovs["default"][5, 7] = 2 * value
        for name in ("diffuseVariance", "specularVariance", "colorVariance"):
            if name in aovs:
                aovs[name][5, 7] = 3 * value * value / 4  # the mean of 4 samples, one of them 4 * value
    return apply


def _extremes(big):
    """Every layer at +-big somewhere: albedo and normal far outside their ranges, depth with misses."""
    def apply(aovs, reference):
        for name in ("diffuse", "specular", "default"):
            aovs[name][0] = big
            aovs[name][1] = -big
        aovs["diffuse"][2, :, 0] = F32_TINY  # subnormal (0 in a half file)
        aovs["albedo"][0] = 0.0  # irradiance big / ALBEDO_EPS: the largest log colour
        aovs["albedo"][3] = big
        aovs["albedo"][4] = -big
        aovs["normal"][5] = big
        aovs["normal"][6] = -big
        aovs["depth"][:] = big
        aovs["depth"][7] = 0.0
        aovs["depth"][8] = -big
        for name in _variances(aovs):
            aovs[name][::2] = big
            aovs[name][1::2, ::3] = -big  # negative variances count as 0
    return apply


def _albedo_zero(aovs, reference):
    aovs["albedo"][:] = 0.0


def _specular_negative_and_zero(aovs, reference):
    s = aovs["specular"]
    s[:, :6] = 0.0
    s[:, 6:9] *= -1.0  # a renderer's rounding
    s[0, 9:] = -F32_MAX
    s[1, 9:] = -F32_TINY
    aovs["default"] = aovs["diffuse"] + s


def _depth_zero(aovs, reference):
    aovs["depth"][:] = 0.0


def _depth_with_misses(aovs, reference):
    miss = (slice(4, 10), slice(3, 12))  # rays that leave the scene and see a light
    aovs["depth"][miss] = 0.0
    aovs["normal"][miss] = 0.0
    aovs["albedo"][miss] = 0.0
    aovs["diffuse"][miss] = 0.0
    aovs["specular"][miss] = 5.0
    aovs["default"][miss] = 5.0
    for name in ("depthVariance", "normalVariance", "albedoVariance"):
        if name in aovs:
            aovs[name][miss] = 0.0


def _depth_1e30(aovs, reference):
    aovs["depth"][:] = 1e30 * np.random.default_rng(1).uniform(0.1, 1.0, aovs["depth"].shape)
    if "depthVariance" in aovs:
        aovs["depthVariance"][:] = 1e20


def _variance(value):
    def apply(aovs, reference):
        for name in _variances(aovs):
            aovs[name][:] = value
    return apply


def _nan_inf_everywhere(aovs, reference):
    for image in aovs.values():
        flat = image.reshape(-1)  # a view: random_aovs' arrays are contiguous
        flat[::7] = np.nan
        flat[1::7] = np.inf
        flat[2::7] = -np.inf


def _constant(aovs, reference):
    values = {"diffuse": 0.5, "specular": 0.25, "default": 0.75, "albedo": 0.6, "depth": 3.0}
    for name, image in aovs.items():
        image[:] = values.get(name, 0.01)
    aovs["normal"][:] = [0.0, 0.0, 1.0]


def _black(aovs, reference):
    for image in aovs.values():
        image[:] = 0.0


@dataclass(frozen=True)
class HardCase:
    apply: Callable[[dict, bool], None]  # edits a render in place; the flag says "reference" (no variances)
    half: bool = False  # write half floats
    default: bool = True  # write the default layer (else read_aovs derives it)

    def render(self, seed: int, reference: bool = False) -> dict:
        aovs = random_aovs(*SIZE, seed=seed, variances=not reference)
        self.apply(aovs, reference)
        if not self.default:
            del aovs["default"]
        return aovs

    def write(self, folder: Path, scene: str, seed: int) -> Path:
        """A noisy (4 spp) and a reference (64 spp) render of the case; returns the noisy one's path."""
        folder.mkdir(parents=True, exist_ok=True)
        exr.write_aovs(folder / exr.render_filename(scene, 64), self.render(seed + 1000, True), half=self.half)
        return exr.write_aovs(folder / exr.render_filename(scene, 4), self.render(seed), half=self.half)


HARD_CASES = {
    "firefly-1e4": HardCase(_firefly(1e4)),
    "firefly-1e5": HardCase(_firefly(1e5)),
    "firefly-1e6": HardCase(_firefly(1e6)),
    "float32-max": HardCase(_extremes(F32_MAX)),
    "half-max": HardCase(_extremes(HALF_MAX), half=True),
    "float32-max-into-half": HardCase(_extremes(F32_MAX), half=True),  # clamped to half max when written
    "albedo-zero": HardCase(_albedo_zero),
    "specular-negative-and-zero": HardCase(_specular_negative_and_zero),
    "depth-zero-everywhere": HardCase(_depth_zero),
    "depth-with-misses": HardCase(_depth_with_misses),
    "depth-1e30": HardCase(_depth_1e30),
    "variance-zero": HardCase(_variance(0.0)),
    "variance-1e20": HardCase(_variance(1e20)),
    "nan-inf-every-layer": HardCase(_nan_inf_everywhere),
    "nan-inf-every-layer-no-default": HardCase(_nan_inf_everywhere, default=False),
    "constant": HardCase(_constant),
    "black": HardCase(_black),
}
SEEDS = {name: 20 + i for i, name in enumerate(HARD_CASES)}


# ---------------------------------------------------------------- documented ranges


def documented_ranges() -> dict[int, tuple[float, float]]:
    """channel -> (low, high) as the table in prep/features.py's docstring states it."""
    doc = features.__doc__
    row = re.compile(r"^(\d+)(?:-(\d+))?\s.*\[(-?\d+(?:\.\d+)?), (-?\d+(?:\.\d+)?)\]\s*$")
    ranges = {}
    for line in doc.splitlines():
        m = row.match(line)
        if m:
            for c in range(int(m[1]), int(m[2] or m[1]) + 1):
                ranges[c] = (float(m[3]), float(m[4]))
    same = re.search(r"^(\d+)-(\d+)\s.*\bas above\s*$", doc, re.M)  # "13-22  dy of the same ... as above"
    first, last = int(same[1]), int(same[2])
    for c in range(first, last + 1):
        ranges[c] = ranges[c - first + 3]
    return ranges


def test_features_docstring_ranges_contain_every_reachable_value():
    doc = documented_ranges()
    assert sorted(doc) == list(range(NUM_FEATURES))
    for first, stop, lo, hi in FEATURE_RANGES:
        for c in range(first, stop):
            assert doc[c][0] <= lo and hi <= doc[c][1], (features.FEATURE_NAMES[c], doc[c], (lo, hi))


def test_largest_float32_inputs_give_exactly_the_largest_documented_features():
    aovs = random_aovs(4, 5, seed=1)
    aovs["albedo"][:] = 0.0
    aovs["diffuse"][0, 0] = F32_MAX
    aovs["specular"][0, 0] = F32_MAX
    aovs["depth"][:] = 0.0
    aovs["depth"][3, 4] = F32_TINY
    aovs["depthVariance"][:] = F32_MAX
    diffuse = features.branch_features(aovs, "diffuse")
    specular = features.branch_features(aovs, "specular")
    assert diffuse[0, 0, :3].tolist() == [np.float32(LOG_COLOUR_MAX)] * 3
    assert specular[0, 0, :3].tolist() == [np.float32(np.log1p(F32_MAX))] * 3
    # every pixel but the one at depth F32_TINY is a miss (d = 0) with the largest depth scale
    assert diffuse[0, 0, 26] == np.float32(RELVAR_BOUND)
    assert_features_in_documented_ranges(diffuse)
    assert_features_in_documented_ranges(specular)


# ---------------------------------------------------------------- each hard case: file -> features -> PDF


@pytest.mark.parametrize("case", list(HARD_CASES))
def test_hard_case_features_and_pdf_are_finite_in_range_and_match_float64(tmp_path, case):
    path = HARD_CASES[case].write(tmp_path, case, SEEDS[case])
    aovs = exr.read_aovs(path)
    for name, image in aovs.items():
        assert np.isfinite(image).all(), name
    assert_features_match_reference(aovs)
    for patch in (1, PATCH, min(SIZE)):
        pdf = assert_variance_pdf_matches(aovs, patch)
        count = min(5, pdf.size)
        pos = sampling.draw_positions(pdf, count, np.random.default_rng(0))
        assert len({tuple(p) for p in pos}) == count and (pdf[pos[:, 0], pos[:, 1]] > 0).all()
    reference = exr.read_aovs(path.with_name(exr.render_filename(case, 64)), variances=False)
    for name, image in reference.items():
        assert np.isfinite(image).all(), name
    for branch, albedo in (("diffuse", reference["albedo"]), ("specular", None)):
        got = features.branch_colour(reference, branch)
        np.testing.assert_allclose(got, reference_log_colour(reference[branch], albedo), rtol=1e-6, atol=1e-7)
        assert got.min() >= 0 and got.max() <= LOG_COLOUR_MAX


NONFINITE_CASES = [(layer, True) for layer in exr.RGB_LAYERS + exr.SCALAR_LAYERS] + [
    (layer, False) for layer in exr.RGB_LAYERS + exr.SCALAR_LAYERS if layer != "default"]


@pytest.mark.parametrize("layer,with_default", NONFINITE_CASES,
                         ids=[f"{layer}-{'with' if d else 'without'}-default" for layer, d in NONFINITE_CASES])
def test_nan_and_inf_in_any_layer_are_repaired_by_the_documented_rule(tmp_path, caplog, layer, with_default):
    aovs = random_aovs(9, 10, seed=3)
    image = aovs[layer]
    chans = image[..., None] if image.ndim == 2 else image  # a view
    picks = np.random.default_rng(4).choice(90, 9, replace=False)
    ys, xs = np.unravel_index(picks, (9, 10))
    chans[ys[:3], xs[:3]] = np.nan
    chans[ys[3:6], xs[3:6]] = np.inf
    chans[ys[6:], xs[6:]] = -np.inf
    if image.ndim == 3:
        chans[..., 2] = np.inf  # a channel with no finite value: +inf has no finite max to go to
    written = image.copy()
    if not with_default:
        del aovs["default"]
    path = exr.write_aovs(tmp_path / "broken-00004spp.exr", aovs)
    with caplog.at_level(logging.WARNING, logger="kpcn"):
        back = exr.read_aovs(path)

    # NaN -> 0, +inf -> the channel's largest finite value, -inf -> its smallest (0 without finite values)
    expected = (written[..., None] if written.ndim == 2 else written).copy()
    for c in range(expected.shape[-1]):
        ch = expected[..., c]
        finite = ch[np.isfinite(ch)]
        hi, lo = (finite.max(), finite.min()) if finite.size else (0.0, 0.0)
        expected[..., c] = np.where(np.isnan(ch), 0.0, np.where(np.isposinf(ch), hi, np.where(np.isneginf(ch), lo, ch)))
    np.testing.assert_array_equal(back[layer], expected.reshape(written.shape))
    if not with_default:
        derived = back["diffuse"].astype(np.float64) + back["specular"]
        np.testing.assert_array_equal(back["default"], np.clip(derived, -F32_MAX, F32_MAX).astype(np.float32))
    assert all(np.isfinite(v).all() for v in back.values())
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1 and f"{layer}: {int((~np.isfinite(written)).sum())}" in messages[0]

    assert_features_match_reference(back)
    assert_variance_pdf_matches(back, 4)


def test_variance_pdf_keeps_relative_accuracy_beside_a_1e20_variance_firefly():
    # an integral image loses every window whose corner sums include the firefly: these came out 0
    aovs = random_aovs(*SIZE, seed=5)
    aovs["colorVariance"][5, 7] = 1e20
    importance = sampling.variance_importance(aovs)
    pdf = sampling.patch_pdf(importance, PATCH, uniform_mix=0.0)
    want = reference_pdf(importance, PATCH, 0.0)
    assert (want > 0).all()
    assert_pdf_is_a_distribution(pdf, want)


def test_patch_pdf_of_huge_finite_importance_follows_it_instead_of_falling_back_to_uniform():
    importance = np.full((6, 6), 1e307)
    importance[0, 0] = 1e308  # window sums of these overflow float64
    pdf = sampling.patch_pdf(importance, 3, uniform_mix=0.0)
    # analytic: the corner window holds 1e308 + 8e307 = 18e307, the other 15 hold 9e307
    np.testing.assert_allclose(pdf[0, 0], 18 / (18 + 15 * 9), rtol=1e-14)
    np.testing.assert_allclose(np.delete(pdf.ravel(), 0), 9 / (18 + 15 * 9), rtol=1e-14)


def test_positions_of_tiny_probability_are_drawn_before_zero_probability_ones():
    # exponential keys -log(u) / p overflow to inf for p = 1e-310, the key of a zero-probability position
    pdf = np.zeros((2, 4))
    pdf[0, 0] = 1.0 - 1e-310
    pdf[1, 3] = 1e-310
    for seed in range(20):
        pos = sampling.draw_positions(pdf, 2, np.random.default_rng(seed))
        assert {tuple(p) for p in pos} == {(0, 0), (1, 3)}


# ---------------------------------------------------------------- each hard case: shards, training, denoising


@dataclass
class HardSet:
    renders: Path
    shard_config: shards.ShardConfig
    runs: dict
    denoisers: dict  # arch -> (tiled, untiled)

    def noisy(self, case: str) -> dict:
        return exr.read_aovs(self.renders / exr.render_filename(case, 4))

    def patches(self, case: str) -> dict[str, np.ndarray]:
        """Every shard dataset restricted to the patches cut from the case's noisy render."""
        sset = shards.ShardSet(self.shard_config.set_dir)
        manifest = sset.complete_manifest()
        ids = [i for i, s in enumerate(manifest["sources"]) if s["scene"] == case and s["role"] == "input"]
        parts: dict[str, list] = {}
        for entry in sset.verified_shards("train", manifest):
            with shards.open_shard(entry.path) as f:
                rows = np.flatnonzero(np.isin(f["source"][:], ids))
                read = shards.read_patches(f, list(shards.VIEWS), rows)  # the features recomputed
                for name in ("position", "pdf"):
                    read[name] = f[name][:][rows]
            for name, data in read.items():
                parts.setdefault(name, []).append(data)
        return {name: np.concatenate(p) for name, p in parts.items()}


# kpal trains with a batch of one: batch normalisation over a single patch
ARCH_BATCH = {"kpcn": 4, "dpcn": 4, "kpal": 1, "unet": 4}
# one residual block (3 convolutions): a receptive field of 7 pixels, within the 8-pixel patches (train refuses more)
# the unet in 8x8 patches: 1x1 convolutions around one 2x2 pooling, so its field is 3x3 (pad, pool and upsample
# still meet every extreme value)
ARCH_MODEL = {"kpcn": TINY, "dpcn": TINY, "kpal": {**TINY, "depth": 1},
              "unet": {**TINY, "depth": 1, "levels": 2, "conv_size": 1}}
PATCHES_PER_IMAGE = 2


@pytest.fixture(scope="module")
def hard_set(tmp_path_factory):
    """One shard set with a scene per hard case, and one tiny run per architecture trained on it: one pass
    over every patch."""
    root = tmp_path_factory.mktemp("hard")
    renders = root / "renders" / "hard"
    for case, spec in HARD_CASES.items():
        spec.write(renders, case, SEEDS[case])
    cfg = shards.ShardConfig(set_name="hard", render_root=str(root / "renders"), out_root=str(root / "shards"),
                             patch_size=PATCH, patches_per_image=PATCHES_PER_IMAGE, patches_per_shard=8,
                             val_fraction=0.0, seed=1)
    shards.build_shards(cfg, progress=False)
    runs, denoisers = {}, {}
    for arch, batch in ARCH_BATCH.items():
        steps = PATCHES_PER_IMAGE * len(HARD_CASES) // batch
        tc = TrainConfig.from_preset("cpu", set_name="hard", shards_root=cfg.out_root,
                                     model={"arch": arch, **ARCH_MODEL[arch]},
                                     steps=steps, steps_per_epoch=steps, batch_size=batch, val_batches=1)
        runs[arch] = train(tc, root / "runs" / arch, verbose=0)
        denoisers[arch] = (Denoiser.from_run(Run(runs[arch]), InferenceSettings(tile=8)),
                           Denoiser.from_run(Run(runs[arch]), InferenceSettings(tile=4096)))
    return HardSet(renders, cfg, runs, denoisers)


@pytest.mark.parametrize("case", list(HARD_CASES))
def test_hard_case_shard_patches_are_finite_and_equal_float64_features(hard_set, case):
    got = hard_set.patches(case)
    assert len(got["position"]) == PATCHES_PER_IMAGE
    for name, data in got.items():
        assert np.isfinite(data).all(), name
    noisy = hard_set.noisy(case)
    reference = exr.read_aovs(hard_set.renders / exr.render_filename(case, 64), variances=False)
    pdf = sampling.patch_pdf(sampling.variance_importance(noisy), PATCH, hard_set.shard_config.uniform_mix)
    want_pdf = reference_pdf(reference_importance(noisy), PATCH, hard_set.shard_config.uniform_mix)
    for i, (y, x) in enumerate(got["position"]):
        window = (slice(y, y + PATCH), slice(x, x + PATCH))
        for branch in features.BRANCHES:
            feats = got[f"{branch}/features"][i]
            assert_features_in_documented_ranges(feats)
            assert_read_features_close(feats, reference_features(noisy, branch)[window], branch)
            albedo = (noisy["albedo"], reference["albedo"]) if branch == "diffuse" else (None, None)
            for kind, render, a in (("noisy", noisy, albedo[0]), ("reference", reference, albedo[1])):
                want = reference_log_colour(render[branch], a)[window]
                # the noisy colour is read from float16 (2**-10 in the last step below the range's top), the
                # reference, a target, is float32
                rtol, atol = (2.0**-10, 2.0**-25) if kind == "noisy" else (1e-6, 1e-7)
                np.testing.assert_allclose(got[f"{branch}/{kind}"][i], want, rtol=rtol, atol=atol)
        np.testing.assert_allclose(got["albedo"][i], np.clip(noisy["albedo"][window], 0.0, 1.0), rtol=2.0**-11,
                                   atol=2.0**-25)
        np.testing.assert_array_equal(got["noisy"][i], noisy["default"][window])
        np.testing.assert_array_equal(got["reference"][i], reference["default"][window])
        assert got["pdf"][i] == pytest.approx(want_pdf[y, x], rel=1e-12) and got["pdf"][i] == pdf[y, x] > 0


@pytest.mark.parametrize("arch", list(ARCH_BATCH))
def test_training_on_every_hard_case_logs_finite_losses_and_keeps_weights_finite(hard_set, arch):
    run = hard_set.runs[arch]
    rows = (run / "log.csv").read_text().splitlines()  # one epoch per branch
    assert rows[0].startswith("epoch,loss") and len(rows) == 3
    assert all(np.isfinite(float(row.split(",")[1])) for row in rows[1:])
    for branch in features.BRANCHES:
        model = load_model(run / f"{branch}.keras", compile=False)
        for w in model.weights:
            value = to_np(w.value)
            assert np.isfinite(value).all(), w.path
            if "moving_variance" in w.path:
                assert value.min() >= 0, w.path
        assert any(np.any(to_np(w.value)) for w in model.weights if "kernel_logits" in w.path or "correction" in w.path)


@pytest.mark.parametrize("arch", list(ARCH_BATCH))
@pytest.mark.parametrize("case", list(HARD_CASES))
def test_hard_case_loss_and_gradients_stay_finite(hard_set, case, arch):
    got = hard_set.patches(case)
    for branch in features.BRANCHES:
        model = load_model(hard_set.runs[arch] / f"{branch}.keras", compile=False)
        out = to_np(finite_loss_and_gradients(model, got[f"{branch}/features"], got[f"{branch}/reference"],
                                              got[f"{branch}/noisy"]))
        assert out.min() >= 0 and out.max() <= LOG_COLOUR_MAX


@pytest.mark.parametrize("arch", list(ARCH_BATCH))
@pytest.mark.parametrize("case", list(HARD_CASES))
def test_hard_case_tiled_denoise_is_finite_non_negative_and_equals_untiled(hard_set, case, arch):
    tiled, whole = hard_set.denoisers[arch]
    noisy = hard_set.noisy(case)
    logs = {}
    for branch in features.BRANCHES:
        logs[branch] = tiled.run_branch(branch, noisy)
        assert np.isfinite(logs[branch]).all()
        assert logs[branch].min() >= 0 and logs[branch].max() <= LOG_COLOUR_MAX
        np.testing.assert_allclose(logs[branch], whole.run_branch(branch, noisy), rtol=1e-5, atol=2e-5)
    out = tiled(noisy)
    for name, image in out.items():
        assert image.dtype == np.float32 and np.isfinite(image).all() and image.min() >= 0, name
    # the branch inverses of the features table, in float64, clamped to the float32 range; the albedo prefiltered
    albedo = prefilter(noisy["albedo"], noisy["albedoVariance"])
    assert np.isfinite(albedo).all() and albedo.min() >= 0 and albedo.max() <= 1
    diffuse = np.expm1(logs["diffuse"].astype(np.float64)) * (albedo + ALBEDO_EPS)
    specular = np.expm1(logs["specular"].astype(np.float64))
    for name, want in (("diffuse", diffuse), ("specular", specular), ("default", diffuse + specular)):
        # (atol: a float32 output can underflow where the float64 value is below the smallest subnormal)
        np.testing.assert_allclose(out[name], np.minimum(want, F32_MAX), rtol=1e-6, atol=F32_TINY, err_msg=name)


@pytest.mark.parametrize("arch", ARCHS)
def test_randomised_networks_keep_denoised_extreme_renders_finite_and_in_range(hard_set, arch):
    denoiser = Denoiser.from_run(Run(hard_set.runs[arch]), InferenceSettings(tile=8))
    for i, model in enumerate(denoiser.models.values()):
        randomise(model, seed=10 + i, scale=1.0)  # logits and corrections of 1e3 and more
    clamped = False
    # dpcn clamps to the colour range; a kernel output is a convex combination of colours within it, but in
    # float32: softmax weights summing to 1 within rounding put a window of LOG_COLOUR_MAX up to 2 ulps above
    # it (KernelApply, any arch: the kpcn's saturated logits here happen to give exact one-hot weights; the
    # unet's 1x1 trunk gives mixed ones). Downstream, exr.to_float32 keeps the linear colour finite.
    top = LOG_COLOUR_MAX if arch == "dpcn" else float(np.float32(LOG_COLOUR_MAX)) * (1 + 4 * F32_EPS)
    for case in ("float32-max", "firefly-1e6", "nan-inf-every-layer", "black"):
        noisy = hard_set.noisy(case)
        for branch in features.BRANCHES:
            log = denoiser.run_branch(branch, noisy)
            assert np.isfinite(log).all() and log.min() >= 0 and log.max() <= top, (case, branch)
            clamped |= bool((log == np.float32(LOG_COLOUR_MAX)).any())
        out = denoiser(noisy)
        for name, image in out.items():
            assert np.isfinite(image).all() and image.min() >= 0, (case, name)
    if arch == "dpcn":
        assert clamped  # a correction pushed the colour past LOG_COLOUR_MAX: the clamp is exercised


# ---------------------------------------------------------------- image sizes


@pytest.mark.slow
@pytest.mark.parametrize("size", [(1, 1), (1, 9), (9, 1), (7, 13)], ids=lambda s: f"{s[0]}x{s[1]}")
def test_odd_and_tiny_renders_go_through_features_shards_training_and_tiled_denoise(tmp_path, size):
    h, w = size
    smallest = shards.PATCH_SIZE.low  # a render with a side below it is refused by kpcn shards: trained on one
    patch = min(h, w, 5)
    renders = tmp_path / "renders" / "odd"
    renders.mkdir(parents=True)
    noisy = random_aovs(h, w, seed=7)
    noisy["diffuse"][0, 0] = 1e6  # and a firefly
    exr.write_aovs(renders / exr.render_filename("odd-000", 4), noisy)
    exr.write_aovs(renders / exr.render_filename("odd-000", 64), random_aovs(h, w, seed=8, variances=False))
    back = exr.read_aovs(renders / exr.render_filename("odd-000", 4))
    assert_features_match_reference(back)
    assert_variance_pdf_matches(back, patch)

    if patch < smallest:  # of the smallest size that kpcn shards cuts: the tiny render is denoised below
        with pytest.raises(KpcnError, match=rf"is {w}x{h}, smaller than a {smallest}x{smallest} patch; the smallest"):
            shards.build_shards(shards.ShardConfig(set_name="odd", render_root=str(tmp_path / "renders"),
                                                   out_root=str(tmp_path / "shards"), patch_size=smallest),
                                progress=False)
        h, w, patch = max(h, smallest), max(w, smallest), smallest
        (tmp_path / "renders" / "odd" / exr.render_filename("odd-000", 4)).unlink()
        exr.write_aovs(renders / exr.render_filename("odd-000", 4), random_aovs(h, w, seed=7))
        exr.write_aovs(renders / exr.render_filename("odd-000", 64), random_aovs(h, w, seed=8, variances=False))
    per_image = min(2, (h - patch + 1) * (w - patch + 1))
    cfg = shards.ShardConfig(set_name="odd", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                             patch_size=patch, patches_per_image=per_image, patches_per_shard=4, val_fraction=0.0)
    shards.build_shards(cfg, progress=False)
    for path in shards.shard_paths(cfg.set_dir, "train"):
        with shards.open_shard(path) as f:
            got = shards.read_patches(f, [f"{b}/features" for b in features.BRANCHES], range(len(f["source"])))
        for branch in features.BRANCHES:
            assert_features_in_documented_ranges(got[f"{branch}/features"])
    # TINY's receptive field is 5 pixels: one convolution fewer on 3-pixel patches (train refuses more)
    model = TINY if patch >= 5 else {**TINY, "depth": 1}
    tc = TrainConfig.from_preset("cpu", set_name="odd", shards_root=cfg.out_root, model=model, steps=1,
                                 steps_per_epoch=1, batch_size=per_image, val_batches=1)
    run = train(tc, tmp_path / "run", verbose=0)
    rows = (run / "log.csv").read_text().splitlines()[1:]
    assert len(rows) == len(features.BRANCHES) and all(np.isfinite(float(r.split(",")[1])) for r in rows)

    # tiles smaller than the margin
    tiled = Denoiser.from_run(Run(run), InferenceSettings(tile=2))
    whole = Denoiser.from_run(Run(run), InferenceSettings(tile=4096))
    for branch in features.BRANCHES:
        np.testing.assert_allclose(tiled.run_branch(branch, back), whole.run_branch(branch, back), rtol=1e-5, atol=1e-6)
    out = tiled(back)
    for name, image in out.items():
        assert image.shape[:2] == size and np.isfinite(image).all() and image.min() >= 0, name


def test_render_smaller_than_a_patch_is_refused_before_anything_is_written(tmp_path):
    renders = tmp_path / "renders" / "small"
    renders.mkdir(parents=True)
    exr.write_aovs(renders / exr.render_filename("small-000", 4), random_aovs(5, 7, seed=1))
    exr.write_aovs(renders / exr.render_filename("small-000", 64), random_aovs(5, 7, seed=2, variances=False))
    cfg = shards.ShardConfig(set_name="small", render_root=str(tmp_path / "renders"),
                             out_root=str(tmp_path / "shards"), patch_size=PATCH, patches_per_image=1)
    with pytest.raises(KpcnError,
                       match=r"small-000-00004spp\.exr is 7x5, smaller than a 8x8 patch; use --patch-size 5"):
        shards.build_shards(cfg, progress=False)
    assert not list((tmp_path / "shards").rglob("*.h5")) and not list((tmp_path / "shards").rglob("manifest.json"))
    with pytest.raises(ValueError, match=r"\[1, 5\] for a 7x5 image, got 8"):
        sampling.patch_pdf(np.ones((5, 7)), PATCH)


def test_a_shard_set_without_a_uniform_share_is_refused_naming_the_option(tmp_path):
    # with uniform_mix = 0 an image without variance has no position of non-zero probability, and the
    # plan could not check patches_per_image against it before writing
    with pytest.raises(OptionError, match=r"uniform_mix must be a number in \(0, 1\], got 0.0"):
        shards.ShardConfig(set_name="flat", uniform_mix=0.0)
