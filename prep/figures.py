"""The figures of what the networks are trained on (docs/method.md §10), drawn from a shard set: the seed
report's Fig. 3 and Fig. 4, for ``kpcn figures`` on a run (its shard set, into ``<run>/figures/``) or on a
shard set alone (``--set``, into ``<set>/figures/``: :func:`shard_set_figures`). No keras, no torch.

=================  =========================================================================================
file               what (seed report figure)
=================  =========================================================================================
``sampling.png``   one input render of the set: its variance PDF over patch positions, with a colourbar;
                   the round-0 patches the set cut from it, outlined on its noisy colour; the PDF over the
                   colour with the same patches (Fig. 3)
``inputs.png``     the network inputs of one of those patches, a row per branch the set holds: the log
                   colour, the x- and y-gradients of colour, normal, albedo and depth, the relative
                   variances, and the reference, one panel each, titled by its name in
                   ``prep.features.FEATURE_NAMES`` (Fig. 4)
=================  =========================================================================================

Each figure is two steps, so that the tests check the picture's values and not only that a PNG was written:
a function that gathers the panels' data (:func:`sampling_panels`, :func:`input_panels`) and one that draws
exactly that data (:func:`sampling_figure`, :func:`inputs_figure`: a matplotlib figure).

**What the set records, not a redraw.** The patches are the positions the set's round-0 shards hold for the
render (``position`` of its patches, by ``source``). The PDF is the one ``kpcn shards`` drew them from,
``prep.shards.round_pdf`` with the set's recorded configuration, computed again from the render, whose
SHA-256 the manifest lists (``ShardSet.check_renders``): the probability each shard recorded for its patch
must be that PDF's at the patch's position, else the figure is refused (ShardError), so the picture is the
set's own and the same set always draws the same one. The PDF is over top-left positions,
(H - P + 1) x (W - P + 1); it is drawn at the patches' centres (offset P // 2) so that it lies over the
pixels it samples. Error rounds (k >= 1) are not drawn here: ``kpcn resample`` draws each over the map that
drove it (``<run>/resample/round-<k>.png``).

**The patch of Fig. 4** is the render's round-0 patch of the highest recorded probability (the first in the
shards' order among equals): where the sampling looks hardest. Its inputs are read from its shard
(``prep.shards.read_patch``): recomputed from the stored buffers exactly as training reads them, forward
differences at its last row and column included. The colour and the reference share one display scale.

**The render shown** is the one given when it is an input of the set, else the set's first held-out input
(by scene, then spp), else its first training input: the frame ``kpcn figures --run`` draws a run's other
figures on. With ``--set``, a given render that is not an input of the set is an error naming the option.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prep import exr, features
from prep.colour import tonemap
from prep.errors import OptionError
from prep.files import check_outputs, pyplot, save_png
from prep.shards import MANIFEST, ShardConfig, ShardError, ShardSet, open_shard, read_patch, round_pdf

log = logging.getLogger("kpcn")

DATA_FIGURES = {name: f"{name}.png" for name in ("sampling", "inputs")}
# a recorded probability is the float64 PDF value the draw returned; recomputed, it is the same arithmetic
PDF_RTOL = 1e-12


def feature_groups() -> dict[str, slice]:
    """The panels of Fig. 4: each stem of ``prep.features.FEATURE_NAMES`` (the name without its ``.R``,
    ``.G``, ``.B``) and the feature channels it names, in the table's order."""
    groups: dict[str, slice] = {}
    for i, name in enumerate(features.FEATURE_NAMES):
        stem = name.split(".")[0]
        groups[stem] = slice(groups[stem].start if stem in groups else i, i + 1)
    return groups


def _same_file(a, b) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


@dataclass(frozen=True)
class RecordedPatches:
    """The round-0 patches a shard set cut from one of its input renders, in the shards' order."""

    source: int  # index into the manifest's sources
    positions: np.ndarray  # (n, 2) int32, top-left (y, x)
    pdf: np.ndarray  # (n,) float64, the probability the shard recorded for each
    where: list[tuple[Path, int]]  # each patch's shard file and its index there

    @property
    def likeliest(self) -> int:
        """The patch of Fig. 4: the highest recorded probability, the first among equals."""
        return int(np.argmax(self.pdf))


