"""Self-supervised adaptation (``kpcn_keras.adapt``, issue 53), each figure checked against an independent
computation: on a synthetic frame (a known clean image, two independent noise draws) the adapted model's error
against the clean image (float64 numpy) is lower than the model's, and its output a convex combination of the
model's own pixels and their box blurs; the guard keeps the model where no checkpoint does better; the loss's
expected gradient under a noisy target is the clean target's (a statistical bound that a biased loss fails); the
same seed and steps give the same weights; a pair that is not two renders of one frame is refused in one line; an
adapted model folder serves what was adapted, bit for bit, and refuses a changed network or another input set;
the crops held are bounded."""

import dataclasses
import shutil

import keras
import numpy as np
import pytest
import torch
from helpers.commands import assert_one_line_error, run_main

from kpcn_keras.adapt import (
    FOLDS,
    GUIDE_CHANNELS,
    HELD_OUT_EVERY,
    MARGIN,
    RADII,
    Adapter,
    Corrected,
    _build_fold,
    _guide,
    n2n_loss,
)
from kpcn_keras.adapted_model import ADAPTATION, POST_FILE
from kpcn_keras.batch import ReadOptions, adapt_shot, read_frame, read_halves
from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR
from kpcn_keras.run import Run
from kpcn_keras.serving import Serving
from kpcn_keras.settings import AdaptSettings
from prep import exr
from prep.inputs import InputSet, mean_layers

MODEL = MODELS_DIR / DEFAULT_MODEL  # the shipped model: a variant for every input set
EPS = 1e-2  # prep.metrics.RELMSE_EPS, written here: the loss's and relMSE's constant
NO_SPLIT = InputSet(split=False, variance=False)  # what the in-memory frames have
SPLIT = InputSet(split=True, variance=False)  # what the EXRs written here have (kpcn layout, no variance)


@pytest.fixture(scope="module")
def serving():
    return Serving(Run(MODEL))


@pytest.fixture(scope="module")
def plain(serving):
    """The shipped model's denoiser for a frame without a split or variance layers."""
    return serving.plain(NO_SPLIT)


def smooth_clean(h: int, w: int) -> np.ndarray:
    """(h, w, 3) float64: half a period of a sine across the frame in each channel, in [0.2, 0.75]: what a box
    blur of radius 12 keeps within a few thousandths."""
    y, x = np.mgrid[0:h, 0:w]
    y, x = y / h, x / w
    return np.stack([0.5 + 0.25 * np.sin(np.pi * x), 0.5 + 0.25 * np.cos(np.pi * y),
                     0.4 + 0.2 * np.sin(np.pi * (x + y) / 2)], -1)


def noisy_half(clean: np.ndarray, seed: int, shape: float, albedo=None) -> dict:
    """One render of ``clean`` as the readers give it (no split, no variance): each value ``clean`` times a
    Gamma(``shape``, 1 / ``shape``) draw (mean 1: unbiased, relative spread 1 / sqrt(shape)), independent per
    ``seed``; flat normal and depth."""
    h, w = clean.shape[:2]
    noise = np.random.default_rng(seed).gamma(shape, 1.0 / shape, clean.shape)
    return {"default": (clean * noise).astype(np.float32),
            "albedo": (np.full((h, w, 3), 0.8) if albedo is None else albedo).astype(np.float32),
            "normal": np.tile(np.float32([0, 0, 1]), (h, w, 1)), "depth": np.full((h, w), 5.0, np.float32)}


def box_blur(image: np.ndarray, r: int) -> np.ndarray:
    """Mean over the (2r+1)^2 box of each pixel, cut at the frame's border, per channel, by a summed-area table in
    float64."""
    h, w = image.shape[:2]
    table = np.zeros((h + 1, w + 1) + image.shape[2:])
    table[1:, 1:] = np.cumsum(np.cumsum(np.asarray(image, np.float64), 0), 1)
    y0, y1 = np.clip(np.arange(h) - r, 0, h), np.clip(np.arange(h) + r + 1, 0, h)
    x0, x1 = np.clip(np.arange(w) - r, 0, w), np.clip(np.arange(w) + r + 1, 0, w)
    total = (table[y1][:, x1] - table[y0][:, x1] - table[y1][:, x0] + table[y0][:, x0])
    count = ((y1 - y0)[:, None] * (x1 - x0)[None, :]).reshape((h, w) + (1,) * (image.ndim - 2))
    return total / count


