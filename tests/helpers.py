"""What several test files share: small inputs (random renders, tiny shard sets), the command line run as a
user runs it (:func:`kpcn`, in a fresh process) or in this process (:func:`run_main`), and the checks of its
one-line errors and of files left byte-identical. Fixtures live in ``conftest.py``; tests import these with
``from helpers import ...``."""

import contextlib
import hashlib
import io
import logging
import math
import os
import subprocess
import sys
import tempfile
import warnings
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


@contextlib.contextmanager
def process_state_kept():
    """Put back what ``kpcn_keras.cli.main`` (or a test around it) changes in the process: the environment
    (``set_threads`` writes ``OMP_NUM_THREADS``/``MKL_NUM_THREADS``), ``sys.argv``, the working directory,
    the root logger (``logging.basicConfig``) and the numba and torch thread counts."""
    import numba

    from prep import threads

    environ, cwd, argv = dict(os.environ), os.getcwd(), sys.argv[:]
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    counts = numba.get_num_threads(), threads.requested()
    torch = sys.modules.get("torch")
    torch_threads = torch.get_num_threads() if torch is not None else None
    try:
        yield
    finally:
        os.chdir(cwd)
        sys.argv[:] = argv
        os.environ.clear()
        os.environ.update(environ)
        root.handlers[:] = handlers
        root.setLevel(level)
        numba.set_num_threads(counts[0])
        threads._requested = counts[1]
        if torch_threads is not None:
            torch.set_num_threads(torch_threads)


def run_main(*args, cwd) -> subprocess.CompletedProcess:
    """``kpcn -q ARGS`` through ``kpcn_keras.cli.main`` in this process, in ``cwd``, as :func:`kpcn` runs it
    (``sys.argv`` as ``python -m kpcn_keras.cli`` sets it, which records keep; no launcher variables, no
    ``KPCN_DEBUG``; the root logger writing to this call's stderr, warnings shown
    as a fresh interpreter shows them, and what a library writes to file descriptors 1 and 2 caught too):
    its exit status (argparse's ``SystemExit`` too) and what it printed, without the seconds a fresh
    interpreter spends importing torch and keras. For the checks of what a command says and writes;
    :func:`kpcn` stays for those of the process itself (signals, limits, imports, a launcher)."""
    from kpcn_keras import cli
    from prep.parts import LOCAL_RANK, LOCAL_WORLD_SIZE, RANK, WORLD_SIZE

    argv = ["-q", *map(str, args)]
    out, err = io.StringIO(), io.StringIO()

    def show(message, category, filename, lineno, file=None, line=None):
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))

    with process_state_kept(), warnings.catch_warnings(), tempfile.TemporaryFile() as fd1, \
            tempfile.TemporaryFile() as fd2:
        for name in (RANK, WORLD_SIZE, LOCAL_RANK, LOCAL_WORLD_SIZE, "KPCN_DEBUG"):
            os.environ.pop(name, None)
        os.chdir(cwd)
        sys.argv[:] = [cli.__file__, *argv]
        root = logging.getLogger()
        root.handlers[:] = []  # as in a fresh process, so that main's basicConfig logs to this stderr
        root.setLevel(logging.WARNING)
        warnings.resetwarnings()  # the filters of a fresh interpreter (python -W default's complement)
        for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
            warnings.simplefilter("ignore", category)
        warnings.showwarning = show
        sys.stdout.flush(), sys.stderr.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(fd1.fileno(), 1), os.dup2(fd2.fileno(), 2)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    status = cli.main(argv)
                except SystemExit as exc:
                    status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                    if exc.code is not None and not isinstance(exc.code, int):
                        print(exc.code, file=sys.stderr)
        finally:
            os.dup2(saved[0], 1), os.dup2(saved[1], 2)
            os.close(saved[0]), os.close(saved[1])
        fd1.seek(0), fd2.seek(0)
        stdout = out.getvalue() + fd1.read().decode(errors="replace")
        stderr = err.getvalue() + fd2.read().decode(errors="replace")
    return subprocess.CompletedProcess(["kpcn", *argv], status, stdout, stderr)


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


def assert_one_line_error(res: subprocess.CompletedProcess, *needles: str) -> None:
    """Of a :func:`kpcn` or :func:`run_main` result: exit status 2, one line on stderr containing every needle, nothing on stdout, no traceback."""
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


def check_keras_layer(make, shapes, tmp_path: Path, batch: int = 2, seed: int = 0) -> None:
    """The contract every custom Keras layer of kpcn keeps (after keras' own ``run_layer_test``), for the
    layer ``make()`` builds, on inputs of the per-sample ``shapes`` (one tuple per input):

    - serialisation: ``serialize_keras_object`` -> ``deserialize_keras_object`` without custom objects
      (the registration) and ``from_config(get_config())`` give a layer of the same type and config;
    - shape inference: ``compute_output_shape`` is the shape of the real output, and a symbolic call keeps
      unknown sizes unknown with the channels inferred;
    - saving: a model around it (a trainable 1x1 convolution on the first input, then the layer) saved and
      loaded gives the same layer types and bit-identical outputs;
    - a training step: finite loss and gradients, the convolution before the layer moves (the gradient
      passes through the layer), the layer's own trainable weights move and its frozen ones do not."""
    import keras
    import torch

    def to_np(x):
        return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)

    def one(xs):
        return xs if len(xs) > 1 else xs[0]

    layer = make()
    for clone in (keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(layer)),
                  type(layer).from_config(layer.get_config())):
        assert type(clone) is type(layer) and clone.get_config() == layer.get_config(), type(layer).__name__

    rng = np.random.default_rng(seed)
    x = [rng.uniform(0.0, 1.0, size=(batch, *s)).astype(np.float32) for s in shapes]
    got = to_np(make()(one(x)))
    assert tuple(make().compute_output_shape(one([a.shape for a in x]))) == got.shape, type(layer).__name__
    symbolic = make()(one([keras.KerasTensor((None, None, None, s[-1])) for s in shapes]))
    assert tuple(symbolic.shape) == (None, None, None, got.shape[-1]), (type(layer).__name__, symbolic.shape)

    inputs = [keras.Input(shape=(None, None, s[-1])) for s in shapes]
    pre = keras.layers.Conv2D(shapes[0][-1], 1, name="pre")
    layer = make()
    model = keras.Model(one(inputs), layer(one([pre(inputs[0]), *inputs[1:]])))
    before = to_np(model(one(x)))
    model.save(tmp_path / "layer.keras")
    loaded = keras.models.load_model(tmp_path / "layer.keras")
    assert [type(la) for la in loaded.layers] == [type(la) for la in model.layers]
    np.testing.assert_array_equal(to_np(loaded(one(x))), before)

    weights = {id(w): to_np(w.value).copy() for w in model.weights}
    frozen = {id(w) for w in model.non_trainable_weights}
    out = model(one([torch.tensor(a) for a in x]), training=True)
    loss = ((out - torch.tensor(before + 0.5)) ** 2).mean() + sum(model.losses)
    grads = torch.autograd.grad(loss, [w.value for w in model.trainable_weights])
    assert torch.isfinite(loss) and all(torch.isfinite(g).all() for g in grads), type(layer).__name__
    model.compile(optimizer=keras.optimizers.SGD(0.1), loss="mse")
    assert np.isfinite(model.train_on_batch(one(x), before + 0.5))
    for w in model.weights:
        moved = not np.array_equal(weights[id(w)], to_np(w.value))
        assert moved == (id(w) not in frozen), (type(layer).__name__, w.path, moved)
