"""``kpcn bench``: what accuracy costs in time, written to ``reports/accuracy_time.{md,json,png}``.

The contract:

- **Frames.** The held-out scenes of the shard set, each rendered again at every spp of the raw ladder
  (``BenchConfig.raw_spp``) and of the denoisers' ladder (``input_spp``), timed: *time = render time*. A
  render takes the seed the render set gave that scene at that spp (``prep.render.renderset.render_seed``), so
  the inputs are the set's own files, and the reference is the set's reference of the scene. The scenes
  come from the render set's ``config.json``: the bench needs a set made by ``kpcn render``.
- **Methods**, each on the same frames: raw Monte Carlo; every configuration of ``configurations`` (and the
  presets) trained for ``budget`` seconds (``kpcn compare``'s planning: :func:`kpcn_keras.compare.plan_and_train`,
  in ``<runs_root>/<set>-<budget>s-seed<seed>/<name>``), a multiscale run with and without its compositor;
  non-local means; Intel Open Image Denoise when ``pyoidn`` is installed. A point is (input spp, seconds =
  render + denoise, relMSE, DSSIM, relSE p99.9); a denoiser's seconds per frame is its own call on that
  frame after a warm-up (model loading is a stage cost, reported apart).
- **Summaries over scenes**: the geometric mean of relMSE and relSE p99.9 (the arithmetic mean is kept in the
  JSON, but one scene whose reference still has fireflies carries it: see the README) and the mean DSSIM.
- **Equal-error spp** (:func:`equal_error_spp`): per scene, the spp at which raw Monte Carlo reaches the
  denoised relMSE, interpolated in log-log between the ladder's points, or outside them extrapolated from
  the least-squares fit e(n) = a / n + b of the raw curve (b: the reference's own noise, which every
  method's error contains alike); "below the floor" when the denoised error is under b. The saving is that
  spp over the input spp, and the raw render time at that spp (a straight line through the ladder's
  seconds) over render + denoise time. The report gives the median over scenes and each scene's value.
- **Training cost**: each preset of ``presets`` trained for each of :meth:`BenchConfig.budgets`, its held-out
  scores against the seconds its phases took.
- **Stage costs** (:func:`stage_costs`): render samples per second; features (numba against the float64 numpy
  reference and the EXR decode); shard layouts side by side (write patches/s, bytes, batch read) and
  ``kpcn shards`` end to end; reading a training batch against a training step; a Keras training step
  against the same network in plain torch; kernel application against the memory-bandwidth floor (k = 13,
  21); inference start-up, then a frame of the held-out size and a ``large_frame`` frame against OIDN for
  the default and the fast configuration (:data:`INFERENCE`), and ``kpcn denoise`` of the large frame as a
  command with its own peak memory.
- **Writes** ``accuracy_time.json`` (every number, the command, the date, the machine and what else was
  running), ``accuracy_time.md`` and ``accuracy_time.png`` in ``out_dir``, each atomically. :data:`SCHEMA`
  lists the figures a record must have; :func:`missing_figures` checks one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import resource
import statistics
import subprocess
import time
from datetime import date, datetime
from pathlib import Path

import numpy as np

from kpcn_keras.config import BenchConfig, CompareConfig, ModelConfig
from prep.errors import KpcnError
from prep.files import atomic_write_text, check_writable, pyplot, read_json, save_png

REPORT = "accuracy_time"
KERNEL_SIZES = (13, 21)  # the kernel sizes whose application is measured against the bandwidth floor
SHARD_READ_BATCHES = 20
SHARD_LAYOUT_IMAGES = 4  # (noisy, reference) pairs whose patches are written in every shard layout
GEOMEAN_FLOOR = 1e-300  # an error of exactly 0 (a perfect frame) counts as this in a geometric mean
OURS = "cpu"  # the configuration of the headline: the default preset
INFERENCE = (OURS, "kernel-5")  # whose frames are timed against OIDN: the default, and the fast configuration

# Every figure a bench record must have: a dotted path into the JSON, where "*" means every element.
SCHEMA = (
    "date", "command", "machine.cpus", "machine.load_average_before", "machine.load_average_after",
    "machine.busy_before", "machine.busy_after", "machine.torch_threads", "machine.numba_threads",
    "config.raw_spp", "config.input_spp", "scenes",
    "methods.*.name", "methods.*.kind", "methods.*.points.*.spp", "methods.*.points.*.seconds",
    "methods.*.points.*.relmse", "methods.*.points.*.dssim", "methods.*.points.*.relse_p999",
    "methods.*.points.*.frames",
    "equal_error.*.method", "equal_error.*.spp", "equal_error.*.median_equal_spp",
    "equal_error.*.median_time_saving", "equal_error.*.scenes",
    "training.*.preset", "training.*.budget", "training.*.training_seconds", "training.*.relmse",
    "stages.render.samples_per_s",
    "stages.features.numba_s", "stages.features.numpy_s", "stages.features.exr_decode_s",
    "stages.shard_layouts.layouts", "stages.shard_layouts.default", "stages.shard_write.patches_per_s",
    "stages.shard_write.sync_s",
    "stages.shard_read.batch_s", "stages.shard_read.step_s", "stages.shard_read.ratio",
    "stages.train_step.keras_s", "stages.train_step.torch_s", "stages.train_step.ratio",
    "stages.kernel_application.*.k", "stages.kernel_application.*.seconds",
    "stages.kernel_application.*.floor_seconds", "stages.kernel_application.*.ratio",
    "stages.inference.load_s", "stages.inference.warm_up_s", "stages.inference.frame_ms",
    "stages.inference.configurations", "stages.inference.large.ours_s", "stages.inference.large.wall_s",
    "stages.inference.large.peak_rss_mb",
)


# ---------------------------------------------------------------- the arithmetic


def fit_inverse_law(spp, errors) -> tuple[float, float]:
    """Least-squares (a, b) of e(n) = a / n + b over the points, each residual relative to its error (so
    that the small errors of the high spp count as much as the large ones)."""
    n = np.asarray(spp, np.float64)
    e = np.asarray(errors, np.float64)
    design = np.stack([1.0 / n, np.ones_like(n)], axis=1) / e[:, None]
    (a, b), *_ = np.linalg.lstsq(design, np.ones_like(e), rcond=None)
    return float(a), float(b)


def equal_error_spp(spp, errors, target: float, *, extrapolate: bool = True) -> dict:
    """The spp at which a raw curve (``errors`` at ``spp``, ascending spp) reaches ``target``.

    ``{"spp": n, "how": ...}``: "interpolated" (log-log, between the first pair of neighbours that bracket
    the target), "extrapolated" (from :func:`fit_inverse_law`; beyond the ladder on either side),
    "below the floor" (the target is under the fit's floor b: raw Monte Carlo measured against this
    reference never gets there; n is inf), "no trend" (the fit does not decrease: n is nan) or
    "beyond the ladder" (outside it, with ``extrapolate=False``; n is nan).
    """
    n = np.asarray(spp, np.float64)
    e = np.asarray(errors, np.float64)
    if len(n) < 2 or len(n) != len(e) or np.any(np.diff(n) <= 0) or not np.all(e > 0) or not target > 0:
        raise ValueError(f"need >= 2 ascending spp with positive errors and a positive target; got spp "
                         f"{list(n)}, errors {list(e)}, target {target!r}")
    for i in range(len(n) - 1):
        lo, hi = sorted((e[i], e[i + 1]))
        if lo <= target <= hi:
            if e[i] == e[i + 1]:
                return {"spp": float(n[i]), "how": "interpolated"}
            t = (math.log(target) - math.log(e[i])) / (math.log(e[i + 1]) - math.log(e[i]))
            return {"spp": float(math.exp(math.log(n[i]) + t * (math.log(n[i + 1]) - math.log(n[i])))),
                    "how": "interpolated"}
    if not extrapolate:
        return {"spp": math.nan, "how": "beyond the ladder"}
    a, b = fit_inverse_law(n, e)
    if a <= 0:
        return {"spp": math.nan, "how": "no trend"}
    if target <= b:
        return {"spp": math.inf, "how": "below the floor"}
    return {"spp": a / (target - b), "how": "extrapolated"}


def render_seconds_at(spp, seconds, n: float) -> float:
    """Render time at ``n`` spp from the least-squares line t = t0 + c n through the ladder's timings."""
    if not math.isfinite(n):
        return n
    c, t0 = np.polyfit(np.asarray(spp, np.float64), np.asarray(seconds, np.float64), 1)
    return float(t0 + c * n)


