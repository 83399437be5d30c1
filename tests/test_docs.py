"""The README and docs/: every relative link resolves (file and heading), and the README stays a user's page."""

import re
import unicodedata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_LINES = 200  # issue 21: the README is for users; everything else lives in docs/

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
CODE_SPAN = re.compile(r"`[^`]*`")


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
    assert broken_links(page) == [f"gone.md (no file {tmp_path / 'gone.md'})", "other.md#nope (no heading #nope in other.md)"]


def test_the_readme_is_at_most_200_lines():
    lines = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines; move the rest to docs/"
