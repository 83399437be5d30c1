"""Denoising files: a batch of EXRs in, denoised EXRs (and their PNGs) and typed reports out.

:func:`denoise_files` denoises many frames (files, or every render in a folder) in one process, each by the
model's variant trained for what it has, loaded and warmed up once (``kpcn_keras.serving.Serving``), and
reports start-up, load and warm-up apart from each frame's time (:class:`BatchReport`, one :class:`FrameReport`
a frame); a frame's ``seconds`` never includes the model load. A frame of a batch is denoised exactly as alone
(the same networks on the same tiles: bit-identical). Inputs and outputs are checked before anything is loaded:
a file it would write (an output EXR, its PNG) that is a file it reads (an input, the reference, the run's
record or models) or another output, or that could not be written, an input whose header lacks a layer, a frame
whose whole-frame arrays (:func:`frame_bytes`) the machine cannot hold. Each output is written atomically, so a
batch stopped by a bad frame leaves every earlier output whole. The default output is ``<input stem>-denoised.exr``
beside the input (:func:`default_output`); with several inputs ``-o`` is a folder.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path

import keras
import numpy as np

from kpcn_keras import slope_map as slope_maps
from kpcn_keras.denoise import Denoiser
from kpcn_keras.panels import panels_png
from kpcn_keras.precision import resolve
from kpcn_keras.run import Run, RunRecord
from kpcn_keras.serving import Serving
from kpcn_keras.settings import AdaptSettings, InferenceSettings
from prep import exr, layouts, pairs
from prep.errors import KpcnError, OptionError
from prep.files import check_outputs, check_writable
from prep.inputs import mean_layers
from prep.processes import memory_shortfall, peak_memory_mb, process_age

DENOISED_SUFFIX = "-denoised.exr"  # what default_output appends; a folder's renders never include one
# Bytes a pixel of what denoising a frame holds whole, the tiles bounding the rest: the render as read (its
# float32 layers) with the three float32 outputs; the side-by-side PNG (canvas, image and encoder); a
# reference as read with the metrics' float64 arithmetic. Upper bounds of what numpy allocates
# (tests/test_denoise.py::test_frame_bytes_bound_what_a_frame_holds_whole), used to refuse a frame the
# machine cannot hold before any work (frame_bytes).
FRAME_BYTES, PNG_BYTES, REFERENCE_BYTES = 128, 32, 384
# A file of another layout is decoded whole before its layers are made (4 bytes a channel, half or float), and a
# pair is two frames and their float64 mean and difference.
FILE_CHANNEL_BYTES, PAIR_BYTES = 4, 512


def frame_bytes(height: int, width: int, *, png: bool = True, reference: bool = False, file_channels: int = 0,
                pair: bool = False) -> int:
    """What :func:`denoise_frame` holds whole for a ``height`` x ``width`` frame (see :data:`FRAME_BYTES`): with
    ``file_channels``, a file of another layout decoded whole (``prep.layouts.read``) beside the layers made
    from it; with ``pair``, a second render read and the pair's float64 arithmetic."""
    per_pixel = FRAME_BYTES + PNG_BYTES * png + REFERENCE_BYTES * reference + FILE_CHANNEL_BYTES * file_channels
    return height * width * (per_pixel + PAIR_BYTES * pair)


def check_frame_memory(path, size: tuple[int, int], *, png: bool = True, reference: bool = False,
                       available_mb: float | None = None, file_channels: int = 0, pair: bool = False) -> None:
    """KpcnError naming the render ``path`` of ``size`` (height, width) if denoising it would hold more
    than this machine has available (:func:`frame_bytes`; ``prep.processes.memory_shortfall``)."""
    needed = frame_bytes(*size, png=png, reference=reference, file_channels=file_channels, pair=pair)
    short = memory_shortfall(needed, available_mb=available_mb)
    if short:
        with_ref = ", with the reference" if reference else ""
        raise KpcnError(f"{path}: denoising its {size[1]}x{size[0]} frame ({needed // (size[0] * size[1])} bytes a "
                        f"pixel held whole{with_ref}) {short}" + ("; without --png it holds less" if png else ""))


