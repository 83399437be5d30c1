"""Small inputs: random renders in the AOV layout, folders of them, tiny shard sets and the training
configuration of a tiny network on one."""

from pathlib import Path

import numpy as np

TINY_MODEL = {"width": 6, "depth": 3, "kernel_size": 5}
# the smallest network the training tests train: a step takes milliseconds
TINY_TRAIN_MODEL = {"width": 4, "depth": 2, "kernel_size": 3}


def random_aovs(h: int, w: int, seed: int = 0, variances: bool = True) -> dict:
    """A random render in the AOV layout (float32), for tests that need no real scene."""
    rng = np.random.default_rng(seed)
    aovs = {
        "diffuse": rng.gamma(1.0, 0.5, (h, w, 3)),
        "specular": rng.gamma(0.3, 1.0, (h, w, 3)),
        "albedo": rng.uniform(0, 1, (h, w, 3)),
        "normal": rng.uniform(-1, 1, (h, w, 3)),
        "depth": rng.uniform(0, 10, (h, w)),
    }
    aovs["default"] = aovs["diffuse"] + aovs["specular"]
    if variances:
        for name in ("diffuse", "specular", "color", "albedo", "normal", "depth"):
            aovs[f"{name}Variance"] = rng.gamma(0.5, 0.1, (h, w))
    return {k: v.astype(np.float32) for k, v in aovs.items()}


def make_renders(root: Path, scenes=("a-000", "a-001", "b-000", "b-001"), size=(40, 44),
                 reference_variances: bool = False) -> Path:
    """A folder of random noisy (4 spp) and reference (64 spp) renders in the AOV layout; the references
    without variance layers unless ``reference_variances``."""
    from prep import exr

    for i, scene in enumerate(scenes):
        exr.write_aovs(root / exr.render_filename(scene, 4), random_aovs(*size, seed=10 + i))
        exr.write_aovs(root / exr.render_filename(scene, 64),
                       random_aovs(*size, seed=100 + i, variances=reference_variances))
    return root


def build_tiny_shards(tmp_path: Path, **kw):
    """Random renders cut into a small shard set; returns its ShardConfig."""
    from prep import shards

    make_renders(tmp_path / "renders" / "s", reference_variances=kw.pop("reference_variances", False))
    values = dict(set_name="s", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                  patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5, seed=3)
    values.update(kw)
    cfg = shards.ShardConfig(**values)
    shards.build_shards(cfg, progress=False)
    return cfg


def tiny_train_config(shard_cfg, **kw):
    """A ``TrainConfig`` of :data:`TINY_TRAIN_MODEL` for the shard set ``shard_cfg`` (:func:`build_tiny_shards`):
    4 steps a branch in epochs of 2, batch 2; ``kw`` overrides."""
    from kpcn_keras.config import TrainConfig

    values = dict(set_name=shard_cfg.set_name, shards_root=shard_cfg.out_root, model=TINY_TRAIN_MODEL, steps=4,
                  steps_per_epoch=2, batch_size=2, val_batches=1)
    values.update(kw)
    return TrainConfig.from_preset("cpu", **values)