@dataclass
class DataPlan:
    """What the data figures of one render of a shard set read, found (and checked) before anything is
    drawn: the set, its manifest and configuration, the render (an input source) and its recorded patches."""

    sset: ShardSet
    manifest: dict
    source: int
    patches: RecordedPatches

    @property
    def render(self) -> Path:
        return self.sset.resolve(self.manifest["sources"][self.source]["path"])

    @property
    def config(self) -> ShardConfig:
        return ShardConfig(**self.manifest["config"])

    def reads(self) -> list[tuple[str, Path]]:
        """Every file the figures read, as ``prep.files.check_outputs`` takes them."""
        shards = sorted({path for path, _ in self.patches.where})
        return [("shard manifest", self.sset.manifest_path), ("render", self.render)] + [("shard", p) for p in shards]

    def draw(self, out_dir: Path) -> dict[str, Path]:
        """Both figures into ``out_dir``; name -> path."""
        out_dir = Path(out_dir)
        return {"sampling": save_png(sampling_figure(sampling_panels(self)), out_dir / DATA_FIGURES["sampling"]),
                "inputs": save_png(inputs_figure(input_panels(self)), out_dir / DATA_FIGURES["inputs"])}


def input_sources(manifest: dict) -> list[int]:
    """The indices of the set's input renders, held-out ones first, each split by (scene, spp)."""
    sources = manifest["sources"]
    order = {"val": 0, "train": 1}
    return sorted((i for i, s in enumerate(sources) if s["role"] == "input"),
                  key=lambda i: (order.get(sources[i]["split"], 2), sources[i]["scene"], sources[i]["spp"]))


def recorded_patches(sset: ShardSet, manifest: dict, source: int) -> RecordedPatches:
    """The round-0 patches of ``source`` that the set's verified shards of its split hold."""
    split = manifest["sources"][source]["split"]
    positions, pdf, where = [], [], []
    for entry in sset.verified_shards(split, manifest, rounds=(0,)):
        with open_shard(entry.path) as f:
            ids, pos, prob = f["source"][:], f["position"][:], f["pdf"][:]
        for i in np.flatnonzero(ids == source):
            positions.append(pos[i])
            pdf.append(prob[i])
            where.append((entry.path, int(i)))
    if not positions:
        raise ShardError(f"{sset.manifest_path}: round-000 holds no patch of "
                         f"{manifest['sources'][source]['path']} (source {source})")
    return RecordedPatches(source, np.asarray(positions, np.int32), np.asarray(pdf, np.float64), where)


def data_plan(set_dir: str | os.PathLike, frame: str | os.PathLike | None = None, *,
              for_run: bool = False) -> DataPlan | None:
    """The data figures' plan for the render ``frame`` of the complete shard set in ``set_dir`` (default: the
    first of :func:`input_sources`).

    ``for_run``: the set of a run, whose other figures need no set: a set that is not there (a shipped model
    without its shards), or a render of it that is not there (a set moved without its renders), gives None,
    logged; a ``frame`` that is not an input of the set gives the default render. Otherwise each of these is
    an error naming the folder or the option (``input``).
    """
    sset = ShardSet(set_dir)
    if for_run and not sset.manifest_path.is_file():
        log.info("no data figures: the run's shard set %s is not there", sset.dir)
        return None
    manifest = sset.complete_manifest()
    inputs = input_sources(manifest)
    if not inputs:
        raise ShardError(f"{sset.manifest_path}: lists no input render")
    source = inputs[0]
    if frame is not None:
        found = [i for i in inputs if _same_file(frame, sset.resolve(manifest["sources"][i]["path"]))]
        if found:
            source = found[0]
        elif not for_run:
            names = [Path(manifest["sources"][i]["path"]).name for i in inputs]
            listed = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
            raise OptionError("input", f"{frame} is not an input render of the shard set {sset.dir} (its inputs: "
                              f"{listed})")
    render = sset.resolve(manifest["sources"][source]["path"])
    if not render.is_file():
        if for_run:
            log.info("no data figures: %s, a render of the run's shard set, is not there", render)
            return None
        raise ShardError(f"{render}: a render of the shard set {sset.dir} is not there; the sampling figure "
                         "draws its PDF from it")
    sset.check_renders(manifest)  # a render replaced since the set was cut would draw another PDF
    return DataPlan(sset, manifest, source, recorded_patches(sset, manifest, source))


