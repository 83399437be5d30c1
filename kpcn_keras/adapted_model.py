"""An adapted model: a model folder whose denoised frames pass through a post-correction adapted on a shot.

``kpcn adapt`` writes one (:func:`write_adapted`): a copy of the model it started from (hard links where the disk
allows: nothing of it changes), and ``adaptation/`` beside its networks: the post-correction network
(``post.keras``, ``kpcn_keras.adapt``) and ``adaptation.json``, the record of what it was adapted for and on:
the quality mode and the input set it corrects (:class:`Adaptation`), the pairs, the settings, the guard's
outcome and the network file's SHA-256. ``kpcn denoise --run``, ``kpcn evaluate``, ``kpcn view`` and
``kpcn.denoise`` take it as any model folder: ``Serving`` applies the correction to the frames of that mode and
input set (:func:`load_adaptation`), and refuses in one line a frame it was not adapted for.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import keras

from kpcn_keras.adapt import CUSTOM_OBJECTS
from kpcn_keras.run import Run
from prep.errors import KpcnError
from prep.files import sha256_file

ADAPTATION = "adaptation"  # the folder of a model's post-correction
POST_FILE = "post.keras"
RECORD_FILE = "adaptation.json"


@dataclass(frozen=True)
class Adaptation:
    """A model's post-correction (``post``), for frames of quality mode ``quality`` and input set ``inputs`` (its
    name, ``prep.inputs``), and its ``record`` (``adaptation.json`` as read)."""

    quality: str
    inputs: str
    post: keras.Model
    record: dict

    def check(self, model: Run, quality: str, inputs: str) -> None:
        """KpcnError in one line unless a frame of ``inputs`` denoised at ``quality`` is what this corrects."""
        if (quality, inputs) != (self.quality, self.inputs):
            raise KpcnError(f"{model.dir} was adapted for {self.inputs} frames at quality {self.quality}; this is a "
                            f"{inputs} frame at quality {quality} (denoise it with the model {self.record['source']})")


def load_adaptation(model: Run) -> Adaptation | None:
    """The post-correction of the model folder ``model``, or None where it has none (or its guard kept none);
    KpcnError naming the file
    where its record cannot be read or its network is not the file the record lists (SHA-256)."""
    folder = model.dir / ADAPTATION
    if not folder.is_dir():
        return None
    path = folder / RECORD_FILE
    try:
        record = json.loads(path.read_text())
        if not record["corrects"]:
            return None  # the guard kept the model as it was
        quality, inputs, digest = record["quality"], record["inputs"], record["sha256"][POST_FILE]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise KpcnError(f"{path}: not an adaptation record ({exc!r})") from None
    post_path = folder / POST_FILE
    if not post_path.is_file() or sha256_file(post_path) != digest:
        raise KpcnError(f"{post_path}: missing or not the network {path} lists (SHA-256)")
    return Adaptation(quality, inputs, keras.models.load_model(post_path, custom_objects=CUSTOM_OBJECTS), record)


def write_adapted(source: Run, out, post: keras.Model | None, record: dict) -> Path:
    """The model folder ``out``: a copy of ``source`` with ``post`` and ``record`` (plus the network's SHA-256) in
    ``adaptation/``, written under a temporary name and renamed, so ``out`` is whole or absent. ``post`` None (the
    guard kept the model as it was; ``record["corrects"]`` False): the record alone, and the folder serves as
    ``source``'s networks do. KpcnError where
    ``out`` exists (an adapted model is not written over)."""
    out = Path(out)
    if out.exists():
        raise KpcnError(f"{out} exists: give --out a new folder")
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        shutil.copytree(source.dir, tmp, copy_function=_link_or_copy, ignore=shutil.ignore_patterns(ADAPTATION))
        folder = tmp / ADAPTATION
        folder.mkdir()
        if post is not None:
            post.save(folder / POST_FILE)
            record = {**record, "sha256": {POST_FILE: sha256_file(folder / POST_FILE)}}
        (folder / RECORD_FILE).write_text(json.dumps(record, indent=1) + "\n")
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _link_or_copy(src, dst) -> None:
    """A hard link where the file system allows it (the model's files are read, never changed), else a copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


__all__ = ["ADAPTATION", "Adaptation", "load_adaptation", "write_adapted"]
