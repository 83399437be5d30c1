"""Whether a file given as ``--pair`` is a second render of the input's frame (docs/robustness.md §4).

Two renders of one frame with different seeds are denoised as one render of all their samples
(``prep.inputs.mean_layers``) and adapted on, each the other's target (``kpcn_keras.adapt``); any other file
would be averaged into the frame, or taken for its noise, silently. Two checks refuse such a file in one line
naming both files:

- :func:`check_header`, from the two headers alone, before a model is loaded or anything written: the input
  itself (the same file, however named), another layout, size, data window, diffuse/specular split or spp;
- :func:`check_colours`, on the two colours once read: identical pixels (the same render twice), or a
  correlation of their smoothed log luminance below :data:`MIN_CORRELATION` (another frame). The smoothing
  (a 5x5 box) averages the noise away and keeps what the picture is; log(1 + luminance) keeps a few bright
  pixels from deciding it. On the validation frames (Blender, three scenes at 4, 16 and 64 spp:
  ``python -m prep.pairs ../shared/validation/blender``, ``reports/pair_correlation.json``) two renders of one
  scene correlate at 0.98 and above, renders of different scenes at 0.31 and below: 0.6 lies between with a
  margin each side.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from prep import exr, layouts
from prep.errors import OptionError
from prep.inputs import box_mean

MIN_CORRELATION = 0.6  # below it a pair is not a render of the input's frame (the module docstring)
SMOOTHING = 2  # radius of the box the correlation smooths by: 5x5
FLAT = 1e-9  # a smoothed log luminance that varies less than this (relative) is flat: no picture to compare
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights of linear R G B


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or os.path.samefile(a, b)
    except OSError:
        return False


def check_header(input_path, pair_path, read_header=layouts.read_header) -> layouts.Header:
    """The pair's :class:`~prep.layouts.Header`, after refusing (OptionError naming both files) a pair that is the
    input itself or whose header differs from the input's in layout, size, data window, split or spp (an spp
    unknown for either is not compared). Reads headers only, each by ``read_header`` (the command's reading
    options: layout, view layer)."""
    input_path, pair_path = Path(input_path), Path(pair_path)
    if _same_file(input_path, pair_path):
        raise OptionError("pair", f"{pair_path} is the input {input_path} itself: give a second render of the "
                                  "frame with another seed")
    heads = [read_header(p) for p in (input_path, pair_path)]
    compared = [("layout", heads[0].layout, heads[1].layout),
                ("size", *("x".join(map(str, h.size[::-1])) for h in heads)),
                ("data window", heads[0].data_window, heads[1].data_window),
                ("diffuse/specular split", heads[0].inputs.split, heads[1].inputs.split)]
    if None not in (heads[0].spp, heads[1].spp):
        compared.append(("spp", heads[0].spp, heads[1].spp))
    differ = [(what, a, b) for what, a, b in compared if a != b]
    if differ:
        raise OptionError("pair", f"{pair_path} is not a second render of {input_path}: it differs in "
                          + ", ".join(f"{what} ({b}, the input's {a})" for what, a, b in differ))
    return heads[1]


def correlation(colour_a: np.ndarray, colour_b: np.ndarray) -> float | None:
    """Pearson's correlation of the two (H, W, 3) colours' log(1 + luminance) (negative luminance as 0), each
    smoothed by a (2 :data:`SMOOTHING` + 1)^2 box, in float64; None where either is flat once smoothed (a spread
    below :data:`FLAT` of its level, the summed-area table's rounding: nothing to compare)."""
    smooth = []
    for colour in (colour_a, colour_b):
        lum = np.maximum(np.asarray(colour, np.float64)[..., :3] @ LUMINANCE, 0.0)
        s = box_mean(np.log1p(lum), SMOOTHING).ravel()
        if s.std() <= FLAT * (1.0 + abs(s.mean())):
            return None
        smooth.append(s - s.mean())
    a, b = smooth
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def check_colours(input_path, colour: np.ndarray, pair_path, pair_colour: np.ndarray) -> None:
    """OptionError naming both files for a pair whose colour is the input's pixel for pixel (the same render
    twice: no variance) or correlates with it below :data:`MIN_CORRELATION` (:func:`correlation`: another
    frame)."""
    if np.array_equal(colour, pair_colour):
        raise OptionError("pair", f"{pair_path} has the same pixels as {input_path}: the same render twice gives "
                                  "no variance; give a second render of the frame with another seed")
    r = correlation(colour, pair_colour)
    if r is not None and r < MIN_CORRELATION:
        raise OptionError("pair", f"{pair_path} is not a render of the frame {input_path}: their smoothed log "
                                  f"luminance correlates at {r:.3f}, below {MIN_CORRELATION} (two renders of one "
                                  "frame correlate near 1)")


def measure(paths) -> list[dict]:
    """:func:`correlation` of every two of ``paths`` of the same size (the colour as ``prep.layouts.read``
    reads it), with their scenes and spp from ``<scene>-<spp>spp.exr``: the figures :data:`MIN_CORRELATION` is
    chosen from."""
    frames = [(Path(p), layouts.read(p)) for p in paths]
    rows = []
    for i, (pa, fa) in enumerate(frames):
        for pb, fb in frames[i + 1:]:
            if fa.size == fb.size:
                (sa, na), (sb, nb) = exr.parse_render_filename(pa), exr.parse_render_filename(pb)
                rows.append({"a": pa.name, "b": pb.name, "same_scene": sa == sb, "spp": [na, nb],
                             "correlation": correlation(fa.layers["default"], fb.layers["default"])})
    return rows


def main(argv=None) -> None:
    """``python -m prep.pairs FOLDER``: :func:`measure` of the noisy renders ``<scene>-<spp>spp.exr`` in FOLDER,
    as JSON, with the range of each kind (same scene, other scenes)."""
    folder = Path((argv or sys.argv[1:])[0])
    paths = sorted(p for p in folder.glob("*spp.exr") if exr.parse_render_filename(p)[1] < 1024)
    rows = measure(paths)
    summary = {kind: [min(r["correlation"] for r in rows if r["same_scene"] == same),
                      max(r["correlation"] for r in rows if r["same_scene"] == same)]
               for kind, same in (("same_scene", True), ("other_scenes", False))}
    print(json.dumps({"folder": str(folder), "min_correlation": MIN_CORRELATION, "range": summary, "pairs": rows},
                     indent=1))


if __name__ == "__main__":
    main()
