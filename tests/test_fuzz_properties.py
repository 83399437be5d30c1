"""Properties of the readers and the API over drawn inputs (hypothesis): every renderer's layout, any subset of its
layers, any data window, half or float channels, non-finite and huge values. Each call returns a finite frame of
the size the input states, or raises a ``KpcnError`` of one line; the header reader agrees with the reader.

The budget is the hypothesis profile of ``conftest.py``: ``ci`` (fixed examples, derandomized) unless
``KPCN_FUZZ_SCALE`` > 1 or ``KPCN_HYPOTHESIS_PROFILE=deep`` (docs/robustness.md §6)."""

import math

import numpy as np
import pytest
from helpers.exr_layouts import CYCLES5_RGB, write_channels
from helpers.malformed import PROFILE
from hypothesis import given, settings
from hypothesis import strategies as st

from prep.errors import KpcnError

FUZZ = settings.get_profile(PROFILE)
HALF_MAX = float(np.finfo(np.float16).max)

# layer -> its components, per layout as each renderer names them (prep/layouts.py); "" is the unprefixed colour
CYCLES4 = ("DiffDir", "DiffInd", "DiffCol", "GlossDir", "GlossInd", "GlossCol", "TransDir", "TransInd", "TransCol",
           "Emit", "Env", "VolumeDir", "VolumeInd")
LAYOUTS = {
    "kpcn": {**{n: "RGB" for n in ("diffuse", "specular", "albedo", "normal")}, "depth": "Z",
             **{f"{n}Variance": "Z" for n in ("diffuse", "specular", "color", "albedo", "normal", "depth")}},
    "cycles5": {"ViewLayer.Combined": "RGBA", **{f"ViewLayer.{n}": "RGB" for n in CYCLES5_RGB},
                "ViewLayer.Normal": "XYZ", "ViewLayer.Denoising Depth": "Z", "ViewLayer.Depth": "Z"},
    "cycles4": {"ViewLayer.Combined": "RGBA", **{f"ViewLayer.{n}": "RGB" for n in CYCLES4},
                "ViewLayer.Normal": "XYZ", "ViewLayer.Depth": "Z", "ViewLayer.Denoising Albedo": "RGB"},
    "pbrt": {"": "RGB", "Albedo": "RGB", "Ns": "XYZ", "P": "XYZ", "Variance": "RGB"},
    "mitsuba": {"path": "XYZ", "m2_path": "XYZ", "aov.albedo": "RGB", "m2_aov.albedo": "RGB", "aov.nn": "XYZ",
                "m2_aov.nn": "XYZ", "aov.dd": "Y", "m2_aov.dd": "Y"},
    "rgb": {"": "RGBA", "albedo": "RGB", "normal": "XYZ", "depth": "Z"},
}
SPECIAL = [0.0, -0.0, 1.0, -1.0, 1e-30, 1e-8, 6e4, 3e38, -3e38, math.inf, -math.inf, math.nan]


@st.composite
def exr_files(draw, whole_layers=True):
    """(channels, header, data window) of a file in a drawn layout; ``whole_layers``: drop layers only, else
    components of a layer too."""
    layout = draw(st.sampled_from(sorted(LAYOUTS)))
    h, w = draw(st.integers(1, 8)), draw(st.integers(1, 8))
    x0, y0 = draw(st.integers(-40, 40)), draw(st.integers(-40, 40))
    half = draw(st.booleans())
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    names = []
    for layer, comps in LAYOUTS[layout].items():
        if draw(st.integers(0, 4)) == 0:  # a layer the file lacks
            continue
        layer_names = [f"{layer}.{c}" if layer else c for c in comps]
        if not whole_layers and len(comps) > 1 and draw(st.booleans()):  # a layer missing one component
            layer_names.pop(draw(st.integers(0, len(comps) - 1)))
        names += layer_names
    if not names:  # a file has a channel at least (the binding writes none without)
        names = ["R"]
    specials = draw(st.lists(st.tuples(st.integers(0, max(len(names) - 1, 0)), st.integers(0, h * w - 1),
                                       st.sampled_from(SPECIAL)), max_size=6))
    scale = 10.0 ** draw(st.integers(-20, 20 if not half else 4))
    channels = {n: (rng.standard_normal((h, w)) * scale) for n in names}
    for i, pixel, value in specials:
        if names:
            channels[names[i]].reshape(-1)[pixel] = value
    dtype = np.float16 if half else np.float32
    with np.errstate(over="ignore"):  # a drawn value beyond half is written as inf, as a renderer would
        channels = {n: v.astype(dtype) for n, v in channels.items()}
    header = {"samplesPerPixel": draw(st.sampled_from([1, 16, 0, -3]))} if layout == "pbrt" else {}
    window = ((x0, y0), (x0 + w - 1, y0 + h - 1))
    return channels, header, window