def geometric_mean(values) -> float:
    values = np.asarray(values, np.float64)
    return float(np.exp(np.mean(np.log(np.maximum(values, GEOMEAN_FLOOR)))))


def summarise(frames: list[dict]) -> dict:
    """The summary of a point over its scenes (module docstring)."""
    return {"relmse": geometric_mean([f["relmse"] for f in frames]),
            "dssim": float(np.mean([f["dssim"] for f in frames])),
            "relse_p999": geometric_mean([f["relse_p999"] for f in frames]),
            "mean_relmse": float(np.mean([f["relmse"] for f in frames]))}


def missing_figures(record: dict) -> list[str]:
    """The entries of :data:`SCHEMA` that ``record`` lacks, with list indices where a "*" was expanded (an
    empty list has none of what its elements should have)."""
    missing = []

    def walk(value, parts, path):
        if not parts:
            return
        head, rest = parts[0], parts[1:]
        absent = ".".join([path, *parts]).lstrip(".")  # the whole schema entry from here on
        if head == "*":
            if not isinstance(value, list) or not value:
                missing.append(absent)
                return
            for i, item in enumerate(value):
                walk(item, rest, f"{path}.{i}")
            return
        if not isinstance(value, dict) or head not in value or value[head] is None:
            missing.append(absent)
            return
        walk(value[head], rest, f"{path}.{head}")

    for entry in SCHEMA:
        walk(record, entry.split("."), "")
    return missing


# ---------------------------------------------------------------- frames


def held_out_scenes(cfg: BenchConfig) -> list[dict]:
    """The held-out scenes of the set: ``name``, ``scene`` (a Scene), ``seeds`` (spp -> seed), the render
    set's ``seed``/``family``/``index``, ``width``, ``height``, ``reference`` (colour) and its ``reference_spp``."""
    from prep import exr
    from prep.render.scene import Scene
    from prep.shards import ShardSet

    sset = ShardSet(Path(cfg.shards_root) / cfg.set_name)
    manifest = sset.complete_manifest()
    refs = {}
    for _, ref in sset.pairs(manifest, "val"):
        refs[exr.parse_render_filename(ref)[0]] = Path(ref)
    if not refs:
        raise KpcnError(f"{sset.dir}: no held-out scenes to measure on")
    render_dir = next(iter(refs.values())).parent
    meta_path = render_dir / "config.json"
    if not meta_path.is_file():
        raise KpcnError(f"{meta_path}: not found; the bench renders the held-out scenes again at every spp of "
                        "its ladder, so it needs a render set made by 'kpcn render'")
    meta = read_json(meta_path, "render set record", keys=("config", "scenes"))
    records = {r["name"]: r for r in meta["scenes"]}
    scenes = []
    for name, ref_path in sorted(refs.items()):
        if name not in records:
            raise KpcnError(f"{meta_path}: no record of held-out scene {name!r}; the bench needs the scene "
                            "description that 'kpcn render' writes there")
        rec = records[name]
        scenes.append({"name": name, "scene": Scene.from_dict(rec["scene"]), "family": rec["family"],
                       "index": rec["index"], "set_seed": meta["config"]["seed"],
                       "seeds": {int(k): int(v) for k, v in rec["seeds"].items()},
                       "width": meta["config"]["width"], "height": meta["config"]["height"],
                       "reference_spp": exr.parse_render_filename(ref_path)[1],
                       "reference": exr.read_aovs(ref_path, variances=False)["default"]})
    return scenes


