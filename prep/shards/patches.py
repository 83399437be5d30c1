"""The per-image step of every round: an input's PDF over its patch positions (:func:`round_pdf`: the
variance PDF, mixed in an error round with an error map's), the positions drawn from it
(:func:`draw`, a generator per input and round: :func:`round_rng`), and the patches cut at them from the
full-image datasets of the shard table (:class:`ImagePatches`). Every round goes through it, round 0
(:func:`variance_patches`) as every error round, and hands its patches to the same writer
(``prep.shards.writer``). Deterministic: the same renders, configuration and round give the same patches.

A set of an input set other than the full one (``ShardConfig.inputs``) cuts its patches from the layers a
model of that set reads (:func:`shard_layers`: ``prep.inputs.restrict`` of the render, its reference's colours
split the same way), at the positions drawn from the render as it is: the renders a set is cut from are
``kpcn render``'s, which have every layer, so every input set of a render set holds its patches at the same
positions, and the variance PDF stays the variance's where the model is given none. Renders without variance
layers (another renderer's, ``kpcn import-renders``) can be cut for the input sets without variance
alone; their PDF reads their error to the reference instead (:func:`round_pdf`).

A set cut with prefiltered auxiliaries (``ShardConfig.auxiliaries``) cuts its patches from
``prep.auxiliary.network_layers`` of each noisy input (the whole frame prefiltered once, before any patch is cut:
what the denoiser gives its networks); the reference is as it is, and the positions are drawn from the render as
it is (the PDF reads the variance and colour layers, which no prefilter changes), so they are the raw set's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prep import colour, convergence, features, sampling
from prep.auxiliary import RAW, network_layers
from prep.exr import VARIANCE_LAYERS
from prep.inputs import InputSet, restrict
from prep.shards.config import ShardConfig
from prep.shards.format import DATASETS, RELSE_MAX, empty_patches, to_half


def noisy_variances(inputs: InputSet) -> bool | None:
    """``exr.read_aovs``'s ``variances`` for a set's inputs: every variance layer where its model reads them, else
    those the render has (another renderer's may have none: :func:`round_pdf` then reads its reference)."""
    return True if inputs.variance else None


def shard_layers(noisy: dict, reference: dict, inputs: InputSet, auxiliaries: str = RAW) -> tuple[dict, dict]:
    """The layers the patches of a set of ``inputs`` and ``auxiliaries`` are cut from: the noisy render as a
    model of that set reads it (``prep.auxiliary.network_layers``: ``prep.inputs.restrict``, then the
    auxiliaries prefiltered), and the reference restricted alike: a no-split set's diffuse
    reference is the total colour, and its variance ``colorVariance``, whatever the set's inputs (the
    reference's variance is no network input, only its ``ref_relse``). A reference without every variance
    layer (read with ``variances=None``: another renderer's) is given zeros, so its ``ref_relse`` is 0."""
    has_variance = all(name in reference for name in VARIANCE_LAYERS)
    given = InputSet(split=inputs.split, variance=has_variance)
    return network_layers(noisy, inputs, auxiliaries), restrict(reference, given)


def image_datasets(noisy: dict, reference: dict) -> dict[str, np.ndarray]:
    """Full-image arrays of every per-patch dataset of the shard table (``prep.shards.format.DATASETS``), for
    one (noisy, reference) pair, in its dtype: a dataset with a border is (H + 1, W + 1, C), the last row and
    column repeated (``prep.features.branch_buffers``), so a patch at (y, x) is [y : y + P + 1, x : x + P + 1].
    The float16 ones are rounded once from the float64 buffers, kept inside their features' ranges
    (``to_half``)."""
    scale = features.depth_scale(noisy["depth"])
    out = {}
    for b in features.BRANCHES:
        buffers, relvar = features.branch_buffers(noisy, b, scale=scale)
        out[f"{b}/log_colour"] = to_half(buffers[..., features.COLOUR], colour.LOG_COLOUR_MAX)
        out[f"{b}/relvar"] = to_half(relvar[..., :1], colour.RELVAR_MAX)
        # the guides are the same for both branches (the kernel computes them alike): the specular's are kept.
        # Normal, albedo and depth lie in [-1, 1], where float16 rounding stays
        out["guides"] = buffers[..., features.COLOUR.stop:].astype(np.float16)
        out["guide_relvar"] = to_half(relvar[..., 1:], colour.RELVAR_MAX)
        out[f"{b}/reference"] = features.branch_colour(reference, b)
        out[f"{b}/ref_relse"] = to_half(convergence.branch_relse(reference, b)[..., None], RELSE_MAX)
    out["noisy"] = noisy["default"]
    out["reference"] = reference["default"]
    return out


@dataclass
class ImagePatches:
    """The patches that one input render gives to one round: the positions drawn for it (:func:`draw`), and
    the full-image datasets they are cut from. Every round (variance or error PDF) goes through this."""

    source_id: int
    round: int
    patch_size: int
    positions: np.ndarray  # (n, 2) int32, top-left (y, x), in drawing order
    pdf: np.ndarray  # (n,) float64, probability of each position under the round's PDF
    images: dict[str, np.ndarray]

    @classmethod
    def at(cls, noisy: dict, reference: dict, positions: np.ndarray, pdf: np.ndarray, *, source_id: int, round: int,
           patch_size: int) -> ImagePatches:
        images = image_datasets(noisy, reference)
        if set(images) != set(DATASETS):  # a patch of a dataset not cut would be written uninitialised
            raise KeyError(f"image_datasets gives {sorted(images)}, the shard table has {sorted(DATASETS)}")
        return cls(source_id, round, patch_size, positions, pdf, images)

    def cut(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Patches ``start:stop`` (in drawing order) with their provenance datasets."""
        out = empty_patches(stop - start, self.patch_size)
        self.cut_into(start, stop, out, 0)
        return out

    def cut_into(self, start: int, stop: int, out: dict[str, np.ndarray], at: int) -> None:
        """Patches ``start:stop`` into rows ``at:`` of ``out`` (:func:`empty_patches`): a shard's arrays are
        filled in place, never stacked and concatenated (that copying was a tenth of the writer's time)."""
        pos = self.positions[start:stop]
        rows = slice(at, at + len(pos))
        for name, image in self.images.items():
            target = out[name]
            side = target.shape[1]  # the patch size, or one more for a dataset with a border
            for k, (y, x) in enumerate(pos):
                target[at + k] = image[y : y + side, x : x + side]
        out["source"][rows] = self.source_id
        out["position"][rows] = pos
        out["round"][rows] = self.round
        out["pdf"][rows] = self.pdf[start:stop]


def round_pdf(noisy: dict, config: ShardConfig, error: np.ndarray | None = None,
              error_weight: float = 0.0, reference: dict | None = None) -> np.ndarray:
    """A round's PDF over the patch positions of one input: its variance PDF (docs/method.md §3), and in an
    error round (docs/method.md §8) ``error_weight`` times the PDF of the per-pixel ``error`` map (built the same way:
    window sums mixed with ``uniform_mix`` of uniform) plus the rest times the variance PDF. A render without
    variance layers (cut for an input set without variance) takes its variances from its error to
    ``reference`` (``sampling.reference_error_variances``)."""
    if "colorVariance" not in noisy:
        noisy = {**noisy, **sampling.reference_error_variances(noisy, reference)}
    importance = sampling.variance_importance(noisy, config.colour_weight, config.normal_weight)
    pdf = sampling.patch_pdf(importance, config.patch_size, config.uniform_mix)
    if error is None or error_weight == 0.0:
        return pdf
    return sampling.mix_pdfs(sampling.patch_pdf(error, config.patch_size, config.uniform_mix), pdf, error_weight)


def round_rng(config: ShardConfig, source_id: int, k: int) -> np.random.Generator:
    """The generator of one input's draw in round ``k``. Round 0 keeps the (seed, source) stream it has
    always had, so sets cut before rounds existed are still the sets this code cuts."""
    key = [config.seed, source_id] if k == 0 else [config.seed, source_id, k]
    return np.random.default_rng(np.random.SeedSequence(key))


def draw(pdf: np.ndarray, count: int, config: ShardConfig, source_id: int, k: int,
         used: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``count`` positions of one input for round ``k`` (without replacement, never one of ``used``: the
    positions earlier rounds took from it) and each one's probability under the round's PDF (``pdf`` with
    ``used`` removed and renormalised)."""
    if used is not None and len(used):
        pdf = sampling.exclude_positions(pdf, used)
    positions = sampling.draw_positions(pdf, count, round_rng(config, source_id, k))
    return positions, pdf[positions[:, 0], positions[:, 1]]


def variance_patches(noisy: dict, reference: dict, config: ShardConfig, source_id: int) -> ImagePatches:
    """Round 0 of one input: ``patches_per_image`` positions from its variance PDF, the patches cut from the
    layers of the set's input set (:func:`shard_layers`)."""
    positions, pdf = draw(round_pdf(noisy, config, reference=reference), config.patches_per_image, config,
                          source_id, 0)
    layers = shard_layers(noisy, reference, config.input_set, config.auxiliaries)
    return ImagePatches.at(*layers, positions, pdf, source_id=source_id, round=0, patch_size=config.patch_size)
