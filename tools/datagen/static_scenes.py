"""Static scenes written in the exact NeRF-synthetic ("Blender") layout."""

from __future__ import annotations

import math
import time
from pathlib import Path

import bpy
import common as C
import geometry as G
import materials as M
import numpy as np
from layouts import opencv_K, rgb_and_mask, scale_mat_from_points, world_mat_from_c2w

N_TRAIN, N_VAL, N_TEST = 100, 10, 20


# ---------------------------------------------------------------- scene builders
def build_monkey_cage(scene):
    """Textured Suzanne inside a thin-strut golden geodesic cage on a brick pedestal,
    with a glossy ring and a striped torus knot (occlusion + thin structures + speculars)."""
    C.setup_world(scene, rot_z=0.3, sun_strength=3.0)
    m = G.monkey(size=0.9, location=(0.0, 0.0, 0.05), rotation=(0.0, 0.0, math.radians(-20)))
    G.subsurf(m, 2)
    G.smooth(m)
    M.assign(m, M.image("astronaut", "astronaut.png", roughness=0.35, coat=0.3))

    cage = G.ico_sphere(radius=1.0, subdivisions=1, location=(0.0, 0.0, 0.05))
    wf = cage.modifiers.new("Wire", "WIREFRAME")
    wf.thickness = 0.045
    wf.use_even_offset = True
    wf.use_relative_offset = False
    M.assign(cage, M.plain("gold", (1.0, 0.72, 0.3), roughness=0.18, metallic=1.0))

    ped = G.cylinder(radius=0.55, depth=0.22, location=(0.0, 0.0, -0.86), vertices=48)
    M.assign(ped, M.image("brick", "brick.png", roughness=0.7, coord="BOX", scale=(2.0, 2.0), bump=0.4))

    ring = G.torus(
        major=0.62, minor=0.035, location=(0.0, 0.0, 0.05), rotation=(math.radians(70), math.radians(15), 0.0)
    )
    M.assign(ring, M.plain("red_lacquer", (0.8, 0.05, 0.04), roughness=0.08, coat=1.0))

    knot = G.tube(G.torus_knot(2, 5, R=0.28, r=0.1, n=500, center=(0.0, 0.0, 0.0)), radius=0.022, name="knot")
    knot.location = (0.55, -0.55, -0.55)
    M.assign(knot, M.stripes("knot_stripes", (0.05, 0.25, 0.8), (0.95, 0.95, 0.9), scale=9.0, roughness=0.25))


