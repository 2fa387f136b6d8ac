#!/bin/bash
# The measured LIBERO-Spatial result (docs/results.md, "LIBERO"): expert demos -> default policy -> fixed
# and AURD on every task. Hours of CPU; every stage resumes where it stopped, so run it again (e.g. under
# nohup) after an interruption:  nohup bash scripts/libero-spatial.sh > runs/libero/log 2>&1 &
#   collect: 20 expert demos per task, official init states from 0 (the files list the states used)
#   train:   the default policy, 3000 x 32 steps, proprio without the wrapping roll angle
#   eval:    10 episodes per task and executor from init states 30-39, task by task (paired partial results)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-runs/libero}
PIVLA=${PIVLA:-.venv/bin/pivla}
THREADS=${THREADS:-2}
export MUJOCO_GL=${MUJOCO_GL:-egl}
mkdir -p "$OUT/data"

for t in 0 1 2 3 4 5 6 7 8 9; do
  [ -f "$OUT/data/.done_t$t" ] && continue
  OMP_NUM_THREADS=1 "$PIVLA" collect --env libero --suite libero_spatial --tasks "$t" --episodes 20 \
    --image-size 96 --seed 0 --out "$OUT/data"
  touch "$OUT/data/.done_t$t"
done

if ! grep -q '"done": true' "$OUT/policy/status.json" 2>/dev/null; then
  RESUME=()
  [ -d "$OUT/policy/checkpoints" ] && RESUME=(--resume)
  "$PIVLA" train "${RESUME[@]}" --data "$OUT/data" --out "$OUT/policy" --steps 3000 --batch-size 32 \
    --val-fraction 0.05 --eval-every 500 --ckpt-every 250 --value-refresh-every 500 --warmup 150 \
    --threads "$THREADS" --model.proprio_keys ee_pos,gripper_states --model.proprio_dim 5 --progress false
fi

[ -f "$OUT/policy/calibration.json" ] || "$PIVLA" calibrate --policy "$OUT/policy" --data "$OUT/data" --held-out \
  > "$OUT/calibration_stats.json"

for t in 0 1 2 3 4 5 6 7 8 9; do
  for ex in fixed aurd; do
    "$PIVLA" eval --policy "$OUT/policy" --env libero --suite libero_spatial --tasks "$t" --executor "$ex" \
      --episodes 10 --first-init-state 30 --seed 1000 --workers 1 --videos 1 --out "$OUT/eval/$ex" 2>/dev/null | tail -1
  done
done
