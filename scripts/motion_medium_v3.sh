#!/usr/bin/env bash
# Issue 41 on `medium` v3: fine-tune the shipped PocoLoco and POP with the last 2 s of motion
# (--motion-window 2.0, from their shipped pose-only weights, on a clock), then score them with each
# frame's own window, none (rest) and another frame's (shuffled), and compare with the shipped
# pose-only models on the same frames (benchmarks/motion_gain.py, paired per frame). Every step
# resumes where a killed run stopped (with the time budget it had left; a finished run is kept): rerun the script.
#
#   bash scripts/motion_medium_v3.sh       # ~2 h on a 2-core CPU (needs CLOTH=v3 scripts/finetune_medium.sh's data
#                                          # and its quality_finetuned reports of the shipped models)
#
# Needs `bash scripts/setup.sh` first.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
RUNS=${RUNS:-$HOME/.cache/pocoloco/runs}
OUT=$RUNS/v3motion
DATA=${DATA:-$HOME/.cache/pocoloco/data/medium_v3}
SHIPPED=${SHIPPED:-$RUNS/v3/quality_finetuned}   # the shipped models' bench quality (finetune_medium.sh (CLOTH=v3))
MIN_POCOLOCO=${MIN_POCOLOCO:-80}
MIN_POP=${MIN_POP:-35}
mkdir -p "$OUT"

# 1. every sequence's whole motion (data synth writes it for new datasets)
$PL data motion-history "$DATA"

# 2. the fine-tunes, side by side, one thread each (the PocoLoco run measured in docs/lab/motion.md was
#    stopped by hand at step 1,000, 62 min in, when a probe showed its samples did not move with the window)
resume() { [ -f "$1/checkpoints/latest" ] && echo --resume || true; }
[ -d "$OUT/pocoloco/model" ] || nice $PL train --data "$DATA" --init-from default --motion-window 2.0 --out "$OUT/pocoloco" $(resume "$OUT/pocoloco") \
  --batch-size 32 --lr 3e-4 --lr-schedule wsd --steps 100000 --decay-steps 30000 --time-budget "$MIN_POCOLOCO" \
  --ckpt-every 250 --sample-every 0 --threads 1 > "$OUT/pocoloco.log" 2>&1 &
POCO=$!
[ -d "$OUT/pop/model" ] || nice $PL train --model pop --data "$DATA" --init-from default:pop --motion-window 2.0 --out "$OUT/pop" $(resume "$OUT/pop") \
  --lr 1e-4 --lr-schedule wsd --steps 100000 --decay-steps 30000 --time-budget "$MIN_POP" \
  --ckpt-every 250 --sample-every 0 --threads 1 > "$OUT/pop.log" 2>&1 &
POP=$!
wait $POCO $POP

# 2b. the PocoLoco pilots from it: the motion encoder's learning rate x10 and x30, EMA 0.995, 30 min each
for scale in 10 30; do
  run=$OUT/pilot_lr$scale
  [ -d "$run/model" ] || nice $PL train --data "$DATA" --init-from "$OUT/pocoloco" --motion-window 2.0 --motion-lr-scale $scale \
    --ema-decay 0.995 --out "$run" $(resume "$run") --batch-size 32 --lr 3e-4 --lr-schedule wsd --steps 100000 \
    --decay-steps 30000 --time-budget 30 --ckpt-every 100 --sample-every 0 --threads 1 \
    > "$run.log" 2>&1 &
done
wait

# 3. each motion-aware model with each kind of window, the standard frames and seeds
bench() {  # bench NAME KIND HISTORY: the run $OUT/NAME, a --ckpt-KIND row, both splits
  for split in test heldout; do
    [ -f "$OUT/quality_$1_$3/$split/quality.json" ] || $PL bench quality --data "$DATA" --split "$split" \
      --frames 28 --seeds 0 1 --points 2048 "--ckpt-$2" "$OUT/$1" --history "$3" --out "$OUT/quality_$1_$3/$split"
  done
}
for history in dataset shuffled rest; do bench pop pop $history; done
for run in pilot_lr10 pilot_lr30; do for history in dataset rest; do bench $run pocoloco $history; done; done

# 4. paired against the shipped pose-only models
for split in test heldout; do
  q() { echo "$OUT/quality_$1_$2/$split/quality.json:$3"; }
  $PY benchmarks/motion_gain.py --reference "$SHIPPED/$split/quality.json:pop" --dataset "$(q pop dataset pop)" \
    --rest "$(q pop rest pop)" --shuffled "$(q pop shuffled pop)" --peer "$SHIPPED/$split/quality.json:pop" \
    --json "$OUT/gain_${split}_pop.json" > "$OUT/gain_${split}_pop.md"
  for run in pilot_lr10 pilot_lr30; do
    $PY benchmarks/motion_gain.py --reference "$SHIPPED/$split/quality.json:pocoloco" \
      --dataset "$(q $run dataset pocoloco)" --rest "$(q $run rest pocoloco)" --peer "$SHIPPED/$split/quality.json:pop" \
      --json "$OUT/gain_${split}_pocoloco_${run#pilot_}.json" > "$OUT/gain_${split}_pocoloco_${run#pilot_}.md"
  done
done
echo "motion_medium_v3: done ($OUT)"
