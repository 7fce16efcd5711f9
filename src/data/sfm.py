"""Photos to a COLMAP sparse model with pycolmap, on the CPU: the input of ``dataset=colmap``.

``python -m src.data.sfm IMAGES_DIR OUT_DIR [--camera-model SIMPLE_PINHOLE|PINHOLE] [--matcher exhaustive|sequential]``
runs SIFT feature extraction, feature matching and incremental mapping on the photos in IMAGES_DIR (one
camera shared by all) and writes ``OUT_DIR/images/`` (copies of the photos), ``OUT_DIR/sparse/0/`` (the
model with the most registered photos, binary) and ``OUT_DIR/database.db`` (features and matches). The
camera is a pinhole model, SIMPLE_PINHOLE (one focal length) or PINHOLE (fx, fy), so that the reader
takes it as is.

``python -m src.data.sfm --undistort SCENE_DIR OUT_DIR`` turns a model with lens distortion
(``SCENE_DIR/images`` + ``SCENE_DIR/sparse[/0]``, any COLMAP camera model, e.g. from the ``colmap`` GUI)
into undistorted PINHOLE photos and model: ``OUT_DIR/images``, ``OUT_DIR/sparse``.

Exit codes: 0 done; 2 for bad input, or a reconstruction that fails or registers fewer than
``--min-registered`` of the photos (one line on stderr saying how many of how many).
"""

from __future__ import annotations

import argparse
import filecmp
import math
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType

from src.data.base import DatasetError
from src.data.colmap import find_model, image_file, import_pycolmap, model_entries, read_model
from src.utils.record import OneLineParser, cli_error, os_error_line

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
MATCHERS = ("exhaustive", "sequential")


def say(message: str) -> None:
    """One progress line on stdout."""
    print(message, flush=True)