def default_output(input_path: str | os.PathLike, folder: str | os.PathLike | None = None) -> Path:
    """``<input stem>-denoised.exr`` beside the input (or in ``folder``), whatever the input's suffix (or none)."""
    path = Path(input_path)
    stem = path.name[: -len(".exr")] if path.name.lower().endswith(".exr") else path.name
    return (Path(folder) if folder is not None else path.parent) / f"{stem}{DENOISED_SUFFIX}"


def png_path(output: str | os.PathLike) -> Path:
    """The side-by-side PNG written beside an output EXR."""
    return Path(output).with_suffix(".png")


def is_output(path: str | os.PathLike) -> bool:
    """Whether ``path`` is named like an output of :func:`default_output` (never taken from a folder)."""
    return Path(path).name.lower().endswith(DENOISED_SUFFIX)


def collect_inputs(paths) -> tuple[list[Path], list[Path]]:
    """The renders to denoise for ``paths`` (files and folders), in order, and the files skipped.

    A file is taken as given. A folder gives every ``*.exr`` directly in it (any case, sorted), except the
    outputs of an earlier run (``*-denoised.exr``) and hidden files (temporaries of an interrupted write),
    which are returned as skipped. KpcnError naming the path for one that does not exist or a folder with
    nothing to denoise.
    """
    inputs, skipped = [], []
    for given in map(Path, paths):
        if given.is_dir():
            found = sorted(p for p in given.iterdir() if p.name.lower().endswith(".exr") and p.is_file())
            take = [p for p in found if not is_output(p) and not p.name.startswith(".")]
            skipped += [p for p in found if p not in take]
            if not take:
                raise KpcnError(f"{given}: no renders to denoise in this folder (found {len(found)} .exr files, "
                                f"{len(found) - len(take)} of them earlier outputs or temporaries)")
            inputs += take
        elif given.exists():
            inputs.append(given)
        else:
            raise KpcnError(f"{given}: no such file or folder")
    return inputs, skipped


def plan_outputs(inputs: list[Path], output=None) -> list[Path]:
    """The output EXR of each input: beside it by default; ``output`` a file for one input, or a folder
    (existing, ending in ``/``, or, with several inputs, to be created) that takes every
    ``<stem>-denoised.exr``. Refuses, before any work, an ``output`` that must be a folder but names a file,
    and two inputs that would write the same output (:func:`denoise_files` checks every file it writes
    against every file it reads)."""
    if output is not None:
        # Path() drops a trailing slash, which is how a user says "a folder" for one input
        as_folder = os.fspath(output).endswith(("/", os.sep)) or Path(output).is_dir()
        output = Path(output)
        if len(inputs) > 1 and not as_folder:
            if output.exists() or output.name.lower().endswith(".exr"):
                raise OptionError("output", f"must be a folder with several inputs ({len(inputs)} given), got {output}"
                                  + (" (a file)" if output.exists() else ""))
            as_folder = True
        outputs = [default_output(p, output) if as_folder else output for p in inputs]
    else:
        outputs = [default_output(p) for p in inputs]
    seen: dict[Path, Path] = {}
    for src, out in zip(inputs, outputs):
        key = Path(os.path.abspath(out))
        if key in seen:
            raise KpcnError(f"{seen[key]} and {src} would both be written to {out}; denoise them "
                            "in separate commands or rename one" if seen[key] != src else f"{src} is given twice")
        seen[key] = src
    return outputs


