"""What several test files share: small inputs (random renders, tiny shard sets), the command line run as a
user runs it (:func:`kpcn`, in a fresh process), in this process (:func:`run_main`) or started to be killed
(:func:`start_kpcn`), and the checks of its one-line errors and of files left byte-identical. Fixtures live
in ``conftest.py``; tests import these with ``from helpers import ...``."""

import atexit
import contextlib
import hashlib
import io
import logging
import math
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck
from hypothesis import strategies as st

from prep import exr as _exr
from prep import features as _features
from prep import sampling as _sampling
from prep.features import ALBEDO_EPS, LOG_COLOUR_MAX, NUM_FEATURES, REL_EPS
from prep.sampling import IMPORTANCE_EPS

os.environ.setdefault("KERAS_BACKEND", "torch")

FIXTURES = Path(__file__).parent / "fixtures"
REPO = Path(__file__).resolve().parents[1]
# what the suite's environment sets (conftest.py; the kernel cache folder where one is given), which kpcn()
# passes to its bare environment
SUITE_SETTINGS = ("KPCN_KERNELS", "KPCN_KERNEL_DIR", "OMP_WAIT_POLICY")
TINY_MODEL = {"width": 6, "depth": 3, "kernel_size": 5}
# the smallest network the training tests train: a step takes milliseconds
TINY_TRAIN_MODEL = {"width": 4, "depth": 2, "kernel_size": 3}
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


def make_renders(root: Path, scenes=("a-000", "a-001", "b-000", "b-001"), size=(40, 44),
                 reference_variances: bool = False) -> Path:
    """A folder of random noisy (4 spp) and reference (64 spp) renders in the AOV layout; the references
    without variance layers unless ``reference_variances``."""
    from prep import exr

    for i, scene in enumerate(scenes):
        exr.write_aovs(root / exr.render_filename(scene, 4), random_aovs(*size, seed=10 + i))
        exr.write_aovs(root / exr.render_filename(scene, 64),
                       random_aovs(*size, seed=100 + i, variances=reference_variances))
    return root


def reference_relse(colour, variance) -> np.ndarray:
    """float64 relSE of prep.convergence, written out again: sqrt(max(v, 0)) / (max(mean_RGB c, 0) + 0.01)."""
    colour, variance = np.asarray(colour, np.float64), np.asarray(variance, np.float64)
    return np.sqrt(np.maximum(variance, 0.0)) / (np.maximum(colour.mean(axis=-1), 0.0) + 0.01)


def build_tiny_shards(tmp_path: Path, **kw):
    """Random renders cut into a small shard set; returns its ShardConfig."""
    from prep import shards

    make_renders(tmp_path / "renders" / "s", reference_variances=kw.pop("reference_variances", False))
    values = dict(set_name="s", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                  patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5, seed=3)
    values.update(kw)
    cfg = shards.ShardConfig(**values)
    shards.build_shards(cfg, progress=False)
    return cfg


def tiny_train_config(shard_cfg, **kw):
    """A ``TrainConfig`` of :data:`TINY_TRAIN_MODEL` for the shard set ``shard_cfg`` (:func:`build_tiny_shards`):
    4 steps a branch in epochs of 2, batch 2; ``kw`` overrides."""
    from kpcn_keras.config import TrainConfig

    values = dict(set_name=shard_cfg.set_name, shards_root=shard_cfg.out_root, model=TINY_TRAIN_MODEL, steps=4,
                  steps_per_epoch=2, batch_size=2, val_batches=1)
    values.update(kw)
    return TrainConfig.from_preset("cpu", **values)


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

    # the suite's settings (conftest.py) rather than the machine's defaults: none changes a byte of output
    kept = {k: os.environ[k] for k in SUITE_SETTINGS if k in os.environ}
    # no bytecode cache written: under a file size limit, importlib writes a module's .pyc cut at the limit
    # (it does not check for a short write) and renames it into place, and every later import of that module,
    # in any process, fails with "marshal data too short"
    return subprocess.run([sys.executable, "-m", "kpcn_keras.cli", "-q", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout,
                          preexec_fn=limit if file_size_limit is not None else None,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "KERAS_BACKEND": "torch",
                               "PYTHONDONTWRITEBYTECODE": "1", **kept})


