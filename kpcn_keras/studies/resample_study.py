"""``kpcn resample-study``: does error-based resampling (docs/method.md §8) beat variance sampling alone?

The report proposed the loop and never measured it. For each seed of
:class:`kpcn_keras.studies.config.ResampleStudyConfig`:

1. **A base run** of the default (cpu) preset, ``base_steps`` per network, on the shard set (round 0: the
   variance-PDF patches of ``kpcn shards``), with the training seed ``seed``:
   ``<runs_root>/<set>-seed<seed>/base``.
2. **Each arm** (:data:`ARMS`) continues a copy of it (``Run.fork``) with ``kpcn resample``'s loop, for the same
   ``rounds`` × ``round_steps`` steps per network: ``continue`` adds no patches (variance sampling only, trained
   as long); ``variance`` adds ``patches_per_image`` per training input each round from the variance PDF
   (the same amount of new data, drawn without the model); ``error`` adds as many from the error PDF mixed
   with the variance PDF. An arm that adds patches writes its rounds in its own copy of the shard set
   (``ShardSet.fork``: round 0 hard-linked), under ``<runs_root>/shards/``.
3. **Equal wall time.** An arm's cost is what its rounds spent on error maps, shards and training (held-out
   measuring is not a cost); the costliest arm's cost after ``rounds`` rounds is the budget, and every other
   arm runs more rounds until it has spent as much (at most :data:`MAX_ROUNDS_FACTOR` × ``rounds``).

Reported (``reports/resample.{md,json,png}``), on the set's held-out frames (never resampled): relMSE and DSSIM
at equal steps (after ``rounds`` rounds) and at equal wall time (linear in time between the measured rounds,
from the base run's error at time 0), per seed and as a mean; the paired differences between arms per seed,
and whether their sign holds in every seed (else the difference is within seed noise); and frame by frame
(:func:`frame_test`), since a mean relMSE over frames can be carried by one frame. Everything is resumable:
the same command reuses finished runs and rounds.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from pathlib import Path

import numpy as np

from kpcn_keras.config import TrainConfig
from kpcn_keras.studies.config import ARMS, ResampleStudyConfig
from kpcn_keras.studies.report import Report
from prep.files import exclusive_lock, pyplot

MAX_ROUNDS_FACTOR = 3
REPORT = "resample"  # resample.json, resample.md, resample.png in the report folder
# the differences the report tests, (a, b): is a better than b?
PAIRS = (("error", "continue"), ("error", "variance"), ("variance", "continue"))
SCORES = ("relmse", "dssim")


def cumulative_cost(loop: dict) -> list[float]:
    """Seconds spent by the end of each round (error maps, shards, training), from 0 before round 1."""
    total, out = 0.0, [0.0]
    for entry in _rounds(loop):
        s = entry["seconds"]
        total += s.get("error_maps", 0.0) + s.get("shards", 0.0) + s.get("training", 0.0)
        out.append(total)
    return out


def _rounds(loop: dict) -> list[dict]:
    return [loop["rounds"][k] for k in sorted(loop["rounds"]) if loop["rounds"][k].get("status") == "done"]


def curve(loop: dict, score: str) -> tuple[list[int], list[float], list[float]]:
    """(steps per network, cumulative seconds, score) before round 1 and after each round."""
    rounds = _rounds(loop)
    steps = [loop["before"]["steps"]] + [e["total_steps"] for e in rounds]
    values = [loop["before"][score]] + [e[score] for e in rounds]
    return steps, cumulative_cost(loop), values


def at_time(loop: dict, score: str, seconds: float) -> float:
    """The score at ``seconds`` of cost, linear between the measured rounds (NaN past the last one)."""
    _, times, values = curve(loop, score)
    if seconds > times[-1] + 1e-9:
        return float("nan")
    return float(np.interp(seconds, times, values))


def frame_scores_at(loop: dict, score: str, *, rounds: int | None = None, seconds: float | None = None) -> np.ndarray:
    """Each held-out frame's score after ``rounds`` rounds, or at ``seconds`` of cost (linear between the
    measured rounds, NaN past the last one), in the loop's frame order."""
    rows = [loop["before"]] + _rounds(loop)
    values = np.array([[f[score] for f in row["frames"]] for row in rows], dtype=np.float64)
    if rounds is not None:
        return values[rounds]
    times = cumulative_cost(loop)
    if seconds > times[-1] + 1e-9:
        return np.full(values.shape[1], np.nan)
    return np.array([np.interp(seconds, times, column) for column in values.T])