def _write(tmp_path, drawn, name="shot-00016spp.exr"):
    channels, header, window = drawn
    header = {**header, "dataWindow": tuple(np.array(c, np.int32) for c in window),
              "displayWindow": tuple(np.array(c, np.int32) for c in window)}
    return write_channels(tmp_path / name, channels, header=header)


def _one_line(exc: KpcnError, path) -> None:
    message = str(exc)
    assert message.strip() and "\n" not in message, repr(message)
    assert str(path) in message, message


def _check_read(path, window, *, alpha: bool = False):
    from prep import layouts

    (x0, y0), (x1, y1) = window
    size = (y1 - y0 + 1, x1 - x0 + 1)
    try:
        header = layouts.read_header(path)
    except KpcnError as exc:
        _one_line(exc, path)
        with pytest.raises(KpcnError):  # what the header refuses, the reader refuses
            layouts.read(path)
        return
    assert header.size == size
    try:
        frame = layouts.read(path)
    except KpcnError as exc:
        _one_line(exc, path)
        return
    assert frame.size == size and frame.layout == header.layout and frame.inputs == header.inputs
    for name, layer in frame.layers.items():
        assert layer.shape[:2] == size, name
        assert layer.dtype == np.float32 and np.all(np.isfinite(layer)), name
    if alpha and frame.alpha is not None:
        assert np.all(np.isfinite(frame.alpha))


@given(drawn=exr_files())
@settings(FUZZ)
def test_any_layout_subset_window_and_values_read_finite_or_refused_in_one_line(drawn, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prop")
    _check_read(_write(tmp, drawn), drawn[2])


@given(drawn=exr_files(whole_layers=False))
@settings(FUZZ)
def test_partial_vector_layers_read_finite_or_refused_in_one_line(drawn, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prop")
    _check_read(_write(tmp, drawn), drawn[2])


@given(drawn=exr_files())
@settings(FUZZ)
def test_alpha_reads_finite(drawn, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prop")
    _check_read(_write(tmp, drawn), drawn[2], alpha=True)


# --- the API -----------------------------------------------------------------------------------------------------

@st.composite
def api_arrays(draw, finite=True):
    """Arguments of ``kpcn.denoise``: a colour of a drawn size (at most 16 x 16) and dtype, with a drawn subset of
    albedo, normal, depth and a variance; values within float32's range (``finite``) or with non-finite ones."""
    h, w = draw(st.integers(1, 16)), draw(st.integers(1, 16))
    dtype = draw(st.sampled_from([np.float16, np.float32, np.float64]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    top = HALF_MAX if dtype == np.float16 else 1e30

    def array(shape, low=0.0):
        a = rng.uniform(low, 1.0, shape) * 10.0 ** draw(st.integers(-6, 3))
        for _ in range(draw(st.integers(0, 2))):
            pool = [0.0, top, -top if low < 0 else 0.0] + ([] if finite else [math.nan, math.inf, -math.inf, 1e300])
            a.reshape(-1)[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from(pool))
        return a.astype(dtype) if finite else a

    kwargs = {"color": array((h, w, draw(st.sampled_from([3, 4]))))}
    for name, shape, low in (("albedo", (h, w, 3), 0.0), ("normal", (h, w, 3), -1.0), ("depth", (h, w), 0.0),
                             ("variance", draw(st.sampled_from([(h, w), (h, w, 3)])), 0.0)):
        if draw(st.booleans()):
            kwargs[name] = array(shape, low)
    return kwargs


def _check_denoise(kwargs):
    import kpcn

    h, w = kwargs["color"].shape[:2]
    try:
        out = kpcn.denoise(**kwargs)
    except KpcnError as exc:
        assert str(exc).strip() and "\n" not in str(exc), repr(str(exc))
        return
    assert out.shape == (h, w, 3) and out.dtype == np.float32
    assert np.all(np.isfinite(out)), f"{int((~np.isfinite(out)).sum())} non-finite of {out.size}"


@given(kwargs=api_arrays())
@settings(FUZZ, max_examples=max(FUZZ.max_examples // 3, 1))
def test_denoise_of_arrays_in_float32_range_is_finite_and_of_the_input_size(kwargs):
    _check_denoise(kwargs)


@given(kwargs=api_arrays(finite=False))
@settings(FUZZ, max_examples=max(FUZZ.max_examples // 3, 1))
def test_denoise_of_arrays_with_non_finite_values_is_finite_or_refused_in_one_line(kwargs):
    _check_denoise(kwargs)
