"""How far the adaptation guard's estimate of a correction's change is from the truth, and which of its terms
misses: on frames with references, and on synthetic frames whose noise is symmetric or skewed.

The guard (``kpcn_keras.adapt``) keeps a correction only where its estimated change to the error of the mean's
output, from the two halves alone (``kpcn_keras.risk.pair_risk``), is a gain of at least two standard errors.
Per pixel, f0 the model's output of the mean M, f1 the correction of it, c the reference and w the guard's weight:

    true change  = w [(f1 - c)^2 - (f0 - c)^2]
                 = w [(f1 - M)^2 - (f0 - M)^2]  +  2 w (f1 - f0)(M - c)          (an identity)
    estimate     = w [(f1 - M)^2 - (f0 - M)^2]  +  w D [(g1+ - g1-) - (g0+ - g0-)] / e

with D = (A - B) / 2 and g+ and g- each output of the mixes M + e D and M - e D of the halves (e = 1: the halves
themselves, the guard's secant). The first term is the same in both; the study reports the second, the
*covariance term*, true and estimated for each secant width e. For an affine correction the estimate is exact in
expectation at any e and for any noise (``tests/test_risk.py``). A network is not affine: with e small the secant
is its Jacobian at M, so what e changes is the secant's own nonlinearity, and what no e changes is the noise's
higher cumulants, which a symmetric difference cannot see (E[D^3] = 0 whatever the skew of the renders' noise).
The synthetic frames tell these apart: the same clean image under Gaussian noise and under Gamma noise of the
same mean and variance, the same correction trained on each. A last column tries the second-order part of the
skew: the secant at e = 1 less w [g(A) + g(B) - 2 g(M)] (M - f0(M)), g = f1 - f0, the model's residual standing in
for the noise M - c.

Every figure is a mean over the held-out blocks of the guard's probes (each pixel under the fold network that
never saw it), the correction being the folds' chosen checkpoints after ``--steps`` steps whatever the guard
decided. Writes ``risk_bias.json`` and ``risk_bias.md`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from kpcn_keras.studies.report import Report
from prep.errors import KpcnError

EXIT_USER_ERROR = 2
WIDTHS = (1.0, 0.5, 0.1)
SKEW = "estimate e=1 less the skew term"
SYNTHETIC_SIZE = 128
SYNTHETIC_SHAPE = 0.25  # Gamma shape of the skewed noise: relative spread 2, skewness 4 (fireflies are heavier still)


def mix(a: dict, b: dict, e: float) -> dict:
    """M + e D of two renders' layers, ((1 + e) A + (1 - e) B) / 2: e = 1 is A, e = -1 is B, 0 their mean; each
    variance layer that of the mix."""
    from prep.exr import VARIANCE_LAYERS

    wa, wb = (1.0 + e) / 2.0, (1.0 - e) / 2.0
    return {k: (np.asarray(a[k], np.float64) * (wa**2 if k in VARIANCE_LAYERS else wa)
                + np.asarray(b[k], np.float64) * (wb**2 if k in VARIANCE_LAYERS else wb)).astype(np.float32)
            for k in a if k in b}


def _outputs(nets: list, window, folds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the model's output, the correction's) of ``window``'s tile in float64, each pixel under the fold network of
    ``nets`` that ``folds`` names (its held-out fold)."""
    import keras

    from kpcn_keras.adapt import _blend

    f0 = np.asarray(keras.ops.convert_to_numpy(window.candidates["default"][(0, *window.kept)]), np.float64)
    f1 = np.zeros_like(f0)
    for k, net in enumerate(nets):
        own = folds == k
        f1[own] = np.asarray(keras.ops.convert_to_numpy(_blend(net, window)["default"]), np.float64)[own]
    return f0, f1


