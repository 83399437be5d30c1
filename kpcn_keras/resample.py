"""``kpcn resample``: grow a run's training set where its denoiser still fails, and keep training on it
(docs/method.md §8, in the manner of DAgger's dataset aggregation).

For each error round k = 1..N of :class:`kpcn_keras.config.ResampleConfig`, on a run whose training finished:

1. **Error maps and new patches.** The run's current denoiser (:class:`kpcn_keras.denoise.Denoiser`, tiled as
   ``kpcn denoise``) denoises every training input; ``prep.shards.build_error_round`` turns each per-pixel
   error map against the reference into a patch PDF, mixes it with the variance PDF, draws new positions that
   no earlier round used, and writes ``shards/<set>/round-<k>/`` with the round's provenance (the model files
   and their SHA-256, the metric, the mix weight). With ``error_weight`` 0 no model runs: the round is drawn
   from the variance PDF alone, the control of the experiment (``kpcn_keras.studies.resample_study``).
2. **Training.** Every branch network of the run (``diffuse`` and ``specular``, or ``shared``) continues from
   its latest file, optimizer and learning-rate schedule included, for ``round_steps`` steps on the training
   patches of rounds 0..k, as one more phase of the run (``<network>-round-<k>``: its own checkpoints, rows of
   ``log.csv``, band of ``loss.png``; the record's components then point at it, so ``kpcn denoise``,
   ``evaluate`` and ``figures`` use the newest networks).
3. **Measure.** Held-out relMSE and DSSIM (the set's validation frames, never resampled; the means and each
   frame's); one printed line;
   the round's entry in the run record (``resample``) and in ``<run>/resample/rounds.json``, its seconds
   (error maps, shards, training, evaluation) in ``<run>/resample/timings.json``, and
   ``<run>/resample/round-<k>.png``: the map that drove the draw on one training render (the one with the
   largest mean) with the round's new patches drawn over it, beside the render with every round's patches.

The networks are loaded once per state (``Denoiser.from_run`` on the loop's own copy of the record): the
scores before the rounds and the next round's error maps share one denoiser, and it is loaded again only
after a round's training wrote new networks.

**Resume.** The run's lock is held throughout. Interrupted anywhere, the same command goes on: a round whose
shards are incomplete is finished from its plan (or drawn again if its plan was not written), a complete round
is never rebuilt or duplicated, and training continues from the phase's checkpoint, ending with the weights an
uninterrupted loop ends with. A rerun with more ``--rounds`` adds rounds; other settings are refused.
Every wall-clock figure is in the timings files (the run's ``timings.json``, per phase, and the resample
folder's, per round), so that a resumed loop ends with the bytes of an uninterrupted one in every other
file (``tests/test_resample_resume.py``); a step's seconds are those of the sessions that finished it.

Runs with joint fine-tuning, an albedo network or a compositor are refused: their final-colour phases would have
to be redone after every round, which this loop does not do.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from kpcn_keras.config import Phase, ResampleConfig, TrainConfig
from prep.errors import KpcnError
from prep.files import atomic_write_json, check_writable, pyplot, read_json, save_png, sha256_file
from prep.shards import ErrorRound, ShardSet, build_error_round, round_name

if TYPE_CHECKING:  # run.py imports keras, which this module imports only when the loop runs
    from kpcn_keras.run import Run


def base_phases(train_cfg: TrainConfig) -> list[Phase]:
    """The run's own phases; KpcnError unless each trains one branch network."""
    phases = train_cfg.phases()
    final = [p.name for p in phases if p.trains_on_final_colour]
    if final:
        raise KpcnError(
            f"kpcn resample continues the branch networks; this run also has {', '.join(final)} phase(s), "
            "which would have to be redone after every round. Resample a run without --joint-steps, "
            "--albedo-steps and --compositor"
        )
    return phases


