"""Training renders from Blender Cycles: random procedural scenes, each a noisy frame per input spp and a
reference, as Blender writes them (one multilayer OpenEXR a frame, every pass a denoiser can use).

Why: kpcn's own path tracer makes its training data, and on Cycles' frames the networks trained on it trail
OIDN (docs/results/13-training-longer.md). These scenes are built from Blender's primitives and shader nodes,
drawn at random from a seed (rooms, studio sweeps and open ground; Principled materials with textures, metal,
glass and coats; area, point, emissive and sky lights), never the validation scenes of ../shared/validation.
Every frame is one render at its spp, so its noise is what Cycles' sampler gives a user (not an average of renders).

Runs under bpy (the wheel wants numpy < 2: a venv of its own), started by ``kpcn render-cycles``
(``prep.render.cycles``, which checks the options and the Python), so it imports nothing of kpcn, only the
standard library and bpy:
  kpcn render-cycles OUT [--scenes 0:32] [--res 128] [--spp 4,8,16,32,64] [--ref-spp 1024]
      [--blender-python .venv-bpy/bin/python]
writes OUT/<kind>-<NNN>-<spp>spp.exr (the reference with the same name at --ref-spp) and OUT/render_log.json;
a frame already there is kept, so a killed run resumes. ``kpcn import-renders`` then writes them into a
render set that ``kpcn shards --inputs no-variance`` cuts (docs/training.md §6, docs/results/16-cycles-frames.md).
"""
import argparse
import colorsys
import json
import math
import os
import random
import sys
import time

try:
    import bpy
except ImportError:  # read without bpy for its arguments alone (arguments(): how kpcn's tests check what it passes)
    bpy = None

PASSES = ("combined", "z", "normal", "emit", "environment",
          "diffuse_direct", "diffuse_indirect", "diffuse_color",
          "glossy_direct", "glossy_indirect", "glossy_color",
          "transmission_direct", "transmission_indirect", "transmission_color")
KINDS = ("room", "studio", "ground")


def reset():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def look(o, location, target):
    d = [t - at for t, at in zip(target, location)]
    o.rotation_mode = "XYZ"
    o.rotation_euler = (math.atan2(math.hypot(d[0], d[1]), -d[2]), 0.0, math.atan2(d[1], d[0]) - math.pi / 2)


def colour(rng, sat=(0.0, 0.9), val=(0.1, 0.95)):
    return colorsys.hsv_to_rgb(rng.random(), rng.uniform(*sat), rng.uniform(*val))


def texture(rng, nt):
    kind = rng.choice(("checker", "brick", "noise", "wave", "voronoi"))
    c1, c2 = colour(rng), colour(rng)
    if kind == "checker":
        t = nt.nodes.new("ShaderNodeTexChecker")
        t.inputs["Color1"].default_value = (*c1, 1.0)
        t.inputs["Color2"].default_value = (*c2, 1.0)
        t.inputs["Scale"].default_value = rng.uniform(2.0, 30.0)
        return t.outputs["Color"]
    if kind == "brick":
        t = nt.nodes.new("ShaderNodeTexBrick")
        t.inputs["Scale"].default_value = rng.uniform(2.0, 12.0)
        t.inputs["Color1"].default_value = (*c1, 1.0)
        t.inputs["Color2"].default_value = (*c2, 1.0)
        t.inputs["Mortar"].default_value = (*colour(rng, val=(0.5, 0.9)), 1.0)
        return t.outputs["Color"]
    t = nt.nodes.new({"noise": "ShaderNodeTexNoise", "wave": "ShaderNodeTexWave",
                      "voronoi": "ShaderNodeTexVoronoi"}[kind])
    t.inputs["Scale"].default_value = rng.uniform(2.0, 25.0)
    r = nt.nodes.new("ShaderNodeValToRGB")
    r.color_ramp.elements[0].color = (*c1, 1.0)
    r.color_ramp.elements[1].color = (*c2, 1.0)
    nt.links.new(t.outputs["Fac"] if "Fac" in t.outputs else t.outputs["Distance"], r.inputs["Fac"])
    return r.outputs["Color"]


