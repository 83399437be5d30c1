"""A model as it serves frames: its variants, their records and files, and the denoisers loaded from them.

A :class:`Serving` is one model (a run folder of ``kpcn train`` or a shipped model, a ``Run``) applied with one
:class:`~kpcn_keras.settings.InferenceSettings`. Its quality mode's run (``Run.for_quality`` of
``settings.quality``: the model itself for ``balanced``) is found when it is made, refused in one line where the
model lacks the mode. A frame is denoised by that run's variant trained for what the
frame has (``Run.serving``: the run itself or one of its ``inputs/`` variants); each variant is found, its
record read and its networks loaded (``Denoiser.from_run``; mixed with OIDN's frame where its record says,
``kpcn_keras.oidn_mix``) once, at its first frame, and kept for the next.
``kpcn denoise`` (``batch.denoise_files``), ``kpcn evaluate``, ``kpcn view`` and ``kpcn.denoise`` each hold one,
so a frame is denoised by the same networks, tiles and arithmetic whichever way it came in. A model adapted on a
shot (``kpcn adapt``: ``kpcn_keras.adapted_model``) serves the frames it was adapted for through its post-correction
(``kpcn_keras.adapt.Corrected``) and refuses others in one line.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path

from kpcn_keras import oidn_mix
from kpcn_keras.denoise import Denoiser
from kpcn_keras.run import Run, RunRecord
from kpcn_keras.settings import InferenceSettings
from prep.inputs import InputSet


class Serving:
    """The model ``model`` with ``settings``: :attr:`run` is the run of its quality mode (``settings.quality``);
    :attr:`load_s` and :attr:`warmup_s` are the seconds its denoisers took to load and to warm up so far (a batch
    reports them apart from its frames' time)."""

    def __init__(self, model: Run, settings: InferenceSettings = InferenceSettings()):
        self.model, self.settings = model, settings
        self.run = model.for_quality(settings.quality)
        self._variants: dict[InputSet, Run] = {}
        self._records: dict[Path, RunRecord] = {}
        self._denoisers: dict[Path, Denoiser] = {}
        self.load_s = self.warmup_s = 0.0
        self._adaptation = _UNREAD

    def variant(self, inputs: InputSet) -> Run:
        """The run whose networks denoise a frame that has ``inputs`` (``Run.serving``, found once); KpcnError
        naming what the frame lacks and how to train for it where the model has none."""
        if inputs not in self._variants:
            self._variants[inputs] = self.run.serving(inputs)
        return self._variants[inputs]

    def record(self, inputs: InputSet) -> RunRecord:
        """The record of :meth:`variant` (``inputs``), read once."""
        variant = self.variant(inputs)
        if variant.dir not in self._records:
            self._records[variant.dir] = variant.record()
        return self._records[variant.dir]

    def records(self, given: Iterable[InputSet]) -> list[RunRecord]:
        """The record of each variant that serves one of ``given``, once each, in the order first met."""
        return list({record.dir: record for record in map(self.record, given)}.values())

    def read_files(self, given: Iterable[InputSet]) -> list[tuple[str, Path]]:
        """What denoising frames that have each of ``given`` reads of the model, ``(what, path)``: each serving
        variant's record and model files (``Run.read_files``; for ``prep.files.check_outputs``)."""
        variants = {self.variant(inputs).dir: inputs for inputs in given}
        return [item for inputs in variants.values() for item in self.variant(inputs).read_files(self.record(inputs))]

    def adaptation(self):
        """The model's post-correction (``kpcn_keras.adapted_model.Adaptation``), read once; None where it has none."""
        if self._adaptation is _UNREAD:
            from kpcn_keras.adapted_model import load_adaptation

            self._adaptation = load_adaptation(self.model)
        return self._adaptation

    def denoiser(self, inputs: InputSet, *, warm_up: bool = False, slope=None) -> Denoiser:
        """The denoiser of :meth:`variant` (``inputs``) with this serving's settings, loaded at its first call
        and, with ``warm_up``, warmed up then at ``slope`` (``Denoiser.warm_up``), so that the frames' timings
        exclude both. For an adapted model, that denoiser followed by its post-correction (``adapt.Corrected``),
        called as a denoiser is; KpcnError where the frame is not one it was adapted for."""
        adaptation = self.adaptation()
        if adaptation is not None:
            from kpcn_keras.adapt import Corrected

            adaptation.check(self.model, self.settings.quality, self.record(inputs).inputs.name)
            return Corrected(self.plain(inputs, warm_up=warm_up, slope=slope), adaptation.post)
        return self.plain(inputs, warm_up=warm_up, slope=slope)

    def plain(self, inputs: InputSet, *, warm_up: bool = False, slope=None) -> Denoiser:
        """:meth:`denoiser` without an adapted model's post-correction: the networks, their frame mixed with OIDN's
        where the variant's record says so (``kpcn_keras.oidn_mix``)."""
        variant = self.variant(inputs)
        if variant.dir not in self._denoisers:
            begin = time.perf_counter()
            record = self.record(inputs)
            denoiser = oidn_mix.served(Denoiser.from_run(variant, self.settings, record=record), record)
            loaded = time.perf_counter()
            if warm_up:
                denoiser.warm_up(slope)
            self.load_s += loaded - begin
            self.warmup_s += time.perf_counter() - loaded
            self._denoisers[variant.dir] = denoiser
        return self._denoisers[variant.dir]


_UNREAD = object()  # an adaptation not read yet (None: read, and the model has none)

__all__ = ["Serving"]