def frame_terms(denoise, a: dict, b: dict, reference: np.ndarray, settings) -> dict | None:
    """The true and estimated covariance terms (module docstring) of the correction an adaptation with
    ``settings`` (``AdaptSettings`` with ``steps``) chooses on the pair (``a``, ``b``), on its held-out blocks:
    per term the mean over their pixels and its standard error over the blocks (``change``: the true change of
    the weighted error, the first term plus the true covariance term), and the guard's outcome for the same
    checkpoints (``guard``); None where every fold chose the model's output."""
    import torch

    from kpcn_keras.adapt import Adapter, _window, fold_networks
    from prep import features

    adapter = Adapter(denoise, [(a, b)], settings)
    end = float(settings.steps + 1)  # a mark no run reaches: its snapshot is the run's end
    adapter.run(marks=(end,))
    outcome, _, chosen = adapter.snapshots[end]
    if chosen is None:
        return None
    nets = fold_networks(adapter.apply_weights(chosen))
    shape = a["depth"].shape
    mixes = {e: [(denoise(m), m, features.depth_scale(m["depth"])) for m in (mix(a, b, e), mix(a, b, -e))]
             for e in WIDTHS}
    names = ["first", "true", "change", *(f"estimate e={e:g}" for e in WIDTHS), SKEW]
    sums = {n: np.zeros(adapter.probe_pixels.size) for n in names}
    with torch.no_grad():
        for p in adapter.probes:
            tile = p.crop.tile
            held, cut = p.crop.blocks >= 0, np.s_[tile[0] : tile[1], tile[2] : tile[3]]
            w = p.weight
            f0, f1 = _outputs(nets, p.mean, p.crop.folds)
            terms = {"first": w * ((f1 - p.colour) ** 2 - (f0 - p.colour) ** 2),
                     "true": 2.0 * w * (f1 - f0) * (p.colour - reference[cut]),
                     "change": w * ((f1 - reference[cut]) ** 2 - (f0 - reference[cut]) ** 2)}
            for e in WIDTHS:
                (g0p, g1p), (g0m, g1m) = (_outputs(nets, _window(out, lay, tile, shape, scale, ("default",)),
                                                   p.crop.folds) for out, lay, scale in mixes[e])
                terms[f"estimate e={e:g}"] = w * p.diff * ((g1p - g1m) - (g0p - g0m)) / e
                if e == 1.0:  # the second-order term the symmetric secant adds, its noise taken as M - f0(M)
                    even = (g1p - g0p) + (g1m - g0m) - 2.0 * (f1 - f0)
                    terms[SKEW] = terms["estimate e=1"] - w * even * (p.colour - f0)
            for n, t in terms.items():
                sums[n] += np.bincount(p.crop.slots, t.mean(-1)[held], minlength=sums[n].size)
    blocks = {n: s / adapter.probe_pixels for n, s in sums.items()}
    found = {n: {"mean": float(v.mean()), "se": float(v.std(ddof=1) / np.sqrt(v.size))} for n, v in blocks.items()}
    for name in [*(f"estimate e={e:g}" for e in WIDTHS), SKEW]:  # each estimate's miss, block by block
        miss = blocks[name] - blocks["true"]
        se = float(miss.std(ddof=1) / np.sqrt(miss.size))
        found[name.replace("estimate", "miss")] = {"mean": float(miss.mean()), "se": se}
    found["blocks"], found["guard"] = int(adapter.probe_pixels.size), outcome.to_dict()
    return found


def synthetic_pair(noise: str, seed: int, size: int = SYNTHETIC_SIZE) -> tuple[dict, dict, np.ndarray]:
    """(A, B, clean): a smooth clean image under multiplicative noise of mean 1 and variance 1 /
    :data:`SYNTHETIC_SHAPE`, ``noise`` "gaussian" (symmetric) or "gamma" (skewed), independent per render; flat
    albedo, normal and depth (a frame without a split or variance layers)."""
    y, x = np.mgrid[0:size, 0:size] / size
    clean = np.stack([0.5 + 0.25 * np.sin(np.pi * x), 0.5 + 0.25 * np.cos(np.pi * y),
                      0.4 + 0.2 * np.sin(np.pi * (x + y) / 2)], -1)
    rng = np.random.default_rng(seed)

    def render():
        if noise == "gamma":
            factor = rng.gamma(SYNTHETIC_SHAPE, 1.0 / SYNTHETIC_SHAPE, clean.shape)
        else:
            factor = 1.0 + rng.normal(0.0, 1.0 / np.sqrt(SYNTHETIC_SHAPE), clean.shape)
        return {"default": (clean * factor).astype(np.float32), "albedo": np.full(clean.shape, 0.8, np.float32),
                "normal": np.tile(np.float32([0, 0, 1]), (size, size, 1)),
                "depth": np.full((size, size), 5.0, np.float32)}

    return render(), render(), clean