def material(rng, name, floor=False):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    b = nt.nodes["Principled BSDF"]
    kind = rng.choices(("diffuse", "plastic", "metal", "glass", "coated"),
                       weights=(3, 3, 2, 1 if not floor else 0, 2))[0]
    b.inputs["Base Color"].default_value = (*colour(rng), 1.0)
    b.inputs["Roughness"].default_value = {"diffuse": rng.uniform(0.6, 1.0), "plastic": rng.uniform(0.05, 0.6),
                                           "metal": rng.uniform(0.0, 0.5), "glass": rng.uniform(0.0, 0.15),
                                           "coated": rng.uniform(0.2, 0.8)}[kind]
    if kind == "metal":
        b.inputs["Metallic"].default_value = 1.0
        b.inputs["Base Color"].default_value = (*colour(rng, sat=(0.0, 0.4), val=(0.6, 1.0)), 1.0)
    if kind == "glass":
        b.inputs["Transmission Weight"].default_value = 1.0
        b.inputs["IOR"].default_value = rng.uniform(1.3, 1.6)
        b.inputs["Base Color"].default_value = (*colour(rng, sat=(0.0, 0.3), val=(0.85, 1.0)), 1.0)
    if kind == "coated":
        b.inputs["Coat Weight"].default_value = rng.uniform(0.3, 1.0)
    if kind != "glass" and rng.random() < (0.6 if floor else 0.35):
        nt.links.new(texture(rng, nt), b.inputs["Base Color"])
    return m


def emissive(name, rgb, strength):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    for n in list(nt.nodes):
        if n.type != "OUTPUT_MATERIAL":
            nt.nodes.remove(n)
    e = nt.nodes.new("ShaderNodeEmission")
    e.inputs["Color"].default_value = (*rgb, 1.0)
    e.inputs["Strength"].default_value = strength
    nt.links.new(e.outputs["Emission"], nt.nodes["Material Output"].inputs["Surface"])
    return m


def quad(m, location, rotation, size):
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=location, rotation=rotation)
    o = bpy.context.active_object
    o.scale = (size[0], size[1], 1.0)
    o.data.materials.append(m)
    return o


PRIMITIVES = ("cube", "uv_sphere", "ico_sphere", "cylinder", "torus", "monkey", "cone")


def primitive(rng, m, location, size):
    kind = rng.choice(PRIMITIVES)
    rot = ((rng.uniform(0, math.pi), rng.uniform(0, math.pi), rng.uniform(0, math.pi)) if kind != "uv_sphere"
           else (0, 0, 0))
    if kind == "torus":
        bpy.ops.mesh.primitive_torus_add(major_radius=size, minor_radius=size * rng.uniform(0.15, 0.4),
                                         location=location, rotation=rot)
    elif kind == "ico_sphere":
        bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=rng.choice((1, 4)), radius=size, location=location)
    elif kind == "monkey":
        bpy.ops.mesh.primitive_monkey_add(size=2 * size, location=location, rotation=rot)
    else:
        op = getattr(bpy.ops.mesh, f"primitive_{kind}_add")
        kw = {"cube": {"size": 1.6 * size}, "cone": {"radius1": size}}.get(kind, {"radius": size})
        if kind in ("cylinder", "cone"):
            kw["depth"] = size * rng.uniform(1.0, 3.0)
        op(location=location, rotation=rot, **kw)
    o = bpy.context.active_object
    o.data.materials.append(m)
    if kind in ("uv_sphere", "cylinder", "torus", "monkey", "cone") or (kind == "ico_sphere" and rng.random() < 0.5):
        for p in o.data.polygons:
            p.use_smooth = True
    if kind == "monkey":
        mod = o.modifiers.new("sub", "SUBSURF")
        mod.levels = mod.render_levels = 1
    return o


