"""Training batches read from HDF5 shards (``prep.shards`` layout) for ``model.fit``.

One :class:`ShardPatches` serves one training phase (``kpcn_keras.train``); ``source`` says what a batch is:

============  ===========================================================  =================================
source        x (network input, ``models.network_input``)                   y (target)
============  ===========================================================  =================================
``diffuse``   the diffuse features + conditioning channels (B, P, P, C)     diffuse reference, log domain
``specular``  likewise, specular                                            specular reference, log domain
``both``      each patch from one of the two branches (a shared network)    that branch's reference
``final``     ``{"diffuse_input", "specular_input", "albedo"}``              reference final colour, linear
``albedo``    ``{"features", "irradiance", "specular"}``: the albedo        reference final colour, linear
              network's input (``models.albedo_input``), the reference's
              irradiance and specular colour (log domain)
============  ===========================================================  =================================

The features are not stored: each batch's are recomputed from the stored per-pixel buffers of its patches,
once per branch for the whole batch (``prep.shards.derive``, by ``prep.features.features_from_buffers``, the
function that makes them at render time; their error against full precision: docs/formats.md §4).

``loss_target`` extends y for the asymmetric loss: ``"reference+noisy"`` appends the noisy colour of the same
domain (6 channels), and a network with a slope channel gets λ as a seventh, the same λ its input carries.
``target_input`` (the ``final`` source only) also gives x the target, as ``x["target"]``: the compositor
phase's per-scale supervision takes it down the pyramid inside the model (``multiscale.ScaleSupervision``).

``reference_relse`` (a branch source only) appends, last of all, the branch reference's relative standard
error per pixel (the shards' ``<branch>/ref_relse``), for the reference-weighted loss (``kpcn_keras.losses``):
moved by the patch's flip or rotation like the reference, never colour-permuted (it is one channel, the
reference's mean over R G B, which a permutation leaves as it is).

Per patch, a training stream draws (from a generator seeded by (seed, batch number), so resume is exact):
an augmentation (``kpcn_keras.augment``: one of 8 flips/rotations times one of 6 colour permutations), and,
for a network with a slope channel, λ log-uniform in ``slope_range`` (with a specialisation module, a λ map
of the patch's size instead: ``kpcn_keras.slope_map.draw``), and with ``firefly_rate`` > 0 (a branch source) a
Poisson number of synthetic fireflies (``kpcn_keras.fireflies``) added to its stored buffers before its features
are made, with variance where ``variance`` says the shard set has it. A validation stream (``shuffle=False``)
augments nothing, adds no fireflies and uses the fixed ``slope``.

Files are opened lazily, once per process, so a dataset object can be pickled into workers. Batch ``i`` is
a pure function of (seed, offset + i): patches are visited in a fresh seeded permutation every pass over
the data, so a resumed run sees exactly the batches that an uninterrupted run would have seen. With
``weights`` (one per shard: the resample loop's weighting of rounds) each batch is instead drawn with
replacement, a patch with probability proportional to its shard's weight, from a generator seeded by
(seed, offset + i).

**Data-parallel training** (``rank`` of ``world`` processes): batch ``i`` of the stream is a *global* batch
of ``world * batch_size`` patches, drawn, augmented and given λ exactly as one process with that batch
size would; process ``rank`` reads and serves its own ``batch_size`` of them, the ``rank``-th slice. So in
one pass over the data no two processes read the same patch, each pass is reshuffled with the seed, and
the processes' batches put together are the one-process batch, bit for bit: with equal slices, the mean of
their gradients is the gradient of that batch. A validation stream is not split: every process reads all
of it, so each reports the same validation loss.
"""

from __future__ import annotations

import math
import os

import h5py
import keras
import numpy as np

from kpcn_keras import augment, fireflies, slope_map
from kpcn_keras.models import FINAL_INPUTS, ModelConfig, albedo_input, network_input
from prep.bounds import is_integer
from prep.features import BRANCHES
from prep.shards import ShardError, branch_datasets, derive, open_shard, read_stored, stored_datasets