def _frames(args):
    """(name, denoiser, A, B, reference) of each frame the study measures."""
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from kpcn_keras.studies import adapt_report as ar
    from prep.inputs import InputSet

    serving = Serving(Run(args.model))
    plain = serving.plain(InputSet(split=False, variance=False))
    for noise in ("gaussian", "gamma"):
        for seed in range(args.synthetic):
            a, b, clean = synthetic_pair(noise, seed)
            yield f"synthetic {noise} {seed}", f"synthetic {noise}", plain, a, b, clean
    for folder in args.frames:
        for recipe, spp, files in ar.frames_ready(Path(folder), (args.spp,)):
            a, b = ar.read_halves(files)
            reference = ar._read_same(files["reference"], files["a"], a.size).astype(np.float64)
            yield (f"{recipe['name']} {spp} spp", Path(folder).name, serving.plain(a.inputs, warm_up=True), a.layers,
                   b.layers, reference)


INTRO = """Per pixel of the held-out blocks, f0 the model's output of the halves' mean M, f1 the correction of it, c the
reference, w the guard's weight, D = (A - B) / 2 and g+, g- each output of the mixes M + e D and M - e D:

    true change = w [(f1 - M)^2 - (f0 - M)^2]  +  2 w (f1 - f0)(M - c)
    estimate    = w [(f1 - M)^2 - (f0 - M)^2]  +  w D [(g1+ - g1-) - (g0+ - g0-)] / e

The first term is the same in both; the second, the covariance term, is what the estimate has to guess (e = 1: the
halves themselves, the guard's own). "less the skew term": e = 1 less w [g(A) + g(B) - 2 g(M)] (M - f0(M)), g = f1 -
f0, the second-order part of the noise's skew with the model's residual for the noise. Each figure: the mean over
the held-out blocks' pixels of the change (the correction minus the model), +- one standard error over the blocks;
"miss": (estimated - true) / its standard error, positive where the estimate is pessimistic (sees less of a
gain, or more of a loss, than there is)."""


def _ratio(t: dict, name: str) -> float:
    return t[name]["mean"] / t["true"]["mean"] if t["true"]["mean"] else float("nan")


def summary(rows: list[dict]) -> dict:
    """Per set: its frames, the median ratio of the estimated covariance term to the true one (e = 1), and the
    frames whose estimate misses by more than 2 standard errors on the pessimistic and on the optimistic side."""
    out = {}
    for group in dict.fromkeys(r["set"] for r in rows):
        terms = [r["terms"] for r in rows if r["set"] == group and r["terms"] is not None]
        z = [t["miss e=1"]["mean"] / t["miss e=1"]["se"] for t in terms if t["miss e=1"]["se"] > 0]
        out[group] = {"frames": len(terms), "median_ratio": float(np.median([_ratio(t, "estimate e=1") for t in terms]))
                      if terms else None, "pessimistic": sum(v > 2 for v in z), "optimistic": sum(v < -2 for v in z)}
    return out


