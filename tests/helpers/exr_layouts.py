"""EXR files in the layouts other renderers write and kpcn does not: Cycles 5's passes (long names), one part
per pass as Blender 5 splits them."""

from pathlib import Path

import numpy as np


def write_channels(path: Path, channels: dict, parts: dict[str, list[str]] | None = None, header=None) -> Path:
    """An EXR of ``channels`` (full name -> (H, W) array) as a renderer writes it: one part, or with ``parts``
    (part name -> its channel names) one part each; ``header``: attributes. For layouts kpcn does not write."""
    import OpenEXR

    # the binding writes each part's name into the header it is given: each part gets its own copy
    head = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    pix = {k: np.ascontiguousarray(v) for k, v in channels.items()}
    if parts is None:
        with OpenEXR.File(head, pix) as f:
            f.write(str(path))
    else:
        with OpenEXR.File([OpenEXR.Part(dict(head), {c: pix[c] for c in names}, name)
                           for name, names in parts.items()]) as f:
            f.write(str(path))
    return path


CYCLES5_RGB = ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color", "Glossy Direct", "Glossy Indirect",
               "Glossy Color", "Transmission Direct", "Transmission Indirect", "Transmission Color", "Emission",
               "Environment", "Volume Direct", "Volume Indirect", "Denoising Albedo")


def cycles_channels(h: int, w: int, seed: int = 0, view: str = "ViewLayer", noise_seed: int | None = None) -> dict:
    """Random Cycles 5 passes (long names) whose Combined is Cycles' own composition of them, in float64.
    ``seed`` makes the scene; ``noise_seed``, one render of it: each pass times 1 + a uniform noise of ±10%
    drawn from it, so two noise seeds are two renders of one frame with different seeds (``--pair``)."""
    rng = np.random.default_rng(seed)
    passes = {name: rng.uniform(0, 1, (h, w, 3)) for name in CYCLES5_RGB}
    if noise_seed is not None:
        noise = np.random.default_rng(noise_seed)
        passes = {name: p * noise.uniform(0.9, 1.1, p.shape) for name, p in passes.items()}
    combined = (passes["Diffuse Direct"] + passes["Diffuse Indirect"]) * passes["Diffuse Color"]
    for lobe in ("Glossy", "Transmission"):
        combined += (passes[f"{lobe} Direct"] + passes[f"{lobe} Indirect"]) * passes[f"{lobe} Color"]
    combined += passes["Emission"] + passes["Environment"] + passes["Volume Direct"] + passes["Volume Indirect"]
    channels = {f"{view}.{name}.{c}": passes[name][..., i].astype(np.float32)
                for name in CYCLES5_RGB for i, c in enumerate("RGB")}
    channels.update({f"{view}.Combined.{c}": combined[..., i].astype(np.float32) for i, c in enumerate("RGB")})
    channels[f"{view}.Combined.A"] = np.ones((h, w), np.float32)
    normal = rng.uniform(-1, 1, (h, w, 3))
    channels.update({f"{view}.Normal.{c}": normal[..., i].astype(np.float32) for i, c in enumerate("XYZ")})
    channels.update({f"{view}.Denoising Normal.{c}": normal[..., i].astype(np.float32) for i, c in enumerate("XYZ")})
    depth = rng.uniform(1, 5, (h, w))
    depth[0, 0] = 0.0  # a miss
    channels[f"{view}.Denoising Depth.Z"] = depth.astype(np.float32)
    channels[f"{view}.Depth.Z"] = np.where(depth > 0, depth, 1e10).astype(np.float32)
    return channels


def parts_of(channels: dict) -> dict[str, list[str]]:
    """Blender 5's split of channels into parts: one part per pass, named ``<view layer>.<pass>``."""
    parts: dict[str, list[str]] = {}
    for name in channels:
        parts.setdefault(name.rpartition(".")[0], []).append(name)
    return parts


def modified_copy(source: Path, path: Path, changes: dict[str, np.ndarray]) -> Path:
    """A copy of the one-part EXR ``source`` at ``path``, header and every channel kept, with ``changes`` (full
    channel name -> (H, W) array, stored in its dtype) in place of those channels: a renderer's own file with a
    fault put in."""
    import OpenEXR

    with OpenEXR.File(str(source), separate_channels=True) as f:
        header = dict(f.header())
        channels = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
    channels.update({k: np.ascontiguousarray(v) for k, v in changes.items()})
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))
    return path
