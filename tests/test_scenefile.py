"""Scene files (prep/render/scenefile.py) and ``kpcn render --scene``: the format round-trips every built-in
family bit for bit, the example renders, and every mistake in a file is one line naming the file, the key
path and the value found."""

from __future__ import annotations

import dataclasses
import inspect
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.files import checksums

from prep import exr
from prep.errors import KpcnError, OptionError
from prep.render import EFFECTS, FAMILIES, Camera, Material, Quad, Scene, Sphere, make_scene, render, scenefile
from prep.render.scene import Vec3
from prep.render.scenefile import RenderSettings, SceneFileError, dump_scene, load_scene, render_scene_file

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "scenes" / "example.toml"
TINY = {"spp": 2, "seed": 3, "width": 8, "height": 6}


def tiny_render(scene, settings=None):
    """An 8x6, 2 spp render with the all-effects kernel (one compiled kernel for every scene)."""
    kw = dataclasses.asdict(settings) if settings is not None else {}
    kw.update(TINY)
    return render(scene, effects=EFFECTS, **kw)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def load_error(path: Path) -> str:
    with pytest.raises(SceneFileError) as info:
        load_scene(path)
    message = str(info.value)
    assert message.startswith(str(path)) and "\n" not in message, message
    assert isinstance(info.value, KpcnError)
    return message


def example_text() -> str:
    return EXAMPLE.read_text()


def edited(tmp_path, old: str, new: str, name="scene.toml") -> Path:
    text = example_text()
    assert old in text, old
    return write(tmp_path / name, text.replace(old, new, 1))


# ------------------------------------------------------------------------------------------------
# round trip and examples
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["toml", "json"])
@pytest.mark.parametrize("family", list(FAMILIES))
def test_every_builtin_family_round_trips_to_an_equal_scene_that_renders_the_same_bits(tmp_path, family, fmt):
    scene = make_scene(family, 2, 11)
    settings = RenderSettings(**TINY)
    path = write(tmp_path / f"{family}.{fmt}", dump_scene(scene, settings, fmt))
    loaded, loaded_settings = load_scene(path)
    assert loaded == scene
    assert list(loaded.materials) == list(scene.materials)  # material order is the kernels' table order
    assert loaded.effects() == scene.effects()
    assert loaded_settings == settings
    assert dump_scene(loaded, loaded_settings, fmt) == path.read_text()
    original, again = tiny_render(scene), tiny_render(loaded)
    for layer in original:
        assert original[layer].tobytes() == again[layer].tobytes(), layer


def test_dumped_floats_are_exact(tmp_path):
    scene = make_scene("cornell", 0, 0)
    scene = dataclasses.replace(scene, environment=(0.1 + 0.2, 1e-300, 123456789.123456789))
    loaded, _ = load_scene(write(tmp_path / "s.toml", dump_scene(scene)))
    assert loaded.environment == scene.environment


def test_the_example_file_loads_and_renders():
    scene, settings = load_scene(EXAMPLE)
    assert scene.name == "example" and scene.family == scenefile.DEFAULT_FAMILY
    assert {m.kind for m in scene.materials.values()} >= {"lambert", "glossy", "emitter"}
    assert scene.materials["floor"].texture != "none"
    assert any(scene.materials[q.material].kind == "emitter" for q in scene.quads)
    assert "texture" in scene.effects() and "glossy" in scene.effects()
    layers = render(scene, **dataclasses.asdict(dataclasses.replace(settings, **TINY)))
    assert layers["default"].shape == (6, 8, 3)
    assert np.all(np.isfinite(layers["default"])) and layers["default"].max() > 0


def test_the_docstring_example_is_a_valid_scene_file(tmp_path):
    doc = scenefile.__doc__
    block = doc[doc.index("A complete example"):].split("::\n\n", 1)[1]
    lines = []
    for line in block.splitlines():
        if line and not line.startswith("    "):
            break
        lines.append(line[4:])
    scene, settings = load_scene(write(tmp_path / "doc.toml", "\n".join(lines)))
    assert scene.name == "two-spheres" and len(scene.spheres) == 2 and settings.spp == 16
    assert tiny_render(scene)["default"].max() > 0


