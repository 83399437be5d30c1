"""A frame's two halves for kpcn's adaptation, without bpy: the samples and Cycles seeds of each of the two
renders of half the samples that ``kpcn denoise A --pair B --adapt S`` takes (docs/adapt.md).

The rule is ``kpcn blend-pair``'s (prep/render/blender/catalogue.half_seeds, the owner of the pairs' names and
seeds): the add-on imports nothing of kpcn, so it holds a copy, which tests/test_blender_addon.py holds equal."""

# The halves' files in the add-on's temporary folder: kpcn reads each half's samples from Cycles' header
NAMES = ("render-a.exr", "render-b.exr")


def half_seeds(seed: int) -> tuple:
    """Cycles' seeds of the two halves of a frame rendered with ``seed``: 2**28 and 2**29 above it (mod 2**31),
    so each is other than the other's and than the frame's own."""
    return tuple((seed + k * 2**28) % 2**31 for k in (1, 2))


def half_samples(samples: int) -> int:
    """Each half's samples: half the frame's. ValueError, in one line, for an odd count or one below 4 (each half
    renders 2 or more, the whole frame's samples between them, as kpcn blend-pair requires)."""
    if samples < 4 or samples % 2:
        raise ValueError(f"a pair renders the frame as two halves of half its samples: the scene's render samples "
                         f"must be even and 4 or more, got {samples}")
    return samples // 2
