"""Malformed OpenEXR and PNG files through every reader of their format (``helpers.malformed``): each read gives
a result (finite, of the size the file states) or a ``KpcnError`` of one line naming the file; never another
exception, a warning, a second of CPU, more memory than the limit the child runs under, or output of its own.
One child process per format, under limits; the families and their counts: ``python -m tests.helpers.malformed --count``
(docs/robustness.md §6). Below them, the reader faults the fuzzing found, one test each."""

import json
import re
import struct
import subprocess
import sys

import numpy as np
import pytest
from helpers import malformed
from helpers.paths import REPO

from prep.errors import KpcnError

MAX_MESSAGE = 2000  # characters: one line a terminal shows in a screen


@pytest.fixture(scope="module")
def fuzz_results(tmp_path_factory) -> dict[str, list[dict]]:
    """family -> its rows: one child per format runs its families (a child's start, the readers' libraries
    imported, costs more than a family's reads)."""
    rows = []
    for families in (malformed.EXR_FAMILIES, malformed.PNG_FAMILIES):
        tmp = tmp_path_factory.mktemp("fuzz")
        out, work = tmp / "results.jsonl", tmp / "cases"
        work.mkdir()
        done = subprocess.run([sys.executable, str(REPO / "tests" / "helpers" / "malformed.py"), "--check",
                               ",".join(families), "--out", str(out), "--workdir", str(work)],
                              capture_output=True, text=True, timeout=300, cwd=REPO)
        assert done.returncode == 0, f"the child of {families} ended with {done.returncode}: {done.stderr[-2000:]}"
        # the readers print nothing of their own (the library's messages are folded into the one error)
        assert done.stdout == "" and done.stderr == "", (done.stdout[-1000:], done.stderr[-1000:])
        rows += [json.loads(line) for line in out.read_text().splitlines()]
    by_family = {}
    for row in rows:
        by_family.setdefault(row["family"], []).append(row)
    return by_family


def _is_cut(row: dict) -> bool:
    """A file cut short of its pixels: a reader of pixels must refuse it, not read what is left."""
    return row["family"] == "exr-truncated" or (
        row["family"] == "exr-multipart" and row["case"].startswith(("part-", "offsets-", "chunks-")))


def _faults(row: dict) -> list[str]:
    faults = []
    name = row["path"].rsplit("/", 1)[-1]
    if row["outcome"] == "result" and row["reader"] != "layouts.read_header" and _is_cut(row):
        faults.append("read a file cut short of its pixels")
    if row["outcome"] == "other":
        faults.append(f"raised {row['message']}")
    elif row["outcome"] == "result" and row["message"]:
        faults.append(f"returned a result with {row['message']}")
    elif row["outcome"] == "kpcn-error":
        message = row["message"]
        if "\n" in message or not message.strip() or len(message) > MAX_MESSAGE or name not in message:
            faults.append(f"message of {len(message)} characters, not one line naming the file: {message[:200]!r}")
    if row["cpu"] > malformed.CPU_LIMIT_S:
        faults.append(f"took {row['cpu']:.2f} s of CPU")
    if row["warnings"]:
        faults.append(f"warned {row['warnings']}")
    return [f"{row['case']} / {row['reader']}: {f}" for f in faults]


@pytest.mark.parametrize("family", malformed.EXR_FAMILIES + malformed.PNG_FAMILIES)
def test_every_malformed_file_gets_a_result_or_one_line(family, fuzz_results):
    rows = fuzz_results[family]
    assert {r["case"] for r in rows} == {c.name for c in malformed.cases(family)}
    faults = [f for row in rows for f in _faults(row)]
    assert not faults, f"{len(faults)} of {len(rows)} reads:\n" + "\n".join(faults[:40])


def test_the_families_are_the_same_files_on_every_run():
    for family in malformed.EXR_FAMILIES + malformed.PNG_FAMILIES:
        first, again = malformed.cases(family), malformed.cases(family)
        assert [(c.name, c.data) for c in first] == [(c.name, c.data) for c in again]
        assert len({c.name for c in first}) == len(first), f"{family} names two cases alike"


def test_the_cases_are_what_their_names_say():
    """A few cases read back with an independent parser: the fuzzing probes what the table says it probes."""
    header = {c.name: c.data for c in malformed.cases("exr-header")}
    parsed, _ = malformed.parse_exr(header["kpcn-window-negative-width"])
    x0, _, x1, _ = struct.unpack("<4i", parsed.get("dataWindow"))
    assert x1 < x0
    assert header["mitsuba-channels-5000"].count(b".R\0") == 5000
    huge = dict(malformed.png_huge())["30000x30000"]
    assert len(huge) < 100 and struct.unpack(">II", huge[16:24]) == (30000, 30000)
    cut = {c.name: c.data for c in malformed.cases("exr-truncated")}
    assert all(len(data) < len(malformed.EXR_BASES[name.split("-")[0]].read_bytes()) for name, data in cut.items())


# --- the faults the fuzzing found, one test each -----------------------------------------------------------------

def _write(tmp_path, family: str, case: str):
    data = next(c for c in malformed.cases(family) if c.name == case)
    path = tmp_path / f"{case}{data.suffix}"
    path.write_bytes(data.data)
    return path