# the commands that never import the deep-learning stack (cli.py), which the others take ~5 s to import here
STACKLESS_COMMANDS = ("render", "shards")


def command_env() -> dict:
    """The environment of a command a test starts to kill: this process's, with the repository importable."""
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)
    return dict(os.environ, PYTHONPATH=path, KERAS_BACKEND="torch", PYTHONUNBUFFERED="1")


def start_kpcn(args, cwd) -> "subprocess.Popen | WarmProcess":
    """``kpcn -q ARGS`` started in ``cwd`` in a process of its own (:func:`command_env`), stdout and stderr
    together, for the tests that kill a command and run it again: ``render`` and ``shards`` (which never import
    the stack) in a fresh interpreter, the others in a :class:`WarmProcess`."""
    args = [str(a) for a in args]
    if args[0] in STACKLESS_COMMANDS:
        return subprocess.Popen([sys.executable, "-m", "kpcn_keras.cli", "-q", *args], cwd=cwd, env=command_env(),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return WarmProcess(_kpcn_main, (args,), cwd=cwd, env=command_env(), name=f"kpcn {args[0]}")


def _kpcn_main(args) -> int:
    """What ``python -m kpcn_keras.cli -q ARGS`` runs, ``sys.argv`` included (records keep it)."""
    from kpcn_keras import cli

    sys.argv[:] = [cli.__file__, "-q", *args]
    return cli.main()


_warm: multiprocessing.context.BaseContext | None = None


class WarmProcess:
    """``target(*args, **kwargs)`` in a process of its own, forked from an interpreter that has already imported
    Keras and torch (multiprocessing's forkserver, started once per test process with the two preloaded), in
    ``cwd`` with the environment ``env``, its stdout and stderr written to one file: a process like any other
    (its own pid, killed by a signal), without the seconds a fresh interpreter spends importing the stack. kpcn
    itself is imported in the child, as in a fresh process. The Popen methods the kill tests use."""

    def __init__(self, target, args=(), kwargs=None, *, cwd, env, name="warm"):
        global _warm
        if _warm is None:
            _warm = multiprocessing.get_context("forkserver")
            _warm.set_forkserver_preload(["keras", "torch"])
        fd, self._out = tempfile.mkstemp(prefix="kpcn-warm-", suffix=".out")
        os.close(fd)
        self.args = name
        self._proc = _warm.Process(target=_warm_child, args=(target, args, kwargs or {}, str(cwd), env, self._out),
                                   name=name)
        self._proc.start()
        self.pid = self._proc.pid

    @property
    def returncode(self) -> int | None:
        return self._proc.exitcode

    def poll(self) -> int | None:
        return self._proc.exitcode

    def send_signal(self, sig) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def communicate(self, timeout=None) -> tuple[str, None]:
        """(stdout and stderr, None) once the process has ended; its output file is then removed, so call it
        (rather than a ``wait``, which this class does not have) once the process is started."""
        self._proc.join(timeout)
        if self._proc.exitcode is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        out = Path(self._out).read_text()
        Path(self._out).unlink(missing_ok=True)
        return out, None


def _warm_child(target, args, kwargs, cwd, env, out) -> None:
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    fd = os.open(out, os.O_WRONLY | os.O_TRUNC)
    os.dup2(fd, 1), os.dup2(fd, 2)
    os.close(fd)
    sys.stdout = sys.stderr = open(1, "w", buffering=1, closefd=False)
    try:
        status = target(*args, **kwargs)
    finally:
        atexit._run_exitfuncs()  # what an interpreter runs at its exit, which a forked child's os._exit skips
        sys.stdout.flush()
    sys.exit(status if isinstance(status, int) else 0)


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
    """Of a :func:`kpcn` or :func:`run_main` result: exit status 2, one line on stderr containing every needle,
    nothing on stdout, no traceback."""
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


# ---------------------------------------------------------------- the float64 references of the numerics
# the ranges of the feature table, float64 evaluations of the features, PDFs and kernels, and the hypothesis
# strategies of float32 renders, which the hard cases (test_numerics) and the module tests hold the code to

F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).smallest_subnormal)
F32_EPS = float(np.finfo(np.float32).eps)
HALF_MAX = float(np.finfo(np.float16).max)
# The largest relative variance a float32 render can give: a depth variance of float32 max at a miss
# (d = 0) in an image whose largest depth is the smallest subnormal (depth scale 1 / F32_TINY).
RELVAR_BOUND = float(np.log1p(F32_MAX / F32_TINY**2 / REL_EPS))
# (first channel, stop, lowest, highest): the table of prep/features.py, each bound derived from the
# module's constants or from the clip range its formula names.
FEATURE_RANGES = [
    (0, 3, 0.0, LOG_COLOUR_MAX),  # colour
    (3, 6, -LOG_COLOUR_MAX, LOG_COLOUR_MAX),  # dx colour
    (6, 9, -2.0, 2.0),  # dx normal: normal clipped to [-1, 1]
    (9, 12, -1.0, 1.0),  # dx albedo: albedo clipped to [0, 1]
    (12, 13, -1.0, 1.0),  # dx depth: depth scaled to [0, 1]
    (13, 16, -LOG_COLOUR_MAX, LOG_COLOUR_MAX),  # dy of the same
    (16, 19, -2.0, 2.0),
    (19, 22, -1.0, 1.0),
    (22, 23, -1.0, 1.0),
    (23, 27, 0.0, RELVAR_BOUND),  # relative variances
]


