"""``kpcn view``'s adapt action: the model adapted to the frame's two halves in the background, its progress polled.

A :class:`Adaptation` holds what ``kpcn view A --pair B`` read (the two halves' layers and their mean, the frame the
page shows) and the denoiser that serves them. :meth:`Adaptation.start` trains a post-correction in a thread, by
the function ``kpcn denoise A --pair B --adapt`` and ``kpcn.denoise(..., pair=, adapt=)`` adapt by
(``batch.adapt_to_layers``), then denoises the mean with it (or without it, where the guard refused it: the model's
output as it is). So the page's *kpcn adapted* view is the command's output on the same pair and steps.
:meth:`Adaptation.status` is what the page polls: the state (``idle``, ``running``, ``done``, ``failed``,
``stopped``), the step, the self-supervised loss and the seconds so far, and once done what the guard decided
(``adapt.Outcome``). One adaptation runs at a time; a new one starts afresh from the model. :meth:`Adaptation.stop`
ends a running one at its next step (the viewer stops it before the process exits: an interpreter that exits while
a thread is inside torch aborts).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from kpcn_keras.settings import AdaptSettings
from prep.errors import KpcnError, OptionError

STATES = ("idle", "running", "done", "failed", "stopped")
QUERY = {"seconds": float, "steps": int, "seed": int}  # what POST /api/adapt takes: AdaptSettings' fields


class _Stopped(Exception):
    """Raised from the progress callback to end the training at its next step."""


def settings_of(query: dict) -> AdaptSettings:
    """The ``AdaptSettings`` of a request's query (``{name: [value]}``: ``seconds``, or ``steps`` and ``seed``);
    OptionError naming what it cannot take (an unknown key, not a number, out of its bounds)."""
    unknown = sorted(set(query) - set(QUERY))
    if unknown:
        raise OptionError("adapt", f"takes {', '.join(QUERY)}; got {', '.join(unknown)}")
    values = {}
    for key, kind in QUERY.items():
        if key in query:
            text = query[key][0]
            try:
                values[key] = kind(text)
            except ValueError:
                raise OptionError("adapt", f"{key} must be {'a number' if kind is float else 'a whole number'}, got "
                                  f"{text!r}") from None
            if kind is float and not math.isfinite(values[key]):
                raise OptionError("adapt", f"{key} must be a finite number, got {text!r}")
    return AdaptSettings(**values)


class Adaptation:
    """The adapt action of a viewed frame: ``denoiser`` (what serves the frame), ``halves`` (the two renders'
    layers), ``layers`` (their mean, what is denoised), ``slope`` (λ the adapted view is denoised at: the page's
    starting λ)."""

    def __init__(self, denoiser, halves: tuple[dict, dict], layers: dict, *, slope=None, log=print):
        self.denoiser, self.halves, self.layers, self.slope, self.log = denoiser, halves, layers, slope, log
        self.lock = threading.Lock()  # guards the fields below, which the page's requests read
        self.state, self.step, self.loss, self.seconds = "idle", 0, None, 0.0
        self.settings: AdaptSettings | None = None
        self.outcome, self.error, self.view = None, None, None
        self.thread: threading.Thread | None = None
        self.stopping = False

    def start(self, settings: AdaptSettings) -> dict:
        """Start adapting with ``settings`` in a thread; :meth:`status` after. KpcnError while one runs or once
        stopped."""
        with self.lock:
            if self.state == "running":
                raise KpcnError(f"an adaptation is running (step {self.step}): wait for it to end")
            if self.stopping:
                raise KpcnError("the viewer is stopping: no more adaptations")
            self.state, self.step, self.loss, self.seconds = "running", 0, None, 0.0
            self.settings, self.outcome, self.error = settings, None, None
            self.thread = threading.Thread(target=self._run, args=(settings,), name="kpcn-adapt", daemon=True)
            self.thread.start()
        budget = f"{settings.steps} steps" if settings.steps is not None else f"{settings.seconds:g} s"
        self.log(f"adapting to the two halves ({budget})")
        return self.status()

    def _progress(self, step: int, loss: float, seconds: float) -> None:
        with self.lock:
            self.step, self.loss, self.seconds = step, loss, seconds
            if self.stopping:
                raise _Stopped

    def _run(self, settings: AdaptSettings) -> None:
        from kpcn_keras.batch import adapt_to_layers

        begin = time.perf_counter()
        try:
            corrected, outcome = adapt_to_layers(self.denoiser, *self.halves, settings, self._progress)
            view = np.ascontiguousarray(corrected(self.layers, slope=self.slope)["default"], "<f4")
        except _Stopped:
            with self.lock:
                self.state = "stopped"
            return
        except KpcnError as exc:
            return self._failed(str(exc))
        except Exception as exc:  # a bug: the page and the console say so, the viewer goes on
            self._failed(f"{type(exc).__name__}: {exc}")
            raise
        with self.lock:
            self.state, self.outcome, self.view = "done", outcome, view
        self.log(f"{outcome.line()}; the adapted view in {time.perf_counter() - begin:.1f} s")

    def _failed(self, message: str) -> None:
        with self.lock:
            self.state, self.error = "failed", message
        self.log(f"adaptation failed: {message}")

    def status(self) -> dict:
        """JSON-ready: ``state`` (:data:`STATES`), ``step``, ``loss`` (the last step's self-supervised loss, None
        before one), ``seconds``, the budget (``steps`` or ``budget_seconds``), and ``outcome`` (the guard's
        decision with its ``line``) once done, ``error`` once failed."""
        with self.lock:
            s = self.settings
            out = {"state": self.state, "step": self.step, "loss": self.loss, "seconds": self.seconds,
                   "steps": None if s is None else s.steps,
                   "budget_seconds": None if s is None or s.steps is not None else s.seconds,
                   "outcome": None, "error": self.error}
            if self.outcome is not None:
                out["outcome"] = {**self.outcome.to_dict(), "line": self.outcome.line()}
            return out

    def view_bytes(self) -> bytes | None:
        """The adapted view's linear RGB, float32 (H, W, 3) little-endian, or None before one is done."""
        with self.lock:
            return None if self.view is None else self.view.tobytes()

    def stop(self, timeout: float) -> bool:
        """End a running adaptation at its next step and take no more: whether it ended within ``timeout``."""
        with self.lock:
            self.stopping = True
            thread = self.thread
        if thread is not None:
            thread.join(timeout)
            return not thread.is_alive()
        return True


__all__ = ["QUERY", "STATES", "Adaptation", "settings_of"]