SOURCES = BRANCHES + ("both", "final", "albedo")
LOSS_TARGETS = ("reference", "reference+noisy")


class _Datasets(dict):
    """The datasets of one open shard by name, each looked up once: h5py's name lookup cost about a fifth of
    reading a training batch (1.1 of 6 ms for 8 patches)."""

    def __init__(self, file: h5py.File):
        super().__init__()
        self.file = file

    def __missing__(self, name: str):
        self[name] = self.file[name]
        return self[name]


class ShardPatches(keras.utils.PyDataset):
    """Batches ``(x, y)`` of one training phase (module docstring), for the network ``model`` (its
    conditioning channels; default: a network without any).

    ``steps`` batches are served (default: one pass); ``offset`` skips that many batches of the stream
    (resume); ``shuffle=False`` serves patches in shard order without augmentation (validation);
    ``weights`` (one per path, > 0) draws training patches in proportion to them; ``rank`` and ``world``:
    this process's slice of each global batch of ``world * batch_size`` (module docstring).
    """

    def __init__(self, paths, source: str, batch_size: int, steps: int | None = None, *,
                 model: ModelConfig | None = None, shuffle: bool = True, seed: int = 0, offset: int = 0,
                 loss_target: str = "reference", augment: bool = False, slope: float = 2.0,
                 slope_range: tuple[float, float] = (1.0, 8.0),
                 weights=None, rank: int = 0, world: int = 1, reference_relse: bool = False,
                 target_input: bool = False, firefly_rate: float = 0.0, variance: bool = True, **kwargs):
        super().__init__(**kwargs)
        if source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
        if loss_target not in LOSS_TARGETS:
            raise ValueError(f"loss_target must be one of {LOSS_TARGETS}, got {loss_target!r}")
        if source == "albedo" and loss_target != "reference":
            raise ValueError(f"the albedo source's target is the reference alone, got loss_target {loss_target!r}")
        if reference_relse and source not in BRANCHES + ("both",):
            raise ValueError(f"reference_relse is a branch reference's: source {source!r} has none")
        if not (isinstance(firefly_rate, (int, float)) and 0 <= firefly_rate < math.inf):
            raise ValueError(f"firefly_rate must be a number of spikes a patch >= 0, got {firefly_rate!r}")
        if firefly_rate and source not in BRANCHES + ("both",):
            raise ValueError(f"fireflies are added to a branch's colour: source {source!r} has none")
        if target_input and source != "final":
            raise ValueError(f"target_input is the final colour's: source {source!r} gives x one tensor")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if not is_integer(world) or world < 1:
            raise ValueError(f"world must be an integer >= 1, got {world!r}")
        if not is_integer(rank) or not 0 <= rank < world:
            raise ValueError(f"rank must be an integer in [0, {world}), got {rank!r}")
        self.paths = [str(p) for p in paths]
        if not self.paths:
            raise ShardError(f"no shards given for the {source} patches")
        model = ModelConfig() if model is None else model
        self.source, self.model, self.batch_size, self.shuffle, self.seed = source, model, batch_size, shuffle, seed
        self.offset, self.loss_target, self.reference_relse = offset, loss_target, reference_relse
        self.rank, self.world, self.target_input = rank, world, target_input
        # a validation stream is read whole by every process: each reports the same validation loss
        self.global_batch = batch_size * world if shuffle else batch_size
        self.augment = augment and shuffle
        self.firefly_rate = float(firefly_rate) if shuffle else 0.0  # validation: the patches as rendered
        self.variance = variance
        self.slope, self.slope_range = slope, tuple(slope_range)
        counts, sizes = [], set()
        for p in self.paths:
            with open_shard(p) as f:
                counts.append(len(f["source"]))
                sizes.add(int(f.attrs["patch_size"]))
        if len(sizes) != 1:
            raise ShardError(f"the shards {self.paths[0]} ... hold patches of sizes {sorted(sizes)}; one set has one")
        self.patch_size = sizes.pop()
        # (branch, shard, patch) of every sample, in shard order; a shared network sees each patch once
        # per branch, so both branches weigh the same
        branches = range(len(BRANCHES)) if source == "both" else [BRANCHES.index(source) if source in BRANCHES else -1]
        self.index = np.array([(b, s, i) for b in branches for s, n in enumerate(counts) for i in range(n)],
                              dtype=np.int64)
        self.probabilities = None
        if weights is not None:
            weights = np.asarray(weights, dtype=np.float64)
            if weights.shape != (len(self.paths),) or not np.all(np.isfinite(weights)) or np.any(weights <= 0):
                raise ValueError(f"weights must be {len(self.paths)} finite numbers > 0 (one per shard), got {weights}")
            per_patch = weights[self.index[:, 1]]
            self.probabilities = per_patch / per_patch.sum()
        if len(self.index) < self.global_batch:
            processes = f" x {world} processes" if self.global_batch > batch_size else ""
            raise ShardError(f"{len(self.index)} patches in {len(self.paths)} shard(s), fewer than "
                             f"batch_size={batch_size}{processes}")
        per_pass = len(self.index) // self.global_batch if shuffle else -(-len(self.index) // self.global_batch)
        self.steps = per_pass if steps is None else int(steps)
        self._files: dict[int, list[_Datasets]] = {}

    def __len__(self):
        return self.steps

    def _global_ids(self, i: int) -> np.ndarray:
        """(branch, shard, patch) of every patch of global batch ``i``, in order."""
        g = self.global_batch
        if not self.shuffle:
            return self.index[i * g : (i + 1) * g]
        step = self.offset + i
        if self.probabilities is not None:
            rng = np.random.default_rng([self.seed, step, 2])
            return self.index[rng.choice(len(self.index), g, p=self.probabilities)]
        per_pass = len(self.index) // g
        epoch, within = divmod(step, per_pass)
        order = np.random.default_rng([self.seed, epoch]).permutation(len(self.index))
        return self.index[order[within * g : (within + 1) * g]]

    def _mine(self) -> slice:
        """This process's slice of a global batch."""
        if not self.shuffle:
            return slice(None)
        return slice(self.rank * self.batch_size, (self.rank + 1) * self.batch_size)

    def _handles(self) -> list[_Datasets]:
        pid = os.getpid()
        if pid not in self._files:
            self._files = {pid: [_Datasets(open_shard(p)) for p in self.paths]}
        return self._files[pid]

    def _read(self, shard: int, patch: int, stored) -> dict[str, np.ndarray]:
        """The stored datasets ``stored`` of one patch, as stored (``prep.shards.read_stored``)."""
        f = self._handles()[shard]
        try:
            return read_stored(f, stored, patch)
        except OSError as exc:  # a chunk whose Fletcher-32 checksum fails, or a damaged file
            raise ShardError(
                f"{self.paths[shard]}: cannot read patch {patch} ({exc}); run 'kpcn shards' again to rebuild it"
            ) from None

    def _names(self, branch: str | None) -> list[str]:
        """What a sample of ``branch`` (None: the final colour) reads (``prep.shards.VIEWS``)."""
        with_noisy = self.loss_target == "reference+noisy"  # else the noisy colour is not read at all
        if self.source == "albedo":
            return ["diffuse/features", "albedo"] + [f"{b}/reference" for b in BRANCHES] + ["reference"]
        if branch is None:
            return [f"{b}/features" for b in BRANCHES] + ["albedo", "reference"] + (["noisy"] if with_noisy else [])
        return branch_datasets(branch, noisy=with_noisy) + ([f"{branch}/ref_relse"] if self.reference_relse else [])

    def _batch_data(self, ids, spikes) -> list[dict[str, np.ndarray]]:
        """The float32 data of each (branch, shard, patch) of ``ids``: the stored datasets read one patch at a
        time, each patch's ``spikes`` added (``kpcn_keras.fireflies``), then made into what is read (the features
        recomputed) once per branch for the whole batch (``prep.shards.derive``, vectorised over the batch)."""
        out: list = [None] * len(ids)
        groups: dict[int, list[int]] = {}
        for k, (b, _, _) in enumerate(ids):
            groups.setdefault(int(b), []).append(k)
        for b, members in groups.items():
            names = self._names(BRANCHES[b] if b >= 0 else None)
            stored = stored_datasets(names)
            reads = [self._read(int(ids[k][1]), int(ids[k][2]), stored) for k in members]
            if b >= 0:
                reads = [fireflies.inject(r, BRANCHES[b], spikes[k], self.variance) for r, k in zip(reads, members)]
            data = derive({n: np.stack([r[n] for r in reads]) for n in stored}, names, self.patch_size)
            for j, k in enumerate(members):
                out[k] = {n: a[j] for n, a in data.items()}
        return out

    def _slopes(self, rng: np.random.Generator, n: int) -> list:
        if not self.model.slope_channel:
            return [None] * n
        if not self.shuffle:
            return [self.slope] * n
        if self.model.slope_module:  # a map per patch, λ varying inside it
            return [slope_map.draw(rng, self.patch_size, self.slope_range) for _ in range(n)]
        lo, hi = self.slope_range
        return list(np.exp(rng.uniform(math.log(lo), math.log(hi), n)))

    def __getitem__(self, i):
        if not 0 <= i < self.steps:
            raise IndexError(f"batch {i} out of range [0, {self.steps})")
        ids = self._global_ids(i)
        # one generator per batch number: what a patch gets does not depend on which batches ran before,
        # nor on which process reads it (the whole global batch draws, each process keeps its slice)
        rng = np.random.default_rng([self.seed, self.offset + i, 1])
        augs = [augment.draw(rng) if self.augment else augment.IDENTITY for _ in ids]
        slopes = self._slopes(rng, len(ids))
        spikes = [fireflies.draw(rng, self.firefly_rate, self.patch_size) for _ in ids]
        mine = self._mine()
        samples = [self._sample(int(b), data, aug, slope)
                   for (b, _, _), data, aug, slope in zip(ids[mine], self._batch_data(ids[mine], spikes[mine]),
                                                           augs[mine], slopes[mine])]
        x = samples[0][0]
        if isinstance(x, dict):
            x = {k: np.stack([s[0][k] for s in samples]) for k in x}
        else:
            x = np.stack([s[0] for s in samples])
        y = np.stack([s[1] for s in samples])
        if self.target_input:
            x["target"] = y
        return x, y

    def _sample(self, branch_id: int, data: dict[str, np.ndarray], aug, slope):
        with_noisy = self.loss_target == "reference+noisy"
        if self.source == "albedo":
            features = albedo_input(augment.augment_features(data["diffuse/features"], aug),
                                    augment.augment_colour(data["albedo"], aug))
            x = {"features": network_input(features, self.model, "diffuse"),
                 "irradiance": augment.augment_colour(data["diffuse/reference"], aug),
                 "specular": augment.augment_colour(data["specular/reference"], aug)}
            reference, noisy = data["reference"], None
        elif self.source == "final":
            x = {FINAL_INPUTS[b]: network_input(augment.augment_features(data[f"{b}/features"], aug),
                                                self.model, b, slope) for b in BRANCHES}
            x["albedo"] = augment.augment_colour(data["albedo"], aug)
            reference, noisy = data["reference"], data.get("noisy")
        else:
            branch = BRANCHES[branch_id]
            x = network_input(augment.augment_features(data[f"{branch}/features"], aug), self.model, branch, slope)
            reference, noisy = data[f"{branch}/reference"], data.get(f"{branch}/noisy")
        y = [augment.augment_colour(reference, aug)]
        if with_noisy:
            y.append(augment.augment_colour(noisy, aug))
            if slope is not None:
                y.append(np.broadcast_to(np.asarray(slope, np.float32), reference.shape[:-1])[..., None])
        if self.reference_relse:
            y.append(augment.augment_spatial(data[f"{branch}/ref_relse"], aug))
        if len(y) == 1:
            return x, y[0]
        return x, np.concatenate(y, axis=-1).astype(np.float32)

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_files"] = {}
        return state
