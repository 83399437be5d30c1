"""The kpcn executable seen from Blender, without bpy: where it is, the command that denoises a file (or a
frame's two halves, adapting to them), and a running denoise that Blender polls, cancels and reads one error
line from.

The add-on adds no package to Blender's Python: kpcn runs in its own environment, as a subprocess."""

import os
import shutil
import subprocess
import tempfile
import time

VERSION_TIMEOUT = 120  # seconds: kpcn --version imports the library to read the model's modes


class AddonError(Exception):
    """One line for Blender's report bar (never a traceback)."""


def find_kpcn(path: str) -> str:
    """The kpcn executable the preference names (``~`` expanded; empty: ``kpcn`` on PATH), absolute.
    AddonError naming the path where there is no executable file there."""
    given = os.path.expanduser(path.strip()) if path and path.strip() else ""
    found = shutil.which(given or "kpcn")
    if found is None or not os.path.isfile(found):
        where = given or "kpcn on PATH"
        raise AddonError(f"kpcn executable not found: {where} (set it in the kpcn add-on's preferences)")
    return os.path.abspath(found)


def denoise_command(kpcn: str, src: str, out: str, quality: str = "", ensemble: int = 1, pair: str = "",
                    adapt_seconds: float = 0.0, adapt_steps: int = 0) -> list[str]:
    """``kpcn denoise SRC -o OUT`` with the preferences' quality mode (empty: the model's default) and
    ensemble (1: the networks once, kpcn's default). With ``pair`` (a second render of SRC's frame with another
    seed, each at half the samples): ``--pair PAIR``, adapting for ``--adapt-steps`` where ``adapt_steps`` > 0
    (the same result on any machine), else ``--adapt`` seconds where ``adapt_seconds`` > 0, else not at all (the
    two halves' mean denoised)."""
    cmd = [kpcn, "denoise", src, "-o", out]
    if quality:
        cmd += ["--quality", quality]
    if ensemble > 1:
        cmd += ["--ensemble", str(ensemble)]
    if pair:
        cmd += ["--pair", pair]
        if adapt_steps > 0:
            cmd += ["--adapt-steps", str(adapt_steps)]
        elif adapt_seconds > 0:
            cmd += ["--adapt", f"{adapt_seconds:g}"]
    return cmd


def last_error(log: str, returncode: int, program: str = "kpcn") -> str:
    """The line of kpcn's output that says why it failed: its ``kpcn <command>: error: ...`` line, else the last
    line it printed, else its exit status."""
    lines = [line.strip() for line in log.replace("\r", "\n").splitlines() if line.strip()]
    errors = [line for line in lines if ": error: " in line]
    if errors:
        return errors[-1]
    return lines[-1] if lines else f"{program} exited with status {returncode}"


def adaptation_line(log: str) -> str:
    """kpcn's line saying what its adaptation's guard decided (``adaptation kept: ...`` or ``adaptation not kept:
    ...``, kpcn_keras.adapt.Outcome.line), empty where it printed none (no pair, no adaptation)."""
    lines = [line.strip() for line in log.replace("\r", "\n").splitlines()]
    found = [line for line in lines if line.startswith(("adaptation kept: ", "adaptation not kept: "))]
    return found[-1] if found else ""


def version(kpcn: str) -> str:
    """What ``kpcn --version`` prints (its version and the model it serves), one line a fact. AddonError in one
    line where it cannot run or fails."""
    try:
        res = subprocess.run([kpcn, "--version"], capture_output=True, text=True, timeout=VERSION_TIMEOUT)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise AddonError(f"{kpcn} --version: {exc}") from None
    if res.returncode != 0:
        raise AddonError(f"{kpcn} --version: {last_error(res.stderr + res.stdout, res.returncode)}")
    return res.stdout.strip()


class Job:
    """One ``kpcn denoise`` subprocess: its output goes to a log file (a pipe nobody reads would fill and
    stall it), polled without blocking, cancelled by terminating it."""

    def __init__(self, cmd: list[str], out: str, label: str):
        self.cmd, self.out, self.label = cmd, out, label
        self.adaptation = ""  # once it has ended: kpcn's adaptation_line
        self.log = tempfile.NamedTemporaryFile("w+", prefix="kpcn-", suffix=".log", delete=False)
        self.started = time.monotonic()
        try:
            self.proc = subprocess.Popen(cmd, stdout=self.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        except OSError as exc:
            self._close()
            raise AddonError(f"{cmd[0]}: {exc.strerror or exc}") from None

    def _close(self) -> None:
        self.log.close()
        try:
            os.remove(self.log.name)
        except OSError:
            pass

    def _text(self) -> str:
        with open(self.log.name, errors="replace") as f:
            return f.read()

    def status(self) -> str:
        """What the status bar shows while it runs: seconds so far and kpcn's last line (its progress)."""
        text = self._text().replace("\r", "\n").strip().splitlines()
        last = f": {text[-1].strip()}" if text else ""
        return f"kpcn: denoising {self.label}, {time.monotonic() - self.started:.0f} s{last} (Esc cancels)"

    def poll(self) -> bool:
        """True once the process has ended."""
        return self.proc.poll() is not None

    def wait(self) -> None:
        self.proc.wait()

    def result(self) -> str:
        """The denoised file; AddonError with kpcn's error line where it failed."""
        code = self.proc.wait()
        text = self._text()
        self._close()
        self.adaptation = adaptation_line(text)
        if code != 0:
            raise AddonError(last_error(text, code))
        if not os.path.isfile(self.out):
            raise AddonError(f"kpcn wrote no {self.out}")
        return self.out

    def cancel(self) -> None:
        """Terminate kpcn (kill it if it does not stop within 5 s) and forget its output."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._close()
