"""The README and docs/: every relative link resolves (file and heading), every docs page the code cites
exists with the section cited, and the README stays a user's page."""

import re
import unicodedata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_LINES = 200  # issue 21: the README is for users; everything else lives in docs/

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
CODE_SPAN = re.compile(r"`[^`]*`")
# a citation in the code: "docs/method.md §8", "docs/method.md §6, §7", "docs/training.md"
CITATION = re.compile(r"docs/([\w-]+\.md)((?:[,;]? ?§\d+)*)")
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


def test_the_readme_is_at_most_200_lines():
    lines = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines; move the rest to docs/"


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
