"""``kpcn.denoise`` on arrays a user hands it: non-finite values are repaired by the reader's rule with the reader's
warning, and an array it cannot take (not numbers, complex, of a wrong shape, or of a frame the machine cannot hold)
is a one-line ``kpcn.ArrayError`` or ``kpcn.KpcnError`` naming the argument, before anything is allocated."""

import dataclasses
import logging

import numpy as np
import pytest

import kpcn
from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR

MODEL = MODELS_DIR / DEFAULT_MODEL  # the shipped model: a variant for every input set, nothing to train
H, W = 24, 20
REPAIRED = "repaired non-finite values (NaN->0, inf->channel's finite max/min)"


def by_hand(value) -> np.ndarray:
    """The reader's rule, in float64 numpy: a value beyond float32's range is the inf float32 makes of it; per
    channel, NaN is 0, +inf the channel's largest finite value (0 if none), -inf its smallest."""
    a = np.array(value, np.float64)
    big = float(np.finfo(np.float32).max)
    a[a > big], a[a < -big] = np.inf, -np.inf
    channels = a[..., None] if a.ndim == 2 else a
    for c in range(channels.shape[-1]):
        ch = channels[..., c]
        finite = ch[np.isfinite(ch)]
        ch[np.isnan(ch)] = 0.0
        ch[np.isposinf(ch)] = finite.max() if finite.size else 0.0
        ch[np.isneginf(ch)] = finite.min() if finite.size else 0.0
    return a.astype(np.float32)


def arrays(seed=0) -> dict:
    rng = np.random.default_rng(seed)
    return {"color": rng.random((H, W, 3), np.float32), "albedo": rng.random((H, W, 3), np.float32),
            "normal": rng.uniform(-1, 1, (H, W, 3)).astype(np.float32), "depth": rng.random((H, W), np.float32),
            "variance": rng.random((H, W), np.float32) * 1e-2}


def _nan(a):
    a[3, 4] = np.nan
    return a


def _posinf(a):
    a[5, 6, 1] = np.inf
    return a


def _huge64(a):
    a = a.astype(np.float64)
    a[7, 8, 2] = 1e300  # beyond float32: inf once cast, then repaired
    return a


def _neginf(a):
    a[2, 2, 0] = -np.inf
    return a


# (argument, how it is spoilt, the count the warning gives it, the name it gives)
CASES = {
    "nan-in-colour": ("color", _nan, 3, "color: 3"),
    "inf-in-colour": ("color", _posinf, 1, "color: 1"),
    "float64-1e300-in-colour": ("color", _huge64, 1, "color: 1"),
    "nan-in-albedo": ("albedo", _nan, 3, "albedo: 3"),
    "neginf-in-normal": ("normal", _neginf, 1, "normal: 1"),
    "nan-in-depth": ("depth", _nan, 1, "depth: 1"),
    "nan-in-variance": ("variance", _nan, 1, "variance: 1"),
}


@pytest.mark.parametrize("case", CASES)
def test_non_finite_arrays_are_repaired_as_a_file_is_with_the_readers_warning(case, caplog):
    name, spoil, _, said = CASES[case]
    given = arrays()
    given[name] = spoil(given[name].copy())
    with caplog.at_level(logging.WARNING, logger="kpcn"):
        out = kpcn.denoise(**given, run=MODEL)
    assert out.shape == (H, W, 3) and np.isfinite(out).all()
    warned = [r.getMessage() for r in caplog.records if r.name == "kpcn" and r.levelno == logging.WARNING]
    assert len(warned) == 1 and REPAIRED in warned[0] and said in warned[0], warned
    caplog.clear()
    repaired = {**given, name: by_hand(given[name])}
    with caplog.at_level(logging.WARNING, logger="kpcn"):
        np.testing.assert_array_equal(out, kpcn.denoise(**repaired, run=MODEL))
    assert not [r for r in caplog.records if r.name == "kpcn"]  # nothing left to repair: no warning


def test_a_variance_dict_and_a_split_are_repaired_layer_by_layer(caplog):
    from prep.exr import VARIANCE_LAYERS

    rng = np.random.default_rng(3)
    given = arrays()
    given.pop("variance")
    variance = {n: rng.random((H, W), np.float32) * 1e-2 for n in VARIANCE_LAYERS}
    variance["specularVariance"] = _nan(variance["specularVariance"])
    diffuse, specular = rng.random((H, W, 3), np.float32), _posinf(rng.random((H, W, 3), np.float32))
    with caplog.at_level(logging.WARNING, logger="kpcn"):
        out = kpcn.denoise(**given, diffuse=diffuse, specular=specular, variance=variance, run=MODEL)
    assert np.isfinite(out).all()
    warned = " ".join(r.getMessage() for r in caplog.records if r.name == "kpcn")
    assert REPAIRED in warned and "specular: 1" in warned and "specularVariance: 1" in warned, warned
    want = kpcn.denoise(**given, diffuse=diffuse, specular=by_hand(specular), run=MODEL,
                        variance={**variance, "specularVariance": by_hand(variance["specularVariance"])})
    np.testing.assert_array_equal(out, want)


