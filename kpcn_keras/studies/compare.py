"""``kpcn compare``: accuracy against cost of every configuration, each trained for the same seconds here.

The contract:

- **Configurations** are :data:`kpcn_keras.studies.config.CONFIGURATIONS` (name -> what it is, preset,
  TrainConfig overrides), the one place they are defined. ``kpcn-paper`` and ``kpal-paper`` keep their presets'
  architectures, batch, learning rates and phases; only their steps (and the decay) are cut to the budget, and the
  report says so.
- **One shard set, one budget.** Every configuration trains on ``<shards_root>/<set_name>`` for
  ``budget`` seconds of training steps into its own run folder
  ``<runs_root>/<set>-<budget>s-seed<seed>/<name>``. Seconds become steps by probing
  (:func:`probe_configuration`): a scratch training of :data:`PROBE_STEPS` steps in every phase times each
  training step itself (a Keras callback), and the median of a phase's steps after the first
  :data:`PROBE_SKIP` (which pay one-time costs) is its seconds per step (:func:`seconds_per_step`); phase
  set-up, shard checksums, validation and checkpoints are not in it, so the noise of a busy machine around
  a short training cannot land in it. :func:`budget_steps` shares the budget out between the phases. The probes and
  the steps are kept in ``plan.json`` beside the runs, so the same command run again reuses them and
  resumes (``train`` refuses a run of another configuration, and fresh probes would give other steps);
  training itself is deterministic given the steps. Model building, validation and checkpoints are not
  steps and come on top: the report gives the seconds each run actually trained (its ``timings.json``).
- **Measured on the held-out frames** of the set (every validation scene at every input spp), the same
  frames for every row: the mean over frames of relMSE, DSSIM and relSE p99.9 (``prep.metrics``) of every
  trained run (``denoise.Denoiser``, multiscale runs with their compositor), of the raw input, of non-local
  means and of Intel Open Image Denoise (the row to beat; "not installed" without ``pyoidn``). Parameters:
  the component networks' ``count_params()``. Milliseconds per frame: the median of ``repeats`` whole
  denoiser calls on a ``frame`` x ``frame`` crop of the first held-out render, after a warm-up: inference
  only, on this CPU, with the torch thread count recorded.
- **Writes** ``<out_dir>/compare.md`` (the table, the date, the machine, the rules above),
  ``compare.json`` (every number, the plan, per-frame metrics) and ``compare.png`` (relMSE against ms per
  frame, log axes), each atomically. ``kpcn compare --report-only`` writes the two reports again from
  ``compare.json`` alone (:func:`rewrite_reports`), training and measuring nothing.
- **The headline judges by frames** (:func:`verdict`): the row with the lowest mean relMSE, then on how
  many held-out frames its relMSE is below OIDN's and the median of their ratio; "beats OIDN" means on most
  frames, never by a mean that one frame can carry.

The table of configurations and :class:`kpcn_keras.studies.config.CompareConfig` are in
``kpcn_keras/studies/config.py``. This module imports keras and torch only inside the functions that train
or denoise.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import shutil
import statistics
import time
from datetime import date
from pathlib import Path

from kpcn_keras.config import PRESETS, TrainConfig
from kpcn_keras.studies.config import CONFIGURATIONS, CompareConfig
from kpcn_keras.studies.report import Report
from prep.errors import KpcnError
from prep.files import atomic_write_json, check_writable, exclusive_lock, pyplot, read_json

PROBE_STEPS = 10
PROBE_SKIP = 2  # the first steps of a phase build the optimizer and warm torch up
# The branch networks are the denoiser; joint fine-tuning and the compositor refine it, so they get the
# smaller share. Without either, the branch phases get the whole budget: every row trains as long.
BRANCH_SHARE = 0.8
BRANCH_PHASES = ("diffuse", "specular", "shared")
FINAL_PHASES = ("joint", "compositor")
PLAN = "plan.json"
REPORT = "compare"  # compare.json, compare.md, compare.png in the report folder


# ---------------------------------------------------------------- seconds to steps


def seconds_per_step(step_times: dict[str, list[float]]) -> dict[str, float]:
    """Each phase's seconds per step: the median of its timed steps after the first :data:`PROBE_SKIP`
    (a median, so one step that the machine delayed does not move it)."""
    out = {}
    for phase, times in step_times.items():
        if len(times) <= PROBE_SKIP:
            raise ValueError(f"phase {phase}: {len(times)} timed steps, need more than {PROBE_SKIP}")
        out[phase] = statistics.median(times[PROBE_SKIP:])
    return out


def budget_shares(phases) -> dict[str, float]:
    """The fraction of the budget each phase gets: :data:`BRANCH_SHARE` for the branch phases together
    (all of it without a joint or compositor phase), the rest split evenly between the others."""
    branch = [p for p in phases if p in BRANCH_PHASES]
    final = [p for p in phases if p in FINAL_PHASES]
    if not branch or len(branch) + len(final) != len(list(phases)):
        raise ValueError(f"unknown or missing phases in {list(phases)}")
    branch_total = BRANCH_SHARE if final else 1.0
    shares = {p: branch_total / len(branch) for p in branch}
    shares.update({p: (1.0 - branch_total) / len(final) for p in final})
    return shares


# the TrainConfig fields budget_steps sets: a plan's steps, not part of what the plan is for (PlannedRuns' key)
BUDGET_FIELDS = ("steps", "decay_steps", *(f"{phase}_steps" for phase in FINAL_PHASES))


def budget_steps(budget: float, per_step: dict[str, float]) -> dict[str, int]:
    """TrainConfig step fields that fill ``budget`` seconds, given each phase's seconds per step.

    The branch phases run the same ``steps`` (one TrainConfig field), chosen so that they take their
    share together: steps = floor(share x budget / sum of their seconds per step); a shared network's one
    phase thus gets about twice the steps of each separate branch. ``joint_steps`` and ``compositor_steps``
    = floor(share x budget / seconds per step). ``decay_steps`` = ``steps``: the learning rate decays by
    ``decay_rate`` over the branch training, as it does in the presets. At least 1 of each.
    """
    shares = budget_shares(per_step)
    branch = [p for p in per_step if p in BRANCH_PHASES]
    branch_share = sum(shares[p] for p in branch)
    steps = _whole_steps(branch_share * budget / sum(per_step[p] for p in branch))
    out = {"steps": steps, "decay_steps": steps}
    for phase in FINAL_PHASES:
        if phase in per_step:
            out[f"{phase}_steps"] = _whole_steps(shares[phase] * budget / per_step[phase])
    return out


def _whole_steps(x: float) -> int:
    # the nudge keeps a whole number of steps in exact arithmetic (0.2 x 100 s / 0.5 s) from rounding to one less
    return max(1, math.floor(x * (1 + 1e-12)))


# ---------------------------------------------------------------- configurations


def train_config(name: str, cfg: CompareConfig, overrides: dict | None = None) -> TrainConfig:
    """The TrainConfig of configuration ``name`` on ``cfg``'s shard set, before its steps are set;
    ``overrides`` apply to every configuration after its own (``model`` merged)."""
    _, preset, own = CONFIGURATIONS[name]
    overrides = dict(overrides or {})
    values = {**own, **overrides}
    values["model"] = {**own.get("model", {}), **(overrides.get("model") or {})}
    return TrainConfig.from_preset(preset, set_name=cfg.set_name, shards_root=cfg.shards_root, seed=cfg.seed,
                                   **values)


def with_steps(base: TrainConfig, steps: dict[str, int]) -> TrainConfig:
    return dataclasses.replace(base, **steps)


def _probe_fields(base: TrainConfig, n: int) -> dict:
    # one epoch per phase and one validation batch: the probe wants the steps, not what comes around them
    fields = {"steps": n, "decay_steps": n, "steps_per_epoch": n, "val_batches": 1, "compositor_steps": n}
    if base.joint_steps:
        fields["joint_steps"] = n
    return fields


def describe(name: str, cfg: TrainConfig) -> str:
    """What the configuration is, for the report: the table's phrase, then the network it trains."""
    phrase, preset, _ = CONFIGURATIONS[name]
    m = cfg.model.to_dict()
    unit = "residual blocks" if m["arch"] == "kpal" else "convolutions"
    net = f"{m['arch'].upper()}, {m['depth']} {unit} of {m['width']} {m['conv_size']}×{m['conv_size']} filters"
    if m["batchnorm"]:
        net += ", batch norm"
    if m["arch"] != "dpcn":
        net += f", {m['kernel_size']}×{m['kernel_size']} kernels"
    if m["dropout"]:
        net += f", dropout {m['dropout']:g}"
    net += f", batch {cfg.batch_size}, lr {cfg.learning_rate:g}"
    if cfg.joint_steps:
        net += f", joint lr {cfg.joint_learning_rate:g}"
    if cfg.compositor:
        c = cfg.compositor
        net += f", {c.levels} levels"
        if c.kind == "kernel":
            net += f", {c.kernel_size}×{c.kernel_size} compositor kernels"
        net += f", {c.downsample} downsampling"
        if c.scale_supervision:
            net += f", inner scales supervised at weight {c.scale_supervision:g}"
    if cfg.loss == "asymmetric":
        net += f", λ = {cfg.slope:g}"
    scaled = " (scaled to the budget)" if preset != TrainConfig.preset else ""
    return f"{phrase}{scaled}: {net}"