@dataclass(frozen=True)
class ReadOptions:
    """How a frame is read, the one holder of a command's reading options (:func:`read_frame`): ``layout`` forces a
    renderer's layout (default: found from its channels, ``prep.layouts``); ``spp`` is the samples per pixel of a
    frame whose name and header do not say; ``view_layer`` the Cycles view layer to read (default: the one with the
    most passes kpcn uses); ``pair`` is a second render of the same frame (another seed), ``albedo`` and ``normal``
    files of an rgb frame's auxiliaries: each for a single input."""

    layout: str | None = None
    pair: str | os.PathLike | None = None
    albedo: str | os.PathLike | None = None
    normal: str | os.PathLike | None = None
    spp: int | None = None
    view_layer: str | None = None

    def singles(self) -> list[tuple[str, str | os.PathLike]]:
        """(option, file) of each file given that belongs to one input."""
        return [(name, value) for name in ("pair", "albedo", "normal") if (value := getattr(self, name)) is not None]

    def header(self, path) -> layouts.Header:
        """``prep.layouts.read_header`` of ``path`` read so: every layer it needs checked whole, before any work."""
        return layouts.read_header(path, self.layout, spp=self.spp, view_layer=self.view_layer)

    def read(self, path) -> layouts.Frame:
        """``prep.layouts.read`` of ``path`` read so, with the auxiliary files given."""
        return layouts.read(path, self.layout, spp=self.spp, albedo=self.albedo, normal=self.normal,
                            view_layer=self.view_layer)

    def for_reference(self) -> ReadOptions:
        """How a reference of a frame read so is read: its own layout, the same view layer if one is named."""
        return ReadOptions(view_layer=self.view_layer)


@dataclass(frozen=True)
class FrameReport:
    """What :func:`denoise_frame` did for one frame: ``input``, its ``layout``, ``inputs`` (what the frame gave),
    ``model`` (the run folder that denoised it), ``output``, ``png`` (if written), ``seconds`` (features, network
    and recombination: no file I/O), ``read_s``, ``write_s``, ``png_s``, ``frame_s`` (all of it) and, with a
    reference, ``metrics`` and ``input_metrics`` (``prep.metrics.all_metrics``); ``adaptation``, what adapting to
    the frame's two halves did (``kpcn_keras.adapt.Outcome``; its seconds are not in ``seconds``)."""

    input: str
    layout: str
    inputs: str
    model: str
    output: str
    seconds: float
    read_s: float
    write_s: float
    png_s: float
    frame_s: float
    png: str | None = None
    input_metrics: dict[str, float] | None = None
    metrics: dict[str, float] | None = None
    adaptation: object | None = None  # kpcn_keras.adapt.Outcome, where the model adapted to the frame first


@dataclass(frozen=True)
class BatchReport:
    """What :func:`denoise_files` did: ``startup_s``, the seconds from process start to the call (None off Linux);
    ``load_s`` and ``warmup_s``, of loading the networks and of their warm-ups; torch's ``threads``; the
    ``precision`` it resolved to; the self-ensemble's members (``ensemble``); the process's ``peak_memory_mb`` at
    the end (``prep.processes.peak_memory_mb``); one :class:`FrameReport` per input, in order (``frames``); the folder
    entries ``skipped`` (earlier outputs)."""

    startup_s: float | None
    load_s: float
    warmup_s: float
    threads: int | None
    precision: str
    ensemble: int
    peak_memory_mb: float | None
    frames: tuple[FrameReport, ...]
    skipped: tuple[str, ...]


def read_frame(input_path, reading: ReadOptions = ReadOptions()) -> layouts.Frame:
    """The frame to denoise: ``input_path`` in its layout (``prep.layouts.read``), or with ``reading.pair`` (a second
    render of the same frame, another seed) the two as one render of all their samples (:func:`join_pair`), after
    ``prep.pairs``' checks that it is one: OptionError naming both files if not."""
    if reading.pair is None:
        return reading.read(input_path)
    frame, other = read_halves(input_path, reading)
    return join_pair(frame, other, (input_path, reading.pair))


