"""Another renderer's frames as a render set that ``kpcn shards`` cuts: training data from the renderer users denoise.

Every ``<scene>-<spp>spp.exr`` of SRC is read as kpcn reads it for denoising (``prep.layouts``: Blender Cycles,
Mitsuba 3, PBRT-v4, kpcn's own) and written in kpcn's layout (``prep.exr``) as ``<renders>/<set>/<same name>``,
atomically; within a scene the file with the most samples is the reference, as for ``kpcn render``'s sets.
Training needs the diffuse/specular split, so a frame without one is refused. A frame without variance layers
(Cycles writes none) is written without them: such a set is cut with ``--inputs no-variance``, whose patch
PDF then reads each input's error to its reference (``prep.sampling.reference_error_variances``); a set with
variance inputs refuses it, naming the layer.

  .venv/bin/python scripts/import_renders.py SRC --set NAME [--renders data/renders]
  .venv/bin/kpcn shards --set NAME --inputs no-variance [--val-scenes ...]

``scripts/render_cycles_set.py`` renders such frames with Blender (docs/results.md §16). Bad input: one line
naming the file, exit 2; an existing set folder is refused rather than mixed with.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from prep import exr, layouts
from prep.errors import KpcnError
from prep.shards import ShardConfig, discover_renders

WRITTEN = ("default", *exr.BASE_LAYERS)  # the colour as the renderer composed it, and what training reads


def import_renders(src: Path, out: Path) -> list[Path]:
    """Write every render of ``src`` into the new folder ``out`` in kpcn's layout; returns the files written.
    Every file is read and checked before the first is written."""
    if out.exists():
        raise KpcnError(f"{out}: the set folder exists; remove it or choose another --set")
    # the renders kpcn shards would find there: named by scene and spp, each scene with a reference
    paths = sorted(Path(s.path) for scene in discover_renders(Path(src)).values()
                   for s in (*scene["inputs"], scene["reference"]))
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
        print(f"{path.name}: {frame.layout}, {frame.inputs}", flush=True)
    return written


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path, help="folder of another renderer's <scene>-<spp>spp.exr frames")
    ap.add_argument("--set", required=True, dest="set_name", help="render set to write")
    ap.add_argument("--renders", type=Path, default=Path(ShardConfig.render_root), help="folder holding render sets")
    args = ap.parse_args(argv)
    try:
        files = import_renders(args.src, args.renders / args.set_name)
    except KpcnError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{len(files)} renders in {args.renders / args.set_name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
