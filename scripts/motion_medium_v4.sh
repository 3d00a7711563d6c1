#!/usr/bin/env bash
# Issue 41 on the whole `medium` v4 (24 train motions per subject, 6x the quarter v3 the earlier tries
# had): POP with the last 2 s of motion against a pose-only control given the same recipe and the
# same clock, both fine-tuned from the shipped `default:pop`. The control tells what the window adds
# from what more training on the same frames does (docs/lab/motion.md: on the quarter v3 a long
# fine-tune's gain was the training, not the window). Each model is scored on the standard frames
# (28 x 2 seeds, 2,048 points, both splits), the motion model with each frame's own window, none
# (rest) and another frame's of the same subject (shuffled), and paired per frame
# (benchmarks/motion_gain.py) against the control and the shipped POP. Rerun to resume.
#
#   bash scripts/motion_medium_v4.sh              # POP ~1 h on a 2-core CPU after the data, then PocoLoco's long run
#   POCOLOCO=0 bash scripts/motion_medium_v4.sh   # POP only
#
# Needs `bash scripts/setup.sh` and the whole `medium` v4:
#   pocoloco data synth --preset medium --workers 2 --frame-storage compact --train-sequences 24 --out $DATA
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
RUNS=${RUNS:-$HOME/.cache/pocoloco/runs}
OUT=${OUT:-$RUNS/v4motion}
DATA=${DATA:-$HOME/.cache/pocoloco/data/medium_v4_eval}
MINUTES=${MINUTES:-40}        # each fine-tune's clock (both run side by side, one thread each)
SCALE=${SCALE:-30}            # the motion encoder's learning rate in multiples of the trunk's
mkdir -p "$OUT"

fine_tune() {  # fine_tune RUN TRAIN_ARGS...: from the shipped POP, on the clock, cooled down (wsd)
  local run=$1; shift
  [ -d "$run/model" ] && return 0
  local again=(); [ -f "$run/checkpoints/latest" ] && again=(--resume)
  nice $PL train --model pop --data "$DATA" --init-from default:pop --lr 1e-4 "$@" --out "$run" "${again[@]}" \
    --lr-schedule wsd --steps 100000 --decay-steps 30000 --time-budget "$MINUTES" --ckpt-every 250 \
    --sample-every 0 --threads 1 > "$run.log" 2>&1
}
fine_tune "$OUT/pop_control" &
A=$!
fine_tune "$OUT/pop_motion" --motion-window 2.0 --motion-lr-scale "$SCALE" &
B=$!
wait $A $B

quality() {  # quality NAME CKPT [ARGS...]: both splits, the standard frames and seeds
  local name=$1 ckpt=$2; shift 2
  for split in test heldout; do
    [ -f "$OUT/quality_$name/$split/quality.json" ] || $PL bench quality --data "$DATA" --split "$split" \
      --frames 28 --seeds 0 1 --points 2048 --ckpt-pop "$ckpt" "$@" --out "$OUT/quality_$name/$split"
  done
}
quality shipped default:pop
quality control "$OUT/pop_control"
for history in dataset rest shuffled; do quality "motion_$history" "$OUT/pop_motion" --history "$history"; done

for split in test heldout; do
  q() { echo "$OUT/quality_$1/$split/quality.json:pop"; }
  for ref in control shipped; do
    $PY benchmarks/motion_gain.py --reference "$(q $ref)" --dataset "$(q motion_dataset)" --rest "$(q motion_rest)" \
      --shuffled "$(q motion_shuffled)" --peer "$(q shipped)" --json "$OUT/gain_${split}_pop_vs_$ref.json" \
      > "$OUT/gain_${split}_pop_vs_$ref.md"
  done
done
echo "motion_medium_v4: POP done ($OUT)"
[ "${POCOLOCO:-1}" = 1 ] || exit 0

# PocoLoco with the window, from the shipped `default`: a long CPU run (POCO_MINUTES of training in
# all, resumed across sessions by rerunning this script), the trunk at a third of the v4 fine-tune's
# learning rate (the GPU runs on the quarter v3 over-fitted it) and the zero-initialised encoder at
# 10x. Scored against the shipped default; `shuffled` and `rest` tell the window from more training.
run=$OUT/pocoloco_motion
if [ ! -d "$run/model" ]; then
  again=(); [ -f "$run/checkpoints/latest" ] && again=(--resume)
  nice $PL train --data "$DATA" --init-from default --motion-window 2.0 --motion-lr-scale 10 --batch-size 32 \
    --lr 1e-4 --lr-schedule wsd --steps 100000 --decay-steps 20000 --time-budget "${POCO_MINUTES:-240}" \
    --ckpt-every 100 --sample-every 0 --threads "${POCO_THREADS:-2}" --out "$run" "${again[@]}" >> "$run.log" 2>&1
fi
pquality() {  # pquality NAME CKPT [ARGS...]
  local name=$1 ckpt=$2; shift 2
  for split in test heldout; do
    [ -f "$OUT/pquality_$name/$split/quality.json" ] || $PL bench quality --data "$DATA" --split "$split" \
      --frames 28 --seeds 0 1 --points 2048 --ckpt-pocoloco "$ckpt" "$@" --out "$OUT/pquality_$name/$split"
  done
}
pquality shipped default
for history in dataset rest shuffled; do pquality "motion_$history" "$run" --history "$history"; done
for split in test heldout; do
  q() { echo "$OUT/pquality_$1/$split/quality.json:pocoloco"; }
  $PY benchmarks/motion_gain.py --reference "$(q shipped)" --dataset "$(q motion_dataset)" --rest "$(q motion_rest)" \
    --shuffled "$(q motion_shuffled)" --peer "$OUT/quality_shipped/$split/quality.json:pop" \
    --json "$OUT/gain_${split}_pocoloco_vs_shipped.json" > "$OUT/gain_${split}_pocoloco_vs_shipped.md"
done
echo "motion_medium_v4: done ($OUT)"
