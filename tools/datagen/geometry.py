"""Small geometry helpers on top of Blender primitives."""

from __future__ import annotations

import math

import bpy
import numpy as np


def _active():
    return bpy.context.view_layer.objects.active


def smooth(obj):
    if obj.type == "MESH":
        n = len(obj.data.polygons)
        obj.data.polygons.foreach_set("use_smooth", [True] * n)
    return obj


def subsurf(obj, levels=2):
    m = obj.modifiers.new("Subsurf", "SUBSURF")
    m.levels = levels
    m.render_levels = levels
    return obj


def monkey(size=1.0, location=(0, 0, 0), rotation=(0, 0, 0)):
    bpy.ops.mesh.primitive_monkey_add(size=size, location=location, rotation=rotation, calc_uvs=True)
    return _active()


def uv_sphere(radius=1.0, location=(0, 0, 0), segments=48, rings=24, rotation=(0, 0, 0), name="Sphere"):
    """UV sphere built from explicit arrays (with a UV map).

    Not bpy.ops.mesh.primitive_uv_sphere_add: in Blender 5.0.1 that operator returns a
    different loop order from call to call, which made renders and the sampled
    ground-truth points differ between otherwise identical runs."""
    verts = [(0.0, 0.0, radius)]
    for i in range(1, rings):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2 * math.pi * j / segments
            verts.append(
                (radius * math.sin(th) * math.cos(ph), radius * math.sin(th) * math.sin(ph), radius * math.cos(th))
            )
    verts.append((0.0, 0.0, -radius))
    south = len(verts) - 1

    def ring(i, j):  # vertex index of ring i (1..rings-1), segment j
        return 1 + (i - 1) * segments + (j % segments)

    faces, uvs = [], []
    for j in range(segments):
        u0, u1 = j / segments, (j + 1) / segments
        faces.append((0, ring(1, j), ring(1, j + 1)))
        uvs.append([((u0 + u1) / 2, 1.0), (u0, 1 - 1 / rings), (u1, 1 - 1 / rings)])
        for i in range(1, rings - 1):
            v0, v1 = 1 - i / rings, 1 - (i + 1) / rings
            faces.append((ring(i, j), ring(i + 1, j), ring(i + 1, j + 1), ring(i, j + 1)))
            uvs.append([(u0, v0), (u0, v1), (u1, v1), (u1, v0)])
        faces.append((ring(rings - 1, j), south, ring(rings - 1, j + 1)))
        uvs.append([(u0, 1 / rings), ((u0 + u1) / 2, 0.0), (u1, 1 / rings)])
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], faces)
    uv = me.uv_layers.new(name="UVMap")
    uv.data.foreach_set("uv", [c for face in uvs for corner in face for c in corner])
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = location
    obj.rotation_euler = rotation
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    return smooth(obj)


def ico_sphere(radius=1.0, location=(0, 0, 0), subdivisions=2):
    bpy.ops.mesh.primitive_ico_sphere_add(radius=radius, location=location, subdivisions=subdivisions, calc_uvs=True)
    return _active()


def cylinder(radius=1.0, depth=2.0, location=(0, 0, 0), rotation=(0, 0, 0), vertices=32):
    bpy.ops.mesh.primitive_cylinder_add(
        radius=radius, depth=depth, location=location, rotation=rotation, vertices=vertices, calc_uvs=True
    )
    return _active()


def cone(radius1=1.0, radius2=0.0, depth=2.0, location=(0, 0, 0), rotation=(0, 0, 0), vertices=32):
    bpy.ops.mesh.primitive_cone_add(
        radius1=radius1,
        radius2=radius2,
        depth=depth,
        location=location,
        rotation=rotation,
        vertices=vertices,
        calc_uvs=True,
    )
    return _active()


def cube(size=1.0, location=(0, 0, 0), rotation=(0, 0, 0), scale=(1, 1, 1)):
    bpy.ops.mesh.primitive_cube_add(size=size, location=location, rotation=rotation, scale=scale, calc_uvs=True)
    return _active()


