"""Two halves of one tiny frame: the same smooth image under two independent draws of noise, as two renders of it
with different seeds are (what ``--pair`` and ``--adapt`` take; ``prep.pairs`` sees one frame)."""

from pathlib import Path

import numpy as np

from helpers.tiny import random_aovs


def halves(h: int, w: int, seed: int = 0) -> tuple[dict, dict]:
    """(A, B) in the AOV layout, float32: a smooth clean diffuse and specular times mean-1 gamma noise (shape 2),
    each half its own draw and its own variance layers; albedo, normal and depth shared."""
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    clean = np.stack([0.5 + 0.4 * np.sin(6 * x + c) * np.cos(4 * y) for c in range(3)], -1)
    out = []
    for i in range(2):
        aovs = random_aovs(h, w, seed=seed)  # the same auxiliaries, variance layers redrawn below
        rng = np.random.default_rng(seed * 10 + i + 1)
        aovs["diffuse"] = clean * rng.gamma(2.0, 0.5, (h, w, 3))
        aovs["specular"] = 0.3 * clean * rng.gamma(2.0, 0.5, (h, w, 3))
        aovs["default"] = aovs["diffuse"] + aovs["specular"]
        for name in ("diffuse", "specular", "color", "albedo", "normal", "depth"):
            aovs[f"{name}Variance"] = rng.gamma(0.5, 0.1, (h, w))
        out.append({k: np.asarray(v, np.float32) for k, v in aovs.items()})
    return out[0], out[1]


def write_halves(folder: Path, h: int, w: int, seed: int = 0) -> tuple[Path, Path]:
    """:func:`halves` written as ``a.exr`` and ``b.exr`` in ``folder``."""
    from prep import exr

    paths = folder / "a.exr", folder / "b.exr"
    for path, aovs in zip(paths, halves(h, w, seed)):
        exr.write_aovs(path, aovs)
    return paths
