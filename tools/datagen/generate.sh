#!/usr/bin/env bash
# One command to regenerate every shipped dataset under data/ (deterministic).
#   bash tools/datagen/generate.sh            # everything
#   bash tools/datagen/generate.sh --only static/plant dynamic_mv/flag
# Steps: (1) set up .venv-datagen (bpy==5.0.1), (2) render all scenes with Cycles on the CPU,
# (3) re-render a few images into a temp dir and check they are byte-identical to the new ones,
# (4) check ground-truth points against the alpha masks, (5) print the wall time.
set -euo pipefail
T0=$(date +%s.%N)
REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$REPO_ROOT"
VPY="${DATAGEN_VENV:-$REPO_ROOT/.venv-datagen}/bin/python"
OUT="${DATAGEN_OUT:-$REPO_ROOT/data}"
STATS="$(mktemp -t splatfields_datagen_stats.XXXXXX.json)"

bash tools/datagen/setup_env.sh

# Blender prints one progress line per render tile; keep only our own lines.
set +e
"$VPY" tools/datagen/render_all.py --out "$OUT" --stats "$STATS" "$@" 2>&1 \
    | grep --line-buffered -E '^\[datagen\]|Error|Traceback|^  File'
rc=${PIPESTATUS[0]}
set -e
[ "$rc" -eq 0 ] || { echo "[datagen] render_all.py failed (exit $rc)" >&2; exit "$rc"; }

if [ "$#" -eq 0 ]; then
    if [ -f tools/datagen/formats.py ]; then "$VPY" tools/datagen/formats.py --data "$OUT"; fi
    # determinism: re-render the first view of every split of two scenes (and their ground-truth
    # points and meshes) in a fresh process and compare bytes with what was just written
    TMP="$(mktemp -d -t splatfields_datagen_check.XXXXXX)"
    "$VPY" tools/datagen/render_all.py --out "$TMP" --only static/plant dynamic_mono/bouncing --limit 1 >/dev/null 2>&1
    n_same=0
    for f in static/plant/{train,val,test}/r_0.png static/plant/gt_{points,mesh}.npz \
             dynamic_mono/bouncing/{train,val,test}/r_000.png dynamic_mono/bouncing/gt_{points,mesh}.npz; do
        if cmp -s "$TMP/$f" "$OUT/$f"; then
            n_same=$((n_same + 1))
        else
            echo "[datagen] determinism: FAILED, re-rendered $f differs" >&2
            exit 1
        fi
    done
    echo "[datagen] determinism: $n_same re-rendered files (6 PNGs, 2 gt_points.npz, 2 gt_mesh.npz) are byte-identical"
    rm -rf "$TMP"
    "$VPY" tools/datagen/verify.py "$OUT"
fi
if [ -s "$STATS" ]; then
    "$VPY" - "$STATS" <<'PYEOF'
import json, sys
rows = json.load(open(sys.argv[1]))
tot_img = sum(r.get("images", 0) for r in rows)
tot_s = sum(r["render_s"] for r in rows)
for r in rows:
    print(f"[datagen]   {r['kind']:>16s}/{r['scene']:<13s} {r['images']:4d} images  "
          f"render {r['render_s']:7.1f} s  ({r.get('s_per_image', 0):.3f} s/image)")
print(f"[datagen] rendered {tot_img} images in {tot_s:.1f} s ({tot_s / max(tot_img, 1):.3f} s/image)")
PYEOF
fi
rm -f "$STATS"
echo "[datagen] data size: $(du -sh --apparent-size "$OUT" | cut -f1)  files: $(find "$OUT" -type f | wc -l)"
T1=$(date +%s.%N)
echo "[datagen] total wall time: $(python3 -c "print(f'{$T1 - $T0:.1f}')") s"
