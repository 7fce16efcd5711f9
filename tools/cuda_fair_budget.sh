#!/usr/bin/env bash
# sweeps/fair_budget.yaml on one CUDA GPU, several sweeps at once: each argument is one lane's overrides, run as
# its own process (at 100 px a run is bound by kernel launches, so lanes share the GPU; their times are not
# single-run timings). Then the leaderboard over every lane.
#   bash tools/cuda_fair_budget.sh OUT_DIR "+experiment=mip_splatting sparse=dropout schedule.budget_scale=4" ...
# Sweep dirs OUT_DIR/lane_N, first stages under OUT_DIR/stage1, the leaderboard in OUT_DIR/board.
# CUDA_LANE_TIMEOUT (seconds, default none) stops a lane that runs longer; its finished runs stay and its
# unfinished one is listed as such. The exit code counts the lanes that failed or were stopped.
set -u
out="${1:?usage: cuda_fair_budget.sh OUT_DIR LANE_OVERRIDES...}"; shift
mkdir -p "$out"
export PYTHONUNBUFFERED=1
limit=()
[ -n "${CUDA_LANE_TIMEOUT:-}" ] && limit=(timeout "$CUDA_LANE_TIMEOUT")
pids=()
n=0
t0=$SECONDS
for lane in "$@"; do
  # shellcheck disable=SC2086  # a lane's overrides are split on spaces on purpose
  "${limit[@]}" python -m src.run -cd sweeps -cn fair_budget $lane device=cuda "paths.output_root=$out" \
    "hydra.sweep.dir=$out/lane_$n" >"$out/lane_$n.log" 2>&1 &
  pids+=($!)
  echo "lane $n: $lane"
  n=$((n + 1))
done
failed=0
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || { echo "--- lane $i failed or was stopped (exit $?; log $out/lane_$i.log)"; failed=$((failed + 1)); }
done
echo "--- lanes: $((SECONDS - t0)) s"
# the equal-time column is read at the main job's time (its label at 4 views: DropGaussian in its second stage)
python -m src.tables "$out"/lane_*/ --leaderboard --reference "${CUDA_BOARD_REFERENCE:-splatfields3d_mip + dropout_few_views}" \
  --out "$out/board" || failed=$((failed + 1))
exit "$failed"