@dataclass(frozen=True)
class SamplingPanels:
    """The data of Fig. 3: the render's noisy colour, its PDF over patch positions and the drawn patches."""

    frame: str  # the render's file name
    colour: np.ndarray  # (H, W, 3) noisy colour, linear
    pdf: np.ndarray  # (H - P + 1, W - P + 1) float64: prep.shards.round_pdf of the render, round 0
    positions: np.ndarray  # (n, 2) top-left (y, x) of the patches the set cut from it
    patch_size: int


def sampling_panels(plan: DataPlan) -> SamplingPanels:
    """Fig. 3's data for the plan's render; ShardError if a recorded probability is not the PDF's."""
    noisy = exr.read_aovs(plan.render)
    config = plan.config
    pdf = round_pdf(noisy, config)
    ys, xs = plan.patches.positions[:, 0], plan.patches.positions[:, 1]
    if not np.allclose(pdf[ys, xs], plan.patches.pdf, rtol=PDF_RTOL, atol=0.0):
        worst = int(np.argmax(np.abs(pdf[ys, xs] - plan.patches.pdf)))
        raise ShardError(
            f"{plan.sset.manifest_path}: the patch at {tuple(int(v) for v in plan.patches.positions[worst])} of "
            f"{plan.render.name} has the recorded probability {plan.patches.pdf[worst]!r}, the PDF this kpcn "
            f"computes {pdf[ys[worst], xs[worst]]!r}: the set was cut by other code; rebuild it with "
            f"{config.command or 'kpcn shards'}")
    return SamplingPanels(plan.render.name, noisy["default"], pdf, plan.patches.positions, config.patch_size)


def _image_axes(ax, shape) -> None:
    """Axes over an image of ``shape`` (pixel centres at integers), ticks off."""
    ax.set_xlim(-0.5, shape[1] - 0.5)
    ax.set_ylim(shape[0] - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])


def pdf_extent(panels: SamplingPanels) -> tuple[float, float, float, float]:
    """Where the PDF is drawn (matplotlib's left, right, bottom, top): its value at top-left (y, x) over the
    patch's centre pixel (y + P // 2, x + P // 2)."""
    r = panels.patch_size // 2
    h, w = panels.pdf.shape
    return (r - 0.5, r + w - 0.5, r + h - 0.5, r - 0.5)


def sampling_figure(panels: SamplingPanels):
    """Fig. 3 of ``panels``: the PDF (colourbar), the patches on the noisy colour, the two over each other."""
    from matplotlib.patches import Rectangle

    plt = pyplot()
    h, w = panels.colour.shape[:2]
    scale = 4.0 / max(h, w)
    fig, axes = plt.subplots(1, 3, figsize=(3 * w * scale + 1.6, h * scale + 0.9))
    image = tonemap(panels.colour)
    extent = pdf_extent(panels)
    shown = axes[0].imshow(panels.pdf, cmap="viridis", interpolation="nearest", extent=extent)
    fig.colorbar(shown, ax=axes[0], fraction=0.046, pad=0.02, label="probability of the patch centred here")
    axes[0].set_title("sampling PDF", fontsize=9)
    axes[1].imshow(image, interpolation="nearest")
    axes[1].set_title(f"{len(panels.positions)} patches {panels.patch_size}x{panels.patch_size}", fontsize=9)
    axes[2].imshow(image, interpolation="nearest")
    axes[2].imshow(panels.pdf, cmap="viridis", interpolation="nearest", extent=extent, alpha=0.55)
    axes[2].set_title("overlaid", fontsize=9)
    p = panels.patch_size
    for ax in axes:
        _image_axes(ax, (h, w))
    for ax, colour in ((axes[1], "cyan"), (axes[2], "white")):
        for y, x in panels.positions:
            ax.add_patch(Rectangle((x - 0.5, y - 0.5), p, p, fill=False, edgecolor=colour, linewidth=0.6))
    fig.suptitle(f"{panels.frame}: where patches are cut (seed report Fig. 3)", fontsize=10)
    fig.tight_layout()
    return fig


@dataclass(frozen=True)
class InputPanels:
    """The data of Fig. 4: per branch, each group of :func:`feature_groups` of one patch, (P, P, channels)
    float32 as training reads it, then ``reference``."""

    frame: str  # the render's file name
    position: tuple[int, int]  # the patch's top-left (y, x) in the render
    branches: dict[str, dict[str, np.ndarray]]