def render_ladder(cfg: BenchConfig, scenes: list[dict], log=print, progress: bool = True) -> tuple[dict, dict]:
    """Render every scene at every spp of both ladders, timed. Returns ``seconds[(scene, spp)]`` and the AOVs
    of the denoisers' inputs ``inputs[(scene, spp)]``; the raw method's scores are added to each scene."""
    from tqdm import tqdm

    from prep import metrics
    from prep.render.frame import render
    from prep.render.renderset import render_seed

    counts = sorted(set(cfg.raw_spp) | set(cfg.input_spp))
    seconds, inputs = {}, {}
    for s in scenes:
        s["raw"] = {}
        too_many = [n for n in counts if n >= s["reference_spp"]]
        if too_many:
            raise KpcnError(f"spp {too_many} of the ladder are not below {s['name']}'s reference "
                            f"({s['reference_spp']} spp): the error would measure the reference's noise")
    for s in scenes:  # compile (or load) each scene's kernel (one per set of effects) before anything is timed
        render(s["scene"], 2, 0, 8, 8)
    bar = tqdm(total=len(scenes) * len(counts), desc="bench renders", unit="render", disable=not progress)
    for s in scenes:
        for n in counts:
            seed = s["seeds"].get(n, render_seed(s["set_seed"], s["family"], s["index"], n))
            bar.set_postfix_str(f"{s['name']} {n} spp")
            start = time.perf_counter()
            aovs = render(s["scene"], n, seed, s["width"], s["height"])
            seconds[(s["name"], n)] = time.perf_counter() - start
            if n in cfg.raw_spp:
                s["raw"][n] = {m: f(aovs["default"], s["reference"]) for m, f in
                               (("relmse", metrics.relmse), ("dssim", metrics.dssim),
                                ("relse_p999", metrics.relse_p999))}
            if n in cfg.input_spp:
                inputs[(s["name"], n)] = aovs
            bar.update(1)
    bar.close()
    total = sum(seconds.values())
    log(f"rendered {len(seconds)} frames in {total:.1f} s")
    return seconds, inputs


def _point(spp: int, seconds: list[float], frames: list[dict], extra: dict | None = None) -> dict:
    return {"spp": spp, "seconds": float(np.mean(seconds)), **(extra or {}), **summarise(frames), "frames": frames}


def raw_method(cfg: BenchConfig, scenes: list[dict], seconds: dict) -> dict:
    points = []
    for n in cfg.raw_spp:
        frames = [{"scene": s["name"], "seconds": seconds[(s["name"], n)], **s["raw"][n]} for s in scenes]
        points.append(_point(n, [f["seconds"] for f in frames], frames))
    return {"name": "raw Monte Carlo", "kind": "raw", "what": "the render itself at more samples", "points": points}


def denoiser_method(name: str, kind: str, what: str, fn, cfg: BenchConfig, scenes: list[dict], seconds: dict,
                    inputs: dict, extra: dict | None = None) -> dict:
    """One denoiser's points: ``fn(aovs) -> colour`` on every input, timed per call."""
    from prep import metrics

    fn(inputs[(scenes[0]["name"], cfg.input_spp[0])])  # warm-up: one-time set-up is not a frame's time
    points = []
    for n in cfg.input_spp:
        frames = []
        for s in scenes:
            start = time.perf_counter()
            out = fn(inputs[(s["name"], n)])
            denoise_s = time.perf_counter() - start
            render_s = seconds[(s["name"], n)]
            frames.append({"scene": s["name"], "render_s": render_s, "denoise_s": denoise_s,
                           "seconds": render_s + denoise_s, "relmse": metrics.relmse(out, s["reference"]),
                           "dssim": metrics.dssim(out, s["reference"]),
                           "relse_p999": metrics.relse_p999(out, s["reference"])})
        points.append(_point(n, [f["seconds"] for f in frames], frames,
                             {"denoise_s": float(np.median([f["denoise_s"] for f in frames]))}))
    return {"name": name, "kind": kind, "what": what, **(extra or {}), "points": points}


# ---------------------------------------------------------------- the trained configurations


def train_runs(cfg: BenchConfig, *, overrides: dict | None, verbose, log) -> dict:
    """``budget -> {name: plan entry}``: the configurations at the budget, the presets at every budget."""
    from kpcn_keras.compare import plan_and_train

    plans, probes = {}, {}
    # the budget itself first: its probes serve the presets' smaller budgets (a probe times steps, not budgets)
    for budget in sorted(cfg.budgets(), key=lambda b: b != cfg.budget):
        names = tuple(cfg.presets) if budget != cfg.budget else \
            tuple(dict.fromkeys(cfg.configurations + tuple(cfg.presets)))
        if not names:
            continue
        ccfg = CompareConfig(set_name=cfg.set_name, shards_root=cfg.shards_root, runs_root=cfg.runs_root,
                             out_dir=cfg.out_dir, budget=budget, configurations=names, seed=cfg.seed)
        log(f"training {len(names)} configurations for {budget:g} s each")
        plans[budget] = plan_and_train(ccfg, overrides=overrides, verbose=verbose, log=log, probes=probes)
        probes.update(plans[budget])
    return dict(sorted(plans.items()))


