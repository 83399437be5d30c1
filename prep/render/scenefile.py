"""Scene files: a scene and its render settings as TOML (``.toml``) or JSON (``.json``).

``load_scene(path) -> (Scene, RenderSettings)`` reads one; ``dump_scene(scene, settings)`` writes the text
of one (every built-in family scene round-trips: the loaded scene equals the original and renders the
same bits); ``render_scene_file`` is what ``kpcn render --scene FILE`` runs. Each table is checked against
the dataclass it becomes by ``schema.py`` (its keys, the types of its values, an error naming the key path and
echoing the value found), so what the format accepts follows the scene model's dataclasses.

Format
------

The file is one table (a TOML document or a JSON object) whose keys are the fields of
:class:`prep.render.scene.Scene` plus ``render``:

``name``, ``family``, ``seed`` (optional)
    The scene's name (default: the file's stem), its family (default ``"custom"``) and the seed a built-in
    family generated it from (informational; the noise seed is ``render.seed``).
``environment``, ``environment_zenith`` (optional)
    RGB radiance of rays that leave the scene, ``[r, g, b]`` (default black), towards the horizon; with
    ``environment_zenith``, blending to that colour straight up.
``[environment_map]`` (optional)
    Instead of ``environment``, radiance from a latitude-longitude map (``scene.EnvironmentMap``; the
    mapping is in ``scene.py``), importance sampled as a light: ``image = "sky.exr"`` (OpenEXR R G B, or a
    PNG; relative to the scene file) or a procedural HDR sky in ``[environment_map.sky]`` (the fields of
    ``scene.Sky``: ``sun_elevation``, ``sun_azimuth``, ``sun_radius`` in degrees, ``sun``, ``zenith``,
    ``horizon``, ``ground`` radiances, ``height`` in texels), and ``scale`` (default 1).
``[camera]``
    The fields of ``Camera``: ``position`` and ``look_at`` (``[x, y, z]``, required), ``up`` (default
    ``[0, 1, 0]``), ``fov`` (vertical, degrees; default 40), ``aperture`` (thin-lens radius; default 0, a
    pinhole) and ``focus_distance`` (default: the distance to ``look_at``).
``[materials.<name>]``
    One table per material, named by ``<name>``; the fields of ``Material``: ``kind`` (required; one of
    ``scene.MATERIAL_KINDS``: ``lambert``, ``glossy``, ``plastic``, ``emitter``, ``mirror``, ``glass``),
    ``albedo``, ``specular``, ``roughness``, ``emission``, ``ior``, and the checker texture ``texture``
    (``"none"``, ``"world"``, ``"uv"``), ``albedo2``, ``checker_scale``. A field a kind does not use is
    ignored; ``scene.py`` says which kind uses which.
``[[spheres]]``
    One table per sphere: ``center``, ``radius``, ``material`` (a name under ``[materials]``).
``[[quads]]``
    One table per parallelogram ``corner + a*u + b*v``: ``corner``, ``u``, ``v``, ``material``. A quad with
    an ``emitter`` material is an area light, emitting on the side of ``cross(u, v)``.
``[[meshes]]``
    One table per triangle mesh (``scene.Mesh``), with a ``material`` and either
    ``obj = "file.obj"`` (a Wavefront OBJ file, relative to the scene file; read by
    ``prep.render.obj.load_obj``), optionally placed by ``scale`` (default 1), ``rotate_y`` (degrees about
    the y axis, default 0) and ``translate`` (``[x, y, z]``, default 0), applied in that order; or the
    arrays ``vertices`` (``[[x, y, z], ...]``) and ``faces`` (``[[i, j, k], ...]``, 0-based vertex
    indices). Faces wound counter-clockwise seen from outside have outward normals (glass needs them). A mesh
    with an ``emitter`` material is an area light, each triangle emitting on the side of
    ``cross(v1 - v0, v2 - v0)``.
    ``dump_scene`` writes meshes as ``vertices`` and ``faces``. A problem in the OBJ file names the key
    (``meshes[0].obj``), the OBJ file and its line.
``[medium]`` (optional)
    A homogeneous participating medium (``scene.Medium``) filling the box [``box_min``, ``box_max``]:
    ``sigma_a`` (RGB absorption), ``sigma_s`` (grey scattering), ``g`` (Henyey-Greenstein asymmetry); ``density``
    ``"noise"`` with ``noise_cells``, ``noise_amount``, ``noise_seed`` for smoke of varying density.
``[render]``
    The render settings, the keyword parameters of :func:`prep.render.render` but ``effects``:
    ``width``, ``height``, ``max_depth``, ``rr_depth`` (defaults: those of ``render``), ``spp`` and
    ``seed`` (``render`` has no defaults for these: the smallest of ``RenderConfig.input_spp`` and
    ``RenderConfig.seed``, those of the built-in sets' inputs). ``kpcn render --scene`` options override
    them.

The keys of each table are the fields of the dataclass it builds (``dataclasses.fields``), read when this
module loads, so fields and material kinds added to ``scene.py`` (and parameters added to ``render``) are
part of the format without a change here; the list above is today's.

Colours and points are arrays of 3 numbers; every number must be finite; an integer is accepted where a
number is. Each table's meaning beyond its type (ranges, degenerate cameras or quads) is checked by the
dataclass it builds.

Errors
------

Every problem is a :class:`SceneFileError` (a :class:`prep.errors.KpcnError`: one line from ``kpcn``)
whose message starts with the file's path and names the key by its full path, array items counted from 0,
with the value found: ``scene.toml: unknown key materials.red.albdo = [0.7, 0.1, 0.1] (did you mean
albedo?); valid keys of materials.red: kind, albedo, ...``, ``scene.toml: spheres[2].radius = -1: Sphere.radius
must be > 0, got -1.0``, ``scene.toml: spheres[0].material = "gold": no such material; defined under
[materials]: red, white``. A syntax error names the line and column; a file that is neither ``.toml`` nor
``.json`` is refused by its suffix.

A complete example (``scenes/example.toml`` is a larger one)::

    name = "two-spheres"
    environment = [0.05, 0.06, 0.08]

    [render]
    width = 320
    height = 240
    spp = 16
    seed = 7

    [camera]
    position = [0.0, 1.2, 4.0]
    look_at = [0.0, 0.5, 0.0]
    fov = 40

    [materials.ground]
    kind = "lambert"
    albedo = [0.7, 0.7, 0.7]
    texture = "world"
    albedo2 = [0.2, 0.2, 0.2]
    checker_scale = 2.0

    [materials.chrome]
    kind = "glossy"
    specular = [0.9, 0.9, 0.9]
    roughness = 0.1

    [materials.red]
    kind = "plastic"
    albedo = [0.6, 0.1, 0.1]
    specular = [0.05, 0.05, 0.05]
    roughness = 0.2

    [materials.light]
    kind = "emitter"
    emission = [12.0, 11.0, 10.0]

    [[quads]]  # the ground, facing up
    corner = [-10.0, 0.0, -10.0]
    u = [0.0, 0.0, 20.0]
    v = [20.0, 0.0, 0.0]
    material = "ground"

    [[quads]]  # an area light above, facing down
    corner = [-0.5, 3.0, -0.5]
    u = [1.0, 0.0, 0.0]
    v = [0.0, 0.0, 1.0]
    material = "light"

    [[spheres]]
    center = [-0.6, 0.5, 0.0]
    radius = 0.5
    material = "chrome"

    [[spheres]]
    center = [0.6, 0.4, 0.3]
    radius = 0.4
    material = "red"

The same scene in JSON has the same keys: ``{"name": ..., "render": {...}, "materials": {"ground": {...}},
"quads": [{...}, ...], ...}``.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import time
import typing
from pathlib import Path
from typing import Any

import numpy as np

from prep.bounds import SEED
from prep.errors import InputFileError, KpcnError, OptionError
from prep.files import read_input
from prep.render.frame import render
from prep.render.renderset import RenderConfig
from prep.render.scene import Mesh, Scene
from prep.render.schema import (
    TableError,
    build,
    convert,
    field_of,
    init_fields,
    join_key,
    key_text,
    show,
    toml_value,
)

__all__ = ["SUFFIXES", "RenderSettings", "SceneFileError", "dump_scene", "load_scene", "read_scene",
           "render_scene_file"]

SUFFIXES = (".toml", ".json")
DEFAULT_FAMILY = "custom"


class SceneFileError(KpcnError):
    """A scene file that cannot be read or describes no valid scene; the message is one line that starts
    with the file's path."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split("\n")))