def join_pair(frame: layouts.Frame, other: layouts.Frame, names) -> layouts.Frame:
    """Two renders of one frame (another seed each; ``names``: what to call the two in its notes) as the one frame
    denoised: one render of all their samples, each layer their mean and each variance layer the variance of that
    mean where both have it (``prep.inputs.mean_layers``), so the network that serves one of them serves it. Not
    a variance estimated from their difference for renderers that write none: on the 16-spp Cycles validation
    frames as two halves, the variance network on that estimate had a median relMSE 1.97x Blender's denoiser's
    against 1.38x for the mean alone (``reports/adapt_pair_join.json``). Files (:func:`read_frame`), arrays
    (``kpcn.denoise(..., pair=)``), the viewer and adapting (whose halves these are) join by this one function."""
    spp = frame.spp + other.spp if frame.spp and other.spp else None
    alpha = frame.alpha if frame.alpha is None or other.alpha is None else exr.to_float32(
        (np.asarray(frame.alpha, np.float64) + other.alpha) / 2)
    return dataclasses.replace(frame, layers=mean_layers(frame.layers, other.layers), alpha=alpha, spp=spp,
                               notes=frame.notes + (f"the mean of the two renders {names[0]} + {names[1]}",))


def read_halves(input_path, reading: ReadOptions) -> tuple[layouts.Frame, layouts.Frame]:
    """``input_path`` and ``reading.pair``, two renders of one frame with different seeds, each as it is, after
    ``prep.pairs``' checks that they are: OptionError naming both files if not."""
    pairs.check_header(input_path, reading.pair, reading.header)
    frame, other = reading.read(input_path), reading.read(reading.pair)
    pairs.check_colours(input_path, frame.layers["default"], reading.pair, other.layers["default"])
    return frame, other


def read_reference(reference, input_path, size: tuple[int, int], reading: ReadOptions = ReadOptions()) -> np.ndarray:
    """The colour of ``reference``, the reference EXR of the frame ``input_path`` of (H, W) ``size`` read by
    ``reading`` (``ReadOptions.for_reference``); KpcnError naming both files and their sizes when they differ."""
    ref = reading.for_reference().read(reference).layers["default"]
    layouts.check_same_size(input_path, size, reference, ref.shape[:2])
    return ref


def output_layers(frame: layouts.Frame, result: dict[str, np.ndarray], split: bool) -> dict[str, np.ndarray]:
    """What an output EXR holds: the denoised colour as layer ``default`` (with the input's alpha as
    ``default.A``), the denoised ``diffuse`` and ``specular`` where the model had a split, and the frame's
    albedo, normal and depth as read."""
    layers = {"default": result["default"]}
    if frame.alpha is not None:
        layers["default.A"] = frame.alpha
    if split:
        layers.update(diffuse=result["diffuse"], specular=result["specular"])
    layers.update({k: frame.layers[k] for k in ("albedo", "normal", "depth")})
    return layers


def denoise_frame(denoiser: Denoiser, input_path, output, reference=None, *, png: bool = True,
                  slope: float | None = None, reading: ReadOptions = ReadOptions()) -> FrameReport:
    """Denoise one EXR with a loaded (warmed-up) ``denoiser`` at ``slope``: writes ``output`` and, with ``png``, the
    side-by-side PNG beside it, each atomically. ``reading``: as :func:`read_frame`. The output carries the
    input's header attributes, data and display windows and alpha. Returns the frame's :class:`FrameReport`."""
    from prep import metrics

    begin = time.perf_counter()
    frame = read_frame(input_path, reading)
    noisy = frame.layers
    ref = read_reference(reference, input_path, frame.size, reading) if reference else None
    start = time.perf_counter()
    result = denoiser(frame.served_layers(), slope=slope)
    done = time.perf_counter()
    exr.write_aovs(output, output_layers(frame, result, denoiser.record.inputs.split), attributes=frame.attributes,
                   windows=(frame.data_window, frame.display_window))
    written = time.perf_counter()
    measured = {}
    panels = [("input", noisy["default"]), ("denoised", result["default"])]
    if ref is not None:
        measured = {"input_metrics": metrics.all_metrics(noisy["default"], ref),
                    "metrics": metrics.all_metrics(result["default"], ref)}
        panels.append(("reference", ref))
    drawn = str(panels_png(png_path(output), panels, title=Path(input_path).name)) if png else None
    return FrameReport(input=str(input_path), layout=frame.layout, inputs=frame.inputs.name,
                       model=str(denoiser.run.dir), output=str(output), seconds=done - start, read_s=start - begin,
                       write_s=written - done, png_s=time.perf_counter() - written,
                       frame_s=time.perf_counter() - begin, png=drawn, **measured)


