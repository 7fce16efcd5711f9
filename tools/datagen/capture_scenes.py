"""Photo captures: a full-background scene photographed as a hand-held capture, for ``python -m src.data.sfm``.

``captures/room`` is a closed, textured room (brick back wall, plaster side walls hung with photo posters,
a tiled floor, a ceiling, a rug), a table with photo-textured boxes, a ball, a mug and a book on it, and a
crate, a barrel and a stool on the floor. Thirty photos are taken from an inward-looking arc of 120°
around the table at standing height, with the small height, distance, aim and roll wobble of a hand-held camera
(fixed seed), so that every photo sees overlapping textured content.

Written into ``OUT/captures/room/``:

* ``images/IMG_0000.jpg`` … ``IMG_0029.jpg``: 400 × 300 px JPEG (quality 92, Pillow, no metadata), the
  photos the structure from motion reads (``python -m src.data.sfm OUT/captures/room/images
  OUT/captures/room`` builds ``sparse/0`` beside them);
* ``gt_cameras.json``: the renderer's cameras, for checking the reconstruction: ``width``, ``height``,
  ``fx``, ``fy``, ``cx``, ``cy`` (pixels; principal point at the image centre, pixel centres at j + 0.5)
  and ``frames`` = [{"file": "IMG_0000.jpg", "c2w": 4 × 4 camera-to-world, **OpenCV** axes (x right,
  y down, z forward), world = Blender's (Z up, metres)}].

Cycles on the CPU, 8 samples per pixel, OpenImageDenoise (albedo and normal passes), seed 0, two threads:
about 8 s of CPU per photo (14 s of wall time each on 2 CPU cores); the photos are byte-identical from run
to run.
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Sequence
from pathlib import Path

import bpy
import common as C
import geometry as G
import materials as M
import numpy as np
from layouts import GL_TO_CV
from PIL import Image

WIDTH, HEIGHT = 400, 300
ANGLE_X = math.radians(60.0)  # horizontal field of view: fx = 200 / tan(30°) = 346.4 px
SAMPLES = 8
N_PHOTOS = 30
JPEG_QUALITY = 92
SEED = 11  # the hand-held wobble of the camera path

ROOM = ((-3.2, 3.2), (-3.0, 3.2), (0.0, 2.8))  # x, y, z extent of the room's inside (metres)
TABLE_TOP = 0.78                                   # table height
TARGET = np.array([0.0, 0.7, 0.9])                 # what the photographer aims at (above the table)


# ---------------------------------------------------------------- materials
def world_texture(name: str, filename: str, tile: float, roughness: float = 0.6,
                  tint: tuple[float, float, float] | None = None, bump: float = 0.0,
                  turn: float = 0.0) -> bpy.types.Material:
    """A scikit-image photo tiled over world space (box projection of the world position, ``tile`` metres per
    repeat), so that large, scaled surfaces keep the photo's texel size; ``turn`` rotates the world position about
    the Y axis first (radians: 90° turns the photo on walls facing ±Y)."""
    mat = M.image(name, filename, roughness=roughness, tint=tint, bump=bump)
    nt = mat.node_tree
    tex = next(n for n in nt.nodes if n.type == "TEX_IMAGE")
    mapping = next(n for n in nt.nodes if n.type == "MAPPING")
    geo = nt.nodes.new("ShaderNodeNewGeometry")
    for link in list(mapping.inputs["Vector"].links):
        nt.links.remove(link)
    nt.links.new(geo.outputs["Position"], mapping.inputs["Vector"])
    mapping.inputs["Scale"].default_value = (1.0 / tile, 1.0 / tile, 1.0 / tile)
    mapping.inputs["Rotation"].default_value = (0.0, turn, 0.0)
    tex.projection = "BOX"
    tex.projection_blend = 0.15
    tex.extension = "REPEAT"
    return mat


def poster(filename: str, center: tuple[float, float, float], normal: str, height: float,
           name: str) -> bpy.types.Object:
    """A flat photo print (the whole image, its aspect kept) of ``height`` metres hung at ``center``, facing
    ``normal`` ('+x', '-x' or '-y')."""
    with Image.open(C.skimage_data_dir() / filename) as im:
        w, h = im.size
    width = height * w / h
    plane = G.plane(size=1.0, location=center)
    plane.name = name
    plane.scale = (width, height, 1.0)
    # the plane lies in XY facing +Z; stand it up (image up = +Z) and turn it to face the room
    turn = {"-y": 0.0, "+x": math.pi / 2, "-x": -math.pi / 2}[normal]
    plane.rotation_euler = (math.pi / 2, 0.0, turn)
    M.assign(plane, M.image(f"{name}_print", filename, roughness=0.45))
    return plane


# ---------------------------------------------------------------- the room
def slab(lo: Sequence[float], hi: Sequence[float], mat: bpy.types.Material, name: str) -> bpy.types.Object:
    """An axis-aligned box from corner ``lo`` to corner ``hi``."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    box = G.cube(size=1.0, location=tuple((lo + hi) / 2), scale=tuple(hi - lo))
    box.name = name
    return M.assign(box, mat)