def reference_log_colour(colour, albedo=None) -> np.ndarray:
    """log(1 + max(x, 0)), x = colour / (clip(albedo, 0, 1) + ALBEDO_EPS) for the diffuse branch, in float64."""
    x = np.asarray(colour, np.float64)
    if albedo is not None:
        x = x / (np.clip(np.asarray(albedo, np.float64), 0.0, 1.0) + ALBEDO_EPS)
    return np.log1p(np.maximum(x, 0.0))


def reference_importance(aovs: dict) -> np.ndarray:
    mean = np.maximum(aovs["default"].astype(np.float64), 0.0).sum(axis=-1) / 3.0
    colour = np.maximum(aovs["colorVariance"].astype(np.float64), 0.0) / (mean**2 + IMPORTANCE_EPS)
    return colour + np.maximum(aovs["normalVariance"].astype(np.float64), 0.0)


def reference_pdf(importance, p: int, mix: float) -> np.ndarray:
    """Explicit window sums (exactly rounded, math.fsum) of the finite, non-negative importance, normalised,
    mixed with the uniform PDF; uniform when nothing is left."""
    imp = np.asarray(importance, np.float64)
    imp = np.where(np.isfinite(imp), np.maximum(imp, 0.0), 0.0)
    if imp.max() > 0:
        imp = np.ldexp(imp, -np.frexp(imp.max())[1])  # an exact power-of-two scale, so that fsum cannot overflow
    h, w = imp.shape
    sums = np.array([[math.fsum(imp[y : y + p, x : x + p].ravel()) for x in range(w - p + 1)]
                     for y in range(h - p + 1)])
    total = math.fsum(sums.ravel())
    uniform = np.full(sums.shape, 1.0 / sums.size)
    if total <= 0:
        return uniform
    return mix * uniform + (1.0 - mix) * (sums / total)


def reference_kernel_apply(colour, logits, k: int):
    """float64: softmax with max subtraction, edge-replicated k x k windows, weighted sum. Returns the output
    (B, H, W, C) and the windows (B, H, W, k*k, C)."""
    c = np.asarray(colour, np.float64)
    z = np.asarray(logits, np.float64)
    z = z - z.max(axis=-1, keepdims=True)
    weights = np.exp(z)
    weights /= weights.sum(axis=-1, keepdims=True)
    r = k // 2
    h, w = c.shape[1:3]
    padded = np.pad(c, ((0, 0), (r, r), (r, r), (0, 0)), mode="edge")
    windows = np.stack([padded[:, i : i + h, j : j + w] for i in range(k) for j in range(k)], axis=3)
    return np.einsum("bhwt,bhwtc->bhwc", weights, windows), windows


def assert_features_in_documented_ranges(feats: np.ndarray) -> None:
    assert feats.shape[-1] == NUM_FEATURES
    assert np.isfinite(feats).all()
    f = feats.astype(np.float64)
    for first, stop, lo, hi in FEATURE_RANGES:
        block = f[..., first:stop]
        assert block.min() >= lo and block.max() <= hi, (
            f"channels {_features.FEATURE_NAMES[first:stop]}: [{block.min()}, {block.max()}] outside [{lo}, {hi}]")


