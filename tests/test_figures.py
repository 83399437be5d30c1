"""`kpcn figures`: what it writes, and what it never writes over; the data figures (Fig. 3, Fig. 4) checked
value by value against what the shard set records and a float64 recomputation here."""

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.files import checksums
from helpers.references import reference_importance, reference_log_colour, reference_pdf
from helpers.tiny import build_tiny_shards, random_aovs

from kpcn_keras.cli import main
from kpcn_keras.run import Run
from prep import exr, features
from prep.figures import data_plan, input_panels, inputs_figure, sampling_figure, sampling_panels
from prep.files import pyplot


def test_figures_never_write_over_a_file_they_read(tiny_run, tmp_path, capsys):
    exr.write_aovs(tmp_path / "x-00004spp.exr", random_aovs(16, 16))
    exr.write_aovs(tmp_path / "x-00064spp.exr", random_aovs(16, 16, variances=False))
    figures = Run(tiny_run).figures_dir
    figures.mkdir(exist_ok=True)
    kernels = figures / "kernels.png"
    os.link(tmp_path / "x-00004spp.exr", kernels)  # the kernel figure's file is the input under another name
    try:
        before = checksums(tmp_path)
        assert main(["-q", "figures", "--run", str(tiny_run), str(tmp_path / "x-00004spp.exr")]) == 2
        err = capsys.readouterr().err
        assert f"figure {kernels} is the input file {tmp_path}/x-00004spp.exr itself" in err, err
        assert checksums(tmp_path) == before and kernels.read_bytes() == (tmp_path / "x-00004spp.exr").read_bytes()
    finally:
        kernels.unlink()


# --- the data figures: Fig. 3 (sampling) and Fig. 4 (network inputs) of a shard set ---

P = 16  # build_tiny_shards' patch size


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    """A tiny shard set (build_tiny_shards) and its ShardConfig."""
    return build_tiny_shards(tmp_path_factory.mktemp("figures"))


def _sources(cfg) -> tuple[list[dict], int]:
    """The set's sources and the index of the render the data figures default to, found from the manifest here:
    the held-out input of the first scene, then the lowest spp."""
    sources = json.loads((cfg.set_dir / "manifest.json").read_text())["sources"]
    held_out = [i for i, s in enumerate(sources) if s["role"] == "input" and s["split"] == "val"]
    return sources, min(held_out, key=lambda i: (sources[i]["scene"], sources[i]["spp"]))


def _recorded(cfg, source: int) -> tuple[np.ndarray, np.ndarray]:
    """(positions, pdf) of ``source``'s patches, read straight from the round-0 shard files with h5py."""
    positions, pdf = [], []
    for path in sorted((cfg.set_dir / "round-000").glob("shard-*.h5")):
        with h5py.File(path, "r") as f:
            mine = f["source"][:] == source
            positions.append(f["position"][:][mine])
            pdf.append(f["pdf"][:][mine])
    return np.concatenate(positions), np.concatenate(pdf)


