import json
import math
import sys

import pytest
from helpers.tiny import make_renders

from kpcn_keras.studies import data_costs
from prep import exr, shards


@pytest.fixture
def renders(tmp_path):
    return make_renders(tmp_path / "renders" / "s", scenes=("a-000", "b-000"))


def pairs(root):
    return [(str(root / exr.render_filename(scene, 4)), str(root / exr.render_filename(scene, 64)))
            for scene in ("a-000", "b-000")]


def finite_positive(d, keys):
    for key in keys:
        assert isinstance(d[key], (int, float)) and math.isfinite(d[key]) and d[key] > 0, (key, d[key])


def test_feature_costs_time_decode_numba_and_the_numpy_reference(renders):
    got = data_costs.feature_costs(renders / exr.render_filename("a-000", 4), repeats=2)
    json.dumps(got)
    assert got["pixels"] == 40 * 44
    finite_positive(got, ["exr_decode_s", "numba_s", "numpy_s", "numba_pixels_per_s", "numpy_over_numba",
                          "numba_over_decode"])
    assert got["numpy_over_numba"] == pytest.approx(got["numpy_s"] / got["numba_s"])
    assert got["numba_over_decode"] == pytest.approx(got["numba_s"] / got["exr_decode_s"])
    assert got["numba_pixels_per_s"] == pytest.approx(2 * 40 * 44 / got["numba_s"])


def test_every_layout_is_measured_and_reads_back_what_was_written(tmp_path, renders):
    out = tmp_path / "costs"
    got = data_costs.shard_layout_costs(pairs(renders), out, patches_per_image=5, batch_size=3, repeats=2,
                                         patch_size=16)
    json.dumps(got)
    assert got["default"] == shards.SHARD_LAYOUT.name and got["default"] in got["layouts"]
    assert set(got["layouts"]) == set(shards.LAYOUTS) and got["patches"] == 10
    for name, row in got["layouts"].items():
        finite_positive(row, ["write_patches_per_s", "bytes_per_patch", "read_batch_s"])
        if shards.LAYOUTS[name].dtype is None:  # the table's dtypes, which the cut patches have
            assert row["exact"] and row["max_abs_error"] == 0.0, name
        else:  # float16 rounds to 11 significant bits
            assert not row["exact"] and 0.0 < row["max_rel_error"] <= 2.0**-11, name
    # a shard holds at least its raw bytes unless it is compressed; float16 halves the table's float32 ones
    raw = shards.patch_bytes(16)
    assert got["layouts"]["none"]["bytes_per_patch"] >= raw
    float32 = sum(16 * 16 * d.channels * 4 for d in shards.DATASETS.values() if d.dtype == "float32")
    assert got["layouts"]["float16"]["bytes_per_patch"] < got["layouts"]["none"]["bytes_per_patch"] - 0.45 * float32
    assert not out.exists()


def test_layout_costs_leave_an_existing_folder_as_it_was_and_refuse_unknown_layouts(tmp_path, renders):
    out = tmp_path / "scratch"
    out.mkdir()
    (out / "keep").write_text("x")
    data_costs.shard_layout_costs(pairs(renders)[:1], out, patches_per_image=2, batch_size=2, repeats=1,
                                   patch_size=16, layouts=["none"])
    assert [p.name for p in out.iterdir()] == ["keep"]
    with pytest.raises(ValueError, match="'zstd'"):
        data_costs.shard_layout_costs(pairs(renders), out, layouts=["zstd"], patch_size=16)
    with pytest.raises(ValueError, match="repeats"):
        data_costs.shard_layout_costs(pairs(renders), out, repeats=0, patch_size=16)
    assert [p.name for p in out.iterdir()] == ["keep"]


@pytest.mark.slow
def test_no_deep_learning_import():
    import subprocess

    code = ("import sys; import kpcn_keras.studies.data_costs; "
            "print(sorted(m for m in ('torch', 'keras') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    assert res.stdout.strip() == "[]"