def mse(x, clean) -> float:
    return float(np.mean((np.asarray(x, np.float64) - clean) ** 2))


def relmse(x, clean) -> float:
    return float(np.mean((np.asarray(x, np.float64) - clean) ** 2 / (clean**2 + EPS)))


# -- 1. the adaptation lowers the error; the guard keeps the model where nothing does better -----------------------


@pytest.mark.slow
def test_adaptation_lowers_the_error_against_the_clean_image_with_a_convex_blend_of_the_models_pixels(plain):
    # smooth content under heavy unbiased noise: the model leaves low-frequency blotches that its blurs remove
    h = w = 96
    clean = smooth_clean(h, w)
    a, b = noisy_half(clean, 11, 1.0), noisy_half(clean, 12, 1.0)
    adapter = Adapter(plain, [(a, b)], AdaptSettings(steps=30, seed=1, learning_rate=1e-2, crop=64, check_every=10))
    outcome = adapter.run()
    assert outcome.kept and adapter.post is not None, outcome.line()
    frame = mean_layers(a, b)  # what is denoised: the mean of the halves, all the samples
    model = np.asarray(plain(frame)["default"], np.float64)
    adapted = np.asarray(Corrected(plain, adapter.post)(frame)["default"], np.float64)
    # measured: MSE 0.0032 -> 0.0024, relMSE down as much; 0.9 leaves a margin over the seeds tried (0.72-0.77)
    assert mse(adapted, clean) < 0.9 * mse(model, clean), (mse(adapted, clean), mse(model, clean))
    assert relmse(adapted, clean) < 0.9 * relmse(model, clean), (relmse(adapted, clean), relmse(model, clean))
    # each output value lies between the smallest and largest of the model's value and its blurs (float32 slack)
    candidates = np.stack([model, *(box_blur(model, r) for r in RADII)])
    slack = 1e-5 * np.abs(candidates).max(axis=0) + 1e-7
    assert np.all(adapted >= candidates.min(axis=0) - slack) and np.all(adapted <= candidates.max(axis=0) + slack)


@pytest.mark.slow
def test_the_guard_keeps_the_models_output_where_the_correction_would_not_help(plain):
    # sharp per-pixel texture, its albedo given, light noise: the model is right already. The folds' chosen
    # checkpoints do a little better than the model on the halves' held-out blocks, yet applied to the mean they
    # would raise its error against the clean image; the guard's estimate at all the samples says so and keeps
    # the model
    h = w = 64
    clean = np.random.default_rng(7).uniform(0.1, 0.9, (h, w, 3))
    a, b = noisy_half(clean, 21, 16.0, albedo=clean), noisy_half(clean, 22, 16.0, albedo=clean)
    settings = AdaptSettings(steps=30, seed=2, learning_rate=1e-2, crop=64, check_every=10)
    adapter = Adapter(plain, [(a, b)], settings)
    outcome = adapter.run(marks=(1e9,))
    assert outcome.kept is False and adapter.post is None, outcome.line()
    assert any(outcome.best_steps) and outcome.z < settings.confidence, outcome.line()  # the z rule decided
    chosen = adapter.snapshots[1e9][2]  # the checkpoints it refused, applied all the same
    frame = mean_layers(a, b)
    model = plain(frame)["default"]
    corrected = Corrected(plain, adapter.apply_weights(chosen))(frame)["default"]
    # measured: relMSE 2.479e-4 -> 2.553e-4, MSE 8.47e-5 -> 8.60e-5
    assert relmse(corrected, clean) > relmse(model, clean) and mse(corrected, clean) > mse(model, clean)
    # a user who asks for less than the estimate gets the same checkpoints kept, the reason naming what was asked
    asked = dataclasses.replace(settings, confidence=min(outcome.z, 0.0) - 1.0)
    forced = Adapter(plain, [(a, b)], asked)
    again = forced.run()
    assert again.kept and again.best_steps == outcome.best_steps and "asked for" in again.reason
    np.testing.assert_array_equal(Corrected(plain, forced.post)(frame)["default"], corrected)


