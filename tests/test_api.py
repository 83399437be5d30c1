"""``kpcn.denoise`` on arrays a user hands it: non-finite values are repaired by the reader's rule with the reader's
warning, and an array it cannot take (not numbers, complex, of a wrong shape, or of a frame the machine cannot hold)
is a one-line ``kpcn.ArrayError`` or ``kpcn.KpcnError`` naming the argument, before anything is allocated."""

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