def denoise_files(inputs, run: Run, output=None, reference=None, *, settings: InferenceSettings = InferenceSettings(),
                  reading: ReadOptions = ReadOptions(), png: bool = True, slope: float | None = None,
                  slope_map=None, on_frame=None, adapt: AdaptSettings | None = None, on_adapt=None) -> BatchReport:
    """Denoise many EXRs in one process with the model ``run``, applied with ``settings``: each of its variants
    is loaded and warmed up once.

    ``inputs``: files and folders (:func:`collect_inputs`), each in any layout ``prep.layouts`` reads
    (``reading.layout`` forces one); ``output``: see :func:`plan_outputs`; ``reference``: one reference EXR, and
    ``reading``'s ``pair``, ``albedo``, ``normal`` (:func:`read_frame`), for a single input only. Each frame is
    denoised by the model trained for what the frame has (``Serving.variant``: the run itself, or one of its
    ``inputs/`` variants). Every input's header, the model each needs and every output are checked before a
    model is loaded, so a missing layer, a missing model, a wrong size or an unwritable output fails before any
    work. A frame that still fails (a truncated file) stops the batch with a KpcnError naming it; the outputs
    written before it are complete (each is written atomically) and are named in the message.
    ``on_frame(report)`` is called after each frame (progress). ``slope_map``: a painted λ map
    (``kpcn_keras.slope_map``) instead of ``slope``, for a run with a specialisation module, read for each
    frame's size before any work. ``adapt``: with a pair, the model first adapts to the frame's two halves
    (:func:`adapt_to_halves`; ``on_adapt(step, loss, seconds)`` its progress), then denoises their mean.
    """
    startup = process_age()
    if adapt is not None:
        if reading.pair is None:
            raise OptionError("adapt", "needs --pair: a second render of the frame with another seed (each of the "
                              "two at half the samples)")
    inputs, skipped = collect_inputs([inputs] if isinstance(inputs, (str, os.PathLike)) else inputs)
    _check_single_inputs(inputs, reference, reading)
    outputs = plan_outputs(inputs, output)
    serving = Serving(run, settings)
    headers = [reading.header(src) for src in inputs]
    if reading.pair is not None:  # a pair that is not a second render of the input (its size too), before a model loads
        pairs.check_header(inputs[0], reading.pair, reading.header)
    given = [h.inputs for h in headers]  # a pair's mean has what each of its renders has (join_pair)
    _check_files(inputs, outputs, headers, serving.read_files(given), reference, reading, png=png,
                 slope_map=slope_map)
    slopes = [slope] * len(inputs)
    if slope_map is not None:
        slopes = _read_slope_maps(slope_map, slope, [serving.record(g) for g in given], headers)
    for record in serving.records(given):
        record.finished().check_slope(slopes[0])  # before the networks are loaded
    frames = []
    for src, out, frame_inputs, frame_slope in zip(inputs, outputs, given, slopes):
        denoiser = serving.denoiser(frame_inputs, warm_up=True, slope=slopes[0])
        outcome = None
        if adapt is not None:
            denoiser, outcome = adapt_to_halves(denoiser, src, reading, adapt, on_adapt)
        try:
            frames.append(dataclasses.replace(denoise_frame(denoiser, src, out, reference, png=png, slope=frame_slope,
                                                            reading=reading), adaptation=outcome))
        except KpcnError as exc:
            if frames:
                raise KpcnError(f"{exc} (stopped after {len(frames)} of {len(inputs)} frames; written: "
                                f"{', '.join(f.output for f in frames)})") from exc
            raise
        if on_frame is not None:
            on_frame(frames[-1])
    return BatchReport(startup_s=startup, load_s=serving.load_s, warmup_s=serving.warmup_s, threads=torch_threads(),
                       precision=resolve(settings.precision), ensemble=settings.ensemble,
                       peak_memory_mb=peak_memory_mb(), frames=tuple(frames), skipped=tuple(map(str, skipped)))


