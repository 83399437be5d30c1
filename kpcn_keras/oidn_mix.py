"""A model's frame mixed with OIDN's: the networks' denoised colour averaged, pixel by pixel, with Intel Open Image
Denoise's of the same render, at a weight fit on frames (``kpcn mix-oidn``). The ``high`` quality mode is served so.

Why: two denoisers whose errors differ average to less error than either (an ensemble of denoisers; Zheng et al.,
"Ensemble Denoising for Monte Carlo Renderings", SIGGRAPH Asia 2021, learn the weights per pixel; one weight per
network is the least of it). On Cycles frames kpcn's networks and OIDN err in different places (a kernel of 13
pixels against a U-Net's hundreds), and their mean is below either: docs/results/29-quality-modes-shipped.md.

- **What is mixed**: ``default = w * networks + (1 - w) * OIDN`` in float64, stored float32; ``w`` is the weight of
  the networks' frame. OIDN runs as Blender runs it (:data:`OIDN_MODE` prefiltered, at :data:`OIDN_QUALITY`) on the
  layers a renderer hands its own denoiser where the frame has them (``prep.baselines.oidn_inputs``: Cycles'
  Denoising Albedo and Normal), which a denoiser is given as ``Frame.served_layers`` names them.
  ``diffuse`` and ``specular`` stay the networks' (OIDN denoises the colour alone).
- **Tiles**: OIDN sees the whole frame and the networks' frame is assembled from its tiles as always, so a frame
  denoised in tiles is mixed as the untiled one is.
- **Where the weight lives**: in the record of each input-set variant of a run (key :data:`KEY`), each fit on the
  frames that variant serves (``Run.serving``): its weight, OIDN's mode and quality, and the fit (frames,
  objective at each weight). A variant without it is served unmixed. It travels with the record: ``kpcn ship``
  copies it, and every command that denoises (``serving.Serving``) mixes where the record says.
- **The fit** is ``kpcn_keras.oidn_mix_fit``'s (``kpcn mix-oidn``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from prep import baselines, exr, layouts
from prep.errors import KpcnError

KEY = "oidn_mix"  # the run record's entry
OIDN_MODE = "prefiltered"  # Blender's default: the strongest OIDN (prep.baselines.oidn_denoise)
OIDN_QUALITY = "high"


@dataclasses.dataclass(frozen=True)
class Mix:
    """The weight of the networks' frame in the mix (OIDN's is ``1 - weight``) and how OIDN runs."""

    weight: float
    oidn_mode: str = OIDN_MODE
    oidn_quality: str = OIDN_QUALITY

    def __post_init__(self):
        if not 0.0 <= self.weight <= 1.0:
            raise ValueError(f"weight {self.weight!r}: expected a number in [0, 1]")
        if self.oidn_mode not in baselines.OIDN_MODES or self.oidn_quality not in baselines.OIDN_QUALITIES:
            raise ValueError(f"OIDN {self.oidn_mode!r} at {self.oidn_quality!r}: expected a mode of "
                             f"{baselines.OIDN_MODES} and a quality of {baselines.OIDN_QUALITIES}")

    def oidn(self, aovs: dict[str, np.ndarray]) -> np.ndarray:
        """OIDN's frame of the layers ``aovs`` (with the renderer's guides where ``served_layers`` put them)."""
        return baselines.oidn_denoise(layouts.denoiser_guides(aovs), mode=self.oidn_mode, quality=self.oidn_quality)

    def apply(self, networks: np.ndarray, oidn: np.ndarray) -> np.ndarray:
        return exr.to_float32(self.weight * networks.astype(np.float64) + (1.0 - self.weight) * oidn.astype(np.float64))


def of_record(data, where: str = "run record") -> Mix | None:
    """The mix a run record's JSON (``RunRecord.data``) holds, None where it has none; KpcnError naming ``where``
    (the record's file) and the entry where it is damaged."""
    entry = data.get(KEY)
    if entry is None:
        return None
    try:
        return Mix(float(entry["weight"]), entry["oidn_mode"], entry["oidn_quality"])
    except (KeyError, TypeError, ValueError) as e:
        raise KpcnError(f"{where}: entry {KEY!r}: {e}") from None


class Mixed:
    """A denoiser (``kpcn_keras.denoise.Denoiser``) whose ``default`` is mixed with OIDN's frame, called as the
    denoiser is; what else a denoiser has (its ``run``, ``record``, ``settings``, ``tile``...) is the denoiser's."""

    def __init__(self, denoiser, mix: Mix):
        if not baselines.oidn_available():
            raise KpcnError(f"{denoiser.run.dir}: its networks' frame is mixed with OIDN's (its record's {KEY!r}), "
                            "which needs the optional package pyoidn: pip install -c constraints.txt -e '.[oidn]'")
        self.denoiser, self.mix = denoiser, mix

    def __getattr__(self, name):
        return getattr(self.denoiser, name)

    def __call__(self, aovs: dict, slope=None) -> dict:
        out = dict(self.denoiser(aovs, slope=slope))
        out["default"] = self.mix.apply(out["default"], self.mix.oidn(aovs))
        return out

    def prepare(self, aovs: dict):
        raise KpcnError(f"{self.denoiser.run.dir}: a frame prepared for λ maps skips the OIDN mix of its record; "
                        "denoise it whole")


def served(denoiser, record):
    """``denoiser`` as the run ``record`` (a ``RunRecord``) says it serves: mixed with OIDN's frame where the
    record holds a mix, itself where it holds none."""
    mix = of_record(record.data, str(record.path))
    return denoiser if mix is None else Mixed(denoiser, mix)


__all__ = ["KEY", "Mix", "Mixed", "of_record", "served"]
