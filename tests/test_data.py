import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.tiny import build_tiny_shards

from kpcn_keras import augment
from kpcn_keras.data import ShardPatches
from prep.shards import ShardError, open_shard, read_patches, shard_paths


@pytest.fixture(scope="module")
def train_paths(tmp_path_factory):
    """The training shards of one tiny set, built once: the tests read them, and the one that damages a
    shard damages a copy."""
    return shard_paths(build_tiny_shards(tmp_path_factory.mktemp("data")).set_dir, "train")


def all_patches(paths, name):
    out = []
    for p in paths:
        with open_shard(p) as f:  # one patch at a time, as a training batch reads them, then recomputed
            out += list(read_patches(f, [name], range(len(f["source"])))[name])
    return np.stack(out)


def test_one_pass_visits_every_patch_once(train_paths):
    ds = ShardPatches(train_paths, "specular", batch_size=2, seed=1)
    assert len(ds) == 14 // 2
    xs = np.concatenate([ds[i][0] for i in range(len(ds))])
    truth = all_patches(train_paths, "specular/features")
    key = lambda a: sorted(float(v) for v in a.reshape(len(a), -1).sum(1))  # noqa: E731
    assert key(xs) == key(truth)


def test_resumed_stream_equals_the_uninterrupted_one(train_paths):
    full = ShardPatches(train_paths, "diffuse", batch_size=3, steps=12, seed=5)
    resumed = ShardPatches(train_paths, "diffuse", batch_size=3, steps=5, seed=5, offset=7)
    for i in range(5):
        np.testing.assert_array_equal(full[7 + i][0], resumed[i][0])
        np.testing.assert_array_equal(full[7 + i][1], resumed[i][1])
    other_seed = ShardPatches(train_paths, "diffuse", batch_size=3, steps=12, seed=6)
    assert not all(np.array_equal(full[i][0], other_seed[i][0]) for i in range(4))


def test_targets_and_pickling(train_paths):
    ds = ShardPatches(train_paths, "diffuse", batch_size=4, shuffle=False, loss_target="reference+noisy")
    ds[0]  # opens the files in this process
    clone = pickle.loads(pickle.dumps(ds))
    x, y = clone[0]
    assert x.shape == (4, 16, 16, 27) and y.shape == (4, 16, 16, 6)
    np.testing.assert_array_equal(y[..., :3], all_patches(train_paths, "diffuse/reference")[:4])
    np.testing.assert_array_equal(y[..., 3:], x[..., :3])  # the noisy colour is features 0-2


def test_bad_arguments_are_echoed(train_paths):
    with pytest.raises(ValueError, match="'glossy'"):
        ShardPatches(train_paths, "glossy", batch_size=2)
    with pytest.raises(ShardError, match="fewer than batch_size=99"):
        ShardPatches(train_paths, "diffuse", batch_size=99)


def test_a_damaged_chunk_is_an_error_naming_the_shard(train_paths, tmp_path):
    path = Path(shutil.copy(train_paths[0], tmp_path))
    with open_shard(path) as f:
        chunk = f["guides"].id.get_chunk_info(0)  # what the features of both branches are made of
    data = bytearray(path.read_bytes())
    data[chunk.byte_offset + 10] ^= 0xFF  # the file keeps its size; its Fletcher-32 no longer matches
    path.write_bytes(bytes(data))
    ds = ShardPatches([path], "diffuse", batch_size=1, shuffle=False)
    with pytest.raises(ShardError, match=f"{path.name}: cannot read patch 0"):
        ds[0]


def _provenance(ds, i) -> list[tuple[int, int, int]]:
    """(branch, shard, patch) of every patch that process ``ds`` reads for batch ``i`` (the stream's own
    choice: reading it back from the batch would need the augmentation's inverse)."""
    return [(int(b), int(s), int(p)) for b, s, p in ds._global_ids(i)[ds._mine()]]


@pytest.mark.parametrize("source,weighted", [("diffuse", False), ("both", False), ("diffuse", True)])
def test_two_processes_batches_put_together_are_the_one_process_batch_and_never_share_a_patch(
        train_paths, source, weighted):
    kw = dict(seed=4, augment=True, steps=9, weights=[1.0, 3.0, 2.0][: len(train_paths)] if weighted else None)
    one = ShardPatches(train_paths, source, batch_size=4, **kw)
    ranks = [ShardPatches(train_paths, source, batch_size=2, rank=r, world=2, **kw) for r in range(2)]
    assert len(ranks[0]) == len(ranks[1]) == len(one)
    per_pass = len(one.index) // 4
    read = [[], []]
    for i in range(len(one)):
        x, y = one[i]
        parts = [ds[i] for ds in ranks]
        np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), x)  # augmentation included
        np.testing.assert_array_equal(np.concatenate([p[1] for p in parts]), y)
        for r, ds in enumerate(ranks):
            read[r].append(_provenance(ds, i))
    if not weighted:  # drawing without replacement: within a pass, the ranks' patches are disjoint
        for start in range(0, len(one) - per_pass + 1, per_pass):
            mine = [{q for batch in read[r][start:start + per_pass] for q in batch} for r in range(2)]
            assert not mine[0] & mine[1]
            assert len(mine[0]) + len(mine[1]) == 4 * per_pass


