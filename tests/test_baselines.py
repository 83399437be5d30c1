"""The OIDN anchor (``prep.baselines``): both modes equal a direct ``pyoidn`` call sequence on the same arrays, the
prefiltered one (as Blender runs OIDN) differs from the plain one on a noisy frame, and a frame is judged against
the strongest of the anchors it has."""

from pathlib import Path

import numpy as np
import pytest

from prep import baselines

needs_oidn = pytest.mark.skipif(not baselines.oidn_available(), reason="pyoidn not installed (pip install '.[oidn]')")


def _noisy_frame(size=40, seed=0) -> dict[str, np.ndarray]:
    """A frame with edges in colour, albedo and normal, each layer noisy as a few samples leave it."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    albedo = np.stack([0.2 + 0.6 * (x > 0.5), 0.3 + 0.4 * (y > 0.4), np.full_like(x, 0.5)], -1)
    normal = np.stack([np.where(x + y > 1, 0.6, 0.0), np.zeros_like(x), np.where(x + y > 1, 0.8, 1.0)], -1)
    clean = albedo * (0.5 + 2.0 * np.exp(-((x - 0.3) ** 2 + (y - 0.6) ** 2) / 0.02))[..., None]
    return {"default": (clean * rng.exponential(1.0, clean.shape)).astype(np.float32),
            "albedo": np.clip(albedo + 0.15 * rng.standard_normal(albedo.shape), 0, 1).astype(np.float32),
            "normal": np.clip(normal + 0.3 * rng.standard_normal(normal.shape), -1, 1).astype(np.float32)}


def _by_hand(colour: np.ndarray, albedo: np.ndarray, normal: np.ndarray, quality=None) -> np.ndarray:
    """OIDN's prefiltering recipe written out with pyoidn's filters on one fresh device: an RT filter with the
    albedo as its only input, one with the normal as its only input, then the colour's RT filter with the cleaned
    layers, HDR and cleanAux set; every filter at ``quality`` (an OIDN_QUALITY_* constant; high where None), as
    Blender's Cycles sets its one denoising quality on the prefilters and the colour filter alike."""
    import pyoidn

    quality = pyoidn.OIDN_QUALITY_HIGH if quality is None else quality

    def run(images: dict, **flags) -> np.ndarray:
        out = np.zeros_like(next(iter(images.values())))
        with pyoidn.Filter(device, "RT") as flt:
            for name, image in images.items():
                flt.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
            flt.set_image("output", out, pyoidn.OIDN_FORMAT_FLOAT3)
            for name, value in flags.items():
                flt.set_bool(name, value)
            flt.set_int("quality", quality)
            flt.commit()
            flt.execute()
        assert device.get_error() is None
        return out

    with pyoidn.Device() as device:
        device.commit()
        albedo_clean = run({"albedo": albedo})
        normal_clean = run({"normal": normal})
        return run({"color": colour, "albedo": albedo_clean, "normal": normal_clean}, hdr=True, cleanAux=True)


@needs_oidn
def test_prefiltered_oidn_equals_the_three_filters_called_by_hand_and_differs_from_plain():
    aovs = _noisy_frame()
    colour, albedo, normal = (np.ascontiguousarray(aovs[k]) for k in ("default", "albedo", "normal"))
    prefiltered = baselines.oidn_denoise(aovs, mode="prefiltered")
    assert prefiltered.shape == colour.shape and prefiltered.dtype == np.float32
    np.testing.assert_array_equal(prefiltered, _by_hand(colour, albedo, normal))
    assert np.array_equal(baselines.oidn_denoise(aovs), prefiltered)  # the default mode is the anchor

    import pyoidn

    plain = baselines.oidn_denoise(aovs, mode="plain")
    np.testing.assert_array_equal(plain, pyoidn.denoise(colour, albedo=albedo, normal=normal, hdr=True))
    # the noisy auxiliaries change what the colour filter makes of them: not the plain mode under a new name
    assert np.mean(np.abs(prefiltered - plain)) > 1e-3 * np.mean(plain)


@needs_oidn
def test_both_modes_clip_the_layers_to_what_oidn_takes():
    aovs = _noisy_frame(seed=1)
    colour, albedo, normal = (aovs[k].copy() for k in ("default", "albedo", "normal"))
    dirty = {"default": colour.copy(), "albedo": albedo.copy(), "normal": normal.copy()}
    dirty["default"][0, 0] = [np.nan, -1.0, 0.5]
    dirty["albedo"][1, 1] = [1.5, -0.5, np.nan]
    dirty["normal"][2, 2] = [2.0, -3.0, np.nan]
    clean = {"default": dirty["default"].copy(), "albedo": dirty["albedo"].copy(), "normal": dirty["normal"].copy()}
    clean["default"][0, 0] = [0.0, 0.0, 0.5]
    clean["albedo"][1, 1] = [1.0, 0.0, 0.0]
    clean["normal"][2, 2] = [1.0, -1.0, 0.0]
    for mode in baselines.OIDN_MODES:
        out = baselines.oidn_denoise(dirty, mode=mode)
        assert np.isfinite(out).all()
        np.testing.assert_array_equal(out, baselines.oidn_denoise(clean, mode=mode))


