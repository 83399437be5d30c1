"""What renderers write, read as kpcn's AOV layout: one adapter per renderer, the only module that knows
their channel names (docs/formats.md §1b).

:func:`read` opens any OpenEXR file (every part of a multi-part one) and returns a :class:`Frame`: the layers
of ``prep.exr``'s AOV layout that the file has, under their kpcn names, and the :class:`~prep.inputs.InputSet`
they make (a diffuse/specular split? variance layers?), with the alpha, the header attributes and windows an
output keeps, and a note of each repair. The adapter is found from the channels (:data:`LAYOUTS`, tried in
order; the first that finds what it needs reads the file) or named by the caller (``--layout``). A file no
adapter reads is refused with one line naming what each looked for and missed.

=========  ===================================================================================================
layout     what it reads
=========  ===================================================================================================
kpcn       ``diffuse specular albedo normal depth`` (R G B / Z) and the six ``<x>Variance`` layers (optional)
cycles     Blender Cycles, ``<view layer>.<pass>.<C>``: Blender 4 short pass names in one part (``DiffDir``,
           ``GlossCol``, ``Emit``, ``VolumeDir``), Blender 5 long names (``Diffuse Direct``), one part per
           pass or interleaved. diffuse = (DiffDir + DiffInd) * DiffCol; specular = (Dir + Ind) * Col of
           glossy and transmission + Emit + Env + VolumeDir + VolumeInd (Combined - diffuse, clipped at 0,
           when one of those is missing); colour = Combined; albedo = DiffCol (Denoising Albedo clipped to
           [0, 1] without a split); normal = Normal (world space; else Denoising Normal, camera space);
           depth = Denoising Depth (else Depth, with values >= DEPTH_MISS, the background, as 0); alpha =
           Combined.A. No variance: Cycles 3.0+ writes none. Of several view layers, the one with the most
           passes kpcn uses (``view_layer`` names another; a note says which and why).
mitsuba    Mitsuba 3, ``moment`` over ``aov`` and a radiance integrator: colour = the radiance integrator's
           layer (``path.X Y Z``, CIE XYZ, taken to linear sRGB; ``R G B`` without ``moment``); albedo,
           normal, depth = the AOVs named ``albedo``, ``sh_normal``/``nn``/``normal``, ``depth``/``dd`` (bare
           or ``aov.<name>``; depth is the ray length, 0 on a miss), each with its second moment
           ``m2_<layer>``: variance of the mean = max(m2 - mean^2, 0) / spp (the colour's taken to sRGB as if
           its XYZ channels were fully correlated: no cross moments are written). No split. Albedo clipped
           to [0, 1] (metals exceed 1).
pbrt       PBRT-v4 GBufferFilm: ``R G B``, ``Albedo``, ``Ns`` (camera space by default: taken to world space by
           the header's ``worldToCamera``), ``P`` (depth = |P|, camera space), ``Variance`` (per sample:
           divided by the spp, from the header's ``samplesPerPixel``). No split.
rgb        a colour alone (``R G B``, or the one RGB layer, or a named colour layer of the layouts above),
           with ``albedo`` and ``normal`` layers when present or given as files (as OIDN takes them). No
           split, no variance; a missing depth is 0, a missing normal 0, a missing albedo 1.
=========  ===================================================================================================

Every layout: half or float channels, ``X Y Z`` or ``R G B`` for a vector, ``Z``, ``T``, ``Y``, ``R`` or
a lone channel for a scalar; non-finite values repaired by ``prep.exr``'s rule. A layer a layout reads that
is in the file but not whole (a channel missing) is refused naming the layer and the channel, from the header
(:meth:`Layout.check`, by :func:`read_header` as by :func:`read`), never passed over for another layout. The
samples per pixel come from the file name (``<scene>-<spp>spp.exr``, or a half of a pair
``<scene>-<spp>spp-pair-a.exr``: its own spp), else the header (Cycles
``cycles.<view layer>.samples``, pbrt ``samplesPerPixel``, kpcn ``kpcn.spp``: ``prep.exr.SPP_ATTRIBUTE``), else
the caller's ``spp``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from prep import exr
from prep.errors import OptionError
from prep.exr import AOVError, ExrImage
from prep.inputs import InputSet

log = logging.getLogger("kpcn")

DEPTH_MISS = 1e9  # Cycles' Depth pass is 1e10 where a ray leaves the scene
VECTOR = ("RGB", "XYZ")
SCALAR = ("Z", "T", "Y", "R")
PARTIAL = 2  # channels of R G B or X Y Z that make a layer a vector cut short (Layout.partial), not a scalar


@dataclass
class Frame:
    """One frame as read from a renderer's file, in kpcn's names (:mod:`prep.exr`): ``default`` (the colour)
    always, ``albedo normal depth`` always (filled when the file lacks them: see ``notes``), ``diffuse
    specular`` when ``inputs.split``, the six variance layers when ``inputs.variance``."""

    path: Path
    layout: str
    layers: dict[str, np.ndarray]
    inputs: InputSet
    alpha: np.ndarray | None = None
    attributes: dict = field(default_factory=dict)
    data_window: tuple = ((0, 0), (0, 0))
    display_window: tuple = ((0, 0), (0, 0))
    spp: int | None = None
    notes: tuple[str, ...] = ()
    # layers the adapter could have taken instead (Cycles' clipped Denoising Albedo for its Diffuse Color, its
    # Denoising Normal for its Normal): what Blender hands its own denoiser, for the OIDN anchor
    # (prep.baselines.oidn_inputs) and for a study to measure which denoises better
    alternatives: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def size(self) -> tuple[int, int]:
        return self.layers["default"].shape[:2]

    def served_layers(self) -> dict[str, np.ndarray]:
        """What a denoiser is given of the frame: its layers, and its :attr:`alternatives` under
        :data:`ALTERNATIVE`-prefixed names (the networks read neither; OIDN, where a model mixes its frame with
        OIDN's, reads them as :func:`denoiser_guides` does)."""
        return {**self.layers, **{ALTERNATIVE + k: v for k, v in self.alternatives.items()}}


# the alternatives a renderer hands its own denoiser in place of the network's layers of the same name
DENOISER_GUIDES = ("albedo", "normal")


def denoiser_guides(layers: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``layers`` (a frame's, or its :meth:`Frame.served_layers`) as a renderer's own denoiser is given them: the
    albedo and normal it hands that denoiser where ``layers`` holds them as alternatives (Cycles' Denoising Albedo
    and Normal, which follow mirrors and glass where Diffuse Color is black), the others as they are."""
    plain = {k: v for k, v in layers.items() if not k.startswith(ALTERNATIVE)}
    return {**plain, **{k.removeprefix(ALTERNATIVE): v for k, v in layers.items()
                        if k.startswith(ALTERNATIVE) and k.removeprefix(ALTERNATIVE) in DENOISER_GUIDES}}


class _Channels:
    """The channels of one file by layer, and the readers of a layer as a vector or a scalar; ``view_layer``: the
    Cycles view layer the caller named (None: the adapter chooses)."""

    def __init__(self, image: ExrImage, view_layer: str | None = None):
        self.image, self.layers, self.view_layer = image, image.components(), view_layer

    def has(self, layer: str, kind=VECTOR) -> bool:
        comps = self.layers.get(layer, set())
        return any(set(c) <= comps for c in kind) or (kind is SCALAR and len(comps) == 1)

    def lacking(self, layer: str, least: int = 0) -> str | None:
        """What vector ``layer`` lacks, in words ("layer N lacks channel Z (it has X Y)"), if it is in the file
        without every channel of R G B or X Y Z (those of the two it has more of) and with at least ``least`` of
        them (``PARTIAL``: a lone channel is a scalar layer, not a vector cut short); None otherwise."""
        comps = self.layers.get(layer)
        if not comps or self.has(layer):
            return None
        closest = max(VECTOR, key=lambda names: len(set(names) & comps))
        if len(set(closest) & comps) < least:
            return None
        missing = [c for c in closest if c not in comps]
        unprefixed = layer == "default" and not any(n.startswith("default.") for n in self.image.names)
        named = "the colour (unprefixed channels)" if unprefixed else f"layer {layer}"
        return (f"{named} lacks channel{'s' if len(missing) > 1 else ''} {' '.join(missing)} "
                f"(it has {' '.join(sorted(comps))})")

    def _pixels(self, layer: str, comp: str) -> np.ndarray:
        name = f"{layer}.{comp}"
        if layer == "default" and name not in self.image.channels:
            name = comp  # the unprefixed channels (R G B) are layer default's (prep.exr._split_name)
        return self.image.channels[name]

    def vector(self, layer: str) -> np.ndarray:
        comps = self.layers[layer]
        names = next((c for c in VECTOR if set(c) <= comps), None)
        if names is None:
            raise AOVError(f"{self.image.path}: {self.lacking(layer)}")
        return np.stack([self._pixels(layer, c) for c in names], axis=-1).astype(np.float32)

    def scalar(self, layer: str) -> np.ndarray:
        comps = self.layers[layer]
        comp = next((c for c in SCALAR if c in comps), None) or next(iter(comps))
        return self._pixels(layer, comp).astype(np.float32)

    def component(self, layer: str, comp: str) -> np.ndarray | None:
        return self._pixels(layer, comp).astype(np.float32) if comp in self.layers.get(layer, ()) else None


def _repaired(layers: dict[str, np.ndarray], notes: list[str]) -> dict[str, np.ndarray]:
    """``layers`` with ``prep.exr``'s repair of non-finite values (``exr.repair_layers``), noted in ``notes``."""
    layers, counts = exr.repair_layers(layers)
    if counts:
        notes.append(exr.repair_note(counts))
    return layers


def _sum(*images) -> np.ndarray:
    return exr.to_float32(np.sum([np.asarray(i, np.float64) for i in images], axis=0))


class Layout:
    """One renderer's layout: :meth:`missing` says what a file lacks for it (None: it reads the file),
    :meth:`check` whether each layer it reads is whole, :meth:`layers` reads it. ``looks_for`` is the one line
    an error shows."""

    name = ""
    looks_for = ""
    decodes_whole = True  # its reader holds every channel of the file beside the layers it makes
    vectors: tuple[str, ...] = ()  # the vector layers that mark a file as this layout's, whole or not (partial)

    def missing(self, ch: _Channels) -> str | None:
        raise NotImplementedError

    def partial(self, ch: _Channels) -> str | None:
        """What one of :attr:`vectors` lacks (``_Channels.lacking``), if the file has it but not whole: a file of
        this layout with a layer cut short, refused rather than read as another layout."""
        return next(filter(None, (ch.lacking(layer, PARTIAL) for layer in self.vectors)), None)

    def check(self, ch: _Channels, spp: int | None) -> None:
        """AOVError naming the file, the layer and its missing channel for one of :attr:`vectors` not whole, or
        where :meth:`layers` would find a layer not whole: :meth:`layers` itself run on a 1x1 stand-in of the
        file's channels (from its header), so that the check before any work and the read cannot disagree."""
        partial = self.partial(ch)
        if partial:
            raise AOVError(f"{ch.image.path}: {partial}")
        image = dataclasses.replace(ch.image, size=(1, 1), channels={
            name: np.zeros((1, 1), np.float32) for name in ch.image.names})
        self.layers(_Channels(image, ch.view_layer), spp)

    def spp(self, ch: _Channels) -> int | None:
        """The samples per pixel the file's header states, if it states them."""
        return None

    def inputs(self, ch: _Channels, spp: int | None) -> InputSet:
        """What a file that :meth:`missing` accepted gives the networks, from its channel names alone."""
        raise NotImplementedError

    def layers(self, ch: _Channels, spp: int | None) -> tuple[dict, np.ndarray | None, list[str]]:
        """(layers, alpha, notes) of a file that :meth:`missing` accepted: the layers :meth:`inputs` says."""
        raise NotImplementedError

    def read(self, path: Path, header: ExrImage, spp: int | None,
             view_layer: str | None = None) -> tuple[dict, np.ndarray | None, list[str]]:
        """:meth:`layers` of the file whose header is ``header``, its pixels read here (the whole file decoded,
        :attr:`decodes_whole`), each layer and the alpha repaired by ``prep.exr``'s rule for non-finite values."""
        layers, alpha, notes = self.layers(_Channels(exr.read_image(path), view_layer), spp)
        layers = _repaired(layers if alpha is None else {**layers, "alpha": alpha}, notes)
        return layers, layers.pop("alpha", None), notes


class KpcnLayout(Layout):
    name = "kpcn"
    looks_for = "diffuse, specular, albedo, normal, depth"
    vectors = ("diffuse", "specular", "albedo", "normal")

    def missing(self, ch):
        lacking = [n for n in ("diffuse", "specular", "albedo", "normal") if not ch.has(n)]
        lacking += [] if ch.has("depth", SCALAR) else ["depth"]
        return ", ".join(lacking) or None

    def inputs(self, ch, spp):
        return InputSet(split=True, variance=all(ch.has(n, SCALAR) for n in exr.VARIANCE_LAYERS))

    def spp(self, ch):
        samples = ch.image.attributes.get(exr.SPP_ATTRIBUTE)  # a half of a pair states it (kpcn render --pair)
        return int(samples) if isinstance(samples, (int, np.integer)) and samples > 0 else None

    decodes_whole = False

    def check(self, ch, spp):
        # the check prep.exr's reader makes of the layers it reads
        exr._check_layers(ch.image.path, ch.layers, self.inputs(ch, spp).variance)

    def read(self, path, header, spp, view_layer=None):
        # prep.exr's own reader: it lets each channel go once its layer is made (what denoise's memory bound counts)
        # and repairs non-finite values itself
        ch = _Channels(header)
        variance = self.inputs(ch, spp).variance
        present = [n for n in exr.VARIANCE_LAYERS if ch.has(n, SCALAR)]
        lacking = ", ".join(sorted(set(exr.VARIANCE_LAYERS) - set(present)))
        notes = [] if variance or not present else [f"variance layers {lacking} missing: read without variance"]
        return exr.read_aovs(path, variances=variance), None, notes


# Cycles pass names: (Blender 5, Blender 4). A light pass is stored divided by its colour pass.
CYCLES_PASSES = {
    "combined": ("Combined", "Combined"),
    "diffuse_direct": ("Diffuse Direct", "DiffDir"),
    "diffuse_indirect": ("Diffuse Indirect", "DiffInd"),
    "diffuse_color": ("Diffuse Color", "DiffCol"),
    "glossy_direct": ("Glossy Direct", "GlossDir"),
    "glossy_indirect": ("Glossy Indirect", "GlossInd"),
    "glossy_color": ("Glossy Color", "GlossCol"),
    "transmission_direct": ("Transmission Direct", "TransDir"),
    "transmission_indirect": ("Transmission Indirect", "TransInd"),
    "transmission_color": ("Transmission Color", "TransCol"),
    "emission": ("Emission", "Emit"),
    "environment": ("Environment", "Env"),
    "volume_direct": ("Volume Direct", "VolumeDir"),
    "volume_indirect": ("Volume Indirect", "VolumeInd"),
    "normal": ("Normal", "Normal"),
    "depth": ("Depth", "Depth"),
    "denoising_normal": ("Denoising Normal", "Denoising Normal"),
    "denoising_albedo": ("Denoising Albedo", "Denoising Albedo"),
    "denoising_depth": ("Denoising Depth", "Denoising Depth"),
}
CYCLES_DIFFUSE = ("diffuse_direct", "diffuse_indirect", "diffuse_color")
CYCLES_LOBES = ("glossy", "transmission")
CYCLES_ADDED = ("emission", "environment", "volume_direct", "volume_indirect")


class CyclesLayout(Layout):
    name = "cycles"
    looks_for = "<view layer>.Combined and Blender's passes"

    @staticmethod
    def view_layers(ch) -> list[str]:
        return sorted(layer.rpartition(".")[0] for layer in ch.layers
                      if layer.endswith(".Combined") and ch.has(layer))

    @classmethod
    def view(cls, ch) -> str:
        """The view layer read: the one named (``ch.view_layer``, checked by :func:`detect`), else the one with the
        most passes kpcn uses (of equals, the first by name)."""
        if ch.view_layer is not None:
            return ch.view_layer
        return max(cls.view_layers(ch), key=lambda view: len(cls._passes(ch, view)))

    @classmethod
    def view_note(cls, ch) -> list[str]:
        """The note of which view layer is read and why, where the file has several."""
        views = cls.view_layers(ch)
        if len(views) < 2:
            return []
        view = cls.view(ch)
        if ch.view_layer is not None:
            return [f"view layers {', '.join(views)}: read {view}, as named (--view-layer)"]
        counts = ", ".join(f"{v} {len(cls._passes(ch, v))}" for v in views)
        return [f"view layers {', '.join(views)}: read {view}, the one with the most passes kpcn uses ({counts}); "
                "--view-layer NAME reads another"]

    def missing(self, ch):
        views = self.view_layers(ch)
        if not views:
            return "<view layer>.Combined (R G B)"
        view = self.view(ch)
        passes = self._passes(ch, view)
        if not any(p in passes for p in CYCLES_DIFFUSE + ("normal", "denoising_normal", "denoising_albedo")):
            return f"Blender's passes beside {view}.Combined (Combined alone is read as rgb)"
        return None

    def partial(self, ch):
        combined = (layer for layer in sorted(ch.layers) if layer.endswith(".Combined"))
        return next(filter(None, (ch.lacking(layer, PARTIAL) for layer in combined)), None)

    @staticmethod
    def _passes(ch, view) -> dict[str, str]:
        """role -> the file's layer for each Cycles pass present in ``view``."""
        found = {}
        for role, names in CYCLES_PASSES.items():
            for name in names:
                layer = f"{view}.{name}"
                if layer in ch.layers:
                    found[role] = layer
                    break
        return found

    def spp(self, ch):
        samples = ch.image.attributes.get(f"cycles.{self.view(ch)}.samples")
        return int(samples) if isinstance(samples, str) and samples.isdigit() else None

    def inputs(self, ch, spp):
        passes = self._passes(ch, self.view(ch))
        return InputSet(split=all(r in passes for r in CYCLES_DIFFUSE), variance=False)

    def layers(self, ch, spp):
        notes = self.view_note(ch)
        p = self._passes(ch, self.view(ch))
        rgb = {role: ch.vector(layer) for role, layer in p.items() if role not in ("depth", "denoising_depth")}
        out = {"default": rgb["combined"][..., :3]}
        if self.inputs(ch, spp).split:
            with np.errstate(invalid="ignore"):  # NaN passes: _combined_where_the_split_breaks
                out["diffuse"] = exr.to_float32(
                    (rgb["diffuse_direct"].astype(np.float64) + rgb["diffuse_indirect"]) * rgb["diffuse_color"])
            terms = [r for lobe in CYCLES_LOBES for r in (f"{lobe}_direct", f"{lobe}_indirect", f"{lobe}_color")]
            if all(r in p for r in terms + list(CYCLES_ADDED)):
                with np.errstate(invalid="ignore"):
                    out["specular"] = _sum(*[(rgb[f"{lobe}_direct"].astype(np.float64) + rgb[f"{lobe}_indirect"])
                                             * rgb[f"{lobe}_color"] for lobe in CYCLES_LOBES],
                                           *[rgb[r] for r in CYCLES_ADDED])
            else:
                lacking = [CYCLES_PASSES[r][0] for r in terms + list(CYCLES_ADDED) if r not in p]
                notes.append(f"passes {', '.join(lacking)} missing: specular = Combined - diffuse, clipped at 0")
                out["specular"] = exr.to_float32(np.maximum(out["default"].astype(np.float64) - out["diffuse"], 0))
            out["albedo"] = rgb["diffuse_color"]
            _combined_where_the_split_breaks(out, notes)
            if "denoising_albedo" in p:
                out["alternative.albedo"] = np.clip(rgb["denoising_albedo"], 0.0, 1.0)
        elif "denoising_albedo" in p:
            out["albedo"] = np.clip(rgb["denoising_albedo"], 0.0, 1.0)
            notes.append("albedo = Denoising Albedo clipped to [0, 1]")
        if "normal" in p:
            out["normal"] = rgb["normal"]
            if "denoising_normal" in p:
                out["alternative.normal"] = rgb["denoising_normal"]
        elif "denoising_normal" in p:
            out["normal"] = rgb["denoising_normal"]
            notes.append("normal = Denoising Normal (camera space; the networks are trained on world space)")
        if "denoising_depth" in p:
            out["depth"] = ch.scalar(p["denoising_depth"])
        elif "depth" in p:
            depth = ch.scalar(p["depth"])
            out["depth"] = np.where(depth >= DEPTH_MISS, np.float32(0), depth)
            notes.append(f"depth = Depth, {DEPTH_MISS:g} and beyond (the background) as 0")
        return out, ch.component(p["combined"], "A"), notes


# Mitsuba AOV names (the aov integrator's "<name>:<type>" pairs name them; these are the usual names and types),
# each bare or under the aov integrator's own prefix ("aov.albedo")
MITSUBA_ALBEDO = ("albedo",)
MITSUBA_NORMAL = ("sh_normal", "nn", "normal")
MITSUBA_DEPTH = ("depth", "dd")
MITSUBA_MOMENT = "m2_"  # the moment integrator's second moment of layer L is layer m2_L
# Mitsuba writes a nested integrator's radiance (path.X Y Z) as CIE XYZ: back to linear sRGB by Mitsuba's own
# xyz_to_srgb (the columns of mi.xyz_to_srgb of the unit vectors, Mitsuba 3.9.1)
MITSUBA_XYZ_TO_RGB = np.array([[3.240479, -1.537150, -0.498535],
                               [-0.969256, 1.875991, 0.041556],
                               [0.055648, -0.204043, 1.057311]])


class MitsubaLayout(Layout):
    name = "mitsuba"
    looks_for = "a colour and the aov integrator's albedo, sh_normal|nn|normal, depth|dd"

    @staticmethod
    def _find(ch, names, kind=VECTOR):
        """The layer of one of ``names``, bare or as the last part of a prefixed name (``aov.nn``)."""
        for name in names:
            for layer in sorted(ch.layers):
                if (layer == name or layer.endswith(f".{name}")) and not layer.startswith(MITSUBA_MOMENT) \
                        and ch.has(layer, kind):
                    return layer
        return None

    @classmethod
    def _colour(cls, ch) -> str:
        """The radiance layer: under the moment integrator, a nested integrator's own layer (``path.X Y Z``): one
        with a moment, not under another layer (as ``aov.albedo`` is under ``aov``) and with none under it (the
        aov integrator's own ``aov.X Y Z`` is 0); else R G B."""
        aovs = {cls._find(ch, MITSUBA_ALBEDO), cls._find(ch, MITSUBA_NORMAL), cls._find(ch, MITSUBA_DEPTH, SCALAR)}

        def nested(layer):
            return (layer in aovs or layer.rpartition(".")[0] in ch.layers
                    or any(o.startswith(f"{layer}.") for o in ch.layers))

        for layer in sorted(ch.layers):
            if (f"{MITSUBA_MOMENT}{layer}" in ch.layers and not layer.startswith(MITSUBA_MOMENT) and ch.has(layer)
                    and not nested(layer)):
                return layer
        return "default"

    def missing(self, ch):
        lacking = [] if ch.has(self._colour(ch)) else ["R G B"]
        lacking += [] if self._find(ch, MITSUBA_ALBEDO) else ["albedo AOV"]
        lacking += [] if self._find(ch, MITSUBA_NORMAL) else ["normal AOV"]
        lacking += [] if self._find(ch, MITSUBA_DEPTH, SCALAR) else ["depth AOV"]
        return ", ".join(lacking) or None

    def _names(self, ch) -> dict[str, str]:
        """kpcn name -> the file's layer, for the colour and the three AOVs."""
        return {"default": self._colour(ch), "albedo": self._find(ch, MITSUBA_ALBEDO),
                "normal": self._find(ch, MITSUBA_NORMAL), "depth": self._find(ch, MITSUBA_DEPTH, SCALAR)}

    def _moments(self, ch) -> dict[str, str | None]:
        """kpcn name -> the file's layer of its second moments (None where the file has none)."""
        return {k: f"{MITSUBA_MOMENT}{v}" if f"{MITSUBA_MOMENT}{v}" in ch.layers else None
                for k, v in self._names(ch).items()}

    def inputs(self, ch, spp):
        return InputSet(split=False, variance=spp is not None and None not in self._moments(ch).values())

    @staticmethod
    def _is_xyz(ch, layer) -> bool:
        return layer != "default" and not set("RGB") <= ch.layers[layer] and set("XYZ") <= ch.layers[layer]

    def layers(self, ch, spp):
        names = self._names(ch)
        out = {k: ch.vector(v) for k, v in names.items() if k != "depth"}
        out["depth"] = ch.scalar(names["depth"])
        notes = [f"{k} = {v}" for k, v in names.items()]
        xyz = self._is_xyz(ch, names["default"])
        if xyz:
            out["default"] = exr.to_float32(out["default"].astype(np.float64) @ MITSUBA_XYZ_TO_RGB.T)
            notes.append(f"colour = {names['default']} (CIE XYZ) in linear sRGB")
        raw_albedo = out["albedo"]
        if float(raw_albedo.max(initial=0.0)) > 1.0:
            notes.append("albedo clipped to [0, 1] (above 1 on metals)")
        out["albedo"] = np.clip(raw_albedo, 0.0, 1.0)
        moments = self._moments(ch)
        if not self.inputs(ch, spp).variance:
            lacking = [k for k, v in moments.items() if v is None]
            notes.append("read without variance: " + (f"no m2_ moments of {', '.join(lacking)}" if lacking else
                                                      "no spp known (name the file <scene>-<spp>spp.exr)"))
            return out, ch.component(names["default"], "A"), notes
        for key, layer in moments.items():
            m2 = ch.vector(layer) if key != "depth" else ch.scalar(layer)
            mean = {"albedo": raw_albedo, "default": ch.vector(names["default"])}.get(key, out[key])
            # clamped at 0: half-float moments of a constant pixel can round below the squared mean
            var = np.maximum(np.asarray(m2, np.float64) - np.asarray(mean, np.float64) ** 2, 0.0) / spp
            if key == "default" and xyz:
                # the moment integrator writes no cross moments: each sRGB channel's variance as if the XYZ
                # channels were fully correlated (a sample's colour varies in brightness more than in hue)
                var = (np.sqrt(var) @ MITSUBA_XYZ_TO_RGB.T) ** 2
            out[exr.VARIANCE_OF[key]] = exr.to_float32(var.mean(axis=-1) if var.ndim == 3 else var)
        out["diffuseVariance"] = out["specularVariance"] = out["colorVariance"]
        notes.append("variance = (m2 - mean^2) / spp, clamped at 0")
        return out, ch.component(names["default"], "A"), notes


class PbrtLayout(Layout):
    name = "pbrt"
    looks_for = "R G B, Albedo, Ns, P (GBufferFilm)"
    vectors = ("default", "Albedo", "Ns", "P", "Variance")

    def missing(self, ch):
        lacking = [n for n in ("default", "Albedo", "Ns", "P") if not ch.has(n)]
        return ", ".join("R G B" if n == "default" else n for n in lacking) or None

    def spp(self, ch):
        samples = ch.image.attributes.get("samplesPerPixel")
        return int(samples) if isinstance(samples, (int, np.integer)) and samples > 0 else None

    def inputs(self, ch, spp):
        return InputSet(split=False, variance=spp is not None and ch.has("Variance"))

    def layers(self, ch, spp):
        out = {"default": ch.vector("default"), "albedo": np.clip(ch.vector("Albedo"), 0.0, 1.0)}
        p = ch.vector("P").astype(np.float64)
        out["depth"] = exr.to_float32(np.sqrt((p * p).sum(axis=-1)))
        notes = ["depth = |P| (camera space)"]
        to_camera = ch.image.attributes.get("worldToCamera")
        normal = ch.vector("Ns").astype(np.float64)
        if isinstance(to_camera, np.ndarray) and to_camera.shape == (4, 4):
            # a normal goes back to world space by the transpose of the point transform's linear part (pbrt's
            # matrices act on column vectors: n_world = W^T n_camera), then is made unit length again
            normal = normal @ np.asarray(to_camera, np.float64)[:3, :3]
            length = np.sqrt((normal * normal).sum(axis=-1, keepdims=True))
            normal = np.where(length > 0, normal / np.where(length > 0, length, 1), 0.0)
            notes.append("normal = Ns taken to world space by the header's worldToCamera")
        else:
            notes.append("normal = Ns as written (camera space: no worldToCamera in the header)")
        out["normal"] = exr.to_float32(normal)
        if not self.inputs(ch, spp).variance:
            notes.append("read without variance: " + ("no Variance layer" if not ch.has("Variance") else
                                                      "no spp known (name the file <scene>-<spp>spp.exr)"))
            return out, ch.component("default", "A"), notes
        var = np.maximum(ch.vector("Variance").astype(np.float64), 0.0).mean(axis=-1) / spp
        out["colorVariance"] = out["diffuseVariance"] = out["specularVariance"] = exr.to_float32(var)
        for name in ("albedoVariance", "normalVariance", "depthVariance"):  # PBRT writes none of these
            out[name] = np.zeros(var.shape, np.float32)
        notes.append("variance = Variance / spp; albedo, normal and depth variance 0 (PBRT writes none)")
        return out, ch.component("default", "A"), notes


class RgbLayout(Layout):
    name = "rgb"
    looks_for = "R G B, or one layer of R G B"
    vectors = ("default", "albedo", "Albedo", "normal", "Normal")

    @staticmethod
    def colour_layer(ch) -> str | None:
        if ch.has("default"):
            return "default"
        if CyclesLayout.view_layers(ch):
            return f"{CyclesLayout.view(ch)}.Combined"
        rgb = [layer for layer in ch.layers if ch.has(layer, ("RGB",))]
        return rgb[0] if len(rgb) == 1 else None

    def missing(self, ch):
        return None if self.colour_layer(ch) else "R G B"

    def inputs(self, ch, spp):
        return InputSet(split=False, variance=False)

    def layers(self, ch, spp):
        layer = self.colour_layer(ch)
        out, notes = {"default": ch.vector(layer)[..., :3]}, CyclesLayout.view_note(ch) if layer != "default" else []
        h, w = out["default"].shape[:2]
        for name, kind in (("albedo", VECTOR), ("normal", VECTOR), ("depth", SCALAR)):
            found = next((n for n in (name, name.capitalize()) if ch.has(n, kind)), None)
            if found:
                out[name] = ch.vector(found) if kind is VECTOR else ch.scalar(found)
        return out, ch.component(layer, "A"), notes


LAYOUTS = {layout.name: layout for layout in (KpcnLayout(), CyclesLayout(), PbrtLayout(), MitsubaLayout(),
                                              RgbLayout())}
FILL = {"albedo": 1.0, "normal": 0.0, "depth": 0.0}  # what a layer the file lacks is (the rgb layout)
ALTERNATIVE = "alternative."  # an adapter's layer named so goes to Frame.alternatives
LISTED_LAYERS = 40  # layers a refusal names: any renderer's file whole, a damaged header's thousands in one line


def check_layout(name: str | None, option: str = "layout") -> str | None:
    if name is not None and name not in LAYOUTS:
        raise OptionError(option, f"must be one of {', '.join(LAYOUTS)}, got {name!r}")
    return name


def detect(image: ExrImage, layout: str | None = None, *, view_layer: str | None = None) -> Layout:
    """The adapter that reads ``image``: ``layout`` if given (AOVError with what the file lacks for it),
    else the first of :data:`LAYOUTS` that finds what it needs (AOVError with what each missed). A layout whose
    layers are in the file but one not whole (``Layout.partial``) is refused naming the channel, not passed
    over for another. ``view_layer``: the Cycles view layer to read (AOVError listing those there are)."""
    ch = _Channels(image, view_layer)
    _check_view_layer(ch)
    if layout is not None:
        adapter = LAYOUTS[check_layout(layout)]
        lacking = adapter.missing(ch)
        if lacking:
            partial = adapter.partial(ch)
            raise AOVError(f"{image.path}: " + (partial or f"not a {layout} file: {layout} looks for "
                                                           f"{adapter.looks_for} and it lacks {lacking}"))
        return adapter
    missed = []
    for adapter in LAYOUTS.values():
        lacking = adapter.missing(ch)
        if lacking is None:
            return adapter
        partial = adapter.partial(ch)
        if partial:
            raise AOVError(f"{image.path}: {partial}")
        missed.append(f"{adapter.name} looks for {adapter.looks_for}, missed {lacking}")
    layers = sorted(ch.layers)
    found = ", ".join(layers[:LISTED_LAYERS]) or "no channels"
    found += f" and {len(layers) - LISTED_LAYERS} more" if len(layers) > LISTED_LAYERS else ""
    raise AOVError(f"{image.path}: no layout kpcn reads: {'; '.join(missed)}; the file has layers {found}")


def _check_view_layer(ch: _Channels) -> None:
    """AOVError naming the file and its view layers if ``ch.view_layer`` is not one of its Cycles view layers."""
    name = ch.view_layer
    views = CyclesLayout.view_layers(ch)
    if name is None or name in views:
        return
    partial = ch.lacking(f"{name}.Combined", PARTIAL)
    there = f"its view layers: {', '.join(views)}" if views else "it has no Cycles view layers (<name>.Combined)"
    raise AOVError(f"{ch.image.path}: " + (partial or f"no view layer {name!r} (--view-layer); {there}"))


def _opened(path, layout: str | None, spp: int | None, view_layer: str | None):
    """(header image, adapter, its channels, spp) of the frame ``path``, every layer the adapter reads checked
    whole (``Layout.check``) from the header alone."""
    path = Path(path)
    image = exr.read_image(path, header_only=True)
    adapter = detect(image, layout, view_layer=view_layer)
    ch = _Channels(image, view_layer)
    spp = _spp_of(path) or adapter.spp(ch) or spp
    adapter.check(ch, spp)
    return image, adapter, ch, spp


def _spp_of(path: Path) -> int | None:
    """The spp the file's name states: ``<scene>-<spp>spp.exr``, or a half of a pair,
    ``<scene>-<spp>spp-pair-a.exr`` (``catalogue.pair_names``: the half's own spp, as Mitsuba writes none)."""
    try:
        return exr.parse_render_filename(path)[1]
    except AOVError:
        from prep.render.cycles import catalogue  # the pairs' names have one owner, beside Blender's side

        half = catalogue().pair_half(Path(path).name)
        return None if half is None else half[1] // 2


def read(path: str | os.PathLike, layout: str | None = None, *, spp: int | None = None,
         albedo: str | os.PathLike | None = None, normal: str | os.PathLike | None = None,
         view_layer: str | None = None) -> Frame:
    """Read any renderer's frame (module docstring); ``layout`` forces an adapter, ``spp`` is used when the
    file name does not say it; ``albedo``, ``normal``: separate files for the auxiliaries of a frame that has
    none of its own (OptionError for one that has: a file never silently replaces a layer the render made);
    ``view_layer``: the Cycles view layer to read (default: the one with the most passes kpcn uses)."""
    path = Path(path)
    image, adapter, ch, spp = _opened(path, layout, spp, view_layer)
    inputs = adapter.inputs(ch, spp)
    layers, alpha, notes = adapter.read(path, image, spp, view_layer)
    for name, aux in (("albedo", albedo), ("normal", normal)):
        if aux is not None and name in layers:
            raise OptionError(name, f"{aux} is for a frame without its own {name}, and {path} ({adapter.name} layout) "
                                    f"has one")
        if aux is not None:
            layers[name] = _repaired({name: exr.read_rgb(aux)}, notes)[name]
            if layers[name].shape != layers["default"].shape:
                raise AOVError(f"{aux}: {name} is {layers[name].shape[1]}x{layers[name].shape[0]}, "
                               f"{path} is {image.size[1]}x{image.size[0]}")
    alternatives = {k.removeprefix(ALTERNATIVE): layers.pop(k) for k in list(layers) if k.startswith(ALTERNATIVE)}
    h, w = image.size
    for name, value in FILL.items():
        if name not in layers:
            layers[name] = np.full((h, w) if name == "depth" else (h, w, 3), value, np.float32)
            notes.append(f"no {name}: {value:g} everywhere")
    for note in notes:
        log.info("%s (%s): %s", path, adapter.name, note)
    return Frame(path, adapter.name, layers, inputs, alpha, image.attributes, image.data_window,
                 image.display_window, spp, tuple(notes), alternatives)


def check_same_size(path, size: tuple[int, int], other, other_size: tuple[int, int], what: str = "reference") -> None:
    """AOVError in one line naming both files and their sizes unless ``other`` (the ``what`` of the frame ``path``:
    its reference, a second render of it) has the frame's (height, width) ``size``: the one check of every command
    that reads a file beside a frame, made before any work."""
    if tuple(other_size) != tuple(size):
        raise AOVError(f"the {what} {other} is {other_size[1]}x{other_size[0]} but {path} is {size[1]}x{size[0]}; "
                       f"a {what} must be its frame's size")


@dataclass(frozen=True)
class Header:
    """What a frame's header says: its size, the layout that reads it, the inputs it gives, its samples per
    pixel (None if unknown), how many channels its reader decodes whole beside the layers it makes (0 for
    the kpcn layout, whose reader lets each go: ``Layout.decodes_whole``) and its data window."""

    size: tuple[int, int]
    layout: str
    inputs: InputSet
    spp: int | None
    channels: int
    data_window: tuple


def read_header(path: str | os.PathLike, layout: str | None = None, *, spp: int | None = None,
                view_layer: str | None = None) -> Header:
    """The :class:`Header` of a frame, from the file's header alone: a command checks every input before work.
    AOVError, as :func:`read` would raise it, for a layer the reader needs that is not whole."""
    image, adapter, ch, spp = _opened(path, layout, spp, view_layer)
    return Header(image.size, adapter.name, adapter.inputs(ch, spp), spp,
                  len(image.names) if adapter.decodes_whole else 0, image.data_window)


def _combined_where_the_split_breaks(out: dict, notes: list) -> None:
    """Where a pixel's composed split is not finite but Combined is (Cycles writes NaN colour passes at some
    pixels of volumes), the pixel's Combined goes to specular, its diffuse and albedo are 0, as for light
    scattered in a medium: the split still sums to Combined, where repairing each layer alone would zero both
    branches and a denoised frame would come out black there."""
    finite = lambda a: np.isfinite(a).all(axis=-1)  # noqa: E731
    broken = ~(finite(out["diffuse"]) & finite(out["specular"])) & finite(out["default"])
    if not broken.any():
        return
    for name in ("diffuse", "specular", "albedo"):
        out[name] = np.array(out[name], dtype=np.float32)  # own, writable copies
    out["diffuse"][broken] = 0.0
    out["albedo"][broken] = 0.0
    out["specular"][broken] = out["default"][broken]
    notes.append(f"{int(broken.sum())} pixels whose light passes are not finite where Combined is: "
                 "their Combined read as specular")