def adapt_to_halves(denoiser: Denoiser, input_path, reading: ReadOptions, settings: AdaptSettings, progress=None):
    """``(denoiser, outcome)``: ``denoiser`` followed by a post-correction adapted to the frame ``input_path`` and
    ``reading.pair``, two independent renders of it (``kpcn_keras.adapt``; :func:`read_halves`' checks first), or
    ``denoiser`` itself where the guard refused it, and what the adaptation decided (``Outcome``)."""
    a, b = read_halves(input_path, reading)
    return adapt_to_layers(denoiser, a.layers, b.layers, settings, progress)


def adapt_to_layers(denoiser: Denoiser, a: dict, b: dict, settings: AdaptSettings, progress=None):
    """:func:`adapt_to_halves` of a frame's two halves given as their layers ``a`` and ``b`` (checked already): the
    one function files, arrays (``kpcn.denoise(..., pair=, adapt=)``) and ``kpcn view`` adapt by."""
    from kpcn_keras.adapt import Adapter, Corrected

    adapter = Adapter(denoiser, [(a, b)], settings)  # from here the adapter needs only its crops
    outcome = adapter.run(progress)
    return (denoiser if adapter.post is None else Corrected(denoiser, adapter.post)), outcome


def shot_pairs(frames, second_renders=None) -> list[tuple[Path, Path]]:
    """(A, B) of each frame of a shot: ``frames`` files with ``second_renders`` the second render of each, in order,
    or folders of pairs named as ``prep.render.blender.catalogue.pair_names`` names them (``second_renders`` None).
    OptionError naming what does not pair."""
    from prep.render.blender.catalogue import pair_half, pair_names

    frames = [Path(f) for f in frames]
    if second_renders:
        if len(second_renders) != len(frames):
            raise OptionError("pairs", f"gives {len(second_renders)} second renders for {len(frames)} frames")
        return list(zip(frames, map(Path, second_renders)))
    out = []
    for folder in frames:
        if not folder.is_dir():
            raise OptionError("pairs", f"{folder} is a file: give the second render of each frame with --pairs, "
                              "or a folder of *-pair-a.exr and *-pair-b.exr")
        for a in sorted(folder.iterdir()):
            half = pair_half(a.name)
            if half is None or half[2] != "a":
                continue
            b = a.with_name(pair_names(half[0], half[1])[1])
            if not b.is_file():
                raise OptionError("pairs", f"{a} has no second half {b.name} beside it")
            out.append((a, b))
        if not out:
            raise OptionError("pairs", f"{folder} holds no pair of renders (<scene>-<spp>spp-pair-a.exr and "
                              "-pair-b.exr)")
    return out


def adapt_shot(pairs, model: Run, out, *, settings: InferenceSettings = InferenceSettings(),
               adapt: AdaptSettings | None = None, reading: ReadOptions = ReadOptions(), progress=None):
    """``(outcome, folder)``: ``model`` adapted once on the shot ``pairs`` ((A, B) files: two independent renders of
    each frame, :func:`read_halves`' checks on each) at ``settings``' quality, written as the model folder ``out``
    (``kpcn_keras.adapted_model.write_adapted``); an adapted ``model`` goes on from its post-correction. Every
    frame must give the same inputs (one variant is adapted): OptionError naming the first that does not."""
    from kpcn_keras.adapt import Adapter
    from kpcn_keras.adapted_model import write_adapted

    adapt = adapt or AdaptSettings()
    serving = Serving(model, settings)
    halves = [read_halves(a, dataclasses.replace(reading, pair=b)) for a, b in pairs]
    given = halves[0][0].inputs
    for (a, _), (frame, _) in zip(pairs, halves):
        if frame.inputs != given:
            raise OptionError("pairs", f"{a} gives {frame.inputs.name}, the first frame {given.name}: a shot's frames "
                              "share one layout")
    record = serving.record(given)
    start = serving.adaptation()
    if start is not None:
        start.check(model, settings.quality, record.inputs.name)
    adapter = Adapter(serving.plain(given), [(a.layers, b.layers) for a, b in halves], adapt,
                      None if start is None else start.post)
    del halves
    outcome = adapter.run(progress)
    source = start.record["source"] if start is not None else str(model.dir)
    entry = {"source": source, "quality": settings.quality, "inputs": record.inputs.name,
             "pairs": [[str(a), str(b)] for a, b in pairs], "settings": dataclasses.asdict(adapt),
             "outcome": outcome.to_dict(), "corrects": adapter.post is not None}
    return outcome, write_adapted(model, out, adapter.post, entry)