def test_the_scene_docs_show_the_example_file_as_it_is():
    page = (REPO / "docs" / "scenes.md").read_text()
    assert "## 5 Scene files" in page
    assert "```toml\n" + example_text() + "```" in page


def test_a_minimal_file_takes_the_documented_defaults(tmp_path):
    path = write(tmp_path / "minimal.toml", '[camera]\nposition = [0, 1, 3]\nlook_at = [0, 1, 0]\n[materials]\n')
    scene, settings = load_scene(path)
    assert scene.name == "minimal" and scene.family == "custom" and scene.spheres == [] and scene.quads == []
    assert scene.camera == Camera(position=(0, 1, 3), look_at=(0, 1, 0))
    for name, p in inspect.signature(render).parameters.items():
        if p.default is not p.empty and name != "effects":
            assert getattr(settings, name) == p.default, name
    assert {f.name for f in dataclasses.fields(RenderSettings)} == (
        set(inspect.signature(render).parameters) - {"scene", "effects"})


def test_json_null_leaves_an_optional_field_unset(tmp_path):
    data = {"camera": {"position": [0, 0, 3], "look_at": [0, 0, 0], "focus_distance": None}, "materials": {}}
    scene, _ = load_scene(write(tmp_path / "n.json", json.dumps(data)))
    assert scene.camera.focus_distance is None


@dataclasses.dataclass(frozen=True)
class Cone:
    """A shape the scene model does not have (yet)."""

    vertices: list[Vec3]
    material: str
    smooth: bool = False


@dataclasses.dataclass
class ConeScene(Scene):
    cones: list[Cone] = dataclasses.field(default_factory=list)


def test_tables_follow_the_dataclass_fields_so_new_fields_and_shapes_need_no_change(tmp_path, monkeypatch):
    """A scene model with a field and a shape list this module has never heard of still loads, checks and
    round-trips: what the format accepts is read from the dataclasses."""

    monkeypatch.setattr(scenefile, "Scene", ConeScene)
    cone = '\n[[cones]]\nvertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\nmaterial = "red"\n'
    scene, settings = load_scene(write(tmp_path / "m.toml", example_text() + cone))
    assert scene.cones == [Cone([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)], "red")]
    again, _ = load_scene(write(tmp_path / "again.toml", dump_scene(scene, settings)))
    assert again == scene

    def error(new_cone):
        return load_error(write(tmp_path / "bad.toml", example_text() + new_cone))

    message = error(cone + "smoth = true\n")
    assert "unknown key cones[0].smoth = true" in message and "vertices, material, smooth" in message
    assert "cones[0].vertices[2] = [0, 1]: expected 3 finite numbers" in error(cone.replace("[0, 1, 0]]", "[0, 1]]"))
    assert 'cones[0].material = "rouge": no such material' in error(cone.replace('"red"', '"rouge"'))


# ------------------------------------------------------------------------------------------------
# meshes: from OBJ files or inline
# ------------------------------------------------------------------------------------------------

TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"


def with_mesh(tmp_path, table: str, obj: str | None = TRIANGLE_OBJ) -> Path:
    if obj is not None:
        write(tmp_path / "shape.obj", obj)
    return write(tmp_path / "scene.toml", example_text() + "\n[[meshes]]\n" + table)


def test_a_mesh_from_an_obj_file_beside_the_scene_is_placed_and_round_trips_inline(tmp_path):
    path = with_mesh(tmp_path, 'obj = "shape.obj"\nscale = 2\nrotate_y = 90\ntranslate = [0, 1, 0]\n'
                               'material = "red"\n')
    scene, settings = load_scene(path)
    (mesh,) = scene.meshes
    assert mesh.faces == ((0, 1, 2), (0, 2, 3)) and mesh.material == "red"
    np.testing.assert_allclose(mesh.vertices[1], (0, 1, -2), atol=1e-12)
    text = dump_scene(scene, settings)
    assert "[[meshes]]" in text and "obj" not in text.split("[[meshes]]")[1]
    again, _ = load_scene(write(tmp_path / "inline.toml", text))
    assert again == scene
    json_again, _ = load_scene(write(tmp_path / "inline.json", dump_scene(scene, settings, "json")))
    assert json_again == scene
    inline = load_scene(with_mesh(tmp_path, 'vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\nfaces = [[0, 1, 2]]\n'
                                            'material = "red"\n', obj=None))[0]
    assert inline.meshes[0].faces == ((0, 1, 2),) and "mesh" in inline.effects()