@pytest.mark.slow
def test_each_fold_never_learns_from_its_own_held_out_blocks_and_the_applied_blend_is_their_mean(plain):
    # what makes the guard's per-block losses honest: a fold's weights are the same whatever the targets of the
    # pixels held out from it, and change with those of the pixels it trains on
    clean = smooth_clean(64, 64)
    a, b = noisy_half(clean, 31, 1.0), noisy_half(clean, 32, 1.0)
    settings = AdaptSettings(steps=8, seed=3, crop=64, block=8)

    def trained(changed_fold=None):
        adapter = Adapter(plain, [(a, b)], settings)
        if changed_fold is not None:  # the targets tripled on the pixels that fold holds out, in both directions
            for crop in adapter.crops:
                target = keras.ops.convert_to_numpy(crop.target).copy()
                target[crop.folds == changed_fold] *= 3.0
                crop.target = keras.ops.convert_to_tensor(target)
        opt = keras.optimizers.Adam(learning_rate=1e-2)
        opt.build(adapter.net.trainable_weights)
        for _ in range(settings.steps):
            adapter.step(opt)
        return adapter

    base = trained()
    folds = base.crops[0].folds
    # each fold holds out about one block in HELD_OUT_EVERY, none of another fold's
    assert [round(float((folds == k).mean()), 2) for k in range(FOLDS)] == [1 / HELD_OUT_EVERY] * FOLDS
    for k in range(FOLDS):
        changed = trained(k)
        for j, (net, other) in enumerate(zip(base.folds, changed.folds, strict=True)):
            same = all(np.array_equal(x, y) for x, y in zip(net.get_weights(), other.get_weights(), strict=True))
            assert same == (j == k), (k, j)
    # applied: the softmax of the combined logits is the mean of the folds' softmaxes (float64 numpy)
    guide = base.crops[0].window.guide
    blends = [_softmax(net(guide)) for net in base.folds]
    assert np.abs(_softmax(base.net(guide)) - np.mean(blends, axis=0)).max() < 1e-6
    assert np.abs(blends[0] - blends[1]).max() > 1e-4  # the folds differ: the mean is a blend of two


