"""``kpcn blend-pair``: a user's .blend frame rendered by Cycles as two halves, two renders of half the samples
with two seeds, every pass kpcn reads, named ``<blend stem>-<spp/2>spp-pair-a.exr`` and ``-pair-b.exr``
(catalogue.pair_names), for ``kpcn denoise <...>-pair-a.exr --pair <...>-pair-b.exr`` (docs/denoise.md, "Renders
in pairs").

The render runs in a Python that has ``bpy`` (``prep/render/blender/blend_pair.py``, :data:`BLENDER_SIDE`,
which imports nothing of kpcn); this module checks the options, the file and that Python, and hands the file its
arguments (:func:`blender_command`), as ``prep.render.cycles`` does for ``kpcn render-cycles``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from prep.bounds import Bound, bounded, check_fields
from prep.errors import OptionError
from prep.render.cycles import BLENDER_PYTHON, catalogue, run_blender_side
from prep.render.frame import SPP

BLENDER_SIDE = Path(__file__).with_name("blender") / "blend_pair.py"
FRAME = Bound(-1_048_574, 1_048_574)  # Blender's frame numbers (MINAFRAME, MAXFRAME)


@dataclass
class BlendPairConfig:
    """What ``kpcn blend-pair`` renders: the frame of ``blend`` (``frame``, default the file's current one) as
    two halves of ``spp / 2`` samples into ``out`` (default: beside the .blend)."""

    blend: str
    spp: int = bounded(64, SPP)  # the whole frame's samples: the mean of the two halves has them
    frame: int | None = bounded(None, FRAME)
    out: str | None = None
    blender_python: str = BLENDER_PYTHON

    def __post_init__(self):
        check_fields(self)
        path = Path(self.blend)
        if path.suffix.lower() != ".blend" or not path.is_file():
            raise OptionError("blend", f"{self.blend}: " + ("no such file" if not path.exists() else
                                                           "not a .blend file"))
        if self.spp % 2 or self.spp < 4:
            raise OptionError("spp", f"must be even and 4 or more (each half renders half of it, 2 or more), "
                              f"got {self.spp}")
        if self.out is None:
            self.out = str(path.parent)

    def outputs(self) -> list[Path]:
        """The two halves' paths."""
        return [Path(self.out) / n for n in catalogue().pair_names(Path(self.blend).stem, self.spp)]


def blender_command(cfg: BlendPairConfig) -> list[str]:
    """The command that renders ``cfg`` in its Python: :data:`BLENDER_SIDE` and its arguments."""
    frame = [] if cfg.frame is None else ["--frame", str(cfg.frame)]
    return [cfg.blender_python, str(BLENDER_SIDE), str(cfg.blend), str(cfg.out), "--spp", str(cfg.spp), *frame]


def render_blend_pair(cfg: BlendPairConfig) -> list[Path]:
    """Render the two halves of ``cfg`` (a half already there is kept); returns their paths. KpcnError if
    Blender's Python stops with an error."""
    run_blender_side(cfg, blender_command(cfg))
    return cfg.outputs()
