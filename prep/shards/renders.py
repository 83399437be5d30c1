"""The sources of a shard set: finding the renders of a folder (:func:`discover_renders`), splitting their
scenes into training and validation (:func:`split_scenes`), and checking them against the options.

**Bad input is found before anything is written** (:func:`find_sources`): every render's header (layers,
size) and the options against every image are checked first, and each error names the file or the option.
Each source's record in the manifest carries the render's SHA-256, so that the set knows what it was cut
from and a rerun whose renders changed is told what changed (:func:`source_changes`).
"""

from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from prep import exr
from prep.errors import OptionError
from prep.files import sha256_file
from prep.render.cycles import catalogue
from prep.shards.config import PATCH_SIZE, ShardConfig
from prep.shards.format import ShardError
from prep.shards.patches import noisy_variances
from prep.shards.shardset import SPLITS, ShardSet


@dataclass(frozen=True)
class Source:
    scene: str
    spp: int
    path: str


def discover_renders(render_dir: Path, input_spp: int | None = None, leave_out=()) -> dict[str, dict]:
    """``scene -> {"reference": Source, "inputs": [Source, ...]}`` for a folder of renders.

    Within a scene the file with the most samples is the reference; ``input_spp`` keeps only inputs of
    that sample count; the scenes named in ``leave_out`` are not looked at. Dot-files (temporaries) are
    ignored, and so are the halves of a pair (``kpcn render --pair``: their mean is an input, not either one).
    Errors name the folder or the scene.
    """
    if not render_dir.is_dir():
        raise ShardError(f"{render_dir}: no such render folder (run 'kpcn render' first)")
    by_scene: dict[str, list[Source]] = defaultdict(list)
    for path in sorted(render_dir.glob("*.exr")):
        if path.name.startswith(".") or catalogue().pair_half(path.name):  # a half of a pair: no shard input
            continue
        scene, spp = exr.parse_render_filename(path)
        if scene in leave_out:
            continue
        by_scene[scene].append(Source(scene, spp, str(path)))
    if not by_scene:
        raise ShardError(f"{render_dir}: no '<scene>-<spp>spp.exr' renders found")
    out = {}
    for scene, sources in sorted(by_scene.items()):
        sources.sort(key=lambda s: s.spp)
        if len(sources) < 2:
            raise ShardError(
                f"{render_dir}: scene {scene!r} has only {Path(sources[0].path).name}; "
                "it needs a noisy input and a reference with more samples"
            )
        inputs = sources[:-1]
        if input_spp is not None:
            inputs = [s for s in inputs if s.spp == input_spp]
            if not inputs:
                raise ShardError(
                    f"{render_dir}: scene {scene!r} has no input at {input_spp} spp; "
                    f"found {[s.spp for s in sources]}"
                )
        out[scene] = {"reference": sources[-1], "inputs": inputs}
    return out


def split_scenes(scenes: list[str], val_fraction: float, val_scenes: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """Train/validation split by scene, never by patch.

    Explicit ``val_scenes`` win. Otherwise scenes are grouped by family (the name without its trailing
    ``-<index>``) and the last ``round(val_fraction * n)`` of each sorted group are held out, at least
    one scene overall when there are two or more and val_fraction > 0.
    """
    scenes = sorted(scenes)
    if val_scenes:
        unknown = sorted(set(val_scenes) - set(scenes))
        if unknown:
            raise ShardError(f"val_scenes {unknown} are not among the renders' scenes {scenes}")
        val = sorted(set(val_scenes))
    else:
        families: dict[str, list[str]] = defaultdict(list)
        for s in scenes:
            families[re.sub(r"-\d+$", "", s)].append(s)
        val = []
        for members in families.values():
            val += members[len(members) - int(round(val_fraction * len(members))):] if val_fraction else []
        if not val and val_fraction > 0 and len(scenes) >= 2:
            val = [scenes[-1]]
    train = [s for s in scenes if s not in val]
    if not train:
        raise ShardError(f"no training scene left after holding out {val}")
    return {"train": train, "val": sorted(val)}


def find_sources(config: ShardConfig, sset: ShardSet) -> tuple[dict[str, list[str]], list[dict],
                                                              list[tuple[str, int, int]]]:
    """Find the renders of ``config``, check every header and the options against every image, fix the
    split and the source ids: returns the split, the sources' manifest records (a source's id is its index)
    and the patches each input gives round 0 as (split, source id, patches), in order. Raises (naming the
    file or option) before any writing."""
    renders = discover_renders(config.render_dir, config.input_spp)
    split = split_scenes(list(renders), config.val_fraction, config.val_scenes)
    p = config.patch_size
    sources: list[dict] = []
    streams: list[tuple[str, int, int]] = []
    for split_name in SPLITS:
        for scene in split[split_name]:
            ref = renders[scene]["reference"]
            ref_size = exr.read_header(ref.path, variances=False)
            sources.append(_source_record(sset, ref, "reference", split_name, 0))
            for src in renders[scene]["inputs"]:
                # a render without variance layers is refused here, naming the layer, unless the set's input
                # set has no variance
                size = exr.read_header(src.path, variances=noisy_variances(config.input_set))
                if size != ref_size:
                    raise ShardError(
                        f"{src.path} is {size[1]}x{size[0]} but its reference {ref.path} is {ref_size[1]}x{ref_size[0]}"
                    )
                if min(size) < p:
                    smaller = (f"use --patch-size {min(size)} or less, or remove the render"
                               if min(size) >= PATCH_SIZE.low else
                               f"the smallest patch is {PATCH_SIZE.low}x{PATCH_SIZE.low}: remove the render")
                    raise ShardError(f"{src.path} is {size[1]}x{size[0]}, smaller than a {p}x{p} patch; {smaller}")
                positions = (size[0] - p + 1) * (size[1] - p + 1)
                if config.patches_per_image > positions:
                    raise OptionError(
                        "patches_per_image",
                        f"{config.patches_per_image} exceeds the {positions} distinct {p}x{p} patch positions of "
                        f"{src.path} ({size[1]}x{size[0]}); patches are drawn without replacement",
                    )
                streams.append((split_name, len(sources), config.patches_per_image))
                sources.append(_source_record(sset, src, "input", split_name, config.patches_per_image))
    return split, sources, streams


def _source_record(sset: ShardSet, src: Source, role: str, split: str, patches: int) -> dict:
    return {"scene": src.scene, "spp": src.spp, "path": sset.relative(src.path), "role": role, "split": split,
            "patches": patches, "sha256": sha256_file(src.path)}


def source_changes(old: list[dict], new: list[dict]) -> str:
    """What differs between two source lists, for the message that explains a rebuild."""
    def index(sources):
        return {(s["scene"], s["spp"]): s for s in sources}

    a, b = index(old), index(new)
    parts = []
    for label, names in (
        ("added", sorted(set(b) - set(a))),
        ("removed", sorted(set(a) - set(b))),
        ("changed", sorted(k for k in set(a) & set(b)
                           if (a[k]["sha256"], a[k]["split"]) != (b[k]["sha256"], b[k]["split"]))),
    ):
        if names:
            parts.append(f"{label} " + ", ".join(f"{scene} ({spp} spp)" for scene, spp in names))
    return "; ".join(parts) or "the patches per source changed"


def reference_of(sources: list[dict], src: dict) -> dict:
    return next(s for s in sources if s["scene"] == src["scene"] and s["role"] == "reference")
