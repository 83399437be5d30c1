"""What the studies that measure kpcn beside other denoisers share (``kpcn inputs-study``, ``kpcn quality``): the
frames of other renderers with their references, the denoisers beside kpcn on them, the scores, the count of
frames one method wins, the grouping by input spp, and the panels.

- **Other renderers' frames** (:func:`renderer_pairs`): every ``<scene>-<spp>spp.exr`` under the given files or
  folders that is not its scene's reference (the same folder's render of the scene with the most samples), with
  that reference.
- **Beside kpcn** (:func:`beside`): Intel Open Image Denoise on the frame's colour, albedo and normal in both its
  modes (``pyoidn``, ``prep.baselines.OIDN_MODES``; left out when it is not installed) and, where the folder has
  it, the renderer's own denoised frame (``<scene>-<spp>spp-blender-oidn.exr``: what Blender wrote at render
  time); :data:`BESIDE_KEYS` names each one's key in a study's rows.
- **Scores** (:func:`scores`): relMSE, DSSIM and relSE p99.9 of ``prep.metrics``, float64.
- **Wins** (:func:`wins`): on how many frames one method's relMSE is strictly below another's, of the frames that
  have both.
- **Panels** (:func:`panels_figure`): one row per frame, one column per method, every image tonemapped by
  ``prep.colour.tonemap``, the same transform for every column.

Only numpy, prep and matplotlib (through ``prep.files``): no keras, no torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prep import baselines, colour, exr, layouts, metrics
from prep.errors import KpcnError
from prep.files import pyplot

RENDERER_DENOISED = baselines.RENDERER_DENOISED  # the validation set's name for Blender's own denoised frame
# each denoiser beside kpcn by its key in a study's rows (prep.baselines.ANCHORS)
BESIDE_KEYS = {"OIDN": "oidn", "OIDN prefiltered": "oidn_prefiltered", "Blender": "blender"}
SCORES = ("relmse", "dssim", "relse_p999")
PANEL_COLUMNS = ("input", "kpcn", "OIDN", "Blender", "reference")


def scores(x: np.ndarray, ref: np.ndarray) -> dict:
    """relMSE, DSSIM and relSE p99.9 of ``x`` against ``ref``."""
    return {"relmse": metrics.relmse(x, ref), "dssim": metrics.dssim(x, ref), "relse_p999": metrics.relse_p999(x, ref)}


def _is_render(path: Path, scene: str) -> bool:
    try:
        return exr.parse_render_filename(path)[0] == scene
    except exr.AOVError:
        return False


def renderer_pairs(paths) -> list[tuple[Path, Path]]:
    """(noisy, reference) of every ``<scene>-<spp>spp.exr`` under ``paths`` that is not its scene's reference."""
    from kpcn_keras.evaluate import pairs_for_inputs

    noisy = []
    for given in map(Path, paths):
        files = sorted(given.rglob("*spp.exr")) if given.is_dir() else [given]
        for path in files:
            try:
                scene, spp = exr.parse_render_filename(path)
            except exr.AOVError:
                continue
            most = max(exr.parse_render_filename(p)[1] for p in path.parent.glob(f"{scene}-*spp.exr")
                       if _is_render(p, scene))
            if spp < most:
                noisy.append(path)
    return [(Path(a), Path(b)) for a, b in pairs_for_inputs([str(p) for p in noisy])]


def some_renderer_pairs(paths) -> list[tuple[Path, Path]]:
    """:func:`renderer_pairs` of ``paths``, or a KpcnError in one line naming them where they hold none (a path
    that is no render, or a folder without a noisy frame and its reference)."""
    try:
        pairs = renderer_pairs(paths)
    except KpcnError:
        pairs = []
    if not pairs:
        raise KpcnError(f"{' '.join(map(str, paths))}: no noisy frame <scene>-<spp>spp.exr with its scene's "
                        "reference (the render with the most samples) beside it")
    return pairs


def read_pairs(pairs):
    """``(noisy_path, frame, reference colour, scene, spp)`` of each pair of :func:`renderer_pairs`, read in its own
    layout (``prep.layouts``), a reference of another size refused in one line naming both files."""
    for noisy_path, ref_path in pairs:
        frame, ref = layouts.read(noisy_path), layouts.read(ref_path).layers["default"]
        layouts.check_same_size(noisy_path, frame.size, ref_path, ref.shape[:2])
        yield (noisy_path, frame, ref, *exr.parse_render_filename(noisy_path))


renderer_denoised = baselines.renderer_denoised


def beside(noisy_path: Path, frame: layouts.Frame) -> dict[str, np.ndarray]:
    """The other denoisers' outputs for a frame: ``OIDN`` (plain) and ``OIDN prefiltered`` when ``pyoidn`` is
    installed (on ``baselines.oidn_inputs``), ``Blender`` when the renderer's own denoised frame is beside it."""
    out = {}
    if baselines.oidn_available():
        given = baselines.oidn_inputs(frame)
        out["OIDN"] = baselines.oidn_denoise(given, mode="plain")
        out["OIDN prefiltered"] = baselines.oidn_denoise(given, mode="prefiltered")
    own = renderer_denoised(Path(noisy_path))
    if own.exists():
        out["Blender"] = layouts.read(own).layers["default"]
    return out


def wins(rows: list[dict], method: str = "kpcn", other: str = "oidn") -> str:
    """"k of n": on how many frames ``method``'s relMSE is below ``other``'s (the frames that have both)."""
    both = [r for r in rows if method in r and other in r]
    return f"{sum(r[method]['relmse'] < r[other]['relmse'] for r in both)} of {len(both)}" if both else "–"


def by_spp(rows: list[dict]) -> dict[int, list[dict]]:
    """The rows grouped by their ``spp``, in increasing spp, each group in the rows' order."""
    return {spp: [r for r in rows if r["spp"] == spp] for spp in sorted({r["spp"] for r in rows})}


def panels_figure(panels: list, columns=PANEL_COLUMNS):
    """One row per ``(title, {column: image})`` of ``panels``, the ``columns`` in order (a column the row lacks
    is left blank), every image tonemapped (``prep.colour.tonemap``)."""
    plt = pyplot()
    rows = max(len(panels), 1)
    fig, axes = plt.subplots(rows, len(columns), figsize=(2.2 * len(columns), 2.3 * rows), squeeze=False)
    for row in axes:
        for ax in row:
            ax.axis("off")
    for row, (title, images) in zip(axes, panels):
        for ax, name in zip(row, columns):
            if name in images:
                ax.imshow(colour.tonemap(images[name]), interpolation="nearest")
                ax.set_title(f"{title}\n{name}" if name == columns[0] else name, fontsize=7)
    fig.tight_layout()
    return fig