def assert_features_match_reference(aovs: dict) -> None:
    for branch in _features.BRANCHES:
        got = _features.branch_features(aovs, branch)
        assert got.dtype == np.float32
        assert_features_in_documented_ranges(got)
        np.testing.assert_allclose(got, reference_features(aovs, branch), rtol=1e-6, atol=1e-6, err_msg=branch)


def assert_read_features_close(got: np.ndarray, want: np.ndarray, err_msg: str = "") -> None:
    """Features read back from a shard (recomputed from its float16 buffers) against the same pixels'
    features at full precision, within the format's bound (docs/formats.md §4) taken over the patch: a value
    within 2**-11 of itself, a difference within 2**-11 of the two values it is made of, which are at most
    1 (normal, albedo, depth) or the patch's largest colour and colour difference together. The exact
    per-channel bound is held in test_compact_shards.py."""
    colour = float(np.abs(want[..., 0:3]).max() + np.abs(want[..., 3:6]).max() + np.abs(want[..., 13:16]).max())
    np.testing.assert_allclose(got, want, rtol=2.0**-11 + 2.0**-22, atol=2.0**-10 * max(colour, 1.0) + 2.0**-24,
                               err_msg=err_msg)


def assert_pdf_is_a_distribution(pdf: np.ndarray, want: np.ndarray) -> None:
    assert pdf.shape == want.shape and pdf.dtype == np.float64
    assert np.isfinite(pdf).all() and pdf.min() >= 0.0
    assert abs(math.fsum(pdf.ravel()) - 1.0) <= 1e-12
    # direct sums of non-negative terms: relative accuracy, even beside a pixel 1e20 times brighter
    np.testing.assert_allclose(pdf, want, rtol=1e-12, atol=1e-300)


def assert_variance_pdf_matches(aovs: dict, patch: int, mix: float = 0.1) -> np.ndarray:
    importance = _sampling.variance_importance(aovs)
    np.testing.assert_allclose(importance, reference_importance(aovs), rtol=1e-12, atol=0)
    pdf = _sampling.patch_pdf(importance, patch, mix)
    assert_pdf_is_a_distribution(pdf, reference_pdf(importance, patch, mix))
    return pdf


def finite_loss_and_gradients(model, x, gt, noisy):
    """SMAPE and asymmetric SMAPE of ``model`` (a keras.Model) in training mode, with their gradients;
    asserts all finite. Returns the output (a torch tensor)."""
    import torch

    from kpcn_keras.losses import SMAPE, AsymmetricSMAPE

    out = model(torch.as_tensor(x), training=True)
    gt_t = torch.as_tensor(gt)
    losses = {
        "smape": SMAPE()(gt_t, out),
        "asymmetric": AsymmetricSMAPE(2.0)(torch.as_tensor(np.concatenate([gt, noisy], axis=-1)), out),
    }
    variables = [w.value for w in model.trainable_weights]
    for name, loss in losses.items():
        assert torch.isfinite(loss), (name, loss)
        grads = torch.autograd.grad(loss, variables, retain_graph=True, allow_unused=True)
        for w, g in zip(model.trainable_weights, grads):
            assert g is None or torch.isfinite(g).all(), f"{name}: non-finite gradient of {w.path}"
    return out


def extreme_features(shape, seed: int) -> np.ndarray:
    """Features with every channel at the low end, the high end of its documented range, or 0."""
    rng = np.random.default_rng(seed)
    x = np.empty(tuple(shape) + (NUM_FEATURES,), np.float32)
    for first, stop, lo, hi in FEATURE_RANGES:
        x[..., first:stop] = rng.choice([lo, hi, 0.0], size=tuple(shape) + (stop - first,))
    return x


