"""The configuration of ``kpcn shards`` (:class:`ShardConfig`): its options, checked when it is made, saved in
the manifest and in every shard, and the hash of those that change the shards' content (the set's
configuration, ``config_hash``; with the sources it makes the content key, ``prep.shards.shardset``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from prep.bounds import PATCH_COUNT, SEED, Bound, bounded, check_fields
from prep.errors import OptionError
from prep.files import check_set_name
from prep.render.frame import SPP
from prep.shards.format import patch_bytes

# A shard is assembled in memory before it is written; this bounds that memory.
MAX_SHARD_BYTES = 2 << 30


# A patch is at least the smallest kernel that filters (3x3; models.KERNEL_SIZE) and at most 512 pixels a
# side, eight times the 65 of the papers; train refuses a kernel or receptive field that the set's patches
# do not hold (kpcn_keras.train.check_inputs).
PATCH_SIZE = Bound(3, 512)


@dataclass
class ShardConfig:
    """Configuration of ``kpcn shards``; saved in the manifest and in every shard."""

    set_name: str = "default"
    render_root: str = "data/renders"
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
    command: str = field(default="", compare=False)

    def __post_init__(self):
        self.val_scenes = tuple(self.val_scenes)
        check_set_name(self.set_name)
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
        return Path(self.render_root) / self.set_name

    @property
    def set_dir(self) -> Path:
        return Path(self.out_root) / self.set_name

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def content_hash(self) -> str:
        """Hash of the options that change the shards' content (not where files are, nor the command)."""
        d = self.to_dict()
        for location in ("command", "out_root", "render_root"):
            d.pop(location)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]
