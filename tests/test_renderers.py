"""``kpcn denoise``, ``kpcn evaluate`` and ``kpcn.denoise`` on what renderers write (``tests/fixtures/renderers``:
the renderers' own files): each file is found without a flag and denoised by the model trained for what it
has; the output keeps the input's alpha and header attributes; the API's output is the command's."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.exr_layouts import cycles_channels, parts_of, write_channels

import kpcn
from prep import exr, layouts
from prep.exr import VARIANCE_LAYERS

pytestmark = pytest.mark.slow

RENDERERS = Path(__file__).parent / "fixtures" / "renderers"
# each renderer's file: (its layout, the input set it gives, the run's folder that serves it)
FILES = {
    "cycles5/studio-00016spp.exr": ("cycles", "no-variance", "inputs/no-variance"),
    "cycles45/studio-00016spp.exr": ("cycles", "no-variance", "inputs/no-variance"),
    "cycles5-interleaved/studio-00016spp.exr": ("cycles", "no-variance", "inputs/no-variance"),
    "mitsuba3/cornell-00016spp.exr": ("mitsuba", "no-split", "inputs/no-split"),
    "pbrt4/cornell-00016spp.exr": ("pbrt", "no-split", "inputs/no-split"),
    "cycles5/studio-00256spp.exr": ("rgb", "no-split-no-variance", "inputs/no-split-no-variance"),
}


@pytest.mark.parametrize("name", FILES)
def test_kpcn_denoise_takes_each_renderers_file_without_a_flag(tiny_run_of_every_input_set, tmp_path, name):
    run = tiny_run_of_every_input_set
    layout, inputs, served_by = FILES[name]
    out = tmp_path / "out.exr"
    res = run_main("denoise", RENDERERS / name, "--run", run, "-o", out, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"({layout} layout, {inputs}, model {run / served_by};" in res.stdout, res.stdout
    back = exr.read_image(out)
    colour = np.stack([back.channels[f"default.{c}"] for c in "RGB"], axis=-1)
    source = layouts.read(RENDERERS / name)
    assert colour.shape == source.layers["default"].shape and np.isfinite(colour).all()
    assert ("diffuse.R" in back.channels) == source.inputs.split


def test_a_denoise_keeps_the_inputs_alpha_header_attributes_and_windows(tiny_run_of_every_input_set, tmp_path):
    src = RENDERERS / "cycles5" / "studio-00016spp.exr"
    res = run_main("denoise", src, "--run", tiny_run_of_every_input_set, "-o", tmp_path / "o.exr",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    given, got = exr.read_image(src), exr.read_image(tmp_path / "o.exr")
    np.testing.assert_array_equal(got.channels["default.A"], given.channels["ViewLayer.Combined.A"])
    for key in ("Software", "cycles.ViewLayer.samples", "Camera", "colorInteropID", "RenderTime"):
        assert got.attributes[key] == given.attributes[key], key
    assert (got.data_window, got.display_window) == (given.data_window, given.display_window)


@pytest.mark.parametrize("name", ["cycles5/studio-00016spp.exr", "mitsuba3/cornell-00016spp.exr"])
def test_the_apis_output_equals_the_commands_on_the_same_frame(tiny_run_of_every_input_set, tmp_path, name):
    run = tiny_run_of_every_input_set
    res = run_main("denoise", RENDERERS / name, "--run", run, "-o", tmp_path / "o.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    command = exr.read_image(tmp_path / "o.exr").channels
    frame = kpcn.read(RENDERERS / name)
    aux = {k: frame.layers[k] for k in ("albedo", "normal", "depth")}
    if frame.inputs.split:
        api = kpcn.denoise(frame.layers["default"], **aux, diffuse=frame.layers["diffuse"],
                           specular=frame.layers["specular"], run=run)
    else:
        api = kpcn.denoise(frame.layers["default"], **aux, run=run,
                           variance={k: frame.layers[k] for k in VARIANCE_LAYERS if k in frame.layers})
    assert api.dtype == np.float32
    np.testing.assert_array_equal(api, np.stack([command[f"default.{c}"] for c in "RGB"], axis=-1))
    np.testing.assert_array_equal(kpcn.denoise(frame, run=run), api)  # the frame itself, as read


def test_kpcn_evaluate_takes_renderers_files_each_by_its_model(tiny_run_of_every_input_set, tmp_path):
    from kpcn_keras.evaluate import read_rows

    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("cycles5/studio-00016spp.exr", "cycles5/studio-00256spp.exr", "mitsuba3/cornell-00016spp.exr",
                 "mitsuba3/cornell-01024spp.exr"):
        shutil.copy(RENDERERS / name, frames / name.split("/")[1])
    run = tiny_run_of_every_input_set
    res = run_main("evaluate", "--run", run, frames / "studio-00016spp.exr", frames / "cornell-00016spp.exr",
                   "--out", tmp_path / "eval", "--no-baseline", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = {r.scene: r for r in read_rows(tmp_path / "eval")}
    assert (rows["studio"].layout, rows["studio"].model) == ("cycles", str(run / "inputs" / "no-variance"))
    assert (rows["cornell"].layout, rows["cornell"].model) == ("mitsuba", str(run / "inputs" / "no-split"))


def test_a_file_of_a_layout_kpcn_does_not_read_is_one_line_before_any_work(tiny_run_of_every_input_set, tmp_path):
    odd = write_channels(tmp_path / "odd.exr", {"Y": np.zeros((4, 4), np.float32)})
    res = run_main("denoise", odd, "--run", tiny_run_of_every_input_set, cwd=tmp_path)
    assert_one_line_error(res, f"{odd}: no layout kpcn reads: kpcn looks for", "rgb looks for R G B, or one layer of "
                          "R G B, missed R G B; the file has layers default")
    assert not (tmp_path / "odd-denoised.exr").exists()
    res = run_main("denoise", RENDERERS / "mitsuba3" / "cornell-00016spp.exr", "--layout", "cycles", "--run",
                   tiny_run_of_every_input_set, cwd=tmp_path)
    assert_one_line_error(res, "not a cycles file: cycles looks for <view layer>.Combined and Blender's passes")


def test_a_pair_of_renders_is_denoised_as_one_render_of_all_their_samples(tiny_run_of_every_input_set, tmp_path):
    a, b = (cycles_channels(12, 10, seed=1, noise_seed=s) for s in (1, 2))
    pa = write_channels(tmp_path / "a-00008spp.exr", a, parts_of(a))
    pb = write_channels(tmp_path / "b-00008spp.exr", b, parts_of(b))
    run = tiny_run_of_every_input_set
    res = run_main("denoise", pa, "--pair", pb, "--run", run, "-o", tmp_path / "o.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    # what one render gives (no variance made from the two): the network for one Cycles render serves it
    assert f"(cycles layout, no-variance, model {run / 'inputs' / 'no-variance'};" in res.stdout, res.stdout
    # each layer the two renders' mean (float64), as one render of their samples
    mean = {k: (layouts.read(pa).layers[k].astype(np.float64) + layouts.read(pb).layers[k]) / 2
            for k in ("default", "diffuse", "specular", "albedo", "normal", "depth")}
    single = kpcn.denoise(color=mean.pop("default"), **mean, run=run)
    pair = np.stack([exr.read_image(tmp_path / "o.exr").channels[f"default.{c}"] for c in "RGB"], axis=-1)
    np.testing.assert_allclose(pair, single, rtol=1e-5, atol=1e-6)
    res = run_main("denoise", pa, tmp_path / "o.exr", "--pair", pb, "--run", run, "-o", tmp_path / "x", cwd=tmp_path)
    assert_one_line_error(res, "--pair is for one input, got 2")
