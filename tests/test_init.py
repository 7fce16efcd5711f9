"""Initialisers: visual hull, from a finished 3DGS run (two-stage protocol), clear error without it."""

from __future__ import annotations

import pytest
import torch

from src.core.splats import Splats
from src.data.base import DatasetError
from src.data.blender import BlenderDataset
from src.data.hull import inside_hull
from src.init import FromRunInit, HullInit
from src.io.ply import write_ply
from src.utils.instantiate import build
from src.utils.validate import ConfigValueError
from tests.scenes import write_blender_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = write_blender_scene(tmp_path_factory.mktemp("s") / "scene", n_train=6, n_test=1, size=32)
    return BlenderDataset(str(root), n_views=6, n_test=1).load()


def test_hull_points_are_inside_every_training_mask(scene):
    pts = HullInit(n_points=500)(scene, torch.Generator().manual_seed(0))
    assert pts.shape == (500, 3) and pts.abs().max() <= 1.0
    assert inside_hull(pts.double(), [v.camera for v in scene.train], [v.mask for v in scene.train]).all()


def test_from_run_reads_the_ply_filters_to_the_hull_and_subsamples(scene, tmp_path):
    g = torch.Generator().manual_seed(1)
    inside = HullInit(n_points=300)(scene, g)
    outside = torch.full((50, 3), 0.99)  # a corner of the box: outside the object's hull
    means = torch.cat([inside, outside])
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    splats = Splats(means, torch.full((n, 3), 0.01), quats, torch.full((n,), 0.5), torch.rand(n, 3, generator=g))
    write_ply(tmp_path / "splats.ply", splats)
    pts = FromRunInit(run_dir=str(tmp_path), n_points=200)(scene, g)
    assert pts.shape == (200, 3)
    assert inside_hull(pts.double(), [v.camera for v in scene.train], [v.mask for v in scene.train]).all()


def test_from_run_select_opacity_keeps_the_most_opaque_first_stage_splats(scene, tmp_path):
    g = torch.Generator().manual_seed(2)
    means = HullInit(n_points=300)(scene, g)
    n = means.shape[0]
    opacity = torch.linspace(0.01, 0.99, n)[torch.randperm(n, generator=g)]  # distinct, shuffled
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    write_ply(tmp_path / "splats.ply", Splats(means, torch.full((n, 3), 0.01), quats, opacity, torch.rand(n, 3)))
    pts = FromRunInit(run_dir=str(tmp_path), n_points=100, select="opacity")(scene, g)
    kept = torch.cdist(pts.double(), means.double()).argmin(1)           # [100] indices into the file
    assert pts.shape == (100, 3) and set(kept.tolist()) == set(opacity.argsort(descending=True)[:100].tolist())
    with pytest.raises(ValueError, match=r"init\.select"):
        FromRunInit(run_dir=str(tmp_path), select="largest")


def test_an_unknown_query_selection_is_refused_before_the_run():
    from hydra import compose, initialize_config_module

    import src.run  # noqa: F401 - registers the config resolvers (if_at_most, ...) the composed config uses
    from src.utils.validate import ConfigValueError, validate_run_config

    with initialize_config_module("conf", version_base="1.3"):
        validate_run_config(compose("config", overrides=["init.select=opacity"]))  # the main job: init=from_run
        with pytest.raises(ConfigValueError, match=r"init\.select='largest': expected one of random, opacity"):
            validate_run_config(compose("config", overrides=["init.select=largest"]))


def test_from_run_without_artefact_names_the_command(scene, tmp_path):
    with pytest.raises(DatasetError, match=r"python -m src.run \+experiment=gs3d"):
        FromRunInit(run_dir=str(tmp_path / "missing"))(scene, torch.Generator())


def _two_frame_scene(scene):
    """``scene`` as a 2-frame sequence whose subject at frame 1 sits elsewhere (masks mirrored)."""
    from dataclasses import replace

    moved = [replace(v, camera=replace(v.camera, frame_id=1, time=1.0), mask=v.mask.flip(1),
                     image=v.image.flip(1)) for v in scene.train]
    return replace(scene, train=scene.train + moved, n_frames=2)


def test_dynamic_hull_first_frame_or_union_of_frames(scene):
    seq = _two_frame_scene(scene)
    cams = [v.camera for v in scene.train]
    in0 = lambda p: inside_hull(p.double(), cams, [v.mask for v in scene.train])  # noqa: E731
    in1 = lambda p: inside_hull(p.double(), cams, [v.mask.flip(1) for v in scene.train])  # noqa: E731
    first = HullInit(n_points=400, first_frame_only=True)(seq, torch.Generator().manual_seed(0))
    assert first.shape == (400, 3) and in0(first).all()
    union = HullInit(n_points=401, first_frame_only=False)(seq, torch.Generator().manual_seed(0))
    assert union.shape == (401, 3)
    assert (in0(union) | in1(union)).all()
    # split evenly over the frames (201 + 200 points), each part inside its own frame's hull
    assert in0(union[:201]).all() and in1(union[201:]).all()
    assert (in1(union) & ~in0(union)).any()


def test_hull_without_masks_samples_the_box_or_refuses(scene, caplog):
    from dataclasses import replace

    unmasked = replace(scene, train=[replace(v, mask=None) for v in scene.train])
    pts = HullInit(n_points=400, box=0.5)(unmasked, torch.Generator().manual_seed(0))
    assert pts.shape == (400, 3) and pts.abs().max() <= 0.5
    assert "sampling the box" in caplog.text and scene.name in caplog.text
    with pytest.raises(DatasetError, match=r"init=hull needs masks.*use init=box"):
        HullInit(n_points=10, without_masks="error")(unmasked, torch.Generator())
    # a bad option is a one-line input error naming the key, also when Hydra builds it (exit 2 in src.run)
    with pytest.raises(ConfigValueError, match=r"^init.without_masks='ignore': expected 'sfm', 'box' or 'error'$"):
        build({"_target_": "src.init.HullInit", "without_masks": "ignore"})


def test_hull_without_masks_starts_from_the_sfm_points_when_the_reader_has_them(scene, caplog):
    from dataclasses import replace

    points = torch.rand(50, 3, generator=torch.Generator().manual_seed(1)) - 0.5      # [P, 3]
    unmasked = replace(scene, train=[replace(v, mask=None) for v in scene.train], meta={**scene.meta, "points": points})
    kept = HullInit(n_points=400)(unmasked, torch.Generator().manual_seed(0))
    assert torch.equal(kept, points) and "50 structure-from-motion points" in caplog.text
    few = HullInit(n_points=20)(unmasked, torch.Generator().manual_seed(0))      # a uniform subsample of them
    assert few.shape == (20, 3) and all(any(torch.equal(p, q) for q in points) for p in few)
    boxed = HullInit(n_points=30, box=0.5, without_masks="box")(unmasked, torch.Generator().manual_seed(0))
    assert boxed.shape == (30, 3) and boxed.abs().max() <= 0.5                    # "box" ignores the points
    no_points = replace(unmasked, meta={**scene.meta, "points": points[:0]})
    assert HullInit(n_points=30, box=0.5)(no_points, torch.Generator()).shape == (30, 3)