def test_the_sampling_figure_draws_the_variance_pdf_and_the_patches_the_set_cut(tiny_set):
    sources, source = _sources(tiny_set)
    plan = data_plan(tiny_set.set_dir)
    assert plan.source == source
    panels = sampling_panels(plan)
    render = tiny_set.set_dir / sources[source]["path"]
    assert panels.frame == render.name
    # the PDF of docs/method.md §3, in float64 numpy here: importance summed over each window, 10 % uniform
    want = reference_pdf(reference_importance(exr.read_aovs(render)), P, tiny_set.uniform_mix)
    assert panels.pdf.shape == want.shape == (40 - P + 1, 44 - P + 1)
    y, x = np.unravel_index(np.argmax(want), want.shape)
    assert panels.pdf[y, x] == pytest.approx(want[y, x], rel=1e-12)  # the likeliest position
    assert panels.pdf[0, 0] == pytest.approx(want[0, 0], rel=1e-12)
    np.testing.assert_allclose(panels.pdf, want, rtol=1e-12, atol=0)
    # the boxes are the positions the shards recorded for this render, in the shards' order
    positions, pdf = _recorded(tiny_set, source)
    assert len(positions) == tiny_set.patches_per_image
    np.testing.assert_array_equal(panels.positions, positions)
    np.testing.assert_allclose(want[positions[:, 0], positions[:, 1]], pdf, rtol=1e-12)

    fig = sampling_figure(panels)
    try:
        pdf_panel, patches_panel, overlay = fig.axes[:3]
        drawn = pdf_panel.images[0]
        np.testing.assert_array_equal(np.asarray(drawn.get_array()), panels.pdf)
        r = P // 2  # the PDF at top-left (y, x) is drawn over the patch's centre pixel
        assert drawn.get_extent() == [r - 0.5, r + want.shape[1] - 0.5, r + want.shape[0] - 0.5, r - 0.5]
        assert overlay.images[1].get_extent() == drawn.get_extent()
        for ax in (patches_panel, overlay):
            boxes = sorted((b.get_y() + 0.5, b.get_x() + 0.5, b.get_width(), b.get_height()) for b in ax.patches)
            assert boxes == sorted((float(py), float(px), float(P), float(P)) for py, px in positions)
        assert len(fig.axes) == 4  # the three panels and the PDF's colourbar
    finally:
        pyplot().close(fig)


def test_the_inputs_figure_draws_the_likeliest_patch_as_training_reads_it(tiny_set):
    sources, source = _sources(tiny_set)
    plan = data_plan(tiny_set.set_dir)
    panels = input_panels(plan)
    positions, pdf = _recorded(tiny_set, source)
    y, x = positions[np.argmax(pdf)]
    assert panels.position == (y, x)
    noisy = exr.read_aovs(tiny_set.set_dir / sources[source]["path"])
    reference = next(s for s in sources if s["role"] == "reference" and s["scene"] == sources[source]["scene"])
    ref = exr.read_aovs(tiny_set.set_dir / reference["path"], variances=False)
    for branch, albedo in (("diffuse", noisy["albedo"]), ("specular", None)):
        groups = panels.branches[branch]
        # the log colour of the render and its forward differences, in float64 here, over the patch and the next
        # row and column: the shard's float16 buffers are within 2**-11 of each value
        c = reference_log_colour(noisy[branch], albedo)[y : y + P + 1, x : x + P + 1]
        bound = 2.0**-10 * max(1.0, float(np.abs(c).max()))
        np.testing.assert_allclose(groups["colour"], c[:P, :P], rtol=2.0**-11, atol=2.0**-25, err_msg=branch)
        np.testing.assert_allclose(groups["dx_colour"], c[:P, 1:] - c[:P, :P], rtol=0, atol=bound, err_msg=branch)
        np.testing.assert_allclose(groups["dy_colour"], c[1:, :P] - c[:P, :P], rtol=0, atol=bound, err_msg=branch)
        ref_albedo = None if albedo is None else ref["albedo"]
        want_ref = reference_log_colour(ref[branch], ref_albedo)[y : y + P, x : x + P]
        np.testing.assert_allclose(groups["reference"], want_ref, rtol=1e-6, atol=1e-7, err_msg=branch)
        d = np.maximum(noisy["depth"].astype(np.float64), 0.0) / noisy["depth"].max()
        want_dy = d[y + 1 : y + P + 1, x : x + P] - d[y : y + P, x : x + P]
        np.testing.assert_allclose(groups["dy_depth"][..., 0], want_dy, rtol=0, atol=2.0**-10, err_msg=branch)
        assert all(v.shape[:2] == (P, P) for v in groups.values())

    fig = inputs_figure(panels)
    try:
        titles = [[ax.get_title() for ax in fig.axes[row * 14 : (row + 1) * 14]] for row in range(2)]
        # Jow's Fig. 4: the colour, the x- and y-gradients of colour, normal, albedo, depth, the relative
        # variances of the four, then the reference
        want = ["colour"] + [f"{d}_{b}" for d in ("dx", "dy") for b in ("colour", "normal", "albedo", "depth")] + \
            [f"relvar_{b}" for b in ("colour", "normal", "albedo", "depth")] + ["reference"]
        assert titles == [want, want] and len(fig.axes) == 28
        assert set(want) - {"colour", "reference"} <= {n.split(".")[0] for n in features.FEATURE_NAMES}
        assert [fig.axes[0].get_ylabel(), fig.axes[14].get_ylabel()] == list(features.BRANCHES)
        dy_depth = fig.axes[8].images[0]
        np.testing.assert_array_equal(np.asarray(dy_depth.get_array()), panels.branches["diffuse"]["dy_depth"][..., 0])
    finally:
        pyplot().close(fig)


