"""The README and docs/: every relative link resolves (file and heading), every docs page the code cites
exists with the section cited, the README stays a user's page whose figures are its JSON's, the results
are one page per entry, and docs/commands.md holds the --help texts the parser prints now."""

import os
import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
RESULTS = ROOT / "docs" / "results"
# the README is for users, read in five minutes; everything else lives in docs/
README_MAX_WORDS, README_MAX_WIDTH = 1200, 120

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
CODE_SPAN = re.compile(r"`[^`]*`")
# a citation in the code: "docs/method.md §8", "docs/method.md §6, §7", "docs/training.md",
# "docs/results/10-quality-levers.md §10d"
CITATION = re.compile(r"docs/([\w/-]+\.md)((?:[,;]? ?§\d+)*)")
# a citation of a page the repository never held, or of the report's sections without a docs page
UNFINDABLE = re.compile(r"(?<!docs/)\bdesign\.md|seed report §")
CODE_DIRS = ("prep", "kpcn_keras", "tests", "reports")


def prose(text: str) -> list[str]:
    """The lines of a markdown page outside fenced code blocks, inline code spans removed."""
    lines, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(CODE_SPAN.sub(lambda m: m.group(0).replace("[", "").replace("]", ""), line))
    return lines


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (letters, digits, '-', '_' and spaces
    kept), spaces to hyphens."""
    text = heading.strip().lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    return {anchor(line.lstrip("#")) for line in prose(page.read_text(encoding="utf-8")) if line.startswith("#")}


def relative_links(page: Path) -> list[str]:
    return [target for line in prose(page.read_text(encoding="utf-8")) for target in LINK.findall(line)
            if not re.match(r"[a-z][a-z0-9+.-]*:", target)]


def broken_links(page: Path) -> list[str]:
    broken = []
    for target in relative_links(page):
        path, _, fragment = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.exists():
            broken.append(f"{target} (no file {resolved})")
        elif fragment and resolved.suffix == ".md" and fragment not in anchors(resolved):
            broken.append(f"{target} (no heading #{fragment} in {resolved.name})")
    return broken


def test_every_relative_link_of_the_readme_and_docs_resolves_to_a_file_and_heading():
    assert len(PAGES) > 1, "docs/*.md not found"
    assert sum(len(relative_links(p)) for p in PAGES) > 0
    broken = {p.relative_to(ROOT).as_posix(): b for p in PAGES if (b := broken_links(p))}
    assert not broken, broken


def test_a_link_to_a_missing_file_or_heading_is_found(tmp_path):
    (tmp_path / "other.md").write_text("# Title\n\n## 2 Some heading: `code` (2026-11-26)\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#2-some-heading-code-2026-11-26) [file](gone.md) [head](other.md#nope)\n"
                    "```\n[in code](gone-too.md)\n```\n`[span](gone-three.md)` [web](https://example.com/x)\n")
    assert broken_links(page) == [f"gone.md (no file {tmp_path / 'gone.md'})",
                                  "other.md#nope (no heading #nope in other.md)"]


def test_the_readme_is_short_and_narrow():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    words = len(text.split())
    assert words <= README_MAX_WORDS, f"README.md has {words} words; move the rest to docs/"
    wide = [i for i, line in enumerate(text.splitlines(), 1) if len(line) > README_MAX_WIDTH]
    assert not wide, f"README.md lines over {README_MAX_WIDTH} characters: {wide}"


def code_files():
    this = Path(__file__).resolve()  # its own examples of what it refuses
    return [f for d in CODE_DIRS for f in sorted((ROOT / d).rglob("*"))
            if f.suffix in (".py", ".md") and f.is_file() and f.resolve() != this]


def cited_sections(text: str) -> list[tuple[str, str]]:
    """(page, section number) of every docs citation in ``text``; section "" for a whole page."""
    found = []
    for page, sections in CITATION.findall(text):
        found += [(page, n) for n in re.findall(r"\d+", sections)] or [(page, "")]
    return found


def numbered_sections(page: Path) -> set[str]:
    return {m.group(1) for line in prose(page.read_text(encoding="utf-8")) if (m := re.match(r"#+ (\d+) ", line))}


def test_every_docs_page_and_section_the_code_cites_exists():
    cited = {}
    for f in code_files():
        for page, section in cited_sections(f.read_text(encoding="utf-8")):
            cited.setdefault((page, section), []).append(f.relative_to(ROOT).as_posix())
    assert cited
    missing = {f"docs/{page} §{section}": where for (page, section), where in cited.items()
               if not (ROOT / "docs" / page).exists()
               or (section and section not in numbered_sections(ROOT / "docs" / page))}
    assert not missing, missing
    stale = [f"{f.relative_to(ROOT).as_posix()}:{i}" for f in code_files()
             for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1) if UNFINDABLE.search(line)]
    assert not stale, f"cite docs/design.md or docs/method.md instead: {stale}"


def test_a_citation_names_each_section_it_cites():
    assert cited_sections("(docs/method.md §6, §7; docs/training.md) and docs/formats.md §5.") == [
        ("method.md", "6"), ("method.md", "7"), ("training.md", ""), ("formats.md", "5")]
    assert UNFINDABLE.search('of design.md "Measuring"') and UNFINDABLE.search("(seed report §3.3.2)")
    assert not UNFINDABLE.search("docs/design.md §3") and not UNFINDABLE.search("(seed report Fig. 2)")


def test_every_test_file_and_test_the_docs_name_exists():
    text = "\n".join(p.read_text(encoding="utf-8") for p in PAGES)
    files = set(re.findall(r"\btests/[\w/]+\.py\b", text))
    names = set(re.findall(r"\b(test_\w+)\b(?!\.py)", text))
    assert files and names
    defined = set()
    for f in (ROOT / "tests").rglob("*.py"):
        defined |= set(re.findall(r"^\s*def (test_\w+)\(", f.read_text(encoding="utf-8"), re.M))
    missing = sorted(f for f in files if not (ROOT / f).exists()) + sorted(names - defined)
    assert not missing, f"the docs name tests that do not exist (renamed?): {missing}"


def test_the_results_index_links_every_entry_once_in_order_and_each_page_is_its_numbered_entry():
    pages = sorted(p.name for p in RESULTS.glob("[0-9][0-9]-*.md"))
    assert len(pages) >= 21
    linked = [t for t in relative_links(RESULTS / "README.md") if re.fullmatch(r"\d\d-[\w-]+\.md", t)]
    assert linked == pages
    for name in pages:
        first = (RESULTS / name).read_text(encoding="utf-8").splitlines()[0]
        assert re.match(rf"# {int(name[:2])} \S", first), f"{name} starts with {first!r}"


def test_nothing_cites_the_single_results_page_the_entries_were_split_from():
    # "results.md", or "results §17" other than as the text of a link to its page
    old = re.compile(r"\bresults\.md\b|\bresults §\d+(?![^\s\]]*\]\()")
    files = [*PAGES, *code_files(), ROOT / "Makefile", *sorted((ROOT / "scripts").rglob("*.py")),
             *sorted((ROOT / "models").rglob("*.md"))]
    stale = [f"{f.relative_to(ROOT).as_posix()}:{i}" for f in files if f.is_file()
             for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1) if old.search(line)]
    assert not stale, f"cite a page of docs/results/ instead: {stale}"


def test_the_commands_page_holds_the_help_texts_the_parser_prints_now():
    from kpcn_keras import helpdoc

    text = helpdoc.PAGE.read_text(encoding="utf-8")
    version = helpdoc.region_version(text)
    assert version, f"{helpdoc.PAGE} names no Python version in its --help region"
    if version != helpdoc.python_version():
        pytest.skip(f"the --help texts were written with Python {version}, whose argparse lays them out otherwise")
    assert text == helpdoc.update(text), "docs/commands.md §4 is not what the parser prints now: run 'make docs'"


def test_the_help_texts_are_every_subcommand_s_at_a_width_the_terminal_does_not_change(monkeypatch):
    from kpcn_keras import helpdoc
    from kpcn_keras.parser import build_parser

    monkeypatch.setenv("COLUMNS", "40")
    narrow = helpdoc.render()
    monkeypatch.setenv("COLUMNS", "250")
    assert helpdoc.render() == narrow and os.environ["COLUMNS"] == "250"
    names = ["kpcn", *(f"kpcn {name}" for name in build_parser().get_default("subcommands"))]
    assert re.findall(r"^### `(.+) --help`$", narrow, re.M) == names


def test_a_page_without_the_help_region_is_refused_naming_it(tmp_path, capsys):
    from kpcn_keras import helpdoc

    page = tmp_path / "commands.md"
    page.write_text("# Commands\n")
    assert helpdoc.main(["--page", str(page)]) == 2
    assert f"{page}: no region" in capsys.readouterr().err and page.read_text() == "# Commands\n"
    page.write_text(f"# Commands\n\n{helpdoc.BEGIN}\nold\n{helpdoc.END}\n")
    assert helpdoc.main(["--page", str(page), "--check"]) == 1
    assert helpdoc.main(["--page", str(page)]) == 0 and helpdoc.main(["--page", str(page), "--check"]) == 0
    assert page.read_text() == f"# Commands\n\n{helpdoc.render()}\n"


# the README's results table and the JSON it names for it (the command that writes it is named beside it)
RESULTS_JSON = "reports/blender.json"
SHIPPED = "models/default"
README_MODES = ("high", "balanced", "Blender's")  # the rows of each spp in the README's results table


def readme_section(title: str) -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return text.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def table_rows(text: str) -> list[list[str]]:
    """The body rows of the markdown tables in ``text``: each table's header and ``|---|`` line left out."""
    lines = [line for line in text.splitlines() if line.startswith("|")]
    rule = [bool(re.fullmatch(r"\|(---\|)+", line)) for line in lines]
    return [[c.strip() for c in line.strip("|").split("|")] for i, line in enumerate(lines)
            if not rule[i] and not (i + 1 < len(lines) and rule[i + 1])]