def _one_line(err, *words):
    message = str(err.value)
    assert "\n" not in message and all(w in message for w in words), message
    assert isinstance(err.value, kpcn.KpcnError)


@pytest.mark.parametrize("value, words", [
    ("x", ("color", "str")),
    (np.array([["a", "b", "c"]] * 4, dtype=object).reshape(2, 2, 3), ("color", "object")),
    (np.full((4, 4, 3), 1 + 2j, np.complex64), ("color", "complex")),
    (np.zeros((4, 4), np.float32), ("color", "(4, 4)")),
    (np.zeros((4, 4, 2), np.float32), ("color", "(4, 4, 2)")),
    (np.zeros((0, 4, 3), np.float32), ("color", "(0, 4, 3)")),
    ([[["a", 1, 2]]], ("color",)),
])
def test_an_array_it_cannot_take_is_an_array_error_naming_it(value, words):
    with pytest.raises(kpcn.ArrayError) as err:
        kpcn.denoise(value, run=MODEL)
    _one_line(err, *words)
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize("name, value", [("albedo", np.full((H, W, 3), 1j)), ("depth", "deep"),
                                         ("normal", np.zeros((H, W), np.float32)),
                                         ("variance", np.array([[None] * W] * H))])
def test_an_auxiliary_it_cannot_take_is_an_array_error_naming_it(name, value):
    given = arrays()
    given[name] = value
    with pytest.raises(kpcn.ArrayError) as err:
        kpcn.denoise(**given, run=MODEL)
    _one_line(err, name)


def test_a_frame_the_machine_cannot_hold_is_refused_by_the_commands_memory_check_before_any_copy():
    from prep.processes import available_memory_mb

    huge = np.broadcast_to(np.float64(0.5), (100000, 100000, 3))  # no memory behind it: a copy would be 240 GB
    with pytest.raises(kpcn.KpcnError) as err:
        kpcn.denoise(huge, run=MODEL)
    _one_line(err, "color", "100000x100000", "this machine has available")
    available = available_memory_mb()
    if available is None:
        pytest.skip("this machine does not say how much memory it has available")
    side = int((2 * available * 2**20 / 128) ** 0.5) + 1  # twice what it has, at 128 bytes a pixel held whole
    with pytest.raises(kpcn.KpcnError) as err:
        kpcn.denoise(np.broadcast_to(np.float32(0.5), (side, side, 3)), run=MODEL)
    _one_line(err, "color", f"{side}x{side}", "this machine has available")


# ---------------------------------------------------------------- pair= and adapt=: as kpcn denoise --pair [--adapt]

PAIR_H, PAIR_W = 48, 64  # three held-out blocks of 16 pixels: the guard's smallest frame with room to spare
STEPS = 30


@pytest.fixture(scope="module")
def halves_files(tmp_path_factory):
    from helpers.halves import write_halves

    return write_halves(tmp_path_factory.mktemp("halves"), PAIR_H, PAIR_W, seed=5)