def lights(rng, scene, centre, kind):
    count = rng.randint(1, 3)
    for i in range(count):
        pick = rng.choices(("area", "point", "strip", "spot"), weights=(4, 3, 2, 1))[0]
        theta, r = rng.uniform(0, 2 * math.pi), rng.uniform(1.5, 3.5)
        loc = (centre[0] + r * math.cos(theta), centre[1] + r * math.sin(theta), rng.uniform(1.5, 3.2))
        rgb = colorsys.hsv_to_rgb(rng.uniform(0.0, 0.17), rng.uniform(0.0, 0.5), 1.0)
        if pick == "strip":
            o = quad(emissive(f"strip{i}", rgb, rng.uniform(5, 60)), loc, (0, 0, 0),
                     (rng.uniform(0.05, 0.3), rng.uniform(0.5, 2.0)))
            look(o, loc, centre)
            continue
        bpy.ops.object.light_add(type={"area": "AREA", "point": "POINT", "spot": "SPOT"}[pick], location=loc)
        li = bpy.context.active_object
        look(li, loc, centre)
        li.data.color = rgb
        if pick == "area":
            li.data.size = rng.uniform(0.2, 1.5)
            li.data.energy = rng.uniform(50, 400)
        elif pick == "point":
            li.data.shadow_soft_size = rng.choice((rng.uniform(0.01, 0.05), rng.uniform(0.1, 0.5)))
            li.data.energy = rng.uniform(30, 300)
        else:
            li.data.energy = rng.uniform(200, 1000)
            li.data.spot_size = rng.uniform(0.4, 1.2)
            li.data.shadow_soft_size = rng.uniform(0.02, 0.3)
    w = bpy.data.worlds.new("w")
    w.use_nodes = True
    bg = w.node_tree.nodes["Background"]
    if kind == "ground":
        sky = w.node_tree.nodes.new("ShaderNodeTexSky")
        if hasattr(sky, "sun_elevation"):
            sky.sun_elevation = math.radians(rng.uniform(5, 70))
            sky.sun_rotation = rng.uniform(0, 2 * math.pi)
        w.node_tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
        bg.inputs["Strength"].default_value = rng.uniform(0.2, 1.0)
    else:
        bg.inputs["Color"].default_value = (*colour(rng, sat=(0, 0.3), val=(0.0, 0.1)), 1.0)
        bg.inputs["Strength"].default_value = rng.uniform(0.0, 1.0)
    scene.world = w


def build(scene, index: int):
    rng = random.Random(index)
    kind = KINDS[index % len(KINDS)]
    centre = (0.0, 0.0, 0.5)
    if kind == "room":
        size = rng.uniform(3.0, 6.0)
        quad(material(rng, "floor", floor=True), (0, 0, 0), (0, 0, 0), (size, size))
        walls = material(rng, "walls", floor=True)
        h = rng.uniform(2.4, 3.2)
        quad(walls, (0, size / 2, h / 2), (math.pi / 2, 0, 0), (size, h))
        quad(walls, (-size / 2, 0, h / 2), (0, math.pi / 2, 0), (size, h))
        if rng.random() < 0.5:
            quad(walls, (size / 2, 0, h / 2), (0, -math.pi / 2, 0), (size, h))
        if rng.random() < 0.6:
            quad(walls, (0, 0, h), (math.pi, 0, 0), (size, size))
    elif kind == "studio":
        quad(material(rng, "sweep", floor=True), (0, 0, 0), (0, 0, 0), (12, 12))
        quad(material(rng, "backdrop", floor=True), (0, 3, 3), (math.pi / 2, 0, 0), (12, 6))
    else:
        quad(material(rng, "ground", floor=True), (0, 0, 0), (0, 0, 0), (40, 40))
    for i in range(rng.randint(3, 7)):
        s = rng.uniform(0.15, 0.6)
        loc = (rng.uniform(-1.3, 1.3), rng.uniform(-1.0, 1.5), s * rng.uniform(0.6, 2.5))
        primitive(rng, material(rng, f"m{i}"), loc, s)
    lights(rng, scene, centre, kind)
    theta = rng.uniform(-2.2, -0.9)
    dist = rng.uniform(3.0, 5.0)
    loc = (dist * math.cos(theta), dist * math.sin(theta), rng.uniform(0.8, 2.4))
    bpy.ops.object.camera_add(location=loc)
    cam = bpy.context.active_object
    look(cam, loc, (rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.6), rng.uniform(0.2, 0.8)))
    cam.data.lens = rng.uniform(24, 50)
    if rng.random() < 0.25:
        cam.data.dof.use_dof = True
        cam.data.dof.aperture_fstop = rng.uniform(1.4, 5.6)
        cam.data.dof.focus_distance = dist
    scene.camera = cam
    return kind


