"""``make time-train`` (``kpcn_keras.studies.fresh_clone``): make train run in a fresh clone of the committed
HEAD, its wall time, commit and printed tables written to a report; a failing make is one line, no report."""

import json
import subprocess

import pytest

from kpcn_keras.studies.fresh_clone import tables, time_make_train
from prep.errors import KpcnError

TABLE = "| scene | relMSE |\n|---|---|\n| boxes-002 | 0.0018 |\n| **mean** | 0.0042 |\n"


def _repo(path, recipe: str):
    """A git repository whose Makefile's ``train`` runs ``recipe`` (and one file left uncommitted)."""
    path.mkdir()
    (path / "Makefile").write_text(f"train:\n\t{recipe}\n")
    git = ["git", "-C", str(path), "-c", "user.name=t", "-c", "user.email=t@example.com"]
    subprocess.run([*git, "init", "--quiet"], check=True)
    subprocess.run([*git, "add", "Makefile"], check=True)
    subprocess.run([*git, "commit", "--quiet", "-m", "one"], check=True)
    (path / "uncommitted.txt").write_text("not timed")
    return subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()


def test_tables_are_the_printed_markdown_tables_as_rows_of_cells():
    out = f"epoch 1\n{TABLE}report: x\n| a |\n|:-:|\n| 1 |\n"
    assert tables(out) == [[["scene", "relMSE"], ["boxes-002", "0.0018"], ["**mean**", "0.0042"]], [["a"], ["1"]]]
    assert tables("no table\n") == []


def test_make_train_runs_in_a_clone_of_the_committed_head_and_its_report_holds_time_commit_and_tables(tmp_path):
    # the clone holds only what was committed: the uncommitted file is not there when make runs
    recipe = "@test ! -e uncommitted.txt && sleep 0.2 && printf '" + TABLE.replace("\n", "\\n") + "'"
    commit = _repo(tmp_path / "repo", recipe)
    record = time_make_train(tmp_path / "repo", tmp_path / "out", command="make time-train")
    saved = json.loads((tmp_path / "out" / "make_train.json").read_text())
    assert saved == record
    assert saved["commit"] == commit and saved["make"] == ["make", "train"] and saved["command"] == "make time-train"
    assert 0.2 <= saved["wall_s"] < 60
    assert saved["tables"] == [[["scene", "relMSE"], ["boxes-002", "0.0018"], ["**mean**", "0.0042"]]]
    md = (tmp_path / "out" / "make_train.md").read_text()
    assert commit in md and "| boxes-002 | 0.0018 |" in md


def test_a_make_train_that_fails_is_one_line_naming_the_commit_and_writes_no_report(tmp_path):
    commit = _repo(tmp_path / "repo", "@echo the renders are missing; exit 3")
    with pytest.raises(KpcnError, match=rf"fresh clone of {commit[:12]} failed \(exit status 2\): "):
        time_make_train(tmp_path / "repo", tmp_path / "out")
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())
