"""Renders a bake's lightmaps on the user's own model in Blender (PyPI `bpy`).

Imports the OBJ with Blender's own importer, gives every object a material that shows its
lightmap (`lightmap-NAME.exr`, and `lightmap-NAME-back.exr` on the back of two-sided faces,
picked by Geometry > Backfacing) through the object's UV map as emission, and renders the
room with Cycles on the CPU from a camera inside it, exposed as the bake's preview is
(`lightmaps.json` records the exposure; view transform Standard).

    ~/.venvs/bpy/bin/python scripts/blender_lightmap.py SCENE.obj BAKE_DIR OUT.png \
        [--size 640x400] [--samples 16] [--camera EX,EY,EZ,TX,TY,TZ]

The camera is in Blender's coordinates (+Z up: the OBJ's (x, y, z) is Blender's
(x, -z, y)); by default it stands high in the corner of the scene's bounds at +x, -y, looking
across the room toward -x, +y.
"""

import argparse
import json
import os

import bpy
from mathutils import Vector

ap = argparse.ArgumentParser()
ap.add_argument("obj")
ap.add_argument("bake")
ap.add_argument("out")
ap.add_argument("--size", default="640x400")
ap.add_argument("--samples", type=int, default=16)
ap.add_argument("--camera", default=None)
args = ap.parse_args()

index = json.load(open(os.path.join(args.bake, "lightmaps.json")))
maps = {}
for e in index["lightmaps"]:
    maps.setdefault(e["object"], {})[e["side"]] = os.path.join(args.bake, e["file"])

bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.obj_import(filepath=os.path.abspath(args.obj), forward_axis="NEGATIVE_Z",
                      up_axis="Y")


def image(path):
    img = bpy.data.images.load(os.path.abspath(path))
    img.colorspace_settings.name = "Linear Rec.709"
    # Alpha is coverage, and the dilated margin has alpha 0 with the chart's colour:
    # keep the colour as stored.
    img.alpha_mode = "CHANNEL_PACKED"
    return img


def lightmap_material(obj, sides):
    m = bpy.data.materials.new("lightmap-" + obj.name)
    m.use_nodes = True
    nt = m.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = index["exposure"]
    uv = nt.nodes.new("ShaderNodeUVMap")
    uv.uv_map = obj.data.uv_layers.active.name

    def texture(path):
        t = nt.nodes.new("ShaderNodeTexImage")
        t.image = image(path)
        t.interpolation = "Linear"
        t.extension = "EXTEND"
        nt.links.new(uv.outputs["UV"], t.inputs["Vector"])
        return t

    front = texture(sides["front"]) if "front" in sides else None
    back = texture(sides["back"]) if "back" in sides else None
    if front and back:
        geo = nt.nodes.new("ShaderNodeNewGeometry")
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        nt.links.new(geo.outputs["Backfacing"], mix.inputs["Factor"])
        nt.links.new(front.outputs["Color"], mix.inputs["A"])
        nt.links.new(back.outputs["Color"], mix.inputs["B"])
        nt.links.new(mix.outputs["Result"], emit.inputs["Color"])
    else:
        nt.links.new((front or back).outputs["Color"], emit.inputs["Color"])
        if back and not front:
            # Only the back was baked: show black on the front.
            geo = nt.nodes.new("ShaderNodeNewGeometry")
            mul = nt.nodes.new("ShaderNodeMath")
            mul.operation = "MULTIPLY"
            nt.links.new(geo.outputs["Backfacing"], mul.inputs[0])
            mul.inputs[1].default_value = index["exposure"]
            nt.links.new(mul.outputs["Value"], emit.inputs["Strength"])
    nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    return m


lo = Vector((1e30, 1e30, 1e30))
hi = -lo
for obj in bpy.context.scene.objects:
    if obj.type != "MESH":
        continue
    if obj.name not in maps:
        raise SystemExit(f"object {obj.name!r} has no lightmap in {args.bake}")
    m = lightmap_material(obj, maps[obj.name])
    obj.data.materials.clear()
    obj.data.materials.append(m)
    for v in obj.data.vertices:
        w = obj.matrix_world @ v.co
        lo = Vector(map(min, lo, w))
        hi = Vector(map(max, hi, w))

scene = bpy.context.scene
if args.camera:
    c = [float(x) for x in args.camera.split(",")]
    eye, target = Vector(c[:3]), Vector(c[3:6])
else:
    d = hi - lo
    eye = Vector((lo.x + 0.967 * d.x, lo.y + 0.0625 * d.y, lo.z + 0.73 * d.z))
    target = Vector((lo.x + 0.367 * d.x, lo.y + 0.65 * d.y, lo.z + 0.077 * d.z))
cam_data = bpy.data.cameras.new("Camera")
cam_data.lens = 16.0
cam = bpy.data.objects.new("Camera", cam_data)
scene.collection.objects.link(cam)
cam.location = eye
cam.rotation_euler = (target - eye).to_track_quat("-Z", "Y").to_euler()
scene.camera = cam

world = bpy.data.worlds.new("black")
world.use_nodes = True
world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
scene.world = world
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = args.samples
scene.cycles.use_denoising = False
scene.cycles.max_bounces = 0
w, h = (int(x) for x in args.size.split("x"))
scene.render.resolution_x, scene.render.resolution_y = w, h
scene.render.resolution_percentage = 100
scene.view_settings.view_transform = "Standard"
scene.render.image_settings.file_format = "PNG"
scene.render.filepath = os.path.abspath(args.out)
bpy.ops.render.render(write_still=True)
print("wrote", os.path.abspath(args.out))
