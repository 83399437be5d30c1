"""The one writer of the studies' reports, and the envelope each report carries.

A study's report is ``<out_dir>/<stem>.json`` (every number), ``<stem>.md`` (what a reader reads) and, where
the study draws one, ``<stem>.png``, each written atomically (``prep.files``), in that order. A study:

1. checks before any work that it can write them (:meth:`Report.check_writable`: a report folder it cannot
   write fails first, not after an hour of training);
2. starts the clock (:meth:`Report.begin`: the time and the load average before the work);
3. heads its record with :meth:`Session.envelope` (``date``, ``command``, ``started``, ``finished``) and puts
   :meth:`Session.machine` (the CPUs, the platform, Python, what the study's own stack adds, the load
   average before and after) under ``machine``;
4. hands the record, its markdown and its figure to :meth:`Report.write`.

The record's other fields, and their order, are the study's own. Only prep and the standard library (and
matplotlib, through ``prep.files``): the studies of prep and of kpcn_keras write through it alike.
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import date, datetime
from pathlib import Path

from prep.files import atomic_write_text, check_writable, save_png


def now() -> str:
    """The time of day a report records, to the second."""
    return datetime.now().isoformat(timespec="seconds")


def machine_record(load_before, **stack) -> dict:
    """Where a report was measured: the CPUs, the platform, Python, then ``stack`` (what the study's own
    libraries add: versions, thread counts), and the load average before the work and now."""
    return {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(), **stack,
            "load_average_before": list(load_before), "load_average_after": list(os.getloadavg())}


@dataclass(frozen=True)
class Session:
    """One run of a study: when it started and the load average then (:meth:`Report.begin`)."""

    started: str = field(default_factory=now)
    load_before: tuple = field(default_factory=os.getloadavg)

    def envelope(self, command: str | None) -> dict:
        """The head of a record: the day, the command that asked, when the work started and finished."""
        return {"date": date.today().isoformat(), "command": command, "started": self.started, "finished": now()}

    def machine(self, **stack) -> dict:
        """:func:`machine_record` of this session."""
        return machine_record(self.load_before, **stack)


@dataclass(frozen=True)
class Report:
    """The files of one study's report: ``<out_dir>/<stem>`` + ``.json``, ``.md`` and, with ``png``, ``.png``."""

    out_dir: Path
    stem: str
    png: bool = True

    def path(self, suffix: str) -> Path:
        return Path(self.out_dir) / f"{self.stem}{suffix}"

    def check_writable(self, suffixes=(".md", ".json", ".png")) -> None:
        """Refuse (a KpcnError naming the file and ``--out``) a report file that cannot be written."""
        for suffix in suffixes:
            if suffix != ".png" or self.png:
                check_writable(self.path(suffix), "report (--out)")

    @staticmethod
    def begin() -> Session:
        return Session()

    def write(self, record: dict, markdown: str, figure: Callable[[dict], object] | None = None, *,
              plain: Callable[[dict], object] = lambda record: record) -> dict:
        """Write ``plain(record)`` as the json (indented by 2, one newline at the end), ``markdown`` as the
        md and ``figure(record)`` (a matplotlib figure) as the png; returns ``record``."""
        atomic_write_text(self.path(".json"), json.dumps(plain(record), indent=2) + "\n")
        self.write_text(record, markdown, figure)
        return record

    def write_text(self, record: dict, markdown: str, figure: Callable[[dict], object] | None = None) -> None:
        """The md and the png alone, from a record already written (a report written again)."""
        atomic_write_text(self.path(".md"), markdown)
        if self.png and figure is not None:
            save_png(figure(record), self.path(".png"))