PROPERTY = dict(deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


SPECIAL_F32 = [0.0, F32_TINY, float(np.float32(1e-30)), 1.0, HALF_MAX, float(np.float32(1e20)), F32_MAX]


@st.composite
def float32_images(draw, shape, signed=True):
    """An image whose magnitudes are log-uniform over a drawn range of decades (subnormal to float32 max),
    with a few special values (0, the smallest subnormal, half max, float32 max) at drawn pixels."""
    size = int(np.prod(shape))
    kind = draw(st.sampled_from(["spread", "spread", "spread", "constant", "zero"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "zero":
        return np.zeros(shape, np.float32)
    lo = draw(st.integers(-46, 38))
    hi = draw(st.integers(lo, 39))
    magnitude = np.minimum(10.0 ** rng.uniform(lo, hi, shape if kind == "spread" else ()), F32_MAX)
    image = np.broadcast_to(magnitude, shape).copy()
    if signed and draw(st.booleans()):
        image *= rng.choice([-1.0, 1.0], shape)
    specials = draw(st.lists(st.tuples(st.integers(0, size - 1), st.sampled_from(SPECIAL_F32), st.booleans()),
                             max_size=4))
    flat = image.reshape(-1)
    for index, value, negative in specials:
        flat[index] = -value if (negative and signed) else value
    return image.astype(np.float32)


@st.composite
def renders(draw, max_side=12):
    h = draw(st.integers(1, max_side))
    w = draw(st.integers(1, max_side))
    aovs = {name: draw(float32_images((h, w, 3))) for name in _exr.RGB_LAYERS}
    aovs.update({name: draw(float32_images((h, w))) for name in _exr.SCALAR_LAYERS})
    return aovs


def write_channels(path: Path, channels: dict, parts: dict[str, list[str]] | None = None, header=None) -> Path:
    """An EXR of ``channels`` (full name -> (H, W) array) as a renderer writes it: one part, or with ``parts``
    (part name -> its channel names) one part each; ``header``: attributes. For layouts kpcn does not write."""
    import OpenEXR

    # the binding writes each part's name into the header it is given: each part gets its own copy
    head = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    pix = {k: np.ascontiguousarray(v) for k, v in channels.items()}
    if parts is None:
        with OpenEXR.File(head, pix) as f:
            f.write(str(path))
    else:
        with OpenEXR.File([OpenEXR.Part(dict(head), {c: pix[c] for c in names}, name)
                           for name, names in parts.items()]) as f:
            f.write(str(path))
    return path


CYCLES5_RGB = ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color", "Glossy Direct", "Glossy Indirect",
               "Glossy Color", "Transmission Direct", "Transmission Indirect", "Transmission Color", "Emission",
               "Environment", "Volume Direct", "Volume Indirect", "Denoising Albedo")


def cycles_channels(h: int, w: int, seed: int = 0, view: str = "ViewLayer") -> dict:
    """Random Cycles 5 passes (long names) whose Combined is Cycles' own composition of them, in float64."""
    rng = np.random.default_rng(seed)
    passes = {name: rng.uniform(0, 1, (h, w, 3)) for name in CYCLES5_RGB}
    combined = (passes["Diffuse Direct"] + passes["Diffuse Indirect"]) * passes["Diffuse Color"]
    for lobe in ("Glossy", "Transmission"):
        combined += (passes[f"{lobe} Direct"] + passes[f"{lobe} Indirect"]) * passes[f"{lobe} Color"]
    combined += passes["Emission"] + passes["Environment"] + passes["Volume Direct"] + passes["Volume Indirect"]
    channels = {f"{view}.{name}.{c}": passes[name][..., i].astype(np.float32)
                for name in CYCLES5_RGB for i, c in enumerate("RGB")}
    channels.update({f"{view}.Combined.{c}": combined[..., i].astype(np.float32) for i, c in enumerate("RGB")})
    channels[f"{view}.Combined.A"] = np.ones((h, w), np.float32)
    normal = rng.uniform(-1, 1, (h, w, 3))
    channels.update({f"{view}.Normal.{c}": normal[..., i].astype(np.float32) for i, c in enumerate("XYZ")})
    channels.update({f"{view}.Denoising Normal.{c}": normal[..., i].astype(np.float32) for i, c in enumerate("XYZ")})
    depth = rng.uniform(1, 5, (h, w))
    depth[0, 0] = 0.0  # a miss
    channels[f"{view}.Denoising Depth.Z"] = depth.astype(np.float32)
    channels[f"{view}.Depth.Z"] = np.where(depth > 0, depth, 1e10).astype(np.float32)
    return channels


def parts_of(channels: dict) -> dict[str, list[str]]:
    """Blender 5's split of channels into parts: one part per pass, named ``<view layer>.<pass>``."""
    parts: dict[str, list[str]] = {}
    for name in channels:
        parts.setdefault(name.rpartition(".")[0], []).append(name)
    return parts


# Debian's Chromium and its driver (.ci/run installs them); the flags keep it from reaching for Google's hosts,
# which a closed network refuses many times a start
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--hide-scrollbars", "--force-device-scale-factor=1")
REQUIRE_BROWSER = "KPCN_REQUIRE_BROWSER"  # set (CI sets it): a missing browser fails the browser tests


@contextlib.contextmanager
def headless_chromium(profile: Path, size=(1280, 800)):
    """A Selenium driver of headless Chromium with an empty profile in ``profile``, the window ``size``; the
    test is skipped where Chromium or Selenium is missing, unless :data:`REQUIRE_BROWSER` is set."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        selenium = None
    else:
        selenium = webdriver
    missing = [what for what, here in (("selenium", selenium is not None), (str(CHROMIUM), CHROMIUM.exists()),
                                        (str(CHROMEDRIVER), CHROMEDRIVER.exists())) if not here]
    if missing:
        message = f"no browser to test the page in: {', '.join(missing)} missing (apt-get install chromium " \
                  "chromium-driver; pip install '.[test]')"
        if os.environ.get(REQUIRE_BROWSER):
            pytest.fail(message)
        pytest.skip(message)
    os.environ.setdefault("SE_OFFLINE", "true")  # Selenium Manager must not look for drivers on the network
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in (*CHROMIUM_FLAGS, f"--window-size={size[0]},{size[1]}", f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    try:
        yield driver
    finally:
        driver.quit()


# driving kpcn view's page (kpcn_keras/view/view.js): its test and scripts/view_screenshot.py


def page_wait(driver, condition: str, timeout: float = 60) -> None:
    """Wait until the page's JavaScript ``condition`` holds."""
    from selenium.webdriver.support.ui import WebDriverWait

    WebDriverWait(driver, timeout).until(lambda d: d.execute_script(f"return Boolean({condition})"))


def page_input(driver, element_id: str, value) -> None:
    """Set a control of the page (a slider or a menu) as a user does: its value, then its input or change event."""
    driver.execute_script("const e = document.getElementById(arguments[0]); e.value = arguments[1]; "
                          "e.dispatchEvent(new Event(e.tagName === 'SELECT' ? 'change' : 'input'));",
                          element_id, str(value))


def page_point(driver, x: float, y: float) -> tuple[int, int]:
    """The viewport position (CSS pixels, rounded; the device scale is 1) of image point (x, y)."""
    return tuple(round(v) for v in driver.execute_script(
        "const s = kpcn.state, r = document.getElementById('canvas').getBoundingClientRect();"
        "return [r.left + s.ox + arguments[0] * s.zoom, r.top + s.oy + arguments[1] * s.zoom];", x, y))


def page_stroke(driver, points) -> None:
    """One stroke of the mouse through the image points ``points`` (x, y): down at the first, up at the last."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.action_builder import ActionBuilder
    from selenium.webdriver.common.actions.mouse_button import MouseButton

    builder = ActionBuilder(driver)
    builder.pointer_action.move_to_location(*page_point(driver, *points[0]))
    builder.pointer_action.pointer_down(MouseButton.LEFT)
    for point in points[1:]:
        builder.pointer_action.move_to_location(*page_point(driver, *point))
    builder.pointer_action.pointer_up(MouseButton.LEFT)
    builder.perform()
    ActionChains(driver).reset_actions()


def moved(image: np.ndarray, spatial: int, inverse: bool = False) -> np.ndarray:
    """``image`` (H, W, ...) transposed (bit 0 of ``spatial``), mirrored left-right (bit 1) and upside down
    (bit 2), in that order, or with ``inverse`` those undone: plain numpy, the reference for
    ``kpcn_keras.augment``'s moves."""
    steps = [(1, lambda x: np.swapaxes(x, 0, 1)), (2, lambda x: x[:, ::-1]), (4, lambda x: x[::-1])]
    for bit, step in reversed(steps) if inverse else steps:
        image = step(image) if spatial & bit else image
    return np.ascontiguousarray(image)