def _prefixed(log, prefix: str):
    """``log`` with each line led by ``prefix`` (which seed and arm a line of the interleaved loops is from)."""
    def say(line):
        log(f"{prefix} {line}")
    return say


def _run_arms(cfg: ResampleStudyConfig, seed: int, sset, *, verbose, progress: bool, command: str, log) -> dict:
    """The base run of ``seed`` and every arm's loop, extended to equal wall time; arm -> loop record."""
    from kpcn_keras.resample import resample
    from kpcn_keras.run import Run
    from kpcn_keras.train import train

    seed_dir = Path(cfg.runs_root) / f"{cfg.set_name}-seed{seed}"
    base_cfg = TrainConfig.from_preset(None, set_name=cfg.set_name, shards_root=cfg.shards_root, seed=seed,
                                       steps=cfg.base_steps)
    log(f"[seed {seed}] base run: {cfg.base_steps} steps per network → {seed_dir / 'base'}")
    base = Run(train(base_cfg, seed_dir / "base", verbose=verbose))
    loops, configs = {}, {}
    for arm in cfg.arms:
        configs[arm] = cfg.loop(**ARMS[arm][1])
        arm_set = sset
        if configs[arm].patches_per_image:
            arm_set = sset.fork(Path(cfg.runs_root) / "shards" / f"{cfg.set_name}-seed{seed}-{arm}")
        run = base.fork(seed_dir / arm, arm_set)
        loops[arm] = resample(configs[arm], run, verbose=verbose, progress=progress, command=command,
                              log=_prefixed(log, f"[seed {seed}, {arm}]"))
    budget = max(cumulative_cost(loop)[cfg.rounds] for loop in loops.values())
    for arm, loop in loops.items():
        rounds = len(_rounds(loop))
        while cumulative_cost(loop)[-1] < budget and rounds < MAX_ROUNDS_FACTOR * cfg.rounds:
            rounds += 1
            loop = resample(dataclasses.replace(configs[arm], rounds=rounds), Run(seed_dir / arm), verbose=verbose,
                            progress=progress, command=command, log=_prefixed(log, f"[seed {seed}, {arm}, equal time]"))
        loops[arm] = loop
    return {"budget_seconds": budget, "loops": loops}


def summarise(cfg: ResampleStudyConfig, seeds: dict) -> dict:
    """Per arm and seed: the scores at equal steps (round ``rounds``) and at equal wall time (the seed's
    budget); per pair of arms, the paired differences and whether their sign holds in every seed."""
    k = cfg.rounds
    table = {}
    for arm in cfg.arms:
        table[arm] = {}
        for score in SCORES:
            steps = [_rounds(seeds[s]["loops"][arm])[k - 1][score] for s in cfg.seeds]
            timed = [at_time(seeds[s]["loops"][arm], score, seeds[s]["budget_seconds"]) for s in cfg.seeds]
            table[arm][score] = {"equal_steps": steps, "equal_time": timed}
    before = {score: [seeds[s]["loops"][cfg.arms[0]]["before"][score] for s in cfg.seeds] for score in SCORES}

    def frames(arm: str, score: str, when: str) -> np.ndarray:  # every (seed, frame), seeds in order
        at = {"equal_steps": lambda s: {"rounds": k}, "equal_time": lambda s: {"seconds": seeds[s]["budget_seconds"]}}
        return np.concatenate([frame_scores_at(seeds[s]["loops"][arm], score, **at[when](s)) for s in cfg.seeds])

    pairs = []
    for a, b in PAIRS:
        if a not in cfg.arms or b not in cfg.arms:
            continue
        for score in SCORES:
            for when in ("equal_steps", "equal_time"):
                d = [x - y for x, y in zip(table[a][score][when], table[b][score][when])]
                pairs.append({"a": a, "b": b, "score": score, "when": when, "differences": d,
                              "mean": _mean(d), "verdict": verdict(d), **frame_test(frames(a, score, when),
                                                                                   frames(b, score, when))})
    return {"before": before, "table": table, "pairs": pairs}