def results_rows(record: dict) -> dict[tuple[str, str], list[str]]:
    """The README's results rows computed from the Blender report's frames: per spp and per shown quality mode of
    the shipped model (and Blender's own frame) the mean relMSE and DSSIM, the frames below Blender's and below the
    better of every OIDN mode and quality scored, and the median ratio to Blender's; keyed by (spp, mode)."""
    from statistics import mean, median

    name = next(name for name, path in record["models"].items() if path == SHIPPED)
    rows = {}
    for spp in sorted({f["spp"] for f in record["frames"]}):
        frames = [f["scores"] for f in record["frames"] if f["spp"] == spp]
        for mode in README_MODES:
            method = "blender" if mode == "Blender's" else f"kpcn {name} {mode}"
            means = [f"{mean(f[method][score] for f in frames):.4f}" for score in ("relmse", "dssim")]
            if method == "blender":
                rows[(str(spp), mode)] = [str(spp), mode, *means, "", "", ""]
                continue
            better = [min(v["relmse"] for k, v in f.items() if k.startswith("oidn")) for f in frames]
            below_blender = sum(f[method]["relmse"] < f["blender"]["relmse"] for f in frames)
            below_oidn = sum(f[method]["relmse"] < b for f, b in zip(frames, better))
            ratio = median(f[method]["relmse"] / f["blender"]["relmse"] for f in frames)
            rows[(str(spp), mode)] = [str(spp), mode, *means, f"{below_blender} of {len(frames)}",
                                      f"{below_oidn} of {len(frames)}", f"{ratio:.2f}×"]
    return rows