# ---------------------------------------------------------------- probing and training


def _group_dir(cfg: CompareConfig) -> Path:
    # budget and seed in the name: another budget is another set of runs, not a clash with these
    return Path(cfg.runs_root) / f"{cfg.set_name}-{cfg.budget:g}s-seed{cfg.seed}"


def _step_timer(phases: list[str], times: dict[str, list[float]]):
    """A Keras callback appending the seconds of every training step to ``times[phase]``; each ``fit`` of
    a fresh training is the next phase of ``phases``."""
    import keras

    class StepTimer(keras.callbacks.Callback):
        def __init__(self):
            super().__init__()
            self.fits = 0

        def on_train_begin(self, logs=None):
            self.phase = phases[self.fits]
            self.fits += 1

        def on_train_batch_begin(self, batch, logs=None):
            self.start = time.perf_counter()

        def on_train_batch_end(self, batch, logs=None):
            times.setdefault(self.phase, []).append(time.perf_counter() - self.start)

    return StepTimer()


def probe_configuration(base: TrainConfig, scratch: Path) -> dict[str, list[float]]:
    """``{phase: [seconds of each step]}`` of a scratch training of ``base``, :data:`PROBE_STEPS` steps in
    every phase (one epoch each, one validation batch)."""
    from kpcn_keras.train import train

    cfg = with_steps(base, _probe_fields(base, PROBE_STEPS))
    if scratch.exists():
        shutil.rmtree(scratch)
    times: dict[str, list[float]] = {}
    train(cfg, scratch, verbose=0, callbacks=[_step_timer([p.name for p in cfg.phases()], times)])
    shutil.rmtree(scratch)
    return times


