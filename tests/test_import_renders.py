"""kpcn import-renders (prep/imported.py): another renderer's frames become a render set in kpcn's layout."""
import json
import shutil
from pathlib import Path

import numpy as np
from helpers.commands import assert_one_line_error, run_main

from prep import exr, layouts
from prep.imported import import_renders
from prep.render.renderset import RenderSet

CYCLES = Path(__file__).parent / "fixtures" / "renderers" / "cycles5" / "studio-00016spp.exr"


def _source(tmp_path, reference: Path = CYCLES) -> Path:
    """A folder of a Cycles frame at 16 spp and ``reference`` as the scene's 64-spp frame."""
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(CYCLES, src / "studio-00016spp.exr")
    shutil.copy(reference, src / "studio-00064spp.exr")  # the scene's reference: its most samples
    return src


def test_a_cycles_frame_is_written_in_kpcns_layout_with_its_layers_and_no_variance(tmp_path):
    res = run_main("import-renders", _source(tmp_path), "--set", "cyc", "--renders", tmp_path / "renders",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    written = RenderSet("cyc", tmp_path / "renders").renders()
    assert [p.name for p in written] == ["studio-00016spp.exr", "studio-00064spp.exr"]
    assert res.stdout.splitlines()[-1] == f"2 renders in {tmp_path / 'renders' / 'cyc'}"
    got = exr.read_aovs(written[0], variances=None)
    want = layouts.read(CYCLES).layers
    assert set(got) == {"default", *exr.BASE_LAYERS}
    for name in got:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_the_library_call_writes_what_the_command_writes_and_says_what_it_read(tmp_path):
    told = []
    written = import_renders(_source(tmp_path), RenderSet("cyc", tmp_path / "renders"), on_frame=told.append)
    assert [p.parent for p in written] == [tmp_path / "renders" / "cyc"] * 2
    assert [line.split(":")[0] for line in told] == ["studio-00016spp.exr", "studio-00064spp.exr"]
    assert all(layouts.read(CYCLES).layout in line for line in told)


def test_a_frame_without_a_split_is_refused_in_one_line_and_nothing_is_written(tmp_path):
    src = _source(tmp_path, reference=CYCLES.with_name("studio-00256spp.exr"))  # Combined alone
    res = run_main("import-renders", src, "--set", "cyc", "--renders", tmp_path / "r", cwd=tmp_path)
    assert_one_line_error(res, "kpcn import-renders: error:", "studio-00064spp.exr", "split")
    assert not (tmp_path / "r" / "cyc").exists()


def test_an_existing_set_folder_and_a_set_name_that_is_no_folder_name_are_refused_in_one_line(tmp_path):
    src = _source(tmp_path)
    (tmp_path / "r" / "cyc").mkdir(parents=True)
    res = run_main("import-renders", src, "--set", "cyc", "--renders", tmp_path / "r", cwd=tmp_path)
    assert_one_line_error(res, str(tmp_path / "r" / "cyc"), "exists", "--set")
    assert list((tmp_path / "r" / "cyc").iterdir()) == []
    res = run_main("import-renders", src, "--set", "../cyc", "--renders", tmp_path / "r", cwd=tmp_path)
    assert_one_line_error(res, "--set", "plain folder name")


def test_a_missing_source_folder_is_one_line_naming_it(tmp_path):
    res = run_main("import-renders", tmp_path / "nowhere", "--set", "mine", "--renders", tmp_path / "r", cwd=tmp_path)
    assert_one_line_error(res, "import-renders", "nowhere: no such folder of renders to import")
    assert not (tmp_path / "r").exists()


def test_a_scene_that_render_cycles_has_not_finished_is_left_out_and_said_so(tmp_path):
    src = _source(tmp_path)  # studio: 16 and 64 spp, both there
    shutil.copy(CYCLES, src / "room-00016spp.exr")  # room: its 64-spp frame and reference not rendered yet
    for index, (name, frames) in enumerate((("studio", [16, 64]), ("room", [16, 64, 1024]))):
        (src / f"{name}.json").write_text(json.dumps({"seed": 0, "index": index, "name": name, "effects": [],
                                                      "frames": frames}))
    told = []
    written = import_renders(src, RenderSet("cyc", tmp_path / "renders"), on_frame=told.append)
    assert [p.name for p in written] == ["studio-00016spp.exr", "studio-00064spp.exr"]
    assert told[0] == "room: left out, its recipe lists frames not rendered yet"
    shutil.copy(CYCLES, src / "room-00064spp.exr")
    shutil.copy(CYCLES, src / "room-01024spp.exr")
    written = import_renders(src, RenderSet("cyc2", tmp_path / "renders"), on_frame=told.append)
    assert [p.name for p in written][:3] == ["room-00016spp.exr", "room-00064spp.exr", "room-01024spp.exr"]


def test_a_json_file_that_is_not_json_is_one_line_naming_the_folder(tmp_path):
    src = _source(tmp_path)
    (src / "notes.json").write_text("{not json")
    res = run_main("import-renders", src, "--set", "cyc", "--renders", tmp_path / "r", cwd=tmp_path)
    assert_one_line_error(res, str(src / "notes.json"), "not readable JSON")
    assert not (tmp_path / "r" / "cyc").exists()
