"""scripts/import_renders.py: another renderer's frames become a render set in kpcn's layout."""
import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from helpers.commands import assert_one_line_error

from prep import exr, layouts

SCRIPT = Path(__file__).parents[1] / "scripts" / "import_renders.py"
CYCLES = Path(__file__).parent / "fixtures" / "renderers" / "cycles5" / "studio-00016spp.exr"


def _script():
    spec = importlib.util.spec_from_file_location("import_renders", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_cycles_frame_is_written_in_kpcns_layout_with_its_layers_and_no_variance(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(CYCLES, src / "studio-00016spp.exr")
    shutil.copy(CYCLES, src / "studio-00064spp.exr")  # the scene's reference: its most samples
    written = _script().import_renders(src, tmp_path / "renders" / "cyc")
    assert [p.name for p in written] == ["studio-00016spp.exr", "studio-00064spp.exr"]
    got = exr.read_aovs(written[0], variances=None)
    want = layouts.read(CYCLES).layers
    assert set(got) == {"default", *exr.BASE_LAYERS}
    for name in got:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_a_frame_without_a_split_is_refused_in_one_line_and_nothing_is_written(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(CYCLES, src / "studio-00016spp.exr")
    shutil.copy(CYCLES.with_name("studio-00256spp.exr"), src / "studio-00256spp.exr")  # Combined alone
    res = subprocess.run([sys.executable, str(SCRIPT), str(src), "--set", "cyc", "--renders", str(tmp_path / "r")],
                         capture_output=True, text=True, cwd=Path(__file__).parents[1])
    assert_one_line_error(res, "studio-00256spp.exr", "split")
    assert not (tmp_path / "r" / "cyc").exists()
