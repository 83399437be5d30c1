"""OIDN's command line on ``kpcn denoise`` (kpcn_keras/oidn_args.py) and the PFM files it reads and writes
(prep/pfm.py): PFM bytes checked against hand-built ones, ``--hdr/--alb/--nrm -o out.pfm`` against ``kpcn denoise``
of EXRs holding the same pixels, each option of ``oidnDenoise`` kpcn cannot honour refused in one line."""

import json
import shutil
import struct

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main

from kpcn_keras import oidn_args
from kpcn_keras.parser import _flags, build_parser, inference_settings
from prep import exr, pfm
from prep.auxiliary import auxiliaries
from prep.inputs import InputSet, restrict

H, W = 20, 28  # a small frame, not a multiple of the tile's alignment


def _frame(seed=0):
    rng = np.random.default_rng(seed)
    colour = rng.gamma(1.0, 0.5, (H, W, 3)).astype(np.float32)
    albedo = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    normal = rng.uniform(-1, 1, (H, W, 3)).astype(np.float32)
    return colour, albedo, normal


def test_a_colour_pfm_is_read_from_hand_built_bytes_bottom_row_first():
    samples = np.arange(12, dtype=np.float32) + 0.5  # 2x2 RGB, file order: the bottom row, then the top
    data = b"PF\n2 2\n-1.0\n" + struct.pack("<12f", *samples)
    expected = samples.reshape(2, 2, 3)[::-1]
    assert_read(data, expected)
    # big endian (a positive scale); the scale's magnitude multiplies, as OIDN's reader applies it
    assert_read(b"PF\n2 2\n1.0\n" + struct.pack(">12f", *samples), expected)
    assert_read(b"PF 2 2 -2.0\n" + struct.pack("<12f", *samples), expected * 2)


def test_a_greyscale_pfm_is_one_channel():
    assert_read(b"Pf\n3 2\n-1\n" + struct.pack("<6f", 1, 2, 3, 4, 5, 6), np.array([[4, 5, 6], [1, 2, 3]], np.float32))


def assert_read(data, expected):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "x.pfm"
        path.write_bytes(data)
        image = pfm.read(path)
    assert image.dtype == np.float32 and image.shape == expected.shape
    np.testing.assert_array_equal(image, expected)


def test_write_makes_the_bytes_oidn_writes_and_reads_them_back(tmp_path):
    image = np.array([[[1, 2, 3], [4, 5, 6]]], np.float32)  # one row of two pixels
    pfm.write(tmp_path / "a.pfm", image)
    assert (tmp_path / "a.pfm").read_bytes() == b"PF\n2 1\n-1.0\n" + struct.pack("<6f", 1, 2, 3, 4, 5, 6)
    pfm.write(tmp_path / "g.pfm", np.array([[1.0], [2.0]]))  # two rows, one column: the bottom row first
    assert (tmp_path / "g.pfm").read_bytes() == b"Pf\n1 2\n-1.0\n" + struct.pack("<2f", 2, 1)
    rng = np.random.default_rng(1)
    for shape in ((5, 7, 3), (6, 4)):
        values = rng.normal(size=shape).astype(np.float32)
        pfm.write(tmp_path / "r.pfm", values)
        np.testing.assert_array_equal(pfm.read(tmp_path / "r.pfm"), values)
    with pytest.raises(pfm.PfmError, match="b.pfm"):
        pfm.write(tmp_path / "b.pfm", np.zeros((2, 2, 4)))
    assert not (tmp_path / "b.pfm").exists()


BAD_PFMS = {
    "empty": b"",
    "another magic": b"P6\n2 2\n255\n" + bytes(12),
    "two channels": b"P=\n1 1\n-1.0\n" + bytes(8),
    "no scale": b"PF\n2 2\n",
    "a word for a width": b"PF\nwide 2\n-1.0\n" + bytes(48),
    "no pixels": b"PF\n0 2\n-1.0\n",
    "a zero scale": b"PF\n1 1\n0\n" + bytes(12),
    "a nan scale": b"PF\n1 1\nnan\n" + bytes(12),
    "cut short": b"PF\n2 2\n-1.0\n" + bytes(47),
    "a size its bytes cannot hold": b"PF\n100000 100000\n-1.0\n" + bytes(12),
}