def build_room(scene: bpy.types.Scene) -> None:
    """Walls, floor, ceiling, posters, furniture and objects, lit by two ceiling area lights and a warm point
    lamp in a corner (no world light: the room is closed)."""
    (x0, x1), (y0, y1), (z0, z1) = ROOM
    t = 0.1  # wall thickness
    scene.world = bpy.data.worlds.new("World")
    scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)

    floor_mat = world_texture("floor_tiles", "gravel.png", tile=0.9, roughness=0.7, tint=(0.85, 0.7, 0.55), bump=0.3)
    slab((x0 - t, y0 - t, z0 - t), (x1 + t, y1 + t, z0), floor_mat, "floor")
    slab((x0 - t, y0 - t, z1), (x1 + t, y1 + t, z1 + t),
         M.noise("ceiling_plaster", (0.82, 0.8, 0.76), (0.95, 0.94, 0.9), scale=3.0, bump=0.1), "ceiling")
    slab((x0 - t, y1, z0), (x1 + t, y1 + t, z1),
         world_texture("back_bricks", "brick.png", tile=1.1, roughness=0.8, tint=(0.9, 0.55, 0.42), bump=0.4,
                       turn=math.pi / 2),
         "wall_back")
    side = world_texture("side_plaster", "grass.png", tile=1.4, roughness=0.8, tint=(0.75, 0.78, 0.9))
    slab((x0 - t, y0 - t, z0), (x0, y1 + t, z1), side, "wall_left")
    slab((x1, y0 - t, z0), (x1 + t, y1 + t, z1), side, "wall_right")
    slab((x0 - t, y0 - t, z0), (x1 + t, y0, z1),
         M.noise("front_plaster", (0.55, 0.6, 0.5), (0.85, 0.85, 0.75), scale=2.5, bump=0.1), "wall_front")
    skirting = M.plain("skirting", (0.25, 0.15, 0.08), roughness=0.4)
    slab((x0, y1 - 0.02, 0.0), (x1, y1, 0.12), skirting, "skirting_back")

    # posters on the back and side walls
    poster("astronaut.png", (-1.6, y1 - 0.005, 1.65), "-y", 0.9, "poster_astronaut")
    poster("rocket.jpg", (1.5, y1 - 0.005, 1.7), "-y", 0.75, "poster_rocket")
    poster("hubble_deep_field.jpg", (x0 + 0.005, 1.2, 1.6), "+x", 1.0, "poster_hubble")
    poster("chelsea.png", (x0 + 0.005, -0.9, 1.5), "+x", 0.7, "poster_chelsea")
    poster("camera.png", (x1 - 0.005, 1.3, 1.6), "-x", 0.9, "poster_camera")
    poster("coffee.png", (x1 - 0.005, -0.8, 1.45), "-x", 0.7, "poster_coffee")

    # a rug under the table
    slab((-1.4, -0.3, 0.0), (1.4, 1.8, 0.01),
         M.checker("rug", (0.55, 0.12, 0.1), (0.9, 0.8, 0.55), scale=9.0, roughness=0.9, coord="Generated"), "rug")

    # the table: a top and four legs
    wood = M.stripes("table_wood", (0.35, 0.18, 0.08), (0.62, 0.4, 0.2), scale=12.0, roughness=0.45)
    cx, cy = 0.0, 0.7
    slab((cx - 0.8, cy - 0.5, TABLE_TOP - 0.05), (cx + 0.8, cy + 0.5, TABLE_TOP), wood, "table_top")
    for i, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
        lx, ly = cx + sx * 0.72, cy + sy * 0.42
        slab((lx - 0.04, ly - 0.04, 0.0), (lx + 0.04, ly + 0.04, TABLE_TOP - 0.05), wood, f"table_leg{i}")

    # objects on the table
    z = TABLE_TOP
    box = slab((-0.6, 0.45, z), (-0.25, 0.75, z + 0.28), world_texture("box_coffee", "coffee.png", tile=0.35), "box0")
    box.rotation_euler = (0.0, 0.0, 0.35)
    slab((0.3, 0.85, z), (0.6, 1.05, z + 0.4), world_texture("box_astro", "astronaut.png", tile=0.3), "box1")
    ball = G.uv_sphere(radius=0.13, location=(0.05, 0.55, z + 0.13), name="ball")
    M.assign(ball, M.voronoi("ball_glaze", (0.05, 0.2, 0.5), (0.9, 0.85, 0.6), scale=12.0, roughness=0.3))
    mug = G.cylinder(radius=0.07, depth=0.16, location=(0.45, 0.35, z + 0.08), vertices=32)
    M.assign(mug, M.checker("mug", (0.95, 0.95, 0.9), (0.1, 0.3, 0.6), scale=6.0, roughness=0.25, coord="Generated"))
    book = slab((-0.2, 0.95, z), (0.15, 1.17, z + 0.06), world_texture("book", "text.png", tile=0.25), "book")
    book.rotation_euler = (0.0, 0.0, -0.2)

    # objects on the floor
    crate = slab((1.3, 1.5, 0.0), (1.85, 2.05, 0.5), world_texture("crate", "chelsea.png", tile=0.5), "crate")
    crate.rotation_euler = (0.0, 0.0, 0.3)
    barrel = G.cylinder(radius=0.25, depth=0.7, location=(-1.7, 1.9, 0.35), vertices=48)
    M.assign(barrel, M.stripes("barrel", (0.2, 0.35, 0.15), (0.8, 0.75, 0.4), scale=5.0, roughness=0.5))
    stool = G.cylinder(radius=0.22, depth=0.45, location=(-1.3, -0.1, 0.225), vertices=6)
    M.assign(stool, M.noise("stool", (0.5, 0.1, 0.1), (0.9, 0.6, 0.2), scale=10.0))
    cube = G.cube(size=0.3, location=(1.4, 0.0, 0.15), rotation=(0.0, 0.0, 0.6))
    M.assign(cube, M.checker("floor_cube", (0.1, 0.1, 0.1), (0.95, 0.9, 0.2), scale=5.0, roughness=0.3))

    # light: two ceiling panels and a warm lamp in the corner (no world light: the room is closed)
    for i, x in enumerate((-1.2, 1.2)):
        panel = bpy.data.lights.new(f"panel{i}", type="AREA")
        panel.shape = "RECTANGLE"
        panel.size, panel.size_y = 1.2, 0.6
        panel.energy = 160.0
        obj = bpy.data.objects.new(f"panel{i}", panel)
        obj.location = (x, 0.4, z1 - 0.02)  # an area light shines along its local -Z: down
        scene.collection.objects.link(obj)
    lamp = bpy.data.lights.new("lamp", type="POINT")
    lamp.energy = 40.0
    lamp.color = (1.0, 0.85, 0.65)
    lamp.shadow_soft_size = 0.15
    obj = bpy.data.objects.new("lamp", lamp)
    obj.location = (-2.4, -1.8, 2.0)
    scene.collection.objects.link(obj)


