"""``kpcn bench``: what accuracy costs in time, written to ``reports/accuracy_time.{md,json,png}``.

The contract:

- **Frames.** The held-out scenes of the shard set, each rendered again at every spp of the raw ladder
  (``BenchConfig.raw_spp``) and of the denoisers' ladder (``input_spp``), timed: *time = render time*. A
  render takes the seed the render set gave that scene at that spp (``prep.render.renderset.render_seed``), so
  the inputs are the set's own files, and the reference is the set's reference of the scene. The scenes
  come from the render set's ``config.json``: the bench needs a set made by ``kpcn render``.
- **Methods**, each on the same frames: raw Monte Carlo; every configuration of ``configurations`` (and the
  presets) trained for ``budget`` seconds (``kpcn compare``'s planning:
  :func:`kpcn_keras.studies.compare.plan_and_train`, in ``<runs_root>/<set>-<budget>s-seed<seed>/<name>``), a
  multiscale run with and without its compositor; non-local means; Intel Open Image Denoise when ``pyoidn`` is
  installed. A point is (input spp, seconds = render + denoise, relMSE, DSSIM, relSE p99.9); a denoiser's seconds
  per frame is its own call on that frame after a warm-up (model loading is a stage cost, reported apart).
- **Summaries over scenes**: the geometric mean of relMSE and relSE p99.9 (the arithmetic mean is kept in the
  JSON, but one scene whose reference still has fireflies carries it: docs/results/06-make-bench.md) and the mean DSSIM.
- **Equal-error spp** (:func:`equal_error_spp`): per scene, the spp at which raw Monte Carlo reaches the
  denoised relMSE, interpolated in log-log between the ladder's points, or outside them extrapolated from
  the least-squares fit e(n) = a / n + b of the raw curve (b: the reference's own noise, which every
  method's error contains alike); "below the floor" when the denoised error is under b. The saving is that
  spp over the input spp, and the raw render time at that spp (a straight line through the ladder's
  seconds) over render + denoise time. The report gives the median over scenes and each scene's value.
- **Training cost**: each preset of ``presets`` trained for each of :meth:`BenchConfig.budgets`, its held-out
  scores against the seconds its phases took.
- **Stage costs** (:func:`kpcn_keras.studies.bench_stages.stage_costs`): render samples per second; features
  (numba against the float64 numpy reference and the EXR decode); shard layouts side by side (write patches/s,
  bytes, batch read) and ``kpcn shards`` end to end; reading a training batch against a training step; a Keras
  training step against the same network in plain torch; kernel application against the memory-bandwidth floor
  (k = 13, 21); inference start-up, then a frame of the held-out size and a ``large_frame`` frame against OIDN
  for the default and the fast configuration (:data:`INFERENCE`), and ``kpcn denoise`` of the large frame as a
  command with its own peak memory.
- **Writes** ``accuracy_time.json`` (every number, the command, the date, the machine and what else was
  running), ``accuracy_time.md`` and ``accuracy_time.png`` in ``out_dir``, each atomically
  (``kpcn_keras.studies.report``; the md and the png are drawn by :mod:`kpcn_keras.studies.bench_report`).
  :data:`SCHEMA` lists the figures a record must have; :func:`missing_figures` checks one.
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np

from kpcn_keras.studies.bench_report import format_report, plot_figure
from kpcn_keras.studies.bench_stages import OURS, planned_train_config, shards_command_cost, stage_costs
from kpcn_keras.studies.config import BenchConfig, CompareConfig
from kpcn_keras.studies.report import Report
from prep.errors import KpcnError
from prep.files import read_json
from prep.render.renderset import RECORD

REPORT = "accuracy_time"
GEOMEAN_FLOOR = 1e-300  # an error of exactly 0 (a perfect frame) counts as this in a geometric mean

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

    sset = ShardSet.named(cfg.shards_root, cfg.set_name)
    manifest = sset.complete_manifest()
    refs = {}
    for _, ref in sset.pairs(manifest, "val"):
        refs[exr.parse_render_filename(ref)[0]] = Path(ref)
    if not refs:
        raise KpcnError(f"{sset.dir}: no held-out scenes to measure on")
    render_dir = next(iter(refs.values())).parent
    meta_path = render_dir / RECORD
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
    from kpcn_keras.studies.compare import plan_and_train

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
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.studies.compare import _training_seconds, describe

    methods, training = [], []
    for budget, runs in plans.items():
        for name, plan in runs.items():
            run = Path(plan["run"])
            train_cfg = planned_train_config(plan)
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
                                   "normal, high quality (pretrained)",
                                   lambda a: baselines.oidn_denoise(a, mode="plain"), cfg, scenes, seconds, inputs))
        out.append(denoiser_method("OIDN prefiltered", "baseline", "Intel Open Image Denoise as Blender runs it: "
                                   "albedo and normal denoised first by its own filters, then the colour with "
                                   "cleanAux (pretrained)", lambda a: baselines.oidn_denoise(a, mode="prefiltered"),
                                   cfg, scenes, seconds, inputs))
    else:
        log("[OIDN] not installed (pip install '.[oidn]'): no OIDN curve")
    return out


def equal_error_rows(cfg: BenchConfig, methods: list[dict], scenes: list[dict], seconds: dict) -> list[dict]:
    """For each denoiser (ours, OIDN in both modes, NLM) and input spp: the per-scene equal-error spp and time
    saving."""
    rows = []
    wanted = [OURS, "OIDN", "OIDN prefiltered", "NLM"]
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


def machine(session, busy_before) -> dict:
    """The report's ``machine``: the studies' record, numba's threads, what else ran before and after."""
    import numba

    from kpcn_keras.studies.compare import deep_learning_stack

    return {**session.machine(**deep_learning_stack()), "numba_threads": numba.get_num_threads(),
            "busy_before": busy_before, "busy_after": busy_processes()}