def _check_single_inputs(inputs: list[Path], reference, reading: ReadOptions) -> None:
    """OptionError for a file of a single input (the reference, a pair, an auxiliary) given with several inputs
    or naming a folder, or for an unknown layout."""
    for option, value in [("reference", reference), *reading.singles()]:
        if value is not None and len(inputs) != 1:
            raise OptionError(option, f"is for one input, got {len(inputs)}"
                              + ("; 'kpcn evaluate' compares many" if option == "reference" else ""))
        if value is not None and Path(value).is_dir():
            what = {"reference": "the input's reference", "pair": "a second render's"}.get(option, f"the {option}")
            raise OptionError(option, f"must be {what} EXR file, got {value}, a folder")
    layouts.check_layout(reading.layout)


def _check_files(inputs: list[Path], outputs: list[Path], headers, models: list[tuple[str, Path]], reference,
                 reading: ReadOptions, *, png: bool, slope_map) -> None:
    """Before any work: no file written is one read (``models``: the model's files) or another written, each can
    be written, the reference is each input's size (a pair's is ``prep.pairs.check_header``'s), and this machine
    can hold each frame."""
    written = [("--output", out) for out in outputs] + [("side-by-side PNG", png_path(out)) for out in outputs if png]
    read = [("input", src) for src in inputs] + [(option, value) for option, value in
                                                 [("reference", reference), *reading.singles()] if value is not None]
    if slope_map is not None:
        read.append(("--slope-map", slope_map))
    check_outputs(written, read + models, "choose another -o" + (" (or leave out --png)" if png else ""))
    ref_size = reading.for_reference().header(reference).size if reference is not None else None
    for src, header in zip(inputs, headers):
        if ref_size is not None:
            layouts.check_same_size(src, header.size, reference, ref_size)
        check_frame_memory(src, header.size, png=png, reference=reference is not None,
                           file_channels=header.channels, pair=reading.pair is not None)
    for out in outputs:
        check_writable(out, "--output")
        if png:
            check_writable(png_path(out), "side-by-side PNG")


def torch_threads() -> int | None:
    """torch's thread count (None on another backend)."""
    if keras.backend.backend() != "torch":
        return None
    import torch

    return torch.get_num_threads()


def _read_slope_maps(path, slope, records: list[RunRecord], headers) -> list[np.ndarray]:
    """The λ map ``path`` for each frame (its record's λ range, its header's size); OptionError for a run that
    cannot take one or with ``--slope`` beside it."""
    if slope is not None:
        raise OptionError("slope_map", "and --slope both give λ: give one")
    maps = {}
    for record, header in zip(records, headers):
        if not record.model.slope_module:
            raise OptionError("slope_map", f"is for a run trained with --slope-module (λ joined after the trunk); "
                              f"{record.dir} takes " + ("one λ for the whole frame (--slope)" if
                                                        record.model.slope_channel else "no λ"))
        key = (tuple(record.train.slope_range), tuple(header.size))
        if key not in maps:
            maps[key] = slope_maps.read(path, header.size, record.train.slope_range)
    return [maps[tuple(r.train.slope_range), tuple(h.size)] for r, h in zip(records, headers)]
