#!/usr/bin/env bash
# Issue 42, the set-level loss: does scoring each frame's draws as a set (the energy score of the
# judge's probe embedding, `distill --set-weight`) give back the spread the shipped student lost
# (0.72 of its teacher ODE's) and close its proper-score gap? A paired pilot at equal wall-clock:
# every arm goes on from the shipped `default:fast` on the same new teacher pairs (256 training
# frames x 4 draws each), one thread each, side by side: `set10` and `set30` with the set term at
# weight 10 and 30 (at weight 1 its gradient is ~0.06x the per-point terms'), `plain` without.
# Then each is judged on the v4 standard test reference set and scored by `bench quality` (4 calls).
#
#   bash scripts/fast_set_pilot.sh                   # 50 min per arm, the three at once on 2 cores
#   MINUTES=90 bash scripts/fast_set_pilot.sh
#   ARMS="set20:20" THREADS=2 MINUTES=75 bash scripts/fast_set_pilot.sh   # one arm alone, two threads
#
# Needs the whole `medium` v4 in $DATA and its standard test reference set in $REFS (see
# scripts/fast_medium_v4.sh). Every step skips what is done; rerun to go on.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
DATA=${DATA:-$HOME/.cache/pocoloco/data/medium_v4_eval}
REFS=${REFS:-$HOME/.cache/pocoloco/data/medium_v4_std_test}
REFS_HELDOUT=${REFS_HELDOUT:-$HOME/.cache/pocoloco/data/medium_v4_std_heldout}
OUT=${OUT:-$HOME/.cache/pocoloco/runs/fast_set}
MINUTES=${MINUTES:-50}
read -r -a ARMS <<< "${ARMS:-set10:10 set30:30 plain:0}"  # NAME:WEIGHT ...
THREADS=${THREADS:-1}
PAIRS=(--pairs 1024 --draws-per-frame 4 --seed 1)
mkdir -p "$OUT"

# 1. the teacher pairs, once (a one-step run makes them), shared by both arms
if [ ! -f "$OUT/pairs_run/model/meta.json" ]; then
  again=(); [ -d "$OUT/pairs_run/pairs" ] && again=(--resume)
  nice $PL distill --ckpt default --data "$DATA" --out "$OUT/pairs_run" --init-from default:fast "${PAIRS[@]}" \
    --steps 1 --threads 2 "${again[@]}" >> "$OUT/pairs.log" 2>&1
fi
# 2. the two arms, side by side
arm() {  # arm NAME WEIGHT
  local run=$OUT/$1 again=()
  [ -f "$run/model/meta.json" ] && return 0
  if [ -d "$run/checkpoints" ]; then again=(--resume); else mkdir -p "$run"; cp -rn "$OUT/pairs_run/pairs" "$run/"; fi
  nice $PL distill --ckpt default --data "$DATA" --out "$run" --init-from default:fast "${PAIRS[@]}" \
    --set-weight "$2" --steps 100000 --batch-size 16 --lr 1e-4 --renoised-share 0.5 --time-budget "$MINUTES" \
    --threads "$THREADS" "${again[@]}" >> "$run.log" 2>&1
}
for a in "${ARMS[@]}"; do arm "${a%%:*}" "${a##*:}" & done
wait
NAMES=("${ARMS[@]%%:*}")
for a in "${NAMES[@]}"; do
  [ -f "$OUT/fast_$a/meta.json" ] || $PL export-model --ckpt "$OUT/$a/checkpoints" --dtype int8 --polish-with default \
    --out "$OUT/fast_$a"
done
# 3. the judge (the test reference set, then the held-out one if it is there), then quality at 4 calls on both splits
for a in "${NAMES[@]}"; do
  [ -f "$OUT/judge_$a/distribution.json" ] || $PL bench distribution --refs "$REFS" --ckpt-pocoloco "$OUT/fast_$a" \
    --out "$OUT/judge_$a"
done
for a in "${NAMES[@]}"; do
  for split in test heldout; do
    [ -f "$OUT/quality_$a/$split/quality.json" ] || $PL bench quality --data "$DATA" --split "$split" --frames 28 \
      --seeds 0 1 --points 2048 --ckpt-pocoloco "$OUT/fast_$a" --threads 2 --out "$OUT/quality_$a/$split"
  done
done
for a in "${NAMES[@]}"; do
  [ -d "$REFS_HELDOUT" ] && { [ -f "$OUT/judge_heldout_$a/distribution.json" ] || $PL bench distribution \
    --refs "$REFS_HELDOUT" --ckpt-pocoloco "$OUT/fast_$a" --out "$OUT/judge_heldout_$a"; }
done
echo "fast_set_pilot: done ($OUT)"