def test_a_mesh_with_an_emitter_material_lights_the_room_like_the_same_quad(tmp_path):
    # the example's ceiling light as two triangles wound so that their normal, cross(v1 - v0, v2 - v0), points
    # down like the quad's cross(u, v): the room is lit alike, up to the noise of either render
    quad = ("[[quads]]  # the light: emits on the side of cross(u, v) = -y, just below the ceiling\n"
            "corner = [-0.25, 1.999, -0.25]\nu = [0.5, 0.0, 0.0]\nv = [0.0, 0.0, 0.5]\nmaterial = \"light\"\n")
    mesh = ("[[meshes]]\nvertices = [[-0.25, 1.999, -0.25], [0.25, 1.999, -0.25], [0.25, 1.999, 0.25], "
            "[-0.25, 1.999, 0.25]]\nfaces = [[0, 1, 2], [0, 2, 3]]\nmaterial = \"light\"\n")
    as_quad, _ = load_scene(EXAMPLE)
    as_mesh, _ = load_scene(edited(tmp_path, quad, mesh))
    assert len(as_mesh.quads) == len(as_quad.quads) - 1 and as_mesh.meshes[0].material == "light"
    assert {"emitter", "mesh"} <= as_mesh.effects()
    size = dict(spp=256, seed=3, width=16, height=12, effects=EFFECTS)
    a, b = render(as_quad, **size), render(as_mesh, **size)
    # pixels are independent: the variance of the image mean is the sum of the pixels' over their number
    # squared (colorVariance, the RGB average, bounds the variance of the RGB mean)
    n = a["default"].shape[0] * a["default"].shape[1]
    mean_a, mean_b = a["default"].astype(np.float64).mean(), b["default"].astype(np.float64).mean()
    sigma = math.sqrt((a["colorVariance"].astype(np.float64).sum() + b["colorVariance"].sum()) / n**2)
    assert np.isfinite(b["default"]).all() and sigma < 0.05 * mean_a
    assert abs(mean_b - mean_a) < 4 * sigma, (mean_a, mean_b, sigma)


@pytest.mark.parametrize("table, obj, needles", [
    ('obj = "shape.obj"\nmaterial = "red"\n', "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
     ['meshes[0].obj = "shape.obj": ', "shape.obj:4: face vertex 9 does not exist"]),
    ('obj = "nothing.obj"\nmaterial = "red"\n', None, ['meshes[0].obj = "nothing.obj": ', "nothing.obj: no such file"]),
    ('obj = "shape.obj"\nscale = 0\nmaterial = "red"\n', TRIANGLE_OBJ, ["meshes[0].scale = 0: scale must be > 0"]),
    ('obj = "shape.obj"\nrotate_y = "left"\nmaterial = "red"\n', TRIANGLE_OBJ,
     ['meshes[0].rotate_y = "left": expected a finite number']),
    ('obj = "shape.obj"\ntranslate = [0, 1]\nmaterial = "red"\n', TRIANGLE_OBJ,
     ["meshes[0].translate = [0, 1]: expected 3 finite numbers"]),
    ('scale = 2\nvertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\nfaces = [[0, 1, 2]]\nmaterial = "red"\n', None,
     ["meshes[0].scale = 2: ", "no obj key"]),
    ('obj = "shape.obj"\nfaces = [[0, 1, 2]]\nmaterial = "red"\n', TRIANGLE_OBJ, ["meshes[0].faces: ", "not both"]),
    ('obj = "shape.obj"\nmaterial = "rouge"\n', TRIANGLE_OBJ, ['meshes[0].material = "rouge": no such material']),
    ('obj = "shape.obj"\nscal = 2\nmaterial = "red"\n', TRIANGLE_OBJ,
     ["unknown key meshes[0].scal = 2 (did you mean scale?)", "vertices, faces, material, obj, translate, scale"]),
    ('vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\nfaces = [[0, 1, 3]]\nmaterial = "red"\n', None,
     ["meshes[0].faces = [[0, 1, 3]]: Mesh.faces must index the 3 vertices"]),
    ('vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\nfaces = [[0, 1.5, 2]]\nmaterial = "red"\n', None,
     ["meshes[0].faces[0] = [0, 1.5, 2]: expected 3 integers"]),
    ('obj = "shape.obj"\n', TRIANGLE_OBJ, ["meshes[0] lacks key material"]),
])
def test_mesh_mistakes_name_the_key_path_and_the_obj_file_and_line(tmp_path, table, obj, needles):
    message = load_error(with_mesh(tmp_path, table, obj))
    for needle in needles:
        assert needle in message, (needle, message)


