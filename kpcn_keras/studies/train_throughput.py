"""Where the seconds of `make train`'s diffuse phase go: a diagnostic to run by hand, on a quiet
machine, after `make shards`. It changes nothing of the set and removes its scratch run.

    .venv/bin/python -m kpcn_keras.studies.train_throughput [--set default] [--steps 1200] [--threads N]
        [--sync | --cold]

It trains the diffuse branch of the default (`cpu`) preset for ``--steps`` (default: the preset's, what
`make train` runs) into a scratch run folder under ``runs/`` through the library call `kpcn train` makes, and
prints the line `kpcn train` prints (`[diffuse] N steps in S s: R steps/s ...`), then where those seconds went,
from Keras callbacks:

- before fit: every shard's checksum (outside the phase's seconds), the record, the model, the data streams;
- per epoch: the steps' compute (each ``on_train_batch_begin`` to ``end``), the wait for the next batch
  between steps (reading and augmenting it from the shards, in the training process), the validation, and
  the end-of-epoch writes (from the validation's end to this script's ``on_epoch_end``, which runs after the
  run's own callbacks: the log row and the checkpoint, written and fsynced);
- epoch 1 apart from the median of the later epochs (a first epoch that reads the shards from disk, or
  that waits for torch to warm up, stands out), and the per-step medians.

Before and after training it prints what else decides the result: the CPUs this process may use against
the CPU quota of its cgroup (torch and numba take the first; a smaller quota means oversubscribed threads),
the thread count used, the CPU model, the load average, the CPU time stolen by the hypervisor during
training, memory available, the dirty and writeback pages (a shard set just written is still being put on
disk, and every checkpoint's fsync waits behind it), and how much of the shard set's bytes is in the
page cache (mincore; `kpcn train` reads every shard once for its checksum before the first phase, so a set
that fits in memory is cached before the first epoch).

``--sync`` first puts every dirty page on disk (and says how long that took: the writeback a fresh
`make train` leaves pending at its first epoch); ``--cold`` also drops the page cache (root:
``echo 3 > /proc/sys/vm/drop_caches``), so that training starts with nothing cached.
"""

from __future__ import annotations

import argparse
import ctypes
import mmap
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


def steal_ticks() -> int:
    with open("/proc/stat") as f:
        fields = f.readline().split()
    return int(fields[8]) if len(fields) > 8 else 0