def _command(tmp_path, a, b, *extra):
    from helpers.commands import run_main

    from prep import exr

    out = tmp_path / "out.exr"
    res = run_main("denoise", a, "--pair", b, "--run", MODEL, "--precision", "float32", "-o", out, *extra,
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    return exr.read_aovs(out, variances=False)["default"], res.stdout


@pytest.mark.parametrize("given", ["frames", "arrays"])
def test_adapting_to_a_pair_gives_what_the_command_gives_on_the_same_files_and_steps(given, halves_files, tmp_path):
    from kpcn_keras.settings import AdaptSettings, InferenceSettings

    a, b = halves_files
    want, printed = _command(tmp_path, a, b, "--adapt-steps", STEPS, "--adapt-seed", 3)
    fa, fb = kpcn.read(a), kpcn.read(b)
    if given == "frames":
        frame, pair = fa, fb
    else:
        frame = {"color": fa.layers["default"], "albedo": fa.layers["albedo"], "normal": fa.layers["normal"],
                 "depth": fa.layers["depth"], "diffuse": fa.layers["diffuse"], "specular": fa.layers["specular"],
                 "variance": {k: v for k, v in fa.layers.items() if k.endswith("Variance")}}
        pair = {**frame, "color": fb.layers["default"], "diffuse": fb.layers["diffuse"],
                "specular": fb.layers["specular"],
                "variance": {k: v for k, v in fb.layers.items() if k.endswith("Variance")}}
        frame = (frame.pop("color"), frame)
    progress, outcomes = [], []
    args, kw = ((frame,), {}) if given == "frames" else ((frame[0],), frame[1])
    got = kpcn.denoise(*args, **kw, pair=pair, run=MODEL, settings=InferenceSettings(precision="float32"),
                       adapt=AdaptSettings(steps=STEPS, seed=3), on_adapt=lambda *p: progress.append(p),
                       on_outcome=outcomes.append)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    (outcome,) = outcomes
    assert [p[0] for p in progress] == list(range(1, STEPS + 1)) and all(np.isfinite(p[1]) for p in progress)
    assert outcome.kept, outcome.line()  # these halves and steps clear the guard: the correction is what is compared
    assert outcome.steps == STEPS and f"at steps {' and '.join(map(str, outcome.best_steps))} of {STEPS}" in printed
    assert ("adaptation kept" if outcome.kept else "adaptation not kept") in printed
    plain = kpcn.denoise(*args, **kw, pair=pair, run=MODEL, settings=InferenceSettings(precision="float32"),
                         adapt=AdaptSettings(steps=STEPS, seed=3, confidence=10.0))  # a guard nothing clears
    from prep.inputs import mean_layers

    mean = kpcn.denoise(dataclasses.replace(fa, layers=mean_layers(fa.layers, fb.layers)), run=MODEL,
                        settings=InferenceSettings(precision="float32"))
    np.testing.assert_array_equal(plain, mean)  # refused: the model's output of the halves' mean, as it is
    assert np.abs(got - mean).max() > 1e-4  # kept: the correction changed the output


def test_a_pair_without_adapt_gives_what_the_command_gives(halves_files, tmp_path):
    from kpcn_keras.settings import InferenceSettings

    a, b = halves_files
    want, _ = _command(tmp_path, a, b)
    got = kpcn.denoise(kpcn.read(a), pair=kpcn.read(b), run=MODEL, settings=InferenceSettings(precision="float32"))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    alone = kpcn.denoise(kpcn.read(a), run=MODEL, settings=InferenceSettings(precision="float32"))
    assert np.abs(got - alone).max() > 1e-4  # the pair is used


def test_a_pair_or_adapt_it_cannot_take_is_one_line_naming_it(halves_files):
    from kpcn_keras.settings import AdaptSettings

    fa, fb = (kpcn.read(p) for p in halves_files)
    colour, other = fa.layers["default"], fb.layers["default"]
    cases = [
        (dict(color=colour, adapt=5), ("adapt", "needs pair=")),
        (dict(color=colour, pair=other, adapt="soon"), ("adapt", "str")),
        (dict(color=colour, pair=other, adapt=-1), ("adapt", "-1")),
        (dict(color=colour, pair=other[:10]), ("pair", "64x10", "64x48")),
        (dict(color=colour, pair=colour.copy()), ("pair", "same pixels", "color")),
        (dict(color=colour, pair=other[::-1, ::-1] * 0 + np.random.default_rng(0).random(other.shape)),
         ("pair", "correlates")),
        (dict(color=fa, pair=other), ("pair", "kpcn.read frame")),
        (dict(color=colour, pair=fb), ("pair", "Frame")),
        (dict(color=colour, pair={"colour": other}), ("pair", "colour")),
        (dict(color=colour, variance=fa.layers["colorVariance"], pair=other), ("pair", "no-variance")),
        (dict(color=colour, pair=other, adapt=AdaptSettings(steps=2, block=256)), ("too small",)),
    ]
    for kw, words in cases:
        with pytest.raises(kpcn.KpcnError) as err:
            kpcn.denoise(**kw, run=MODEL)
        _one_line(err, *words)


def test_halves_without_depth_adapt_to_a_finite_frame_and_the_guide_s_depth_is_over_the_largest(halves_files):
    from kpcn_keras.adapt import _candidates, _guide
    from kpcn_keras.settings import AdaptSettings
    from prep import features

    fa, fb = (kpcn.read(p) for p in halves_files)
    outcomes = []
    out = kpcn.denoise(fa.layers["default"], pair=fb.layers["default"], run=MODEL, on_outcome=outcomes.append,
                       adapt=AdaptSettings(steps=10, seed=1))  # no depth: filled 0, as the rgb layout fills it
    assert np.isfinite(out).all() and np.isfinite([outcomes[0].initial, outcomes[0].best]).all()
    depth = fa.layers["depth"]
    guide = _guide(_candidates(fa.layers["default"]), fa.layers, (0, PAIR_H, 0, PAIR_W), features.depth_scale(depth))
    np.testing.assert_allclose(guide[..., -1], depth.astype(np.float64) / depth.astype(np.float64).max(), rtol=1e-6)
