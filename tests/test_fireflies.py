"""Synthetic fireflies in training patches (kpcn_keras/fireflies.py): a spike is the render with one bright sample
more, seen by the training stream's inputs alone."""

import numpy as np
import pytest
from helpers.references import assert_read_features_close
from helpers.tiny import build_tiny_shards, random_aovs, tiny_train_config

from kpcn_keras import fireflies
from kpcn_keras.config import TrainConfig
from kpcn_keras.data import ShardPatches
from prep.colour import ALBEDO_EPS
from prep.errors import OptionError
from prep.features import BRANCHES, branch_features
from prep.shards import shard_paths
from prep.shards.format import derive
from prep.shards.patches import image_datasets

SIZE = 12
# the last one about as large as its pixel's own spread: there the variance the pixel had before counts
SPIKES = (fireflies.Spike(3, 5, 40.0), fireflies.Spike(7, 2, 2500.0), fireflies.Spike(11, 11, 0.5))


def grey_render(variance: bool) -> dict:
    """A random render one pixel larger than the patch (the patch's last row and column have true neighbours,
    as inside an image) whose every colour and albedo is grey: there the pixel's variance read back from its
    relative variance is exact (kpcn_keras/fireflies.py)."""
    aovs = random_aovs(SIZE + 1, SIZE + 1, seed=4)
    for name in ("diffuse", "specular", "albedo"):
        aovs[name] = np.repeat(aovs[name].mean(-1, keepdims=True), 3, -1)
    aovs["default"] = aovs["diffuse"] + aovs["specular"]
    for name in ("diffuseVariance", "specularVariance"):
        aovs[name] = aovs[name] * 10  # noisy, as a render where fireflies occur is
    if not variance:  # what prep.inputs.restrict gives a frame without variance layers
        aovs.update({n: np.zeros_like(v) for n, v in aovs.items() if n.endswith("Variance")})
    return aovs


def with_samples(aovs: dict, branch: str, spikes, variance: bool) -> dict:
    """The render with each spike's sample added to ``branch``'s layer, in float64: ``value`` more in the
    branch's colour (the irradiance, for the diffuse branch) and ``value ** 2`` more in its variance."""
    out = {n: v.astype(np.float64) for n, v in aovs.items()}
    for s in spikes:
        scale = np.clip(out["albedo"][s.y, s.x, 0], 0, 1) + ALBEDO_EPS if branch == "diffuse" else 1.0
        out[branch][s.y, s.x] += s.value * scale
        if variance:
            out[f"{branch}Variance"][s.y, s.x] += (s.value * scale) ** 2
    return out


def patch_of(image: dict) -> dict:
    """The patch at (0, 0) of a render's full-image datasets, as a shard stores it (its border: the true next
    row and column)."""
    return {n: a[: SIZE + 1, : SIZE + 1] if n.endswith("log_colour") or n == "guides" else a[:SIZE, :SIZE]
            for n, a in image.items()}


@pytest.mark.parametrize("variance", [True, False], ids=["variance", "no-variance"])
@pytest.mark.parametrize("branch", BRANCHES)
def test_a_spike_gives_the_features_of_the_render_with_that_sample_added(branch, variance):
    aovs = grey_render(variance)
    stored = patch_of(image_datasets(aovs, aovs))
    got = derive(fireflies.inject(stored, branch, SPIKES, variance), [f"{branch}/features"], SIZE)[f"{branch}/features"]
    want = branch_features(with_samples(aovs, branch, SPIKES, variance), branch)[:SIZE, :SIZE]
    assert_read_features_close(got, want)
    before = derive(stored, [f"{branch}/features"], SIZE)[f"{branch}/features"]
    changed = np.argwhere(np.any(got != before, axis=-1))
    # a spike changes its pixel's features and the forward differences of the pixels before it, nothing else
    near = {(s.y + dy, s.x + dx) for s in SPIKES for dy, dx in ((0, 0), (-1, 0), (0, -1))}
    assert {tuple(p) for p in changed} <= near and {(s.y, s.x) for s in SPIKES} <= {tuple(p) for p in changed}
    if not variance:
        np.testing.assert_array_equal(got[..., 23], 0.0)


