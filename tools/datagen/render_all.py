"""Regenerate the project's rendered datasets under data/ (run inside .venv-datagen).

    .venv-datagen/bin/python tools/datagen/render_all.py [--only static/plant ...] [--out data]
    .venv-datagen/bin/python tools/datagen/render_all.py --only heldout/totem heldout/teaset --out /tmp/heldout
    .venv-datagen/bin/python tools/datagen/render_all.py --only static/plant --res 200 --out /tmp/data200

Use tools/datagen/generate.sh for the full, one-command regeneration.
"""

from __future__ import annotations

import argparse
import functools
import json
import shutil
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import static_scenes  # noqa: E402

JOBS = {f"static/{n}": functools.partial(static_scenes.render_static, n) for n in static_scenes.STATIC_SCENES}

import dynamic_scenes  # noqa: E402

JOBS.update(dynamic_scenes.JOBS)
JOBS["formats/dtu_neus/trinkets"] = lambda out, limit: static_scenes.render_dtu("trinkets", out, limit)

import capture_scenes  # noqa: E402
import heldout_scenes  # noqa: E402

# Held-out scenes: rendered only when named (--only heldout/NAME, dynamic_mv/mocap_trial3), never part of the
# shipped data/.
HELDOUT_JOBS = {
    f"heldout/{n}": functools.partial(static_scenes.render_static, n, builders=heldout_scenes.HELDOUT_SCENES,
                                      group="heldout")
    for n in heldout_scenes.HELDOUT_SCENES
}
HELDOUT_JOBS.update(dynamic_scenes.HELDOUT_JOBS)
# Photo captures: rendered only when named (--only captures/room); their COLMAP model is built afterwards, in the
# project's environment, by `python -m src.data.sfm data/captures/room/images data/captures/room`.
CAPTURE_JOBS = dict(capture_scenes.JOBS)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=HERE.parent.parent / "data")
    ap.add_argument("--only", nargs="*", default=None, help="job names, e.g. static/plant")
    ap.add_argument("--limit", type=int, default=None, help="debug: at most this many views per split")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--stats", type=Path, default=None, help="write per-job timings as JSON here")
    ap.add_argument("--res", type=int, default=None,
                    help="image width = height in px of the static, held-out and dynamic scenes (default: common.RES, "
                         "the shipped data's 100; the DTU-format job keeps its own size); the cameras keep their "
                         "field of view, so the focal length in px scales with it. Needs --out: never over the "
                         "shipped data")
    args = ap.parse_args(argv)
    if args.res is not None:
        import common

        if args.res < 8:
            ap.error(f"--res {args.res}: expected an image size of at least 8 px")
        if args.res != common.RES and args.out.resolve() == (HERE.parent.parent / "data").resolve():
            ap.error(f"--res {args.res}: name an --out directory; data/ holds the shipped {common.RES} px scenes")
        common.RES = args.res
    if args.list:
        print("\n".join([*JOBS, *(f"{n}  (held out: only when named)" for n in HELDOUT_JOBS),
                         *(f"{n}  (photo capture: only when named)" for n in CAPTURE_JOBS)]))
        return
    jobs = {**JOBS, **HELDOUT_JOBS, **CAPTURE_JOBS}
    names = args.only or list(JOBS)
    unknown = [n for n in names if n not in jobs]
    if unknown:
        ap.error(f"unknown job(s) {unknown}; --list names them")
    stats = []
    for name in names:
        t0 = time.time()
        # render into a staging tree, then swap it in, so readers never see a half-written scene
        staging = args.out / ".staging"
        if (staging / name).exists():
            shutil.rmtree(staging / name)
        print(f"[datagen] {name} ...", flush=True)
        st = jobs[name](staging, args.limit)
        dst = args.out / name
        if dst.exists():
            shutil.rmtree(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        (staging / name).rename(dst)
        st["wall_s"] = round(time.time() - t0, 2)
        st["render_s"] = round(st.get("render_s", 0.0), 2)
        if st.get("images"):
            st["s_per_image"] = round(st["render_s"] / st["images"], 3)
        print(f"[datagen] {name}: {json.dumps(st)}", flush=True)
        stats.append(st)
    shutil.rmtree(args.out / ".staging", ignore_errors=True)
    if args.stats:
        args.stats.write_text(json.dumps(stats, indent=2) + "\n")
    return stats


if __name__ == "__main__":
    main()
