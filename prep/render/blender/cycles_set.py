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
  kpcn render-cycles OUT [--scenes 0:32] [--res 128[,192...]] [--spp 4,8,16,32,64] [--ref-spp 1024] [--seed 0]
      [--blender-python .venv-bpy/bin/python]
builds each scene from its recipe (``catalogue.py`` beside this file: the effects it drew, written as
OUT/<scene>.json), writes OUT/<kind>-<NNN>-<spp>spp.exr (the reference with the same name at --ref-spp),
OUT/render_log.json, and OUT/manifest.json after each scene; a frame already there is kept, so a killed run
resumes. ``kpcn import-renders`` then writes them into a
render set that ``kpcn shards --inputs no-variance`` cuts (docs/training.md §6, docs/results/16-cycles-frames.md).
"""
import argparse
import json
import math
import os
import sys
import time

try:
    import bpy
except ImportError:  # read without bpy for its arguments alone (arguments(): how kpcn's tests check what it passes)
    bpy = None

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # as when run as a script, for a reader's import
import catalogue  # noqa: E402  beside this file: the effects, a scene's recipe, the manifest (the standard library alone)

PASSES = ("combined", "z", "normal", "emit", "environment",
          "diffuse_direct", "diffuse_indirect", "diffuse_color",
          "glossy_direct", "glossy_indirect", "glossy_color",
          "transmission_direct", "transmission_indirect", "transmission_color")


def reset():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def look(o, location, target):
    d = [t - at for t, at in zip(target, location)]
    o.rotation_mode = "XYZ"
    o.rotation_euler = (math.atan2(math.hypot(d[0], d[1]), -d[2]), 0.0, math.atan2(d[1], d[0]) - math.pi / 2)


def texture(t, nt):
    if t["kind"] in ("checker", "brick"):
        n = nt.nodes.new("ShaderNodeTexChecker" if t["kind"] == "checker" else "ShaderNodeTexBrick")
        n.inputs["Color1"].default_value = (*t["c1"], 1.0)
        n.inputs["Color2"].default_value = (*t["c2"], 1.0)
        n.inputs["Scale"].default_value = t["scale"]
        if "mortar" in t:
            n.inputs["Mortar"].default_value = (*t["mortar"], 1.0)
        if "brick_width" in t:  # a validation wall's proportions (a training one keeps Blender's default)
            n.inputs["Brick Width"].default_value, n.inputs["Row Height"].default_value = t["brick_width"], \
                t["row_height"]
        return n.outputs["Color"]
    n = nt.nodes.new({"noise": "ShaderNodeTexNoise", "wave": "ShaderNodeTexWave", "voronoi": "ShaderNodeTexVoronoi",
                      "magic": "ShaderNodeTexMagic", "gabor": "ShaderNodeTexGabor"}[t["kind"]])
    n.inputs["Scale"].default_value = t["scale"]
    r = nt.nodes.new("ShaderNodeValToRGB")
    r.color_ramp.elements[0].color = (*t["c1"], 1.0)
    r.color_ramp.elements[1].color = (*t["c2"], 1.0)
    fac = next(n.outputs[o] for o in ("Fac", "Distance", "Value") if o in n.outputs)
    nt.links.new(fac, r.inputs["Fac"])
    return r.outputs["Color"]


def only_output(nt):
    for n in list(nt.nodes):
        if n.type != "OUTPUT_MATERIAL":
            nt.nodes.remove(n)
    return nt.nodes["Material Output"]


PRINCIPLED = {"base": "Base Color", "roughness": "Roughness", "metallic": "Metallic", "transmission":
              "Transmission Weight", "ior": "IOR", "coat": "Coat Weight", "coat_roughness": "Coat Roughness",
              "coat_tint": "Coat Tint", "sheen": "Sheen Weight", "sheen_roughness": "Sheen Roughness",
              "sheen_tint": "Sheen Tint", "subsurface": "Subsurface Weight", "sss_radius": "Subsurface Radius",
              "sss_scale": "Subsurface Scale"}


def material(spec, name):
    """A material from its recipe: an emission shader, or a Principled BSDF with the inputs the spec sets, a
    texture on its base colour, and a volume inside (a medium in glass)."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    if spec["kind"] == "emission":
        out = only_output(nt)  # before the new nodes: it removes every other node
        e = nt.nodes.new("ShaderNodeEmission")
        e.inputs["Color"].default_value = (*spec["emission"], 1.0)
        e.inputs["Strength"].default_value = spec["strength"]
        nt.links.new(e.outputs["Emission"], out.inputs["Surface"])
        return m
    b = nt.nodes["Principled BSDF"]
    for key, socket in PRINCIPLED.items():
        if key in spec:
            v = spec[key]
            b.inputs[socket].default_value = (*v, 1.0) if key in ("base", "coat_tint", "sheen_tint") else v
    if "texture" in spec:
        nt.links.new(texture(spec["texture"], nt), b.inputs["Base Color"])
    if "volume" in spec:
        v = nt.nodes.new("ShaderNodeVolumePrincipled")
        v.inputs["Density"].default_value = spec["volume"]["density"]
        v.inputs["Color"].default_value = (*spec["volume"]["colour"], 1.0)
        v.inputs["Absorption Color"].default_value = (*spec["volume"]["absorption"], 1.0)
        nt.links.new(v.outputs["Volume"], nt.nodes["Material Output"].inputs["Volume"])
    return m