# ---------------------------------------------------------------- the camera path
def capture_poses(n: int = N_PHOTOS, seed: int = SEED) -> list[np.ndarray]:
    """``n`` Blender camera-to-world matrices on an inward-looking arc (azimuth −60°…60° around the table, from
    the front of the room), 2.3 m from the aim point at eye height, with a hand-held wobble (fixed seed): height
    1.55 m + 8 cm · sin(3 · azimuth) + U(±4 cm), radius 2.3 m + U(±10 cm), aim U(±10 cm) per axis and roll
    U(±2°)."""
    rng = np.random.default_rng(seed)
    poses = []
    for k in range(n):
        az = math.radians(-60.0 + 120.0 * k / (n - 1))
        r = 2.3 + rng.uniform(-0.1, 0.1)
        eye = np.array([TARGET[0] + r * math.sin(az), TARGET[1] - r * math.cos(az),
                        1.55 + 0.08 * math.sin(3.0 * az) + rng.uniform(-0.04, 0.04)])
        aim = TARGET + rng.uniform(-0.1, 0.1, size=3)
        c2w = C.look_at_c2w(eye, aim)
        roll = math.radians(rng.uniform(-2.0, 2.0))
        rot = np.eye(4)  # roll about the camera's viewing axis (its local Z)
        rot[:2, :2] = [[math.cos(roll), -math.sin(roll)], [math.sin(roll), math.cos(roll)]]
        poses.append(c2w @ rot)
    return poses


