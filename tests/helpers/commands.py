"""The command line as a test runs it: as a user runs it (:func:`kpcn`, in a fresh process), in this process
(:func:`run_main`), started to be killed and run again (:func:`start_kpcn`), on two processes under the
documented launcher (:func:`torchrun`); and the check of its one-line errors."""

import atexit
import contextlib
import io
import logging
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

from helpers.paths import REPO

# what the suite's environment sets (conftest.py; the kernel cache folder where one is given), which kpcn()
# passes to its bare environment
SUITE_SETTINGS = ("KPCN_KERNELS", "KPCN_KERNEL_DIR", "OMP_WAIT_POLICY")


def launcher_free_env(**extra) -> dict:
    """This process's environment without a launcher's variables (a test may run under one), and ``extra``."""
    from prep.parts import LOCAL_RANK, RANK, WORLD_SIZE

    return {**{k: v for k, v in os.environ.items() if k not in (RANK, WORLD_SIZE, LOCAL_RANK)}, **extra}


def torchrun(*args) -> list[str]:
    """The documented launch line on 2 processes of this machine, for ``kpcn <args>``."""
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
            "-m", "kpcn_keras.cli", *args]


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


def assert_one_line_error(res: subprocess.CompletedProcess, *needles: str) -> None:
    """Of a :func:`kpcn` or :func:`run_main` result: exit status 2, one line on stderr containing every needle,
    nothing on stdout, no traceback."""
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert res.stdout.strip() == "", res.stdout
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
