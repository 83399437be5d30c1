"""``kpcn bench``'s stage costs: what each stage of the pipeline costs, measured side by side.

:func:`stage_costs` (the ``stages`` of ``accuracy_time.json``): render samples per second; features (numba
against the float64 numpy reference and the EXR decode, ``kpcn_keras.studies.data_costs``); shard layouts side by
side; reading a training batch against a training step; a Keras training step against the same network in
plain torch (``kpcn_keras.studies.network_costs``); kernel application against the memory-bandwidth floor (the
kernel sizes of :data:`KERNEL_SIZES`); inference start-up, then a frame of the held-out size and a
``large_frame`` frame against OIDN for the configurations of :data:`INFERENCE`, and ``kpcn denoise`` of the
large frame as a command with its own peak memory. ``kpcn shards`` end to end is timed as a command too
(:func:`shards_command_cost`). The bench itself (:mod:`kpcn_keras.studies.bench`) calls these.

:func:`shard_format_costs` alone (whether the reader keeps a training step fed, and the format's bytes) is a
command of its own, on a set's training shards, or on a scratch set of random renders cut for it (the
reading time does not depend on the pixels)::

    python -m kpcn_keras.studies.bench_stages [--set-dir shards/default] [--batch-size 8]
"""

from __future__ import annotations

import dataclasses
import os
import re
import resource
import subprocess
import time
from pathlib import Path

import numpy as np

from kpcn_keras.config import ModelConfig
from kpcn_keras.studies.config import BenchConfig
from prep.errors import KpcnError

KERNEL_SIZES = (13, 21)  # the kernel sizes whose application is measured against the bandwidth floor
SHARD_READ_BATCHES = 20
SHARD_LAYOUT_IMAGES = 4  # (noisy, reference) pairs whose patches are written in every shard layout
OURS = "cpu"  # the configuration of the headline: the default preset
INFERENCE = (OURS, "kernel-5")  # whose frames are timed against OIDN: the default, and the fast configuration


def stage_costs(cfg: BenchConfig, scenes, seconds, inputs, plans, log) -> dict:
    """The costs of each stage (module docstring); every function it calls measures side by side."""
    from kpcn_keras.studies import data_costs, network_costs
    from prep.shards import ShardSet

    pixels = {s["name"]: s["width"] * s["height"] for s in scenes}
    stages = {"render": {
        "samples_per_s": sum(pixels[name] * n for name, n in seconds) / sum(seconds.values()),
        "per_scene": {name: sum(pixels[name] * n for n in cfg.raw_spp) / sum(seconds[(name, n)] for n in cfg.raw_spp)
                      for name in pixels}}}
    sset = ShardSet.named(cfg.shards_root, cfg.set_name)
    manifest = sset.complete_manifest()
    val_pairs = sset.pairs(manifest, "val")
    log("stage costs: features")
    stages["features"] = data_costs.feature_costs(val_pairs[0][0], repeats=cfg.repeats)
    log("stage costs: shard layouts")
    scratch = Path(cfg.runs_root) / "shard-layouts"
    train_pairs = [(str(a), str(b)) for a, b in sset.pairs(manifest, "train")]
    stages["shard_layouts"] = data_costs.shard_layout_costs(train_pairs[:SHARD_LAYOUT_IMAGES], scratch,
                                                            repeats=cfg.repeats, seed=cfg.seed,
                                                            patch_size=manifest["patch_size"])
    log("stage costs: a training step, Keras and plain torch")
    ours = planned_train_config(plans.get(cfg.budget, {}).get(OURS))
    model_config, batch = ours.model, ours.batch_size
    stages["train_step"] = network_costs.train_step_cost(model_config, batch_size=batch)
    paths = [e.path for e in sset.verified_shards("train", manifest, rounds=(0,))]
    stages["shard_read"] = shard_read_cost(paths, model_config, batch, cfg.seed)
    stages["shard_read"]["step_s"] = stages["train_step"]["keras_s"]
    stages["shard_read"]["ratio"] = stages["shard_read"]["batch_s"] / stages["train_step"]["keras_s"]
    stages["shard_read"]["bytes_per_patch"] = shard_bytes(paths, manifest["patch_size"])
    log("stage costs: kernel application")
    bandwidth = network_costs.memory_bandwidth()  # one floor for every kernel size of the report
    stages["kernel_application"] = [network_costs.kernel_application_cost(k, scenes[0]["height"], scenes[0]["width"],
                                                                      repeats=cfg.repeats, bandwidth=bandwidth)
                                    for k in KERNEL_SIZES]
    log("stage costs: inference")
    stages["repeats"] = cfg.repeats
    stages["inference"] = inference_cost(cfg, plans.get(cfg.budget, {}), inputs[(scenes[0]["name"], cfg.input_spp[0])])
    return stages