# ---------------------------------------------------------------- rendering
def save_jpeg(src: Path, dst: Path) -> None:
    """Re-encode a rendered PNG as a JPEG without metadata (deterministic bytes)."""
    with Image.open(src) as im:
        rgb = im.convert("RGB")
    buf = io.BytesIO()
    rgb.save(buf, format="JPEG", quality=JPEG_QUALITY, optimize=True, subsampling="4:2:0")
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(buf.getvalue())


def setup_render(scene: bpy.types.Scene) -> None:
    """Cycles settings of the captures: a full frame (no transparency), few samples and a denoiser."""
    r = scene.render
    r.resolution_x, r.resolution_y = WIDTH, HEIGHT
    r.film_transparent = False
    r.image_settings.color_mode = "RGB"
    scene.cycles.use_denoising = True
    scene.cycles.denoiser = "OPENIMAGEDENOISE"
    scene.cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    scene.cycles.denoising_prefilter = "FAST"
    scene.cycles.pixel_filter_type = "BLACKMAN_HARRIS"  # a camera's anti-aliasing
    scene.cycles.filter_width = 1.5
    scene.cycles.max_bounces = 3
    scene.cycles.diffuse_bounces = 1
    scene.cycles.glossy_bounces = 1


def render_room(out_root: Path, limit: int | None = None) -> dict:
    """Render ``captures/room`` into ``out_root/captures/room`` (module docstring)."""
    scene = C.reset_scene(SAMPLES)
    setup_render(scene)
    build_room(scene)
    C.triangulate_all(scene)
    cam = C.make_camera(scene)
    cam.data.angle_x = ANGLE_X
    out = out_root / "captures" / "room"
    fx = 0.5 * WIDTH / math.tan(0.5 * ANGLE_X)
    frames = []
    tmp = C._TMP / "capture.png"
    t0 = time.time()
    poses = capture_poses()
    for k, c2w in enumerate(poses[:limit] if limit else poses):
        m = np.asarray(C.set_camera_pose(cam, c2w))
        C.render_to(scene, tmp)
        name = f"IMG_{k:04d}.jpg"
        save_jpeg(tmp, out / "images" / name)
        frames.append({"file": name, "c2w": [[round(float(v), 9) for v in row] for row in m @ GL_TO_CV]})
    t_render = time.time() - t0
    C.write_json(out / "gt_cameras.json", {
        "width": WIDTH, "height": HEIGHT, "fx": fx, "fy": fx, "cx": WIDTH / 2, "cy": HEIGHT / 2,
        "convention": "c2w: camera-to-world, OpenCV axes (x right, y down, z forward); world: Z up, metres",
        "frames": frames,
    })
    return {"scene": "room", "kind": "capture", "images": len(frames), "render_s": t_render}


JOBS = {"captures/room": render_room}
