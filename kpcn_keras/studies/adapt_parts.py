"""Which part of a model to adapt to a frame: the kernel head of its own networks, or a post-correction after them.

For each pair of renders of a frame (two seeds, half the samples each) and its reference, both parts are trained
for the same steps on the same loss (``adapt.n2n_loss``: A -> B and B -> A, one crop a step, Adam) and the mean
of the pair denoised by each is measured against the reference (relMSE, and its ratio to a comparison frame, e.g.
Blender's own denoised frame of one render of all the samples), at several step counts. The kernel head: the last
1x1 convolution of each branch network, the trunk frozen and run once a crop (its activations kept); the
post-correction: ``adapt.Adapter``'s network, guard off (every checkpoint measured as it is). Writes
``reports/adapt_parts.json`` and prints a table; docs/adapt.md §4 cites it.

  python -m kpcn_keras.studies.adapt_parts data/cycles/validation --scenes val-studio-000,val-studio-001 \\
      --spp 16 --steps 40,100,200
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import keras
import numpy as np

from kpcn_keras.adapt import Adapter, correct, descend, n2n_loss
from kpcn_keras.batch import ReadOptions, read_frame, read_halves
from kpcn_keras.models import network_input
from kpcn_keras.run import Run
from kpcn_keras.serving import Serving
from kpcn_keras.settings import AdaptSettings
from prep import features, layouts, metrics
from prep.colour import ALBEDO_EPS
from prep.render.blender.catalogue import denoised_name, frame_name, pair_names


class HeadTuning:
    """The kernel head (last 1x1 convolution) of each branch network of ``denoiser``, fine-tuned on the pair."""

    def __init__(self, denoiser, a: dict, b: dict, crop: int = 128, seed: int = 0):
        self.denoiser = denoiser
        self.models = {}
        for branch, model in denoiser.models.items():
            copy = keras.models.clone_model(model)
            copy.set_weights(model.get_weights())
            head = [layer for layer in copy.layers if isinstance(layer, keras.layers.Conv2D)][-1]
            cut = head.input
            self.models[branch] = (keras.Model(copy.input, cut), keras.Model([cut, copy.input], copy.output), copy)
        self.params = [w for _, tail, _ in self.models.values() for w in tail.trainable_weights]
        self.rng = np.random.default_rng(seed)
        self.crops = [c for x, y in ((a, b), (b, a)) for c in self._crops(x, y, crop)]

    def _crops(self, half: dict, other: dict, side: int) -> list:
        import torch

        d = self.denoiser
        given = d.given(half)
        h, w = given["depth"].shape
        scale = features.depth_scale(given["depth"])
        out = []
        for y0 in range(0, h, side):
            for x0 in range(0, w, side):
                tile = (y0, min(y0 + side, h), x0, min(x0 + side, w))
                m = d.margin
                win = (max(y0 - m, 0), min(tile[1] + m, h), max(x0 - m, 0), min(tile[3] + m, w))
                inputs = {}
                for branch, (frozen, _, _) in self.models.items():
                    x = keras.ops.convert_to_tensor(network_input(
                        features.branch_features(given, branch, win, scale=scale), d.model_config, branch)[None])
                    with torch.no_grad():
                        inputs[branch] = (frozen(x), x)
                albedo = np.clip(d.albedo_tile(given, tile, win, scale), 0, 1) + ALBEDO_EPS
                kept = np.s_[tile[0] - win[0] : tile[1] - win[0], tile[2] - win[2] : tile[3] - win[2]]
                target = np.asarray(other["default"][tile[0] : tile[1], tile[2] : tile[3]], np.float32)
                out.append((inputs, keras.ops.convert_to_tensor(albedo.astype(np.float32)), kept,
                            keras.ops.convert_to_tensor(target)))
        return out

    def _predict(self, crop):
        inputs, albedo, kept, _ = crop
        total = 0.0
        for branch, (_, tail, _) in self.models.items():
            log = tail(list(inputs[branch]))[0][kept]
            total = total + (keras.ops.expm1(log) * albedo if branch == "diffuse" else keras.ops.expm1(log))
        return total

    def train(self, steps: int, learning_rate: float = 1e-3) -> None:

        opt = keras.optimizers.Adam(learning_rate=learning_rate)
        opt.build(self.params)
        for _ in range(steps):
            crop = self.crops[int(self.rng.integers(len(self.crops)))]
            descend(self.params, opt, n2n_loss(self._predict(crop), crop[3]))

    def denoise(self, layers: dict) -> np.ndarray:
        from kpcn_keras.denoise import Denoiser

        d = self.denoiser
        nets = {("shared" if d.model_config.branch_channels else b): m[2] for b, m in self.models.items()}
        return Denoiser(d.run, d.record, nets, None, d.settings, d.albedo_network)(layers)["default"]


def _train_post(adapter: Adapter, opt, steps: int) -> None:
    """``steps`` steps of the adapter's own loss on its crops, every checkpoint kept as it is (no guard)."""
    for _ in range(steps):
        adapter.step(opt)


