"""PLY export/import (3DGS layout through plyfile): renders survive a round trip, the property names
and order that splat viewers expect, clear errors for malformed files, per-frame PLYs of 4D models."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from src.core.splats import Splats
from src.io.ply import (
    BakedFrame,
    ply_property_names,
    read_baked_frames,
    read_ply,
    scene_frames,
    write_baked_frames,
    write_baked_ply,
    write_ply,
)
from src.models.deformable import DeformableGaussianModel
from src.models.gaussians import GaussianSplatModel
from src.rasterizer.torch_ref import TorchRefRasterizer
from tests.conftest import random_camera, random_scene


def _trained_like(model: GaussianSplatModel, seed: int = 0) -> GaussianSplatModel:
    """Random parameters in the ranges training produces (the initial ones are too uniform to test)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        p = model.params
        p["opacities"].copy_(torch.rand(p["opacities"].shape, generator=g) * 6 - 3)
        p["sh0"].copy_(torch.randn(p["sh0"].shape, generator=g) * 0.8)
        p["shN"].copy_(torch.randn(p["shN"].shape, generator=g) * 0.2)
        p["quats"].copy_(torch.randn(p["quats"].shape, generator=g))
        p["scales"].copy_(torch.log(torch.rand(p["scales"].shape, generator=g) * 0.1 + 0.02))
    return model


def _model(n: int = 60, sh_degree: int = 1, seed: int = 0) -> GaussianSplatModel:
    g = torch.Generator().manual_seed(seed)
    m = GaussianSplatModel(torch.randn(n, 3, generator=g) * 0.4, sh_degree=sh_degree)
    m.active_sh_degree = sh_degree
    return _trained_like(m, seed)


def _write_table(path, columns: dict[str, np.ndarray], text: bool = False) -> None:
    n = len(next(iter(columns.values())))
    arr = np.empty(n, dtype=[(k, v.dtype) for k, v in columns.items()])
    for k, v in columns.items():
        arr[k] = v
    PlyData([PlyElement.describe(arr, "vertex")], text=text).write(str(path))