def build_plant(scene):
    """Ficus-like potted plant: many thin bent stems with textured leaves in a gravel pot."""
    C.setup_world(scene, hdri="forest.exr", rot_z=1.2, sun_strength=2.5, sun_dir=(-0.4, 0.5, 0.7))
    rng = np.random.default_rng(7)
    pot = G.cylinder(radius=0.42, depth=0.55, location=(0, 0, -0.72), vertices=48)
    taper = pot.modifiers.new("Taper", "SIMPLE_DEFORM")
    taper.deform_method = "TAPER"
    taper.factor = 0.35
    taper.deform_axis = "Z"
    M.assign(
        pot,
        M.image(
            "pot_gravel", "gravel.png", roughness=0.8, coord="BOX", scale=(1.5, 1.5), bump=0.5, tint=(0.95, 0.6, 0.45)
        ),
    )
    rim = G.torus(major=0.47, minor=0.04, location=(0, 0, -0.44))
    M.assign(rim, M.plain("terracotta", (0.7, 0.3, 0.15), roughness=0.5))
    soil = G.cylinder(radius=0.44, depth=0.03, location=(0, 0, -0.43), vertices=48)
    M.assign(soil, M.noise("soil", (0.05, 0.03, 0.02), (0.25, 0.16, 0.08), scale=40.0, bump=0.8))

    stem_mat = M.plain("stem", (0.25, 0.16, 0.07), roughness=0.6)
    leaf_mat = M.image("leaf", "grass.png", roughness=0.45, coat=0.4, scale=(0.5, 0.5), tint=(0.35, 0.9, 0.25))
    n_stems = 9
    leaves = []
    for s in range(n_stems):
        az = 2 * math.pi * s / n_stems + rng.uniform(-0.3, 0.3)
        lean = rng.uniform(0.15, 0.5)
        h = rng.uniform(1.1, 1.6)
        k = 10
        t = np.linspace(0.0, 1.0, k)
        r = lean * t**1.4
        wob = 0.06 * np.sin(6 * t + s)
        pts = np.stack([(r + wob) * math.cos(az), (r + wob) * math.sin(az), -0.45 + h * t], axis=1)
        stem = G.tube(pts, radius=0.016, name=f"stem{s}")
        M.assign(stem, stem_mat)
        # leaves along the upper part of the stem
        for _ in range(rng.integers(3, 6)):
            u = rng.uniform(0.35, 1.0)
            i = min(k - 2, int(u * (k - 1)))
            p = pts[i] + (pts[i + 1] - pts[i]) * (u * (k - 1) - i)
            leaf = G.uv_sphere(radius=1.0, segments=16, rings=8, location=tuple(p))
            leaf.scale = (0.22, 0.085, 0.014)
            leaf.rotation_euler = (rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.2), rng.uniform(0, 2 * math.pi))
            # offset the leaf so that it hangs off the stem
            d = np.array([math.cos(leaf.rotation_euler[2]), math.sin(leaf.rotation_euler[2]), 0.0])
            leaf.location = tuple(p + 0.19 * d)
            leaf.data.materials.append(leaf_mat)
            leaves.append(leaf)
    # a small metallic watering can spout / label stick for speculars
    stick = G.cylinder(radius=0.012, depth=0.6, location=(0.25, -0.2, -0.25), rotation=(0.15, -0.2, 0.0), vertices=12)
    M.assign(stick, M.plain("chrome", (0.9, 0.9, 0.92), roughness=0.05, metallic=1.0))
    label = G.cube(size=1.0, location=(0.29, -0.23, 0.03), rotation=(0.15, -0.2, 0.6), scale=(0.14, 0.008, 0.09))
    M.assign(label, M.image("label", "text.png", roughness=0.6, coord="BOX", scale=(3, 3)))


