"""kpcn_keras/studies/report.py: the one writer of the studies' reports and the envelope each report carries."""

import json
import os
import platform

import pytest

from kpcn_keras.studies.report import Report, machine_record
from prep.errors import KpcnError
from prep.files import pyplot


def _figure(record):
    fig, ax = pyplot().subplots(figsize=(2, 2))
    ax.plot(record["values"])
    return fig


def test_a_report_writes_the_json_the_markdown_and_the_figure_with_the_envelope_first(tmp_path):
    report = Report(tmp_path / "out", "study")
    report.check_writable()
    session = report.begin()
    record = {**session.envelope("kpcn study --seed 1"), "config": {"seed": 1}, "machine": session.machine(x=2),
              "values": [1.0, float("inf")]}
    written = report.write(record, "# the study\n", _figure, plain=lambda r: {**r, "values": [1.0, "inf"]})

    assert written is record
    assert list(record)[:4] == ["date", "command", "started", "finished"]
    assert record["command"] == "kpcn study --seed 1" and record["started"] <= record["finished"]
    text = (tmp_path / "out/study.json").read_text()
    assert text == json.dumps({**record, "values": [1.0, "inf"]}, indent=2) + "\n"
    assert (tmp_path / "out/study.md").read_text() == "# the study\n"
    assert (tmp_path / "out/study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["study.json", "study.md", "study.png"]


def test_the_machine_record_puts_the_studys_stack_between_the_platform_and_the_load():
    got = machine_record((0.5, 0.25, 0.125), torch="2.x", torch_threads=3)
    assert list(got) == ["cpus", "platform", "python", "torch", "torch_threads", "load_average_before",
                         "load_average_after"]
    assert got["cpus"] == os.cpu_count() and got["python"] == platform.python_version()
    assert got["load_average_before"] == [0.5, 0.25, 0.125] and len(got["load_average_after"]) == 3


def test_a_report_without_a_figure_writes_no_png(tmp_path):
    (tmp_path / "render.png").mkdir()  # in the way of a png, which this report does not write
    report = Report(tmp_path, "render", png=False)
    report.check_writable()
    report.write({"config": {}}, "md\n", _figure)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["render.json", "render.md", "render.png"]
    assert (tmp_path / "render.png").is_dir()


def test_a_report_file_that_cannot_be_written_is_refused_before_any_work(tmp_path):
    (tmp_path / "study.md").mkdir()
    with pytest.raises(KpcnError, match=r"report \(--out\) .*study\.md: is a folder"):
        Report(tmp_path, "study").check_writable()
