"""Hard numerical cases end to end, and property-based tests of the numerics (issue 5).

Every hard case is a synthetic render (``helpers.random_aovs`` with the case applied) that goes through
the whole pipeline: written with ``prep.exr.write_aovs`` and read back (the repair rule), the features of
both branches (finite, inside the ranges of the table in ``prep/features.py``, equal to a float64 numpy
evaluation of that table), the variance PDF (a distribution equal to explicit window sums), shards, real
training steps of the three architectures (losses and gradients finite) and tiled denoising (finite,
non-negative, equal to an untiled run). Figures are checked against independent float64 references;
the property-based tests (hypothesis) cover the feature transforms, the PDF and the kernel application
over random shapes and value ranges.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers import random_aovs, randomise, reference_features
from kpcn_keras.denoise import Denoiser
from kpcn_keras.layers import KernelApply, softmax_kernels
from kpcn_keras.losses import SMAPE, SMAPE_EPS, AsymmetricSMAPE, asymmetric_smape, smape
from kpcn_keras.models import ARCHS, ModelConfig, build_branch_model
from kpcn_keras.run import load_model
from kpcn_keras.train import TrainConfig, train
from prep import exr, features, sampling, shards
from prep.errors import KpcnError, OptionError
from prep.features import ALBEDO_EPS, LOG_COLOUR_MAX, NUM_FEATURES, REL_EPS
from prep.sampling import IMPORTANCE_EPS

import keras  # noqa: E402  (after kpcn_keras, which fixes the torch backend)
import torch  # noqa: E402

F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).smallest_subnormal)
F32_EPS = float(np.finfo(np.float32).eps)
HALF_MAX = float(np.finfo(np.float16).max)

# The largest relative variance a float32 render can give: a depth variance of float32 max at a miss
# (d = 0) in an image whose largest depth is the smallest subnormal (depth scale 1 / F32_TINY).
RELVAR_BOUND = float(np.log1p(F32_MAX / F32_TINY**2 / REL_EPS))

# (first channel, stop, lowest, highest): the table of prep/features.py, each bound derived from the
# module's constants or from the clip range its formula names.
FEATURE_RANGES = [
    (0, 3, 0.0, LOG_COLOUR_MAX),  # colour
    (3, 6, -LOG_COLOUR_MAX, LOG_COLOUR_MAX),  # dx colour
    (6, 9, -2.0, 2.0),  # dx normal: normal clipped to [-1, 1]
    (9, 12, -1.0, 1.0),  # dx albedo: albedo clipped to [0, 1]
    (12, 13, -1.0, 1.0),  # dx depth: depth scaled to [0, 1]
    (13, 16, -LOG_COLOUR_MAX, LOG_COLOUR_MAX),  # dy of the same
    (16, 19, -2.0, 2.0),
    (19, 22, -1.0, 1.0),
    (22, 23, -1.0, 1.0),
    (23, 27, 0.0, RELVAR_BOUND),  # relative variances
]

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


# ---------------------------------------------------------------- float64 references


def reference_log_colour(colour, albedo=None) -> np.ndarray:
    """log(1 + max(x, 0)), x = colour / (clip(albedo, 0, 1) + ALBEDO_EPS) for the diffuse branch, in float64."""
    x = np.asarray(colour, np.float64)
    if albedo is not None:
        x = x / (np.clip(np.asarray(albedo, np.float64), 0.0, 1.0) + ALBEDO_EPS)
    return np.log1p(np.maximum(x, 0.0))


def reference_importance(aovs: dict) -> np.ndarray:
    mean = np.maximum(aovs["default"].astype(np.float64), 0.0).sum(axis=-1) / 3.0
    colour = np.maximum(aovs["colorVariance"].astype(np.float64), 0.0) / (mean**2 + IMPORTANCE_EPS)
    return colour + np.maximum(aovs["normalVariance"].astype(np.float64), 0.0)


def reference_pdf(importance, p: int, mix: float) -> np.ndarray:
    """Explicit window sums (exactly rounded, math.fsum) of the finite, non-negative importance, normalised,
    mixed with the uniform PDF; uniform when nothing is left."""
    imp = np.asarray(importance, np.float64)
    imp = np.where(np.isfinite(imp), np.maximum(imp, 0.0), 0.0)
    if imp.max() > 0:
        imp = np.ldexp(imp, -np.frexp(imp.max())[1])  # an exact power-of-two scale, so that fsum cannot overflow
    h, w = imp.shape
    sums = np.array([[math.fsum(imp[y : y + p, x : x + p].ravel()) for x in range(w - p + 1)]
                     for y in range(h - p + 1)])
    total = math.fsum(sums.ravel())
    uniform = np.full(sums.shape, 1.0 / sums.size)
    if total <= 0:
        return uniform
    return mix * uniform + (1.0 - mix) * (sums / total)


def reference_kernel_apply(colour, logits, k: int):
    """float64: softmax with max subtraction, edge-replicated k x k windows, weighted sum. Returns the output
    (B, H, W, C) and the windows (B, H, W, k*k, C)."""
    c = np.asarray(colour, np.float64)
    z = np.asarray(logits, np.float64)
    z = z - z.max(axis=-1, keepdims=True)
    weights = np.exp(z)
    weights /= weights.sum(axis=-1, keepdims=True)
    r = k // 2
    h, w = c.shape[1:3]
    padded = np.pad(c, ((0, 0), (r, r), (r, r), (0, 0)), mode="edge")
    windows = np.stack([padded[:, i : i + h, j : j + w] for i in range(k) for j in range(k)], axis=3)
    return np.einsum("bhwt,bhwtc->bhwc", weights, windows), windows


# ---------------------------------------------------------------- checks


def assert_features_in_documented_ranges(feats: np.ndarray) -> None:
    assert feats.shape[-1] == NUM_FEATURES
    assert np.isfinite(feats).all()
    f = feats.astype(np.float64)
    for first, stop, lo, hi in FEATURE_RANGES:
        block = f[..., first:stop]
        assert block.min() >= lo and block.max() <= hi, (
            f"channels {features.FEATURE_NAMES[first:stop]}: [{block.min()}, {block.max()}] outside [{lo}, {hi}]")


def assert_features_match_reference(aovs: dict) -> None:
    for branch in features.BRANCHES:
        got = features.branch_features(aovs, branch)
        assert got.dtype == np.float32
        assert_features_in_documented_ranges(got)
        np.testing.assert_allclose(got, reference_features(aovs, branch), rtol=1e-6, atol=1e-6, err_msg=branch)


def assert_pdf_is_a_distribution(pdf: np.ndarray, want: np.ndarray) -> None:
    assert pdf.shape == want.shape and pdf.dtype == np.float64
    assert np.isfinite(pdf).all() and pdf.min() >= 0.0
    assert abs(math.fsum(pdf.ravel()) - 1.0) <= 1e-12
    # direct sums of non-negative terms: relative accuracy, even beside a pixel 1e20 times brighter
    np.testing.assert_allclose(pdf, want, rtol=1e-12, atol=1e-300)


def assert_variance_pdf_matches(aovs: dict, patch: int, mix: float = 0.1) -> np.ndarray:
    importance = sampling.variance_importance(aovs)
    np.testing.assert_allclose(importance, reference_importance(aovs), rtol=1e-12, atol=0)
    pdf = sampling.patch_pdf(importance, patch, mix)
    assert_pdf_is_a_distribution(pdf, reference_pdf(importance, patch, mix))
    return pdf


def finite_loss_and_gradients(model: keras.Model, x, gt, noisy) -> torch.Tensor:
    """SMAPE and asymmetric SMAPE of ``model`` in training mode, with their gradients; asserts all finite.
    Returns the output."""
    out = model(torch.as_tensor(x), training=True)
    gt_t = torch.as_tensor(gt)
    losses = {
        "smape": SMAPE()(gt_t, out),
        "asymmetric": AsymmetricSMAPE(2.0)(torch.as_tensor(np.concatenate([gt, noisy], axis=-1)), out),
    }
    variables = [w.value for w in model.trainable_weights]
    for name, loss in losses.items():
        assert torch.isfinite(loss), (name, loss)
        grads = torch.autograd.grad(loss, variables, retain_graph=True, allow_unused=True)
        for w, g in zip(model.trainable_weights, grads):
            assert g is None or torch.isfinite(g).all(), f"{name}: non-finite gradient of {w.path}"
    return out


def extreme_features(shape, seed: int) -> np.ndarray:
    """Features with every channel at the low end, the high end of its documented range, or 0."""
    rng = np.random.default_rng(seed)
    x = np.empty(tuple(shape) + (NUM_FEATURES,), np.float32)
    for first, stop, lo, hi in FEATURE_RANGES:
        x[..., first:stop] = rng.choice([lo, hi, 0.0], size=tuple(shape) + (stop - first,))
    return x


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
            with h5py.File(entry.path, "r") as f:
                rows = np.isin(f["source"][:], ids)
                for name in list(shards.PATCH_DATASETS) + ["position", "pdf"]:
                    parts.setdefault(name, []).append(f[name][:][rows])
        return {name: np.concatenate(p) for name, p in parts.items()}


# kpal trains with a batch of one: batch normalisation over a single patch
ARCH_BATCH = {"kpcn": 4, "dpcn": 4, "kpal": 1}
# one residual block (3 convolutions): a receptive field of 7 pixels, within the 8-pixel patches (train refuses more)
ARCH_MODEL = {"kpcn": TINY, "dpcn": TINY, "kpal": {**TINY, "depth": 1}}
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
        tc = TrainConfig.from_preset("cpu", set_name="hard", shards_root=cfg.out_root, model={"arch": arch, **ARCH_MODEL[arch]},
                                     steps=steps, steps_per_epoch=steps, batch_size=batch, val_batches=1)
        runs[arch] = train(tc, root / "runs" / arch, verbose=0)
        denoisers[arch] = (Denoiser(runs[arch], tile=8), Denoiser(runs[arch], tile=4096))
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
            np.testing.assert_allclose(feats, reference_features(noisy, branch)[window], rtol=1e-6, atol=1e-6)
            albedo = (noisy["albedo"], reference["albedo"]) if branch == "diffuse" else (None, None)
            for kind, render, a in (("noisy", noisy, albedo[0]), ("reference", reference, albedo[1])):
                want = reference_log_colour(render[branch], a)[window]
                np.testing.assert_allclose(got[f"{branch}/{kind}"][i], want, rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(got["albedo"][i], noisy["albedo"][window])
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
    # the branch inverses of the features table, in float64, clamped to the float32 range
    diffuse = np.expm1(logs["diffuse"].astype(np.float64)) * (np.clip(noisy["albedo"], 0, 1) + ALBEDO_EPS)
    specular = np.expm1(logs["specular"].astype(np.float64))
    for name, want in (("diffuse", diffuse), ("specular", specular), ("default", diffuse + specular)):
        # (atol: a float32 output can underflow where the float64 value is below the smallest subnormal)
        np.testing.assert_allclose(out[name], np.minimum(want, F32_MAX), rtol=1e-6, atol=F32_TINY, err_msg=name)


@pytest.mark.parametrize("arch", ARCHS)
def test_randomised_networks_keep_denoised_extreme_renders_finite_and_in_range(hard_set, arch):
    denoiser = Denoiser(hard_set.runs[arch], tile=8)
    for i, model in enumerate(denoiser.models.values()):
        randomise(model, seed=10 + i, scale=1.0)  # logits and corrections of 1e3 and more
    clamped = False
    for case in ("float32-max", "firefly-1e6", "nan-inf-every-layer", "black"):
        noisy = hard_set.noisy(case)
        for branch in features.BRANCHES:
            log = denoiser.run_branch(branch, noisy)
            assert np.isfinite(log).all() and log.min() >= 0 and log.max() <= LOG_COLOUR_MAX, (case, branch)
            clamped |= bool((log == np.float32(LOG_COLOUR_MAX)).any())
        out = denoiser(noisy)
        for name, image in out.items():
            assert np.isfinite(image).all() and image.min() >= 0, (case, name)
    if arch == "dpcn":
        assert clamped  # a correction pushed the colour past LOG_COLOUR_MAX: the clamp is exercised


# ---------------------------------------------------------------- image sizes


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
                                                   out_root=str(tmp_path / "shards"), patch_size=smallest), progress=False)
        h, w, patch = max(h, smallest), max(w, smallest), smallest
        (tmp_path / "renders" / "odd" / exr.render_filename("odd-000", 4)).unlink()
        exr.write_aovs(renders / exr.render_filename("odd-000", 4), random_aovs(h, w, seed=7))
        exr.write_aovs(renders / exr.render_filename("odd-000", 64), random_aovs(h, w, seed=8, variances=False))
    per_image = min(2, (h - patch + 1) * (w - patch + 1))
    cfg = shards.ShardConfig(set_name="odd", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                             patch_size=patch, patches_per_image=per_image, patches_per_shard=4, val_fraction=0.0)
    shards.build_shards(cfg, progress=False)
    for path in shards.shard_paths(cfg.set_dir, "train"):
        with h5py.File(path, "r") as f:
            for branch in features.BRANCHES:
                assert_features_in_documented_ranges(f[f"{branch}/features"][:])
    # TINY's receptive field is 5 pixels: one convolution fewer on 3-pixel patches (train refuses more)
    model = TINY if patch >= 5 else {**TINY, "depth": 1}
    tc = TrainConfig.from_preset("cpu", set_name="odd", shards_root=cfg.out_root, model=model, steps=1,
                                 steps_per_epoch=1, batch_size=per_image, val_batches=1)
    run = train(tc, tmp_path / "run", verbose=0)
    rows = (run / "log.csv").read_text().splitlines()[1:]
    assert len(rows) == len(features.BRANCHES) and all(np.isfinite(float(r.split(",")[1])) for r in rows)

    tiled, whole = Denoiser(run, tile=2), Denoiser(run, tile=4096)  # tiles smaller than the margin
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
    with pytest.raises(KpcnError, match=r"small-000-00004spp\.exr is 7x5, smaller than a 8x8 patch; use --patch-size 5"):
        shards.build_shards(cfg, progress=False)
    assert not list((tmp_path / "shards").rglob("*.h5")) and not list((tmp_path / "shards").rglob("manifest.json"))
    with pytest.raises(ValueError, match=r"\[1, 5\] for a 7x5 image, got 8"):
        sampling.patch_pdf(np.ones((5, 7)), PATCH)


def test_a_shard_set_without_a_uniform_share_is_refused_naming_the_option(tmp_path):
    # with uniform_mix = 0 an image without variance has no position of non-zero probability, and the
    # plan could not check patches_per_image against it before writing
    with pytest.raises(OptionError, match=r"uniform_mix must be a number in \(0, 1\], got 0.0"):
        shards.ShardConfig(set_name="flat", uniform_mix=0.0)


# ---------------------------------------------------------------- kernels, losses, batch norm, DPCN


@pytest.mark.parametrize("colour_level", [0.0, 1.0, LOG_COLOUR_MAX])
def test_softmax_kernels_at_logits_of_plus_minus_1e4_are_exact_averages_with_finite_gradients(colour_level):
    k = 3
    rng = np.random.default_rng(6)
    signs = rng.choice([-1.0, 1.0], size=(2, 5, 4, k * k))
    signs[0, 0, 0] = 1.0  # every tap tied at the maximum
    signs[0, 0, 1] = -1.0  # every tap tied at the minimum
    colour = (rng.uniform(0, 1, (2, 5, 4, 3)) * colour_level).astype(np.float32)
    logits_np = (signs * 1e4).astype(np.float32)
    # analytic: exp(-2e4) is 0, so the weights are 1/m on the m taps at the maximum
    top = logits_np == logits_np.max(axis=-1, keepdims=True)
    want_weights = top / top.sum(axis=-1, keepdims=True)
    np.testing.assert_allclose(to_np(softmax_kernels(logits_np)), want_weights, rtol=1e-6, atol=0)
    want, _ = reference_kernel_apply(colour, logits_np, k)
    colour_t = torch.tensor(colour, requires_grad=True)
    logits = torch.tensor(logits_np, requires_grad=True)
    out = KernelApply(k)([colour_t, logits])
    np.testing.assert_allclose(to_np(out), want, rtol=1e-6, atol=1e-6 * max(colour_level, 1.0))
    smape(torch.zeros_like(out), out).backward()
    assert torch.isfinite(colour_t.grad).all() and torch.isfinite(logits.grad).all()


def test_smape_at_zero_is_zero_with_finite_bounded_gradient():
    out = torch.zeros((2, 3, 3, 3), requires_grad=True)
    gt = torch.zeros((2, 3, 3, 3))
    for loss in (smape(gt, out), SMAPE()(gt, out)):
        assert float(loss.detach()) == 0.0
        (grad,) = torch.autograd.grad(loss, out)
        # one-sided derivatives at out = gt = 0 are +-1 / SMAPE_EPS per element (over the mean's count)
        assert torch.isfinite(grad).all() and float(grad.abs().max()) <= 1.0 / SMAPE_EPS / out.numel()


@pytest.mark.parametrize("gt_level", [0.0, 1e-6, 1.0, LOG_COLOUR_MAX])
@pytest.mark.parametrize("slope", [1.0, 2.0, 8.0])
def test_asymmetric_smape_at_out_equal_gt_is_zero_with_finite_bounded_gradient(gt_level, slope):
    rng = np.random.default_rng(8)
    gt = torch.tensor(rng.uniform(0, 1, (2, 4, 4, 3)) * gt_level, dtype=torch.float32)
    noisy = gt + torch.tensor(rng.normal(size=(2, 4, 4, 3)), dtype=torch.float32)
    out = gt.clone().requires_grad_(True)
    for loss in (asymmetric_smape(noisy, gt, out, slope), AsymmetricSMAPE(slope)(torch.cat([gt, noisy], -1), out)):
        assert float(loss.detach()) == 0.0
        (grad,) = torch.autograd.grad(loss, out)
        # one-sided derivative bound at out = gt: slope / (2|gt| + SMAPE_EPS), over the mean's count
        bound = slope / (2 * gt.abs() + SMAPE_EPS) / out.numel()
        assert torch.isfinite(grad).all() and bool((grad.abs() <= bound * (1 + 1e-6)).all())


@pytest.mark.parametrize("out_value,gt_value", [(0.0, LOG_COLOUR_MAX), (LOG_COLOUR_MAX, 0.0), (F32_MAX, 0.0),
                                                (F32_MAX, F32_MAX), (F32_TINY, 0.0), (0.0, F32_TINY)])
def test_smape_over_the_colour_range_matches_float64_with_finite_gradient(out_value, gt_value):
    out = torch.tensor([out_value], dtype=torch.float32, requires_grad=True)
    gt = torch.tensor([gt_value], dtype=torch.float32)
    loss = smape(gt, out)
    o, g = float(np.float32(out_value)), float(np.float32(gt_value))
    want = abs(o - g) / (abs(o) + abs(g) + SMAPE_EPS)
    value = float(loss.detach())
    assert value == pytest.approx(want, rel=1e-6, abs=1e-12) and 0.0 <= value <= 1.0
    loss.backward()
    assert torch.isfinite(out.grad).all()


@pytest.mark.parametrize("content", ["constant", "extreme"])
@pytest.mark.parametrize("size", [1, 6])
def test_batch_norm_with_a_batch_of_one_keeps_loss_gradients_and_statistics_finite(size, content):
    keras.utils.set_random_seed(0)
    model = build_branch_model(ModelConfig(arch="kpal", **TINY))
    assert any(isinstance(layer, keras.layers.BatchNormalization) for layer in model.layers)
    randomise(model, seed=1, scale=0.5)
    if content == "constant":  # zero batch variance in every channel
        x = np.zeros((1, size, size, NUM_FEATURES), np.float32)
        x[..., :3] = 1.0
    else:
        x = extreme_features((1, size, size), seed=2)
    gt = np.full((1, size, size, 3), 0.5, np.float32)
    out = to_np(finite_loss_and_gradients(model, x, gt, x[..., :3]))
    assert out.min() >= 0 and out.max() <= LOG_COLOUR_MAX
    model.compile(optimizer=keras.optimizers.Adam(1e-3, clipnorm=1.0), loss=SMAPE())
    for _ in range(2):
        assert np.isfinite(float(model.train_on_batch(x, gt)))
    for w in model.weights:
        value = to_np(w.value)
        assert np.isfinite(value).all(), w.path
        if "moving_variance" in w.path:
            assert value.min() >= 0, w.path
    assert np.isfinite(to_np(model(x, training=False))).all()


def test_dpcn_output_is_clamped_to_the_log_colour_range_at_extreme_inputs():
    model = build_branch_model(ModelConfig(arch="dpcn", **TINY))
    x = extreme_features((2, 9, 9), seed=3)
    x[0, 0, 0, :3] = LOG_COLOUR_MAX
    # untrained: the identity on the colour, which maps back to float32 max, not to inf
    out = to_np(model(x, training=False))
    np.testing.assert_array_equal(out, x[..., :3])
    assert np.isfinite(exr.to_float32(features.diffuse_from_log(out, np.zeros_like(out)))).all()
    randomise(model, seed=4, scale=1.0)  # corrections far beyond the colour range, both ways
    out = to_np(finite_loss_and_gradients(model, x, np.zeros_like(x[..., :3]), x[..., :3]))
    assert out.min() == 0.0 and out.max() == np.float32(LOG_COLOUR_MAX)
    linear = features.diffuse_from_log(out, np.ones_like(out))  # the largest albedo multiplier
    assert np.isfinite(linear).all() and np.isfinite(exr.to_float32(linear)).all()


# ---------------------------------------------------------------- property-based

PROPERTY = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
SPECIAL_F32 = [0.0, F32_TINY, float(np.float32(1e-30)), 1.0, HALF_MAX, float(np.float32(1e20)), F32_MAX]


@st.composite
def float32_images(draw, shape, signed=True):
    """An image whose magnitudes are log-uniform over a drawn range of decades (subnormal to float32 max),
    with a few special values (0, the smallest subnormal, half max, float32 max) at drawn pixels."""
    size = int(np.prod(shape))
    kind = draw(st.sampled_from(["spread", "spread", "spread", "constant", "zero"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "zero":
        return np.zeros(shape, np.float32)
    lo = draw(st.integers(-46, 38))
    hi = draw(st.integers(lo, 39))
    magnitude = np.minimum(10.0 ** rng.uniform(lo, hi, shape if kind == "spread" else ()), F32_MAX)
    image = np.broadcast_to(magnitude, shape).copy()
    if signed and draw(st.booleans()):
        image *= rng.choice([-1.0, 1.0], shape)
    specials = draw(st.lists(st.tuples(st.integers(0, size - 1), st.sampled_from(SPECIAL_F32), st.booleans()),
                             max_size=4))
    flat = image.reshape(-1)
    for index, value, negative in specials:
        flat[index] = -value if (negative and signed) else value
    return image.astype(np.float32)


@st.composite
def renders(draw, max_side=12):
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    aovs = {name: draw(float32_images((h, w, 3))) for name in exr.RGB_LAYERS}
    aovs.update({name: draw(float32_images((h, w))) for name in exr.SCALAR_LAYERS})
    return aovs


@settings(max_examples=60, **PROPERTY)
@given(aovs=renders())
def test_features_of_any_finite_float32_render_match_float64_and_stay_in_documented_ranges(aovs):
    assert_features_match_reference(aovs)


@settings(max_examples=60, **PROPERTY)
@given(aovs=renders())
def test_colour_transform_inverses_recover_the_clamped_input_to_float32_rounding(aovs):
    # c is rounded to float32 (relative 2^-24), which expm1 turns into a relative error of at most
    # (c + 1) * 2^-24 <= (LOG_COLOUR_MAX + 1) * 2^-24; subnormal inputs keep an absolute error of ~F32_TINY
    rtol = (LOG_COLOUR_MAX + 1) * F32_EPS / 2
    albedo = aovs["albedo"]
    diffuse = features.diffuse_from_log(features.branch_colour(aovs, "diffuse"), albedo)
    specular = features.specular_from_log(features.branch_colour(aovs, "specular"))
    for got, x in ((diffuse, aovs["diffuse"]), (specular, aovs["specular"])):
        assert np.isfinite(got).all() and got.min() >= 0
        np.testing.assert_allclose(got, np.maximum(x.astype(np.float64), 0.0), rtol=rtol, atol=2 * F32_TINY)
        assert np.isfinite(exr.to_float32(got)).all()


@st.composite
def importance_maps(draw):
    h = draw(st.integers(1, 12))
    w = draw(st.integers(1, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    lo = draw(st.integers(-320, 308))
    hi = draw(st.integers(lo, 308))
    imp = np.minimum(10.0 ** rng.uniform(lo, hi, (h, w)), np.finfo(np.float64).max)
    imp[rng.uniform(size=(h, w)) < draw(st.floats(0, 1))] = 0.0
    specials = [np.nan, np.inf, -np.inf, -1.0, 0.0, 5e-324, np.finfo(np.float64).max, 1e20]
    for index, value in draw(st.lists(st.tuples(st.integers(0, h * w - 1), st.sampled_from(specials)), max_size=4)):
        imp.reshape(-1)[index] = value
    patch = draw(st.integers(1, min(h, w)))
    mix = draw(st.one_of(st.sampled_from([0.0, 0.1, 1.0]), st.floats(0, 1)))
    return imp, patch, mix


@settings(max_examples=150, **PROPERTY)
@given(case=importance_maps())
def test_patch_pdf_of_any_importance_is_a_distribution_equal_to_explicit_window_sums(case):
    importance, patch, mix = case
    pdf = sampling.patch_pdf(importance, patch, mix)
    assert_pdf_is_a_distribution(pdf, reference_pdf(importance, patch, mix))
    count = min(3, int(np.count_nonzero(pdf)))
    pos = sampling.draw_positions(pdf, count, np.random.default_rng(0))
    assert len({tuple(p) for p in pos}) == count and (pdf[pos[:, 0], pos[:, 1]] > 0).all()


@settings(max_examples=40, **PROPERTY)
@given(aovs=renders(), data=st.data())
def test_variance_pdf_of_any_finite_render_is_a_distribution_equal_to_float64_reference(aovs, data):
    h, w = aovs["depth"].shape
    patch = data.draw(st.integers(1, min(h, w)))
    assert_variance_pdf_matches(aovs, patch, data.draw(st.floats(0, 1)))


@st.composite
def kernel_inputs(draw):
    k = draw(st.sampled_from([1, 3, 5]))
    shape = (draw(st.integers(1, 2)), draw(st.integers(1, 8)), draw(st.integers(1, 8)))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    domain = draw(st.sampled_from(["log-colour", "signed", "non-negative"]))
    if domain == "log-colour":  # what the networks filter: [0, LOG_COLOUR_MAX], ends included
        colour = rng.uniform(0, LOG_COLOUR_MAX, shape + (3,))
        colour[rng.uniform(size=colour.shape) < 0.2] = 0.0
        colour[rng.uniform(size=colour.shape) < 0.2] = LOG_COLOUR_MAX
    else:
        # magnitudes up to 1e37: a convex combination within k*k rounding errors of float32 max may round to inf
        colour = draw(float32_images(shape + (3,), signed=domain == "signed")).astype(np.float64)
        colour = np.clip(colour, -1e37, 1e37)
    scale = draw(st.sampled_from([0.0, 1.0, 30.0, 1e4, 1e30, F32_MAX / 8]))
    logits = rng.normal(size=shape + (k * k,)) * scale
    if draw(st.booleans()):
        logits = np.sign(logits) * scale  # saturated: ties at +-scale
    return colour.astype(np.float32), np.clip(logits, -F32_MAX, F32_MAX).astype(np.float32), k


@settings(max_examples=80, **PROPERTY)
@given(case=kernel_inputs())
def test_kernel_application_matches_float64_and_stays_inside_each_window(case):
    colour, logits, k = case
    colour_t = torch.tensor(colour, requires_grad=True)
    logits_t = torch.tensor(logits, requires_grad=True)
    out = KernelApply(k)([colour_t, logits_t])
    got = to_np(out).astype(np.float64)
    want, windows = reference_kernel_apply(colour, logits, k)
    # float32 error: the shifted logits' rounding through exp (|z| <= ~104 before exp underflows), the
    # normalisation and the k*k-term sum, relative to the window's largest magnitude
    scale = np.abs(windows).max(axis=3)
    tol = (128 + 2 * k * k) * F32_EPS * scale + k * k * F32_TINY
    assert np.isfinite(got).all()
    assert (np.abs(got - want) <= tol).all()
    # a convex combination: inside [min, max] of the window, per channel
    assert (got >= windows.min(axis=3) - tol).all() and (got <= windows.max(axis=3) + tol).all()
    (out * out.detach().sign()).sum().backward()
    assert torch.isfinite(colour_t.grad).all() and torch.isfinite(logits_t.grad).all()