def build_trinkets(scene):
    """Chrome spring, mirror ball, checker dice, a lathe vase with Voronoi glaze and photo cards."""
    C.setup_world(scene, hdri="city.exr", rot_z=2.0, sun_strength=3.5, sun_dir=(0.3, 0.7, 0.6))
    spring = G.tube(G.helix(0.22, 0.11, 7.5, n=600, center=(-0.45, 0.35, -0.85)), radius=0.025, name="spring")
    M.assign(spring, M.plain("chrome", (0.95, 0.95, 0.97), roughness=0.06, metallic=1.0))
    ball = G.uv_sphere(radius=0.3, location=(0.5, 0.45, -0.6))
    M.assign(ball, M.plain("mirror", (0.9, 0.85, 0.8), roughness=0.02, metallic=1.0))

    # vase by spinning a profile (screw modifier, like a lathe)
    prof = np.array(
        [
            [0.0, -0.95],
            [0.28, -0.95],
            [0.33, -0.8],
            [0.36, -0.55],
            [0.22, -0.25],
            [0.12, 0.0],
            [0.12, 0.25],
            [0.2, 0.35],
        ]
    )
    me = bpy.data.meshes.new("vase_profile")
    verts = [(float(x), 0.0, float(z)) for x, z in prof]
    edges = [(i, i + 1) for i in range(len(verts) - 1)]
    me.from_pydata(verts, edges, [])
    vase = bpy.data.objects.new("vase", me)
    scene.collection.objects.link(vase)
    vase.location = (0.0, -0.3, 0.0)
    sc = vase.modifiers.new("Lathe", "SCREW")
    sc.steps = 64
    sc.render_steps = 64
    sc.use_smooth_shade = True
    sol = vase.modifiers.new("Solid", "SOLIDIFY")
    sol.thickness = 0.02
    G.subsurf(vase, 1)
    M.assign(vase, M.voronoi("glaze", (0.02, 0.15, 0.35), (0.85, 0.9, 0.95), scale=14.0, roughness=0.12))
    # a branch of thin flower stems out of the vase
    for i, (dx, dy, h) in enumerate([(0.1, 0.05, 0.65), (-0.12, 0.02, 0.75), (0.02, -0.13, 0.55)]):
        pts = np.array([[0.0, -0.3, 0.2], [dx * 0.8, -0.3 + dy * 0.8, 0.5], [dx * 2.0, -0.3 + dy * 2.0, 0.2 + h]])
        st = G.tube(pts, radius=0.012, name=f"flower_stem{i}")
        M.assign(st, M.plain("stem_green", (0.1, 0.4, 0.08), roughness=0.5))
        head = G.ico_sphere(radius=0.07, subdivisions=2, location=tuple(pts[-1]))
        G.smooth(head)
        M.assign(head, M.noise(f"petal{i}", (0.9, 0.2, 0.4), (1.0, 0.85, 0.2), scale=30.0, bump=0.2))

    for i, (loc, rot) in enumerate([((0.55, -0.35, -0.8), (0.3, 0.2, 0.5)), ((0.75, 0.05, -0.85), (0.0, 0.0, 1.1))]):
        d = G.cube(size=0.26, location=loc, rotation=rot)
        bev = d.modifiers.new("Bevel", "BEVEL")
        bev.width = 0.03
        bev.segments = 3
        M.assign(d, M.checker(f"dice{i}", (0.95, 0.95, 0.9), (0.1, 0.1, 0.12), scale=6.0, roughness=0.2))
    # two photo cards leaning on each other (thin, textured both sides)
    for i, (img, loc, rot) in enumerate(
        [
            ("chelsea.png", (-0.55, -0.45, -0.55), (0.25, 0.0, 0.7)),
            ("coffee.png", (-0.25, -0.75, -0.55), (-0.2, 0.0, 0.4)),
        ]
    ):
        card = G.cube(size=1.0, location=loc, rotation=rot, scale=(0.55, 0.012, 0.42))
        M.assign(card, M.image(f"card{i}", img, roughness=0.3, coord="BOX", scale=(1.0, 1.0)))
    base = G.cylinder(radius=1.0, depth=0.04, location=(0, 0, -0.98), vertices=64)
    M.assign(
        base, M.checker("board", (0.25, 0.12, 0.05), (0.7, 0.55, 0.35), scale=16.0, roughness=0.3, coord="Generated")
    )


STATIC_SCENES = {
    "monkey_cage": build_monkey_cage,
    "plant": build_plant,
    "trinkets": build_trinkets,
}


# ---------------------------------------------------------------- rendering
def camera_sets():
    train = C.hemisphere_poses(N_TRAIN, seed=0)
    val = C.hemisphere_poses(N_VAL, seed=1)
    test = []
    for i in range(N_TEST):  # a ring like the NeRF-synthetic test path, elevation oscillating
        az = 2 * math.pi * i / N_TEST + 0.1
        el = math.radians(30.0 + 15.0 * math.sin(4 * math.pi * i / N_TEST))
        test.append(C.look_at_c2w(C.sph_to_xyz(C.CAM_RADIUS, az, el), np.zeros(3)))
    return {"train": train, "val": val, "test": test}