def network_methods(cfg: BenchConfig, plans: dict, scenes, seconds, inputs, log) -> tuple[list[dict], list[dict]]:
    """The error-against-time methods of the trained runs at the budget, and the training-cost rows."""
    from kpcn_keras.compare import _training_seconds, describe
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run

    methods, training = [], []
    for budget, runs in plans.items():
        for name, plan in runs.items():
            run = Path(plan["run"])
            train_cfg = _train_config(plan)
            variants = [(name, True)] + ([(f"{name} (compositor off)", False)] if train_cfg.compositor else [])
            for label, multiscale in variants:
                start = time.perf_counter()
                denoiser = Denoiser.from_run(Run(run), multiscale=multiscale)
                load_s = time.perf_counter() - start
                extra = {"run": str(run), "budget": budget, "load_s": load_s,
                         "training_seconds": _training_seconds(run), "phase_steps": plan["phase_steps"]}
                method = denoiser_method(label, "network", describe(name, train_cfg),
                                         lambda aovs, d=denoiser: d(aovs)["default"], cfg, scenes, seconds, inputs,
                                         extra)
                everything = [f for p in method["points"] for f in p["frames"]]
                if multiscale and name in cfg.presets:
                    training.append({"preset": name, "budget": budget, "run": str(run),
                                     "training_seconds": extra["training_seconds"], **summarise(everything)})
                if budget == cfg.budget and (name in cfg.configurations or name in cfg.presets):
                    methods.append(method)
                log(f"[{label}, {budget:g} s] held-out relMSE (geometric mean) "
                    f"{summarise(everything)['relmse']:.4f}")
    return methods, training


def baseline_methods(cfg: BenchConfig, scenes, seconds, inputs, log) -> list[dict]:
    from prep import baselines

    out = [denoiser_method("NLM", "baseline", "scikit-image non-local means on the colour, told the noise level",
                           lambda a: baselines.nlm_denoise(a["default"], a["colorVariance"]), cfg, scenes,
                           seconds, inputs)]
    if baselines.oidn_available():
        out.append(denoiser_method("OIDN", "baseline", "Intel Open Image Denoise, RT filter with albedo and "
                                   "normal, high quality (pretrained)", baselines.oidn_denoise, cfg, scenes,
                                   seconds, inputs))
    else:
        log("[OIDN] not installed (pip install '.[oidn]'): no OIDN curve")
    return out


def equal_error_rows(cfg: BenchConfig, methods: list[dict], scenes: list[dict], seconds: dict) -> list[dict]:
    """For each denoiser (ours, OIDN, NLM) and input spp: the per-scene equal-error spp and time saving."""
    rows = []
    wanted = [OURS, "OIDN", "NLM"]
    for method in sorted((m for m in methods if m["name"] in wanted), key=lambda m: wanted.index(m["name"])):
        for point in method["points"]:
            per_scene = []
            for s, frame in zip(scenes, point["frames"]):
                ladder = [s["raw"][n]["relmse"] for n in cfg.raw_spp]
                eq = equal_error_spp(cfg.raw_spp, ladder, frame["relmse"])
                raw_s = render_seconds_at(cfg.raw_spp, [seconds[(s["name"], n)] for n in cfg.raw_spp], eq["spp"])
                per_scene.append({"scene": s["name"], "equal_spp": eq["spp"], "how": eq["how"],
                                  "spp_saving": eq["spp"] / point["spp"], "raw_seconds": raw_s,
                                  "time_saving": raw_s / frame["seconds"]})
            finite = [p for p in per_scene if not math.isnan(p["equal_spp"])]
            rows.append({"method": method["name"], "spp": point["spp"],
                         "median_equal_spp": _median([p["equal_spp"] for p in finite]),
                         "median_spp_saving": _median([p["spp_saving"] for p in finite]),
                         "median_time_saving": _median([p["time_saving"] for p in finite]),
                         "hows": {h: sum(p["how"] == h for p in per_scene) for h in {p["how"] for p in per_scene}},
                         "scenes": per_scene})
    return rows


def _median(values) -> float:
    # inf (below the floor) sorts last, so a median of mostly finite values stays finite
    return float(statistics.median(values)) if values else math.nan


# ---------------------------------------------------------------- stage costs


def stage_costs(cfg: BenchConfig, scenes, seconds, inputs, plans, log) -> dict:
    """The costs of each stage (module docstring); every function it calls measures side by side."""
    from kpcn_keras import stage_costs as net_costs
    from prep import stage_costs as prep_costs
    from prep.shards import ShardSet

    pixels = {s["name"]: s["width"] * s["height"] for s in scenes}
    stages = {"render": {
        "samples_per_s": sum(pixels[name] * n for name, n in seconds) / sum(seconds.values()),
        "per_scene": {name: sum(pixels[name] * n for n in cfg.raw_spp) / sum(seconds[(name, n)] for n in cfg.raw_spp)
                      for name in pixels}}}
    sset = ShardSet(Path(cfg.shards_root) / cfg.set_name)
    manifest = sset.complete_manifest()
    val_pairs = sset.pairs(manifest, "val")
    log("stage costs: features")
    stages["features"] = prep_costs.feature_costs(val_pairs[0][0], repeats=cfg.repeats)
    log("stage costs: shard layouts")
    scratch = Path(cfg.runs_root) / "shard-layouts"
    train_pairs = [(str(a), str(b)) for a, b in sset.pairs(manifest, "train")]
    stages["shard_layouts"] = prep_costs.shard_layout_costs(train_pairs[:SHARD_LAYOUT_IMAGES], scratch,
                                                            repeats=cfg.repeats, seed=cfg.seed,
                                                            patch_size=manifest["patch_size"])
    log("stage costs: a training step, Keras and plain torch")
    ours = _train_config(plans.get(cfg.budget, {}).get(OURS))
    model_config, batch = ours.model, ours.batch_size
    stages["train_step"] = net_costs.train_step_cost(model_config, batch_size=batch)
    stages["shard_read"] = shard_read_cost(sset, manifest, model_config, batch, cfg.seed)
    stages["shard_read"]["step_s"] = stages["train_step"]["keras_s"]
    stages["shard_read"]["ratio"] = stages["shard_read"]["batch_s"] / stages["train_step"]["keras_s"]
    log("stage costs: kernel application")
    bandwidth = net_costs.memory_bandwidth()  # one floor for every kernel size of the report
    stages["kernel_application"] = [net_costs.kernel_application_cost(k, scenes[0]["height"], scenes[0]["width"],
                                                                      repeats=cfg.repeats, bandwidth=bandwidth)
                                    for k in KERNEL_SIZES]
    log("stage costs: inference")
    stages["repeats"] = cfg.repeats
    stages["inference"] = inference_cost(cfg, plans.get(cfg.budget, {}), inputs[(scenes[0]["name"], cfg.input_spp[0])])
    return stages