def test_a_validation_stream_is_read_whole_by_every_process(train_paths):
    one = ShardPatches(train_paths, "specular", batch_size=3, shuffle=False)
    other = ShardPatches(train_paths, "specular", batch_size=3, shuffle=False, rank=1, world=2)
    assert len(one) == len(other)
    for i in range(len(one)):
        np.testing.assert_array_equal(one[i][0], other[i][0])


@pytest.mark.parametrize("rank,world,named", [(2, 2, "rank"), (-1, 2, "rank"), (0, 0, "world"), (0, True, "world")])
def test_a_rank_outside_the_world_is_refused_naming_the_value(train_paths, rank, world, named):
    bad = rank if named == "rank" else world
    with pytest.raises(ValueError, match=rf"^{named} .*got {bad!r}$"):
        ShardPatches(train_paths, "diffuse", batch_size=2, rank=rank, world=world)


def test_a_global_batch_larger_than_the_shards_is_refused_saying_so(train_paths):
    with pytest.raises(ShardError, match="batch_size=4 x 4 processes"):
        ShardPatches(train_paths, "diffuse", batch_size=4, world=4)


@pytest.fixture(scope="module")
def relse_paths(tmp_path_factory):
    """Training shards whose references have variance layers: ref_relse not all 0."""
    cfg = build_tiny_shards(tmp_path_factory.mktemp("relse"), reference_variances=True)
    return shard_paths(cfg.set_dir, "train")


@pytest.mark.parametrize("source,loss_target", [("diffuse", "reference"), ("both", "reference+noisy")])
def test_the_reference_relse_is_the_last_target_channel_moved_with_the_patch_never_permuted(
        relse_paths, source, loss_target):
    ds = ShardPatches(relse_paths, source, batch_size=4, seed=2, augment=True, steps=3, loss_target=loss_target,
                      reference_relse=True)
    plain = ShardPatches(relse_paths, source, batch_size=4, seed=2, augment=True, steps=3, loss_target=loss_target)
    found = set()
    for i in range(len(ds)):
        (x, y), (x0, y0) = ds[i], plain[i]
        np.testing.assert_array_equal(x, x0)
        np.testing.assert_array_equal(y[..., :-1], y0)  # the rest of the target is as it was
        assert y.shape[-1] == y0.shape[-1] + 1
        for k, (b, s, p) in enumerate(_provenance(ds, i)):
            branch = ("diffuse", "specular")[b]
            with open_shard(relse_paths[s]) as f:
                relse, ref = f[f"{branch}/ref_relse"][p], f[f"{branch}/reference"][p]
            # the augmentation this patch got is the one that moves its reference to the target's
            augs = [a for a in augment.ALL if np.array_equal(augment.augment_colour(ref, a), y[k, ..., :3])]
            assert augs and any(np.array_equal(augment.augment_spatial(relse, a), y[k, ..., -1:]) for a in augs)
            found.add(augs[0].spatial)
            assert relse.max() > 0
    assert len(found) > 1  # flips and rotations were drawn, and the relSE moved with them
    with pytest.raises(ValueError, match="'final' has none"):
        ShardPatches(relse_paths, "final", batch_size=2, reference_relse=True)


def test_a_network_with_a_slope_module_learns_from_a_lambda_map_per_patch_its_loss_sees_too(train_paths):
    from kpcn_keras.config import ModelConfig

    model = ModelConfig(slope_channel=True, slope_module=1)
    ds = ShardPatches(train_paths, "diffuse", batch_size=7, model=model, loss_target="reference+noisy",
                      slope_range=(1.0, 8.0), seed=3)
    x, y = ds[0]
    log_input, loss_slope = x[..., -1].astype(np.float64), y[..., 6].astype(np.float64)
    np.testing.assert_allclose(np.exp(log_input), loss_slope, rtol=1e-6)  # the λ the loss weighs is the input's
    assert loss_slope.min() >= 1.0 - 1e-6 and loss_slope.max() <= 8.0 + 1e-5
    varying = [np.ptp(m) > 0 for m in loss_slope]
    assert any(varying)  # λ varies inside a patch
    validation = ShardPatches(train_paths, "diffuse", batch_size=7, model=model, loss_target="reference+noisy",
                              shuffle=False, slope=2.0)
    assert np.all(validation[0][1][..., 6] == 2.0)  # validation keeps one λ