def plan_steps(base: TrainConfig, budget: float, scratch: Path, times: dict | None = None) -> dict:
    """The plan of ``base`` for ``budget`` seconds: the step ``probes`` (``times`` when given, else a probe
    training in ``scratch``), each phase's ``seconds_per_step``, its share of the budget (``shares``), the
    TrainConfig ``steps`` fields and the ``phase_steps`` they give."""
    if times is None:
        times = probe_configuration(base, scratch)
    per_step = seconds_per_step(times)
    steps = budget_steps(budget, per_step)
    return {"probes": times, "seconds_per_step": per_step, "shares": budget_shares(per_step), "steps": steps,
            "phase_steps": {p.name: p.steps for p in with_steps(base, steps).phases()}}


class PlannedRuns:
    """The plans of a study that trains for seconds (``compare``, ``quality``, ``inputs-study``), in its group
    folder: the one owner of ``<group>/plan.json`` and ``<group>/probes/``.

    Entered, it holds the folder's lock (one study at a time), empties the probes' scratch folder (what a killed
    study left) and reads the plans stored; :meth:`entry` gives a training's plan, reused when it was made for the
    same key, else made and saved at once (so an interrupted study resumes with the same steps); leaving it
    empties the scratch folder again. Plans are stored under a path of names (a configuration; a lever and an
    input set)."""

    def __init__(self, group: Path, what: str):
        self.group, self.what = Path(group), what
        self.path, self.scratch = self.group / PLAN, self.group / "probes"
        self.stored: dict = {}

    def __enter__(self) -> PlannedRuns:
        check_writable(self.group, "runs folder (--runs)", directory=True)
        self._lock = exclusive_lock(self.group, f"{self.what} folder")
        self._lock.__enter__()
        try:
            if self.scratch.exists():
                shutil.rmtree(self.scratch)
            self.stored = read_json(self.path, f"{self.what} plan") if self.path.is_file() else {}
        except BaseException:
            self._lock.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        try:
            if exc[0] is None and self.scratch.exists():
                shutil.rmtree(self.scratch)
        finally:
            self._lock.__exit__(*exc)

    def entry(self, names: tuple[str, ...], key: dict, run_dir: Path, plan) -> tuple[dict, bool]:
        """``(plan entry, reused)``: the entry stored under ``names`` when its ``key`` fields equal ``key``; else
        ``{**key, **plan(scratch)}`` (``plan`` probes in the scratch folder it is given), stored and saved. A run
        already trained in ``run_dir`` for another key is refused (KpcnError): its steps would not be these."""
        node = self.stored
        for name in names[:-1]:
            node = node.get(name, {})
        entry = node.get(names[-1])
        if entry is not None and all(_as_read(k, entry.get(k)) == _as_read(k, v) for k, v in key.items()):
            return entry, True
        from kpcn_keras.run import Run

        if Run(run_dir).has_record():
            raise KpcnError(f"{run_dir}: trained for other settings than this {self.what}'s (another "
                            "configuration, shard set or budget); choose another --runs or remove it")
        entry = {**key, **plan(self.scratch / "-".join(names))}
        node = self.stored
        for name in names[:-1]:
            node = node.setdefault(name, {})
        node[names[-1]] = entry
        atomic_write_json(self.path, self.stored)
        return entry, False


