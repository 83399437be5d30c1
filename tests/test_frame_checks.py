"""What a renderer's file gets when a layer it needs is not whole (a channel missing), and which of a Cycles
file's view layers is read: each refusal is one line naming the file, the layer and the channel, given by the
header check before any work (``prep.layouts.read_header``) as by the reader itself, through ``kpcn.read``,
``kpcn denoise`` (its inputs, a folder, ``--reference``), ``kpcn evaluate`` and ``kpcn view``."""

import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.exr_layouts import cycles_channels, write_channels
from helpers.files import checksums

import kpcn
from prep import exr, layouts
from prep.exr import AOVError
from prep.inputs import InputSet

RENDERERS = Path(__file__).parent / "fixtures" / "renderers"
FIXTURES = Path(__file__).parent / "fixtures"
STUDIO = RENDERERS / "cycles45" / "studio-00016spp.exr"


def without(src: Path, channel: str, dest: Path) -> Path:
    """``src`` written again to ``dest`` by the OpenEXR API, every channel and header attribute but ``channel``."""
    import OpenEXR

    with OpenEXR.File(str(src), separate_channels=True) as f:
        header = {k: v for k, v in f.header().items() if k != "channels"}
        channels = {name: c.pixels for name, c in f.channels().items()}
    assert channel in channels, sorted(channels)
    del channels[channel]
    with OpenEXR.File(header, channels) as f:
        f.write(str(dest))
    return dest


# ---------------------------------------------------------------- a layer missing a channel

# (file, channel removed, the layer and channel the one line names)
PARTIAL = [
    (STUDIO, "ViewLayer.Normal.Z", "layer ViewLayer.Normal lacks channel Z"),
    (STUDIO, "ViewLayer.DiffCol.B", "layer ViewLayer.DiffCol lacks channel B"),
    (STUDIO, "ViewLayer.Combined.B", "layer ViewLayer.Combined lacks channel B"),
    # a kpcn file with a colour layer of its own: not read as an rgb file of that colour alone
    (FIXTURES / "fixture-00008spp.exr", "diffuse.G", "layer diffuse lacks channel G"),
    # a pbrt file: not read as its R G B alone
    (RENDERERS / "pbrt4" / "cornell-00016spp.exr", "Ns.Z", "layer Ns lacks channel Z"),
]


@pytest.mark.parametrize("src, channel, named", PARTIAL, ids=[c for _, c, _ in PARTIAL])
def test_a_layer_without_one_of_its_channels_is_named_by_the_header_check_and_the_reader(tmp_path, src, channel,
                                                                                       named):
    bad = without(src, channel, tmp_path / src.name)
    for read in (layouts.read_header, layouts.read, kpcn.read):
        with pytest.raises(AOVError) as err:
            read(bad)
        message = str(err.value)
        assert message.startswith(f"{bad}: ") and named in message and "\n" not in message, message


def test_a_forced_layout_names_the_missing_channel_too(tmp_path):
    bad = without(STUDIO, "ViewLayer.Normal.Z", tmp_path / STUDIO.name)
    with pytest.raises(AOVError, match="layer ViewLayer.Normal lacks channel Z"):
        layouts.read_header(bad, "cycles")


@pytest.mark.slow
@pytest.mark.parametrize("channel, named", [("ViewLayer.Normal.Z", "layer ViewLayer.Normal lacks channel Z"),
                                            ("ViewLayer.DiffCol.B", "layer ViewLayer.DiffCol lacks channel B")])
def test_every_command_that_reads_a_frame_refuses_it_in_one_line_before_writing(tiny_run_of_every_input_set,
                                                                              tmp_path, channel, named):
    run = tiny_run_of_every_input_set
    folder = tmp_path / "frames"
    folder.mkdir()
    shutil.copy(STUDIO, folder / "a-00016spp.exr")  # a good frame first: the bad one must stop the batch before it
    bad = without(STUDIO, channel, folder / "b-00016spp.exr")
    shutil.copy(RENDERERS / "cycles45" / "studio-00256spp.exr", folder / "b-00256spp.exr")  # evaluate's reference
    before = checksums(tmp_path)
    for args in (("denoise", bad), ("denoise", folder), ("denoise", folder / "a-00016spp.exr", "--reference", bad),
                 ("evaluate", bad, "--out", tmp_path / "eval", "--no-baseline"), ("view", bad, "--port", "0")):
        res = run_main(*args, "--run", run, cwd=tmp_path)
        assert_one_line_error(res, f"{bad}: ", named)
        assert checksums(tmp_path) == before, args