def medium(spec, name):
    """A box of Principled Volume: homogeneous, or with its density a noise texture through a ramp (smoke)."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    out = only_output(nt)  # no surface: the box is the medium alone
    v = nt.nodes.new("ShaderNodeVolumePrincipled")
    v.inputs["Color"].default_value = (*spec["colour"], 1.0)
    v.inputs["Anisotropy"].default_value = spec["anisotropy"]
    v.inputs["Density"].default_value = spec["density"]
    if "noise" in spec:
        n = nt.nodes.new("ShaderNodeTexNoise")
        n.inputs["Scale"].default_value = spec["noise"]["scale"]
        n.inputs["Detail"].default_value = spec["noise"]["detail"]
        r = nt.nodes.new("ShaderNodeValToRGB")
        r.color_ramp.elements[0].position = spec["noise"]["threshold"]
        r.color_ramp.elements[1].position = min(1.0, spec["noise"]["threshold"] + 0.25)
        mul = nt.nodes.new("ShaderNodeMath")
        mul.operation = "MULTIPLY"
        mul.inputs[1].default_value = spec["density"]
        nt.links.new(n.outputs["Fac"], r.inputs["Fac"])
        nt.links.new(r.outputs["Color"], mul.inputs[0])
        nt.links.new(mul.outputs["Value"], v.inputs["Density"])
    nt.links.new(v.outputs["Volume"], out.inputs["Volume"])
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=spec["location"])
    o = bpy.context.active_object
    o.scale = spec["size"]
    o.data.materials.append(m)
    return o


def surface(spec, name):
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=spec["location"], rotation=spec["rotation"])
    o = bpy.context.active_object
    o.scale = (spec["size"][0], spec["size"][1], 1.0)
    o.data.materials.append(material(spec["material"], name))
    if "waves" in spec:  # a water surface: subdivided, displaced by a noise texture
        sub = o.modifiers.new("sub", "SUBSURF")
        sub.subdivision_type, sub.levels, sub.render_levels = "SIMPLE", 6, 6
        tex = bpy.data.textures.new(name, "CLOUDS")
        tex.noise_scale = 1.0 / spec["waves"]["scale"]
        disp = o.modifiers.new("waves", "DISPLACE")
        disp.texture, disp.strength = tex, spec["waves"]["height"] / max(spec["size"])
        for p in o.data.polygons:
            p.use_smooth = True
    return o


def primitive(spec, name):
    kind, size, loc, rot = spec["shape"], spec["size"], spec["location"], spec["rotation"]
    if kind == "torus":
        bpy.ops.mesh.primitive_torus_add(major_radius=size, minor_radius=spec["minor"], location=loc, rotation=rot)
    elif kind == "ico_sphere":
        bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=spec["subdivisions"], radius=size, location=loc)
    elif kind == "monkey":
        bpy.ops.mesh.primitive_monkey_add(size=2 * size, location=loc, rotation=rot)
    else:
        kw = {"cube": {"size": 1.6 * size}, "cone": {"radius1": size}}.get(kind, {"radius": size})
        if "depth" in spec:
            kw["depth"] = spec["depth"]
        getattr(bpy.ops.mesh, f"primitive_{kind}_add")(location=loc, rotation=rot, **kw)
    o = bpy.context.active_object
    o.data.materials.append(material(spec["material"], name))
    for p in o.data.polygons:
        p.use_smooth = spec["smooth"]
    if kind == "monkey":
        mod = o.modifiers.new("sub", "SUBSURF")
        mod.levels = mod.render_levels = 1
    if "motion" in spec:  # keyed over frames 1..2, rendered at frame 1 with the shutter open across them
        o.keyframe_insert("location", frame=1)
        o.keyframe_insert("rotation_euler", frame=1)
        o.location = [a + b for a, b in zip(loc, spec["motion"])]
        o.rotation_euler[2] += spec["spin"]
        o.keyframe_insert("location", frame=2)
        o.keyframe_insert("rotation_euler", frame=2)
    if "hair" in spec:
        hair(o, spec["hair"], name)
    return o


def hair(o, spec, name):
    mod = o.modifiers.new("hair", "PARTICLE_SYSTEM")
    ps = mod.particle_system.settings
    ps.type, ps.count, ps.hair_length = "HAIR", spec["count"], spec["length"]
    ps.use_advanced_hair = True
    ps.root_radius, ps.tip_radius = 0.02, 0.0
    mod.particle_system.seed = spec["seed"]
    m = bpy.data.materials.new(name + "-hair")
    m.use_nodes = True
    nt = m.node_tree
    out = only_output(nt)
    h = nt.nodes.new("ShaderNodeBsdfHairPrincipled")
    h.inputs["Color"].default_value = (*spec["colour"], 1.0)
    h.inputs["Roughness"].default_value = spec["roughness"]
    nt.links.new(h.outputs[0], out.inputs["Surface"])
    o.data.materials.append(m)
    ps.material = len(o.data.materials)


def text(spec, name):
    bpy.ops.object.text_add(location=spec["location"], rotation=spec["rotation"])
    o = bpy.context.active_object
    o.data.body, o.data.size, o.data.extrude = spec["body"], spec["size"], 0.002
    o.data.materials.append(material(spec["material"], name))
    return o


def lamp(spec, i):
    if spec["type"] == "strip":
        m = {"kind": "emission", "emission": spec["rgb"], "strength": spec["energy"]}
        o = surface({"location": spec["location"], "rotation": (0, 0, 0), "size": spec["size"], "material": m},
                    f"strip{i}")
        look(o, spec["location"], spec["target"])
        return
    bpy.ops.object.light_add(type=spec["type"].upper(), location=spec.get("location", (0, 0, 5)))
    li = bpy.context.active_object
    li.data.color, li.data.energy = spec["rgb"], spec["energy"]
    if spec["type"] == "sun":
        d = spec["direction"]
        look(li, (0, 0, 0), d)
        li.data.angle = spec["angle"]
        return
    look(li, spec["location"], spec["target"])
    if spec["type"] == "area":
        li.data.size = spec["size"]
    else:
        li.data.shadow_soft_size = spec["size"]
    if spec["type"] == "spot":
        li.data.spot_size = spec["spot_size"]


def world(spec):
    w = bpy.data.worlds.new("w")
    w.use_nodes = True
    nt = w.node_tree
    bg = nt.nodes["Background"]
    bg.inputs["Strength"].default_value = spec["strength"]
    if spec["type"] == "flat":
        bg.inputs["Color"].default_value = (*spec["rgb"], 1.0)
    elif spec["type"] == "sky":
        sky = nt.nodes.new("ShaderNodeTexSky")
        sky.sky_type = spec["sky"]
        sky.sun_elevation, sky.sun_rotation = math.radians(spec["elevation"]), spec["rotation"]
        nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    else:  # an HDRI-like environment: noise patches between two colours, a hot spot towards one direction
        n = nt.nodes.new("ShaderNodeTexNoise")
        n.inputs["Scale"].default_value = spec["scale"]
        r = nt.nodes.new("ShaderNodeValToRGB")
        r.color_ramp.elements[0].color = (*spec["low"], 1.0)
        r.color_ramp.elements[1].color = (*spec["high"], 1.0)
        nt.links.new(n.outputs["Fac"], r.inputs["Fac"])
        coords = nt.nodes.new("ShaderNodeTexCoord")
        dot = nt.nodes.new("ShaderNodeVectorMath")
        dot.operation = "DOT_PRODUCT"
        az, el = spec["spot_direction"]
        dot.inputs[1].default_value = (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))
        nt.links.new(coords.outputs["Generated"], n.inputs["Vector"])
        nt.links.new(coords.outputs["Generated"], dot.inputs[0])
        ramp = nt.nodes.new("ShaderNodeMapRange")
        ramp.inputs["From Min"].default_value = 1.0 - spec["spot_size"]
        ramp.inputs["To Max"].default_value = spec["spot"]
        nt.links.new(dot.outputs["Value"], ramp.inputs["Value"])
        add = nt.nodes.new("ShaderNodeMix")
        add.data_type, add.blend_type = "RGBA", "ADD"
        add.inputs["Factor"].default_value = 1.0
        nt.links.new(r.outputs["Color"], add.inputs["A"])
        nt.links.new(ramp.outputs["Result"], add.inputs["B"])
        nt.links.new(add.outputs["Result"], bg.inputs["Color"])
    return w


def camera(scene, spec):
    bpy.ops.object.camera_add(location=spec["location"])
    cam = bpy.context.active_object
    look(cam, spec["location"], spec["target"])
    cam.data.lens = spec["lens"]
    if "dof" in spec:
        cam.data.dof.use_dof = True
        cam.data.dof.aperture_fstop = spec["dof"]["fstop"]
        cam.data.dof.focus_distance = spec["dof"]["distance"]
    if "shutter" in spec:
        scene.render.use_motion_blur = True
        scene.render.motion_blur_shutter = spec["shutter"]
    scene.camera = cam


def build(scene, recipe):
    """Scene ``recipe`` (catalogue.draw) in bpy."""
    scene.frame_set(1)
    for i, s in enumerate(recipe["surfaces"]):
        surface(s, f"s{i}")
    for i, o in enumerate(recipe["objects"]):
        primitive(o, f"m{i}")
    for i, t in enumerate(recipe["texts"]):
        text(t, f"t{i}")
    for i, v in enumerate(recipe["media"]):
        medium(v, f"v{i}")
    for i, li in enumerate(recipe["lights"]):
        lamp(li, i)
    scene.world = world(recipe["world"])
    camera(scene, recipe["camera"])
    scene.frame_set(1)


def brighten(scene, factor):
    """Every light source times ``factor``: radiance is linear in them, so every pass scales alike."""
    for li in bpy.data.lights:
        li.energy *= factor
    for m in list(bpy.data.materials) + [scene.world]:
        for n in m.node_tree.nodes:
            if n.type in ("EMISSION", "BACKGROUND"):
                n.inputs["Strength"].default_value *= factor


def exposure(recipe):
    """The factor that brings the recipe's mean linear colour to its ``exposure``, from a small probe render
    (32 x 32, 16 spp): random scenes otherwise range from black rooms to a blinding sky."""
    scene = reset()
    build(scene, recipe)
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", 16, False
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.resolution_percentage = 100
    im = scene.render.image_settings
    im.file_format, im.color_depth = "OPEN_EXR", "32"
    path = os.path.join(bpy.app.tempdir, f"probe-{recipe['index']}.exr")
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(path)
    px = list(img.pixels)
    mean = sum(v for i, v in enumerate(px) if i % 4 != 3) / (3 * len(px) / 4)
    os.remove(path)
    return recipe["exposure"] / max(mean, 1e-4)


def setup(recipe, spp, seed, factor, denoise=False, passes=True):
    """The scene to render at ``spp`` with Cycles' ``seed``: every pass a denoiser can use, or (``passes`` False)
    Combined alone; ``denoise``: Blender's default denoiser at render time (OIDN on albedo + normal, accurate
    prefilter), which writes the same render's noisy Combined beside it as "Noisy Image"."""
    scene = reset()
    build(scene, recipe)
    brighten(scene, factor)
    scene.render.engine = "CYCLES"
    scene.render.motion_blur_position = "START"  # the shutter opens at frame 1, where the motion keys start
    c = scene.cycles
    c.device = "CPU"
    c.samples = spp
    c.use_adaptive_sampling = False
    c.seed = seed
    c.max_bounces = 12
    c.use_denoising = denoise
    if denoise:
        c.denoiser, c.denoising_input_passes = "OPENIMAGEDENOISE", "RGB_ALBEDO_NORMAL"
        c.denoising_prefilter = "ACCURATE"
    scene.render.resolution_x = scene.render.resolution_y = recipe["res"]
    scene.render.resolution_percentage = 100
    use_passes(scene.view_layers[0], passes)
    multilayer_exr(scene)
    return scene