def _as_read(field: str, value):
    """A plan key's stored value as this kpcn writes it: a training identity through
    :meth:`TrainConfig.recorded_identity`, so that a plan made before a field was added keeps its runs, without
    the step counts the budget sets (:data:`BUDGET_FIELDS`; a joint phase's only as whether it has one), so that a
    changed default step count keeps them too: the plan's own steps are what its runs trained."""
    if field != "train" or not isinstance(value, dict):
        return value
    identity = TrainConfig.recorded_identity(value)
    kept = {k: v for k, v in identity.items() if k not in BUDGET_FIELDS}
    if "joint_steps" in identity:  # whether there is a joint phase is the configuration's, not the budget's
        kept["joint_steps"] = min(identity["joint_steps"], 1)
    return kept


def _fmt_phases(values: dict, fmt: str) -> str:
    return ", ".join(f"{k} {fmt.format(v)}" for k, v in values.items())


def plan_and_train(cfg: CompareConfig, *, overrides: dict | None = None, verbose="auto", log=print,
                   probes: dict | None = None) -> dict:
    """Probe (or reuse the plan of) and train every configuration; returns ``name -> plan entry``.

    ``probes``: ``name -> {"train": identity, "probes": step times}`` of probes already made (another budget's
    plan entries): a configuration of the same identity takes its steps from them instead of probing again.
    """
    from kpcn_keras.train import train
    from prep.shards import ShardSet

    manifest = ShardSet.named(cfg.shards_root, cfg.set_name).complete_manifest()
    group = _group_dir(cfg)
    plans = {}
    with PlannedRuns(group, "comparison") as planned:
        for name in cfg.configurations:
            base = train_config(name, cfg, overrides)
            run_dir = group / name
            key = {"train": base.identity(), "budget": cfg.budget, "content_key": manifest["content_key"]}
            known = (probes or {}).get(name)
            same = known is not None and _as_read("train", known["train"]) == _as_read("train", key["train"])
            times = known["probes"] if same else None
            entry, reused = planned.entry((name,), key, run_dir,
                                          functools.partial(plan_steps, base, cfg.budget, times=times))
            if reused:
                log(f"[{name}] steps from {planned.path}: {_fmt_phases(entry['phase_steps'], '{}')}")
            else:
                log(f"[{name}] seconds per step: {_fmt_phases(entry['seconds_per_step'], '{:.4f}')}; for "
                    f"{cfg.budget:g} s: {_fmt_phases(entry['phase_steps'], '{}')} steps")
            log(f"[{name}] training into {run_dir}")
            train(with_steps(base, entry["steps"]), run_dir, verbose=verbose)
            plans[name] = {**entry, "run": str(run_dir)}
    return plans


