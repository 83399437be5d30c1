"""``make time-train``: ``make train`` timed from a fresh clone, the figure the README gives for its time.

The repository's committed HEAD is cloned (``git clone`` of the checkout: what is not committed is not timed)
into a temporary folder, and ``make train`` runs there with nothing reused: its own ``.venv``, renders, shards,
run and numba cache (numba caches beside the sources), only pip's download cache being the user's, as on any
fresh clone. Its output streams to the terminal as it comes, and the report is ``reports/make_train.json``
(through :mod:`kpcn_keras.studies.report`: the date, the command, when it started and finished, the machine, then the
commit timed, the wall seconds ``make train`` took in the clone, and every table
``make train`` printed, as rows of cells, header first) and ``make_train.md`` (the time and the last table,
the held-out table of ``kpcn evaluate``). The clone is removed afterwards. A ``make train`` that fails is a
KpcnError naming the commit and its last line of output, and no report is written.

    python -m kpcn_keras.studies.fresh_clone [--repo DIR] [--out reports] [MAKE_ARGS ...]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from kpcn_keras.studies.report import Report
from prep.errors import KpcnError

STEM = "make_train"
ROOT = Path(__file__).resolve().parents[2]


def tables(output: str) -> list[list[list[str]]]:
    """The markdown tables in ``output``, each as rows of cells (header first, the ``|---|`` line left out)."""
    found, current = [], None
    for line in output.splitlines():
        line = line.strip()
        if line.startswith("|") and line.endswith("|"):
            if current is None:
                current = []
                found.append(current)
            cells = [cell.strip() for cell in line[1:-1].split("|")]
            if not all(set(cell) <= set("-:") and cell for cell in cells):
                current.append(cells)
        else:
            current = None
    return found


def _stream(command: list[str], cwd: Path) -> tuple[int, str]:
    """Run ``command`` in ``cwd``, its output (stdout and stderr) echoed as it comes; (exit status, output)."""
    lines = []
    with subprocess.Popen(command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          bufsize=1) as process:
        for line in process.stdout:
            sys.stdout.write(line)
            lines.append(line)
    return process.returncode, "".join(lines)


def _git(repo: Path, *args: str) -> str:
    result = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    if result.returncode:
        raise KpcnError(f"{repo}: git {' '.join(args)} failed: {result.stderr.strip() or result.returncode}")
    return result.stdout.strip()


def markdown(record: dict) -> str:
    """The md of a record: what was timed, the time, and the last table ``make train`` printed."""
    minutes, seconds = divmod(round(record["wall_s"]), 60)
    lines = [f"# `{' '.join(record['make'])}` from a fresh clone", "",
             f"{record['date']}, commit {record['commit']}, {record['machine']['cpus']} CPUs "
             f"({record['machine']['platform']}): **{minutes} min {seconds} s** in all "
             f"({record['started']} to {record['finished']}; `{record['command']}`).", ""]
    if record["tables"]:
        lines += ["What it printed last:", ""]
        header, *rows = record["tables"][-1]
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def time_make_train(repo: str | Path = ROOT, out_dir: str | Path = ROOT / "reports", make_args=(),
                    command: str | None = None) -> dict:
    """Clone ``repo``'s HEAD into a temporary folder, run ``make train`` (with ``make_args``) there and write
    the report (the module docstring); returns its record."""
    report = Report(Path(out_dir), STEM, png=False)
    report.check_writable((".md", ".json"))
    repo = Path(repo).resolve()
    commit = _git(repo, "rev-parse", "HEAD")
    make = ["make", "train", *make_args]
    session = report.begin()
    with tempfile.TemporaryDirectory(prefix="kpcn-fresh-clone-") as tmp:
        clone = Path(tmp) / repo.name
        _git(repo, "clone", "--quiet", "--no-hardlinks", str(repo), str(clone))
        start = time.perf_counter()
        status, output = _stream(make, clone)
        wall = time.perf_counter() - start
    if status:
        last = output.strip().splitlines()[-1:] or ["no output"]
        raise KpcnError(f"{' '.join(make)} in a fresh clone of {commit[:12]} failed (exit status {status}): "
                        f"{last[0]}")
    record = {**session.envelope(command or " ".join(["python -m kpcn_keras.studies.fresh_clone", *make_args])),
              "machine": session.machine(), "commit": commit, "make": make, "wall_s": round(wall, 1),
              "tables": tables(output)}
    return report.write(record, markdown(record))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.fresh_clone",
                                     description="make train timed from a fresh clone of the committed HEAD")
    parser.add_argument("--repo", type=Path, default=ROOT, help="the checkout to clone (default: this one)")
    parser.add_argument("--out", type=Path, default=ROOT / "reports", help="the report's folder (default: reports)")
    parser.add_argument("make_args", nargs="*", help="passed to make, e.g. TRAIN_ARGS='--steps 100'")
    args = parser.parse_args(argv)
    try:
        record = time_make_train(args.repo, args.out, args.make_args)
    except KpcnError as exc:
        print(f"kpcn_keras.studies.fresh_clone: error: {exc}", file=sys.stderr)
        return 2
    print(f"make train: {record['wall_s']:.1f} s from a fresh clone of {record['commit'][:12]}; "
          f"report: {Path(args.out) / STEM}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