# ------------------------------------------------------------------------------------------------
# errors: every message starts with the file, names the key path and the value found
# ------------------------------------------------------------------------------------------------

def test_unknown_top_level_key_names_it_and_lists_the_valid_keys(tmp_path):
    message = load_error(edited(tmp_path, 'name = "example"', 'name = "example"\nenvironmnet = [1, 1, 1]'))
    assert "unknown key environmnet = [1, 1, 1]" in message and "did you mean environment?" in message
    valid = message.split("valid keys at the top level: ")[1]
    assert valid.split(", ") == [f.name for f in dataclasses.fields(Scene)] + ["render"]


@pytest.mark.parametrize("old, new, key, cls", [
    ("fov = 40.0", "fov = 40.0\nfov_degrees = 40", "camera.fov_degrees = 40", Camera),
    ("albedo = [0.63, 0.07, 0.05]", "albdo = [0.63, 0.07, 0.05]", "materials.red.albdo = [0.63, 0.07, 0.05]",
     Material),
    ("radius = 0.3\n", "radius = 0.3\nradios = 2\n", "spheres[1].radios = 2", Sphere),
    ('material = "floor"', 'material = "floor"\nw = [0, 1, 0]', "quads[0].w = [0, 1, 0]", Quad),
    ("spp = 16", "spp = 16\nsamples = 4", "render.samples = 4", RenderSettings),
])
def test_unknown_key_in_a_table_names_the_key_path_and_the_valid_keys(tmp_path, old, new, key, cls):
    message = load_error(edited(tmp_path, old, new))
    assert f"unknown key {key}" in message
    assert ", ".join(f.name for f in dataclasses.fields(cls)) in message


@pytest.mark.parametrize("old, new, needle", [
    ("radius = 0.3\n", "radius = -1\n", "spheres[1].radius = -1: Sphere.radius must be > 0"),
    ("albedo = [0.63, 0.07, 0.05]", "albedo = [0.63, 0.07]",
     "materials.red.albedo = [0.63, 0.07]: expected 3 finite numbers"),
    ("albedo = [0.63, 0.07, 0.05]", "albedo = [0.63, 1.5, 0.05]", "materials.red.albedo = [0.63, 1.5, 0.05]: "),
    ('kind = "glossy"', 'kind = "chrome"', 'materials.gold.kind = "chrome": material kind must be one of'),
    ('material = "blue"', 'material = "bleu"', 'spheres[1].material = "bleu": no such material'),
    ('fov = 40.0', 'fov = "wide"', 'camera.fov = "wide": expected a finite number'),
    ('fov = 40.0', 'fov = 200', 'camera.fov = 200: Camera.fov must be in (0, 180)'),
    ('roughness = 0.15', 'roughness = nan', 'materials.gold.roughness = nan: expected a finite number'),
    ('spp = 16', 'spp = 16.5', 'render.spp = 16.5: expected an integer'),
    ('spp = 16', 'spp = true', 'render.spp = true: expected an integer'),
    ('radius = 0.3\n', '', 'spheres[1] lacks key radius (required: center, radius, material)'),
    ('position = [0.0, 1.0, 3.4]', 'position = 3', 'camera.position = 3: expected 3 finite numbers'),
    ('environment = [0.0, 0.0, 0.0]', 'environment = [-1.0, 0.0, 0.0]',
     'environment = [-1.0, 0.0, 0.0]: Scene.environment must be >= 0'),
    ('v = [0.0, 0.0, 0.5]', 'v = [1.0, 0.0, 0.0]', 'quads[5]: Quad edges are parallel'),
])
def test_a_wrong_value_names_the_key_path_and_the_value_found(tmp_path, old, new, needle):
    assert needle in load_error(edited(tmp_path, old, new))