# ------------------------------------------------------------------------------------------------
# render settings: the keyword parameters of prep.render.render, with its defaults
# ------------------------------------------------------------------------------------------------

def _config_default(name: str):
    return next(f.default for f in dataclasses.fields(RenderConfig) if f.name == name)


def _smallest(value):
    return min(value) if isinstance(value, (tuple, list)) else value


# render() has no defaults for these: a scene file takes the built-in sets' (their smallest input spp)
_FALLBACK_DEFAULTS = {"spp": lambda: _smallest(_config_default("input_spp")),
                      "seed": lambda: _config_default("seed")}
_NOT_SETTINGS = ("scene", "effects")


def _settings_fields() -> list:
    try:
        hints = typing.get_type_hints(render)
    except Exception:  # an annotation that does not resolve: take the values as they come
        hints = {}
    required, optional = [], []
    for p in inspect.signature(render).parameters.values():
        if p.name in _NOT_SETTINGS or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        hint = hints.get(p.name, Any)
        if p.default is not p.empty:
            optional.append((p.name, hint, dataclasses.field(default=p.default)))
        elif p.name in _FALLBACK_DEFAULTS:
            optional.append((p.name, hint, dataclasses.field(default=_FALLBACK_DEFAULTS[p.name]())))
        else:
            required.append((p.name, hint))
    return required + optional