def measure(folder: Path, scene: str, spp: int, steps: list[int], model: Run, seed: int) -> dict:
    """Both parts on ``scene``'s pair of ``spp`` samples in ``folder``: relMSE of the pair's mean after each count
    of ``steps``, the unadapted model's, and the comparison frame's (Blender's denoised frame of one render)."""
    a_path, b_path = (folder / n for n in pair_names(scene, spp))
    reading = ReadOptions(pair=b_path)
    a, b = read_halves(a_path, reading)
    mean = read_frame(a_path, reading).layers
    ref = layouts.read(folder / frame_name(scene, 2048)).layers["default"]
    comparison = layouts.read(folder / denoised_name(scene, spp)).layers["default"]
    denoiser = Serving(model).plain(a.inputs)
    rel = lambda x: metrics.relmse(x, ref)  # noqa: E731
    base = denoiser(mean)
    row = {"scene": scene, "spp": spp, "comparison": rel(comparison), "unadapted": rel(base["default"]),
           "head": {}, "post": {}, "head_s": {}, "post_s": {}}
    head = HeadTuning(denoiser, a.layers, b.layers, seed=seed)
    done, begin = 0, time.perf_counter()
    for n in steps:
        head.train(n - done)
        done = n
        row["head"][n], row["head_s"][n] = rel(head.denoise(mean)), time.perf_counter() - begin
    post = Adapter(denoiser, [(a.layers, b.layers)], AdaptSettings(seed=seed))
    opt = keras.optimizers.Adam(learning_rate=post.settings.learning_rate)
    opt.build(post.net.trainable_weights)
    done, begin = 0, time.perf_counter()
    for n in steps:
        _train_post(post, opt, n - done)
        done = n
        row["post"][n] = rel(correct(post.net, base, mean, 256)["default"])
        row["post_s"][n] = time.perf_counter() - begin
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folder", help="a folder of pairs, references and comparison frames (kpcn cycles-validation's)")
    ap.add_argument("--scenes", required=True, help="comma-separated scenes")
    ap.add_argument("--spp", type=int, default=16, help="the frames' total samples (each half has half)")
    ap.add_argument("--steps", default="40,100,200", help="step counts measured, comma-separated")
    ap.add_argument("--model", default="models/default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="reports/adapt_parts.json")
    a = ap.parse_args(argv)
    steps = sorted(int(s) for s in a.steps.split(","))
    rows = [measure(Path(a.folder), scene, a.spp, steps, Run(a.model), a.seed) for scene in a.scenes.split(",")]
    for row in rows:
        c = row["comparison"]
        print(f"{row['scene']} {row['spp']} spp: unadapted {row['unadapted'] / c:.3f}x; "
              + "; ".join(f"{n} steps head {row['head'][n] / c:.3f}x post {row['post'][n] / c:.3f}x" for n in steps))
    record = {"command": "python -m kpcn_keras.studies.adapt_parts " + " ".join(argv or []), "folder": a.folder,
              "model": a.model, "seed": a.seed, "metric": "relmse", "comparison": "Blender's denoised frame of one "
              "render of all the samples", "rows": rows}
    out = Path(a.out)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    tmp.replace(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
