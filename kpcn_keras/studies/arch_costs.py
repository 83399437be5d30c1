"""The cost of the cpu, unet and dilated presets' networks side by side, in one process (docs/method.md §4).

Prints one JSON object: per preset the parameter count, the receptive radius (``models.receptive_radius``) and
input alignment, the best and median forward time of one 256 x 256 tile (``predict_on_batch``), the median
Keras training step (forward, SMAPE, backward, Adam; batch and patch as the preset trains: 8 x 65 x 65) with
the same step in plain torch (``studies.plain_torch``), and the best time to denoise one random 1920 x 1080 frame
(features, both branches, recombination; tiles of 256) by a run of the preset trained for one step. The
presets are measured alternately, so that load from other processes hits them alike; ``busy`` lists the
busiest other processes when it starts. Untrained weights: the time of a convolution does not depend on them.

  .venv/bin/python -m kpcn_keras.studies.arch_costs [--repeats 7] [--frames 2]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")

PRESETS = ("cpu", "unet", "dilated")
TILE_SIDE = 256
FRAME = (1080, 1920)


def random_aovs(h: int, w: int, seed: int) -> dict:
    """A random render in the AOV layout (float32), variances included."""
    import numpy as np

    rng = np.random.default_rng(seed)
    aovs = {"diffuse": rng.gamma(1.0, 0.5, (h, w, 3)), "specular": rng.gamma(0.3, 1.0, (h, w, 3)),
            "albedo": rng.uniform(0, 1, (h, w, 3)), "normal": rng.uniform(-1, 1, (h, w, 3)),
            "depth": rng.uniform(0, 10, (h, w))}
    aovs["default"] = aovs["diffuse"] + aovs["specular"]
    for name in ("diffuse", "specular", "color", "albedo", "normal", "depth"):
        aovs[f"{name}Variance"] = rng.gamma(0.5, 0.1, (h, w))
    return {k: v.astype(np.float32) for k, v in aovs.items()}


def timed(fn) -> float:
    begin = time.perf_counter()
    fn()
    return time.perf_counter() - begin


def trained_runs(root: Path) -> dict:
    """One run of each preset, one step a branch, on four random 72 x 70 renders cut into 65 x 65 patches."""
    from kpcn_keras.train import TrainConfig, train
    from prep import exr, shards
    from prep.render.renderset import RenderSet

    renders = RenderSet("s", root / "renders")
    for i, scene in enumerate(("a-000", "a-001", "b-000", "b-001")):
        exr.write_aovs(renders.render_path(scene, 4), random_aovs(72, 70, 10 + i))
        reference = {k: v for k, v in random_aovs(72, 70, 100 + i).items() if not k.endswith("Variance")}
        exr.write_aovs(renders.render_path(scene, 64), reference)
    cfg = shards.ShardConfig(set_name=renders.name, render_root=str(renders.root), out_root=str(root / "shards"),
                             patches_per_image=8, patches_per_shard=8, val_fraction=0.5, seed=3)
    shards.build_shards(cfg, progress=False)
    with contextlib.redirect_stdout(sys.stderr):  # training's one line a phase: stdout is the JSON alone
        return {p: train(TrainConfig.from_preset(p, set_name="s", shards_root=cfg.out_root, steps=1, val_batches=1),
                         root / "runs" / p, verbose=0) for p in PRESETS}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7, help="timed forward passes and training steps a preset")
    ap.add_argument("--frames", type=int, default=2, help="timed 1920 x 1080 frames a preset")
    args = ap.parse_args()

    import keras
    import numpy as np
    import torch

    from kpcn_keras.config import TrainConfig
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.losses import SMAPE
    from kpcn_keras.models import build_branch_model, input_alignment, receptive_radius
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings
    from kpcn_keras.studies.bench import busy_processes
    from kpcn_keras.studies.network_costs import train_step_cost

    out = {"threads": torch.get_num_threads(), "busy": busy_processes(), "presets": {}}
    configs = {p: TrainConfig.from_preset(p) for p in PRESETS}
    models = {p: build_branch_model(c.model) for p, c in configs.items()}
    rng = np.random.default_rng(0)
    tile = rng.uniform(0, 1, (1, TILE_SIDE, TILE_SIDE, 27)).astype(np.float32)
    for p, c in configs.items():
        out["presets"][p] = {"params": models[p].count_params(), "receptive_radius": receptive_radius(c.model),
                             "input_alignment": input_alignment(c.model), "model": c.model.to_dict()}
        models[p].predict_on_batch(tile)  # warm-up
    forward = {p: [] for p in PRESETS}
    for _ in range(args.repeats):
        for p in PRESETS:
            forward[p].append(timed(lambda m=models[p]: m.predict_on_batch(tile)))

    batches = {}
    for p, c in configs.items():
        models[p].compile(optimizer=keras.optimizers.Adam(1e-3), loss=SMAPE())
        x = rng.uniform(0, 1, (c.batch_size, 65, 65, 27)).astype(np.float32)
        batches[p] = (x, rng.uniform(0, 1, x.shape[:3] + (3,)).astype(np.float32))
        for _ in range(2):
            models[p].train_on_batch(*batches[p])
    steps = {p: [] for p in PRESETS}
    for _ in range(args.repeats):
        for p in PRESETS:
            steps[p].append(timed(lambda p=p: models[p].train_on_batch(*batches[p])))
    for p, c in configs.items():
        twin = train_step_cost(c.model, batch_size=c.batch_size, patch=65, steps=max(3, args.repeats // 2))
        out["presets"][p].update(
            forward_256_best_ms=1e3 * min(forward[p]), forward_256_median_ms=1e3 * statistics.median(forward[p]),
            train_step_median_s=statistics.median(steps[p]), train_step_best_s=min(steps[p]),
            batch=c.batch_size, plain_torch_step_s=twin["torch_s"], keras_over_torch=twin["ratio"])

    with tempfile.TemporaryDirectory() as tmp:
        runs = trained_runs(Path(tmp))
        denoisers = {p: Denoiser.from_run(Run(runs[p]), InferenceSettings(tile=TILE_SIDE)) for p in PRESETS}
        for d in denoisers.values():
            d.warm_up()
        frame = random_aovs(*FRAME, seed=1)
        seconds = {p: [] for p in PRESETS}
        for _ in range(args.frames):
            for p in PRESETS:
                seconds[p].append(timed(lambda d=denoisers[p]: d(frame)))
        for p in PRESETS:
            out["presets"][p].update(frame_1080p_best_s=min(seconds[p]), frame_margin=denoisers[p].margin,
                                     frame_tile=denoisers[p].tile)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