def round_phases(train_cfg: TrainConfig, cfg: ResampleConfig, k: int, newest: int) -> list[Phase]:
    """The phases of round ``k``: each branch network continues its previous phase on rounds 0..``newest``
    (``k``, or 0 when the loop adds no patches)."""
    base = base_phases(train_cfg)
    epoch_steps = min(train_cfg.steps_per_epoch, cfg.round_steps)
    first = sum(p.epochs for p in base) + (k - 1) * len(base) * -(-cfg.round_steps // epoch_steps)
    phases = []
    for p in base:
        done = p.steps + (k - 1) * cfg.round_steps  # the optimizer's iterations when the phase starts
        lr = p.learning_rate * train_cfg.decay_rate ** (done / train_cfg.decay_steps)  # ExponentialDecay's
        phase = Phase(f"{p.name}-{round_name(k)}", cfg.round_steps, lr, first, epoch_steps, network=p.component,
                      rounds=newest, continues=p.name if k == 1 else f"{p.name}-{round_name(k - 1)}")
        phases.append(phase)
        first += phase.epochs
    return phases


def round_weights(entries, k: int, decay: float) -> list[float] | None:
    """One weight per training shard of rounds 0..k: ``decay`` ** (k − j) for round j (None when every
    patch weighs the same)."""
    if decay == 1.0:
        return None
    from prep.shards import round_index

    return [decay ** (k - round_index(e.round)) for e in entries]


def _model_provenance(run, record: dict) -> dict:
    """What makes the error maps: each component's file and its SHA-256."""
    return {name: {"file": entry["file"], "sha256": sha256_file(run.dir / entry["file"])}
            for name, entry in sorted(record["components"].items())}


def _check_loop(record: dict, cfg: ResampleConfig, run) -> dict:
    """The record's ``resample`` entry (created if new); KpcnError if it was started with other settings."""
    loop = record.setdefault("resample", {"config": cfg.to_dict(), "rounds": {}})
    old = {k: v for k, v in loop["config"].items() if k != "rounds"}
    if old != cfg.identity():
        differ = sorted(k for k in cfg.identity() if old.get(k) != cfg.identity()[k])
        raise KpcnError(f"{run.record_path}: its resample loop was started with other settings (differs in "
                        f"{', '.join(differ)}); continue it with those, or resample a copy of the run")
    # the most rounds ever asked for: a rerun asking for fewer finds the loop as it is
    loop["config"] = {**cfg.to_dict(), "rounds": max(cfg.rounds, loop["config"]["rounds"])}
    return loop


def resample(cfg: ResampleConfig, run: Run, *, verbose="auto", progress: bool = True, command: str = "",
             log=print) -> dict:
    """Run (or resume) the loop on the finished ``run``; returns the record's ``resample`` entry with
    the seconds of the run before the rounds and of each round joined in (:func:`with_seconds`)."""
    import keras

    from kpcn_keras.evaluate import held_out_frames
    from kpcn_keras.train import check_inputs

    if keras.backend.backend() != "torch":
        raise KpcnError(f"kpcn trains on the torch backend; KERAS_BACKEND selects {keras.backend.backend()!r}")
    finished = run.finished_record(resampling=True)
    train_cfg = finished.train
    base = base_phases(train_cfg)
    sset = run.shard_set(finished)
    manifest, _ = check_inputs(train_cfg, sset)
    if manifest["content_key"] != finished.content_key:
        raise KpcnError(f"{sset.dir}: the shard set changed since {run.dir} was trained (its renders or options)")
    patches_per_image = cfg.patches_per_image
    if patches_per_image is None:
        patches_per_image = int(manifest["config"]["patches_per_image"])
    check_writable(run.resample_dir, "resample folder", directory=True)
    frames = held_out_frames(run, finished)
    if not frames:
        raise KpcnError(f"{sset.dir}: no held-out scenes to measure the rounds on")

    with run.lock():
        run.remove_temporaries()
        record = run.read_record()  # what the lock holder before us left
        loop = _check_loop(record, cfg, run)
        # the networks as they are now, loaded when first needed and again only after a round trained them
        current = _Current(run, record)
        if "before" not in loop:
            start = time.perf_counter()
            loop["before"] = {**_scores(current(), frames), "steps": base[0].steps,
                              "patches": sum(e.patches for e in sset.entries(manifest, "train", [0]))}
            seconds = time.perf_counter() - start
            run.write_record(record)
            _write_rounds(run, loop)
            add_seconds(run, "before", {"evaluation": seconds})
        previous = loop["before"]
        for k in range(1, cfg.rounds + 1):
            name = round_name(k)
            entry = loop["rounds"].setdefault(name, {"status": "shards"})
            if entry["status"] != "done":
                if entry["status"] == "shards":
                    _new_patches(run, record, sset, cfg, k, patches_per_image, command, progress, current)
                total_patches = _train_round(run, record, sset, train_cfg, cfg, k, patches_per_image > 0, verbose)
                current.trained()
                start = time.perf_counter()
                entry.update(status="done", round=k, **_scores(current(), frames), steps=cfg.round_steps,
                             total_steps=base[0].steps + k * cfg.round_steps, total_patches=total_patches)
                seconds = time.perf_counter() - start
                run.write_record(record)
                _write_rounds(run, loop)
                log(round_line(name, entry, previous, add_seconds(run, name, {"evaluation": seconds})))
            previous = entry
    return with_seconds(loop, read_timings(run))


def read_timings(run) -> dict:
    """``<run>/resample/timings.json``: ``before`` and each round's name -> what -> seconds ({} before any)."""
    path = run.resample_timings_path
    return read_json(path, "resample timings") if path.is_file() else {}


def add_seconds(run, key: str, seconds: dict) -> dict:
    """Add ``seconds`` (error_maps, shards, training, evaluation -> s) to ``key``'s entry of the resample
    timings (``before`` or a round's name), written after the record says the work is done: a kill in
    between loses them, as a kill during the work does. Returns the entry."""
    timings = read_timings(run)
    entry = timings.setdefault(key, {})
    for what, value in seconds.items():
        entry[what] = round(entry.get(what, 0.0) + value, 2)
    atomic_write_json(run.resample_timings_path, timings)
    return entry


def with_seconds(loop: dict, timings: dict) -> dict:
    """A copy of the loop record with the seconds of ``before`` and of every round joined in as ``seconds``
    (what the study's costs and reports read)."""
    joined = {**loop, "rounds": {name: {**entry, "seconds": timings.get(name, {})}
                                 for name, entry in loop["rounds"].items()}}
    if "before" in loop:
        joined["before"] = {**loop["before"], "seconds": timings.get("before", {})}
    return joined


class _Current:
    """The denoiser of the run's current networks (those the loop's ``record`` names): loaded on the first
    call, and again on the first call after :meth:`trained` (a round's training wrote new ones)."""

    def __init__(self, run, record: dict):
        self.run, self.record, self.denoiser = run, record, None

    def __call__(self):
        from kpcn_keras.denoise import Denoiser

        if self.denoiser is None:
            self.denoiser = Denoiser.from_run(self.run, record=self.run.parse_record(self.record), resampling=True)
        return self.denoiser

    def trained(self) -> None:
        self.denoiser = None


def _scores(denoiser, frames: list[dict]) -> dict:
    """Held-out relMSE and DSSIM of the run's current networks (``denoiser``): the means and every frame's."""
    from kpcn_keras.evaluate import frame_scores

    scores = frame_scores([denoiser(f["noisy"])["default"] for f in frames], frames)
    return {"relmse": scores["relmse"], "dssim": scores["dssim"], "frames": scores["frames"]}


def _new_patches(run, record: dict, sset: ShardSet, cfg: ResampleConfig, k: int, patches_per_image: int,
                 command: str, progress: bool, current: _Current) -> None:
    """Step 1 of round ``k``: its shards (none when the loop adds no patches), drawn from the error maps of
    the ``current`` networks, and its picture; the round's entry then says ``training``."""
    entry = record["resample"]["rounds"][round_name(k)]
    patches, seconds = 0, {}
    if patches_per_image:
        denoise = None
        if cfg.error_weight > 0:
            denoiser = current()
            denoise = lambda aovs: denoiser(aovs)["default"]  # noqa: E731
        model = _model_provenance(run, record) if cfg.error_weight > 0 else {}
        rnd = ErrorRound(k, patches_per_image, cfg.error_weight, cfg.metric, model, command=command)
        result = build_error_round(sset.dir, rnd, denoise, progress=progress)
        seconds = result.seconds
        if result.figure:
            entry["png"] = run.relative(round_png(run, sset, result, k, cfg))
        patches = result.patches
    entry.update(status="training", patches=patches)
    run.write_record(record)
    add_seconds(run, round_name(k), seconds)


def _train_round(run, record: dict, sset: ShardSet, train_cfg: TrainConfig, cfg: ResampleConfig, k: int,
                 adds_patches: bool, verbose) -> int:
    """Step 2 of round ``k``: every branch network continues on rounds 0..k (round 0 alone when the loop
    adds no patches); returns the training patches it read."""
    from kpcn_keras.train import run_phase

    manifest = sset.complete_manifest()
    rounds = list(range(k + 1)) if adds_patches else [0]
    train_entries = sset.verified_shards("train", manifest, rounds=rounds)
    paths = {"train": [e.path for e in train_entries],
             "val": [e.path for e in sset.verified_shards("val", manifest, rounds=[0])],
             "train_weights": round_weights(train_entries, k, cfg.round_decay)}
    for phase in round_phases(train_cfg, cfg, k, rounds[-1]):
        elapsed = run_phase(train_cfg, run, record, phase, paths, verbose=verbose)
        add_seconds(run, round_name(k), {"training": elapsed})
    return sum(e.patches for e in train_entries)


def _write_rounds(run, loop: dict) -> None:
    """``<run>/resample/rounds.json``: the settings, the run before the rounds, and every round so far."""
    atomic_write_json(run.resample_record_path, loop)


def round_line(name: str, entry: dict, previous: dict, s: dict) -> str:
    """The one line printed per round; ``s``: its seconds (:func:`add_seconds`)."""
    return (f"[{name}] +{entry['patches']} patches ({entry['total_patches']} in all), {entry['steps']} steps per "
            f"network ({entry['total_steps']} in all): held-out relMSE {previous['relmse']:.4f} → "
            f"{entry['relmse']:.4f}, DSSIM {previous['dssim']:.4f} → {entry['dssim']:.4f}; error maps "
            f"{s.get('error_maps', 0.0):.1f} s, shards {s.get('shards', 0.0):.1f} s, training "
            f"{s.get('training', 0.0):.1f} s")


def round_png(run, sset: ShardSet, result, k: int, cfg: ResampleConfig) -> Path:
    """``round-<k>.png``: the map that drove the draw on one training render with the round's new patches
    outlined (left), and the render with the patches of every round so far (right), like Fig. 3 of the report."""
    from matplotlib.patches import Rectangle

    from prep import exr
    from prep.colour import tonemap
    from prep.shards import used_positions

    plt = pyplot()
    fig_info = result.figure
    manifest = result.manifest
    source = manifest["sources"][fig_info["source"]]
    p = int(manifest["patch_size"])
    noisy = exr.read_aovs(sset.resolve(source["path"]), variances=False)["default"]
    earlier = used_positions(sset, manifest, range(k)).get(fig_info["source"], np.empty((0, 2)))
    h, w = noisy.shape[:2]
    scale = 4.0 / max(h, w)
    fig, axes = plt.subplots(1, 2, figsize=(2 * w * scale + 1.2, h * scale + 0.9))
    what = f"{cfg.metric} error" if fig_info["is_error"] else "variance importance"
    shown = axes[0].imshow(np.log10(fig_info["map"] + 1e-6), cmap="magma", interpolation="nearest")
    fig.colorbar(shown, ax=axes[0], fraction=0.046, pad=0.02, label=f"log10 {what}")
    axes[0].set_title(f"{what}, {round_name(k)} patches", fontsize=9)
    axes[1].imshow(tonemap(noisy), interpolation="nearest")
    axes[1].set_title(f"{Path(source['path']).name}: earlier rounds (white), {round_name(k)} (cyan)", fontsize=9)
    for ax, layers in ((axes[0], [(fig_info["positions"], "cyan")]),
                       (axes[1], [(earlier, "white"), (fig_info["positions"], "cyan")])):
        for positions, colour in layers:
            for y, x in positions:
                ax.add_patch(Rectangle((x - 0.5, y - 0.5), p, p, fill=False, edgecolor=colour, linewidth=0.6))
        ax.axis("off")
    fig.tight_layout()
    return save_png(fig, run.resample_png(round_name(k)))