# ---------------------------------------------------------------- several Cycles view layers


def two_view_layers(path: Path, h: int = 6, w: int = 5) -> tuple[Path, dict]:
    """A Cycles file of view layer ``A`` with Combined alone and view layer ``B`` with every pass."""
    channels = cycles_channels(h, w, seed=4, view="B")
    rng = np.random.default_rng(5)
    channels.update({f"A.Combined.{c}": rng.uniform(0, 1, (h, w)).astype(np.float32) for c in "RGBA"})
    return write_channels(path, channels), channels


def _rgb(channels, layer):
    return np.stack([channels[f"{layer}.{c}"] for c in "RGB"], axis=-1)


def test_of_two_view_layers_the_one_with_the_passes_kpcn_uses_is_read_and_said(tmp_path, caplog):
    path, channels = two_view_layers(tmp_path / "two-00016spp.exr")
    assert layouts.read_header(path).layout == "cycles"
    with caplog.at_level(logging.INFO, logger="kpcn"):
        frame = layouts.read(path)
    assert frame.layout == "cycles" and frame.inputs == InputSet(split=True, variance=False)
    np.testing.assert_array_equal(frame.layers["default"], _rgb(channels, "B.Combined"))
    said = [r.getMessage() for r in caplog.records if "view layer" in r.getMessage()]
    assert len(said) == 1 and "read B" in said[0] and "A" in said[0], said


def test_a_view_layer_named_is_read_and_an_unknown_one_refused_listing_those_there_are(tmp_path):
    path, channels = two_view_layers(tmp_path / "two-00016spp.exr")
    frame = layouts.read(path, view_layer="A")
    assert frame.layout == "rgb" and frame.inputs == InputSet(split=False, variance=False)
    np.testing.assert_array_equal(frame.layers["default"], _rgb(channels, "A.Combined"))
    np.testing.assert_array_equal(frame.alpha, channels["A.Combined.A"])
    assert layouts.read_header(path, view_layer="A").layout == "rgb"
    assert layouts.read(path, view_layer="B").layout == "cycles"
    for read in (layouts.read, layouts.read_header):
        with pytest.raises(AOVError) as err:
            read(path, view_layer="Z")
        assert str(err.value).startswith(f"{path}: ") and "no view layer 'Z'" in str(err.value)
        assert "its view layers: A, B" in str(err.value) and "\n" not in str(err.value)
    plain = exr.write_aovs(tmp_path / "plain.exr", {"default": np.ones((2, 2, 3), np.float32)})
    with pytest.raises(AOVError, match="no view layer 'A'.*no Cycles view layers"):
        layouts.read(plain, view_layer="A")


@pytest.mark.slow
def test_the_commands_take_view_layer(tiny_run_of_every_input_set, tmp_path):
    run = tiny_run_of_every_input_set
    path, _ = two_view_layers(tmp_path / "two-00016spp.exr", 12, 10)
    shutil.copy(path, tmp_path / "two-00256spp.exr")  # evaluate's reference
    res = run_main("denoise", path, "--run", run, "-o", tmp_path / "b.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "(cycles layout, no-variance," in res.stdout and "read B" in res.stderr
    res = run_main("denoise", path, "--view-layer", "A", "--run", run, "-o", tmp_path / "a.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "(rgb layout, no-split-no-variance," in res.stdout
    before = checksums(tmp_path)
    for args in (("denoise", path), ("evaluate", path, "--out", tmp_path / "eval", "--no-baseline"),
                 ("view", path, "--port", "0")):
        res = run_main(*args, "--view-layer", "Z", "--run", run, cwd=tmp_path)
        assert_one_line_error(res, f"{path}: no view layer 'Z'", "its view layers: A, B")
        assert checksums(tmp_path) == before, args
