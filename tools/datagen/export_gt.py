"""Re-export the ground-truth meshes (``gt_mesh.npz``) of the shipped scenes WITHOUT rendering
(run inside .venv-datagen; a full ``generate.sh`` writes them too, during the renders).

    .venv-datagen/bin/python tools/datagen/export_gt.py [--data data] [--only static/plant ...]

Each scene is built exactly as ``render_all.py`` builds it and its evaluated render geometry is
taken at every frame time of the shipped data. Before writing, the script re-samples the
ground-truth points from that geometry with the generator's own sampler (same seed, count and
triangle order) and requires them to be **bit-identical** to the shipped ``gt_points.npz``: the
exported mesh is then provably the geometry the images were rendered from. Images, cameras and
``gt_points.npz`` are not touched. The DTU-like copy (``formats/dtu_neus/trinkets``) renders
``static/trinkets``' geometry: its 20 000 points are checked against that mesh too, and no separate
mesh is written for it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import common as C  # noqa: E402
import dynamic_scenes as D  # noqa: E402
import static_scenes as S  # noqa: E402

# scene -> (builder, number of gt points, frame times); the counts are those of dynamic_scenes.JOBS
DYNAMIC = {
    "dynamic_mv/mocap_figure": (D.build_mocap_figure, 12000, [f / (D.N_FRAMES_MV - 1) for f in range(D.N_FRAMES_MV)]),
    "dynamic_mv/flag": (D.build_flag, 16000, [f / (D.N_FRAMES_MV - 1) for f in range(D.N_FRAMES_MV)]),
    "dynamic_mono/bouncing": (D.build_bouncing, 16000,
                              [f / (D.N_FRAMES_MONO - 1) for f in range(D.N_FRAMES_MONO)]),
}
SCENES = [f"static/{n}" for n in S.STATIC_SCENES] + list(DYNAMIC)


def _same(a: np.ndarray, b: np.ndarray, what: str) -> None:
    if a.shape != b.shape or a.dtype != b.dtype or not np.array_equal(a, b):
        err = np.abs(a.astype(np.float64) - b.astype(np.float64)).max() if a.shape == b.shape else "shape"
        raise SystemExit(f"[export_gt] {what}: re-sampled points differ from the shipped ones ({err})")


def export_static(name: str, data: Path) -> dict:
    scene = C.reset_scene(C.SAMPLES_STATIC)
    S.STATIC_SCENES[name](scene)
    C.triangulate_all(scene)
    verts, faces = C.world_mesh(scene)
    tris = verts[faces]
    area = float(C.triangle_areas(tris).sum())
    n = C.points_for_area(area, per_unit_area=5000.0, lo=20000, hi=50000)  # as render_static
    out = data / "static" / name
    _same(C.SurfaceSampler(tris, n, seed=123)(tris), np.load(out / "gt_points.npz")["points"], f"static/{name}")
    dtu = data / "formats" / "dtu_neus" / name / "gt_points.npz"
    if dtu.is_file():  # as render_dtu: 20 000 points, seed 123, same geometry
        _same(C.SurfaceSampler(tris, 20000, seed=123)(tris), np.load(dtu)["points"], f"formats/dtu_neus/{name}")
    err = C.write_gt_mesh(out / "gt_mesh.npz", verts, faces)
    return {"vertices": len(verts), "faces": len(faces), "frames": 1, "quant_err": err}


def export_dynamic(job: str, data: Path) -> dict:
    builder, n_points, times = DYNAMIC[job]
    scene = C.reset_scene(C.SAMPLES_DYNAMIC)
    update = builder(scene)
    C.triangulate_all(scene)
    sampler, _ = D._gt_sampler(scene, update, n_points)
    mesh, pts = [], []
    for t in times:
        update(t)
        verts, faces = C.world_mesh(scene)
        mesh.append((verts, faces))
        pts.append(sampler(verts[faces]))
    out = data / job
    shipped = np.load(out / "gt_points.npz")
    _same(np.stack(pts).astype(np.float32), np.ascontiguousarray(shipped["points"]), job)
    times32 = np.asarray(times, dtype=np.float32)
    _same(times32, shipped["times"], f"{job} times")
    verts, faces = D.stack_meshes(mesh)
    err = C.write_gt_mesh(out / "gt_mesh.npz", verts, faces, times=times32)
    return {"vertices": verts.shape[1], "faces": len(faces), "frames": len(times), "quant_err": err}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=HERE.parent.parent / "data")
    ap.add_argument("--only", nargs="*", default=None, help=f"scenes (default all): {' '.join(SCENES)}")
    args = ap.parse_args(argv)
    for job in args.only or SCENES:
        t0 = time.time()
        kind, name = job.split("/")
        st = export_static(name, args.data) if kind == "static" else export_dynamic(job, args.data)
        size = (args.data / job / "gt_mesh.npz").stat().st_size
        print(f"[export_gt] {job}: {st['frames']} frame(s), {st['vertices']} vertices, {st['faces']} triangles, "
              f"max quantisation error {st['quant_err']:.1e}, {size / 1e6:.2f} MB, points bit-identical "
              f"({time.time() - t0:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