def test_an_unknown_mode_is_refused_naming_the_modes():
    with pytest.raises(ValueError, match="plain, prefiltered"):
        baselines.oidn_denoise(_noisy_frame(8), mode="accurate")
    with pytest.raises(ValueError, match="OIDN quality 'ultra': expected one of fast, balanced, high"):
        baselines.oidn_denoise(_noisy_frame(8), quality="ultra")


@needs_oidn
def test_each_oidn_quality_equals_pyoidns_filters_at_that_quality_by_hand():
    import pyoidn

    aovs = _noisy_frame(seed=2)
    colour, albedo, normal = (np.ascontiguousarray(aovs[k]) for k in ("default", "albedo", "normal"))
    levels = {"fast": pyoidn.OIDN_QUALITY_FAST, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
              "high": pyoidn.OIDN_QUALITY_HIGH}
    assert tuple(levels) == baselines.OIDN_QUALITIES
    outs = {}
    for quality, level in levels.items():
        outs[quality] = baselines.oidn_denoise(aovs, mode="prefiltered", quality=quality)
        np.testing.assert_array_equal(outs[quality], _by_hand(colour, albedo, normal, level))
        np.testing.assert_array_equal(baselines.oidn_denoise(aovs, mode="plain", quality=quality),
                                      pyoidn.denoise(colour, albedo=albedo, normal=normal, hdr=True, quality=level))
    assert np.array_equal(baselines.oidn_denoise(aovs), outs["high"])  # the default quality is OIDN's own: high
    assert np.mean(np.abs(outs["fast"] - outs["high"])) > 1e-4 * np.mean(outs["high"])  # another network


def test_a_frame_is_judged_against_the_strongest_anchor_it_has():
    def s(relmse):
        return {"relmse": relmse, "dssim": 0.1}

    assert baselines.anchor({"oidn": s(0.4), "oidn_prefiltered": s(0.3), "blender": s(0.35)}) == \
        ("oidn_prefiltered", s(0.3))
    assert baselines.anchor({"oidn": s(0.2), "oidn_prefiltered": s(0.3)}) == ("oidn", s(0.2))
    assert baselines.anchor({"oidn": s(0.4), "oidn_prefiltered": s(0.3), "blender": s(0.1)})[0] == "blender"
    assert baselines.anchor({"oidn": s(0.3), "oidn_prefiltered": s(0.3)})[0] == "oidn"  # a tie: the first
    assert baselines.anchor({"oidn": None, "blender": s(0.5)})[0] == "blender"  # an anchor that did not run
    assert baselines.anchor({"raw": s(0.9)}) is None


def test_blenders_own_frame_is_named_beside_the_noisy_render():
    assert baselines.renderer_denoised(Path("val/studio-00016spp.exr")) == \
        Path("val/studio-00016spp-blender-oidn.exr")


def test_oidn_is_given_the_auxiliaries_blender_gives_its_own_denoiser_where_the_file_has_them():
    import OpenEXR

    from prep import layouts

    path = Path(__file__).parent / "fixtures" / "renderers" / "cycles5" / "studio-00016spp.exr"
    with OpenEXR.File(str(path), separate_channels=True) as f:
        raw = {n: np.asarray(c.pixels) for part in f.parts for n, c in part.channels.items()}

    def passes(name, comps):
        return np.stack([raw[f"ViewLayer.{name}.{c}"] for c in comps], axis=-1).astype(np.float64)

    frame = layouts.read(path)
    given = baselines.oidn_inputs(frame)
    np.testing.assert_array_equal(given["albedo"], np.clip(passes("Denoising Albedo", "RGB"), 0, 1).astype(np.float32))
    np.testing.assert_array_equal(given["normal"], passes("Denoising Normal", "XYZ").astype(np.float32))
    assert not np.array_equal(given["albedo"], frame.layers["albedo"])  # Diffuse Color: the network's albedo
    assert given["default"] is frame.layers["default"]
    own = layouts.Frame(path=Path("x.exr"), layout="kpcn", layers=frame.layers, inputs=frame.inputs)
    assert baselines.oidn_inputs(own) == frame.layers  # no alternatives: the network's own layers