def list_photos(images_dir: Path) -> list[Path]:
    """The photos directly in ``images_dir`` (by suffix, case-insensitive), sorted by name; at least 2."""
    if not images_dir.is_dir():
        raise DatasetError(f"{images_dir}: not a directory of photos")
    photos = sorted(p for p in images_dir.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if len(photos) < 2:
        raise DatasetError(f"{images_dir}: {len(photos)} photo(s) ({', '.join(PHOTO_SUFFIXES)}); structure from "
                           "motion needs at least 2 of one scene")
    return photos


def photo_size(path: Path) -> tuple[int, int]:
    """(width, height) of a photo from its header; DatasetError if it cannot be read."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DatasetError(f"{path}: cannot read the photo ({oiio.geterror()})")
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


def check_one_camera(photos: list[Path]) -> None:
    """DatasetError unless every photo has the first one's size (one camera is fitted to all)."""
    first = photo_size(photos[0])
    for p in photos[1:]:
        size = photo_size(p)
        if size != first:
            raise DatasetError(f"{p}: {size[0]}x{size[1]} px, but {photos[0].name} is {first[0]}x{first[1]} px; one "
                               "camera is fitted to all photos, so they must share one size (one camera, one zoom)")


def check_out_dir(out: Path) -> None:
    """DatasetError if ``out`` already holds a model (never overwritten)."""
    for sub in ("sparse/0", "sparse"):
        if any((out / sub / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            raise DatasetError(f"{out / sub}: already holds a COLMAP model; choose another OUT_DIR or remove it")


def copy_photos(photos: list[Path], out: Path) -> Path:
    """``out/images`` holding ``photos`` (copied; kept as they are when the photos already lie there)."""
    target = out / "images"
    if photos[0].parent.resolve() == target.resolve():
        return target
    target.mkdir(parents=True, exist_ok=True)
    for p in photos:  # a re-run after a failed reconstruction finds its own copies
        if (target / p.name).exists() and not filecmp.cmp(p, target / p.name, shallow=False):
            raise DatasetError(f"{target / p.name}: exists and differs from {p}; choose an empty OUT_DIR")
    for p in photos:
        if not (target / p.name).exists():
            shutil.copy2(p, target / p.name)
    return target


def quiet_logs(pycolmap: ModuleType, verbose: bool) -> None:
    """COLMAP's own log lines: all of them with ``verbose``, else none but fatal ones (this module says
    what happened in its own lines)."""
    pycolmap.logging.minloglevel = 0 if verbose else 3


def extract(pycolmap: ModuleType, database: Path, images: Path, names: list[str], camera_model: str,
            threads: int) -> None:
    """SIFT features of ``names`` in ``images`` on the CPU, one camera of ``camera_model`` for all."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    options = pycolmap.FeatureExtractionOptions()
    options.use_gpu = False
    options.num_threads = threads
    pycolmap.extract_features(str(database), str(images), image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=options, device=pycolmap.Device.cpu)


def match(pycolmap: ModuleType, database: Path, matcher: str, threads: int) -> None:
    """SIFT matching and geometric verification on the CPU: every pair, or neighbours in name order."""
    options = pycolmap.FeatureMatchingOptions()
    options.use_gpu = False
    options.num_threads = threads
    run = pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential
    run(str(database), matching_options=options, device=pycolmap.Device.cpu)


def incremental_map(pycolmap: ModuleType, database: Path, images: Path, work: Path, threads: int) -> list:
    """The reconstructions of incremental mapping (pycolmap ``Reconstruction``s), most registered images first."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = 0
    models = pycolmap.incremental_mapping(str(database), str(images), str(work), options=options)
    return sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)


def needed(n_photos: int, min_registered: float) -> int:
    """How many of ``n_photos`` must be registered: ``ceil(min_registered * n)``, at least 2."""
    return max(2, math.ceil(min_registered * n_photos - 1e-9))


def run_sfm(images_dir: Path, out: Path, camera_model: str = "SIMPLE_PINHOLE", matcher: str = "exhaustive",
            threads: int = -1, min_registered: float = 0.8, verbose: bool = False) -> Path:
    """Photos in ``images_dir`` to ``out/{images, sparse/0}`` (module docstring); returns the model folder.

    Raises:
        DatasetError for bad input, a failed reconstruction, or fewer than ``min_registered`` (a fraction)
        of the photos registered; no model is written then.
    """
    pycolmap = import_pycolmap()
    quiet_logs(pycolmap, verbose)
    photos = list_photos(images_dir)
    check_one_camera(photos)
    check_out_dir(out)
    images = copy_photos(photos, out)
    names = [p.name for p in photos]
    database = out / "database.db"
    if database.exists():
        database.unlink()  # a previous attempt's features and matches: extracted afresh
    say(f"[1/3] SIFT features of {len(names)} photos on the CPU ({camera_model}, one camera)")
    extract(pycolmap, database, images, names, camera_model, threads)
    say(f"[2/3] {matcher} matching")
    match(pycolmap, database, matcher, threads)
    say("[3/3] incremental mapping")
    with tempfile.TemporaryDirectory(dir=out, prefix=".mapping-") as work:
        models = incremental_map(pycolmap, database, images, Path(work), threads)
        registered = models[0].num_reg_images() if models else 0
        need = needed(len(names), min_registered)
        if registered < need:
            what = (f"registered {registered} of {len(names)} photos in its largest model" if models
                    else f"registered none of the {len(names)} photos (no model)")
            raise DatasetError(f"{images_dir}: the reconstruction failed: it {what}, {need} needed "
                               f"(--min-registered {min_registered:g}); no model written. Photos need overlap "
                               "(each scene point in 3+ photos), texture and sharpness"
                               + ("; try --matcher exhaustive" if matcher != "exhaustive" else "")
                               + "; --verbose shows COLMAP's log")
        folder = out / "sparse" / "0"
        folder.mkdir(parents=True, exist_ok=True)
        models[0].write_binary(str(folder))
    best = models[0]
    say(f"registered {registered} of {len(names)} photos, {best.num_points3D()} 3D points, mean reprojection error "
        f"{best.compute_mean_reprojection_error():.2f} px" + (f"; {len(models) - 1} smaller model(s) dropped"
                                                              if len(models) > 1 else ""))
    say(f"model: {folder}")
    say(f"train: python -m src.run +experiment=gs3d dataset=colmap dataset.root={out} init=sfm dataset.n_views=3")
    return folder


def undistort(scene: Path, out: Path, threads: int = -1, verbose: bool = False) -> Path:
    """Undistorted PINHOLE photos and model of ``scene`` (images/ + sparse[/0]) in ``out/{images, sparse}``."""
    pycolmap = import_pycolmap()
    quiet_logs(pycolmap, verbose)
    folder, ext = find_model(scene)
    rec = read_model(folder, ext)
    entries = model_entries(rec, str(folder / f"images{ext}"))
    for e in entries:
        image_file(scene, "images", e, str(folder / f"images{ext}"))
    check_out_dir(out)
    if (out / "images").exists():
        raise DatasetError(f"{out / 'images'}: already exists; choose an empty OUT_DIR")
    say(f"undistorting {len(entries)} photos of {folder}")
    pycolmap.undistort_images(str(out), str(folder), str(scene / "images"), output_type="COLMAP",
                              num_threads=threads)
    say(f"model: {out / 'sparse'} (PINHOLE), photos: {out / 'images'}")
    say(f"train: python -m src.run +experiment=gs3d dataset=colmap dataset.root={out} init=sfm dataset.n_views=3")
    return out / "sparse"


def parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="python -m src.data.sfm",
                      description="Photos to a COLMAP sparse model (pycolmap, CPU), the layout dataset=colmap reads.")
    p.add_argument("source", type=Path, help="folder of photos (with --undistort: a scene with images/ and sparse/)")
    p.add_argument("out", type=Path, help="output folder: images/ and sparse/0/ (sparse/ with --undistort)")
    p.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_PINHOLE",
                   help="one camera for all photos (default: SIMPLE_PINHOLE, one focal length)")
    p.add_argument("--matcher", choices=MATCHERS, default="exhaustive",
                   help="exhaustive: every pair (default); sequential: neighbours in name order (videos)")
    p.add_argument("--min-registered", type=float, default=0.8,
                   help="fail unless at least this fraction of the photos is registered (default: 0.8)")
    p.add_argument("--threads", type=int, default=-1, help="CPU threads (default: all)")
    p.add_argument("--undistort", action="store_true", help="undistort the model in SOURCE instead (any camera model)")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's own log lines")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if not 0.0 < args.min_registered <= 1.0:
        return cli_error(f"--min-registered={args.min_registered:g}: expected a fraction in (0, 1]")
    try:
        if args.undistort:
            undistort(args.source, args.out, args.threads, args.verbose)
        else:
            run_sfm(args.source, args.out, args.camera_model, args.matcher, args.threads, args.min_registered,
                    args.verbose)
    except DatasetError as e:
        return cli_error(str(e))
    except OSError as e:
        return cli_error(os_error_line(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