def _columns(n: int = 5, dtype=np.float32) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    cols = {k: rng.normal(size=n).astype(dtype) for k in ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity")}
    cols.update({f"scale_{i}": np.full(n, -3.0, dtype) for i in range(3)})
    cols.update({f"rot_{i}": np.full(n, 1.0 if i == 0 else 0.0, dtype) for i in range(4)})
    return cols


def test_baked_ply_round_trip_renders_identically(tmp_path, one_thread):
    model = _model(sh_degree=1)
    write_baked_ply(model, tmp_path)
    back = read_ply(tmp_path / "splats.ply")
    baked = model.bake()
    rast = TorchRefRasterizer()
    bg = torch.tensor([0.2, 0.3, 0.4])
    for seed in (1, 2):
        cam = random_camera(40, 32, seed=seed)
        a = rast.render(baked, cam, bg)
        b = rast.render(back.splats, cam, bg)
        assert a.alpha.max() > 0.3  # the camera sees the splats
        torch.testing.assert_close(b.color, a.color, atol=2e-5, rtol=0)
        torch.testing.assert_close(b.alpha, a.alpha, atol=2e-5, rtol=0)
    # the trained higher SH band travels as f_rest (for external viewers), channel-major in the file
    assert back.sh_rest is not None and back.sh_rest.shape == (60, 3, 3)
    torch.testing.assert_close(back.sh_rest, model.params["shN"].detach()[:, :3])


def test_write_ply_round_trip_values(tmp_path):
    s = random_scene(30, seed=3)
    rest = torch.randn(30, 8, 3)
    write_ply(tmp_path / "a.ply", s, rest)
    back = read_ply(tmp_path / "a.ply")
    for k in ("means", "scales", "opacities", "colors"):
        torch.testing.assert_close(getattr(back.splats, k), getattr(s, k), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(back.splats.quats, torch.nn.functional.normalize(s.quats, dim=-1))
    assert torch.equal(back.sh_rest, rest)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_property_names_and_order_match_the_3dgs_layout(tmp_path, degree):
    model = _model(n=7, sh_degree=degree)
    write_baked_ply(model, tmp_path)
    path = tmp_path / "splats.ply"
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(n_rest)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert ply_property_names(n_rest) == expected
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n")].decode("ascii").splitlines()
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 7"]
    assert [ln for ln in header if ln.startswith("property")] == [f"property float {nm}" for nm in expected]
    assert len(raw) - raw.index(b"end_header\n") - len(b"end_header\n") == 7 * len(expected) * 4
    ply = PlyData.read(str(path))
    assert [el.name for el in ply.elements] == ["vertex"]
    # the file's conventions: log-scales, logit opacities, unit wxyz quaternions, zero normals
    v = ply["vertex"].data
    baked = model.bake()
    np.testing.assert_allclose(np.exp(np.stack([v[f"scale_{i}"] for i in range(3)], 1)), baked.scales, rtol=1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-v["opacity"])), baked.opacities, atol=1e-6)
    q = np.stack([v[f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(q, baked.quats, atol=1e-6)
    assert not np.any(np.stack([v["nx"], v["ny"], v["nz"]]))


def test_reads_third_party_files_in_other_formats_and_types(tmp_path):
    cols = _columns(dtype=np.float64)  # double properties, no normals, ASCII
    _write_table(tmp_path / "a.ply", cols, text=True)
    s = read_ply(tmp_path / "a.ply").splats
    assert s.means.dtype == torch.float32 and s.n == 5 and s.colors.shape == (5, 3)
    np.testing.assert_allclose(s.means[:, 0], cols["x"], rtol=1e-6)


def test_missing_file_and_non_ply_name_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.ply"):
        read_ply(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"import os; os.system('echo hi')\n")
    with pytest.raises(ValueError, match=r"bad\.ply"):
        read_ply(bad)


def test_truncated_file_names_the_path(tmp_path):
    write_ply(tmp_path / "t.ply", random_scene(20))
    raw = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-100])
    with pytest.raises(ValueError, match=r"t\.ply"):
        read_ply(tmp_path / "t.ply")


@pytest.mark.parametrize("drop", ["opacity", "rot_3", "f_dc_1", "scale_0"])
def test_missing_property_is_named(tmp_path, drop):
    cols = _columns()
    del cols[drop]
    _write_table(tmp_path / "m.ply", cols)
    with pytest.raises(ValueError, match=rf"m\.ply: missing vertex property '{drop}'"):
        read_ply(tmp_path / "m.ply")


def test_malformed_properties_are_named(tmp_path):
    cols = _columns()
    cols["opacity"][2] = np.nan
    _write_table(tmp_path / "nan.ply", cols)
    with pytest.raises(ValueError, match=r"nan\.ply: vertex property 'opacity' is not finite at vertex 2"):
        read_ply(tmp_path / "nan.ply")
    cols = _columns()
    cols["f_rest_0"] = np.zeros(5, np.float32)  # one f_rest value cannot be an SH band of 3 channels
    _write_table(tmp_path / "rest.ply", cols)
    with pytest.raises(ValueError, match=r"rest\.ply: malformed f_rest_\*"):
        read_ply(tmp_path / "rest.ply")
    # a list property where a scalar belongs
    arr = np.empty(2, dtype=[(k, "f4") for k in _columns() if k != "x"] + [("x", "O")])
    for k in _columns():
        if k != "x":
            arr[k] = 0.0
    arr["x"] = [np.zeros(2, np.float32), np.zeros(2, np.float32)]
    PlyData([PlyElement.describe(arr, "vertex", val_types={"x": "f4"})]).write(str(tmp_path / "list.ply"))
    with pytest.raises(ValueError, match=r"list\.ply: vertex property 'x' is not a numeric scalar"):
        read_ply(tmp_path / "list.ply")


def test_no_vertex_element_is_named(tmp_path):
    arr = np.zeros(3, dtype=[("a", "f4")])
    PlyData([PlyElement.describe(arr, "face")]).write(str(tmp_path / "f.ply"))
    with pytest.raises(ValueError, match=r"f\.ply: no 'vertex' element \(found: face\)"):
        read_ply(tmp_path / "f.ply")


def test_non_rgb_colours_are_refused(tmp_path):
    s = random_scene(4, channels=5)
    with pytest.raises(ValueError, match="RGB"):
        write_ply(tmp_path / "x.ply", s)
    assert not (tmp_path / "x.ply").exists()


def _deformable(seed: int = 0) -> DeformableGaussianModel:
    g = torch.Generator().manual_seed(seed)
    m = DeformableGaussianModel(torch.randn(25, 3, generator=g) * 0.4, n_frames=5, depth=2, width=16,
                                skip=1, sh_degree=0)
    _trained_like(m, seed)
    with torch.no_grad():  # a deformation that is not the identity
        for p in m.deform.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.3)
    return m.eval()