# ---------------------------------------------------------------- measuring


def _crop(aovs: dict, side: int) -> dict:
    h, w = aovs["default"].shape[:2]
    y0, x0 = max(0, (h - side) // 2), max(0, (w - side) // 2)
    return {k: v[y0:y0 + side, x0:x0 + side].copy() for k, v in aovs.items()}


def _median_ms(fn, repeats: int) -> tuple[float, list[float]]:
    fn()  # warm-up: per-shape setup is not inference
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(1e3 * (time.perf_counter() - start))
    return statistics.median(samples), samples


def _training_seconds(run_dir: Path) -> float:
    from kpcn_keras.run import Run

    timings = read_json(Run(run_dir).timings_path, "run timings")
    return float(sum(timings.values()))


def measure(cfg: CompareConfig, plans: dict, *, log=print) -> tuple[list[dict], dict]:
    """The report's rows (trained configurations, then raw input, NLM, OIDN) and what was timed."""
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import frame_scores, held_out_frames
    from kpcn_keras.run import Run
    from prep import baselines

    first = Run(next(iter(plans.values()))["run"])
    frames = held_out_frames(first, first.record())
    if not frames:
        raise KpcnError(f"{cfg.shards_root}/{cfg.set_name}: no held-out scenes to compare on")
    crop = _crop(frames[0]["noisy"], cfg.frame)
    h, w = crop["default"].shape[:2]
    timed = {"frame": frames[0]["name"], "width": w, "height": h}
    rows = []
    for name, plan in plans.items():
        denoiser = Denoiser.from_run(Run(plan["run"]))
        denoiser.warm_up()
        scores = frame_scores([denoiser(f["noisy"])["default"] for f in frames], frames)
        ms, samples = _median_ms(lambda d=denoiser: d(crop), cfg.repeats)
        networks = list(denoiser.networks.values()) + ([denoiser.compositor] if denoiser.compositor else [])
        train_cfg = denoiser.record.train
        rows.append({"name": name, "kind": "network", "what": describe(name, train_cfg), "run": plan["run"],
                     "phase_steps": plan["phase_steps"], "training_seconds": _training_seconds(Path(plan["run"])),
                     "parameters": int(sum(n.count_params() for n in networks)), "ms_per_frame": ms,
                     "ms_samples": samples, **scores})
        log(f"[{name}] held-out relMSE {scores['relmse']:.4f}, DSSIM {scores['dssim']:.4f}, relSE p99.9 "
            f"{scores['relse_p999']:.4f}; {ms:.1f} ms per {w}×{h} frame")
    rows.append({"name": "raw input", "kind": "input", "what": "the noisy render itself",
                 **frame_scores([f["noisy"]["default"] for f in frames], frames)})

    def nlm(aovs):
        return baselines.nlm_denoise(aovs["default"], aovs["colorVariance"])

    baseline_rows = [("NLM", "scikit-image non-local means on the colour, told the render's noise level", nlm)]
    oidn_here = baselines.oidn_available()
    if oidn_here:
        baseline_rows.append(("OIDN", "Intel Open Image Denoise, RT filter with albedo and normal (pretrained)",
                              lambda aovs: baselines.oidn_denoise(aovs, mode="plain")))
    for name, what, fn in baseline_rows:
        scores = frame_scores([fn(f["noisy"]) for f in frames], frames)
        ms, samples = _median_ms(lambda fn=fn: fn(crop), cfg.repeats)
        rows.append({"name": name, "kind": "baseline", "available": True, "what": what, "ms_per_frame": ms,
                     "ms_samples": samples, **scores})
        log(f"[{name}] held-out relMSE {scores['relmse']:.4f}; {ms:.1f} ms per {w}×{h} frame")
    if not oidn_here:
        rows.append({"name": "OIDN", "kind": "baseline", "available": False,
                     "what": "Intel Open Image Denoise: not installed (pip install '.[oidn]')"})
        log("[OIDN] not installed (pip install '.[oidn]')")
    return rows, timed


# ---------------------------------------------------------------- the command


def compare(cfg: CompareConfig, *, overrides: dict | None = None, command: str | None = None, verbose="auto",
            log=print) -> dict:
    """Run the comparison (see the module docstring); writes the three reports and returns the record.

    ``overrides``: TrainConfig fields applied to every configuration after its own (a smaller network for
    a quick look or a test); they are part of the plan's key and of the record. ``command``: the command
    line that asked, for the report.
    """
    report = Report(cfg.out_dir, REPORT)
    report.check_writable()
    session = report.begin()
    from prep.shards import ShardSet

    sset = ShardSet.named(cfg.shards_root, cfg.set_name)
    log(f"compare: {len(cfg.configurations)} configurations, {cfg.budget:g} s of training each, "
        f"shard set {sset.dir}")
    plans = plan_and_train(cfg, overrides=overrides, verbose=verbose, log=log)
    rows, timed = measure(cfg, plans, log=log)
    manifest = sset.complete_manifest()
    record = {
        **session.envelope(command),
        "config": {**dataclasses.asdict(cfg), "configurations": list(cfg.configurations)},
        "overrides": overrides or {},
        "shards": {"set_dir": str(sset.dir), "content_key": manifest["content_key"],
                   "held_out_frames": len(rows[0]["frames"])},
        "rules": {"probe_steps": PROBE_STEPS, "probe_skip": PROBE_SKIP, "branch_share": BRANCH_SHARE},
        "machine": session.machine(**deep_learning_stack()),
        "timed": timed,
        "plans": plans,
        "rows": rows,
    }
    return report.write(record, format_report(record), scatter_figure)


RECORD_KEYS = ("date", "config", "shards", "rules", "machine", "timed", "rows")


def rewrite_reports(out_dir: str | Path) -> dict:
    """``compare.md`` and ``compare.png`` written again from ``<out_dir>/compare.json``, nothing trained or
    measured (``kpcn compare --report-only``): a committed comparison re-rendered after the report's text
    changed, its numbers those of the record, the report saying so with the day. Returns the record as
    the report read it (with ``rewritten``; ``compare.json`` is left as it is)."""
    report = Report(out_dir, REPORT)
    record = read_json(report.path(".json"), "comparison record", RECORD_KEYS)
    report.check_writable((".md", ".png"))
    # the numbers stay the record's; the report says when, and by what, it was written again
    record = {**record, "rewritten": f"`kpcn compare --report-only` on {date.today().isoformat()}"}
    report.write_text(record, format_report(record), scatter_figure)
    return record


def deep_learning_stack() -> dict:
    """What a kpcn_keras study's ``machine`` record adds (``kpcn_keras.studies.report.machine_record``): the torch
    and keras versions and torch's thread count."""
    import keras
    import torch

    return {"torch": torch.__version__, "keras": keras.__version__, "torch_threads": torch.get_num_threads()}


def best(record: dict) -> dict:
    """The trained configuration with the lowest held-out relMSE."""
    return min((r for r in record["rows"] if r["kind"] == "network"), key=lambda r: r["relmse"])


def against(row: dict, other: dict) -> dict:
    """``row`` against ``other`` frame by frame, as the report judges them: ``lower``, the held-out frames
    where ``row``'s relMSE is below ``other``'s, of ``frames``, and ``median_ratio``, the median over the
    frames of ``row``'s relMSE over ``other``'s. A mean over frames can be carried by one frame (a
    firefly OIDN leaves: ``compare.json``); these cannot."""
    pairs = list(zip(row["frames"], other["frames"], strict=True))
    ratios = [a["relmse"] / b["relmse"] if b["relmse"] > 0 else (math.inf if a["relmse"] > 0 else 1.0)
              for a, b in pairs]
    return {"lower": sum(a["relmse"] < b["relmse"] for a, b in pairs), "frames": len(pairs),
            "median_ratio": statistics.median(ratios)}


def _wins(row: dict, other: dict) -> str:
    """On how many of the held-out frames ``row``'s relMSE is below ``other``'s, as "k/n"."""
    got = against(row, other)
    return f"{got['lower']}/{got['frames']}"


def verdict(record: dict) -> str:
    """The report's headline: the lowest mean relMSE, then how it does against OIDN judged by frames
    (:func:`against`: on most frames, or not), the means only beside it."""
    top = best(record)
    oidn = next(r for r in record["rows"] if r["name"] == "OIDN")
    line = f"**Best by held-out relMSE: `{top['name']}`** (mean {top['relmse']:.4f})"
    if not oidn.get("available"):
        return line + "; OIDN, the row to beat, is not installed here."
    got = against(top, oidn)
    lower, n = got["lower"], got["frames"]
    judged = ("it beats OIDN on most frames" if 2 * lower > n else
              "OIDN is better on most frames" if 2 * lower < n else "level with OIDN: lower on half the frames")
    return (line + f". Against OIDN, the row to beat: lower relMSE on {lower} of {n} frames, the median ratio "
            f"of its relMSE to OIDN's {got['median_ratio']:.2f}×: {judged}. The means ({top['relmse']:.4f} "
            f"against OIDN's {oidn['relmse']:.4f}) are not the verdict: one frame can carry a mean.")


def _num(value, fmt="{:.4f}") -> str:
    return "—" if value is None else fmt.format(value)


def _ms(value) -> str:
    return "—" if value is None else f"{value:.0f}" if value >= 100 else f"{value:.1f}"


def format_report(record: dict) -> str:
    """compare.md: the table, the best configuration, and what the numbers are."""
    cfg, machine, timed = record["config"], record["machine"], record["timed"]
    frame = f"{timed['width']}×{timed['height']}"
    top = best(record)
    oidn = next(r for r in record["rows"] if r["name"] == "OIDN")
    lines = [
        f"# Every configuration under one training budget ({record['date']})",
        "",
        (f"`{record['command']}`: e" if record.get("command") else "E") + "ach configuration trained for "
        f"{cfg['budget']:g} s on this machine on the shard set `{record['shards']['set_dir']}` (content key "
        f"`{record['shards']['content_key'][:12]}`), then measured on the same {record['shards']['held_out_frames']} "
        "held-out frames (every validation scene at every input spp): all rows share one shard set and one budget."
        + (f" This report was written again from `compare.json` by {record['rewritten']}; every number is the "
           "record's." if record.get("rewritten") else ""),
        "",
        f"| configuration | what it is | steps per phase | training s | held-out relMSE | DSSIM | relSE p99.9 "
        f"| frames with a lower relMSE than OIDN | parameters | ms / {frame} frame |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in record["rows"]:
        if r.get("available") is False:
            lines.append(f"| {r['name']} | {r['what']} |" + " — |" * 8)
            continue
        relmse = _num(r["relmse"])
        if r is top:
            relmse = f"**{relmse}**"
        steps = _fmt_phases(r["phase_steps"], "{}") if "phase_steps" in r else "—"
        params = f"{r['parameters']:,}" if "parameters" in r else "—"
        wins = "—" if r is oidn or not oidn.get("available") else _wins(r, oidn)
        lines.append(f"| {r['name']} | {r['what']} | {steps} | {_num(r.get('training_seconds'), '{:.0f}')} | "
                     f"{relmse} | {_num(r['dssim'])} | {_num(r['relse_p999'])} | {wins} | {params} | "
                     f"{_ms(r.get('ms_per_frame'))} |")
    paper = [n for n in cfg["configurations"] if CONFIGURATIONS[n][1] != TrainConfig.preset]
    lines += ["", verdict(record), ""]
    lines.append(
        f"- **Same budget.** Each configuration's phases were timed by a scratch training of "
        f"{record['rules']['probe_steps']} steps per phase, every step timed by a callback; a phase's seconds "
        f"per step is the median of its steps after the first {record['rules']['probe_skip']}. The branch "
        f"phases get {100 * record['rules']['branch_share']:.0f} % of the budget (all of it without joint "
        "fine-tuning or a compositor) and run the same steps, so a shared network's one phase gets about twice "
        "the steps of each separate branch; joint fine-tuning or the compositor gets the rest. The learning "
        "rate decays over the branch steps. Building, validation and checkpoints come on top: *training s* is "
        "what the run's phases took (its `timings.json`); the probes are not counted.")
    if paper:
        lengths = {CONFIGURATIONS[n][1]: (PRESETS[CONFIGURATIONS[n][1]]["steps"],
                                          PRESETS[CONFIGURATIONS[n][1]]["joint_steps"]) for n in paper}
        if len(set(lengths.values())) == 1:
            full = "{} steps per branch and {} joint steps".format(*next(iter(lengths.values())))
        else:
            full = ", ".join(f"{p}: {s} steps per branch and {j} joint" for p, (s, j) in sorted(lengths.items()))
        lines.append(f"- **Scaled to the budget:** {' and '.join(paper)} keep their presets' networks, batch, learning "
                     f"rates and phases; only the steps (and the decay) are cut to the budget, far below the "
                     f"papers' GPU training ({full}).")
    lines.append(
        f"- **ms per frame** is inference only: one whole denoiser call (features, both branches, compositor, "
        f"back to colour; for NLM and OIDN their call) on a {frame} crop of `{timed['frame']}`, the median of "
        f"{cfg['repeats']} after a warm-up, on this CPU with {machine['torch_threads']} torch threads.")
    if record.get("overrides"):
        lines.append(f"- **Every configuration overridden** with `{json.dumps(record['overrides'])}` (TrainConfig "
                     "fields, after the configuration's own).")
    load_b, load_a = machine["load_average_before"][0], machine["load_average_after"][0]
    lines.append(
        f"- **Machine:** {machine['cpus']} CPUs, load average {load_b:.2f} before and {load_a:.2f} after; "
        f"{machine['platform']}, Python {machine['python']}, torch {machine['torch']}, keras {machine['keras']}. "
        "The probes that set the steps are timings too: on a busy machine the budgets are not the same.")
    lines.append(
        "- **Metrics** (`prep/metrics.py`, as in `kpcn evaluate`): the mean over the held-out frames of relMSE, "
        "DSSIM and relSE p99.9 (the 99.9th percentile of the per-pixel relative squared error). `compare.json` "
        "has every frame's values, the probes and the steps; `compare.png` plots relMSE against ms per frame.")
    lines.append("")
    return "\n".join(lines)


def scatter_figure(record: dict):
    """relMSE against ms per frame, log axes, each point labelled; the raw input's relMSE is a line."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7.5, 5))
    styles = {"network": dict(marker="o", color="C0"), "NLM": dict(marker="s", color="C2"),
              "OIDN": dict(marker="*", color="C3", s=160)}
    plotted, legend = 0, {"network": "trained configuration", "NLM": "non-local means", "OIDN": "Open Image Denoise"}
    for r in record["rows"]:
        if r["kind"] == "input":
            ax.axhline(r["relmse"], color="grey", linestyle="--", linewidth=1)
            ax.annotate("raw input", (0.01, r["relmse"]), xycoords=("axes fraction", "data"), va="bottom",
                        fontsize=8, color="grey")
            continue
        if r.get("available") is False:
            continue
        kind = "network" if r["kind"] == "network" else r["name"]
        ax.scatter([r["ms_per_frame"]], [r["relmse"]], zorder=3, label=legend.pop(kind, None), **styles[kind])
        # staggered: configurations that tie on both axes would print their names over each other
        ax.annotate(r["name"], (r["ms_per_frame"], r["relmse"]), textcoords="offset points",
                    xytext=(5, 4 - 10 * (plotted % 4)), fontsize=8)
        plotted += 1
    ax.set_xscale("log")
    ax.set_yscale("log")
    t = record["timed"]
    ax.set_xlabel(f"ms per {t['width']}×{t['height']} frame (inference, this CPU)")
    ax.set_ylabel("held-out relMSE")
    ax.set_title(f"{record['config']['budget']:g} s of training each, {record['date']}", fontsize=10)
    ax.grid(True, which="both", alpha=0.2)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return fig
