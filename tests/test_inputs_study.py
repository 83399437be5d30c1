"""``kpcn inputs-study`` at toy size: a run per input set, the held-out table, and other renderers' frames
each served by its model, with the raw input's scores a float64 computation of its own."""

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.exr_layouts import cycles_channels, parts_of, write_channels
from helpers.tiny import TINY_MODEL, build_tiny_shards

from kpcn_keras.studies.config import InputsStudyConfig
from prep import layouts
from prep.errors import OptionError
from prep.inputs import INPUT_SETS

RENDERERS = Path(__file__).parent / "fixtures" / "renderers"


def test_the_study_refuses_no_frames_and_an_unknown_preset():
    with pytest.raises(OptionError, match="frames must name at least one file or folder"):
        InputsStudyConfig(frames=())
    with pytest.raises(OptionError, match="preset must be one of"):
        InputsStudyConfig(preset="huge")


@pytest.mark.slow
def test_the_study_trains_every_input_set_and_serves_each_renderers_frame_by_its_model(tmp_path):
    from kpcn_keras.studies.inputs_study import study

    full = build_tiny_shards(tmp_path)
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    a, b = (cycles_channels(12, 10, seed=1, noise_seed=s) for s in (1, 2))  # two renders of one frame
    write_channels(pairs / "p-00004spp-pair-a.exr", a, parts_of(a))  # the halves of an 8-spp frame
    write_channels(pairs / "p-00004spp-pair-b.exr", b, parts_of(b))
    reference = cycles_channels(12, 10, seed=3)
    write_channels(pairs / "p-00256spp.exr", {k: v for k, v in reference.items() if ".Combined." in k})
    cfg = InputsStudyConfig(set_name="s", render_root=full.render_root, shards_root=full.out_root,
                            runs_root=str(tmp_path / "runs"), out_dir=str(tmp_path / "reports"), budget=0.5,
                            frames=(str(RENDERERS / "cycles5"), str(RENDERERS / "mitsuba3"), str(RENDERERS / "pbrt4")),
                            pairs=(str(pairs),))
    record = study(cfg, overrides={"model": TINY_MODEL, "batch_size": 2, "val_batches": 1}, log=lambda *_: None,
                   verbose=0)
    saved = json.loads((tmp_path / "reports" / "inputs.json").read_text())
    assert saved["held_out"]["means"].keys() >= set(INPUT_SETS) | {"raw"}
    for inputs in INPUT_SETS:
        assert record["plans"][inputs]["run"].endswith("run" if inputs == "full" else f"run/inputs/{inputs}")
    served = {(r["renderer"], r["scene"]): (r["layout"], r["inputs"], r["model"]) for r in record["renderers"]}
    assert served == {("cycles5", "studio"): ("cycles", "no-variance", "no-variance"),
                      ("mitsuba3", "cornell"): ("mitsuba", "no-split", "no-split"),
                      ("pbrt4", "cornell"): ("pbrt", "no-split", "no-split")}
    row = next(r for r in record["renderers"] if r["renderer"] == "cycles5")
    x = layouts.read(RENDERERS / "cycles5" / "studio-00016spp.exr").layers["default"].astype(np.float64)
    ref = layouts.read(RENDERERS / "cycles5" / "studio-00256spp.exr").layers["default"].astype(np.float64)
    assert row["raw"]["relmse"] == pytest.approx(np.mean((x - ref) ** 2 / (ref ** 2 + 0.01)), rel=1e-6)
    (pair,) = record["pairs"]
    assert (pair["spp"], pair["without_model"], pair["pair_model"]) == (8, "no-variance", "full")
    mean = np.stack([(a[f"ViewLayer.Combined.{c}"].astype(np.float64) + b[f"ViewLayer.Combined.{c}"]) / 2
                     for c in "RGB"], axis=-1)
    r = np.stack([reference[f"ViewLayer.Combined.{c}"].astype(np.float64) for c in "RGB"], axis=-1)
    assert pair["raw"]["relmse"] == pytest.approx(np.mean((mean - r) ** 2 / (r ** 2 + 0.01)), rel=1e-6)
    report = (tmp_path / "reports" / "inputs.md").read_text()
    assert "The pair's variance lowers relMSE on " in report
    for inputs in INPUT_SETS:
        assert f"| {inputs} | " in report
    assert (tmp_path / "reports" / "inputs.png").stat().st_size > 0