def test_a_render_setting_out_of_range_in_the_file_names_its_key(tmp_path):
    path = edited(tmp_path, "spp = 16", "spp = 1")
    with pytest.raises(SceneFileError,
                       match=r"scene\.toml: render\.spp = 1: spp must be an integer in \[2, 65536\], got 1"):
        render_scene_file(path, tmp_path / "out.exr", png=False)
    # the same value given as an option is the option's fault (the command line names the flag)
    with pytest.raises(OptionError, match=r"spp must be an integer in \[2, 65536\]"):
        render_scene_file(EXAMPLE, tmp_path / "out.exr", overrides={"spp": 1}, png=False)
    assert not (tmp_path / "out.exr").exists()


def test_a_seed_option_beyond_the_projects_range_is_refused_before_rendering(tmp_path):
    # the option's seed is in the one range of every command (prep.bounds.SEED); a file's is the noise seed
    with pytest.raises(OptionError, match=r"seed must be an integer in \[0, 4294967295\], got 4294967296"):
        render_scene_file(EXAMPLE, tmp_path / "out.exr", overrides={"seed": 2**32}, png=False)
    assert not any(tmp_path.iterdir())


def test_toml_syntax_error_names_the_line_and_column(tmp_path):
    path = edited(tmp_path, "fov = 40.0", "fov = = 40")
    line = next(i for i, text in enumerate(path.read_text().splitlines(), 1) if text.startswith("fov = ="))
    message = load_error(path)
    assert f"line {line}, column 7: invalid TOML" in message


def test_json_syntax_error_names_the_line_and_column(tmp_path):
    path = write(tmp_path / "s.json", '{\n  "name": "x",\n  "camera": {"position": [0, 0, 3] "look_at": [0, 0, 0]}\n}')
    assert "line 3, column 36: invalid JSON" in load_error(path)


def test_json_duplicate_keys_and_a_non_object_are_refused(tmp_path):
    assert 'duplicate key "name"' in load_error(write(tmp_path / "d.json", '{"name": "a", "name": "b"}'))
    assert "expected a JSON object at the top level, found [1, 2]" in load_error(write(tmp_path / "l.json", "[1, 2]"))


def test_unsupported_suffix_and_missing_file_are_refused(tmp_path):
    message = load_error(write(tmp_path / "scene.yaml", "name: x\n"))
    assert "must end in .toml or .json" in message and "'.yaml'" in message
    assert "no such file" in load_error(tmp_path / "nothing.toml")


def test_json_files_give_the_same_key_paths(tmp_path):
    scene, settings = load_scene(EXAMPLE)
    data = json.loads(dump_scene(scene, settings, "json"))
    data["spheres"][1]["radius"] = -2
    message = load_error(write(tmp_path / "s.json", json.dumps(data)))
    assert "spheres[1].radius = -2: Sphere.radius must be > 0" in message


# ------------------------------------------------------------------------------------------------
# kpcn render --scene
# ------------------------------------------------------------------------------------------------