def test_a_header_of_thousands_of_channels_is_refused_before_its_pixels(tmp_path):
    from prep import exr, layouts

    path = _write(tmp_path, "exr-header", "mitsuba-channels-5000")
    with pytest.raises(exr.AOVError, match=r"lists 5000 channels, more than the 4096") as caught:
        exr.read_image(path)
    assert str(path) in str(caught.value)
    for read in (layouts.read_header, layouts.read):
        with pytest.raises(exr.AOVError) as caught:
            read(path)
        assert len(str(caught.value)) < MAX_MESSAGE


def test_a_refusal_lists_at_most_forty_layers(tmp_path):
    from helpers.exr_layouts import write_channels

    from prep import layouts
    from prep.exr import AOVError

    path = write_channels(tmp_path / "many.exr", {f"pass{i:03d}.Q": np.zeros((2, 2), np.float32) for i in range(100)})
    with pytest.raises(AOVError, match=r"pass039, and 60 more$|pass039 and 60 more$") as caught:
        layouts.read_header(path)
    assert "pass040" not in str(caught.value)


def test_a_multipart_file_cut_short_is_refused_not_read_without_its_last_parts(tmp_path):
    from prep import exr, layouts

    path = tmp_path / "studio-00016spp.exr"
    path.write_bytes(malformed.EXR_MULTIPART.read_bytes()[:200_000])  # parts 0-5 whole, 6-18 cut away
    with pytest.raises(exr.AOVError, match=r"channels its header lists could not be read .*cut short") as caught:
        exr.read_image(path)
    assert str(caught.value).startswith(f"{path}: ") and "\n" not in str(caught.value)
    with pytest.raises(exr.AOVError, match="could not be read"):
        layouts.read(path)
    assert layouts.read_header(path).size == (64, 64)  # the header alone is whole


def test_a_data_window_beyond_memory_is_refused_before_the_binding_allocates_it(tmp_path):
    from prep import exr

    path = _write(tmp_path, "exr-header", "kpcn-window-beyond-memory")
    for header_only in (True, False):
        with pytest.raises(exr.AOVError, match=r"268435457x64 data window of \d+ channels needs [\d.]+ GiB, more "
                                               r"than the [\d.]+ GiB this machine has available"):
            exr.read_image(path, header_only=header_only)


@pytest.mark.parametrize("case", ["grey16-ihdr-short", "rgb8-ihdr-short", "grey16-chunk-length-huge",
                                  "grey16-IDAT-crc", "grey16-IEND-crc"])
def test_a_damaged_png_is_refused_in_one_line_by_both_readers(case, tmp_path):
    from kpcn_keras import slope_map
    from prep.errors import InputFileError
    from prep.render.environment import load_texels
    from prep.render.scene import EnvironmentMap

    family = "png-crc" if "crc" in case else "png-header"
    path = _write(tmp_path, family, case)
    with pytest.raises(KpcnError, match=r"^" + str(path).replace(".", r"\.") + ": ") as caught:
        slope_map.read(path, malformed.PNG_SHAPE, (0.25, 4.0))
    assert "\n" not in str(caught.value)
    with pytest.raises(InputFileError, match=r"^" + str(path).replace(".", r"\.") + ": "):
        load_texels(EnvironmentMap(image=str(path)))


def test_png_cut_in_its_last_chunk_is_refused(tmp_path):
    from prep.png import PngError, check

    data = malformed.png_bases()["rgb8"]
    assert check(_bytes(tmp_path, data)) == (12, 8)
    with pytest.raises(PngError, match="cut short"):
        check(_bytes(tmp_path, data[:-3]))


def _bytes(tmp_path, data: bytes):
    path = tmp_path / "map.png"
    path.write_bytes(data)
    return path


def test_an_environment_map_or_texture_png_beyond_the_pixel_limit_is_refused_in_one_line(tmp_path):
    from PIL import Image

    from prep.errors import InputFileError
    from prep.render.environment import load_texels
    from prep.render.scene import EnvironmentMap

    for size, data in malformed.png_huge():
        path = _bytes(tmp_path, data)
        w, h = (int(v) for v in size.split("x"))
        if w * h <= Image.MAX_IMAGE_PIXELS:
            continue
        with pytest.raises(InputFileError, match=rf"^{path}: a PNG of {w} x {h} pixels, more than the "
                                                 rf"{Image.MAX_IMAGE_PIXELS} kpcn decodes from a PNG"):
            load_texels(EnvironmentMap(image=str(path)))


@pytest.mark.skipif(malformed.SCALE != 1, reason="the table states the counts CI runs, at KPCN_FUZZ_SCALE=1")
def test_the_table_of_probe_families_states_the_counts_ci_runs():
    table = (REPO / "docs" / "robustness.md").read_text().split("## 6 Probe families")[1]
    stated = {m[0]: int(m[1]) for m in re.findall(r"^\| `([\w-]+)` \|.*?\| (\d+) \|[^|]*\|$", table, re.M)}
    assert stated == {f: len(malformed.cases(f)) for f in malformed.EXR_FAMILIES + malformed.PNG_FAMILIES}
