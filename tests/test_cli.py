"""The command line as a user meets it: bad input gives one clear line and exit status 2, and the whole
pipeline at toy size through its entry point: render, shards, 20 training steps, denoise (our render and the
Mitsuba fixture), evaluate."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, kpcn, run_main
from helpers.files import checksums
from helpers.tiny import build_tiny_shards, make_renders, random_aovs

from kpcn_keras.cli import main
from kpcn_keras.evaluate import read_rows
from prep import exr

REPO = Path(__file__).resolve().parents[1]


def test_missing_layer_is_reported_without_traceback(tmp_path):
    aovs = random_aovs(8, 8)
    del aovs["specularVariance"]
    exr.write_aovs(tmp_path / "renders" / "s" / "x-00004spp.exr", aovs)
    exr.write_aovs(tmp_path / "renders" / "s" / "x-00064spp.exr", random_aovs(8, 8, variances=False))
    res = run_main("shards", "--set", "s", "--renders", str(tmp_path / "renders"), "--out", str(tmp_path / "sh"),
               "--patch-size", "4", cwd=tmp_path)
    assert res.returncode == 2
    assert "x-00004spp.exr" in res.stderr and "specularVariance" in res.stderr
    assert "Traceback" not in res.stderr


def test_missing_render_folder_and_bad_option_values(tmp_path):
    res = run_main("shards", "--set", "nothing", "--renders", str(tmp_path), cwd=tmp_path)
    assert res.returncode == 2 and "no such render folder" in res.stderr and "Traceback" not in res.stderr
    res = run_main("shards", "--set", "nothing", "--renders", str(tmp_path), "--val-fraction", "1.5", cwd=tmp_path)
    assert res.returncode == 2 and "--val-fraction" in res.stderr and "1.5" in res.stderr


def test_denoise_without_a_run_names_the_folder(tmp_path, fixture_noisy):
    res = run_main("denoise", str(fixture_noisy), "--run", str(tmp_path / "no-run"), cwd=tmp_path)
    assert res.returncode == 2 and "no-run" in res.stderr and "not a run folder" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.slow
def test_render_and_shards_do_not_import_the_deep_learning_stack():
    # prep.figures: kpcn figures --set (a shard set's figures) too
    code = ("import sys; import kpcn_keras.cli, prep.render, prep.shards, prep.features, prep.sampling, prep.figures; "
            "bad = [m for m in ('keras', 'torch', 'tensorflow') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_main_run_in_this_process_leaves_the_process_as_it_found_it(tmp_path):
    # run_main is how these tests call main without a fresh interpreter; main sets the thread counts, their
    # environment variables and the root logger, which later tests in this process must not inherit
    import logging
    import os

    import numba
    import torch

    before = (dict(os.environ), os.getcwd(), sys.argv[:], logging.getLogger().handlers[:],
              numba.get_num_threads(), torch.get_num_threads())
    exr.write_aovs(tmp_path / "in.exr", random_aovs(8, 8))
    res = run_main("denoise", "in.exr", "--run", "no-run", "--threads", "1", cwd=tmp_path)
    assert_one_line_error(res, "no-run", "not a run folder")
    assert (dict(os.environ), os.getcwd(), sys.argv[:], logging.getLogger().handlers[:],
            numba.get_num_threads(), torch.get_num_threads()) == before


# --- kpcn denoise's default output: beside its input, never the input itself ---

@pytest.mark.parametrize("name", ["noext", "UP.EXR", "frame.exr.d/in.exr", "x.Exr"])
def test_denoise_without_output_writes_beside_the_input_and_never_over_it(tmp_path, tiny_run, name):
    src = tmp_path / name
    exr.write_aovs(src, random_aovs(20, 24))
    before = checksums(tmp_path)
    res = run_main("denoise", name, "--run", tiny_run, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    stem = src.name[:-4] if src.name.lower().endswith(".exr") else src.name
    out = src.with_name(stem + "-denoised.exr")
    assert checksums(tmp_path)[name] == before[name]  # the input is untouched
    assert sorted(checksums(tmp_path)) == sorted([name, str(out.relative_to(tmp_path))])
    assert exr.read_aovs(out, variances=False)["default"].shape == (20, 24, 3)


def test_denoise_refuses_an_output_that_is_its_input_or_its_reference(tmp_path, tiny_run):
    exr.write_aovs(tmp_path / "in.exr", random_aovs(12, 12))
    before = checksums(tmp_path)
    res = run_main("denoise", "in.exr", "--run", tiny_run, "-o", "./in.exr", cwd=tmp_path)
    assert_one_line_error(res, "in.exr", "input")
    assert checksums(tmp_path) == before
    exr.write_aovs(tmp_path / "ref.exr", random_aovs(12, 12, variances=False))
    before = checksums(tmp_path)
    res = run_main("denoise", "in.exr", "--run", tiny_run, "--reference", "ref.exr", "-o", "./ref.exr", cwd=tmp_path)
    assert_one_line_error(res, "ref.exr", "reference file")
    assert checksums(tmp_path) == before


def test_denoise_checks_every_file_it_writes_against_every_file_it_reads(tmp_path, tiny_run, monkeypatch):
    import json
    import os

    from kpcn_keras.batch import denoise_files
    from kpcn_keras.run import Run
    from prep.errors import KpcnError

    pp = tmp_path / "pp"
    exr.write_aovs(pp / "frame.png", random_aovs(12, 12))  # an EXR named .png
    exr.write_aovs(pp / "ref.png", random_aovs(12, 12, variances=False))
    exr.write_aovs(tmp_path / "in.exr", random_aovs(12, 12))
    (tmp_path / "alias").symlink_to(pp)
    os.link(tmp_path / "in.exr", tmp_path / "hard.exr")
    model = Path(tiny_run) / json.loads((Path(tiny_run) / "config.json").read_text())["components"]["diffuse"]["file"]
    before, models = checksums(tmp_path), checksums(tiny_run)
    res = run_main("denoise", "pp/frame.png", "--run", tiny_run, "-o", "pp/frame.exr", "--png", cwd=tmp_path)
    assert_one_line_error(res, "side-by-side PNG pp/frame.png is the input file pp/frame.png itself")
    monkeypatch.chdir(tmp_path)
    for inputs, output, reference, message in [
        ("pp/frame.png", "alias/frame.exr", None, "side-by-side PNG alias/frame.png is the input file pp/frame.png"),
        ("in.exr", "pp/ref.exr", "pp/ref.png", "side-by-side PNG pp/ref.png is the reference file pp/ref.png"),
        ("hard.exr", "in.exr", None, "--output in.exr is the input file hard.exr"),  # a hard link of the input
        ("in.exr", model, None, f"--output {model} is the diffuse model file {model}"),
        ("in.exr", "out.png", None, "side-by-side PNG out.png and --output out.png are the same file"),
    ]:
        with pytest.raises(KpcnError, match="^" + re.escape(message)):
            denoise_files([inputs], Run(tiny_run), output, reference)
    assert checksums(tmp_path) == before and checksums(tiny_run) == models


def test_denoise_reference_that_is_a_folder_is_named_as_one(tmp_path, tiny_run):
    exr.write_aovs(tmp_path / "in.exr", random_aovs(12, 12))
    (tmp_path / "refs").mkdir()
    res = run_main("denoise", "in.exr", "--run", tiny_run, "--reference", "refs", cwd=tmp_path)
    assert_one_line_error(res, "--reference", "refs, a folder", "reference EXR file")


# --- outputs are checked before the work starts (defect 6) ---

def test_denoise_output_under_a_file_is_refused_before_inference(tmp_path, tiny_run):
    exr.write_aovs(tmp_path / "in.exr", random_aovs(12, 12))
    (tmp_path / "afile").write_text("not a folder")
    before = checksums(tmp_path)
    res = run_main("denoise", "in.exr", "--run", tiny_run, "-o", "afile/out.exr", cwd=tmp_path)
    assert_one_line_error(res, "afile/out.exr")
    assert checksums(tmp_path) == before


@pytest.mark.slow
def test_render_output_under_a_file_is_refused_before_rendering(tmp_path):
    (tmp_path / "afile").write_text("not a folder")
    # a set that would take hours: the refusal has to come first to return within the timeout
    res = kpcn("render", "--set", "s", "--out", "afile/renders", "--width", "2048", "--height", "2048",
               "--reference-spp", "4096", cwd=tmp_path, timeout=60)
    assert_one_line_error(res, "afile")
    assert checksums(tmp_path) == {"afile": checksums(tmp_path)["afile"]}


def test_shards_output_under_a_file_is_refused(tmp_path):
    make_renders(tmp_path / "renders" / "s")
    (tmp_path / "afile").write_text("not a folder")
    before = checksums(tmp_path)
    res = run_main("shards", "--set", "s", "--renders", "renders", "--out", "afile", "--patch-size", "8", cwd=tmp_path)
    assert_one_line_error(res, "afile")
    assert checksums(tmp_path) == before


# --- a full disk: one line, nothing half-written, and a rerun with space finishes ---

def test_denoise_on_a_full_disk_ends_in_one_line_and_a_rerun_with_space_writes_it(tmp_path, tiny_run, small_disk):
    exr.write_aovs(tmp_path / "in.exr", random_aovs(64, 64))
    args = ("denoise", "in.exr", "--run", tiny_run, "-o", "disk/out.exr", "--png")
    assert_one_line_error(run_main(*args, cwd=tmp_path), "disk/out.exr: cannot write (No space left on device)")
    assert list(small_disk.path.iterdir()) == []
    small_disk.grow()
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in small_disk.path.iterdir()) == ["out.exr", "out.png"]
    assert exr.read_aovs(small_disk.path / "out.exr", variances=False)["default"].shape == (64, 64, 3)


@pytest.mark.slow
def test_denoise_refused_a_write_by_the_file_system_ends_in_one_line(tmp_path, tiny_run):
    # the failure injected at write(2) without a mount: files may not grow past 64 kB. numba caches the
    # kernels it compiles on first use beside their source, in files larger than that: a run without the limit
    # first, so that the limited one fails at the output, where the test means it to, in any order of tests
    warm, case = tmp_path / "warm", tmp_path / "case"
    for folder in (warm, case):
        folder.mkdir()
        exr.write_aovs(folder / "in.exr", random_aovs(64, 64))
    assert kpcn("denoise", "in.exr", "--run", tiny_run, cwd=warm).returncode == 0
    before = checksums(case)
    res = kpcn("denoise", "in.exr", "--run", tiny_run, cwd=case, file_size_limit=64 << 10)
    assert_one_line_error(res, "in-denoised.exr: cannot write (File too large)")
    assert checksums(case) == before and sorted(p.name for p in case.iterdir()) == ["in.exr"]


def test_an_internal_error_is_not_reported_as_bad_input(monkeypatch, tmp_path):
    # a ValueError from a bug is not the user's fault: it must surface as a traceback, not as exit 2
    from kpcn_keras import cli
    from prep import render

    def bug(*args, **kwargs):
        raise ValueError("an internal bug")

    monkeypatch.setattr(render, "render_set", bug)
    with pytest.raises(ValueError, match="an internal bug"):
        cli.main(["-q", "render", "--set", "s", "--out", str(tmp_path)])


# --- corrupt and broken inputs give one line (defect 10) ---

def test_corrupt_exr_gives_one_line_and_no_library_output(tmp_path, tiny_run):
    good = tmp_path / "good.exr"
    exr.write_aovs(good, random_aovs(16, 16))
    data = bytearray(good.read_bytes())
    bad = tmp_path / "bad.exr"
    bad.write_bytes(bytes(data[: len(data) // 2]))  # truncated mid-file, as a killed copy leaves it
    before = checksums(tmp_path)
    res = run_main("denoise", "bad.exr", "--run", tiny_run, cwd=tmp_path)
    assert_one_line_error(res, "bad.exr")
    assert checksums(tmp_path) == before


# --- kpcn denoise of many frames: one model load for all ---

def test_denoise_many_inputs_into_a_folder_and_refuses_a_file_output(tmp_path, tiny_run):
    for name in ("a.exr", "b.exr"):
        exr.write_aovs(tmp_path / "in" / name, random_aovs(12, 14))
    before = checksums(tmp_path)
    res = run_main("denoise", "in/a.exr", "in/b.exr", "--run", tiny_run, "-o", "one.exr", cwd=tmp_path)
    assert_one_line_error(res, "--output", "one.exr", "folder")
    assert checksums(tmp_path) == before
    res = run_main("--quiet", "denoise", "in", "--run", tiny_run, "-o", "out", "--threads", "1", "--png", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "a-denoised.exr", "a-denoised.png", "b-denoised.exr", "b-denoised.png"]
    assert "model load" in res.stdout and "warm-up" in res.stdout and "(1 thread, " in res.stdout
    # a second run over the folder beside the inputs skips nothing silently: earlier outputs are named
    res = run_main("denoise", "out", "--run", tiny_run, cwd=tmp_path)
    assert res.returncode == 2 and "no renders to denoise" in res.stderr


def test_denoise_batch_stopped_by_a_bad_frame_keeps_the_outputs_before_it(tmp_path, tiny_run):
    exr.write_aovs(tmp_path / "a.exr", random_aovs(12, 12))
    data = (tmp_path / "a.exr").read_bytes()
    (tmp_path / "b.exr").write_bytes(data[: len(data) - 200])  # header intact, pixels cut off
    res = run_main("denoise", "a.exr", "b.exr", "--run", tiny_run, cwd=tmp_path)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert "b.exr" in lines[0] and "a-denoised.exr" in lines[0]  # names the bad frame and what was written
    assert "wrote a-denoised.exr" in res.stdout
    assert exr.read_aovs(tmp_path / "a-denoised.exr", variances=False)["default"].shape == (12, 12, 3)
    assert not (tmp_path / "b-denoised.exr").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left


def test_denoise_reference_is_for_one_input(tmp_path, tiny_run):
    for name in ("a.exr", "b.exr"):
        exr.write_aovs(tmp_path / name, random_aovs(12, 12))
    res = run_main("denoise", "a.exr", "b.exr", "--run", tiny_run, "--reference", "a.exr", cwd=tmp_path)
    assert_one_line_error(res, "--reference", "one input")


def _actions(parser) -> list:
    import argparse

    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found += _actions(sub)
        elif action.option_strings:
            found.append(action)
    return found


def test_torchrun_passes_every_option_of_ours_through_to_the_command():
    """torchrun parses the whole command line before it starts ours, and stops at any argument that is an
    abbreviation of two of its options: `--run` is one (`--run-path`, `--run_path`), so every option of
    ours has a spelling that is not (`--run-dir`)."""
    from torch.distributed.run import get_args_parser

    from kpcn_keras.parser import build_parser

    torchrun = get_args_parser()
    theirs = {s for action in torchrun._actions for s in action.option_strings}

    def ambiguous(option):
        return sum(t.startswith(option) for t in theirs if t != option) > 1

    blocked = sorted({"/".join(a.option_strings) for a in _actions(build_parser())
                      if all(ambiguous(o) for o in a.option_strings)})
    assert blocked == []
    ours = ["train", "--set", "t", "--run-dir", "runs/x", "--steps", "2"]
    args = torchrun.parse_args(["--standalone", "--nproc-per-node", "2", "-m", "kpcn_keras.cli", *ours])
    assert (args.module, args.training_script, args.training_script_args) == (True, "kpcn_keras.cli", ours)
    assert build_parser().parse_args(ours).run == "runs/x"
    with pytest.raises(SystemExit):  # what the issue met: argparse's "ambiguous option", an exit
        torchrun.parse_args(["--standalone", "-m", "kpcn_keras.cli", "train", "--run", "runs/x"])


def test_a_command_line_built_from_values_parses_back_to_them():
    from kpcn_keras.parser import build_parser, command_line

    values = {"set_name": "s", "render_root": "r", "patch_size": 16, "val_scenes": ("a", "b"), "input_spp": 4,
              "out_root": "x", "seed": 3}
    args = build_parser().parse_args(["shards", *command_line("shards", {**values, "val_fraction": None})])
    assert {k: getattr(args, k) for k in values} == values
    assert not hasattr(args, "val_fraction")  # None is left out, so the command's default holds
    with pytest.raises(ValueError, match="uniform_mix"):  # a field without a flag
        command_line("shards", {"uniform_mix": 0.2})


def test_shards_record_their_command_without_the_options_that_change_no_byte():
    from kpcn_keras import parser as cli

    argv = ["-q", "shards", "--set", "t", "--threads=2", "--part", "1/2", "--seed", "3", "--thr", "1"]
    parser = cli.build_parser()
    args = parser.parse_args(argv)
    args.argv, args.parser = argv, parser
    assert cli._command_line(args, cli.DATA_INVARIANT) == "kpcn shards --set t --seed 3"
    assert cli._command_line(args) == "kpcn " + " ".join(argv)  # a report keeps every option


# --- the bounds of every numeric option, and no repeats in a list ---

_NUMERIC = ("int", "float", "csv_ints", "csv_floats")
_STATED = re.compile(r"(an odd integer|an integer|a number) in ([\[(])([^,]+), ([^\])]+)([\])])")
# the lists whose entries have a place (y,x; width,height; low,high; a dilation per convolution): a repeat means
# something there
_POSITIONAL = {"pixel", "large_frame", "slope_range", "speed_frame", "dilations"}
# what a command needs besides the option for its check to be reached (the option's bound is checked first)
_NEEDS = {"denoise": ["in.exr", "--run", "no-run"], "evaluate": ["--run", "no-run"], "figures": ["--run", "no-run"],
          "resample": ["--run", "no-run"], "ship": ["--run", "no-run", "--out", "m"],
          "view": ["in.exr", "--run", "no-run"], "render-cycles": ["out"], "cycles-validation": ["out"],
          "import-renders": ["src", "--set", "s"], "export": ["no-run", "--onnx", "out"], "blend-pair": ["x.blend"],
          "adapt": ["in.exr", "--out", "m", "--run", "no-run"], "mix-oidn": ["in.exr", "--run", "no-run"]}
_NEEDS_FOR = {("bench", "width"): ["render"], ("bench", "height"): ["render"], ("bench", "spp"): ["render"],
              ("bench", "families"): ["render"], ("train", "gamma"): ["--compositor", "alpha"],
              ("train", "compositor_kernel"): ["--compositor", "kernel"],
              ("train", "scale_supervision"): ["--compositor", "kernel"]}


def _options():
    """(command, action) of every option of every subcommand."""
    from kpcn_keras.parser import build_parser

    return [(command, action) for command, sub in build_parser().get_default("subcommands").items()
            for action in sub._actions if action.option_strings and action.dest != "help"]


def _beyond(kind, opening, low, high, closing):
    """The values just outside a stated bound, below then above."""
    if kind != "a number":
        return [int(low) - 1, int(high) + 1]
    low, high = float(low), float(high)
    return [low if opening == "(" else low - 1e-3 * max(1.0, abs(low)),
            high if closing == ")" else high + 1e-3 * max(1.0, abs(high))]


def _error_line(capsys, tmp_path, argv):
    from kpcn_keras.cli import main

    assert main(["-q", *argv]) == 2, argv
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1, (argv, out, err)
    assert not any(tmp_path.iterdir()), argv  # refused before anything is written
    return err.strip()


def test_every_numeric_option_states_both_bounds_and_refuses_a_value_beyond_each(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    numeric = [(c, a) for c, a in _options() if getattr(a.type, "__name__", None) in _NUMERIC]
    assert len(numeric) > 60
    unstated = [f"{c} {a.option_strings[-1]}" for c, a in numeric
                if a.dest != "threads" and not _STATED.search(a.help or "")]
    assert unstated == []
    for command, action in numeric:
        flag = max(action.option_strings, key=len)
        if action.dest == "threads":  # its upper bound is the machine's: the cores this process may use
            assert "an integer from 1 to the cores this process may use" in action.help
            values, stated = [0, 10**6], "an integer from 1 to"
        else:
            found = _STATED.search(action.help)
            values, stated = _beyond(*found.groups()), found.group(0)
        for value in values:
            text = f"{value},{value}" if action.dest in _POSITIONAL else str(value)
            argv = [command, *_NEEDS.get(command, []), *_NEEDS_FOR.get((command, action.dest), []), f"{flag}={text}"]
            line = _error_line(capsys, tmp_path, argv)
            assert line.startswith(f"kpcn {command}: error: {flag} must be {stated}"), (argv, line)
            assert f"got {value}" in line, (argv, line)


def test_train_compositor_options_reach_its_config_and_are_refused_in_one_line(tmp_path, monkeypatch, capsys):
    import kpcn_keras.train

    monkeypatch.chdir(tmp_path)
    trained = []
    monkeypatch.setattr(kpcn_keras.train, "train", lambda cfg, run, verbose: trained.append(cfg) or tmp_path)
    from kpcn_keras.cli import main

    assert main(["-q", "train", "--compositor", "kernel", "--compositor-kernel", "21", "--downsample", "bicubic",
                 "--scale-supervision", "0.5", "--kernel-size", "7"]) == 0
    comp = trained[0].compositor
    assert (comp.kind, comp.kernel_size, comp.downsample, comp.scale_supervision) == ("kernel", 21, "bicubic", 0.5)
    assert trained[0].model.kernel_size == 7  # --kernel-size stays the branch network's
    assert main(["-q", "train", "--compositor", "alpha"]) == 0  # the defaults, written once in the config
    assert (trained[1].compositor.kernel_size, trained[1].compositor.downsample,
            trained[1].compositor.scale_supervision) == (5, "average", 0.0)
    capsys.readouterr()
    for argv, words in (
        (["--compositor", "kernel", "--compositor-kernel", "22"], ["--compositor-kernel", "odd", "got 22"]),
        (["--compositor", "kernel", "--compositor-kernel=43"], ["--compositor-kernel", "got 43"]),
        (["--compositor", "alpha", "--compositor-kernel", "9"], ["--compositor-kernel", "--compositor kernel"]),
        (["--downsample", "bicubic"], ["--downsample", "--compositor"]),
        (["--scale-supervision", "1"], ["--scale-supervision", "--compositor"]),
        (["--compositor", "kernel", "--scale-supervision", "-1"], ["--scale-supervision", "got -1"]),
    ):
        line = _error_line(capsys, tmp_path, ["train", *argv])
        assert all(w in line for w in words), (argv, line)
    with pytest.raises(SystemExit) as exc:  # argparse's own choice check: exit 2, one usage line and the error
        main(["-q", "train", "--compositor", "kernel", "--downsample", "lanczos"])
    assert exc.value.code == 2 and "--downsample" in capsys.readouterr().err
    assert len(trained) == 2


def test_every_list_option_whose_repeats_mean_nothing_refuses_one_naming_it(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    lists = [(c, a) for c, a in _options() if getattr(a.type, "__name__", None) in ("csv", "csv_ints", "csv_floats")]
    assert {a.dest for _, a in lists} >= {"families", "input_spp", "branches", "configurations", "arms", "seeds",
                                          "val_scenes", "presets", "raw_spp", "budget_fractions", "slopes"}
    for command, action in lists:
        if action.dest in _POSITIONAL:
            assert "no repeats" not in action.help
            continue
        assert "no repeats" in action.help, (command, action.dest)
        flag = max(action.option_strings, key=len)
        valid = {"families": "cornell", "branches": "diffuse", "configurations": "cpu", "presets": "cpu",
                 "levers": "cpu", "arms": "error", "val_scenes": "a", "budget_fractions": "0.5",
                 "slopes": "2.5"}.get(action.dest, "4")
        argv = [command, *_NEEDS.get(command, []), *_NEEDS_FOR.get((command, action.dest), []), flag,
                f"{valid},{valid}"]
        line = _error_line(capsys, tmp_path, argv)
        assert line.startswith(f"kpcn {command}: error: {flag} names {valid} more than once"), (argv, line)


def test_render_of_one_family_twice_is_refused_in_one_line_before_anything_is_written(tmp_path):
    res = run_main("render", "--families", "cornell,cornell", "--per-family", "1", "--out", "renders", cwd=tmp_path)
    assert_one_line_error(res, "--families names cornell more than once")
    assert not any(tmp_path.iterdir())


def test_every_seed_option_takes_the_one_seed_range():
    from prep.bounds import SEED

    seeds = {c: a.help for c, a in _options() if a.dest in ("seed", "seeds")}
    assert set(seeds) >= {"render", "shards", "train", "bench", "compare", "resample-study"}
    assert all(SEED.text() in text for text in seeds.values()), seeds


@pytest.mark.slow
def test_train_unet_options_reach_the_record_and_are_refused_with_another_arch(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for flag, value in (("--levels", "3"), ("--width-growth", "2"), ("--width-cap", "12")):
        line = _error_line(capsys, tmp_path, ["train", flag, value])  # the cpu preset: a kpcn
        field = flag[2:].replace("-", "_")
        assert line.startswith(f"kpcn train: error: {flag} is a setting of arch unet alone, received {value}"), line
        assert field not in line.replace(flag, "")
    shard_cfg = build_tiny_shards(tmp_path, patch_size=32, patches_per_image=4, patches_per_shard=4)
    assert main(["-q", "train", "--set", "s", "--shards", shard_cfg.out_root, "--run", "runs/u", "--steps", "2",
                 "--batch-size", "2", "--arch", "unet", "--levels", "3", "--width-growth", "2", "--width-cap", "12",
                 "--width", "4", "--depth", "1", "--kernel-size", "5", "--branches", "diffuse"]) == 0
    record = json.loads((tmp_path / "runs/u/config.json").read_text())
    model = record["train"]["model"]
    assert (model["arch"], model["levels"], model["width_growth"], model["width_cap"]) == ("unet", 3, 2.0, 12)


# --- the whole pipeline ---

@pytest.mark.slow
def test_render_shard_train_denoise_evaluate(tmp_path, monkeypatch, fixture_noisy, fixture_reference, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["-q", "render", "--set", "toy", "--families", "cornell,caustics,outdoor", "--per-family", "2",
                 "--width", "48", "--height", "40", "--input-spp", "4,8", "--reference-spp", "32"]) == 0
    renders = sorted((tmp_path / "data/renders/toy").glob("*.exr"))
    assert len(renders) == 3 * 2 * 3  # families x scenes x (two inputs and the reference)

    assert main(["-q", "shards", "--set", "toy", "--patch-size", "24", "--patches-per-image", "6",
                 "--val-fraction", "0.5"]) == 0
    manifest = json.loads((tmp_path / "shards/toy/manifest.json").read_text())
    assert len(manifest["split"]["val"]) == 3 and not set(manifest["split"]["val"]) & set(manifest["split"]["train"])

    assert main(["-q", "train", "--set", "toy", "--run", "runs/toy", "--steps", "20", "--batch-size", "4",
                 "--width", "8", "--depth", "3", "--kernel-size", "5"]) == 0
    record = json.loads((tmp_path / "runs/toy/config.json").read_text())
    assert record["train"]["steps"] == 20 and set(record["results"]) == {"diffuse", "specular"}

    noisy = next(p for p in renders if p.name.endswith("00004spp.exr"))
    assert main(["-q", "denoise", str(noisy), "--run", "runs/toy", "-o", "out/ours.exr", "--tile", "16", "--png"]) == 0
    assert main(["-q", "denoise", str(fixture_noisy), "--run", "runs/toy", "-o", "out/mitsuba.exr",
                 "--reference", str(fixture_reference), "--png"]) == 0
    for name, shape in (("ours", (40, 48, 3)), ("mitsuba", (64, 64, 3))):
        out = exr.read_aovs(tmp_path / f"out/{name}.exr", variances=False)
        assert out["default"].shape == shape and np.isfinite(out["default"]).all()
        assert (tmp_path / f"out/{name}.png").stat().st_size > 0
    assert "relmse" in capsys.readouterr().out

    assert main(["-q", "evaluate", "--run", "runs/toy"]) == 0
    rows = read_rows(tmp_path / "runs/toy/eval")
    assert sorted((r.scene, r.spp) for r in rows) == sorted((s, n) for s in manifest["split"]["val"] for n in (4, 8))
    assert all(np.isfinite(r.denoised["relmse"]) and np.isfinite(r.nlm["relmse"]) for r in rows)
    assert all(np.isfinite(r.score(k, "relse_p999")) for r in rows for k in ("raw", "denoised", "nlm"))
    report = (tmp_path / "runs/toy/eval/report.md").read_text()
    assert "| scene | input spp | raw relMSE | denoised relMSE | raw relSE p99.9 | denoised relSE p99.9 |" in report
    assert "| NLM relMSE | NLM relSE p99.9 |" in report


def test_the_flags_a_library_hint_spells_are_the_parsers():
    # a run's hint ("train it with 'kpcn shards ...' then 'kpcn train ...'") spells its flags from config, the
    # library not reaching up to the parser: the two must agree
    from kpcn_keras.config import HINT_FLAGS
    from kpcn_keras.parser import _flags, build_parser

    parser = build_parser()
    for command, flags in HINT_FLAGS.items():
        assert {dest: _flags(parser, command).get(dest) for dest in flags} == flags, command