def test_kpcn_figures_set_draws_both_data_figures_of_a_shard_set_the_same_each_time(tiny_set, tmp_path):
    root = tiny_set.out_root
    res = run_main("figures", "--set", "s", "--shards", root, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    figures = tiny_set.set_dir / "figures"
    assert res.stdout.splitlines() == [f"sampling: {figures / 'sampling.png'}", f"inputs: {figures / 'inputs.png'}"]
    first = {name: (figures / name).read_bytes() for name in ("sampling.png", "inputs.png")}
    assert all(b.startswith(b"\x89PNG") for b in first.values())
    # a render of the set given by name: the same one as the default here; the same bytes again
    sources, source = _sources(tiny_set)
    render = tiny_set.set_dir / sources[source]["path"]
    assert run_main("figures", "--set", "s", "--shards", root, render, cwd=tmp_path).returncode == 0
    assert {name: (figures / name).read_bytes() for name in first} == first


def test_kpcn_figures_refuses_a_bad_shard_set_option_in_one_line(tiny_set, tmp_path):
    root = tiny_set.out_root
    assert_one_line_error(run_main("figures", "--set", "nope", "--shards", root, cwd=tmp_path),
                          "kpcn figures: error: --set 'nope' names no shard set", f"{root}/nope has no manifest.json",
                          "its shard sets: s")
    exr.write_aovs(tmp_path / "x-00004spp.exr", random_aovs(16, 16))
    sources, source = _sources(tiny_set)
    outside = tmp_path / "x-00004spp.exr"
    assert_one_line_error(run_main("figures", "--set", "s", "--shards", root, outside, cwd=tmp_path),
                          "error: input ", "x-00004spp.exr is not an input render of the shard set",
                          f"(its inputs: {Path(sources[source]['path']).name}, ")
    assert_one_line_error(run_main("figures", "--set", "s", "--shards", root, "--tile", "64", cwd=tmp_path),
                          "--tile is an option of a run's figures: it needs --run")
    assert_one_line_error(run_main("figures", "--run", "r", "--set", "s", cwd=tmp_path),
                          "--set is for the figures of a shard set alone")
    assert_one_line_error(run_main("figures", cwd=tmp_path), "give --run RUN", "or --set NAME")


def test_a_runs_figures_draw_its_shard_sets_data_figures_and_skip_them_without_the_set(tiny_run, tmp_path):
    # the run with its shard set and renders, where its record finds them (relative to the run folder)
    root = shutil.copytree(Path(tiny_run).parents[1], tmp_path / "root")
    run = root / Path(tiny_run).relative_to(Path(tiny_run).parents[1])
    res = run_main("figures", "--run", run, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert {"sampling", "inputs", "kernels"} <= {line.split(":")[0] for line in res.stdout.splitlines()}
    # the run's held-out frame is the set's default render: the figures of the set alone are the same bytes
    assert run_main("figures", "--set", "s", "--shards", root / "shards", cwd=tmp_path).returncode == 0
    for name in ("sampling.png", "inputs.png"):
        assert (run / "figures" / name).read_bytes() == (root / "shards" / "s" / "figures" / name).read_bytes()
    # without its shard set (a shipped model) a run still draws the figures of its networks
    alone = shutil.copytree(run, tmp_path / "a" / "b" / "alone")  # its record's set: tmp_path/a/shards/s
    shutil.rmtree(alone / "figures")
    noisy = next((root / "renders" / "s").glob("*-00004spp.exr"))
    res = run_main("figures", "--run", alone, noisy, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (alone / "figures").iterdir()) == ["kernels.png"]
