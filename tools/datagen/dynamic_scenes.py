"""Dynamic scenes: multi-view (OwlII-like) and monocular (D-NeRF-like) sequences.

Every sequence is driven frame by frame from Python (``update(t)`` sets the pose /
deformation for normalised time t in [0, 1]); no simulation caches, so any frame can be
re-rendered on its own and the result is deterministic.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import bpy
import common as C
import geometry as G
import materials as M
import numpy as np
from mathutils import Matrix, Vector

N_FRAMES_MV = 24
N_TRAIN_CAMS_MV = 10
N_TEST_CAMS_MV = 2
N_FRAMES_MONO = 50
N_VAL_MONO = 10
N_TEST_MONO = 20

BVH_FILE = "01_01.bvh"  # CMU subject 1, trial 1 (cgspeed BVH conversion), via assimp-testmodels
# BVH_START: window picked by motion energy with the figure kept inside r < 1 (see README): a forward
# jump. In the capture the hips travel ~1.13 units along world Y over the window (the silhouette's
# centre moves 7-36 px on the 100 px images, by camera); with MOCAP_ROOT_MOTION = "in_place" that
# ground-plane travel is removed, so the figure jumps on the spot (hips rise 0.40 units) like an
# OwlII performer. The window still ranks in the top ~18 % of all 24-frame windows of 01_01 by
# hips-relative limb motion (mean per-joint step 0.027 units/frame; best window 0.032), so it was kept.
BVH_START = 2391
BVH_STEP = 6  # 120 fps mocap -> 20 fps sequence
BVH_SCALE = 0.06
# "in_place": subtract, per frame, the root (hips) bone's horizontal (world X/Y, Z is up) offset from
# its mean over the window, keep its height (jumps); "full": the captured root translation (the
# figure travels further than its own width; the shipped data before this option existed).
MOCAP_ROOT_MOTION = "in_place"


# ================================================================ articulated: mocap figure
def _capsule(name, length, radius, mat, segs=16):
    """Capsule along +Y from 0 to length (bone-local frame: Y runs head -> tail)."""
    cyl = G.cylinder(
        radius=radius,
        depth=max(length, 1e-4),
        location=(0, length / 2, 0),
        rotation=(-math.pi / 2, 0, 0),
        vertices=segs,
    )
    cyl.name = name
    caps = []
    for y in (0.0, length):
        caps.append(G.uv_sphere(radius=radius, location=(0, y, 0), segments=segs, rings=8))
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in [cyl, *caps]:
        o.select_set(True)
    bpy.context.view_layer.objects.active = cyl
    bpy.ops.object.join()
    G.apply_transform(cyl)
    G.smooth(cyl)
    M.assign(cyl, mat)
    return cyl


def build_mocap_figure(
    scene,
    bvh_file=BVH_FILE,
    start=BVH_START,
    step=BVH_STEP,
    n_frames=N_FRAMES_MV,
    scale=BVH_SCALE,
    palette=0,
    root_motion: str = MOCAP_ROOT_MOTION,
):
    """Capsule figure driven by a BVH window. ``root_motion`` = "in_place" (the figure moves its
    limbs and jumps on the spot: per frame the root bone's ground-plane (world X/Y) displacement from
    its window mean is subtracted, its height is kept) or "full" (the captured global translation)."""
    if root_motion not in ("in_place", "full"):
        raise ValueError(f"root_motion must be 'in_place' or 'full', got {root_motion!r}")
    C.setup_world(scene, hdri="studio.exr", rot_z=0.8, sun_strength=3.0, sun_dir=(0.5, -0.6, 0.6))
    bpy.ops.import_anim.bvh(
        filepath=str(C.BVH_DIR / bvh_file),
        global_scale=1.0,
        frame_start=1,
        use_fps_scale=False,
        update_scene_fps=False,
        update_scene_duration=True,
        rotate_mode="NATIVE",
        axis_forward="-Z",
        axis_up="Y",
    )
    arm = bpy.context.active_object
    arm.hide_render = True
    bvh_frames = [start + step * i for i in range(n_frames)]
    root = next(pb for pb in arm.pose.bones if pb.parent is None)  # "Hips" in the CMU files

    # joint positions over the window (world, before scaling; world Z is up after the import)
    joints = []
    for fr in bvh_frames:
        scene.frame_set(fr)
        mw = np.array(arm.matrix_world)
        joints.append([(mw @ np.r_[np.array(pb.head), 1.0])[:3] for pb in arm.pose.bones])
    joints = np.array(joints)  # [n_frames, n_bones, 3]
    root_i = list(arm.pose.bones).index(root)
    # per-frame world offset removed from the whole figure (unscaled units): the root's X/Y
    # displacement from its window mean; Z (jumps, crouches) is untouched
    root_off = np.zeros((n_frames, 3), dtype=joints.dtype)  # float32 (Blender matrices), as before
    if root_motion == "in_place":
        root_xy = joints[:, root_i, :2]
        root_off[:, :2] = root_xy - root_xy.mean(0)
    joints = joints - root_off[:, None, :]
    # frame -> world translation (after scaling) applied on top of the armature's world matrix
    frame_shift = {fr: Matrix.Translation(Vector(tuple(-scale * root_off[i]))) for i, fr in enumerate(bvh_frames)}

    # centre the figure over the whole window (constant offset, so the motion is unchanged)
    pts = joints.reshape(-1, 3) * scale
    lo, hi = pts.min(0), pts.max(0)
    centre = np.array([pts[:, 0].mean(), pts[:, 1].mean(), 0.5 * (lo[2] + hi[2])])
    arm.scale = (scale, scale, scale)
    arm.location = tuple(-centre)

    if palette == 0:
        shirt = M.stripes("shirt", (0.85, 0.1, 0.1), (0.95, 0.9, 0.8), scale=7.0, roughness=0.5)
        pants = M.image("jeans", "gravel.png", roughness=0.8, coord="BOX", scale=(3, 3), tint=(0.3, 0.4, 0.9))
        skin = M.plain("skin", (0.8, 0.55, 0.4), roughness=0.45, coat=0.2)
        shoes = M.plain("shoes", (0.05, 0.05, 0.05), roughness=0.15, coat=1.0)
        head_mat = M.image("head", "chelsea.png", roughness=0.4, scale=(1.0, 1.0))
    else:
        shirt = M.checker("shirt2", (0.1, 0.5, 0.2), (0.9, 0.9, 0.2), scale=10.0, roughness=0.5, coord="Object")
        pants = M.noise("pants2", (0.1, 0.1, 0.15), (0.5, 0.5, 0.6), scale=25.0)
        skin = M.plain("skin2", (0.55, 0.35, 0.25), roughness=0.45, coat=0.2)
        shoes = M.plain("shoes2", (0.9, 0.9, 0.9), roughness=0.2, coat=1.0)
        head_mat = M.image("head2", "coffee.png", roughness=0.4)
    gold = M.plain("gold", (1.0, 0.75, 0.3), roughness=0.15, metallic=1.0)

    def style(name):
        n = name.lower()
        if "head" in n:
            return None
        if "toe" in n or "foot" in n:
            return shoes, 0.035
        if "upleg" in n or n.endswith("hipjoint") or n in ("lefthip", "righthip"):
            return pants, 0.055
        if "leg" in n or "knee" in n:
            return pants, 0.045
        if "spine" in n or "back" in n or n in ("ab", "chest", "hips"):
            return shirt, 0.11
        if "shoulder" in n or "collar" in n:
            return shirt, 0.045
        if "forearm" in n or "elbow" in n:
            return skin, 0.028
        if "arm" in n:
            return shirt, 0.036
        if "neck" in n:
            return skin, 0.04
        if "finger" in n or "thumb" in n or "hand" in n or "wrist" in n:
            return skin, 0.02
        return skin, 0.03

    parts = []  # (object, pose bone)
    for pb in arm.pose.bones:
        length = pb.bone.length
        st = style(pb.name)
        if st is None:  # head: a textured sphere with a thin halo ring (thin structure)
            head = G.uv_sphere(radius=0.12 / scale, location=(0, 0.1 / scale, 0))
            M.assign(head, head_mat)
            head.rotation_euler = (0, 0, 0)
            ring = G.torus(
                major=0.16 / scale, minor=0.012 / scale, location=(0, 0.2 / scale, 0), rotation=(math.pi / 2, 0, 0)
            )
            M.assign(ring, gold)
            for o in (head, ring):
                G.apply_transform(o)
                parts.append((o, pb))
            continue
        if length * scale < 0.02:
            continue
        mat, radius = st
        parts.append((_capsule(f"part_{pb.name}", length, radius / scale, mat), pb))

    def update(t: float):
        fr = bvh_frames[round(t * (n_frames - 1))]
        scene.frame_set(fr)
        mw = arm.matrix_world
        if root_motion == "in_place":
            mw = frame_shift[fr] @ mw
        for obj, pb in parts:
            obj.matrix_world = mw @ pb.matrix
        bpy.context.view_layer.update()

    return update


# ================================================================ non-rigid: flag + twisting column
def build_flag(scene, n_frames=N_FRAMES_MV):
    """A waving textured flag on a thin chrome pole next to a twisting, bending striped column."""
    C.setup_world(scene, hdri="courtyard.exr", rot_z=0.4, sun_strength=3.0, sun_dir=(-0.3, -0.7, 0.6))
    pole = G.cylinder(radius=0.022, depth=2.0, location=(-0.6, 0.0, 0.0), vertices=16)
    M.assign(pole, M.plain("chrome", (0.95, 0.95, 0.97), roughness=0.08, metallic=1.0))
    knob = G.uv_sphere(radius=0.05, location=(-0.6, 0.0, 1.02))
    M.assign(knob, M.plain("gold", (1.0, 0.75, 0.3), roughness=0.15, metallic=1.0))
    base = G.cylinder(radius=0.2, depth=0.06, location=(-0.6, 0.0, -0.97), vertices=32)
    M.assign(base, M.image("stone", "brick.png", roughness=0.7, coord="BOX", scale=(2, 2)))

    nx, ny = 40, 28
    W, H = 1.3, 0.9
    flag = G.grid(x_sub=nx, y_sub=ny, size=1.0)
    flag.name = "flag"
    me = flag.data
    rest = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    u = rest[:, 0] + 0.5  # 0 at the pole, 1 at the free end
    v = rest[:, 1] + 0.5  # 0 bottom .. 1 top
    sol = flag.modifiers.new("Solid", "SOLIDIFY")
    sol.thickness = 0.012
    sol.offset = 0.0
    G.smooth(flag)
    M.assign(flag, M.image("flag", "astronaut.png", roughness=0.55, coat=0.1))

    col = G.star_column(0.2, 0.11, 5, 1.5, 40, z0=-0.95)
    col.location = (0.75, 0.15, 0.0)
    twist = col.modifiers.new("Twist", "SIMPLE_DEFORM")
    twist.deform_method = "TWIST"
    twist.deform_axis = "Z"
    bend = col.modifiers.new("Bend", "SIMPLE_DEFORM")
    bend.deform_method = "BEND"
    bend.deform_axis = "Z"
    origin = bpy.data.objects.new("col_origin", None)
    scene.collection.objects.link(origin)
    origin.location = (0.75, 0.15, -0.95)  # column foot stays put
    origin.rotation_euler = (0.0, 0.0, 0.0)
    twist.origin = origin
    bend.origin = origin
    M.assign(
        col, M.stripes("col_stripes", (0.9, 0.6, 0.05), (0.1, 0.1, 0.4), scale=5.0, roughness=0.25, coord="Generated")
    )

    def update(t: float):
        ph = 2 * math.pi * t
        # flag: travelling wave growing from the pole, plus gravity sag and a gust at mid-sequence
        gust = 0.6 + 0.4 * math.sin(ph)
        amp = 0.16 * gust * u**1.3
        w = amp * np.sin(2 * math.pi * (1.6 * u - 2.0 * t) + 1.5 * v)
        sag = -0.25 * (1 - gust) * u**2
        x = -0.6 + W * u * (1 - 0.08 * (1 - gust)) + 0.03 * np.sin(3 * ph + 4 * v) * u
        y = w
        z = 0.95 - H * (1 - v) + sag + 0.05 * u * np.sin(2 * math.pi * (u - t))
        co = np.stack([x, y, z], axis=1)
        flag.data.vertices.foreach_set("co", co.ravel())
        flag.data.update()
        twist.angle = math.radians(160) * math.sin(ph)
        bend.angle = math.radians(50) * math.sin(2 * ph + 0.5)
        origin.rotation_euler = (0.0, 0.0, ph)  # bend direction turns around over time
        bpy.context.view_layer.update()

    return update


# ================================================================ monocular: bouncing toys
def build_bouncing(scene):
    """Bouncing balls with squash & stretch, a spinning top and a swinging pendulum on a thin string."""
    C.setup_world(scene, hdri="interior.exr", rot_z=1.0, sun_strength=3.0, sun_dir=(0.4, 0.5, 0.7))
    bpy.ops.mesh.primitive_circle_add(radius=1.0, vertices=64, fill_type="NGON", location=(0, 0, -0.825))
    floor = bpy.context.view_layer.objects.active  # one-sided disk: cameras are all above it
    M.assign(
        floor, M.checker("floor", (0.9, 0.9, 0.85), (0.15, 0.2, 0.35), scale=10.0, roughness=0.35, coord="Generated")
    )
    balls = []
    specs = [
        (0.18, (-0.5, -0.55), 0.0, M.image("ball_a", "astronaut.png", roughness=0.3, coat=0.5)),
        (0.14, (0.5, -0.55), 0.33, M.stripes("ball_b", (0.9, 0.1, 0.1), (1, 1, 1), scale=5.0)),
        (0.12, (0.1, 0.7), 0.66, M.plain("ball_c", (0.1, 0.6, 0.9), roughness=0.05, coat=1.0)),
    ]
    for r, xy, phase, mat in specs:
        b = G.uv_sphere(radius=r)
        M.assign(b, mat)
        balls.append((b, r, xy, phase))
    top = G.cone(radius1=0.18, radius2=0.0, depth=0.3, rotation=(math.pi, 0, 0), vertices=48)
    G.apply_transform(top)
    cap = G.cylinder(radius=0.18, depth=0.06, location=(0, 0, 0.18), vertices=48)
    stem = G.cylinder(radius=0.02, depth=0.2, location=(0, 0, 0.3), vertices=12)
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in (top, cap, stem):
        o.select_set(True)
    bpy.context.view_layer.objects.active = top
    bpy.ops.object.join()
    M.assign(top, M.voronoi("top", (0.9, 0.3, 0.05), (0.1, 0.05, 0.3), scale=12.0, roughness=0.2))
    # pendulum: gallows with a thin string and a chrome bob
    post = G.cylinder(radius=0.02, depth=1.6, location=(0.0, -0.75, -0.05), vertices=12)
    arm_ = G.cylinder(radius=0.02, depth=0.6, location=(0.0, -0.45, 0.75), rotation=(math.pi / 2, 0, 0), vertices=12)
    wood = M.noise("wood", (0.35, 0.18, 0.07), (0.7, 0.45, 0.2), scale=30.0, bump=0.1)
    M.assign(post, wood)
    M.assign(arm_, wood)
    pivot = np.array([0.0, -0.2, 0.75])
    string = G.cylinder(radius=0.01, depth=1.0, vertices=8)
    M.assign(string, M.plain("string", (0.95, 0.95, 0.9), roughness=0.6))
    bob = G.uv_sphere(radius=0.09)
    M.assign(bob, M.plain("bob", (0.95, 0.95, 0.97), roughness=0.04, metallic=1.0))
    L = 0.85

    def update(t: float):
        for b, r, (x, y), phase in balls:
            s = (2.0 * t + phase) % 1.0  # two bounces over the sequence
            hgt = 4 * s * (1 - s)  # parabola, 0 at contact
            squash = max(0.0, 1.0 - hgt / 0.12)  # squash near the floor
            sz = 1.0 - 0.35 * squash
            sxy = 1.0 / math.sqrt(sz)
            zc = -0.825 + r * sz + 0.9 * hgt
            b.location = (x, y, zc)
            b.scale = (sxy, sxy, sz)
            b.rotation_euler = (0.0, 2 * math.pi * t * (1 + phase), 0.0)
        top.location = (0.45 * math.cos(2 * math.pi * t), 0.1 + 0.2 * math.sin(2 * math.pi * t), -0.675)
        top.rotation_euler = (0.25 * math.sin(6 * math.pi * t), 0.2 * math.cos(6 * math.pi * t), 6 * math.pi * t)
        ang = 0.55 * math.sin(2 * math.pi * 1.5 * t)
        d = np.array([math.sin(ang), 0.0, -math.cos(ang)])
        bob.location = tuple(pivot + L * d)
        mid = pivot + 0.5 * (L - 0.09) * d
        string.location = tuple(mid)
        string.rotation_euler = (0.0, -ang, 0.0)
        string.scale = (1.0, 1.0, L - 0.09)
        bpy.context.view_layer.update()

    return update


# ================================================================ writers
def mv_cameras():
    """10 training cameras evenly in azimuth (k * 36 deg; so cameras 1, 3, 6, 8 spread around the
    subject as in ResFields' 4-view protocol), elevations alternating; 2 test cameras in between."""
    train, test = [], []
    for k in range(N_TRAIN_CAMS_MV):
        az = math.radians(36.0 * k + 5.0)
        el = math.radians([8.0, 22.0, 35.0, 15.0, 28.0][k % 5])
        train.append(C.look_at_c2w(C.sph_to_xyz(C.CAM_RADIUS, az, el), np.zeros(3)))
    for az, el in [(23.0, 18.0), (203.0, 30.0)][:N_TEST_CAMS_MV]:
        test.append(C.look_at_c2w(C.sph_to_xyz(C.CAM_RADIUS, math.radians(az), math.radians(el)), np.zeros(3)))
    return train, test


def stack_meshes(meshes):
    """[(vertices [V, 3], faces [T, 3])] per frame -> (vertices [F, V, 3], faces); the topology must not change."""
    faces = meshes[0][1]
    assert all(np.array_equal(f, faces) for _, f in meshes), "topology changed between frames"
    return np.stack([v for v, _ in meshes]), faces


def _gt_sampler(scene, update, n):
    update(0.0)
    tris = C.world_triangles(scene)
    return C.SurfaceSampler(tris, n, seed=321), float(C.triangle_areas(tris).sum())


def render_multiview(name, builder, out_root: Path, limit=None, n_points=12000, **kw):
    scene = C.reset_scene(C.SAMPLES_DYNAMIC)
    update = builder(scene, **kw)
    C.triangulate_all(scene)
    cam = C.make_camera(scene)
    out = out_root / "dynamic_mv" / name
    train, test = mv_cameras()
    n_frames = N_FRAMES_MV if not limit else min(limit, N_FRAMES_MV)
    times = np.array([f / (N_FRAMES_MV - 1) for f in range(N_FRAMES_MV)], dtype=np.float32)[:n_frames]
    sampler, area = _gt_sampler(scene, update, n_points)
    frames = {"train": [], "test": []}
    gt, mesh = [], []
    t0 = time.time()
    n_img = 0
    for f in range(n_frames):
        t = f / (N_FRAMES_MV - 1)  # exact in the JSON; gt "times" holds the same values as float32
        update(t)
        verts, faces = C.world_mesh(scene)
        gt.append(sampler(verts[faces]))
        mesh.append((verts, faces))
        for split, poses in (("train", train), ("test", test)):
            for c, c2w in enumerate(poses):
                m = C.set_camera_pose(cam, c2w)
                stem = f"c{c:02d}_f{f:03d}"
                C.render_to(scene, out / split / f"{stem}.png")
                n_img += 1
                frames[split].append(
                    {
                        "file_path": C.rel_file_path(split, stem),
                        "transform_matrix": m,
                        "time": t,
                        "frame_id": f,
                        "camera_id": c,
                    }
                )
    t_render = time.time() - t0
    for split in frames:
        frames[split].sort(key=lambda e: (e["camera_id"], e["frame_id"]))
        C.write_json(
            out / f"transforms_{split}.json",
            {
                "camera_angle_x": C.CAMERA_ANGLE_X,
                "num_frames": n_frames,
                "num_cameras": len(train if split == "train" else test),
                "frames": frames[split],
            },
        )
    C.write_npz(out / "gt_points.npz", points=np.asfortranarray(np.stack(gt).astype(np.float32)), times=times)
    C.write_gt_mesh(out / "gt_mesh.npz", *stack_meshes(mesh), times=times)
    return {
        "scene": name,
        "kind": "dynamic_mv",
        "images": n_img,
        "render_s": t_render,
        "gt_points": n_points,
        "surface_area": area,
        "frames": n_frames,
    }


def mono_cameras(n_train=N_FRAMES_MONO):
    """Train: one camera orbiting ~1.5 times while bobbing in elevation (like D-NeRF's moving
    virtual camera); val/test: other poses at a subset of the training times."""
    train = []
    for i in range(n_train):
        s = i / max(1, n_train - 1)
        az = 2 * math.pi * 1.5 * s
        el = math.radians(25.0 + 15.0 * math.sin(2 * math.pi * 2 * s))
        train.append(C.look_at_c2w(C.sph_to_xyz(C.CAM_RADIUS, az, el), np.zeros(3)))
    rng = np.random.default_rng(5)

    def others(n, seed_off):
        out = []
        for k in range(n):
            fi = round(k * (n_train - 1) / max(1, n - 1))
            az = rng.uniform(0, 2 * math.pi)
            el = math.radians(rng.uniform(10.0, 60.0))
            out.append((fi, C.look_at_c2w(C.sph_to_xyz(C.CAM_RADIUS, az, el), np.zeros(3))))
        return out

    return [(i, p) for i, p in enumerate(train)], others(N_VAL_MONO, 1), others(N_TEST_MONO, 2)


def render_mono(name, builder, out_root: Path, limit=None, n_points=6000):
    scene = C.reset_scene(C.SAMPLES_DYNAMIC)
    update = builder(scene)
    C.triangulate_all(scene)
    cam = C.make_camera(scene)
    out = out_root / "dynamic_mono" / name
    n_train = N_FRAMES_MONO
    times = np.array([i / (n_train - 1) for i in range(n_train)], dtype=np.float32)
    sampler, area = _gt_sampler(scene, update, n_points)
    train, val, test = mono_cameras(n_train)
    splits = {"train": train, "val": val, "test": test}
    if limit:
        splits = {k: v[:limit] for k, v in splits.items()}
    jobs = sorted(
        ((fi, split, k, c2w) for split, lst in splits.items() for k, (fi, c2w) in enumerate(lst)),
        key=lambda j: (j[0], ["train", "val", "test"].index(j[1]), j[2]),
    )
    frames = {k: [] for k in splits}
    gt, mesh = {}, {}
    t0 = time.time()
    for fi, split, k, c2w in jobs:
        t = fi / (n_train - 1)
        update(t)
        if fi not in gt:
            mesh[fi] = C.world_mesh(scene)
            gt[fi] = sampler(mesh[fi][0][mesh[fi][1]])
        m = C.set_camera_pose(cam, c2w)
        C.render_to(scene, out / split / f"r_{k:03d}.png")
        frames[split].append(
            {
                "file_path": C.rel_file_path(split, f"r_{k:03d}"),
                "rotation": 0.0,
                "time": t,
                "transform_matrix": m,
                "frame_id": fi,
            }
        )
    t_render = time.time() - t0
    for split, lst in frames.items():
        lst.sort(key=lambda e: e["file_path"])
        C.write_json(out / f"transforms_{split}.json", {"camera_angle_x": C.CAMERA_ANGLE_X, "frames": lst})
    # gt for every training time (val/test times are a subset)
    for fi in range(n_train):
        if fi not in gt:
            update(fi / (n_train - 1))
            mesh[fi] = C.world_mesh(scene)
            gt[fi] = sampler(mesh[fi][0][mesh[fi][1]])
    pts = np.stack([gt[i] for i in range(n_train)]).astype(np.float32)
    C.write_npz(out / "gt_points.npz", points=np.asfortranarray(pts), times=times)
    C.write_gt_mesh(out / "gt_mesh.npz", *stack_meshes([mesh[i] for i in range(n_train)]), times=times)
    return {
        "scene": name,
        "kind": "dynamic_mono",
        "images": len(jobs),
        "render_s": t_render,
        "gt_points": n_points,
        "surface_area": area,
        "frames": n_train,
    }


JOBS = {
    "dynamic_mv/mocap_figure": lambda out, limit: render_multiview(
        "mocap_figure", build_mocap_figure, out, limit, n_points=12000
    ),
    "dynamic_mv/flag": lambda out, limit: render_multiview("flag", build_flag, out, limit, n_points=16000),
    "dynamic_mono/bouncing": lambda out, limit: render_mono("bouncing", build_bouncing, out, limit, n_points=16000),
}

# A multi-view sequence no setting was chosen on (rendered only when named: --only dynamic_mv/mocap_trial3):
# another CMU capture of subject 1 (trial 3), a later window, the second palette, the same cameras.
HELDOUT_JOBS = {
    "dynamic_mv/mocap_trial3": lambda out, limit: render_multiview(
        "mocap_trial3", build_mocap_figure, out, limit, n_points=12000, bvh_file="01_03.bvh", start=1800, palette=1
    ),
}
