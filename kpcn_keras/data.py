"""Training batches read from HDF5 shards (``prep.shards`` layout) for ``model.fit``.

Files are opened lazily, once per process, so a dataset object can be pickled into workers.
Batch ``i`` is a pure function of (seed, offset + i): patches are visited in a fresh seeded
permutation every pass over the data, so a resumed run sees exactly the batches that an
uninterrupted run would have seen.
"""

from __future__ import annotations

import os

import h5py
import keras
import numpy as np

from prep.shards import ShardError, open_shard

TARGETS = ("reference", "reference+noisy")


class ShardPatches(keras.utils.PyDataset):
    """Batches ``(features, target)`` of one branch.

    ``features`` is ``<branch>/features`` (B, P, P, 27). ``target`` is ``<branch>/reference``
    (B, P, P, 3), or with ``target="reference+noisy"`` the reference and the noisy colour
    concatenated on channels (B, P, P, 6), the layout the asymmetric loss expects.
    ``steps`` batches are served; ``offset`` skips that many batches of the stream (resume);
    ``shuffle=False`` serves patches in shard order (validation).
    """

    def __init__(self, paths, branch: str, batch_size: int, steps: int | None = None, *,
                 shuffle: bool = True, seed: int = 0, offset: int = 0, target: str = "reference", **kwargs):
        super().__init__(**kwargs)
        if branch not in ("diffuse", "specular"):
            raise ValueError(f"branch must be 'diffuse' or 'specular', got {branch!r}")
        if target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.paths = [str(p) for p in paths]
        if not self.paths:
            raise ShardError(f"no shards given for the {branch} branch")
        self.branch, self.batch_size, self.shuffle, self.seed = branch, batch_size, shuffle, seed
        self.offset, self.target = offset, target
        counts = []
        for p in self.paths:
            with open_shard(p) as f:
                counts.append(len(f["source"]))
        # (shard, patch) of every patch, in shard order
        self.index = np.array([(s, i) for s, n in enumerate(counts) for i in range(n)], dtype=np.int64)
        if len(self.index) < batch_size:
            raise ShardError(f"{len(self.index)} patches in {len(self.paths)} shard(s), fewer than batch_size={batch_size}")
        per_pass = len(self.index) // batch_size if shuffle else -(-len(self.index) // batch_size)
        self.steps = per_pass if steps is None else int(steps)
        self._files: dict[int, list[h5py.File]] = {}

    def __len__(self):
        return self.steps

    def _patch_ids(self, i: int) -> np.ndarray:
        if not self.shuffle:
            return self.index[i * self.batch_size : (i + 1) * self.batch_size]
        step = self.offset + i
        per_pass = len(self.index) // self.batch_size
        epoch, within = divmod(step, per_pass)
        order = np.random.default_rng([self.seed, epoch]).permutation(len(self.index))
        return self.index[order[within * self.batch_size : (within + 1) * self.batch_size]]

    def _handles(self) -> list[h5py.File]:
        pid = os.getpid()
        if pid not in self._files:
            self._files = {pid: [open_shard(p) for p in self.paths]}
        return self._files[pid]

    def __getitem__(self, i):
        if not 0 <= i < self.steps:
            raise IndexError(f"batch {i} out of range [0, {self.steps})")
        files = self._handles()
        ids = self._patch_ids(i)
        x, y, noisy = [], [], []
        for shard, patch in ids:
            f = files[shard]
            try:
                x.append(f[f"{self.branch}/features"][patch])
                y.append(f[f"{self.branch}/reference"][patch])
                if self.target == "reference+noisy":
                    noisy.append(f[f"{self.branch}/noisy"][patch])
            except OSError as exc:  # a chunk whose Fletcher-32 checksum fails, or a damaged file
                raise ShardError(
                    f"{self.paths[shard]}: cannot read patch {patch} ({exc}); run 'kpcn shards' again to rebuild it"
                ) from None
        x, y = np.stack(x), np.stack(y)
        if noisy:
            y = np.concatenate([y, np.stack(noisy)], axis=-1)
        return x, y

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_files"] = {}
        return state