def torus(major=1.0, minor=0.25, location=(0, 0, 0), rotation=(0, 0, 0), major_seg=64, minor_seg=16):
    bpy.ops.mesh.primitive_torus_add(
        major_radius=major,
        minor_radius=minor,
        location=location,
        rotation=rotation,
        major_segments=major_seg,
        minor_segments=minor_seg,
        generate_uvs=True,
    )
    return smooth(_active())


def plane(size=2.0, location=(0, 0, 0), rotation=(0, 0, 0)):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location, rotation=rotation, calc_uvs=True)
    return _active()


def grid(x_sub=32, y_sub=32, size=2.0, location=(0, 0, 0), rotation=(0, 0, 0)):
    bpy.ops.mesh.primitive_grid_add(
        x_subdivisions=x_sub, y_subdivisions=y_sub, size=size, location=location, rotation=rotation, calc_uvs=True
    )
    return _active()


def tube(points, radius=0.02, name="Tube", resolution=4, bevel_res=3, radii=None, collection=None):
    """A thin tube along a poly/NURBS path (curve with round bevel), converted to a mesh."""
    cu = bpy.data.curves.new(name, type="CURVE")
    cu.dimensions = "3D"
    cu.bevel_mode = "ROUND"
    cu.bevel_depth = radius
    cu.bevel_resolution = bevel_res
    cu.use_fill_caps = True
    cu.resolution_u = resolution
    sp = cu.splines.new("NURBS")
    pts = np.asarray(points, dtype=np.float64)
    sp.points.add(len(pts) - 1)
    for i, p in enumerate(pts):
        sp.points[i].co = (float(p[0]), float(p[1]), float(p[2]), 1.0)
        if radii is not None:
            sp.points[i].radius = float(radii[i])
    sp.use_endpoint_u = True
    sp.order_u = min(4, len(pts))
    obj = bpy.data.objects.new(name, cu)
    (collection or bpy.context.scene.collection).objects.link(obj)
    return to_mesh(obj)


def to_mesh(obj):
    """Convert a curve (or anything) into a plain mesh object (keeps materials)."""
    bpy.context.view_layer.objects.active = obj
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.ops.object.convert(target="MESH")
    return smooth(_active())


def helix(radius, pitch, turns, n=200, center=(0, 0, 0), phase=0.0):
    t = np.linspace(0.0, 2 * math.pi * turns, n)
    c = np.asarray(center)
    return np.stack(
        [c[0] + radius * np.cos(t + phase), c[1] + radius * np.sin(t + phase), c[2] + pitch * t / (2 * math.pi)], axis=1
    )


def torus_knot(p=2, q=3, R=0.6, r=0.25, n=400, center=(0, 0, 0)):
    t = np.linspace(0.0, 2 * math.pi, n)
    rr = R + r * np.cos(q * t)
    c = np.asarray(center)
    return np.stack([c[0] + rr * np.cos(p * t), c[1] + rr * np.sin(p * t), c[2] + r * np.sin(q * t)], axis=1)


def apply_modifiers(obj):
    bpy.context.view_layer.objects.active = obj
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    for m in list(obj.modifiers):
        bpy.ops.object.modifier_apply(modifier=m.name)
    return obj


def apply_transform(obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.transform_apply(location=True, rotation=True, scale=True)
    return obj


def star_column(radius_out, radius_in, points, height, rings, z0=0.0, name="column"):
    """A star-shaped prism along +Z with many rings (so it can twist and bend smoothly)."""
    k = 2 * points
    verts, faces = [], []
    for j in range(rings + 1):
        z = z0 + height * j / rings
        for i in range(k):
            a = 2 * math.pi * i / k
            r = radius_out if i % 2 == 0 else radius_in
            verts.append((r * math.cos(a), r * math.sin(a), z))
    for j in range(rings):
        for i in range(k):
            a, b = j * k + i, j * k + (i + 1) % k
            faces.append((a, b, b + k, a + k))
    faces.append(tuple(reversed(range(k))))
    faces.append(tuple(rings * k + i for i in range(k)))
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], faces)
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj
