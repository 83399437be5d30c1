"""``kpcn --version``: kpcn's version and the model ``kpcn denoise`` uses without --run, what a program driving
kpcn (the Blender add-on's Check button) shows to say which kpcn it found."""

from __future__ import annotations


def version_text() -> str:
    """Two lines: ``kpcn <version>``, then ``model <folder> (quality modes: ...)`` or why there is none."""
    from importlib.metadata import PackageNotFoundError, version

    from kpcn_keras.run import default_model  # here: the model's modes need the run (keras), --help does not
    from prep.errors import KpcnError

    try:
        number = version("kpcn")
    except PackageNotFoundError:
        number = "(not installed as a package)"
    try:
        model = default_model()
        found = f"model {model.dir} (quality modes: {', '.join(model.quality_modes())})"
    except KpcnError as exc:
        found = f"no model: {exc}"
    return f"kpcn {number}\n{found}"
