"""The inference settings (kpcn_keras/settings.py) and the serving object that applies them (kpcn_keras/serving.py):
made once from the command line, checked once, by the settings themselves, and what each denoiser is loaded with."""

import pytest

from kpcn_keras.cli import main
from kpcn_keras.config import DEFAULT_ENSEMBLE, DEFAULT_PRECISION, DEFAULT_TILE, ENSEMBLE, TILE
from kpcn_keras.parser import _flags, build_parser, inference_settings
from kpcn_keras.settings import InferenceSettings
from prep.errors import OptionError

SETTINGS = ("tile", "precision", "ensemble")


def _parsed(*argv):
    parser = build_parser()
    args = parser.parse_args(list(argv))
    args.flags = _flags(parser, args.command)  # as cli.main sets them
    return args


def test_the_command_lines_settings_reach_the_denoiser(tiny_run):
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from prep.inputs import FULL

    args = _parsed("denoise", "in.exr", "--tile", "64", "--ensemble", "2", "--precision", "float32")
    settings = inference_settings(args)
    assert settings == InferenceSettings(tile=64, precision="float32", ensemble=2)
    serving = Serving(Run(tiny_run), settings)
    denoiser = serving.denoiser(FULL)
    assert (denoiser.settings, denoiser.asked_tile, denoiser.ensemble, denoiser.precision) == (settings, 64, 2,
                                                                                             "float32")
    assert serving.denoiser(FULL) is denoiser and serving.load_s > 0  # loaded once, its time counted
    # an option left out is the config's default; one a command does not have is too
    assert inference_settings(_parsed("view", "in.exr", "--tile", "32")) == InferenceSettings(
        32, DEFAULT_PRECISION, DEFAULT_ENSEMBLE)
    assert inference_settings(_parsed("figures")) == InferenceSettings(DEFAULT_TILE, DEFAULT_PRECISION,
                                                                       DEFAULT_ENSEMBLE)


@pytest.mark.parametrize("field, value, message", [
    ("tile", 0, f"must be {TILE.text()}, got 0"),
    ("ensemble", 9, f"must be {ENSEMBLE.text()}, got 9"),
    ("precision", "half", "must be one of auto, float32, bfloat16, received 'half'"),
])
def test_a_bad_setting_is_refused_by_the_settings_naming_the_option(field, value, message):
    with pytest.raises(OptionError) as err:
        InferenceSettings(**{field: value})
    assert (err.value.option, err.value.detail) == (field, message)


@pytest.mark.parametrize("command, args", [
    ("denoise", ["in.exr"]), ("evaluate", ["--run", "nowhere"]), ("view", ["in.exr"]), ("figures", [])])
def test_every_command_refuses_a_bad_tile_once_by_its_flag(tmp_path, monkeypatch, capsys, command, args):
    # the one check is the settings': the parser's own bounds hold none of their options
    _, own, _ = build_parser().get_default("bounded")[command]
    assert not set(own) & set(SETTINGS)
    monkeypatch.chdir(tmp_path)
    bad = [("--tile", "0", TILE)] + ([("--ensemble", "9", ENSEMBLE)] if command in ("denoise", "evaluate") else [])
    for flag, value, bound in bad:
        assert main(["-q", command, *args, flag, value]) == 2
        out, err = capsys.readouterr()
        assert (out, err) == ("", f"kpcn {command}: error: {flag} must be {bound.text()}, got {value}\n")


def test_kpcn_denoise_applies_its_settings(tiny_run, tmp_path, fixture_noisy):
    # end to end: what the command wrote is, bit for bit, what a denoiser loaded with those settings gives, and
    # not what the defaults give (a 2-member ensemble changes the output)
    import numpy as np

    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from prep import exr, layouts

    out = tmp_path / "out.exr"
    assert main(["-q", "denoise", str(fixture_noisy), "--run", str(tiny_run), "-o", str(out), "--tile", "16",
                 "--ensemble", "2", "--precision", "float32"]) == 0
    written = exr.read_aovs(out, variances=False)["default"]
    frame = layouts.read(fixture_noisy).layers
    want = Denoiser.from_run(Run(tiny_run), InferenceSettings(16, "float32", 2))(frame)["default"]
    np.testing.assert_array_equal(written, want)
    assert not np.array_equal(written, Denoiser.from_run(Run(tiny_run), InferenceSettings(precision="float32"))(
        frame)["default"])