def use_passes(vl, passes=True):
    """View layer ``vl`` with every pass kpcn reads (:data:`PASSES`, the volume passes, Denoising Data), or
    (``passes`` False) Combined alone: the one place the passes are turned on, for the training and validation
    frames as for a user's .blend (``blend_pair.py``)."""
    for p in PASSES if passes else ("combined",):
        setattr(vl, "use_pass_" + p, True)
    vl.cycles.use_pass_volume_direct = passes  # media scenes: what the fog scatters, direct and indirect
    vl.cycles.use_pass_volume_indirect = passes
    vl.cycles.denoising_store_passes = passes


def multilayer_exr(scene):
    """The scene's output: one 32-bit multilayer OpenEXR (ZIP) a frame, its colours as rendered (Standard)."""
    im = scene.render.image_settings
    if hasattr(im, "media_type"):
        im.media_type = "MULTI_LAYER_IMAGE"
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"
    im.exr_codec = "ZIP"
    scene.view_settings.view_transform = "Standard"


def arguments(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--scenes", default="0:32", help="first:end scene indices")
    ap.add_argument("--res", default="128", help="comma-separated frame sides, one drawn per scene")
    ap.add_argument("--spp", default="4,8,16,32,64")
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--split", default="train", choices=sorted(catalogue.SPLITS))
    return ap.parse_args(argv)


def without_frames(recipe):
    return {k: v for k, v in recipe.items() if k != "frames"}


def write_json(path, obj):
    tmp = os.path.join(os.path.dirname(path), "." + os.path.basename(path))
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


def cycles_seed(a, index, li):
    """Cycles' seed of frame ``li`` of scene ``index``; a validation scene's are others than a training one's."""
    offset = 2**30 if a.split == catalogue.VALIDATION.name else 0
    return (100 * index + li + 1 + 1_000_003 * a.seed + offset) % 2**31


def pair_seeds(a, index, li):
    """Cycles' seeds of the two halves of frame ``li`` of scene ``index`` (catalogue.half_seeds of its seed; no
    other frame's either while 1_000_003 * --seed + 100 * index stays under 2**28), so the halves' noise is
    independent of each other and of the input beside them."""
    return catalogue.half_seeds(cycles_seed(a, index, li))


def planned_renders(a, recipe, spps):
    """(file name, spp, Cycles seed, denoise, passes) of every frame of a scene: the inputs with every pass;
    the reference, of a validation scene Combined alone; of each validation input, Blender's denoised frame (the
    input's seed: its noise) and the input's two halves at half its spp (every pass, two seeds of their own)."""
    valid = a.split == catalogue.VALIDATION.name
    out = []
    for li, spp in enumerate(spps):
        seed = cycles_seed(a, recipe["index"], li)
        out.append((catalogue.frame_name(recipe["name"], spp), spp, seed, False,
                    not (valid and li == len(spps) - 1)))
        if valid and li < len(spps) - 1:  # the same seed as the input beside it: the same noise, denoised
            out.append((catalogue.denoised_name(recipe["name"], spp), spp, seed, True, False))
            for name, half_seed in zip(catalogue.pair_names(recipe["name"], spp), pair_seeds(a, recipe["index"], li)):
                out.append((name, spp // 2, half_seed, False, True))
    return out


def render_scene(a, index, log):
    """Scene ``index``'s recipe (OUT/<scene>.json) and its frames; a frame already there is kept; returns the
    names written. SystemExit if the folder records another scene under that name (another seed, --res or
    catalogue version)."""
    spps = [int(s) for s in a.spp.split(",")] + [a.ref_spp]
    recipe = json.loads(json.dumps(catalogue.draw(a.seed, index, [int(r) for r in a.res.split(",")], spps,
                                                  a.split)))
    path = os.path.join(a.out, recipe["name"] + ".json")
    if os.path.exists(path):
        with open(path) as f:
            if without_frames(json.load(f)) != without_frames(recipe):
                sys.exit(f"{path}: records another scene than --seed {a.seed} --res {a.res} draws; use another OUT")
    write_json(path, recipe)
    factor, written = None, []
    for name, spp, seed, denoise, passes in planned_renders(a, recipe, spps):
        if os.path.exists(os.path.join(a.out, name)):
            continue
        t, cpu = time.perf_counter(), time.process_time()
        if factor is None:
            factor = exposure(recipe)
        scene = setup(recipe, spp, seed, factor, denoise, passes)
        scene.render.filepath = os.path.join(a.out, "." + name)
        bpy.ops.render.render(write_still=True)
        os.replace(scene.render.filepath, os.path.join(a.out, name))
        log["renders"][name] = time.perf_counter() - t
        log.setdefault("cpu", {})[name] = time.process_time() - cpu
        log["threads"] = scene.render.threads
        print(name, f"{log['renders'][name]:.1f} s, {log['cpu'][name]:.1f} CPU s", flush=True)
        write_json(os.path.join(a.out, catalogue.RENDER_LOG), log)
        written.append(name)
    return written


def main():
    a = arguments(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
    first, end = (int(x) for x in a.scenes.split(":"))
    os.makedirs(a.out, exist_ok=True)
    log_path = os.path.join(a.out, catalogue.RENDER_LOG)
    log = json.load(open(log_path)) if os.path.exists(log_path) else {"blender": bpy.app.version_string, "renders": {}}
    for index in range(first, end):
        written = render_scene(a, index, log)
        manifest = catalogue.write_manifest(a.out, fresh=written)
        print(f"scene {index}: {manifest['scenes']} scenes, frames {manifest['frames_done']} of "
              f"{manifest['frames_planned']}, {manifest['cpu_hours']:.3f} CPU hours", flush=True)


if __name__ == "__main__":
    main()