def test_cli_renders_a_scene_file_to_a_readable_exr_and_a_preview(tmp_path):
    res = run_main("render", "--scene", EXAMPLE, "--width", 8, "--height", 6, "--spp", 2, "--out", "x.exr",
               cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    aovs = exr.read_aovs(tmp_path / "x.exr")
    assert aovs["default"].shape == (6, 8, 3) and set(aovs) >= set(exr.RGB_LAYERS + exr.SCALAR_LAYERS)
    assert (tmp_path / "x.png").read_bytes().startswith(b"\x89PNG")
    # the command-line values replaced the file's, the rest came from the file
    scene, settings = load_scene(EXAMPLE)
    expected = render(scene, **dataclasses.asdict(dataclasses.replace(settings, spp=2, width=8, height=6)))
    assert np.array_equal(aovs["default"], expected["default"])


def test_cli_default_output_is_named_after_the_scene_file_beside_it(tmp_path):
    (tmp_path / "scenes").mkdir()
    shutil.copy(EXAMPLE, tmp_path / "scenes" / "room.toml")
    res = run_main("render", "--scene", "scenes/room.toml", "--width", 4, "--height", 4, "--spp", 3, "--no-png",
               cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(checksums(tmp_path)) == ["scenes/room-00003spp.exr", "scenes/room.toml"]


def test_cli_bad_scene_file_is_one_line_naming_the_key_and_changes_nothing(tmp_path):
    edited(tmp_path, "albedo = [0.63, 0.07, 0.05]", "albdo = [0.63, 0.07, 0.05]", name="bad.toml")
    (tmp_path / "x.exr").write_bytes(b"an older render")
    before = checksums(tmp_path)
    res = run_main("render", "--scene", "bad.toml", "--out", "x.exr", cwd=tmp_path)
    assert_one_line_error(res, "bad.toml", "materials.red.albdo", "albedo")
    assert checksums(tmp_path) == before


def test_cli_refuses_options_of_the_other_mode_and_an_output_over_the_scene_file(tmp_path):
    shutil.copy(EXAMPLE, tmp_path / "s.toml")
    before = checksums(tmp_path)
    assert_one_line_error(run_main("render", "--scene", "s.toml", "--input-spp", "4", cwd=tmp_path), "--input-spp")
    assert_one_line_error(run_main("render", "--spp", "4", "--out", "r", cwd=tmp_path), "--spp", "--scene")
    assert_one_line_error(run_main("render", "--scene", "s.toml", "--out", "s.toml", cwd=tmp_path), "s.toml",
                          "scene file")
    assert_one_line_error(run_main("render", "--scene", "s.toml", "--spp", "1", "--out", "o.exr", cwd=tmp_path),
                          "--spp", "got 1")
    assert checksums(tmp_path) == before


def test_an_image_texture_is_found_beside_the_scene_file_and_a_missing_one_is_named(tmp_path):
    import matplotlib.image

    (tmp_path / "tex").mkdir()
    matplotlib.image.imsave(tmp_path / "tex" / "wood.png", np.full((2, 2, 3), 200, dtype=np.uint8))
    text = (EXAMPLE.read_text().replace('texture = "uv"', 'texture = "image"\nimage = "tex/wood.png"')
            .replace("albedo2 = [0.2, 0.2, 0.24]\n", ""))
    scene_file = tmp_path / "s.toml"
    scene_file.write_text(text)
    scene, _ = load_scene(scene_file)
    assert Path(scene.materials["floor"].image) == tmp_path / "tex" / "wood.png"
    scene_file.write_text(text.replace("tex/wood.png", "tex/oak.png"))
    assert 'materials.floor.image = "tex/oak.png": no such file' in load_error(scene_file)


def test_an_environment_map_is_read_beside_the_scene_file_or_baked_from_a_sky_table(tmp_path):
    (tmp_path / "maps").mkdir()
    exr.write_aovs(tmp_path / "maps" / "sky.exr", {"default": np.full((4, 8, 3), 0.25, dtype=np.float32)})
    base = example_text().replace("environment = [0.0, 0.0, 0.0]", "", 1)
    scene_file = write(tmp_path / "s.toml", base + '\n[environment_map]\nimage = "maps/sky.exr"\nscale = 2.0\n')
    scene, settings = load_scene(scene_file)
    assert Path(scene.environment_map.image) == tmp_path / "maps" / "sky.exr"
    assert scene.environment_map.scale == 2.0 and "environment_map" in scene.effects()
    again, _ = load_scene(write(tmp_path / "again.toml", dump_scene(scene, settings)))
    assert again == scene
    sky = base + "\n[environment_map]\nscale = 2.0\n\n[environment_map.sky]\nsun_elevation = 25\nsun_radius = 3.0\n"
    scene, _ = load_scene(write(tmp_path / "sky.toml", sky))
    assert scene.environment_map.sky.sun_elevation == 25.0 and scene.environment_map.image == ""
    assert tiny_render(scene)["default"].max() > 0
    missing = write(tmp_path / "m.toml", scene_file.read_text().replace("maps/sky.exr", "maps/none.exr"))
    assert 'environment_map.image = "maps/none.exr": no such file' in load_error(missing)
    bad = write(tmp_path / "b.toml", sky.replace("sun_radius = 3.0", "sun_radius = -3.0"))
    assert "environment_map.sky.sun_radius = -3.0: Sky.sun_radius must be in (0, 20]" in load_error(bad)
    both = write(tmp_path / "both.toml", "environment = [0.1, 0.1, 0.1]\n" + sky)
    assert "Scene.environment must stay black" in load_error(both)


def test_an_unreadable_environment_map_is_one_line_naming_the_scene_and_the_map(tmp_path):
    (tmp_path / "sky.exr").write_bytes(b"not an exr")
    text = example_text().replace("environment = [0.0, 0.0, 0.0]", "")
    scene_file = write(tmp_path / "s.toml", text + '\n[environment_map]\nimage = "sky.exr"\n')
    with pytest.raises(SceneFileError, match=r"s\.toml: .*sky\.exr: not a readable OpenEXR file"):
        render_scene_file(scene_file, tmp_path / "out.exr", overrides=TINY)
    assert not (tmp_path / "out.exr").exists()


def test_the_sky_example_is_lit_by_its_sky_alone():
    scene, _ = load_scene(REPO / "scenes" / "sky.toml")
    assert scene.environment_map.sky is not None and "emitter" not in scene.effects()
    layers = tiny_render(scene)
    assert layers["diffuse"].max() > 0  # the ground is lit, by the map as a light


def test_render_never_writes_over_a_file_the_scene_reads(tmp_path, monkeypatch):
    # the scene file, its image texture, its environment map and its OBJ mesh: the EXR and its PNG preview
    # are each checked against every one of them, before anything is rendered
    import matplotlib.image

    (tmp_path / "tex").mkdir()
    (tmp_path / "maps").mkdir()
    matplotlib.image.imsave(tmp_path / "tex" / "wood.png", np.full((2, 2, 3), 200, dtype=np.uint8))
    exr.write_aovs(tmp_path / "maps" / "sky.exr", {"default": np.full((4, 8, 3), 0.25, dtype=np.float32)})
    shutil.copy(REPO / "scenes" / "torus.obj", tmp_path / "torus.obj")
    text = (example_text().replace('texture = "uv"', 'texture = "image"\nimage = "tex/wood.png"')
            .replace("albedo2 = [0.2, 0.2, 0.24]\n", "").replace("environment = [0.0, 0.0, 0.0]", "", 1)
            + '\n[environment_map]\nimage = "maps/sky.exr"\n\n[[meshes]]\nobj = "torus.obj"\nmaterial = "floor"\n')
    write(tmp_path / "s.toml", text)
    before = checksums(tmp_path)
    res = run_main("render", "--scene", "s.toml", "--out", "tex/wood.exr", cwd=tmp_path)
    assert_one_line_error(res, "PNG preview tex/wood.png is the materials.floor.image file tex/wood.png itself")
    monkeypatch.chdir(tmp_path)
    for out, message in [("maps/sky.exr", "output EXR (--out) maps/sky.exr is the environment_map.image file"),
                         ("torus.obj", "output EXR (--out) torus.obj is the meshes[0].obj file torus.obj"),
                         ("./s.toml", "output EXR (--out) s.toml is the scene file s.toml")]:
        with pytest.raises(KpcnError, match="^" + re.escape(message)):
            render_scene_file("s.toml", out, overrides=TINY)
    assert checksums(tmp_path) == before