def to_markdown(record: dict) -> str:
    head = ["frame", "set", "blocks", "first term", "covariance term: true", *(f"estimated, e={e:g}" for e in WIDTHS),
            "less the skew term", "estimated / true (e=1)", "miss (e=1), standard errors"]
    lines = [f"# The guard's estimate of a correction's change, term by term ({record['date'][:10]})", "",
             f"`{record['command']}`, {record['started']} to {record['finished']}; {record['machine']['cpus']} CPUs, "
             f"load average {record['machine']['load_average_before'][0]:.2f} before; {record['settings']['steps']} "
             "steps of adaptation a frame, the folds' chosen checkpoints whatever the guard decided.", "",
             "```", INTRO, "```", "", "| set | frames | median estimated / true (e=1) | estimate pessimistic by > 2 "
             "standard errors | optimistic by > 2 |", "|---|---|---|---|---|"]
    for group, s in summary(record["frames"]).items():
        ratio = "–" if s["median_ratio"] is None else f"{s['median_ratio']:.2f}"
        lines.append(f"| {group} | {s['frames']} | {ratio} | {s['pessimistic']} | {s['optimistic']} |")
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    pm = lambda t: f"{t['mean']:+.3g} ± {t['se']:.2g}"  # noqa: E731
    for row in record["frames"]:
        t = row["terms"]
        if t is None:
            lines.append(f"| {row['frame']} | {row['set']} | – | every fold chose the model's output |"
                         + " |" * (len(head) - 4))
            continue
        miss = t["miss e=1"]["mean"] / t["miss e=1"]["se"] if t["miss e=1"]["se"] > 0 else float("nan")
        lines.append(f"| {row['frame']} | {row['set']} | {t['blocks']} | {pm(t['first'])} | {pm(t['true'])} | "
                     + " | ".join(pm(t[k]) for k in [*(f"estimate e={e:g}" for e in WIDTHS), SKEW])
                     + f" | {_ratio(t, 'estimate e=1'):.2f} | {miss:+.1f} |")
    return "\n".join(lines) + "\n"


def rewrite(out: Path) -> None:
    """``--report-only``: the md again from the json at ``out``, computing nothing."""
    report = Report(out, "risk_bias", png=False)
    try:
        record = json.loads(report.path(".json").read_text())
    except (OSError, ValueError) as exc:
        raise KpcnError(f"{report.path('.json')}: no report to write again ({type(exc).__name__})") from None
    report.write_text(record, to_markdown(record))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.risk_bias", description=__doc__.split("\n\n")[0])
    p.add_argument("frames", nargs="*", help="folders of frames in pairs with references (adapt_report's layout)")
    p.add_argument("--spp", type=int, default=16, help="the frames' samples (default: %(default)s)")
    p.add_argument("--steps", type=int, default=1500, help="adaptation steps a frame (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="the adaptations' seed (default: %(default)s)")
    p.add_argument("--synthetic", type=int, default=3, help="synthetic pairs of each noise (default: %(default)s)")
    p.add_argument("--model", default="models/default", help="the model (default: %(default)s)")
    p.add_argument("--out", default="reports", help="report folder (default: %(default)s)")
    p.add_argument("--report-only", action="store_true", help="write the md again from the json at --out")
    args = p.parse_args(argv)
    if args.report_only:
        try:
            rewrite(Path(args.out))
        except KpcnError as exc:
            print(f"risk_bias: error: {exc}", file=sys.stderr)
            return EXIT_USER_ERROR
        return 0
    from kpcn_keras.settings import AdaptSettings

    report = Report(Path(args.out), "risk_bias", png=False)
    report.check_writable()
    session = report.begin()
    command = "python -m kpcn_keras.studies.risk_bias " + " ".join(sys.argv[1:] if argv is None else argv)
    rows = []
    for name, group, denoise, a, b, reference in _frames(args):
        terms = frame_terms(denoise, a, b, reference, AdaptSettings(steps=args.steps, seed=args.seed))
        rows.append({"frame": name, "set": group, "terms": terms})
        print(name, "no correction chosen" if terms is None else
              f"covariance term true {terms['true']['mean']:+.3g}, estimated {terms['estimate e=1']['mean']:+.3g}",
              flush=True)
    record = {**session.envelope(command), "machine": session.machine(), "settings": vars(args), "frames": rows}
    report.write(record, to_markdown(record))
    print(f"report: {report.path('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
