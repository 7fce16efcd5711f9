#!/usr/bin/env bash
# The project's CUDA path on a GPU machine, in one go (about 6 minutes on one H100 or H200, gsplat's first
# JIT build included): gsplat parity tests, the default command against 3DGS, Mip-Splatting, Mip-Splatting +
# DropGaussian and 2DGS (full runs, wall time, one at a time), smoke runs of every static and 4D method and
# sparse-view ingredient on the GPU, the training and rasterizer benchmarks (CUDA_CHECK_BENCH=0 skips them).
#   pip install -r requirements-lock.txt -e ".[dev,cuda]"   # then:
#   bash tools/cuda_check.sh [OUT_DIR]                      # default outputs/cuda_check
# Each step's failure is reported and the next step runs; the exit code counts the failed steps.
set -u
out="${1:-outputs/cuda_check}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1
failed=0
step() {  # step NAME COMMAND...: run, report its time and exit code
  local name="$1"; shift
  local t0=$SECONDS
  echo "=== $name"
  "$@" || { echo "--- $name failed (exit $?)"; failed=$((failed + 1)); }
  echo "--- $name: $((SECONDS - t0)) s"
}
python -c "import torch; assert torch.cuda.is_available(), 'no CUDA GPU'; print(torch.__version__, torch.cuda.get_device_name())" || exit 2
step "gsplat build" python -c "from gsplat.cuda._backend import _C; assert _C is not None"
step "gsplat parity tests" python -m pytest -q -p no:cacheprovider tests/test_rasterizer_gsplat.py -rs
step "full run 3DGS" python -m src.run +experiment=gs3d device=cuda "hydra.run.dir=$out/gs3d"
step "full run, the main job" python -m src.run device=cuda "hydra.run.dir=$out/main" "paths.stage1_dir=$out/stage1"
for e in mip_splatting gs2d; do  # gs2d: gsplat's 2DGS path with its own distortion weight (loss.lambda_dist_l1)
  step "full run $e" python -m src.run "+experiment=$e" device=cuda "hydra.run.dir=$out/$e"
done
# the strongest other method on the shipped scenes at 2x the tables' budget (3 000 iterations, its schedule scaled with
# it: schedule.budget_scale); on validation views it chooses 4 500 at 8 views (docs/results.md), kept at 3 000
# here so the check stays short and its CPU reference (CPU_PSNR below) stays the recorded one
step "full run Mip-Splatting + DropGaussian, 3 000 iterations" python -m src.run +experiment=mip_splatting sparse=dropout \
  schedule.budget_scale=2 device=cuda "hydra.run.dir=$out/mip_dropout_x2"
# Smoke runs after the timed full runs, six at a time (each its own process on the one GPU)
smoke() {  # smoke NAME OVERRIDES...: a 20-iteration run, its log in $out/smoke_NAME.log
  local name="$1"; shift
  python -m src.run "$@" +ci=smoke device=cuda "hydra.run.dir=$out/smoke_$name" \
    "paths.stage1_dir=$out/stage1_smoke_$name" >"$out/smoke_$name.log" 2>&1 \
    && echo "smoke $name: ok" || { echo "--- smoke $name failed (log: $out/smoke_$name.log)"; tail -n 5 "$out/smoke_$name.log"; return 1; }
}
t0=$SECONDS
echo "=== smoke runs"
pids=()
for e in splatfields3d_mip gs3d gs3d_moran mip_splatting gs2d lightgaussian scaffold_gs sugar dropgaussian binocular3dgs \
    corgs owl_4view deformable3dgs gaussians4d gs4d; do
  smoke "$e" "+experiment=$e" & pids+=($!)
  while [ "$(jobs -rp | wc -l)" -ge 6 ]; do sleep 1; done
done
for s in dropout_decay binocular corgs; do  # the sparse-view ingredients on Mip-Splatting
  smoke "mip_$s" +experiment=mip_splatting "sparse=$s" & pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid" || failed=$((failed + 1)); done
echo "--- smoke runs: $((SECONDS - t0)) s"
[ "${CUDA_CHECK_BENCH:-1}" = 0 ] || {
step "training benchmark" python -m src.bench training --device cuda --methods gs3d,splatfields3d_mip,owl_4view \
  --sizes 10000,50000 --out "$out/training.json"
step "rasterizer benchmark" python -m src.bench rasterizer --quick --out "$out/rasterizer.json" \
  --chart "$out/rasterizer.png"
}
# The full runs' test PSNR against the CPU kernel's on the same scene and seed (docs/benchmarks.md, "On CUDA"):
# more than 1 dB below it counts as a failed step.
python - "$out" <<'PY' || failed=$((failed + $?))
import json, sys
from pathlib import Path
CPU_PSNR = {"gs3d": 19.64, "main": 20.13, "mip_splatting": 20.38, "gs2d": 17.93, "mip_dropout_x2": 20.48}
low = 0
for p in sorted(Path(sys.argv[1]).glob("*/metrics.json")):
    m = json.loads(p.read_text())
    mt = m.get("metrics", {})
    psnr, ref = mt.get("psnr"), CPU_PSNR.get(p.parent.name)
    flag = ""
    if ref is not None and (m.get("status") != "ok" or psnr is None or psnr < ref - 1.0):
        flag, low = f"  <-- more than 1 dB below the CPU run's {ref:.2f}", low + 1
    print(f"{p.parent.name:<28} {m.get('status'):<8} {m.get('rasterizer') or '-':<10} wall {m.get('wall_s') or 0:7.1f} s"
          f"  PSNR {psnr or float('nan'):6.2f}  {m.get('error') or ''}{flag}")
sys.exit(low)
PY
echo "failed steps: $failed"
exit "$failed"