def brighten(scene, factor):
    """Every light source times ``factor``: radiance is linear in them, so every pass scales alike."""
    for li in bpy.data.lights:
        li.energy *= factor
    for m in list(bpy.data.materials) + [scene.world]:
        for n in m.node_tree.nodes:
            if n.type in ("EMISSION", "BACKGROUND"):
                n.inputs["Strength"].default_value *= factor


def exposure(index, target):
    """The factor that brings scene ``index``'s mean linear colour to ``target``, from a small probe render
    (32 x 32, 16 spp): random scenes otherwise range from black rooms to a blinding sky."""
    scene = reset()
    build(scene, index)
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", 16, False
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.resolution_percentage = 100
    im = scene.render.image_settings
    im.file_format, im.color_depth = "OPEN_EXR", "32"
    path = os.path.join(bpy.app.tempdir, f"probe-{index}.exr")
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(path)
    px = list(img.pixels)
    mean = sum(v for i, v in enumerate(px) if i % 4 != 3) / (3 * len(px) / 4)
    os.remove(path)
    return target / max(mean, 1e-4)


def setup(index, res, spp, seed, factor):
    scene = reset()
    kind = build(scene, index)
    brighten(scene, factor)
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = spp
    c.use_adaptive_sampling = False
    c.seed = seed
    c.max_bounces = 12
    c.use_denoising = False
    scene.render.resolution_x = scene.render.resolution_y = res
    scene.render.resolution_percentage = 100
    vl = scene.view_layers[0]
    for p in PASSES:
        setattr(vl, "use_pass_" + p, True)
    vl.cycles.use_pass_volume_direct = True
    vl.cycles.use_pass_volume_indirect = True
    vl.cycles.denoising_store_passes = True
    im = scene.render.image_settings
    if hasattr(im, "media_type"):
        im.media_type = "MULTI_LAYER_IMAGE"
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"
    im.exr_codec = "ZIP"
    scene.view_settings.view_transform = "Standard"
    return scene, kind


def arguments(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--scenes", default="0:32", help="first:end scene indices")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", default="4,8,16,32,64")
    ap.add_argument("--ref-spp", type=int, default=1024)
    return ap.parse_args(argv)


def main():
    a = arguments(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
    first, end = (int(x) for x in a.scenes.split(":"))
    os.makedirs(a.out, exist_ok=True)
    log_path = os.path.join(a.out, "render_log.json")
    log = json.load(open(log_path)) if os.path.exists(log_path) else {"blender": bpy.app.version_string, "renders": {}}
    for index in range(first, end):
        factor = None
        for li, spp in enumerate([int(s) for s in a.spp.split(",")] + [a.ref_spp]):
            kind = KINDS[index % len(KINDS)]
            name = f"{kind}-{index:03d}-{spp:05d}spp.exr"
            path = os.path.join(a.out, name)
            if os.path.exists(path):
                continue
            if factor is None:
                factor = exposure(index, random.Random(-1 - index).uniform(0.1, 0.5))
            scene, _ = setup(index, a.res, spp, seed=100 * index + li + 1, factor=factor)
            scene.render.filepath = os.path.join(a.out, "." + name)
            t = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            os.replace(scene.render.filepath, path)
            log["renders"][name] = time.perf_counter() - t
            print(name, f"{log['renders'][name]:.1f} s", flush=True)
            json.dump(log, open(log_path, "w"), indent=1)


if __name__ == "__main__":
    main()