def test_every_figure_of_the_readme_results_table_is_the_json_it_names():
    import json

    section = readme_section("Results")
    assert f"`{RESULTS_JSON}`" in section and "make blender-report" in section
    shown = table_rows(section)
    assert shown, "no results table in the README"
    computed = results_rows(json.loads((ROOT / RESULTS_JSON).read_text(encoding="utf-8")))
    assert {(row[0], row[1]) for row in shown} == set(computed), "the README's rows are not the JSON's spp and modes"
    for row in shown:
        key = (row[0], row[1])
        assert row == computed[key], f"README row {row} is not {RESULTS_JSON}'s {computed[key]}"


# The living pages (docs/results/ holds the dated records, the README and the card are checked above): a
# measured figure there names the committed JSON a command wrote it into, or links the dated page that printed it.
LIVING_PAGES = [*(ROOT / "docs" / f"{name}.md" for name in
                  ("denoise", "training", "scenes", "formats", "method", "robustness", "design", "commands",
                   "onnx")),
                ROOT / "shards" / "README.md"]
# a number and a unit of time, memory, throughput, or a ratio ("1.28×", "4x"; "65 × 65" is a size, not a ratio)
MEASURED = re.compile(r"(?<![\w.,/-])\d[\d,]*(?:\.\d+)?\s?(?:(?:ms|min|minutes?|seconds?|hours?|s|h"
                      r"|kB|KiB|MB|MiB|GB|GiB|steps/s|samples/s|patches/s)(?![\w/])|[×x](?!\s?\d)(?!\w))")
