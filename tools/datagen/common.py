"""Shared helpers for the Blender (bpy 5.0.1) data generator.

Runs only inside the isolated ``.venv-datagen`` (bpy pins numpy<2).
Everything here is deterministic: fixed seeds, fixed sample counts, no
render-time metadata in the written PNGs (they are re-encoded with Pillow,
which writes only IHDR/IDAT/IEND, with maximum zlib compression).
"""

from __future__ import annotations

import atexit
import io
import math
import os
import shutil
import tempfile
from pathlib import Path

import bpy
import numpy as np
from layouts import write_gt_mesh, write_json, write_npz  # noqa: F401  (re-exported)
from mathutils import Matrix
from PIL import Image

# ---------------------------------------------------------------- constants
RES = 100  # image width = height (px)
CAMERA_ANGLE_X = 0.6911112070083618  # NeRF-synthetic value (radians)
CAM_RADIUS = 4.0
SAMPLES_STATIC = 64
SAMPLES_DYNAMIC = 48
THREADS = 2
HDRI = "studio.exr"  # bundled CC0 studio light (Poly Haven), see data/README.md

STUDIOLIGHT_DIR = Path(bpy.utils.system_resource("DATAFILES", path="studiolights/world"))
BVH_DIR = Path("/usr/share/assimp/models/BVH")


def skimage_data_dir() -> Path:
    import skimage

    return Path(skimage.__file__).resolve().parent / "data"


# ---------------------------------------------------------------- scene setup
def reset_scene(samples: int = SAMPLES_STATIC) -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.use_preview_denoising = False
    scene.cycles.seed = 0
    scene.cycles.use_animated_seed = False
    scene.cycles.max_bounces = 6
    scene.cycles.diffuse_bounces = 3
    scene.cycles.glossy_bounces = 3
    scene.cycles.transmission_bounces = 4
    scene.cycles.transparent_max_bounces = 8
    scene.cycles.caustics_reflective = False
    scene.cycles.caustics_refractive = False
    # Box filter of one pixel: alpha = fraction of the pixel covered by geometry,
    # so (alpha > 0) is exactly the set of pixels the surface projects into.
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    r.threads_mode = "FIXED"
    r.threads = THREADS
    r.film_transparent = True
    r.resolution_x = RES
    r.resolution_y = RES
    r.resolution_percentage = 100
    r.pixel_aspect_x = 1.0
    r.pixel_aspect_y = 1.0
    r.dither_intensity = 0.0
    r.use_persistent_data = True
    ims = r.image_settings
    ims.file_format = "PNG"
    ims.color_mode = "RGBA"
    ims.color_depth = "8"
    ims.compression = 100
    r.use_stamp = False
    for attr in dir(r):
        if attr.startswith("use_stamp"):
            setattr(r, attr, False)
    r.metadata_input = "SCENE"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    scene.unit_settings.system = "METRIC"
    return scene


def setup_world(
    scene,
    hdri: str = HDRI,
    strength: float = 1.0,
    rot_z: float = 0.0,
    sun_strength: float = 3.0,
    sun_dir=(0.6, -0.4, 0.45),
):
    world = bpy.data.worlds.new("World")
    scene.world = world
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    mapping = nt.nodes.new("ShaderNodeMapping")
    coord = nt.nodes.new("ShaderNodeTexCoord")
    env.image = bpy.data.images.load(str(STUDIOLIGHT_DIR / hdri), check_existing=True)
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, rot_z)
    nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = strength
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    if sun_strength > 0:
        sun = bpy.data.lights.new("Sun", type="SUN")
        sun.energy = sun_strength
        sun.angle = math.radians(4.0)
        obj = bpy.data.objects.new("Sun", sun)
        scene.collection.objects.link(obj)
        d = np.asarray(sun_dir, dtype=np.float64)
        d /= np.linalg.norm(d)
        # a sun shines along its local -Z: point -Z towards -d (i.e. light comes from d)
        obj.matrix_world = Matrix(look_at_c2w(d * 10.0, np.zeros(3)).tolist())


# ---------------------------------------------------------------- cameras
def look_at_c2w(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world in Blender/OpenGL convention (camera looks along -Z, +Y up)."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(fwd, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    m = np.eye(4)
    m[:3, 0] = right
    m[:3, 1] = cam_up
    m[:3, 2] = -fwd
    m[:3, 3] = eye
    return m


def sph_to_xyz(radius, azimuth, elevation, center=(0.0, 0.0, 0.0)):
    c = np.asarray(center, dtype=np.float64)
    return c + radius * np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )


def make_camera(scene, name: str = "Camera"):
    cam = bpy.data.cameras.new(name)
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = 36.0
    cam.angle_x = CAMERA_ANGLE_X
    cam.clip_start = 0.05
    cam.clip_end = 100.0
    cam.shift_x = 0.0
    cam.shift_y = 0.0
    obj = bpy.data.objects.new(name, cam)
    scene.collection.objects.link(obj)
    scene.camera = obj
    return obj


def set_camera_pose(cam_obj, c2w: np.ndarray) -> list:
    cam_obj.matrix_world = Matrix(np.asarray(c2w).tolist())
    bpy.context.view_layer.update()
    m = np.array(cam_obj.matrix_world, dtype=np.float64)
    return [[float(v) for v in row] for row in m]