def bench(cfg: BenchConfig, *, overrides: dict | None = None, command: str | None = None, verbose="auto",
          progress: bool = True, log=print) -> dict:
    """Run the benchmark (module docstring); writes the three reports and returns the record.
    ``overrides``: TrainConfig fields applied to every configuration (a tiny network for a test)."""
    from prep.shards import ShardSet

    report = Report(cfg.out_dir, REPORT)
    report.check_writable()
    session, busy_before = report.begin(), busy_processes()
    scenes = held_out_scenes(cfg)
    log(f"bench: {len(scenes)} held-out scenes, raw spp {list(cfg.raw_spp)}, denoised at {list(cfg.input_spp)} spp")
    # First, before this process holds anything: measured after the other stages, the same command took
    # twice the CPU (6.5 against 3.3 s; alone again right after the bench, 3.6 s), for a cause not found.
    log("stage costs: kpcn shards end to end")
    shard_write = shards_command_cost(ShardSet.named(cfg.shards_root, cfg.set_name).dir,
                                      Path(cfg.runs_root) / "shards-command")
    seconds, inputs = render_ladder(cfg, scenes, log, progress)
    plans = train_runs(cfg, overrides=overrides, verbose=verbose, log=log)
    methods = [raw_method(cfg, scenes, seconds)]
    nets, training = network_methods(cfg, plans, scenes, seconds, inputs, log)
    methods += nets + baseline_methods(cfg, scenes, seconds, inputs, log)
    stages = {**stage_costs(cfg, scenes, seconds, inputs, plans, log), "shard_write": shard_write}
    record = {
        **session.envelope(command),
        "config": {**dataclasses.asdict(cfg), "budgets": list(cfg.budgets())},
        "overrides": overrides or {},
        "machine": machine(session, busy_before),
        "scenes": [{"name": s["name"], "reference_spp": s["reference_spp"]} for s in scenes],
        "methods": methods,
        "equal_error": equal_error_rows(cfg, methods, scenes, seconds),
        "training": training,
        "stages": stages,
    }
    return report.write(record, format_report(record), plot_figure, plain=plain_json)


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