RenderSettings = dataclasses.make_dataclass("RenderSettings", _settings_fields(), frozen=True,
                                            namespace={"__module__": __name__})
RenderSettings.__doc__ = ("The ``[render]`` table of a scene file: the keyword parameters of "
                          "``prep.render.render`` (but ``effects``), with its defaults. "
                          "``render(scene, **dataclasses.asdict(settings))`` renders.")


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------

# keys a table may have beyond its dataclass's fields (taken out before it is built; listed as valid)
_OBJ_KEYS = ("obj", "translate", "scale", "rotate_y")
_EXTRA_KEYS = {Mesh: _OBJ_KEYS}


def _obj_meshes(data: dict, base: Path, read: list) -> None:
    """Replace each ``[[meshes]]`` entry that names an ``obj`` file (relative to ``base``) by the
    vertices and faces read from it, placed by ``translate``, ``scale`` and ``rotate_y``; each file
    read is added to ``read`` as (its key, its path)."""
    from prep.render.obj import ObjError, load_obj

    meshes = data.get("meshes")
    if not isinstance(meshes, list):
        return
    for i, entry in enumerate(meshes):
        if not isinstance(entry, dict) or not any(k in entry for k in _OBJ_KEYS):
            continue
        path = f"meshes[{i}]"
        if "obj" not in entry:
            key = next(k for k in _OBJ_KEYS if k in entry)
            raise TableError(f"{path}.{key} = {show(entry[key])}: {key} places a mesh read from an OBJ file, "
                             f"and {path} has no obj key")
        inline = [k for k in ("vertices", "faces") if k in entry]
        if inline:
            raise TableError(f"{path}.{inline[0]}: a mesh is either read from obj = {show(entry['obj'])} or "
                             "given by vertices and faces, not both")
        name = convert(entry["obj"], str, f"{path}.obj")
        translate = convert(entry.get("translate", [0.0, 0.0, 0.0]), tuple[float, float, float],
                             f"{path}.translate")
        scale = convert(entry.get("scale", 1.0), float, f"{path}.scale")
        if not scale > 0:
            raise TableError(f"{path}.scale = {show(entry['scale'])}: scale must be > 0")
        rotate_y = convert(entry.get("rotate_y", 0.0), float, f"{path}.rotate_y")
        obj_path = Path(name) if Path(name).is_absolute() else base / name
        read.append((f"{path}.obj", obj_path))
        try:
            mesh = load_obj(obj_path, "", translate, scale, rotate_y)
        except ObjError as exc:
            raise TableError(f"{path}.obj = {show(name)}: {exc}") from None
        rest = {k: v for k, v in entry.items() if k not in _OBJ_KEYS}
        meshes[i] = {"vertices": [list(v) for v in mesh.vertices], "faces": [list(f) for f in mesh.faces],
                     **rest}


