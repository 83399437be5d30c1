import hashlib
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prep import features as _features

os.environ.setdefault("KERAS_BACKEND", "torch")

FIXTURES = Path(__file__).parent / "fixtures"
REPO = Path(__file__).resolve().parents[1]
TINY_MODEL = {"width": 6, "depth": 3, "kernel_size": 5}
# the float64 features the numba kernel is held to; it lives in the package, where the benchmark times it
reference_features = _features.reference_features


@pytest.fixture
def fixture_noisy() -> Path:
    return FIXTURES / "fixture-00008spp.exr"


@pytest.fixture
def fixture_reference() -> Path:
    return FIXTURES / "fixture-01024spp.exr"


def random_aovs(h: int, w: int, seed: int = 0, variances: bool = True) -> dict:
    """A random render in the AOV layout (float32), for tests that need no real scene."""
    rng = np.random.default_rng(seed)
    aovs = {
        "diffuse": rng.gamma(1.0, 0.5, (h, w, 3)),
        "specular": rng.gamma(0.3, 1.0, (h, w, 3)),
        "albedo": rng.uniform(0, 1, (h, w, 3)),
        "normal": rng.uniform(-1, 1, (h, w, 3)),
        "depth": rng.uniform(0, 10, (h, w)),
    }
    aovs["default"] = aovs["diffuse"] + aovs["specular"]
    if variances:
        for name in ("diffuse", "specular", "color", "albedo", "normal", "depth"):
            aovs[f"{name}Variance"] = rng.gamma(0.5, 0.1, (h, w))
    return {k: v.astype(np.float32) for k, v in aovs.items()}


def make_renders(root: Path, scenes=("a-000", "a-001", "b-000", "b-001"), size=(40, 44)) -> Path:
    """A folder of random noisy (4 spp) and reference (64 spp) renders in the AOV layout."""
    from prep import exr

    for i, scene in enumerate(scenes):
        exr.write_aovs(root / exr.render_filename(scene, 4), random_aovs(*size, seed=10 + i))
        exr.write_aovs(root / exr.render_filename(scene, 64), random_aovs(*size, seed=100 + i, variances=False))
    return root


def build_tiny_shards(tmp_path: Path, **kw):
    """Random renders cut into a small shard set; returns its ShardConfig."""
    from prep import shards

    make_renders(tmp_path / "renders" / "s")
    values = dict(set_name="s", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                  patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5, seed=3)
    values.update(kw)
    cfg = shards.ShardConfig(**values)
    shards.build_shards(cfg, progress=False)
    return cfg


def launcher_free_env(**extra) -> dict:
    """This process's environment without a launcher's variables (a test may run under one), and ``extra``."""
    from prep.parts import LOCAL_RANK, RANK, WORLD_SIZE

    return {**{k: v for k, v in os.environ.items() if k not in (RANK, WORLD_SIZE, LOCAL_RANK)}, **extra}


def torchrun(*args) -> list[str]:
    """The documented launch line on 2 processes of this machine, for ``kpcn <args>``."""
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
            "-m", "kpcn_keras.cli", *args]


def _corner_form_factor(a, b, h):
    """Form factor from a differential area to a parallel a x b rectangle at height h whose corner is
    straight above it (standard closed form)."""
    x, y = a / h, b / h
    return (x / math.sqrt(1 + x * x) * math.atan(y / math.sqrt(1 + x * x))
            + y / math.sqrt(1 + y * y) * math.atan(x / math.sqrt(1 + y * y))) / (2 * math.pi)


def rect_form_factor(x0, x1, z0, z1, h):
    """Form factor from a differential area at the origin (normal +y) to the rectangle
    [x0, x1] x [z0, z1] at height h, parallel to it: signed corner decomposition (the corner form
    factor is odd in each extent)."""
    f = _corner_form_factor
    return f(x1, z1, h) - f(x0, z1, h) - f(x1, z0, h) + f(x0, z0, h)


def randomise(model, seed: int = 0, scale: float = 0.3) -> None:
    """Replace every weight (the zero-initialised head too) by random values; BN variances stay positive."""
    rng = np.random.default_rng(seed)
    new = []
    for w in model.weights:
        shape = tuple(w.shape)
        if "variance" in w.path:
            new.append(rng.uniform(0.5, 1.5, size=shape))
        else:
            new.append(rng.normal(size=shape) * scale)
    model.set_weights([v.astype(np.float32) for v in new])


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A run folder with both branches of a tiny KPCN trained for a few steps on random renders."""
    from kpcn_keras.train import TrainConfig, train

    tmp = tmp_path_factory.mktemp("run")
    shard_cfg = build_tiny_shards(tmp)
    cfg = TrainConfig.from_preset(
        "cpu", set_name="s", shards_root=shard_cfg.out_root,
        model=TINY_MODEL, steps=8, steps_per_epoch=4, batch_size=2, val_batches=1,
    )
    return train(cfg, tmp / "runs" / "r", verbose=0)


def kpcn(*args, cwd, timeout=300, file_size_limit=None) -> subprocess.CompletedProcess:
    """``kpcn -q ARGS`` as a user runs it, in a fresh process with a bare environment.

    ``file_size_limit`` (bytes): the process and its children may write no file larger (RLIMIT_FSIZE), so
    a write past it fails in ``write(2)`` itself with EFBIG ("File too large"; Python ignores SIGXFSZ), as
    on a full disk, for every library alike: a file system error at the write primitive, without root."""
    def limit():
        import resource

        resource.setrlimit(resource.RLIMIT_FSIZE, (file_size_limit, file_size_limit))

    return subprocess.run([sys.executable, "-m", "kpcn_keras.cli", "-q", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout,
                          preexec_fn=limit if file_size_limit is not None else None,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "KERAS_BACKEND": "torch"})


class SmallDisk:
    """A folder on a tmpfs of its own, ``size`` bytes (64 kB: full after the first file of any size), and
    :meth:`grow`, the space freed."""

    def __init__(self, path: Path, size: str = "64k"):
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        try:
            res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                                 capture_output=True, text=True)
            why = (res.stderr.strip() or f"exit {res.returncode}") if res.returncode else None
        except OSError as exc:
            why = str(exc)
        if why:
            pytest.skip(f"a full disk needs a small tmpfs, and mounting one is not permitted here (uid "
                        f"{os.getuid()}: {why})")

    def grow(self, size: str = "256m") -> None:
        subprocess.run(["mount", "-o", f"remount,size={size}", str(self.path)], check=True)

    def unmount(self) -> None:
        subprocess.run(["umount", "--lazy", str(self.path)], check=True)


@pytest.fixture
def small_disk(tmp_path):
    """A full disk: :class:`SmallDisk` at ``tmp_path/disk`` (root only; the test is skipped, saying why,
    where mounting is not permitted)."""
    disk = SmallDisk(tmp_path / "disk")
    yield disk
    disk.unmount()


def assert_one_line_error(res: subprocess.CompletedProcess, *needles: str) -> None:
    """Exit status 2, one line on stderr containing every needle, nothing on stdout, no traceback."""
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert res.stdout.strip() == "", res.stdout
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def checksums(root: Path) -> dict[str, str]:
    """SHA-256 of every file under ``root`` but dot files (locks, temporaries), by path relative to it."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(root).rglob("*")) if p.is_file() and not p.name.startswith(".")}


def checksums_but_timings(root: Path) -> dict[str, str]:
    """:func:`checksums` but the timings files (``timings.json``, one per folder that keeps seconds): what a
    resumed command must leave byte-identical to an uninterrupted one."""
    return {k: v for k, v in checksums(root).items() if Path(k).name != "timings.json"}