def test_no_spikes_leave_the_patch_as_stored():
    stored = patch_of(image_datasets(grey_render(True), grey_render(True)))
    assert fireflies.inject(stored, "diffuse", (), True) is stored
    spiked = fireflies.inject(stored, "diffuse", SPIKES[:1], True)
    assert spiked["specular/log_colour"] is stored["specular/log_colour"]  # the other branch's own arrays
    assert not np.array_equal(spiked["diffuse/log_colour"], stored["diffuse/log_colour"])


def test_spikes_are_drawn_poisson_with_log_uniform_values():
    rng = np.random.default_rng(0)
    draws = [fireflies.draw(rng, 2.0, 65) for _ in range(4000)]
    counts = np.array([len(d) for d in draws])
    # Poisson(2): mean 2, variance 2; the mean of 4000 within 5 standard errors
    assert abs(counts.mean() - 2.0) < 5 * np.sqrt(2.0 / 4000)
    assert abs(counts.var() - 2.0) < 0.25
    values = np.log([s.value for d in draws for s in d])
    lo, hi = np.log(fireflies.SPIKE_RANGE)
    assert lo <= values.min() and values.max() <= hi
    # log-uniform: the mean and the quartiles of log S are those of the uniform, within a statistical bound
    n = len(values)
    assert abs(values.mean() - (lo + hi) / 2) < 5 * (hi - lo) / np.sqrt(12 * n)
    assert abs(np.quantile(values, 0.25) - (lo + 0.25 * (hi - lo))) < 0.05 * (hi - lo)
    assert all(0 <= s.y < 65 and 0 <= s.x < 65 for d in draws for s in d)
    assert fireflies.draw(rng, 0.0, 65) == ()


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    return build_tiny_shards(tmp_path_factory.mktemp("fireflies"))


def test_a_training_stream_brightens_inputs_only_and_validation_reads_the_patches_as_rendered(tiny_set):
    paths = shard_paths(tiny_set.set_dir, "train")
    plain = ShardPatches(paths, "both", batch_size=2, steps=6, seed=2, augment=True)
    spiked = ShardPatches(paths, "both", batch_size=2, steps=6, seed=2, augment=True, firefly_rate=3.0)
    brightened = 0
    for i in range(6):
        (x0, y0), (x1, y1) = plain[i], spiked[i]
        np.testing.assert_array_equal(y1, y0)  # the target is the reference, spikes or not
        colour = x1[..., :3] != x0[..., :3]
        assert np.all(x1[..., :3][colour] > x0[..., :3][colour])  # a spike only adds light
        brightened += int(np.any(colour, axis=-1).sum())
    # 12 patches at 3 spikes each on average: Poisson(36), far from 0 and below 36 + 5 standard deviations
    assert 10 <= brightened <= 36 + 5 * 6
    val = shard_paths(tiny_set.set_dir, "val")
    for a, b in zip(ShardPatches(val, "diffuse", batch_size=2, shuffle=False),
                    ShardPatches(val, "diffuse", batch_size=2, shuffle=False, firefly_rate=3.0)):
        np.testing.assert_array_equal(a[0], b[0])


def test_fireflies_are_for_the_branch_sources_and_a_rate_is_a_number_at_least_0(tiny_set):
    paths = shard_paths(tiny_set.set_dir, "train")
    with pytest.raises(ValueError, match="source 'final'"):
        ShardPatches(paths, "final", batch_size=2, firefly_rate=1.0)
    with pytest.raises(ValueError, match="-1"):
        ShardPatches(paths, "diffuse", batch_size=2, firefly_rate=-1)


def test_a_run_without_fireflies_keeps_the_identity_it_had_before_they_existed(tiny_set):
    cfg = tiny_train_config(tiny_set, fireflies=0)
    assert "fireflies" not in cfg.to_dict() and TrainConfig.from_record(cfg.to_dict()) == cfg
    assert tiny_train_config(tiny_set).to_dict()["fireflies"] == 1.0  # the default adds them, and says so
    spiked = tiny_train_config(tiny_set, fireflies=1.5)
    assert spiked.to_dict()["fireflies"] == 1.5 and spiked.identity() != cfg.identity()
    with pytest.raises(OptionError, match="fireflies"):
        tiny_train_config(tiny_set, fireflies=-0.5)