def _softmax(logits) -> np.ndarray:
    z = np.asarray(keras.ops.convert_to_numpy(logits), np.float64)
    e = np.exp(z - z.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def test_an_adaptation_goes_on_from_a_post_correction_of_folds_or_of_one_network(plain):
    clean = smooth_clean(32, 32)
    pairs = [(noisy_half(clean, 1, 1.0), noisy_half(clean, 2, 1.0))]
    settings = AdaptSettings(steps=1, seed=9, crop=32, block=8)
    first = Adapter(plain, pairs, settings)
    for k, w in enumerate(first.net.trainable_weights):  # weights no fresh network has
        w.assign(w.value + 0.01 * (k + 1))
    again = Adapter(plain, pairs, dataclasses.replace(settings, seed=10), first.net)
    assert all(np.array_equal(x, y) for x, y in zip(first.net.get_weights(), again.net.get_weights(), strict=True))
    one = _build_fold(5, "post_correction")  # one network, as adaptations before the cross-fitted guard wrote
    for w in one.trainable_weights:
        w.assign(w.value - 0.02)
    for fold in Adapter(plain, pairs, settings, one).folds:
        assert all(np.array_equal(x, y) for x, y in zip(fold.get_weights(), one.get_weights(), strict=True))


# -- 2. the loss's expected gradient -------------------------------------------------------------------------------


def _per_draw_gradients(loss, f: np.ndarray, targets: np.ndarray, mask=None) -> np.ndarray:
    """(D, N) float64: the gradient of ``loss(f, y_d)`` with respect to ``f`` (N values) for each of the D targets
    ``y_d``, from one backward pass: f repeated D times as one leaf, the loss of the (D, N) batch being the mean of
    the D losses (D times the batch's gradient is each draw's)."""
    d = targets.shape[0]
    leaf = torch.tensor(np.broadcast_to(f, targets.shape).copy(), dtype=torch.float64, requires_grad=True)
    y = torch.tensor(targets, dtype=torch.float64)
    value = loss(leaf, y) if mask is None else loss(leaf, y, torch.tensor(np.broadcast_to(mask, targets.shape)))
    value.backward()
    return leaf.grad.numpy() * d


def _target_weighted(f, y, mask=None):
    """A biased loss for the contrast: the weight of the target, (f - y)^2 / (y^2 + eps)."""
    return keras.ops.mean((f - y) ** 2 / (y**2 + EPS))


def _no_stop_gradient(f, y, mask=None):
    """A biased loss for the contrast: the weight's f not stopped, (f - y)^2 / (f^2 + eps)."""
    return keras.ops.mean((f - y) ** 2 / (f**2 + EPS))


def _max_z(gradients: np.ndarray, clean_gradient: np.ndarray) -> float:
    """The largest |mean - clean| over the elements in standard errors of the draws' mean."""
    se = gradients.std(axis=0, ddof=1) / np.sqrt(gradients.shape[0])
    return float(np.max(np.abs(gradients.mean(axis=0) - clean_gradient) / se))


def test_the_losss_expected_gradient_under_a_noisy_target_is_the_clean_targets():
    assert keras.backend.backend() == "torch"
    rng = np.random.default_rng(5)
    n, draws = 24, 40000
    clean = rng.uniform(0.05, 2.0, n)  # around the weight's eps and well above it
    f = clean * rng.uniform(0.5, 1.5, n)  # the network's output: not the clean image
    mask = np.arange(n) % 3 != 0  # the held-out pixels (a third) outside the loss
    targets = clean * rng.gamma(2.0, 0.5, (draws, n))  # unbiased: E[y] = clean, relative spread 0.71
    # the gradient with the clean target, analytically in float64: 2 (f - c) / (f^2 + eps) / (pixels in the mask)
    clean_gradient = np.where(mask, 2 * (f - clean) / (f**2 + EPS) / mask.sum(), 0.0)
    gradients = _per_draw_gradients(n2n_loss, f, targets, mask)
    assert np.all(gradients[:, ~mask] == 0)  # held out: no gradient at all
    z = _max_z(gradients[:, mask], clean_gradient[mask])
    # 16 elements at 4 standard errors: a false alarm once in 1,000 runs of fresh draws (these are fixed)
    assert z < 4.0, z
    # the bound catches a biased loss: the target's weight, or the weight's f not stopped, fail by far
    unmasked_clean = 2 * (f - clean) / (f**2 + EPS) / n
    assert _max_z(_per_draw_gradients(n2n_loss, f, targets), unmasked_clean) < 4.0
    assert _max_z(_per_draw_gradients(_target_weighted, f, targets), unmasked_clean) > 20.0
    assert _max_z(_per_draw_gradients(_no_stop_gradient, f, targets), unmasked_clean) > 20.0


# -- 3. the same seed and steps give the same weights --------------------------------------------------------------


@pytest.mark.slow
def test_the_same_seed_and_steps_give_the_same_weights_and_another_seed_others(plain):
    clean = smooth_clean(48, 48)
    pairs = [(noisy_half(clean, 1, 1.0), noisy_half(clean, 2, 1.0))]

    def weights(seed):
        adapter = Adapter(plain, pairs, AdaptSettings(steps=12, seed=seed, learning_rate=1e-2, crop=32, block=8,
                                                      check_every=4, confidence=0.0))
        adapter.run()
        return adapter.net.get_weights()

    first, again, other = weights(4), weights(4), weights(5)
    assert all(np.array_equal(x, y) for x, y in zip(first, again, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(first, other, strict=True))


# -- 4. a pair that is not two renders of one frame ----------------------------------------------------------------


def write_render(path, clean: np.ndarray, seed: int, variances: bool = False):
    """A kpcn-layout EXR of ``clean`` (diffuse 0.6 of it, specular 0.4, each with its own Gamma(1) noise), flat
    albedo, normal and depth; with ``variances``, variance layers too (another input set)."""
    h, w = clean.shape[:2]
    rng = np.random.default_rng(seed)
    layers = {"diffuse": 0.6 * clean * rng.gamma(1.0, 1.0, clean.shape),
              "specular": 0.4 * clean * rng.gamma(1.0, 1.0, clean.shape),
              "albedo": np.full((h, w, 3), 0.8), "normal": np.tile([0.0, 0.0, 1.0], (h, w, 1)),
              "depth": np.full((h, w), 5.0)}
    if variances:
        layers.update({f"{k}Variance": np.full((h, w), 0.01) for k in
                       ("diffuse", "specular", "color", "albedo", "normal", "depth")})
    return exr.write_aovs(path, {k: v.astype(np.float32) for k, v in layers.items()})


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """Two renders of one 64x64 frame (a, b) at 8 spp, and the pairs that are not one: a copy of a under another
    name, a frame of another size, the frame at another spp; a render of it with variance layers."""
    folder = tmp_path_factory.mktemp("renders")
    clean = smooth_clean(64, 64)
    out = {"a": write_render(folder / "a-00008spp.exr", clean, 1),
           "b": write_render(folder / "b-00008spp.exr", clean, 2),
           "small": write_render(folder / "small-00008spp.exr", smooth_clean(48, 64), 3),
           "spp": write_render(folder / "c-00016spp.exr", clean, 4),
           "variance": write_render(folder / "v-00008spp.exr", clean, 5, variances=True)}
    out["copy"] = shutil.copy(out["a"], folder / "copy-00008spp.exr")
    return folder, out


@pytest.mark.parametrize("other", ["a", "copy", "small", "spp"])
def test_a_pair_that_is_not_a_second_render_is_refused_in_one_line_naming_both(renders, other):
    folder, files = renders
    res = run_main("denoise", files["a"].name, "--pair", files[other].name, "--adapt-steps", "2", cwd=folder)
    assert_one_line_error(res, files["a"].name, files[other].name)
    assert not list(folder.glob("*-denoised.*"))


def test_adapt_without_a_pair_is_refused_in_one_line(renders):
    folder, files = renders
    res = run_main("denoise", files["a"].name, "--adapt", "5", cwd=folder)
    assert_one_line_error(res, "--adapt", "--pair")


def test_an_adapt_confidence_out_of_its_range_is_refused_in_one_line(renders):
    folder, files = renders
    res = run_main("denoise", files["a"].name, "--pair", files["b"].name, "--adapt-steps", "2",
                   "--adapt-confidence", "-11", cwd=folder)
    assert_one_line_error(res, "--adapt-confidence", "-11")
    assert not list(folder.glob("*-denoised.*"))


@pytest.mark.slow
def test_an_adaptation_the_guard_refuses_leaves_the_models_output_bit_for_bit(renders, serving, tmp_path):
    # 2 steps, a check every 10: no checkpoint, so the guard keeps the model; the output is its denoise of the
    # mean of the halves (each with its own inputs: no variance from their difference), exactly
    folder, files = renders
    out = tmp_path / "out.exr"
    res = run_main("denoise", files["a"], "--pair", files["b"], "--adapt-steps", "2", "-o", out, cwd=folder)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "adaptation not kept" in res.stdout, res.stdout
    frame = read_frame(files["a"], ReadOptions(pair=files["b"]))
    a, b = read_halves(files["a"], ReadOptions(pair=files["b"]))
    assert frame.inputs == SPLIT
    expected = serving.plain(SPLIT)(mean_layers(a.layers, b.layers))["default"]
    assert np.array_equal(exr.read_aovs(out, variances=False)["default"], expected)


# -- 5. an adapted model folder ------------------------------------------------------------------------------------


@pytest.mark.slow
def test_an_adapted_model_folder_serves_the_adapted_network_bit_for_bit_and_refuses_what_it_was_not(
        renders, serving, tmp_path):
    folder, files = renders
    settings = AdaptSettings(steps=20, seed=2, learning_rate=1e-2, crop=64, check_every=10, confidence=0.0)
    outcome, adapted = adapt_shot([(files["a"], files["b"])], Run(MODEL), tmp_path / "adapted", adapt=settings)
    assert outcome.kept, outcome.line()
    # the same adaptation in memory: the same seed and steps give the same network
    a, b = read_halves(files["a"], ReadOptions(pair=files["b"]))
    memory = Adapter(serving.plain(SPLIT), [(a.layers, b.layers)], settings)
    memory.run()
    assert memory.post is not None
    # served from the folder (its post.keras loaded) and in memory: the same weights, the same float32 ops, so the
    # same bits (no tolerance)
    frame = read_frame(files["a"]).layers
    served = Serving(Run(adapted)).denoiser(SPLIT)(frame)
    expected = Corrected(serving.plain(SPLIT), memory.post)(frame)
    for name in ("default", "diffuse", "specular"):
        assert np.array_equal(served[name], expected[name]), name
    assert not np.array_equal(expected["default"], serving.plain(SPLIT)(frame)["default"])  # it does correct
    res = run_main("denoise", files["a"], "--run", adapted, "-o", tmp_path / "d.exr", cwd=folder)
    assert res.returncode == 0, res.stderr[-2000:]
    assert np.array_equal(exr.read_aovs(tmp_path / "d.exr", variances=False)["default"], expected["default"])
    # a frame of another input set (with variance layers): refused in one line naming the folder and both sets
    res = run_main("denoise", files["variance"], "--run", adapted, "-o", tmp_path / "v.exr", cwd=folder)
    assert_one_line_error(res, str(adapted), SPLIT.name, InputSet().name)
    # a network that is not the one the record lists
    post = adapted / ADAPTATION / POST_FILE
    post.write_bytes(post.read_bytes() + b"\0")
    res = run_main("denoise", files["a"], "--run", adapted, "-o", tmp_path / "t.exr", cwd=folder)
    assert_one_line_error(res, str(post), "SHA-256")


# -- 6. memory ---------------------------------------------------------------------------------------------------


def test_the_crops_held_are_at_most_crops_a_render_each_at_most_crop_plus_two_margins(plain):
    h, w = 100, 150
    clean = smooth_clean(h, w)
    a, b = noisy_half(clean, 1, 4.0), noisy_half(clean, 2, 4.0)
    s = AdaptSettings(steps=1, crop=32, crops=3, block=8)
    adapter = Adapter(plain, [(a, b)], s)
    assert len(adapter.crops) == 2 * s.crops  # each render's crops (its tiles: 4 x 5 = 20 > 3)
    side = s.crop + 2 * MARGIN
    for crop in adapter.crops:
        _, gh, gw, channels = crop.window.guide.shape
        assert channels == GUIDE_CHANNELS and gh <= side and gw <= side
        k, ch, cw, _ = crop.window.candidates["default"].shape
        assert (k, ch, cw) == (1 + len(RADII), gh, gw)
        th, tw, _ = crop.target.shape
        assert th <= s.crop and tw <= s.crop


# -- the guide -----------------------------------------------------------------------------------------------------


def test_the_guides_depth_is_the_depth_over_its_largest_and_finite_without_one():
    h, w = 20, 30
    layers = {"default": np.ones((h, w, 3), np.float32), "albedo": np.ones((h, w, 3), np.float32),
              "normal": np.zeros((h, w, 3), np.float32)}
    candidates = np.ones((1 + len(RADII), h, w, 3), np.float32)
    depth = np.random.default_rng(0).uniform(1.0, 40.0, (h, w)).astype(np.float32)
    from prep.features import depth_scale

    guide = _guide(candidates, {**layers, "depth": depth}, (0, h, 0, w), depth_scale(depth))
    np.testing.assert_allclose(guide[..., -1], depth.astype(np.float64) / depth.max(), rtol=1e-6)
    # the rgb layout's frame has no depth: filled with 0 (prep.layouts.FILL), its scale 0
    zero = np.zeros((h, w), np.float32)
    guide = _guide(candidates, {**layers, "depth": zero}, (0, h, 0, w), depth_scale(zero))
    assert np.all(np.isfinite(guide)) and np.all(guide[..., -1] == 0)


def test_the_progress_bar_appears_at_the_first_step_so_a_refused_pair_is_its_one_line_alone(capsys):
    from kpcn_keras.cli import _AdaptBar

    with _AdaptBar(AdaptSettings(steps=3), quiet=False):
        pass  # refused before training: no step
    assert capsys.readouterr().err == ""
    with _AdaptBar(AdaptSettings(steps=3), quiet=False) as bar:
        bar(1, 0.5, 0.1)
    assert "adapting" in capsys.readouterr().err
    with _AdaptBar(AdaptSettings(steps=3), quiet=True) as bar:
        bar(1, 0.5, 0.1)
    assert capsys.readouterr().err == ""


def test_denoises_adapt_options_become_the_adaptations_settings():
    from kpcn_keras.parser import adapt_settings, build_parser

    args = build_parser().parse_args(["denoise", "a.exr", "--pair", "b.exr", "--adapt", "5", "--adapt-seed", "3",
                                      "--adapt-confidence", "-1.5"])
    assert adapt_settings(args) == AdaptSettings(seconds=5.0, seed=3, confidence=-1.5)
    assert adapt_settings(build_parser().parse_args(["denoise", "a.exr"])) is None
