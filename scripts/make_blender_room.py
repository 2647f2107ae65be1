"""Makes scenes/blender-room.obj/.mtl with Blender itself (PyPI `bpy`), as a user would.

A room made from Blender's default cube scaled up (its normals point OUT of the room, as
every user's first room has them), two boxes standing on the floor, a hexagonal rug written
as one 6-corner face (an n-gon), a ceiling lamp with an emissive material (Blender's OBJ
exporter writes it as `Ke`), UVs from Smart UV Project on every object, exported by
Blender's own OBJ exporter (`bpy.ops.wm.obj_export`, +Y up, -Z forward).

    python3 -m venv ~/.venvs/bpy && ~/.venvs/bpy/bin/pip install bpy==4.4.0 'numpy<2'
    ~/.venvs/bpy/bin/python scripts/make_blender_room.py [OUT.obj]
"""

import math
import os
import sys

import bpy
import bmesh  # after bpy: the module ships inside it

OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "scenes", "blender-room.obj")


def material(name, rgb, emit=None, strength=1.0):
    """A Principled BSDF material: base colour `rgb`, emission `emit` x `strength`."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    bsdf = m.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    if emit is not None:
        bsdf.inputs["Emission Color"].default_value = (*emit, 1.0)
        bsdf.inputs["Emission Strength"].default_value = strength
    return m


def smart_uv(obj):
    """Smart UV Project on every face of `obj`, islands 0.03 apart (room for dilation)."""
    bpy.ops.object.select_all(action="DESELECT")
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.uv.smart_project(angle_limit=math.radians(66), island_margin=0.03)
    bpy.ops.object.mode_set(mode="OBJECT")


def box(name, size, location, angle, mat):
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=location,
                                    rotation=(0, 0, math.radians(angle)))
    o = bpy.context.active_object
    o.name = o.data.name = name
    o.scale = size
    bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
    o.data.materials.append(mat)
    return o


bpy.ops.wm.read_factory_settings(use_empty=False)
# The factory scene: a 2 m cube at the origin, a camera and a light. Keep the cube.
for name in ("Camera", "Light"):
    bpy.data.objects.remove(bpy.data.objects[name], do_unlink=True)
room = bpy.data.objects["Cube"]
room.name = room.data.name = "Room"
# 6 m x 4 m, 2.6 m high (Blender is +Z up), floor at z = 0; normals still point out.
room.scale = (3.0, 2.0, 1.3)
room.location = (0.0, 0.0, 1.3)
bpy.context.view_layer.objects.active = room
room.select_set(True)
bpy.ops.object.transform_apply(location=True, rotation=True, scale=True)
wall = material("Wall", (0.6, 0.6, 0.58))
floor = material("Floor", (0.55, 0.42, 0.30))
red = material("RedWall", (0.70, 0.12, 0.10))
room.data.materials.clear()
for m in (wall, floor, red):
    room.data.materials.append(m)
for p in room.data.polygons:
    n = p.normal
    if n.z < -0.5:
        p.material_index = 1  # the floor (its normal points down, out of the room)
    elif n.x < -0.5:
        p.material_index = 2  # the wall at x = -3
    else:
        p.material_index = 0

boxes = material("Box", (0.65, 0.65, 0.65))
box("TallBox", (0.6, 0.6, 1.7), (0.7, 0.5, 0.85), 20.0, boxes)
box("LowBox", (1.0, 0.8, 0.6), (-0.4, -1.0, 0.3), -15.0, boxes)

# A hexagonal rug, one 6-corner face, 1 cm above the floor, facing up.
rug_mesh = bpy.data.meshes.new("Rug")
bm = bmesh.new()
corners = [bm.verts.new((1.6 + 0.8 * math.cos(k * math.pi / 3),
                         -0.8 + 0.7 * math.sin(k * math.pi / 3), 0.01)) for k in range(6)]
bm.faces.new(corners)
bm.to_mesh(rug_mesh)
bm.free()
rug = bpy.data.objects.new("Rug", rug_mesh)
bpy.context.collection.objects.link(rug)
rug.data.materials.append(material("Rug", (0.20, 0.35, 0.60)))

# The ceiling lamp: a 0.6 m x 0.4 m panel 2 cm below the ceiling, facing down, toward one
# end of the room, so the boxes cast long shadows toward the other.
bpy.ops.mesh.primitive_plane_add(size=1.0, location=(-1.6, 0.3, 2.58),
                                 rotation=(math.pi, 0.0, 0.0))
lamp = bpy.context.active_object
lamp.name = lamp.data.name = "Lamp"
lamp.scale = (0.6, 0.4, 1.0)
bpy.ops.object.transform_apply(location=False, rotation=True, scale=True)
lamp.data.materials.append(material("Lamp", (0.8, 0.8, 0.8), emit=(1.0, 0.95, 0.85),
                                    strength=25.0))

for o in (room, bpy.data.objects["TallBox"], bpy.data.objects["LowBox"], rug, lamp):
    smart_uv(o)

bpy.ops.object.select_all(action="DESELECT")
bpy.ops.wm.obj_export(filepath=os.path.abspath(OUT), export_selected_objects=False,
                      export_uv=True, export_normals=True, export_materials=True,
                      forward_axis="NEGATIVE_Z", up_axis="Y", apply_modifiers=True,
                      export_triangulated_mesh=False, path_mode="RELATIVE")
print("wrote", os.path.abspath(OUT))
