"""Error rounds (docs/method.md §8): round k >= 1 of a set, written by :func:`build_error_round`.

From every training input, positions are drawn from the PDF of a model's per-pixel error mixed with the
variance PDF, never at a position an earlier round used; the round's manifest entry keeps its provenance
(the model's files with their SHA-256, the error metric, the mix weight: :class:`ErrorRound`). The positions
are drawn first and written as the round's plan (``round-<k>/plan.npz``), then its shards are cut from the
plan through the same per-image step and writer as round 0 (``prep.shards.patches``,
``prep.shards.writer``). Both steps resume. Held-out scenes are never resampled. A set of another input set
than the full one is cut as its round 0 is (``prep.shards.patches.shard_layers``); the ``denoise`` it is given
(a run's ``Denoiser``) restricts the renders to its run's input set itself.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from prep import exr, sampling
from prep.bounds import is_integer
from prep.errors import OptionError
from prep.files import atomic_path, atomic_write_json, remove_temporaries, sha256_file
from prep.shards.config import ShardConfig
from prep.shards.format import ShardError, open_shard
from prep.shards.patches import draw, round_pdf
from prep.shards.renders import reference_of
from prep.shards.shardset import PLAN, ShardSet, round_index, round_name
from prep.shards.writer import RoundDraw, shard_specs, write_round

log = logging.getLogger("kpcn")


@dataclass(frozen=True)
class ErrorRound:
    """What error round ``index`` (>= 1) of a set is drawn with; all but ``command`` is its provenance.

    ``patches_per_image`` new positions per training input, from ``error_weight`` times the PDF of the
    ``metric`` error map (``prep.sampling.ERROR_METRICS``) of ``model``'s output plus the rest times the
    variance PDF; ``model`` says what made the error maps (the caller's record: files with SHA-256). With
    ``error_weight`` 0 no model is run: the round is drawn from the variance PDF alone (a control).
    """

    index: int
    patches_per_image: int
    error_weight: float
    metric: str
    model: dict
    command: str = field(default="", compare=False)

    def __post_init__(self):
        if not is_integer(self.index) or self.index < 1:
            raise OptionError("rounds", f"error rounds are numbered from 1, got {self.index!r}")
        if not is_integer(self.patches_per_image) or self.patches_per_image < 1:
            raise OptionError("patches_per_image", f"must be an integer >= 1, got {self.patches_per_image!r}")
        if not 0.0 <= self.error_weight <= 1.0:
            raise OptionError("error_weight", f"must be in [0, 1], got {self.error_weight!r}")
        if self.metric not in sampling.ERROR_METRICS:
            raise OptionError("metric", f"must be one of {', '.join(sampling.ERROR_METRICS)}, got {self.metric!r}")

    def provenance(self) -> dict:
        return {"patches_per_image": self.patches_per_image, "error_weight": float(self.error_weight),
                "metric": self.metric, "model": self.model}


@dataclass
class RoundResult:
    """What :func:`build_error_round` did: the manifest after it, the patches the round holds, seconds spent
    on error maps (denoising included) and on shards in this call (0 for a round found complete), and the
    map that drove the draw on one input (``figure``: source id, the map, whether it is an error map,
    and the round's positions on that input)."""

    manifest: dict
    patches: int
    seconds: dict
    figure: dict


def training_inputs(manifest: dict) -> list[int]:
    """The source ids of the training inputs: the renders that error rounds resample."""
    return [i for i, s in enumerate(manifest["sources"]) if s["role"] == "input" and s["split"] == "train"]


def used_positions(sset: ShardSet, manifest: dict, rounds) -> dict[int, np.ndarray]:
    """source id -> (n, 2) positions that the training shards of ``rounds`` took from it."""
    found: dict[int, list[np.ndarray]] = defaultdict(list)
    for entry in sset.verified_shards("train", manifest, rounds):
        with open_shard(entry.path) as f:
            source, position = f["source"][:], f["position"][:]
        for sid in np.unique(source):
            found[int(sid)].append(position[source == sid])
    return {sid: np.concatenate(parts) for sid, parts in found.items()}


def _read_plan(path: Path) -> dict:
    with np.load(path) as z:
        return {name: z[name] for name in z.files}


def _write_plan(path: Path, plan: dict) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **plan)


def build_error_round(set_dir: str | os.PathLike, rnd: ErrorRound, denoise=None, *, progress: bool = True,
                      workers: int | None = None) -> RoundResult:
    """Write error round ``rnd.index`` of the complete set in ``set_dir``; returns what was done.

    ``denoise(noisy AOVs) -> (H, W, 3)`` linear colour is the model whose error is measured against each
    training input's reference (not called when ``rnd.error_weight`` is 0). Two steps, each resumable:
    the positions of every training input are drawn and written as the round's plan (``plan.npz``), then
    its shards are cut from the plan. Interrupted anywhere, the same call finishes the round: a plan whose
    provenance matches is reused, whole shards are kept. A complete round of the same provenance is never
    rebuilt; one of another provenance, or a gap in the rounds, is a ShardError.
    """
    sset = ShardSet(set_dir)
    k, name = rnd.index, round_name(rnd.index)
    with sset.lock():
        remove_temporaries(sset.dir)  # a manifest write that a kill cut short
        manifest = sset.complete_manifest()
        config = ShardConfig(**manifest["config"])
        have = set(manifest["rounds"])
        later = sorted(n for n in have if round_index(n) > k)
        if later:
            raise ShardError(f"{sset.dir}: has {', '.join(later)} beyond {name}; rounds are drawn in order")
        before = list(range(k))
        incomplete = [round_name(j) for j in before if j not in sset.complete_rounds(manifest)]
        if incomplete:
            raise ShardError(f"{sset.dir}: {name} needs every earlier round complete; {', '.join(incomplete)} "
                             "is not (run the command that writes it again)")
        entry = manifest["rounds"].get(name)
        if entry is not None and entry.get("provenance") != rnd.provenance():
            if entry.get("status") == "complete":
                raise ShardError(
                    f"{sset.round_dir(k)}: drawn with another model or settings ({_provenance_diff(entry, rnd)}); "
                    f"remove {sset.round_dir(k)} and its entry, or continue on a copy of the set"
                )
            log.warning("%s: an unfinished %s of other settings; drawing it again", sset.dir, name)
            entry = None
        if entry is None and sset.round_dir(k).exists():
            shutil.rmtree(sset.round_dir(k))
        seconds = {"error_maps": 0.0, "shards": 0.0}
        plan_path = sset.round_dir(k) / PLAN
        plan = None
        if entry is not None and plan_path.is_file() and sha256_file(plan_path) == entry["plan"]["sha256"]:
            plan = _read_plan(plan_path)
        if entry is not None and entry["status"] == "complete":
            return RoundResult(manifest, _round_patches(entry), seconds, _figure(plan))
        if plan is None:
            start = time.perf_counter()
            plan = _draw_error_round(sset, manifest, config, rnd, denoise, progress)
            seconds["error_maps"] = time.perf_counter() - start
            _write_plan(plan_path, plan)
            entry = {"kind": "error", "status": "building", "provenance": rnd.provenance(),
                     "plan": {"path": sset.relative(plan_path), "sha256": sha256_file(plan_path)}, "shards": []}
            manifest["rounds"][name] = entry
            atomic_write_json(sset.manifest_path, manifest)
        start = time.perf_counter()
        inputs = training_inputs(manifest)
        specs = shard_specs([("train", sid, rnd.patches_per_image) for sid in inputs], config.patches_per_shard)
        rows = {int(sid): np.flatnonzero(plan["source"] == sid) for sid in inputs}
        drawn = {sid: (plan["position"][r], plan["pdf"][r]) for sid, r in rows.items()}
        write_round(sset, config, manifest, k, specs, RoundDraw(config, k, drawn), rnd.command, progress, workers)
        entry["status"] = "complete"
        atomic_write_json(sset.manifest_path, manifest)
        seconds["shards"] = time.perf_counter() - start
    return RoundResult(manifest, _round_patches(entry), seconds, _figure(plan))


def _draw_error_round(sset: ShardSet, manifest: dict, config: ShardConfig, rnd: ErrorRound, denoise,
                      progress: bool) -> dict:
    """The plan of an error round: every training input's positions (and PDF values), and the map that
    drove the draw on the input where it is largest on average (for the round's figure)."""
    from tqdm import tqdm

    inputs = training_inputs(manifest)
    used = used_positions(sset, manifest, range(rnd.index))
    uses_model = rnd.error_weight > 0.0
    if uses_model and denoise is None:
        raise ValueError("an error round with error_weight > 0 needs a denoise function")
    p = config.patch_size
    for sid in inputs:  # before any denoising: the positions left must hold the round
        src = manifest["sources"][sid]
        h, w = exr.read_header(sset.resolve(src["path"]))
        left = (h - p + 1) * (w - p + 1) - len(np.unique(used.get(sid, np.empty((0, 2))), axis=0))
        if rnd.patches_per_image > left:
            raise OptionError("patches_per_image", f"{rnd.patches_per_image} exceeds the {left} patch positions of "
                              f"{src['path']} that earlier rounds left unused")
    sources, positions, pdfs = [], [], []
    figure = {"figure_source": -1, "figure_mean": -np.inf}
    for sid in tqdm(inputs, desc=f"error maps {round_name(rnd.index)}", unit="image", disable=not progress):
        src = manifest["sources"][sid]
        noisy = exr.read_aovs(sset.resolve(src["path"]))
        if uses_model:
            reference = exr.read_aovs(sset.resolve(reference_of(manifest["sources"], src)["path"]), variances=False)
            drive = sampling.error_map(np.asarray(denoise(noisy)), reference["default"], rnd.metric)
        else:
            drive = sampling.variance_importance(noisy, config.colour_weight, config.normal_weight)
        pos, pdf = draw(round_pdf(noisy, config, drive if uses_model else None, rnd.error_weight),
                        rnd.patches_per_image, config, sid, rnd.index, used.get(sid))
        sources.append(np.full(len(pos), sid, np.int32))
        positions.append(pos)
        pdfs.append(pdf)
        mean = float(np.mean(drive))
        if mean > figure["figure_mean"]:
            figure = {"figure_source": sid, "figure_mean": mean, "figure_map": drive.astype(np.float32)}
    return {"source": np.concatenate(sources), "position": np.concatenate(positions).astype(np.int32),
            "pdf": np.concatenate(pdfs), "figure_source": np.int32(figure["figure_source"]),
            "figure_map": figure["figure_map"], "figure_is_error": np.bool_(uses_model)}


def _figure(plan: dict | None) -> dict:
    if plan is None:
        return {}
    sid = int(plan["figure_source"])
    return {"source": sid, "map": plan["figure_map"], "is_error": bool(plan["figure_is_error"]),
            "positions": plan["position"][plan["source"] == sid]}


def _round_patches(entry: dict) -> int:
    return sum(s["patches"] for s in entry["shards"])


def _provenance_diff(entry: dict, rnd: ErrorRound) -> str:
    old, new = entry.get("provenance") or {}, rnd.provenance()
    return ", ".join(f"{k} {old.get(k)!r} vs {new[k]!r}" for k in new if old.get(k) != new[k]) or "unknown"