SOURCED = re.compile(r"\.json\b|\]\((?:\.\./)*(?:docs/)?results/[^)]*\)")
# figures that are not measurements: what the code holds or a study is given, each with where it is defined
NOT_MEASURED = re.compile("|".join((
    r"25 MiB",  # kpcn_keras.config.SHIPPED_MAX_BYTES, the bound on a shipped model's folder
    r"64 kB tmpfs",  # the size of the full disk the robustness tests mount
    # a patch's bytes and 100,000 patches': prep.shards.patch_bytes(65), and v2_patch_bytes(65) of the old format
    r"375 kB|1\.27 MB|37\.5 GB|127 GB",
    r"\bat (?:`[^`]+`'s )?\d+ s\b",  # a study's --budget, the seconds it is given
    r"30 minutes",  # the time `make train` is to fit in, a target
)))


def sentences(text: str) -> list[str]:
    """The page's sentences, bullets and table rows: fenced code line by line, the --help region left out (the
    parser writes it), a paragraph split at each full stop that ends a sentence."""
    from kpcn_keras import helpdoc

    if helpdoc.BEGIN in text:
        text = text.split(helpdoc.BEGIN, 1)[0] + text.split(helpdoc.END, 1)[1]
    units, block, fenced = [], [], False
    for line in [*text.splitlines(), ""]:
        fence = line.lstrip().startswith("```")
        row = fenced or fence or line.lstrip().startswith(("|", "#"))
        if row or not line.strip() or re.match(r"\s*(?:[-*]|\d+\.) ", line):
            units += re.split(r"(?<=\.)\s+(?=[A-Z(`*\[])", " ".join(block))
            block = []
        (units.append if row else block.append)(line)
        fenced ^= fence
    return [u for u in units if u.strip()]


def unsourced_figures(text: str) -> list[str]:
    """Each measured figure of ``text`` in a sentence that neither names a JSON file nor links docs/results/."""
    return [f"{m.group(0)!r} in: {unit.strip()[:160]}" for unit in sentences(text) if not SOURCED.search(unit)
            for m in MEASURED.finditer(NOT_MEASURED.sub("", unit))]


def test_every_measured_figure_of_a_living_page_names_its_json_or_its_dated_page():
    assert all(p.exists() for p in LIVING_PAGES), [p for p in LIVING_PAGES if not p.exists()]
    found = {p.relative_to(ROOT).as_posix(): f for p in LIVING_PAGES if (f := unsourced_figures(p.read_text("utf-8")))}
    assert not found, found


def test_a_planted_figure_without_its_source_is_found():
    # a sentence naming a JSON sources its own figures, not its paragraph's
    page = ("The card's frame takes 3.39 s (`speed.json`). Denoising a 1080p frame takes 3.2 s on 2 cores. "
            "The network is 1.28× slower (2026-12-03).\n\n"
            "- It takes 3.39 s (`models/default/speed.json`, `kpcn ship`).\n"
            "- Found in [results](results/11-painted-slope-map.md): 1.5 GB held.\n\n"
            "| 256 × 256 tiles | 91 ms |\n\nA shipped model is refused above 25 MiB, at 300 s a lever.\n\n"
            "```sh\nkpcn denoise f.exr --ensemble 4   # about 4x the time\n```\n")
    assert [f.split(" in: ")[0] for f in unsourced_figures(page)] == ["'3.2 s'", "'1.28×'", "'91 ms'", "'4x'"]
    denoise = (ROOT / "docs" / "denoise.md").read_text(encoding="utf-8")
    assert not unsourced_figures(denoise)
    assert unsourced_figures(denoise + "\nA 1080p frame takes 9.9 s here.\n")