def _train_config(plan: dict | None):
    """The training configuration of a planned run, or the default one where the run is not in the bench."""
    from kpcn_keras.config import TrainConfig
    from kpcn_keras.run import Run

    if plan is None:
        return TrainConfig()
    return Run(plan["run"]).record().train


def shard_read_cost(sset, manifest, model_config: ModelConfig, batch_size: int, seed: int) -> dict:
    """Seconds of reading one training batch (``ShardPatches``, augmented, diffuse) from the set's shards:
    the median of :data:`SHARD_READ_BATCHES` batches after one that opens the files."""
    from kpcn_keras.data import ShardPatches

    paths = [e.path for e in sset.verified_shards("train", manifest, rounds=(0,))]
    data = ShardPatches(paths, "diffuse", batch_size, steps=SHARD_READ_BATCHES + 1, model=model_config,
                        seed=seed, augment=True)
    data[0]
    times = []
    for i in range(1, SHARD_READ_BATCHES + 1):
        start = time.perf_counter()
        data[i]
        times.append(time.perf_counter() - start)
    return {"batch_s": float(np.median(times)), "batch_size": batch_size, "batches": SHARD_READ_BATCHES,
            "patches_per_s": batch_size / float(np.median(times))}


def _tile_to(aovs: dict, width: int, height: int) -> dict:
    """A ``width`` x ``height`` frame made of copies of ``aovs`` (a large frame from a small render)."""
    out = {}
    for k, v in aovs.items():
        h, w = v.shape[:2]
        reps = (-(-height // h), -(-width // w)) + (1,) * (v.ndim - 2)
        out[k] = np.ascontiguousarray(np.tile(v, reps)[:height, :width])
    return out


def _alternating_best(fns: dict, frame: dict, repeats: int) -> dict:
    """Best seconds of each of ``fns`` on ``frame``, called in turn ``repeats`` times after one warm-up call
    each, so that a slow spell of a shared machine hits them alike."""
    for fn in fns.values():
        fn(frame)
    best = {name: math.inf for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn(frame)
            best[name] = min(best[name], time.perf_counter() - start)
    return best


def shards_command_cost(set_dir: Path, scratch: Path) -> dict:
    """``kpcn shards`` of the shard set ``set_dir``'s renders with its own options, into a fresh set under
    ``scratch``, in a process of its own as a user runs it: its wall time,
    start-up included, with the thread count it got (shards are cut by that many processes); then the
    time ``sync`` takes after it, since the command leaves the last of its bytes to the system to write."""
    import shutil
    import sys

    from kpcn_keras.cli import command_line
    from prep import threads
    from prep.shards import SHARD_LAYOUT, ShardConfig, ShardSet, round_name

    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    given = ShardConfig(**ShardSet(set_dir).complete_manifest()["config"])
    workers = threads.requested() or threads.default_threads()
    # the options that differ from the defaults (some fields have no flag; command_line refuses those)
    default = dataclasses.asdict(ShardConfig())
    options = {k: v for k, v in dataclasses.asdict(given).items() if k != "command" and v != default[k]}
    args = command_line("shards", {"threads": workers, **options, "out_root": str(scratch)})
    os.sync()  # the disk owes nothing from before
    memory = _meminfo_mb()
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "kpcn_keras.cli", "-q", "shards", *args], capture_output=True,
                         text=True)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime - children.ru_utime) + (after.ru_stime - children.ru_stime)
    if res.returncode != 0:
        raise KpcnError(f"kpcn shards {' '.join(args)} failed: {res.stderr.strip()[-500:]}")
    start = time.perf_counter()
    os.sync()
    sync_s = time.perf_counter() - start
    sset = ShardSet(scratch / given.set_name)
    listed = sset.complete_manifest()["rounds"][round_name(0)]["shards"]
    count = sum(s["patches"] for s in listed)
    size = sum(sset.resolve(s["path"]).stat().st_size for s in listed)
    shutil.rmtree(scratch)
    return {"command": f"kpcn shards {' '.join(args)}", "patches": count, "shards": len(listed),
            "seconds": seconds, "patches_per_s": count / seconds, "sync_s": sync_s, "bytes_per_patch": size / count,
            "cpu_s": cpu_s, "workers": workers, "layout": SHARD_LAYOUT.name, "memory_mb_before": memory}


def _meminfo_mb() -> dict:
    """MemAvailable, Dirty and this process's resident size (MB), Linux; {} elsewhere. The share of memory
    that may hold written-but-unflushed pages scales with what is available, so it says whether a command
    that writes gigabytes ran at the speed of the page cache or of the disk."""
    from prep.processes import proc_megabytes

    return {**proc_megabytes("/proc/meminfo", ("MemAvailable", "Dirty")),
            **proc_megabytes("/proc/self/status", ("VmRSS",))}


