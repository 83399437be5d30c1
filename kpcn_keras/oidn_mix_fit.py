"""Fitting the weight at which a run's networks' frame is mixed with OIDN's (``kpcn mix-oidn``; the mix itself,
and where its weight lives, is ``kpcn_keras.oidn_mix``'s).

The weight of :data:`GRID` that minimises the mean over the frames of log relMSE: every frame counts alike whatever
the scale of its error (the median ratio the reports judge by, without needing a renderer's own denoised frame);
the grid's ends are OIDN alone (0) and the networks alone (1). Each input-set variant of a run is fit on the frames
it serves (``Run.serving``) and the weight written into its record, with the fit (frames, objective at each weight).
Fit on frames of scenes neither trained on nor judged: the weight is a parameter of the model.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from kpcn_keras.batch import read_reference
from kpcn_keras.denoise import Denoiser
from kpcn_keras.oidn_mix import KEY, Mix
from prep import layouts, metrics
from prep.errors import KpcnError

GRID = tuple(round(i * 0.05, 2) for i in range(21))  # the weights tried: 0 (OIDN alone) ... 1 (the networks alone)


def fit_weight(frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[float, dict[float, float]]:
    """The weight of :data:`GRID` whose mix has the lowest mean log relMSE over ``frames`` (each the networks'
    frame, OIDN's and the reference), and that objective at each weight (the lower weight where two tie)."""
    logs = {w: [] for w in GRID}
    for networks, oidn, ref in frames:
        for w in GRID:
            logs[w].append(np.log(metrics.relmse(Mix(w).apply(networks, oidn), ref)))
    if not logs[GRID[0]]:
        raise KpcnError("no frames to fit the OIDN mix on")
    objective = {w: float(np.mean(v)) for w, v in logs.items()}
    return min(GRID, key=lambda w: (objective[w], w)), objective


def fit_run(run, pairs: list[tuple[str, str]], *, log: Callable[[str], None] = print) -> dict[str, dict]:
    """Fit the mix of each input-set variant of ``run`` (a finished run or model folder, a ``Run``) on the frames of
    ``pairs`` (noisy render, reference) that it serves (``Run.serving``: the variant of the most the frame has),
    and write it into that variant's record; a variant that serves none of them is left as it is. Returns
    {input set: the entry written}."""
    by_variant: dict[Path, list] = {}  # the frames each variant serves, found once per frame
    for noisy, ref in pairs:
        frame = layouts.read(noisy)
        by_variant.setdefault(run.serving(frame.inputs).dir, []).append(
            (noisy, frame, read_reference(ref, noisy, frame.size)))
    written = {}
    for variant in run.variants():
        served = by_variant.get(variant.dir)
        if not served:
            continue
        record = variant.record().finished()
        denoiser, mix = Denoiser.from_run(variant, record=record), Mix(1.0)
        triples, names = [], []
        for noisy, frame, ref in served:
            layers = frame.served_layers()
            triples.append((denoiser(layers)["default"], mix.oidn(layers), ref))
            names.append(str(noisy))
        weight, objective = fit_weight(triples)
        entry = {"weight": weight, "oidn_mode": mix.oidn_mode, "oidn_quality": mix.oidn_quality,
                 "fit": {"frames": names, "objective": "mean log relMSE",
                         "by_weight": {f"{w:g}": v for w, v in objective.items()}}}
        with variant.lock():  # not while a trainer writes the record
            data = variant.read_record()
            data[KEY] = entry
            variant.write_record(data)
        written[record.inputs.name] = entry
        log(f"{variant.dir}: weight {weight:g} of the networks' frame, OIDN's {1 - weight:g}: mean log relMSE "
            f"{objective[weight]:.4f} against {objective[1.0]:.4f} the networks alone and {objective[0.0]:.4f} "
            f"OIDN alone, on {len(names)} frames")
    return written


__all__ = ["GRID", "fit_run", "fit_weight"]