def render_static(name: str, out_root: Path, limit: int | None = None, builders: dict | None = None,
                  group: str = "static") -> dict:
    """Render scene ``name`` (built by ``builders[name]``, default the shipped ``STATIC_SCENES``) into
    ``out_root/group/name`` in the NeRF-synthetic layout."""
    scene = C.reset_scene(C.SAMPLES_STATIC)
    (builders or STATIC_SCENES)[name](scene)
    C.triangulate_all(scene)
    cam = C.make_camera(scene)
    out = out_root / group / name
    n_img = 0
    t0 = time.time()
    for split, poses in camera_sets().items():
        frames = []
        for i, c2w in enumerate(poses[:limit] if limit else poses):
            m = C.set_camera_pose(cam, c2w)
            C.render_to(scene, out / split / f"r_{i}.png")
            n_img += 1
            frames.append(
                {"file_path": C.rel_file_path(split, f"r_{i}"), "rotation": 0.012566370614359171, "transform_matrix": m}
            )
        C.write_json(out / f"transforms_{split}.json", {"camera_angle_x": C.CAMERA_ANGLE_X, "frames": frames})
    t_render = time.time() - t0
    verts, faces = C.world_mesh(scene)
    tris = verts[faces]
    area = float(C.triangle_areas(tris).sum())
    n = C.points_for_area(area, per_unit_area=5000.0, lo=20000, hi=50000)
    pts = C.SurfaceSampler(tris, n, seed=123)(tris)
    C.write_npz(out / "gt_points.npz", points=pts)
    C.write_gt_mesh(out / "gt_mesh.npz", verts, faces)
    return {
        "scene": name,
        "kind": "static",
        "images": n_img,
        "render_s": t_render,
        "gt_points": int(n),
        "surface_area": area,
    }


# ---------------------------------------------------------------- DTU-like NeuS layout
DTU_W, DTU_H = 128, 96  # 4:3 like DTU (1600x1200), square pixels
DTU_RADIUS = 5.0  # farther than the NeRF-style cameras: the 4:3 frame has a narrower vertical FoV
DTU_TARGET = np.array([0.0, 0.0, -0.25])


def dtu_poses():
    """49 cameras on a frontal spherical cap (7 rows x 7 columns), like DTU's robot-arm grid."""
    poses = []
    for r, el in enumerate(np.linspace(12.0, 57.0, 7)):
        azs = np.linspace(-60.0, 60.0, 7)
        if r % 2:  # serpentine order, as a robot arm would sweep
            azs = azs[::-1]
        for az in azs:
            eye = C.sph_to_xyz(DTU_RADIUS, math.radians(-90.0 + az), math.radians(el), DTU_TARGET)
            poses.append(C.look_at_c2w(eye, DTU_TARGET))
    return poses


def render_dtu(name: str, out_root: Path, limit: int | None = None) -> dict:
    """Render one static scene again from 49 DTU-like views at 128x96 and write the NeuS
    layout: image/000000.png (RGB on black), mask/000000.png, cameras_sphere.npz."""
    scene = C.reset_scene(C.SAMPLES_STATIC)
    scene.render.resolution_x = DTU_W
    scene.render.resolution_y = DTU_H
    STATIC_SCENES[name](scene)
    C.triangulate_all(scene)
    cam = C.make_camera(scene)
    out = out_root / "formats" / "dtu_neus" / name
    K = opencv_K(DTU_W, DTU_H, C.CAMERA_ANGLE_X)
    tris = C.world_triangles(scene)
    pts = C.SurfaceSampler(tris, 20000, seed=123)(tris)
    S = scale_mat_from_points(pts)
    mats = {}
    t0 = time.time()
    poses = dtu_poses()[:limit] if limit else dtu_poses()
    tmp = C._TMP / "dtu.png"
    for i, c2w in enumerate(poses):
        m = np.array(C.set_camera_pose(cam, c2w))
        C.render_to(scene, tmp)
        rgb_and_mask(tmp, out / "image" / f"{i:06d}.png", out / "mask" / f"{i:06d}.png")
        mats[f"world_mat_{i}"] = world_mat_from_c2w(m, K)
        mats[f"scale_mat_{i}"] = S
    t_render = time.time() - t0
    C.write_npz(out / "cameras_sphere.npz", **mats)
    C.write_npz(out / "gt_points.npz", points=pts)
    return {
        "scene": name,
        "kind": "formats/dtu_neus",
        "images": len(poses),
        "render_s": t_render,
        "gt_points": len(pts),
    }