def _image_paths(data: dict, base: Path, read: list) -> None:
    """Image textures and environment maps are named relative to the scene file: make each path one that
    works from anywhere, and add it to ``read`` as (its key, its path)."""
    tables = {}
    materials = data.get("materials")
    if isinstance(materials, dict):
        tables.update({join_key("materials", name): (materials, name) for name in materials})
    if "environment_map" in data:
        tables["environment_map"] = (data, "environment_map")
    for path, (parent, key) in tables.items():
        table = parent[key]
        if isinstance(table, dict) and isinstance(table.get("image"), str) and table["image"]:
            image = Path(table["image"]) if Path(table["image"]).is_absolute() else base / table["image"]
            if not image.is_file():
                raise TableError(f"{join_key(path, 'image')} = {show(table['image'])}: no such file {image}")
            read.append((join_key(path, "image"), image))
            parent[key] = {**table, "image": str(image)}


def _scene_problem(scene: Scene, exc: ValueError) -> str:
    """A Scene.validate() message with the key path of the object or field it is about."""
    message = str(exc).removeprefix(f"{scene.name}: ")
    for f in init_fields(Scene):
        items = getattr(scene, f.name)
        if isinstance(items, list):
            for i, obj in enumerate(items):
                if repr(obj) in message:
                    return f"{f.name}[{i}]: {message}"
    name = field_of(message, Scene, [f.name for f in init_fields(Scene)])
    if name is not None:
        return f"{name} = {show(_plain(getattr(scene, name)))}: {message}"
    return message


def _check_material_names(scene: Scene) -> None:
    """Every object's ``material`` names a key of ``scene.materials``."""
    materials = getattr(scene, "materials", None)
    if not isinstance(materials, dict):
        return
    for f in init_fields(Scene):
        items = getattr(scene, f.name)
        if not isinstance(items, list):
            continue
        for i, obj in enumerate(items):
            name = getattr(obj, "material", None)
            if isinstance(name, str) and name not in materials:
                raise TableError(f"{f.name}[{i}].material = {show(name)}: no such material; defined under "
                                 f"[materials]: {', '.join(materials) or 'none'}")


def _parse(path: Path) -> dict:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise SceneFileError(f"{path}: a scene file must end in {' or '.join(SUFFIXES)} (TOML or JSON), "
                             f"found {path.suffix or 'no suffix'!r}")
    data = read_input(path, "a scene file", SceneFileError)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneFileError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    if suffix == ".json":
        return _parse_json(path, text)
    return _parse_toml(path, text)


def _parse_json(path: Path, text: str) -> dict:
    def pairs(items):
        out = {}
        for k, v in items:
            if k in out:
                raise SceneFileError(f"{path}: duplicate key {show(k)} in a JSON object")
            out[k] = v
        return out

    try:
        data = json.loads(text, object_pairs_hook=pairs)
    except json.JSONDecodeError as exc:
        raise SceneFileError(f"{path}: line {exc.lineno}, column {exc.colno}: invalid JSON: {exc.msg}") from None
    if not isinstance(data, dict):
        raise SceneFileError(f"{path}: expected a JSON object at the top level, found {show(data)}")
    return data


def _parse_toml(path: Path, text: str) -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        try:
            import tomli as tomllib
        except ModuleNotFoundError:
            raise SceneFileError(f"{path}: reading TOML needs Python >= 3.11 or the tomli package; "
                                 "a .json scene file works everywhere") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        line, col = getattr(exc, "lineno", None), getattr(exc, "colno", None)
        m = re.fullmatch(r"(.*) \(at line (\d+), column (\d+)\)", message, re.S)
        if m:
            message, line, col = m.group(1), m.group(2), m.group(3)
        else:
            message = getattr(exc, "msg", None) or re.sub(r" \(at end of document\)$", "", message)
        where = f"line {line}, column {col}" if line is not None else "at the end of the file"
        raise SceneFileError(f"{path}: {where}: invalid TOML: {message}") from None


def load_scene(path) -> tuple[Scene, RenderSettings]:
    """Read a scene file (see the module docstring): the scene and its render settings.

    Raises :class:`SceneFileError` naming the file, the key path and the value found.
    """
    scene, settings, _ = read_scene(path)
    return scene, settings


def read_scene(path) -> tuple[Scene, RenderSettings, list[tuple[str, Path]]]:
    """:func:`load_scene`, and every file it read as (what, path): the scene file, then each OBJ mesh,
    image texture and environment map under its key (``meshes[0].obj``), what a render must not write over."""
    path = Path(path)
    data = dict(_parse(path))
    render_table = data.pop("render", {})
    read = [("scene", path)]
    try:
        if isinstance(data.get("meshes"), list):
            data["meshes"] = list(data["meshes"])
            _obj_meshes(data, path.parent, read)
        _image_paths(data, path.parent, read)
        scene = build(Scene, data, "", defaults={"name": path.stem, "family": DEFAULT_FAMILY},
                      also_valid=("render",), extra_keys=_EXTRA_KEYS)
        _check_material_names(scene)
        if hasattr(scene, "validate"):
            try:
                scene.validate()
            except ValueError as exc:
                raise TableError(_scene_problem(scene, exc)) from None
        settings = build(RenderSettings, render_table, "render")
    except TableError as exc:
        raise SceneFileError(f"{path}: {exc}") from None
    return scene, settings, read


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------

def _plain(value):
    """Dataclasses to dicts (init fields, in order), tuples to lists, numpy to Python; None dropped from
    tables (TOML has no null; a field that is None is left to its default)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in init_fields(type(value))
                if getattr(value, f.name) is not None}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _toml_table(lines: list, prefix: list, table: dict) -> None:
    for k, v in table.items():
        if not isinstance(v, dict) and not _is_table_array(v):
            lines.append(f"{key_text(k)} = {toml_value(v)}")
    for k, v in table.items():
        name = ".".join(key_text(p) for p in prefix + [k])
        if isinstance(v, dict):
            if not v or any(not isinstance(x, dict) and not _is_table_array(x) for x in v.values()):
                lines += ["", f"[{name}]"]
            _toml_table(lines, prefix + [k], v)
        elif _is_table_array(v):
            for item in v:
                lines += ["", f"[[{name}]]"]
                _toml_table(lines, prefix + [k], item)


def _json_value(v, indent: int) -> str:
    pad = "  " * (indent + 1)
    if isinstance(v, dict):
        if not v:
            return "{}"
        items = [f"{pad}{json.dumps(k, ensure_ascii=False)}: {_json_value(x, indent + 1)}" for k, x in v.items()]
        return "{\n" + ",\n".join(items) + "\n" + "  " * indent + "}"
    if isinstance(v, list) and any(isinstance(x, (dict, list)) for x in v):
        return "[\n" + ",\n".join(pad + _json_value(x, indent + 1) for x in v) + "\n" + "  " * indent + "]"
    return json.dumps(v, ensure_ascii=False)


def dump_scene(scene: Scene, settings: RenderSettings | None = None, format: str = "toml") -> str:
    """The text of a scene file (``format`` ``"toml"`` or ``"json"``) describing ``scene`` and its render
    ``settings`` (default: ``RenderSettings()``). Every field is written, defaults too, and floats in their
    shortest exact form, so :func:`load_scene` gives back an equal scene that renders the same bits."""
    if format not in ("toml", "json"):
        raise ValueError(f"format must be 'toml' or 'json', got {format!r}")
    settings = RenderSettings() if settings is None else settings
    data = _plain(scene)
    data = {"render": _plain(settings), **data}
    if format == "json":
        return _json_value(data, 0) + "\n"
    lines = [f"# kpcn scene file (format: prep/render/scenefile.py); scene {scene.name}"]
    _toml_table(lines, [], data)
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------
# kpcn render --scene
# ------------------------------------------------------------------------------------------------

def half_seeds(seed: int, spp: int) -> tuple[int, int]:
    """The noise seeds of the two halves of a scene file's ``spp`` frame of noise seed ``seed``: two words of
    one SeedSequence (its entropy the frame's seed, spp and a tag of its own), neither the frame's own seed."""
    words = np.random.SeedSequence([int(seed), int(spp), 0x50414952]).generate_state(2, dtype=np.uint64)
    return tuple(int(w) for w in words)


def render_pair(scene_path, scene, settings, read, folder, png: bool) -> dict:
    """The two halves of the scene file's frame (``catalogue.pair_names``: ``settings.spp / 2`` samples each,
    stated in the header, seeds :func:`half_seeds`) into ``folder`` (default: beside the scene file), each with
    a PNG with ``png``. OptionError ``spp`` for an odd spp or one below 4 (a half renders 2 spp or more)."""
    from prep.exr import SPP_ATTRIBUTE, write_aovs
    from prep.files import check_outputs, check_writable
    from prep.render.cycles import catalogue

    if settings.spp % 2 or settings.spp < 4:
        raise OptionError("spp", f"with --pair the frame renders as two halves of half its samples: it needs an "
                          f"even spp of 4 or more, got {settings.spp}")
    folder = Path(folder) if folder is not None else Path(scene_path).parent
    outputs = [folder / n for n in catalogue().pair_names(Path(scene_path).stem, settings.spp)]
    pngs = [png_path(o) for o in outputs] if png else []
    check_outputs(zip(("half a (--out)", "half b (--out)", "PNG preview", "PNG preview"), outputs + pngs), read,
                  "choose another --out")
    for path in outputs + pngs:
        check_writable(path, "output EXR (--out)")
    report = {"outputs": outputs, "seconds": 0.0, "settings": settings}
    for path, seed in zip(outputs, half_seeds(settings.seed, settings.spp)):
        t0 = time.perf_counter()
        layers = render(scene, **{**dataclasses.asdict(settings), "spp": settings.spp // 2, "seed": seed})
        report["seconds"] += time.perf_counter() - t0
        write_aovs(path, layers, attributes={SPP_ATTRIBUTE: settings.spp // 2})
        if png:
            _write_png(png_path(path), layers["default"])
    return report

def default_output(scene_path, spp: int) -> Path:
    """``<scene file stem>-<spp, 5 digits>spp.exr`` beside the scene file."""
    from prep.exr import render_filename

    scene_path = Path(scene_path)
    return scene_path.with_name(render_filename(scene_path.stem, spp))


def png_path(output) -> Path:
    """The tonemapped preview written beside an output EXR."""
    output = Path(output)
    png = output.with_suffix(".png")
    return png if png != output else output.with_name(output.name + ".png")


def _write_png(path: Path, colour: np.ndarray) -> None:
    import matplotlib.image

    from prep.colour import tonemap
    from prep.files import atomic_path

    pixels = np.round(tonemap(colour) * 255.0).astype(np.uint8)
    with atomic_path(path) as tmp:
        matplotlib.image.imsave(tmp, pixels, format="png")


def render_scene_file(scene_path, output=None, *, overrides: dict | None = None, png: bool = True,
                      pair: bool = False) -> dict:
    """Render a scene file to one EXR in the AOV layout (``prep.exr.write_aovs``) and, with ``png``, a
    tonemapped PNG beside it. ``overrides`` (``spp``, ``seed``, ``width``, ... as given on the command
    line) replace the file's ``[render]`` values. The outputs are checked before rendering; an output that
    is a file the scene reads (the scene file, a mesh, a texture) is refused. Returns ``{"output", "png" (if
    written), "seconds", "settings"}``.

    A render setting out of range raises OptionError when it came from ``overrides`` (the command line
    names the flag) and SceneFileError naming ``render.<key>`` when it came from the file.

    ``pair``: the frame's two halves instead (:func:`render_pair`; ``output``, their folder).
    """
    from prep.exr import write_aovs
    from prep.files import check_outputs, check_writable

    scene_path = Path(scene_path)
    overrides = dict(overrides or {})
    scene, settings, read = read_scene(scene_path)
    unknown = set(overrides) - {f.name for f in dataclasses.fields(RenderSettings)}
    if unknown:
        raise ValueError(f"unknown render settings {sorted(unknown)}")
    if "seed" in overrides:  # an option's seed, in the project's one range; a file's is the noise seed itself
        SEED.check("seed", overrides["seed"])
    settings = dataclasses.replace(settings, **overrides)
    if pair:
        return render_pair(scene_path, scene, settings, read, output, png)
    output = Path(output) if output is not None else default_output(scene_path, settings.spp)
    outputs = [output] + ([png_path(output)] if png else [])
    check_outputs(zip(("output EXR (--out)", "PNG preview"), outputs), read, "choose another --out")
    check_writable(output, "output EXR (--out)")
    if png:
        check_writable(outputs[1], "PNG preview")
    t0 = time.perf_counter()
    try:
        layers = render(scene, **dataclasses.asdict(settings))
    except InputFileError as exc:
        raise SceneFileError(f"{scene_path}: {exc}") from None
    except OptionError as exc:
        if exc.option in overrides or exc.option not in {f.name for f in dataclasses.fields(RenderSettings)}:
            raise
        raise SceneFileError(f"{scene_path}: render.{exc.option} = {show(getattr(settings, exc.option))}: "
                             f"{exc.option} {exc.detail}") from None
    seconds = time.perf_counter() - t0
    write_aovs(output, layers)
    report = {"output": output, "seconds": seconds, "settings": settings}
    if png:
        _write_png(outputs[1], layers["default"])
        report["png"] = outputs[1]
    return report