@pytest.mark.parametrize("case", BAD_PFMS)
def test_a_bad_pfm_is_refused_in_one_line_naming_it(tmp_path, case):
    path = tmp_path / "bad.pfm"
    path.write_bytes(BAD_PFMS[case])
    with pytest.raises(pfm.PfmError) as err:
        pfm.read(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_a_bad_pfm_on_the_command_line_is_one_line_naming_it(tmp_path):
    (tmp_path / "c.pfm").write_bytes(BAD_PFMS["cut short"])
    res = run_main("denoise", "--hdr", "c.pfm", "-o", "out.pfm", cwd=tmp_path)
    assert_one_line_error(res, "c.pfm", "needs 48 bytes")
    res = run_main("denoise", "--hdr", "missing.pfm", "-o", "out.pfm", cwd=tmp_path)
    assert_one_line_error(res, "missing.pfm")
    assert not (tmp_path / "out.pfm").exists()


def _write_inputs(folder, colour, albedo, normal):
    """The frame as OIDN's three PFMs and as three plain RGB EXRs."""
    for name, image in (("color", colour), ("albedo", albedo), ("normal", normal)):
        pfm.write(folder / f"{name}.pfm", image)
        exr.write_aovs(folder / f"{name}.exr", {"default": image})


@pytest.fixture(scope="module")
def exr_path_output(tmp_path_factory):
    """(folder, kpcn denoise's colour) of the frame as three plain RGB EXRs, denoised by the shipped model, whose
    no-split-no-variance variant serves a colour with its albedo and normal; the PFMs of the same pixels beside."""
    folder = tmp_path_factory.mktemp("oidn")
    _write_inputs(folder, *_frame())
    res = run_main("denoise", "color.exr", "--albedo", "albedo.exr", "--normal", "normal.exr", "-o", "kpcn.exr",
                   cwd=folder)
    assert res.returncode == 0, res.stderr
    assert "rgb layout, no-split-no-variance" in res.stdout
    expected = exr.read_rgb(folder / "kpcn.exr")
    assert np.isfinite(expected).all() and not np.array_equal(expected, pfm.read(folder / "color.pfm"))
    return folder, expected


def test_oidns_command_line_on_pfms_denoises_as_kpcn_denoise_does_the_same_pixels_in_exrs(exr_path_output):
    folder, expected = exr_path_output
    before = set(folder.iterdir())
    res = run_main("denoise", "-hdr", "color.pfm", "--alb", "albedo.pfm", "--nrm", "normal.pfm", "-o", "out.pfm",
                   cwd=folder)
    assert res.returncode == 0, res.stderr
    assert "wrote out.pfm (PFM" in res.stdout
    np.testing.assert_array_equal(pfm.read(folder / "out.pfm"), expected)
    assert set(folder.iterdir()) - before == {folder / "out.pfm"}  # no temporary left


@pytest.mark.slow
@pytest.mark.parametrize("out, albedo", [("out.exr", "albedo.pfm"), ("mixed.pfm", "albedo.exr")])
def test_an_exr_output_or_exr_inputs_are_the_same_pixels_too(exr_path_output, out, albedo):
    folder, expected = exr_path_output
    res = run_main("denoise", "--hdr", "color.pfm", "--albedo", albedo, "--normal", "normal.pfm", "-o", out, "-q", "b",
                   cwd=folder)
    assert res.returncode == 0, res.stderr
    got = pfm.read(folder / out) if out.endswith(".pfm") else exr.read_rgb(folder / out)
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("args, needles", [
    (["--ldr", "c.pfm"], ["--ldr c.pfm", "HDR"]),
    (["--hdr", "c.pfm", "--srgb"], ["--srgb"]),
    (["--hdr", "c.pfm", "-f", "RTLightmap"], ["-f RTLightmap"]),
    (["--hdr", "c.pfm", "-d", "sycl"], ["-d sycl"]),
    (["--hdr", "c.pfm", "--maxmem", "512"], ["--maxmem 512", "--tile"]),
    (["--hdr", "c.pfm", "-w", "rt.tza"], ["-w rt.tza", "--run"]),
    (["--hdr", "c.pfm", "-r", "ref.pfm"], ["-r ref.pfm"]),
    (["--hdr", "c.pfm", "--is", "2"], ["--is 2"]),
    (["--hdr", "c.pfm", "-t", "half"], ["-t half", "float"]),
    (["--hdr", "c.pfm", "-n", "10"], ["-n 10"]),
    (["--hdr", "c.pfm", "--ld"], ["--ld"]),
    (["--hdr", "c.pfm", "-q", "ultra"], ["-q ultra"]),
    (["--hdr", "c.pfm", "--bogus"], ["--bogus"]),
    (["--hdr", "c.pfm", "extra.pfm"], ["'extra.pfm'"]),
    (["--hdr", "c.pfm", "-o"], ["-o needs a value"]),
    (["--alb", "a.pfm"], ["--alb", "--hdr"]),
    (["--hdr", "c.pfm", "-o", "out.png"], ["-o out.png", ".png"]),
    (["--hdr", "c.ppm"], ["--hdr c.ppm"]),
    (["--hdr", "c.pfm", "-o", "c.pfm"], ["-o c.pfm", "--hdr"]),
])
def test_what_kpcn_cannot_do_of_oidns_options_is_one_line_naming_it(tmp_path, args, needles):
    pfm.write(tmp_path / "c.pfm", _frame()[0])
    before = sorted(p.name for p in tmp_path.iterdir())
    res = run_main("denoise", *args, cwd=tmp_path)
    assert_one_line_error(res, *needles)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_images_of_another_size_or_one_channel_are_refused_naming_them(tmp_path):
    colour, albedo, _ = _frame()
    pfm.write(tmp_path / "c.pfm", colour)
    pfm.write(tmp_path / "a.pfm", albedo[:-1])
    pfm.write(tmp_path / "g.pfm", colour[..., 0])
    assert_one_line_error(run_main("denoise", "--hdr", "c.pfm", "--alb", "a.pfm", cwd=tmp_path), "--alb a.pfm",
                          f"{W}x{H - 1}", f"{W}x{H}")
    assert_one_line_error(run_main("denoise", "--hdr", "g.pfm", cwd=tmp_path), "--hdr g.pfm", "one-channel")


def test_oidns_options_become_kpcn_denoises_own():
    cmd = oidn_args.parse(["--hdr", "c.pfm", "--albedo", "a.pfm", "---nrm", "n.pfm", "--clean_aux", "-q", "h",
                           "--threads", "3", "-t", "fp32", "-f", "RT", "-d", "cpu", "-n", "1", "--affinity", "0",
                           "--inplace", "--buffer", "host", "-v", "2", "--run", "models/default"])
    assert (str(cmd.colour), str(cmd.albedo), str(cmd.normal), cmd.clean_aux) == ("c.pfm", "a.pfm", "n.pfm", True)
    images = {"--hdr": "c.exr", "--alb": "a.exr", "--nrm": "n.exr"}
    argv = ["denoise", *oidn_args.kpcn_arguments(cmd, images, "o.exr")]
    parser = build_parser()
    args = parser.parse_args(argv)
    args.flags = _flags(parser, "denoise")
    assert (args.inputs, args.albedo, args.normal, args.output, args.layout, args.threads, args.run) == (
        ["c.exr"], "a.exr", "n.exr", "o.exr", "rgb", 3, "models/default")
    settings = inference_settings(args)
    assert (settings.quality, settings.precision, settings.clean_aux) == ("high", "float32", True)
    assert oidn_args.parse(["--hdr", "c.pfm", "-q", "default", "--threads", "0"]).kpcn == {}
    assert oidn_args.applies(["-q", "denoise", "-hdr", "c.pfm"])
    assert not oidn_args.applies(["denoise", "c.exr", "--albedo", "a.exr", "--normal", "n.exr"])
    assert not oidn_args.applies(["view", "--hdr"])


def test_every_option_of_oidn_is_mapped_or_refused():
    """Each name of apps/oidnDenoise.cpp's parser (RenderKit/oidn) is taken (MAPPED) or refused (REFUSED)."""
    oidn = {"device", "filter", "hdr", "ldr", "srgb", "dir", "alb", "nrm", "output", "ref", "input_scale", "clean_aux",
            "type", "quality", "weights", "n", "threads", "affinity", "maxmem", "inplace", "buffer", "maxerror",
            "verbose", "list_devices", "help"}
    assert oidn - {"help"} <= set(oidn_args.MAPPED) | set(oidn_args.REFUSED)
    assert not set(oidn_args.MAPPED) & set(oidn_args.REFUSED)
    assert oidn <= set(oidn_args.ALIASES.values())


def test_help_lists_what_kpcn_takes(tmp_path):
    res = run_main("denoise", "--hdr", "c.pfm", "-h", cwd=tmp_path)
    assert res.returncode == 0 and "--hdr" in res.stdout and "maxmem" in res.stdout


def test_clean_aux_gives_a_prefiltered_model_the_auxiliaries_as_they_are(tiny_run, tmp_path):
    from helpers.tiny import random_aovs

    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings

    model = tmp_path / "nlm-model"
    shutil.copytree(tiny_run, model)
    record = json.loads(Run(model).record_path.read_text())
    record["train"]["auxiliaries"] = "nlm"  # as if trained on kpcn's prefilter
    Run(model).record_path.write_text(json.dumps(record))
    frame = random_aovs(24, 24, seed=4)
    full = InputSet()
    prefiltered = Denoiser.from_run(Run(model)).given(frame)
    as_given = Denoiser.from_run(Run(model), InferenceSettings(clean_aux=True)).given(frame)
    for name in ("albedo", "normal", "depth"):
        np.testing.assert_array_equal(prefiltered[name], auxiliaries(restrict(frame, full), "nlm")[name])
        np.testing.assert_array_equal(as_given[name], frame[name])
        assert not np.array_equal(prefiltered[name], frame[name])