def frame_test(a: np.ndarray, b: np.ndarray) -> dict:
    """Frame by frame (every seed's held-out frames): how many are lower under ``a``, the two-sided sign-test
    p-value of that count (ties and unmeasured frames left out), and the geometric mean of a / b. A mean
    over frames can be carried by one frame (relMSE on a caustic); these cannot."""
    measured = np.isfinite(a) & np.isfinite(b)
    ok = measured & (a != b)
    lower, n = int(np.sum(a[ok] < b[ok])), int(np.sum(ok))
    positive = measured & (a > 0) & (b > 0)  # ties count here, as ratio 1
    ratio = float(np.exp(np.mean(np.log(a[positive] / b[positive])))) if positive.any() else float("nan")
    return {"frames_lower": lower, "frames_compared": n,
            "sign_test_p": sign_test(lower, n), "geomean_ratio": ratio}


def sign_test(k: int, n: int) -> float:
    """Two-sided p-value of ``k`` successes in ``n`` fair coin flips: the probability of a count at least as
    far from n/2 (exact binomial sums; NaN for n = 0)."""
    if n == 0:
        return float("nan")
    tail = min(k, n - k)
    p = 2 * sum(math.comb(n, i) for i in range(tail + 1)) / 2**n
    return float(min(1.0, p))


def verdict(differences: list[float]) -> str:
    """'better' / 'worse' when every seed's difference (a − b, lower is better) has that sign, else 'seed noise'."""
    d = [x for x in differences if np.isfinite(x)]
    if len(d) < len(differences) or not d:
        return "not measured"
    if all(x < 0 for x in d):
        return "better"
    if all(x > 0 for x in d):
        return "worse"
    return "within seed noise"


def _mean(values) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(statistics.fmean(finite)) if finite else float("nan")


def study(cfg: ResampleStudyConfig, *, command: str = "", verbose="auto", progress: bool = True, log=print) -> dict:
    """Run (or resume) the study of the module docstring; writes the three reports, returns the record."""
    from kpcn_keras.studies.compare import deep_learning_stack
    from prep.shards import ShardSet

    report = Report(cfg.out_dir, REPORT)
    report.check_writable()
    sset = ShardSet.named(cfg.shards_root, cfg.set_name)
    manifest = sset.complete_manifest()
    session = report.begin()
    seeds = {}
    with exclusive_lock(cfg.runs_root, "study folder"):
        for seed in cfg.seeds:
            seeds[seed] = _run_arms(cfg, seed, sset, verbose=verbose, progress=progress, command=command, log=log)
    record = {
        **session.envelope(command),
        "config": dataclasses.asdict(cfg),
        "arms": {arm: ARMS[arm][0] for arm in cfg.arms},
        "loop": {arm: cfg.loop(**ARMS[arm][1]).to_dict() for arm in cfg.arms},
        "shards": {"set_dir": str(sset.dir), "content_key": manifest["content_key"],
                   "training_inputs": sum(1 for s in manifest["sources"]
                                          if s["role"] == "input" and s["split"] == "train"),
                   "held_out_frames": sum(1 for s in manifest["sources"]
                                          if s["role"] == "input" and s["split"] == "val")},
        "machine": session.machine(**deep_learning_stack()),
        "seeds": {str(s): v for s, v in seeds.items()},
        "summary": summarise(cfg, seeds),
    }
    return report.write(record, format_report(record), curves_figure)


def _fmt(values, fmt="{:.4f}") -> str:
    return " / ".join("—" if not np.isfinite(v) else fmt.format(v) for v in values)