def hemisphere_poses(
    n: int,
    seed: int,
    radius: float = CAM_RADIUS,
    min_elev_deg: float = 5.0,
    max_elev_deg: float = 85.0,
    center=(0.0, 0.0, 0.0),
) -> list[np.ndarray]:
    """Random cameras uniform (in area) on the upper hemisphere band, looking at the centre."""
    rng = np.random.default_rng(seed)
    zlo = math.sin(math.radians(min_elev_deg))
    zhi = math.sin(math.radians(max_elev_deg))
    poses = []
    for _ in range(n):
        z = rng.uniform(zlo, zhi)
        az = rng.uniform(0.0, 2.0 * math.pi)
        eye = sph_to_xyz(radius, az, math.asin(z), center)
        poses.append(look_at_c2w(eye, center))
    return poses


# ---------------------------------------------------------------- rendering
_TMP = Path(tempfile.mkdtemp(prefix="splatfields_datagen_"))
atexit.register(shutil.rmtree, _TMP, ignore_errors=True)


def optimise_png(src: Path, dst: Path) -> None:
    """Re-encode an RGBA PNG deterministically (no text chunks, max compression).

    Fully transparent pixels get RGB = 0 so the background compresses to nothing.
    """
    with Image.open(src) as im:
        im.load()
        arr = np.asarray(im.convert("RGBA")).copy()
    arr[arr[..., 3] == 0, :3] = 0
    out = Image.fromarray(arr, mode="RGBA")
    buf = io.BytesIO()
    out.save(buf, format="PNG", optimize=True, compress_level=9)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(buf.getvalue())


def render_to(scene, dst: Path) -> None:
    tmp = _TMP / "render.png"
    scene.render.filepath = str(tmp)
    bpy.ops.render.render(write_still=True)
    optimise_png(tmp, Path(dst))


def triangulate_all(scene) -> None:
    """Append a Triangulate modifier (fixed quad split, ear-clipped n-gons) to every render mesh.

    Without it, Blender picks the diagonal of quads whose two diagonals are (almost) equally long
    non-deterministically from run to run, which changed a few pixels and the sampled
    ground-truth points between otherwise identical runs."""
    for obj in scene.objects:
        if obj.type == "MESH" and not obj.hide_render:
            m = obj.modifiers.new("Triangulate", "TRIANGULATE")
            m.quad_method = "FIXED"
            m.ngon_method = "CLIP"
            m.min_vertices = 4


# ---------------------------------------------------------------- ground-truth points
def _render_mesh_objects(scene):
    return [
        o
        for o in scene.objects
        if o.type in {"MESH", "CURVE", "SURFACE", "META", "FONT"} and not o.hide_render and o.visible_get()
    ]


def world_mesh(scene) -> tuple[np.ndarray, np.ndarray]:
    """The evaluated (deformed) render geometry as one indexed triangle mesh in world coordinates:
    (vertices [V, 3] float64, faces [T, 3] int64), objects in name order; ``vertices[faces]`` is
    exactly ``world_triangles(scene)``."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    verts, faces, nv_total = [], [], 0
    for obj in sorted(_render_mesh_objects(scene), key=lambda o: o.name):
        ev = obj.evaluated_get(depsgraph)
        mesh = ev.to_mesh()
        try:
            mesh.calc_loop_triangles()
            nv = len(mesh.vertices)
            nt = len(mesh.loop_triangles)
            if nt == 0:
                continue
            co = np.empty(nv * 3, dtype=np.float64)
            mesh.vertices.foreach_get("co", co)
            co = co.reshape(-1, 3)
            idx = np.empty(nt * 3, dtype=np.int64)
            mesh.loop_triangles.foreach_get("vertices", idx)
            mw = np.array(ev.matrix_world, dtype=np.float64)
            verts.append(co @ mw[:3, :3].T + mw[:3, 3])
            faces.append(idx.reshape(-1, 3) + nv_total)
            nv_total += nv
        finally:
            ev.to_mesh_clear()
    return np.concatenate(verts, axis=0), np.concatenate(faces, axis=0)


def world_triangles(scene) -> np.ndarray:
    """All triangles of the evaluated (deformed) render geometry, world coords, [T,3,3]."""
    verts, faces = world_mesh(scene)
    return verts[faces]


def triangle_areas(tris: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)


class SurfaceSampler:
    """Area-weighted surface samples; the triangle ids and barycentrics are drawn once,
    so for a fixed topology the same samples follow the surface over time."""

    def __init__(self, tris: np.ndarray, n: int, seed: int):
        rng = np.random.default_rng(seed)
        a = triangle_areas(tris)
        self.n_tris = len(tris)
        self.tri_idx = rng.choice(len(tris), size=n, p=a / a.sum())
        u = rng.random(n)
        v = rng.random(n)
        flip = u + v > 1.0
        u[flip] = 1.0 - u[flip]
        v[flip] = 1.0 - v[flip]
        self.bary = np.stack([1.0 - u - v, u, v], axis=1)

    def __call__(self, tris: np.ndarray) -> np.ndarray:
        assert len(tris) == self.n_tris, "topology changed between frames"
        t = tris[self.tri_idx]
        return np.einsum("nk,nkd->nd", self.bary, t).astype(np.float32)


def points_for_area(area: float, per_unit_area: float = 4000.0, lo: int = 5000, hi: int = 20000) -> int:
    return int(min(hi, max(lo, round(area * per_unit_area))))


# ---------------------------------------------------------------- writing
def rel_file_path(split: str, stem: str) -> str:
    return f"./{split}/{stem}"


def env_int(name: str, default: int) -> int:
    return int(os.environ.get(name, default))