def denoise_command_cost(run: str, frame: dict, scratch: Path) -> dict:
    """``kpcn denoise`` of ``frame`` (written to an EXR in ``scratch``) in a process of its own, as a user runs
    it: its wall time, start-up included, what it printed about itself, and the peak resident memory it
    printed (its own: a parent's rusage of children would count the bench's size, copied at fork)."""
    import sys

    from prep import exr

    scratch.mkdir(parents=True, exist_ok=True)
    h, w = frame["default"].shape[:2]
    path = scratch / f"frame-{w}x{h}-00004spp.exr"
    exr.write_aovs(path, frame)
    start = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "kpcn_keras.cli", "-q", "denoise", str(path), "--run", run,
                          "-o", str(scratch) + os.sep, "--no-png"], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if res.returncode != 0:
        raise KpcnError(f"kpcn denoise {path} failed: {res.stderr.strip()[-500:]}")
    printed = res.stdout.strip().splitlines()
    peak = [float(m.group(1)) for m in map(re.compile(r"^peak memory (\d+) MB").match, printed) if m]
    return {"frame": [w, h], "wall_s": seconds, "printed": printed[-3:], "peak_rss_mb": peak[0] if peak else None}


def inference_cost(cfg: BenchConfig, plans: dict, aovs: dict) -> dict:
    """Start-up of our denoiser (load, warm-up), then, for each configuration of :data:`INFERENCE`
    that was trained, a frame of the held-out size and a ``large_frame`` against OIDN (alternating, best of
    ``repeats``), and ``kpcn denoise`` of the large frame as a command (its wall time and peak memory)."""
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from prep import baselines

    if OURS not in plans:
        raise KpcnError(f"the bench's inference costs are those of the {OURS!r} configuration: add it to "
                        "--configurations")
    start = time.perf_counter()
    denoiser = Denoiser.from_run(Run(plans[OURS]["run"]))
    out = {"load_s": time.perf_counter() - start}
    start = time.perf_counter()
    denoiser.warm_up()
    out["warm_up_s"] = time.perf_counter() - start
    oidn = baselines.oidn_available()
    large = _tile_to(aovs, *cfg.large_frame)
    h, w = aovs["default"].shape[:2]
    out["frame"] = [w, h]
    out["configurations"] = {}
    for name in (n for n in INFERENCE if n in plans):
        d = denoiser if name == OURS else Denoiser.from_run(Run(plans[name]["run"]))
        fns = {"ours": lambda a, d=d: d(a), **({"oidn": baselines.oidn_denoise} if oidn else {})}
        small = _alternating_best(fns, aovs, cfg.repeats)
        big = _alternating_best(fns, large, cfg.repeats)
        row = {"frame_ms": 1e3 * small["ours"], "large_s": big["ours"], "tile": d.tile}
        if oidn:
            row.update(oidn_frame_ms=1e3 * small["oidn"], frame_ratio=small["ours"] / small["oidn"],
                       oidn_large_s=big["oidn"], large_ratio=big["ours"] / big["oidn"])
        out["configurations"][name] = row
    ours = out["configurations"][OURS]
    out["frame_ms"], out["oidn_frame_ms"], out["frame_ratio"] = (ours["frame_ms"], ours.get("oidn_frame_ms"),
                                                                 ours.get("frame_ratio"))
    out["large"] = {"frame": list(cfg.large_frame), "ours_s": ours["large_s"], "oidn_s": ours.get("oidn_large_s"),
                    "ratio": ours.get("large_ratio"), "tile": ours["tile"],
                    **denoise_command_cost(plans[OURS]["run"], large, Path(cfg.runs_root) / "large-frame")}
    return out


# ---------------------------------------------------------------- the command