def planned_train_config(plan: dict | None):
    """The training configuration of a planned run, or the default one where the run is not in the bench."""
    from kpcn_keras.config import TrainConfig
    from kpcn_keras.run import Run

    if plan is None:
        return TrainConfig()
    return Run(plan["run"]).record().train


def shard_bytes(paths, patch_size: int) -> dict:
    """Bytes a patch: of ``kpcn-shard/2`` and of this format from the format's table
    (``prep.shards.v2_patch_bytes``, ``patch_bytes``), of the files ``paths`` on disk, and the patches of
    this format that 40 GB hold."""
    from prep.shards import FORMAT, open_shard, patch_bytes, v2_patch_bytes

    count = 0
    for path in paths:
        with open_shard(path) as f:
            count += len(f["source"])
    on_disk = sum(Path(p).stat().st_size for p in paths) / count
    return {"kpcn-shard/2": v2_patch_bytes(patch_size), FORMAT: patch_bytes(patch_size), "file": on_disk,
            "patch_size": patch_size, "patches_in_40GB": int(40e9 // on_disk)}


def shard_format_costs(paths, model_config: ModelConfig, batch_size: int, seed: int = 0) -> dict:
    """Side by side in one process: the bytes a patch (:func:`shard_bytes`), reading a training batch from
    ``paths`` (:func:`shard_read_cost`: the features recomputed) and a Keras training step of ``model_config``
    at that batch size on patches of the shards' size (``kpcn_keras.studies.network_costs.train_step_cost``),
    and the patches a second that the reader feeds against those that the step takes."""
    from kpcn_keras.studies import network_costs
    from prep.shards import open_shard

    with open_shard(paths[0]) as f:
        patch_size = int(f.attrs["patch_size"])
    read = shard_read_cost(paths, model_config, batch_size, seed)
    step = network_costs.train_step_cost(model_config, batch_size=batch_size, patch=patch_size)
    return {"bytes_per_patch": shard_bytes(paths, patch_size), "read": read,
            "read_only": read_only_costs(paths[0], batch_size, seed), "step_s": step["keras_s"],
            "step_patches_per_s": batch_size / step["keras_s"], "read_over_step": read["batch_s"] / step["keras_s"]}


def read_only_costs(path, batch_size: int, seed: int = 0) -> dict:
    """The HDF5 read of a diffuse training batch alone (no augmentation, no network input), median of
    :data:`SHARD_READ_BATCHES` batches, the same patches in both: from the shard ``path``, its stored
    datasets then the features recomputed (``prep.shards.read_stored``, ``derive``: ``compact_s``), against
    the same patches' features and reference read from a copy in ``kpcn-shard/2``'s layout (float32, one
    patch a chunk, Fletcher-32: ``v2_s``), written beside it for the measure and removed."""
    import h5py

    from prep.shards import branch_datasets, derive, open_shard, read_patches, read_stored, stored_datasets

    names = branch_datasets("diffuse")
    stored = stored_datasets(names)
    with open_shard(path) as f:
        n, p = len(f["source"]), int(f.attrs["patch_size"])
        whole = read_patches(f, names, range(n))
    v2 = Path(path).with_name(".v2-layout-copy.h5")
    try:
        with h5py.File(v2, "w") as g:
            for name in names:
                g.create_dataset(name, data=whole[name], chunks=(1,) + whole[name].shape[1:], fletcher32=True)
        rng = np.random.default_rng(seed)
        times = {"compact_s": [], "v2_s": []}
        with open_shard(path) as f, h5py.File(v2, "r") as g:
            ds = {name: f[name] for name in stored}
            old = {name: g[name] for name in names}
            for _ in range(SHARD_READ_BATCHES):
                ids = [int(i) for i in rng.integers(0, n, batch_size)]
                start = time.perf_counter()
                reads = [read_stored(ds, stored, i) for i in ids]
                derive({k: np.stack([r[k] for r in reads]) for k in stored}, names, p)
                times["compact_s"].append(time.perf_counter() - start)
                start = time.perf_counter()
                np.stack([old[names[0]][i] for i in ids]), np.stack([old[names[1]][i] for i in ids])
                times["v2_s"].append(time.perf_counter() - start)
    finally:
        v2.unlink(missing_ok=True)
    return {key: float(np.median(t)) for key, t in times.items()} | {"batch_size": batch_size}


def shard_read_cost(paths, model_config: ModelConfig, batch_size: int, seed: int) -> dict:
    """Seconds of reading one training batch (``ShardPatches``, augmented, diffuse, the features recomputed)
    from the shards ``paths``: the median of :data:`SHARD_READ_BATCHES` batches after one that opens the files."""
    from kpcn_keras.data import ShardPatches

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
    from kpcn_keras.studies.denoise_costs import alternating_seconds

    for fn in fns.values():
        fn(frame)
    calls = {name: (lambda fn=fn: fn(frame)) for name, fn in fns.items()}
    return {name: min(seconds) for name, seconds in alternating_seconds(calls, repeats).items()}


def shards_command_cost(set_dir: Path, scratch: Path) -> dict:
    """``kpcn shards`` of the shard set ``set_dir``'s renders with its own options, into a fresh set under
    ``scratch``, in a process of its own as a user runs it: its wall time,
    start-up included, with the thread count it got (shards are cut by that many processes); then the
    time ``sync`` takes after it, since the command leaves the last of its bytes to the system to write."""
    import shutil
    import sys

    from kpcn_keras.parser import command_line
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
                          "-o", str(scratch) + os.sep], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if res.returncode != 0:
        raise KpcnError(f"kpcn denoise {path} failed: {res.stderr.strip()[-500:]}")
    printed = res.stdout.strip().splitlines()
    peak = [float(m.group(1)) for m in map(re.compile(r"^peak memory (\d+) MiB").match, printed) if m]
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
        # timed against plain OIDN, one filter: the stricter of the two modes to be within a multiple of
        fns = {"ours": lambda a, d=d: d(a),
               **({"oidn": lambda a: baselines.oidn_denoise(a, mode="plain")} if oidn else {})}
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


def _scratch_set(folder: Path, patch_size: int) -> list[Path]:
    """The training shards of a set cut, with the default options but ``patch_size``, from random renders
    (4 scenes, 128 x 128, a noisy and a reference render each) written into ``folder``."""
    from prep import exr
    from prep.render.renderset import RenderSet
    from prep.shards import ShardConfig, build_shards, shard_paths

    rng = np.random.default_rng(0)
    renders = RenderSet("bench", folder / "renders")
    for i in range(4):
        for spp, variances in ((4, True), (256, False)):
            size = (128, 128)
            aovs = {"diffuse": rng.gamma(1.0, 0.5, size + (3,)), "specular": rng.gamma(0.3, 1.0, size + (3,)),
                    "albedo": rng.uniform(0, 1, size + (3,)), "normal": rng.uniform(-1, 1, size + (3,)),
                    "depth": rng.uniform(0, 10, size)}
            aovs["default"] = aovs["diffuse"] + aovs["specular"]
            if variances:
                aovs.update({n: rng.gamma(0.5, 0.1, size) for n in exr.VARIANCE_LAYERS})
            exr.write_aovs(renders.render_path(f"s{i}-000", spp),
                           {k: v.astype(np.float32) for k, v in aovs.items()})
    cfg = ShardConfig(set_name=renders.name, render_root=str(renders.root), out_root=str(folder / "shards"),
                      patch_size=patch_size, val_fraction=0.0)
    build_shards(cfg, progress=False)
    return shard_paths(cfg.set_dir, "train")


def main(argv=None) -> int:
    """Print :func:`shard_format_costs` for the ``cpu`` preset (module docstring) as JSON."""
    import argparse
    import json
    import tempfile

    from kpcn_keras.config import TrainConfig
    from prep.shards import shard_paths

    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.bench_stages", description=main.__doc__)
    parser.add_argument("--set-dir", help="a complete shard set (default: a scratch set of random renders)")
    parser.add_argument("--batch-size", type=int, help="default: the cpu preset's")
    args = parser.parse_args(argv)
    train = TrainConfig.from_preset(OURS)
    batch = args.batch_size or train.batch_size
    with tempfile.TemporaryDirectory(prefix="bench-shards-") as tmp:
        paths = shard_paths(args.set_dir, "train") if args.set_dir else _scratch_set(Path(tmp), 65)
        print(json.dumps({"preset": OURS, "batch_size": batch, "model": dataclasses.asdict(train.model),
                          **shard_format_costs(paths, train.model, batch)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
