"""``kpcn import-renders``: another renderer's frames as a render set that ``kpcn shards`` cuts, training data from
the renderer users denoise.

Every ``<scene>-<spp>spp.exr`` of SRC is read as kpcn reads it for denoising (``prep.layouts``: Blender Cycles,
Mitsuba 3, PBRT-v4, kpcn's own) and written in kpcn's layout (``prep.exr``) into the render set
(:class:`~prep.render.renderset.RenderSet`, ``<renders>/<set>/<same name>``), atomically; within a scene the file
with the most samples is the reference, as for ``kpcn render``'s sets. Training needs the diffuse/specular split,
so a frame without one is refused. In a folder that ``kpcn render-cycles`` is still filling, a scene whose recipe
(``<scene>.json``) lists a frame not yet there is left out and said so: its frame with the most samples so far is no
reference. A frame without variance layers (Cycles writes none) is written without them:
such a set is cut with ``--inputs no-variance``, whose patch PDF then reads each input's error to its reference
(``prep.sampling.reference_error_variances``); a set with variance inputs refuses it, naming the layer.

  kpcn import-renders SRC --set NAME [--renders data/renders]
  kpcn shards --set NAME --inputs no-variance [--val-scenes ...]

``kpcn render-cycles`` renders such frames with Blender (docs/results/16-cycles-frames.md). Bad input: a KpcnError
naming the file; an existing set folder is refused rather than mixed with, and every file is read and checked before
the first is written.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from prep import exr, layouts
from prep.errors import KpcnError
from prep.render.cycles import catalogue
from prep.render.renderset import RenderSet
from prep.shards.renders import discover_renders

WRITTEN = ("default", *exr.BASE_LAYERS)  # the colour as the renderer composed it, and what training reads


def import_renders(src: str | Path, render_set: RenderSet, on_frame: Callable[[str], object] = print) -> list[Path]:
    """Write every render of ``src`` into the new folder of ``render_set`` in kpcn's layout; returns the files
    written. ``on_frame`` is told each file's name, layout and inputs as it is written."""
    out = render_set.dir
    if not Path(src).is_dir():  # before the render folder's own check, whose hint is kpcn render's
        raise KpcnError(f"{src}: no such folder of renders to import")
    if out.exists():
        raise KpcnError(f"{out}: the set folder exists; remove it or choose another --set")
    # the renders kpcn shards would find there: named by scene and spp, each scene with a reference
    unfinished = unfinished_scenes(src)
    for name in unfinished:
        on_frame(f"{name}: left out, its recipe lists frames not rendered yet")
    scenes = discover_renders(Path(src), leave_out=unfinished)
    paths = sorted(Path(s.path) for scene in scenes.values() for s in (*scene["inputs"], scene["reference"]))
    for path in paths:
        header = layouts.read_header(path)
        if not header.inputs.split:
            raise KpcnError(f"{path}: a {header.layout} frame without a diffuse/specular split; training needs it")
    out.mkdir(parents=True)
    written = []
    for path in paths:
        frame = layouts.read(path)
        keep = WRITTEN + (exr.VARIANCE_LAYERS if frame.inputs.variance else ())
        written.append(exr.write_aovs(out / path.name, {name: frame.layers[name] for name in keep}))
        on_frame(f"{path.name}: {frame.layout}, {frame.inputs}")
    return written


def unfinished_scenes(src: str | Path) -> list[str]:
    """The scenes of a ``kpcn render-cycles`` folder whose recipe lists a frame that is not there (yet)."""
    return [name for name, finished in _scenes(src) if not finished]


def finished_scenes(src: str | Path) -> list[str]:
    """The scenes of a ``kpcn render-cycles`` folder with every frame their recipe lists."""
    return [name for name, finished in _scenes(src) if finished]


def _scenes(src: str | Path) -> list[tuple[str, bool]]:
    """Each recipe's scene of ``src`` and whether every frame it lists is there."""
    cat = catalogue()
    return [(r["name"], all((Path(src) / cat.frame_name(r["name"], spp)).is_file() for spp in r.get("frames", [])))
            for r in _recipes(src)]


def _recipes(src: str | Path) -> list:
    """The scene recipes (``<scene>.json``) of ``src``; KpcnError naming a JSON file there it cannot read."""
    try:
        return catalogue().read_recipes(str(src))
    except (OSError, ValueError):
        for path in sorted(Path(src).glob("*.json")):
            try:
                json.loads(path.read_text())
            except (OSError, ValueError) as e:
                raise KpcnError(f"{path}: not readable JSON ({e}); a scene recipe must be") from None
        raise