def busy_processes(limit: int = 5) -> list[str]:
    """The processes using the most CPU besides this one (``ps``), for the record of what else ran."""
    try:
        res = subprocess.run(["ps", "-eo", "pid,pcpu,etime,comm", "--sort=-pcpu", "--no-headers"],
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return []
    rows = [line.split(None, 3) for line in res.stdout.splitlines() if line.strip()]
    return [" ".join(r) for r in rows if len(r) == 4 and int(r[0]) != os.getpid() and r[3] != "ps"][:limit]


def machine(load_before, busy_before) -> dict:
    import numba

    from kpcn_keras.compare import machine_record

    return {**machine_record(load_before), "numba_threads": numba.get_num_threads(), "busy_before": busy_before,
            "busy_after": busy_processes()}


def bench(cfg: BenchConfig, *, overrides: dict | None = None, command: str | None = None, verbose="auto",
          progress: bool = True, log=print) -> dict:
    """Run the benchmark (module docstring); writes the three reports and returns the record.
    ``overrides``: TrainConfig fields applied to every configuration (a tiny network for a test)."""
    out = Path(cfg.out_dir)
    for suffix in (".md", ".json", ".png"):
        check_writable(out / f"{REPORT}{suffix}", "report (--out)")
    load_before, busy_before = os.getloadavg(), busy_processes()
    started = datetime.now().isoformat(timespec="seconds")
    scenes = held_out_scenes(cfg)
    log(f"bench: {len(scenes)} held-out scenes, raw spp {list(cfg.raw_spp)}, denoised at {list(cfg.input_spp)} spp")
    # First, before this process holds anything: measured after the other stages, the same command took
    # twice the CPU (6.5 against 3.3 s; alone again right after the bench, 3.6 s), for a cause not found.
    log("stage costs: kpcn shards end to end")
    shard_write = shards_command_cost(Path(cfg.shards_root) / cfg.set_name, Path(cfg.runs_root) / "shards-command")
    seconds, inputs = render_ladder(cfg, scenes, log, progress)
    plans = train_runs(cfg, overrides=overrides, verbose=verbose, log=log)
    methods = [raw_method(cfg, scenes, seconds)]
    nets, training = network_methods(cfg, plans, scenes, seconds, inputs, log)
    methods += nets + baseline_methods(cfg, scenes, seconds, inputs, log)
    stages = {**stage_costs(cfg, scenes, seconds, inputs, plans, log), "shard_write": shard_write}
    record = {
        "date": date.today().isoformat(),
        "command": command,
        "started": started,
        "finished": datetime.now().isoformat(timespec="seconds"),
        "config": {**dataclasses.asdict(cfg), "budgets": list(cfg.budgets())},
        "overrides": overrides or {},
        "machine": machine(load_before, busy_before),
        "scenes": [{"name": s["name"], "reference_spp": s["reference_spp"]} for s in scenes],
        "methods": methods,
        "equal_error": equal_error_rows(cfg, methods, scenes, seconds),
        "training": training,
        "stages": stages,
    }
    atomic_write_text(out / f"{REPORT}.json", json.dumps(plain_json(record), indent=2) + "\n")
    atomic_write_text(out / f"{REPORT}.md", format_report(record))
    plot_png(record, out / f"{REPORT}.png")
    return record


def plain_json(value):
    """``value`` with numpy scalars made Python numbers, NaN made null and infinities "inf" / "-inf", so
    that any JSON reader (not only Python's) reads the report."""
    if isinstance(value, dict):
        return {str(k): plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


# ---------------------------------------------------------------- the reports


def _f(value, fmt="{:.4f}") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if isinstance(value, float) and math.isinf(value):
        return "∞"
    return fmt.format(value)


def format_report(record: dict) -> str:
    cfg, m = record["config"], record["machine"]
    lines = [
        f"# What accuracy costs in time ({record['date']})",
        "",
        f"`{record['command'] or 'kpcn bench'}`, {record['started']} to {record['finished']}: "
        f"{len(record['scenes'])} held-out scenes ({', '.join(s['name'] for s in record['scenes'])}) rendered at "
        f"{', '.join(map(str, cfg['raw_spp']))} spp (raw Monte Carlo) and denoised at "
        f"{', '.join(map(str, cfg['input_spp']))} spp; every network trained for {cfg['budget']:g} s here.",
        "",
        f"Machine: {m['cpus']} CPUs, torch {m['torch']} on {m['torch_threads']} threads, numba on "
        f"{m['numba_threads']}; load average {m['load_average_before'][0]:.2f} before and "
        f"{m['load_average_after'][0]:.2f} after. Busiest other processes before: "
        f"{'; '.join(m['busy_before']) or 'none'}; after: {'; '.join(m['busy_after']) or 'none'}.",
        "",
        "## Equal-error saving: the spp raw Monte Carlo needs to reach the denoised relMSE",
        "",
        "Per scene (log-log interpolation on the raw ladder, or the fit a/n + b outside it), the median over "
        "scenes; *time saving* is raw render time at that spp over render + denoise time.",
        "",
        "| method | input spp | median equal-error spp | samples saved | time saved | how (scenes) |",
        "|---|---|---|---|---|---|",
    ]
    for row in record["equal_error"]:
        hows = ", ".join(f"{k} {v}" for k, v in sorted(row["hows"].items()))
        lines.append(f"| {row['method']} | {row['spp']} | {_f(row['median_equal_spp'], '{:.0f}')} | "
                     f"{_f(row['median_spp_saving'], '{:.1f}×')} | {_f(row['median_time_saving'], '{:.1f}×')} | {hows} |")
    lines += [
        "",
        "## Error against time per frame",
        "",
        "Seconds per frame: render (at the input spp) + denoise, the mean over scenes; relMSE and relSE p99.9: the "
        "geometric mean over scenes (the arithmetic mean of relMSE is in the JSON); DSSIM: the mean.",
        "",
        "| method | spp | s / frame | denoise ms | relMSE | DSSIM | relSE p99.9 |",
        "|---|---|---|---|---|---|---|",
    ]
    for method in record["methods"]:
        for p in method["points"]:
            denoise = _f(1e3 * p["denoise_s"], "{:.0f}") if "denoise_s" in p else "—"
            lines.append(f"| {method['name']} | {p['spp']} | {p['seconds']:.3f} | {denoise} | {p['relmse']:.4f} | "
                         f"{p['dssim']:.4f} | {p['relse_p999']:.4f} |")
    lines += ["", "Methods:", ""]
    lines += [f"- **{mm['name']}**: {mm['what']}" + (f" ({mm['training_seconds']:.0f} s of training)"
                                                    if "training_seconds" in mm else "")
              for mm in record["methods"]]
    lines += [
        "",
        "## Training cost: held-out error against training time",
        "",
        "| preset | budget s | trained s | relMSE | DSSIM | relSE p99.9 |",
        "|---|---|---|---|---|---|",
    ]
    for row in record["training"]:
        lines.append(f"| {row['preset']} | {row['budget']:g} | {row['training_seconds']:.0f} | {row['relmse']:.4f} | "
                     f"{row['dssim']:.4f} | {row['relse_p999']:.4f} |")
    lines += ["", "## Stage costs", ""] + _stage_lines(record["stages"])
    return "\n".join(lines) + "\n"


def _stage_lines(st: dict) -> list[str]:
    f, tr, sr, inf = st["features"], st["train_step"], st["shard_read"], st["inference"]
    lines = [
        "| stage | measured | against | ratio |",
        "|---|---|---|---|",
        f"| render | {st['render']['samples_per_s'] / 1e6:.2f} Msamples/s | — | — |",
        f"| features, numba | {1e3 * f['numba_s']:.1f} ms | EXR decode {1e3 * f['exr_decode_s']:.1f} ms | "
        f"{f['numba_s'] / f['exr_decode_s']:.2f}× |",
        f"| features, float64 numpy reference | {1e3 * f['numpy_s']:.1f} ms | numba {1e3 * f['numba_s']:.1f} ms | "
        f"{f['numpy_s'] / f['numba_s']:.1f}× |",
        f"| reading a training batch | {1e3 * sr['batch_s']:.1f} ms | a training step {1e3 * sr['step_s']:.0f} ms | "
        f"{100 * sr['ratio']:.1f} % |",
        f"| a Keras training step | {1e3 * tr['keras_s']:.0f} ms | plain torch {1e3 * tr['torch_s']:.0f} ms | "
        f"{tr['ratio']:.2f}× |",
    ]
    for ka in st["kernel_application"]:
        lines.append(f"| kernel application k={ka['k']} | {1e3 * ka['seconds']:.1f} ms | bandwidth floor "
                     f"{1e3 * ka['floor_seconds']:.1f} ms | {ka['ratio']:.2f}× |")
    lg = inf["large"]
    for name, row in inf["configurations"].items():
        lines.append(f"| denoise a {inf['frame'][0]}×{inf['frame'][1]} frame, {name} | {row['frame_ms']:.0f} ms | "
                     f"OIDN {_f(row.get('oidn_frame_ms'), '{:.0f} ms')} | {_f(row.get('frame_ratio'), '{:.2f}×')} |")
        lines.append(f"| denoise a {lg['frame'][0]}×{lg['frame'][1]} frame, {name} | {row['large_s']:.2f} s | "
                     f"OIDN {_f(row.get('oidn_large_s'), '{:.2f} s')} | {_f(row.get('large_ratio'), '{:.2f}×')} |")
    lines += [
        "",
        f"Frames alternate between our denoiser and OIDN, best of {st.get('repeats', '?')} each. Denoiser start-up: "
        f"loading the run {inf['load_s']:.2f} s, warm-up {inf['warm_up_s']:.2f} s (paid once per process). "
        f"`kpcn denoise` of the {lg['frame'][0]}×{lg['frame'][1]} frame as a command ({OURS}, tiles of {lg['tile']} "
        f"pixels): {lg['wall_s']:.1f} s in all, start-up included (its one frame also pays the convolutions' "
        f"set-up at the tiles' sizes, which the best-of times above leave out), peak resident memory "
        f"{_f(lg['peak_rss_mb'], '{:.0f} MB')}; it printed: {' / '.join(lg['printed'])}",
        "",
    ]
    sl, sw = st["shard_layouts"], st["shard_write"]
    lines += [
        f"`kpcn shards` of this render set as a command ({sw['layout']} layout, {sw['workers']} worker processes, "
        f"{sw['patches']} patches in {sw['shards']} shards): {sw['seconds']:.2f} s, start-up included, "
        f"{sw['patches_per_s']:.0f} patches/s, {sw['bytes_per_patch'] / 2**20:.2f} MB per patch; the `sync` after "
        f"it (the bytes the system had yet to put on disk) took {sw['sync_s']:.2f} s more; the command used "
        f"{sw['cpu_s']:.1f} s of CPU; memory available before it "
        f"{_f(sw['memory_mb_before'].get('MemAvailable'), '{:.0f} MB')}, the bench's own resident size "
        f"{_f(sw['memory_mb_before'].get('VmRSS'), '{:.0f} MB')}. Command: `{sw['command']}`.",
        "",
        f"Shard layouts, side by side on {sl['patches']} patches ({sl['patch_size']}×{sl['patch_size']}); writing "
        f"includes the file's checksum; a batch is {sl['batch_size']} random patches; the shipped one is "
        f"**{sl['default']}**:",
        "",
        "| layout | write patches/s | MB per patch | read a batch | largest relative error |",
        "|---|---|---|---|---|",
    ]
    for name, lay in sl["layouts"].items():
        lines.append(f"| {name} | {lay['write_patches_per_s']:.0f} | {lay['bytes_per_patch'] / 2**20:.3f} | "
                     f"{1e3 * lay['read_batch_s']:.1f} ms | {lay['max_rel_error']:.1e} |")
    return lines


def plot_png(record: dict, path: Path) -> Path:
    """Error against seconds per frame (log axes), one curve per method, for relMSE, DSSIM and relSE p99.9;
    and the presets' held-out relMSE against training seconds."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(12, 10))
    panels = (("relmse", "relMSE (geometric mean over scenes)"), ("dssim", "DSSIM (mean over scenes)"),
              ("relse_p999", "relSE p99.9 (geometric mean over scenes)"))
    # fixed styles for the yardsticks, and a colour of its own for each network (tab20 has enough)
    fixed = {"raw Monte Carlo": dict(color="black", lw=2, marker="o"), "OIDN": dict(color="crimson", ls="--", marker="s"),
             "NLM": dict(color="grey", ls="--", marker="s")}
    networks = [m["name"] for m in record["methods"] if m["name"] not in fixed]
    # tab10 without its red and grey (OIDN's and NLM's), then tab20's light shades
    colours = [plt.cm.tab10.colors[i] for i in (0, 1, 2, 4, 5, 6, 8, 9)] + list(plt.cm.tab20.colors[1::2])

    def colour(name):
        return colours[networks.index(name) % len(colours)] if name in networks else None
    for ax, (key, label) in zip(axes.ravel(), panels):
        for method in record["methods"]:
            xs = [p["seconds"] for p in method["points"]]
            ys = [p[key] for p in method["points"]]
            style = fixed.get(method["name"]) or dict(marker="^", color=colour(method["name"]))
            ax.plot(xs, ys, label=method["name"], markersize=4, alpha=0.85, **style)
            for p in method["points"] if method["kind"] != "raw" else method["points"][::2]:
                ax.annotate(str(p["spp"]), (p["seconds"], p[key]), fontsize=6, alpha=0.7)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds per frame: render + denoise (points: spp)")
        ax.set_ylabel(label)
    ax = axes[1, 1]
    for preset in dict.fromkeys(r["preset"] for r in record["training"]):
        rows = [r for r in record["training"] if r["preset"] == preset]
        ax.plot([r["training_seconds"] for r in rows], [r["relmse"] for r in rows], "o-", label=preset,
                color=colour(preset))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training seconds (this machine)")
    ax.set_ylabel("held-out relMSE (geometric mean)")
    ax.set_title("training cost of the presets", fontsize=9)
    ax.legend(fontsize=8)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.suptitle(f"{record['command'] or 'kpcn bench'} ({record['date']})", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.legend(handles, labels, loc="lower center", ncol=min(6, len(labels)), fontsize=8, frameon=False)
    return save_png(fig, path)
