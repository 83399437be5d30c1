import pickle

import numpy as np
import pytest

from conftest import build_tiny_shards
from kpcn_keras.data import ShardPatches
from prep.shards import ShardError, open_shard, shard_paths


@pytest.fixture
def train_paths(tmp_path):
    return shard_paths(build_tiny_shards(tmp_path).set_dir, "train")


def all_patches(paths, name):
    out = []
    for p in paths:
        with open_shard(p) as f:
            out += list(f[name][()])
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


def test_a_damaged_chunk_is_an_error_naming_the_shard(train_paths):
    path = train_paths[0]
    with open_shard(path) as f:
        chunk = f["diffuse/features"].id.get_chunk_info(0)
    data = bytearray(path.read_bytes())
    data[chunk.byte_offset + 10] ^= 0xFF  # the file keeps its size; its Fletcher-32 no longer matches
    path.write_bytes(bytes(data))
    ds = ShardPatches([path], "diffuse", batch_size=1, shuffle=False)
    with pytest.raises(ShardError, match=f"{path.name}: cannot read patch 0"):
        ds[0]
