#!/usr/bin/env bash
# Reproduce the models trained on `medium` from nothing (issue 15): the dataset, PocoLoco (one model
# for every subject, conditioned on who wears what), POP and CloSET, their held-out comparison and
# the unseen-outfit fit. Every step resumes where a killed run stopped: rerun the script.
#
#   bash scripts/reproduce_medium.sh                  # everything, ~10 h on a 2-core CPU
#   RUNS=/big/disk STEPS_POCOLOCO=15000 bash scripts/reproduce_medium.sh
#
# Two jobs run side by side (one thread each): PocoLoco on one core, POP then CloSET on the other.
# Progress goes to $RUNS/*.log. Needs `bash scripts/setup.sh` first.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
RUNS=${RUNS:-$HOME/.cache/pocoloco/runs}
DATA=${DATA:-$HOME/.cache/pocoloco/data}
STEPS_POCOLOCO=${STEPS_POCOLOCO:-10000}  # the who run converged by ~7,000 (BENCHMARKS, "Training length")
STEPS_POP=${STEPS_POP:-10000}
STEPS_CLOSET=${STEPS_CLOSET:-10000}
mkdir -p "$RUNS" "$DATA"

# 1. data: 14 subjects x 7 garment kinds, test and held-out motions (1.5 h on 2 workers, 11 GB)
$PL data synth --preset medium --workers 2 --frame-storage compact --out "$DATA/medium"
$PL data synth --preset unseen --workers 2 --frame-storage compact --out "$DATA/unseen"

# 2. the three models, side by side
resume() { [ -f "$1/checkpoints/latest" ] && echo --resume || true; }
nice $PL train --data "$DATA/medium" --out "$RUNS/medium_pocoloco" $(resume "$RUNS/medium_pocoloco") \
  --preset latent_small --bf16 --outfit-codes --body-shape --steps "$STEPS_POCOLOCO" --ckpt-every 250 \
  --threads 1 > "$RUNS/medium_pocoloco.log" 2>&1 &
POCO=$!
( nice $PL train --model pop --data "$DATA/medium" --preset small --out "$RUNS/medium_pop" $(resume "$RUNS/medium_pop") \
    --steps "$STEPS_POP" --ckpt-every 500 --sample-every 0 --threads 1 > "$RUNS/medium_pop.log" 2>&1
  nice $PL train --model closet --data "$DATA/medium" --preset small --out "$RUNS/medium_closet" \
    $(resume "$RUNS/medium_closet") --steps "$STEPS_CLOSET" --ckpt-every 500 --sample-every 0 --threads 1 \
    > "$RUNS/medium_closet.log" 2>&1 ) &
PEERS=$!
wait $POCO $PEERS

# 3. the comparison on the test split and on motions drawn with other seeds
for split in test heldout; do
  $PL bench quality --data "$DATA/medium" --split "$split" --frames 28 --seeds 0 1 --points 2048 \
    --ckpt-pocoloco "$RUNS/medium_pocoloco" --ckpt-pop "$RUNS/medium_pop" --ckpt-closet "$RUNS/medium_closet" \
    --out "$RUNS/quality_medium_$split"
done

# 4. an outfit none of them saw: fitted to 1 and 3 scans, scored at new poses
$PY benchmarks/bench_fit.py --data "$DATA/unseen" --ckpt-pocoloco "$RUNS/medium_pocoloco" \
  --ckpt-pop "$RUNS/medium_pop" --scans 1 3 --frames 12 --seeds 0 1 --points 2048 \
  --work "$RUNS/bench_fit" --json "$RUNS/fit_unseen.json"
