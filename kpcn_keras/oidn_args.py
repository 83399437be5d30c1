"""OIDN's command line on ``kpcn denoise``: ``kpcn denoise --hdr color.pfm --alb albedo.pfm --nrm normal.pfm
-o out.pfm`` runs as ``oidnDenoise`` with the same arguments would (docs/denoise.md §1d).

The conventions are those of OIDN's example program (RenderKit/oidn ``apps/oidnDenoise.cpp`` and
``apps/utils/arg_parser.cpp``): an option is its name after any number of dashes (``-hdr`` is ``--hdr``), each
alias it has there (``--alb``/``--albedo``, ``--clean_aux``/``--clean-aux``/``--cleanAux``, ``-q h``/``high``),
and a value never starts with a dash. A command line is OIDN's when an option only OIDN has (:data:`TRIGGERS`)
follows ``denoise`` (:func:`applies`). :func:`parse` maps each option onto kpcn's own (:data:`MAPPED`) or refuses
it in one line naming it (:data:`REFUSED`); a few of kpcn's own (``--run``, ``--tile``, ``--ensemble``,
``--precision``) may be added. :func:`run` gives the colour to ``kpcn denoise`` as an ``rgb``-layout frame with
its albedo and normal files: PFM inputs are converted to EXR in a temporary folder first (``prep.pfm``), and an
output ending in ``.pfm`` is the denoised colour written as PFM; ``.exr`` is kpcn's output EXR.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from prep.errors import KpcnError

# options only OIDN's program has: one of them after ``denoise`` makes the command line OIDN's
TRIGGERS = frozenset({"hdr", "ldr", "dir", "alb", "nrm", "srgb", "clean_aux", "clean-aux", "cleanAux", "cleanaux"})
ALIASES = {  # OIDN's spellings -> one name (apps/oidnDenoise.cpp)
    **dict.fromkeys(("d", "dev", "device"), "device"), **dict.fromkeys(("f", "filter"), "filter"),
    **dict.fromkeys(("alb", "albedo"), "alb"), **dict.fromkeys(("nrm", "normal"), "nrm"),
    **dict.fromkeys(("o", "out", "output"), "output"), **dict.fromkeys(("r", "ref", "reference"), "ref"),
    **dict.fromkeys(("is", "input_scale", "input-scale", "inputScale", "inputscale"), "input_scale"),
    **dict.fromkeys(("clean_aux", "clean-aux", "cleanAux", "cleanaux"), "clean_aux"),
    **dict.fromkeys(("t", "type"), "type"), **dict.fromkeys(("q", "quality"), "quality"),
    **dict.fromkeys(("w", "weights"), "weights"), **dict.fromkeys(("maxmem", "maxMemoryMB"), "maxmem"),
    **dict.fromkeys(("maxerror", "maxError", "max_error", "maxerr"), "maxerror"),
    **dict.fromkeys(("v", "verbose"), "verbose"), **dict.fromkeys(("h", "help"), "help"),
    **dict.fromkeys(("ld", "list_devices", "list-devices", "listDevices", "listdevices"), "list_devices"),
    **dict.fromkeys(("run", "run-dir", "run_dir"), "run"),
    **{name: name for name in ("hdr", "ldr", "srgb", "dir", "n", "threads", "affinity", "inplace", "buffer", "tile",
                               "ensemble", "precision")},
}
FLAGS = frozenset({"srgb", "clean_aux", "inplace", "help", "list_devices"})  # the options that take no value
QUALITY = {"h": "high", "high": "high", "b": "balanced", "balanced": "balanced", "f": "fast", "fast": "fast"}
SUFFIXES = (".pfm", ".exr")
# what kpcn cannot do of OIDN's options: the option -> why, in the one line that refuses it
REFUSED = {
    "ldr": "is OIDN's low-dynamic-range colour; kpcn's networks denoise linear HDR colour: give it as --hdr",
    "srgb": "is OIDN's sRGB-encoded LDR colour; kpcn denoises linear HDR colour (--hdr)",
    "dir": "is OIDN's directional lightmap (RTLightmap); kpcn denoises a rendered colour (--hdr)",
    "ref": "is oidnDenoise's check of its output against an expected one; kpcn has none (kpcn denoise "
           "--reference prints the error against a reference EXR)",
    "maxerror": "is the tolerance of oidnDenoise's check against -r/--ref, which kpcn does not have",
    "input_scale": "scales OIDN's input to its networks' range; kpcn's networks take the colour as rendered",
    "weights": "loads OIDN's weights (.tza); kpcn's networks are a model folder: --run",
    "maxmem": "bounds OIDN's memory in MB; kpcn bounds it by the tile's side: --tile (docs/denoise.md §3)",
    "list_devices": "lists OIDN's devices; kpcn runs where keras's torch backend runs, with no device to pick",
}
MAPPED = {  # what each of OIDN's other options becomes (docs/denoise.md §1d)
    "hdr": "the colour: kpcn denoise's input, an rgb-layout frame", "alb": "--albedo", "nrm": "--normal",
    "output": "-o (.pfm: PFM; .exr: kpcn's output EXR)", "clean_aux": "--clean-aux",
    "quality": "--quality (default: the model's default mode)", "threads": "--threads (0 or less: every core)",
    "type": "float: --precision float32", "filter": "RT: kpcn denoise itself", "device": "default, cpu: as kpcn runs",
    "n": "1: once", "affinity": "0: no pinning, as kpcn runs", "inplace": "nothing: kpcn writes a new file",
    "buffer": "nothing: kpcn's buffers are numpy's", "verbose": "nothing: kpcn prints its own lines",
}


@dataclass
class OidnCommand:
    """What an OIDN command line asks of ``kpcn denoise``: the colour, albedo and normal files, the output and
    the options (``kpcn`` holds kpcn's own, dest -> value, among them ``quality``, ``threads``, ``precision``)."""

    colour: Path | None = None
    albedo: Path | None = None
    normal: Path | None = None
    output: Path | None = None
    clean_aux: bool = False
    help: bool = False
    kpcn: dict[str, str] = field(default_factory=dict)

    def inputs(self) -> dict[str, Path]:
        """The image files given, by the OIDN option that named each (``--hdr``, ``--alb``, ``--nrm``)."""
        return {o: p for o, p in (("--hdr", self.colour), ("--alb", self.albedo), ("--nrm", self.normal)) if p}


def _subcommand_at(argv: list[str]) -> int | None:
    """The index of ``denoise`` in ``argv`` when it is the subcommand (after kpcn's global options), else None."""
    for i, token in enumerate(argv):
        if not token.startswith("-"):
            return i if token == "denoise" else None
    return None


def applies(argv: list[str]) -> bool:
    """Whether ``argv`` (``kpcn``'s arguments) is ``denoise`` with OIDN's options (:data:`TRIGGERS`)."""
    at = _subcommand_at(argv)
    return at is not None and any(t.startswith("-") and t.lstrip("-") in TRIGGERS for t in argv[at + 1:])


def _value(tokens: list[str], i: int, option: str) -> str:
    if i >= len(tokens) or tokens[i].startswith("-"):
        raise KpcnError(f"{option} needs a value (OIDN's convention: a value never starts with '-')")
    return tokens[i]


def _mapped(cmd: OidnCommand, name: str, option: str, value: str | None) -> None:
    """Set in ``cmd`` what the OIDN option ``name`` (typed ``option``) with ``value`` asks, or refuse it."""
    refuse = lambda why: KpcnError(f"{option} {value}: {why}")  # noqa: E731
    if name in ("hdr", "alb", "nrm", "output"):
        setattr(cmd, {"hdr": "colour", "alb": "albedo", "nrm": "normal", "output": "output"}[name], Path(value))
    elif name in ("clean_aux", "help"):
        setattr(cmd, name, True)
    elif name == "quality":
        if value.lower() != "default" and value.lower() not in QUALITY:
            raise refuse("is not one of OIDN's quality modes (default, h, high, b, balanced, f, fast)")
        if value.lower() != "default":
            cmd.kpcn["quality"] = QUALITY[value.lower()]
    elif name == "type":
        if value.lower() not in ("f", "float", "fp32"):
            raise refuse("kpcn's networks take float32 buffers (-t float); their arithmetic is --precision")
        cmd.kpcn["precision"] = "float32"
    elif name == "threads":
        if not value.isdigit():
            raise refuse("must be a whole number")
        if int(value) > 0:
            cmd.kpcn["threads"] = value
    elif name == "filter" and value != "RT":
        raise refuse("kpcn denoises as OIDN's RT filter does (a rendered colour); RTLightmap is not one of kpcn's")
    elif name == "device" and value.lower() not in ("default", "cpu"):
        raise refuse("kpcn has no device choice: it runs where keras's torch backend runs (default, cpu)")
    elif name == "n" and value not in ("0", "1"):
        raise refuse("kpcn denoises once a command (kpcn bench times repeated runs)")
    elif name == "affinity" and value != "0":
        raise refuse("kpcn never pins its threads to cores (--affinity 0)")
    elif name == "buffer" and value.lower() not in ("host", "device", "managed"):
        raise refuse("is not one of OIDN's storage modes (host, device, managed)")
    elif name in ("run", "tile", "ensemble", "precision"):
        cmd.kpcn[name] = value


def parse(tokens: list[str]) -> OidnCommand:
    """The :class:`OidnCommand` of the arguments after ``denoise``, read as ``oidnDenoise`` reads its own; KpcnError
    in one line naming the first option kpcn cannot honour (:data:`REFUSED`) or that OIDN does not have."""
    cmd, i = OidnCommand(), 0
    while i < len(tokens):
        option = tokens[i]
        name = ALIASES.get(option.lstrip("-"))
        if not option.startswith("-") or not option.strip("-"):
            raise KpcnError(f"{option!r}: with OIDN's options (--hdr, --alb, --nrm, -o) every file follows its "
                            "option; kpcn denoise's own form takes input files first (kpcn denoise --help)")
        if name is None:
            raise KpcnError(f"{option}: not an option of oidnDenoise that kpcn takes (it takes --hdr, --alb, --nrm, "
                            "-o, --clean_aux, -q, --threads, -t float, and --run, --tile, --ensemble, --precision)")
        value = None if name in FLAGS else _value(tokens, i + 1, option)
        if name in REFUSED:
            raise KpcnError(f"{option}{'' if value is None else ' ' + value}: {REFUSED[name]}")
        _mapped(cmd, name, option, value)
        i += 1 if value is None else 2
    if cmd.colour is None and not cmd.help:
        given = " and ".join(cmd.inputs())  # no --hdr: what is given is --alb, --nrm or neither
        raise KpcnError(f"{given or 'no --hdr'}: oidnDenoise denoises an albedo or a normal given alone; kpcn "
                        "denoises a colour: give it as --hdr")
    return cmd


def _checked_suffix(path: Path, option: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise KpcnError(f"{option} {path}: kpcn reads and writes .pfm and .exr images, not {suffix or 'no suffix'}")
    return suffix


def default_output(colour: Path) -> Path:
    """Where the result of ``--hdr colour`` without ``-o`` goes: ``<stem>-denoised`` and its suffix, beside it."""
    return colour.with_name(f"{colour.stem}-denoised{colour.suffix}")


def _images(cmd: OidnCommand, folder: Path) -> dict[str, Path]:
    """Each input as the EXR kpcn denoise reads (a PFM converted into ``folder``, an EXR as it is), by option;
    KpcnError naming the file for one kpcn cannot take or of another size than the colour."""
    from prep import exr, pfm

    given = cmd.inputs()
    out, sizes = {}, {}
    for option, path in given.items():
        if _checked_suffix(path, option) == ".exr":
            out[option], sizes[option] = path, exr.read_image(path, header_only=True).size
            continue
        image = pfm.read(path)
        if image.ndim != 3:
            raise KpcnError(f"{option} {path}: a one-channel PFM (Pf); kpcn takes a colour, albedo or normal as "
                            "three channels (PF)")
        sizes[option], out[option] = image.shape[:2], folder / f"{option.strip('-')}.exr"
        exr.write_aovs(out[option], {"default": image})
    for option, size in sizes.items():
        if size != sizes["--hdr"]:
            (h, w), (ch, cw) = size, sizes["--hdr"]
            raise KpcnError(f"{option} {given[option]} is {w}x{h} but --hdr {given['--hdr']} is {cw}x{ch}; "
                            "every image of a frame must be its size")
    return out


def kpcn_arguments(cmd: OidnCommand, images: dict[str, Path], output_exr: Path) -> list[str]:
    """The arguments of ``kpcn denoise`` (after ``denoise``) that denoise ``images`` (:func:`_images`) into
    ``output_exr`` as ``cmd`` asks."""
    args = [str(images["--hdr"]), "--layout", "rgb", "-o", str(output_exr)]
    args += [a for option, flag in (("--alb", "--albedo"), ("--nrm", "--normal")) if option in images
             for a in (flag, str(images[option]))]
    args += ["--clean-aux"] if cmd.clean_aux else []
    return args + [a for dest, value in cmd.kpcn.items() for a in (f"--{dest}", value)]


def run(argv: list[str], main) -> int:
    """``kpcn`` with OIDN's arguments ``argv`` (:func:`applies`): parsed (:func:`parse`), the inputs made EXRs kpcn
    reads, ``main`` (``kpcn_keras.cli.main``) run on the kpcn command line they make, and a PFM output written
    from its output EXR. ``main``'s status; KpcnError in one line for what kpcn cannot do, before any work."""
    from prep import exr, pfm
    from prep.files import check_outputs, check_writable

    at = _subcommand_at(argv)
    cmd = parse(argv[at + 1:])
    if cmd.help:
        print(usage())
        return 0
    read = list(cmd.inputs().items())
    for option, path in read:
        _checked_suffix(path, option)
    output = cmd.output or default_output(cmd.colour)
    as_pfm = _checked_suffix(output, "-o") == ".pfm"
    check_outputs([("-o", output)], read, "choose another -o")
    check_writable(output, "-o")
    with tempfile.TemporaryDirectory(prefix="kpcn-oidn-") as tmp:
        images = _images(cmd, Path(tmp))
        output_exr = Path(tmp) / "output.exr" if as_pfm else output
        status = main([*argv[:at], "denoise", *kpcn_arguments(cmd, images, output_exr)])
        if status == 0 and as_pfm:
            pfm.write(output, exr.read_rgb(output_exr))
            print(f"wrote {output} (PFM: the denoised colour)")
    return status


def usage() -> str:
    """What ``kpcn denoise`` takes of ``oidnDenoise``'s options, as its usage line lists them."""
    return ("usage: kpcn denoise --hdr color.pfm|exr [--alb albedo.pfm|exr] [--nrm normal.pfm|exr] [--clean_aux]\n"
            "                    [-o/--output output.pfm|exr] [-q/--quality default|h|high|b|balanced|f|fast]\n"
            "                    [-t/--type float] [--threads n] [-f/--filter RT] [-d/--device default|cpu]\n"
            "                    [-n 1] [--affinity 0] [--inplace] [--buffer host|device|managed] [-v n]\n"
            "                    [--run MODEL] [--tile n] [--ensemble n] [--precision auto|float32|bfloat16]\n"
            "OIDN's conventions (oidnDenoise); refused, each in one line: " + ", ".join(sorted(REFUSED)) +
            "; docs/denoise.md §1d")