def input_panels(plan: DataPlan) -> InputPanels:
    """Fig. 4's data: the inputs of the plan's likeliest patch, read from its shard."""
    k = plan.patches.likeliest
    path, index = plan.patches.where[k]
    # a set without the split holds the whole colour in the diffuse branch; its specular one is zeros
    branches = features.BRANCHES if plan.config.input_set.split else features.BRANCHES[:1]
    names = [n for b in branches for n in (f"{b}/features", f"{b}/reference")]
    with open_shard(path) as f:
        patch = read_patch(f, names, index)
    panels = {}
    for b in branches:
        feats = patch[f"{b}/features"]
        panels[b] = {name: feats[..., channels] for name, channels in feature_groups().items()}
        panels[b]["reference"] = patch[f"{b}/reference"]
    y, x = plan.patches.positions[k]
    return InputPanels(plan.render.name, (int(y), int(x)), panels)


def _signed_rgb(values: np.ndarray) -> np.ndarray:
    """A signed 3-channel difference as an image: 0 mid-grey, the largest magnitude at 0 or 1."""
    top = float(np.abs(values).max())
    return np.clip(0.5 + 0.5 * values / (top if top > 0 else 1.0), 0.0, 1.0)


def inputs_figure(panels: InputPanels):
    """Fig. 4 of ``panels``: a row per branch, a panel per group, titled by its feature name."""
    plt = pyplot()
    rows = list(panels.branches.items())
    cols = len(rows[0][1])
    fig, axes = plt.subplots(len(rows), cols, figsize=(1.3 * cols, 1.55 * len(rows) + 0.5), squeeze=False)
    for ax_row, (branch, groups) in zip(axes, rows):
        # the colour and its reference on one scale, so they compare by eye
        top = max(float(groups["colour"].max()), float(groups["reference"].max()), 1e-6)
        for ax, (name, values) in zip(ax_row, groups.items()):
            if name in ("colour", "reference"):
                ax.imshow(np.clip(values / top, 0.0, 1.0), interpolation="nearest")
            elif values.shape[-1] == 3:
                ax.imshow(_signed_rgb(values), interpolation="nearest")
            elif name.startswith("relvar"):
                ax.imshow(values[..., 0], cmap="magma", interpolation="nearest", vmin=0.0)
            else:
                m = max(float(np.abs(values).max()), 1e-6)
                ax.imshow(values[..., 0], cmap="coolwarm", interpolation="nearest", vmin=-m, vmax=m)
            ax.set_title(name, fontsize=7)
            ax.set_xticks([])
            ax.set_yticks([])
        ax_row[0].set_ylabel(branch, fontsize=8)
    y, x = panels.position
    fig.suptitle(f"network inputs of the patch at ({y}, {x}) of {panels.frame} (seed report Fig. 4)", fontsize=9)
    fig.tight_layout()
    return fig


def shard_set_figures(shards_root: str | os.PathLike, set_name: str, frame=None) -> dict[str, Path]:
    """``kpcn figures --set``: both data figures of the shard set ``<shards_root>/<set_name>`` into its
    ``figures/`` folder (``ShardSet.figures_dir``), for the render ``frame`` (default: :func:`data_plan`'s);
    name -> path."""
    sset = ShardSet.named(shards_root, set_name)
    if not sset.manifest_path.is_file():
        root = Path(shards_root)
        sets = sorted(p.name for p in root.iterdir() if (p / MANIFEST).is_file()) if root.is_dir() else None
        held = "no such folder" if sets is None else f"its shard sets: {', '.join(sets) or 'none'}"
        raise OptionError("set_name", f"{set_name!r} names no shard set: {sset.dir} has no {MANIFEST} "
                          f"({root}: {held})")
    plan = data_plan(sset.dir, frame)
    out_dir = sset.figures_dir
    check_outputs([("figure", out_dir / name) for name in DATA_FIGURES.values()], plan.reads(),
                  f"remove {out_dir}'s figure first")
    return plan.draw(out_dir)


__all__ = ["DATA_FIGURES", "DataPlan", "InputPanels", "SamplingPanels", "data_plan", "feature_groups",
           "input_panels", "inputs_figure", "pdf_extent", "recorded_patches", "sampling_figure", "sampling_panels",
           "shard_set_figures"]
