"""The configuration of ``kpcn shards`` (:class:`ShardConfig`): its options, checked when it is made, saved in
the manifest and in every shard, and the hash of those that change the shards' content (the set's
configuration, ``config_hash``; with the sources it makes the content key, ``prep.shards.shardset``).

A set is cut for one input set (``inputs``, ``prep.inputs``): its patches hold what a model of that set reads
(``prep.shards.patches.shard_layers``). Its folder is :func:`shard_set_dir`: ``<out_root>/<set>`` for the full
set, ``<out_root>/<set>.<inputs>`` for the others, all cut from the same renders (``<render_root>/<set>``). A
full configuration's dict, and so its hash, is the one from before input sets existed (no ``inputs`` key):
every set cut before is still the set this code cuts.

A set's patches hold the auxiliaries of ``auxiliaries`` (``prep.auxiliary.TRAINED``: ``raw``, as rendered, or
prefiltered by ``oidn`` or ``nlm``, each noisy input's whole frame once before its patches are cut; the
reference as it is). A prefiltered set is another set, of its own folder, ``<set>[.<inputs>].aux-<method>``
(:func:`shard_set_dir`), so that it is cut beside the raw set of the same renders rather than refused over it
(the raw set, and the runs trained on it, stay as they are). A raw configuration's dict has no ``auxiliaries``
key (:func:`without_defaults`): every set cut before is still the set this code cuts, byte for byte.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from prep.auxiliary import RAW, TRAINED
from prep.bounds import PATCH_COUNT, SEED, Bound, bounded, check_fields
from prep.errors import OptionError
from prep.files import check_set_name
from prep.inputs import FULL, InputSet
from prep.render.frame import SPP
from prep.render.renderset import RENDER_ROOT, RenderSet
from prep.shards.format import patch_bytes

# A shard is assembled in memory before it is written; this bounds that memory.
MAX_SHARD_BYTES = 2 << 30


# A patch is at least the smallest kernel that filters (3x3; models.KERNEL_SIZE) and at most 512 pixels a
# side, eight times the 65 of the papers; train refuses a kernel or receptive field that the set's patches
# do not hold (kpcn_keras.train.check_inputs).
PATCH_SIZE = Bound(3, 512)


def shard_set_dir(out_root: str | Path, set_name: str, inputs: str, auxiliaries: str = RAW) -> Path:
    """The folder of the shard set ``set_name`` cut for the input set ``inputs`` (a name of
    ``prep.inputs.INPUT_SETS``) with the auxiliaries ``auxiliaries`` (``prep.auxiliary.TRAINED``): the one rule,
    for ``kpcn shards`` and for ``kpcn train``."""
    name = set_name if inputs == FULL.name else f"{set_name}.{inputs}"
    return Path(out_root) / (name if auxiliaries == RAW else f"{name}.aux-{auxiliaries}")


def without_full_inputs(d: dict) -> dict:
    """``d`` (a configuration's dict) without its ``inputs`` where that is the full set: the dict of a full
    configuration is the one written before input sets existed, so its hashes (a shard set's, a run's) and
    records are unchanged."""
    if d.get("inputs") == FULL.name:
        d.pop("inputs")
    return d


def without_defaults(d: dict) -> dict:
    """``d`` (a shard or train configuration's dict) without the fields added since the first sets and runs that
    hold the value those were made with (``inputs`` full, ``auxiliaries`` raw), so that their hashes and
    records are unchanged."""
    if d.get("auxiliaries") == RAW:
        d.pop("auxiliaries")
    return without_full_inputs(d)


@dataclass
class ShardConfig:
    """Configuration of ``kpcn shards``; saved in the manifest and in every shard."""

    set_name: str = "default"
    render_root: str = RENDER_ROOT
    out_root: str = "shards"
    patch_size: int = bounded(65, PATCH_SIZE)
    patches_per_image: int = bounded(32, PATCH_COUNT)  # per input render: a ladder of three inputs gives 96 per scene
    patches_per_shard: int = bounded(256, PATCH_COUNT)
    val_fraction: float = bounded(0.25, Bound(0.0, 1.0, integer=False, high_open=True))
    val_scenes: tuple[str, ...] = bounded((), distinct=True)
    input_spp: int | None = bounded(None, SPP)
    colour_weight: float = 1.0
    normal_weight: float = 1.0
    # > 0: every position can be drawn, so the plan's check of patches_per_image against the positions of
    # each image is complete (with 0, an image without variance has none)
    uniform_mix: float = bounded(0.1, Bound(0.0, 1.0, integer=False, low_open=True))
    seed: int = bounded(0, SEED)
    inputs: str = FULL.name  # what the set's patches hold (prep.inputs.INPUT_SETS)
    auxiliaries: str = RAW  # the auxiliaries the patches hold (prep.auxiliary.TRAINED)
    command: str = field(default="", compare=False)

    def __post_init__(self):
        self.val_scenes = tuple(self.val_scenes)
        check_set_name(self.set_name)
        InputSet.named(self.inputs)
        if self.auxiliaries not in TRAINED:  # pyoidn is checked where it runs (build_shards), not where it is read
            raise OptionError("auxiliaries", f"must be one of {', '.join(TRAINED)}, got {self.auxiliaries!r}")
        check_fields(self)
        if self.colour_weight < 0 or self.normal_weight < 0 or self.colour_weight + self.normal_weight <= 0:
            raise OptionError("colour_weight", f"and normal_weight must be >= 0 and not both 0, got "
                              f"{self.colour_weight} and {self.normal_weight}")
        shard_bytes = self.patches_per_shard * patch_bytes(self.patch_size)
        if shard_bytes > MAX_SHARD_BYTES:
            most = MAX_SHARD_BYTES // patch_bytes(self.patch_size)
            raise OptionError(
                "patches_per_shard",
                f"{self.patches_per_shard} would hold {shard_bytes / 2**30:.1f} GiB in memory per shard; "
                f"at patch size {self.patch_size} at most {most} fit in {MAX_SHARD_BYTES >> 30} GiB",
            )

    @property
    def render_dir(self) -> Path:
        return RenderSet(self.set_name, self.render_root).dir

    @property
    def input_set(self) -> InputSet:
        return InputSet.named(self.inputs)

    @property
    def set_dir(self) -> Path:
        return shard_set_dir(self.out_root, self.set_name, self.inputs, self.auxiliaries)

    def to_dict(self) -> dict:
        return without_defaults(dataclasses.asdict(self))

    def content_hash(self) -> str:
        """Hash of the options that change the shards' content (not where files are, nor the command)."""
        d = self.to_dict()
        for location in ("command", "out_root", "render_root"):
            d.pop(location)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]