def format_report(record: dict) -> str:
    """resample.md: what ran, the two tables, the paired differences and their verdicts."""
    cfg, summary = record["config"], record["summary"]
    seeds = ", ".join(str(s) for s in cfg["seeds"])
    loop_any = next(iter(record["loop"].values()))
    lines = [
        f"# Error-based resampling against variance sampling ({record['date']})",
        "",
        (f"`{record['command']}`" if record.get("command") else "kpcn resample-study") +
        f" on the shard set `{record['shards']['set_dir']}` ({record['shards']['training_inputs']} training inputs, "
        f"{record['shards']['held_out_frames']} held-out frames), seeds {seeds}. Each seed trains a base run "
        f"({cfg['base_steps']} steps per network, cpu preset), then each arm continues a copy of it for "
        f"{cfg['rounds']} rounds of {cfg['round_steps']} steps per network; arms that add patches add "
        f"{cfg['patches_per_image']} per training input per round (error metric {loop_any['metric']}, error "
        f"weight {record['loop'].get('error', loop_any)['error_weight']:g}).",
        "",
        "| arm | what it is |",
        "|---|---|",
        *[f"| {arm} | {what} |" for arm, what in record["arms"].items()],
        "",
        f"Before the rounds (the base runs): held-out relMSE {_fmt(summary['before']['relmse'])}, DSSIM "
        f"{_fmt(summary['before']['dssim'])} (per seed).",
        "",
    ]
    for when, title in (("equal_steps", f"At equal training steps (after {cfg['rounds']} rounds)"),
                        ("equal_time", "At equal wall time (the costliest arm's seconds after "
                                       f"{cfg['rounds']} rounds; error maps, shards and training count)")):
        budgets = _fmt([record["seeds"][str(s)]["budget_seconds"] for s in cfg["seeds"]], "{:.0f}")
        lines += [f"## {title}", ""]
        if when == "equal_time":
            lines += [f"Budget per seed: {budgets} s.", ""]
        lines += ["| arm | held-out relMSE per seed | mean | DSSIM per seed | mean |", "|---|---|---|---|---|"]
        for arm, scores in summary["table"].items():
            r, d = scores["relmse"][when], scores["dssim"][when]
            lines.append(f"| {arm} | {_fmt(r)} | {_mean(r):.4f} | {_fmt(d)} | {_mean(d):.4f} |")
        lines.append("")
        lines += ["| comparison | score | difference of the means per seed (lower: the first is better) | mean | "
                  "verdict | frames lower under the first | sign test p | geometric mean ratio |",
                  "|---|---|---|---|---|---|---|---|"]
        for pair in summary["pairs"]:
            if pair["when"] == when:
                lines.append(f"| {pair['a']} − {pair['b']} | {pair['score']} | "
                             f"{_fmt(pair['differences'], '{:+.4f}')} | {pair['mean']:+.4f} | {pair['verdict']} | "
                             f"{pair['frames_lower']} of {pair['frames_compared']} | {pair['sign_test_p']:.3g} | "
                             f"{pair['geomean_ratio']:.3f} |")
        lines.append("")
    m = record["machine"]
    lines += [
        "A difference of the means is called better or worse only when it has the same sign in every seed; "
        "otherwise it is within seed noise. The frame columns compare every seed's held-out frames one by one: "
        "how many are lower under the first arm, the two-sided sign-test p-value of that count (frames of one "
        "seed are not independent draws, so read it as a guide), and the geometric mean of the ratio of the two "
        "arms' scores (below 1: the first is lower), which no single frame can carry. Seconds are this machine's "
        f"({m['cpus']} CPUs, torch {m['torch']} on {m['torch_threads']} threads; load average "
        f"{m['load_average_before'][0]:.1f} before, {m['load_average_after'][0]:.1f} after), from "
        f"{record['started']} to {record['finished']}. Raw numbers: `resample.json`; curves: `resample.png`.",
        "",
    ]
    return "\n".join(lines)


def _geomean_curve(loop: dict) -> list[float]:
    rows = [loop["before"]] + _rounds(loop)
    return [float(np.exp(np.mean(np.log([max(f["relmse"], 1e-12) for f in row["frames"]])))) for row in rows]


def curves_figure(record: dict):
    """Held-out relMSE (top: the mean over frames; bottom: their geometric mean, which no single frame can
    carry) against training steps (left) and wall time (right); one colour per arm, one line per seed."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex="col")
    for i, arm in enumerate(record["arms"]):
        for j, seed in enumerate(record["config"]["seeds"]):
            loop = record["seeds"][str(seed)]["loops"][arm]
            steps, times, values = curve(loop, "relmse")
            label = arm if j == 0 else None
            for row, ys in enumerate((values, _geomean_curve(loop))):
                axes[row, 0].plot(steps, ys, "o-", color=f"C{i}", alpha=0.8, markersize=3, label=label)
                axes[row, 1].plot(times, ys, "o-", color=f"C{i}", alpha=0.8, markersize=3, label=label)
    for seed in record["config"]["seeds"]:
        for ax in axes[:, 1]:
            ax.axvline(record["seeds"][str(seed)]["budget_seconds"], color="grey", lw=0.6, ls=":")
    axes[1, 0].set_xlabel("training steps per network")
    axes[1, 1].set_xlabel("seconds after the base run: error maps, shards, training (dotted: budgets)")
    for row, what in enumerate(("mean", "geometric mean")):
        for ax in axes[row]:
            ax.set_ylabel(f"held-out relMSE, {what} over frames")
            ax.set_yscale("log")
            ax.legend(fontsize=8)
    fig.suptitle(f"Resampling rounds, seeds {', '.join(map(str, record['config']['seeds']))}", fontsize=10)
    fig.tight_layout()
    return fig