def cgroup_cpus() -> str:
    for path in ("/sys/fs/cgroup/cpu.max", "/sys/fs/cgroup/cpu/cpu.cfs_quota_us"):
        try:
            text = Path(path).read_text().split()
        except OSError:
            continue
        if text[0] in ("max", "-1"):
            return "no quota"
        period = int(text[1]) if len(text) > 1 else int(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        return f"{int(text[0]) / period:.2f} CPUs of quota"
    return "quota unknown"


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def cached_bytes(path: Path) -> tuple[int, int]:
    """(bytes of ``path`` in the page cache, its size), by mincore over a private mapping (nothing is read)."""
    size = path.stat().st_size
    if size == 0:
        return 0, 0
    libc = ctypes.CDLL(None, use_errno=True)
    page = mmap.PAGESIZE
    pages = (size + page - 1) // page
    vec = (ctypes.c_ubyte * pages)()
    with open(path, "rb") as f, mmap.mmap(f.fileno(), size, access=mmap.ACCESS_COPY) as mm:
        anchor = ctypes.c_char.from_buffer(mm)
        try:
            if libc.mincore(ctypes.c_void_p(ctypes.addressof(anchor)), ctypes.c_size_t(size), vec) != 0:
                raise OSError(ctypes.get_errno(), f"mincore of {path}")
        finally:
            del anchor  # the mapping cannot close while a pointer into it is exported
    return min(size, sum(v & 1 for v in vec) * page), size


def state(label: str, shards: list[Path]) -> None:
    from prep.processes import proc_megabytes

    cached = [cached_bytes(p) for p in shards]
    mem = {k: int(v) for k, v in proc_megabytes("/proc/meminfo", ("MemTotal", "MemAvailable", "Dirty",
                                                                  "Writeback")).items()}
    print(f"{label}: load average {os.getloadavg()[0]:.2f}; memory available {mem['MemAvailable']} of "
          f"{mem['MemTotal']} MB, dirty {mem['Dirty']} MB, writeback {mem['Writeback']} MB; the set's shards "
          f"in the page cache: {sum(c for c, _ in cached) / 1e6:.0f} of {sum(s for _, s in cached) / 1e6:.0f} MB")


class Timer:
    """Keras callbacks that time each step, the wait before it, the validation and the end-of-epoch writes."""

    def __new__(cls):
        import keras

        class _Timer(keras.callbacks.Callback):
            def __init__(self):
                super().__init__()
                self.epochs: list[dict] = []
                self.started = time.perf_counter()
                self.first_epoch_at = None

            def on_train_begin(self, logs=None):
                self.fit_at = time.perf_counter()

            def on_epoch_begin(self, epoch, logs=None):
                now = time.perf_counter()
                if self.first_epoch_at is None:
                    self.first_epoch_at = now
                self.epoch = {"begin": now, "steps": [], "waits": [], "val": 0.0}
                self.last_end = now

            def on_train_batch_begin(self, batch, logs=None):
                self.batch_start = time.perf_counter()
                self.epoch["waits"].append(self.batch_start - self.last_end)

            def on_train_batch_end(self, batch, logs=None):
                self.last_end = time.perf_counter()
                self.epoch["steps"].append(self.last_end - self.batch_start)

            def on_test_begin(self, logs=None):
                self.val_start = time.perf_counter()

            def on_test_end(self, logs=None):
                self.val_end = time.perf_counter()
                self.epoch["val"] = self.val_end - self.val_start

            def on_epoch_end(self, epoch, logs=None):
                now = time.perf_counter()
                after = self.val_end if self.epoch["val"] else self.last_end
                self.epoch["writes"] = now - after
                self.epoch["total"] = now - self.epoch["begin"]
                self.epochs.append(self.epoch)

        return _Timer()


def summary(timer) -> None:
    def row(name, e):
        steps = len(e["steps"])
        print(f"  {name:<22} {e['total']:7.2f} s: compute {sum(e['steps']):6.2f} s ({steps} steps, median "
              f"{1e3 * statistics.median(e['steps']):.1f} ms), batch wait {sum(e['waits']):5.2f} s (median "
              f"{1e3 * statistics.median(e['waits']):.1f} ms), validation {e['val']:5.2f} s, "
              f"writes {e['writes']:5.2f} s")

    epochs = timer.epochs
    print(f"before fit: {timer.fit_at - timer.started:.2f} s (every shard's checksum, the record, the model, the data "
          f"streams; only the last two count in the phase's seconds); fit to its first epoch "
          f"{timer.first_epoch_at - timer.fit_at:.2f} s")
    row("epoch 1", epochs[0])
    if len(epochs) > 1:
        rest = epochs[1:]
        median = {k: statistics.median(sum(e[k]) if isinstance(e[k], list) else e[k] for e in rest)
                  for k in ("total", "val", "writes")}
        merged = {"steps": [t for e in rest for t in e["steps"]], "waits": [t for e in rest for t in e["waits"]]}
        print(f"  later epochs ({len(rest)}), median: {median['total']:.2f} s; validation {median['val']:.2f} s, "
              f"writes {median['writes']:.2f} s; step median {1e3 * statistics.median(merged['steps']):.1f} ms, "
              f"batch wait median {1e3 * statistics.median(merged['waits']):.1f} ms")
        print(f"  all epochs: compute {sum(sum(e['steps']) for e in epochs):.1f} s, batch wait "
              f"{sum(sum(e['waits']) for e in epochs):.1f} s, validation {sum(e['val'] for e in epochs):.1f} s, "
              f"writes {sum(e['writes'] for e in epochs):.1f} s")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--set", dest="set_name", default="default")
    p.add_argument("--shards", dest="shards_root", default="shards")
    p.add_argument("--steps", type=int, help="diffuse steps (default: the cpu preset's)")
    p.add_argument("--threads", type=int, help="as kpcn --threads (default: every core this process may use)")
    cache = p.add_mutually_exclusive_group()
    cache.add_argument("--sync", action="store_true", help="put every dirty page on disk first")
    cache.add_argument("--cold", action="store_true", help="sync and drop the page cache first (root)")
    args = p.parse_args(argv)

    from prep.threads import set_threads

    threads = set_threads(args.threads)
    if args.sync or args.cold:
        start = time.perf_counter()
        os.sync()
        print(f"sync: {time.perf_counter() - start:.2f} s")
    if args.cold:
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        print("page cache dropped")

    from kpcn_keras.config import TrainConfig
    from kpcn_keras.train import train

    fields = {"steps": args.steps, "decay_steps": args.steps} if args.steps else {}
    cfg = TrainConfig(set_name=args.set_name, shards_root=args.shards_root, branches=("diffuse",), **fields)
    shards = sorted(Path(cfg.set_dir).glob("round-000/shard-*.h5"))
    print(f"{cpu_model()}; {len(os.sched_getaffinity(0))} CPUs this process may use ({os.cpu_count()} in the "
          f"machine, {cgroup_cpus()}); threads for torch and numba: {threads}; python {sys.version.split()[0]}")
    state("before training", shards)
    Path("runs").mkdir(exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix="throughput-", dir="runs"))
    timer = Timer()
    steal = steal_ticks()
    try:
        train(cfg, scratch / "run", verbose=0, callbacks=[timer])
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    stolen = (steal_ticks() - steal) / os.sysconf("SC_CLK_TCK")
    state("after training", shards)
    print(f"CPU time stolen by the hypervisor during training: {stolen:.1f} s (all CPUs)")
    summary(timer)
    return 0


if __name__ == "__main__":
    sys.exit(main())
