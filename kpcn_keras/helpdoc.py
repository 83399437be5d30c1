"""The ``--help`` of ``kpcn`` and of every subcommand, written into docs/commands.md so that the page cannot
drift from the parser (``make docs``, or ``python -m kpcn_keras.helpdoc``).

:func:`render` is the text of the page's marked region (between :data:`BEGIN` and :data:`END`), made from
``kpcn_keras.parser.build_parser`` alone; :func:`update` puts it into a page's text, and ``tests/test_docs.py``
checks that the committed page equals what :func:`update` makes of it now. The help is formatted at a fixed
width (:data:`WIDTH`, not the terminal's) and without colour, so the same parser writes the same bytes.
argparse's layout changes between Python minor versions (3.13 stopped repeating a short option's metavar),
so the region names the version it was written with and the test compares only under that version.
"""

from __future__ import annotations

import argparse
import os
import sys
from contextlib import contextmanager
from pathlib import Path

from prep.errors import KpcnError
from prep.files import atomic_write_text

WIDTH = 100  # the columns argparse wraps the help to
BEGIN = "<!-- BEGIN kpcn --help: written by `make docs` (python -m kpcn_keras.helpdoc); do not edit -->"
END = "<!-- END kpcn --help -->"
PAGE = Path(__file__).resolve().parent.parent / "docs" / "commands.md"
# what argparse reads from the environment: the terminal's width, and (Python >= 3.14) whether to colour
_FIXED_ENVIRONMENT = {"COLUMNS": str(WIDTH), "NO_COLOR": "1", "PYTHON_COLORS": "0"}


def python_version() -> str:
    """The Python minor version the help is formatted by, as the region names it (``3.11``)."""
    return f"{sys.version_info.major}.{sys.version_info.minor}"


@contextmanager
def _fixed_terminal():
    saved = {key: os.environ.get(key) for key in _FIXED_ENVIRONMENT}
    os.environ.update(_FIXED_ENVIRONMENT)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def help_texts() -> dict[str, str]:
    """``{"kpcn": its --help, "kpcn <subcommand>": its --help, ...}``, the subcommands in ``kpcn --help``'s
    order, each formatted at :data:`WIDTH` columns."""
    from kpcn_keras.parser import build_parser

    with _fixed_terminal():
        parser = build_parser()
        texts = {"kpcn": parser.format_help()}
        for name, sub in parser.get_default("subcommands").items():
            texts[f"kpcn {name}"] = sub.format_help()
    return texts


def render() -> str:
    """The marked region of docs/commands.md: every ``--help``, markers included."""
    lines = [BEGIN, "", f"Written with Python {python_version()} at {WIDTH} columns.", ""]
    for name, text in help_texts().items():
        lines += [f"### `{name} --help`", "", "```text", text.rstrip(), "```", ""]
    return "\n".join([*lines, END])


def region_version(page_text: str) -> str | None:
    """The Python version the page's region was written with, or None where it names none."""
    start = page_text.find(BEGIN)
    for line in page_text[start:].splitlines()[:4] if start >= 0 else ():
        if line.startswith("Written with Python "):
            return line.split()[3]
    return None


def update(page_text: str, where: str | os.PathLike = PAGE) -> str:
    """``page_text`` with its marked region replaced by :func:`render`'s; KpcnError naming ``where`` if the page
    has no region."""
    start, end = page_text.find(BEGIN), page_text.find(END)
    if start < 0 or end < start:
        raise KpcnError(f"{where}: no region between '{BEGIN}' and '{END}' to write the --help texts into")
    return page_text[:start] + render() + page_text[end + len(END):]


def main(argv: list[str] | None = None) -> int:
    """Write the --help texts into the page (default docs/commands.md); with ``--check``, write nothing and
    return 1 where the page differs from what would be written."""
    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.helpdoc", description=main.__doc__)
    parser.add_argument("--page", type=Path, default=PAGE, help="the page holding the region (default: %(default)s)")
    parser.add_argument("--check", action="store_true", help="only say whether the page is up to date")
    args = parser.parse_args(argv)
    try:
        text = args.page.read_text(encoding="utf-8")
        new = update(text, args.page)
    except (OSError, KpcnError) as exc:
        print(f"kpcn_keras.helpdoc: error: {exc}", file=sys.stderr)
        return 2
    if args.check:
        if new != text:
            print(f"{args.page}: the --help texts differ from the parser's; run 'make docs'", file=sys.stderr)
            return 1
        return 0
    if new != text:
        atomic_write_text(args.page, new)
        print(f"wrote the --help texts into {args.page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
