"""The command line as a user meets it: bad input gives one clear line and exit status 2."""

import subprocess
import sys
from pathlib import Path

from conftest import random_aovs
from prep import exr

REPO = Path(__file__).resolve().parents[1]


def kpcn(*args, cwd):
    return subprocess.run([sys.executable, "-m", "kpcn_keras.cli", "-q", *args], cwd=cwd, capture_output=True,
                          text=True, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})


def test_missing_layer_is_reported_without_traceback(tmp_path):
    aovs = random_aovs(8, 8)
    del aovs["specularVariance"]
    exr.write_aovs(tmp_path / "renders" / "s" / "x-00004spp.exr", aovs)
    exr.write_aovs(tmp_path / "renders" / "s" / "x-00064spp.exr", random_aovs(8, 8, variances=False))
    res = kpcn("shards", "--set", "s", "--renders", str(tmp_path / "renders"), "--out", str(tmp_path / "sh"),
               "--patch-size", "4", cwd=tmp_path)
    assert res.returncode == 2
    assert "x-00004spp.exr" in res.stderr and "specularVariance" in res.stderr
    assert "Traceback" not in res.stderr


def test_missing_render_folder_and_bad_option_values(tmp_path):
    res = kpcn("shards", "--set", "nothing", "--renders", str(tmp_path), cwd=tmp_path)
    assert res.returncode == 2 and "no such render folder" in res.stderr and "Traceback" not in res.stderr
    res = kpcn("shards", "--set", "nothing", "--renders", str(tmp_path), "--val-fraction", "1.5", cwd=tmp_path)
    assert res.returncode == 2 and "--val-fraction" in res.stderr and "1.5" in res.stderr


def test_denoise_without_a_run_names_the_folder(tmp_path, fixture_noisy):
    res = kpcn("denoise", str(fixture_noisy), "--run", str(tmp_path / "no-run"), cwd=tmp_path)
    assert res.returncode == 2 and "no-run" in res.stderr and "not a run folder" in res.stderr
    assert "Traceback" not in res.stderr


def test_render_and_shards_do_not_import_the_deep_learning_stack():
    code = ("import sys; import kpcn_keras.cli, prep.render, prep.shards, prep.features, prep.sampling; "
            "bad = [m for m in ('keras', 'torch', 'tensorflow') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