def test_dynamic_model_bakes_one_ply_per_frame(tmp_path, one_thread):
    m = _deformable()
    frames = [(3, 0.75), (0, 0.0), (1, 0.25), (2, 0.5), (4, 1.0)]
    write_baked_ply(m, tmp_path, frames=frames, max_frames=None)
    assert (tmp_path / "splats.ply").is_file()
    got = read_baked_frames(tmp_path)
    assert [(f.frame_id, f.time) for f in got] == sorted(frames, key=lambda ft: ft[1])
    for f in got:
        assert f.path == tmp_path / "frames" / f"frame_{f.frame_id:04d}.ply"
        torch.testing.assert_close(read_ply(f.path).splats.means, m.bake(time=f.time, frame_id=f.frame_id).means)
    assert not torch.allclose(read_ply(got[0].path).means, read_ply(got[-1].path).means)


def test_frames_are_subsampled_evenly_and_static_scenes_write_none(tmp_path):
    m = _deformable()
    frames = [(i, i / 9) for i in range(10)]
    got = write_baked_frames(m, tmp_path, frames, max_frames=4)
    assert [f.frame_id for f in got] == [0, 3, 6, 9]
    assert read_baked_frames(tmp_path) == got
    static = tmp_path / "static"
    write_baked_ply(m, static, frames=[(0, 0.0)])
    assert (static / "splats.ply").is_file() and read_baked_frames(static) == []


def test_scene_frames_lists_distinct_training_times():
    class _Cam:
        def __init__(self, fid, t):
            self.frame_id, self.time = fid, t

    class _View:
        def __init__(self, fid, t):
            self.camera = _Cam(fid, t)

    class _Scene:
        def __init__(self, n_frames):
            self.n_frames = n_frames
            self.train = [_View(2, 1.0), _View(0, 0.0), _View(2, 1.0), _View(1, 0.5)]

    assert scene_frames(_Scene(3)) == [(0, 0.0), (1, 0.5), (2, 1.0)]
    assert scene_frames(_Scene(1)) == []


def test_frame_index_errors_name_the_index(tmp_path):
    (tmp_path / "frames").mkdir()
    index = tmp_path / "frames" / "frames.json"
    index.write_text(json.dumps({"frames": [{"frame_id": 0, "time": 0.0, "file": "frame_0000.ply"}]}))
    with pytest.raises(ValueError, match=r"frames\.json: frame 0 names .*frame_0000\.ply, which does not exist"):
        read_baked_frames(tmp_path)
    index.write_text("{not json")
    with pytest.raises(ValueError, match=r"frames\.json: malformed frame index"):
        read_baked_frames(tmp_path)
    write_ply(tmp_path / "frames" / "frame_0000.ply", Splats.empty())
    index.write_text(json.dumps({"frames": [{"frame_id": 0, "time": 0.0, "file": "frame_0000.ply"}]}))
    assert read_baked_frames(tmp_path) == [BakedFrame(0, 0.0, tmp_path / "frames" / "frame_0000.ply")]
    assert read_ply(tmp_path / "frames" / "frame_0000.ply").splats.n == 0
