#!/usr/bin/env bash
# Carry the shipped `medium` models over to a new cloth version (issue 39): make `medium` with that
# cloth, score the shipped models on it, fine-tune each from its shipped weights on a clock, assemble
# the hybrid of the two fine-tuned networks, and score those on the same frames. Every step resumes
# where a killed run stopped: rerun the script.
#
#   bash scripts/finetune_medium.sh            # the v4 cloth; ~2.5 h on a 2-core CPU: 4 / 2 / 1 sequences per subject
#   CLOTH=v3 bash scripts/finetune_medium.sh   # the v2 -> v3 carry-over of 2026-11-29 (from the v2 weights then shipped)
#   TRAIN_SEQUENCES=24 TEST_SEQUENCES=8 HELDOUT_SEQUENCES=2 MIN_POCOLOCO=120 bash scripts/finetune_medium.sh
#                                              # all of medium (~4 h of generation here), longer
#
# Two jobs run side by side (one thread each): PocoLoco on one core, POP then CloSET on the other.
# Each fine-tune runs on a time budget with a warm-stable-decay schedule, so it ends cooled down.
# The comparison (`benchmarks/compare_quality.py`, paired per frame) is written to $RUNS/*.md (RUNS ends in the cloth version).
# Needs `bash scripts/setup.sh` first.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
CLOTH=${CLOTH:-v4}                          # a key of pocoloco.synth.config.CLOTH_VERSIONS
RUNS=${RUNS:-$HOME/.cache/pocoloco/runs}/$CLOTH
DATA=${DATA:-$HOME/.cache/pocoloco/data/medium_$CLOTH}
TRAIN_SEQUENCES=${TRAIN_SEQUENCES:-4}       # of medium's 24 per subject
TEST_SEQUENCES=${TEST_SEQUENCES:-2}         # of 8
HELDOUT_SEQUENCES=${HELDOUT_SEQUENCES:-1}   # of 2
MIN_POCOLOCO=${MIN_POCOLOCO:-40}
MIN_POP=${MIN_POP:-15}
MIN_CLOSET=${MIN_CLOSET:-25}
mkdir -p "$RUNS"

# 1. the data: medium's subjects, motions and captures with that cloth (a dataset can grow later)
$PL data synth --preset medium --cloth "$CLOTH" --train-sequences "$TRAIN_SEQUENCES" --test-sequences "$TEST_SEQUENCES" \
  --heldout-sequences "$HELDOUT_SEQUENCES" --workers 2 --frame-storage compact --out "$DATA"

# 2. the shipped models on it (before anything replaces them: default:hybrid links default and default:pop)
quality() {  # quality OUT [--ckpt-... CKPT]...: both splits, the standard frames and seeds
  local out=$1; shift
  for split in test heldout; do
    [ -f "$out/$split/quality.json" ] || $PL bench quality --data "$DATA" --split "$split" --frames 28 --seeds 0 1 \
      --points 2048 "$@" --out "$out/$split"
  done
}
quality "$RUNS/quality_shipped" --ckpt-pocoloco default --ckpt-pop default:pop --ckpt-closet default:closet \
  --ckpt-hybrid default:hybrid

# 3. the fine-tunes, side by side; each from the shipped weights, its cool-down on the clock (a budget
#    is the whole run's: a killed run resumes with the minutes it had left; a finished one, its model/
#    exported, is kept)
fine_tune() {  # fine_tune RUN LOG TRAIN_ARGS...
  local run=$1 log=$2; shift 2
  [ -d "$run/model" ] && return 0
  local again=(); [ -f "$run/checkpoints/latest" ] && again=(--resume)
  nice $PL train "$@" --out "$run" "${again[@]}" --lr-schedule wsd --steps 100000 --decay-steps 30000 \
    --ckpt-every 250 --sample-every 0 --threads 1 > "$log" 2>&1
}
fine_tune "$RUNS/pocoloco" "$RUNS/pocoloco.log" --data "$DATA" --init-from default --batch-size 32 --lr 3e-4 \
  --time-budget "$MIN_POCOLOCO" &
POCO=$!
( fine_tune "$RUNS/pop" "$RUNS/pop.log" --model pop --data "$DATA" --init-from default:pop --lr 1e-4 \
    --time-budget "$MIN_POP"
  fine_tune "$RUNS/closet" "$RUNS/closet.log" --model closet --data "$DATA" --init-from default:closet --lr 1e-4 \
    --time-budget "$MIN_CLOSET" ) &
PEERS=$!
wait $POCO $PEERS

# 4. the hybrid of the two fine-tuned networks, its maps learnt on the new data (the shipped recipe)
[ -d "$RUNS/hybrid/checkpoints" ] || $PL hybrid --attached "$RUNS/pop" --free "$RUNS/pocoloco" --data "$DATA" \
  --generator-share 0.5 --inside-tolerance 0.01 --trust 0.03 --out "$RUNS/hybrid"

# 5. the fine-tuned models on the same frames, and the paired comparison per model and split
quality "$RUNS/quality_finetuned" --ckpt-pocoloco "$RUNS/pocoloco" --ckpt-pop "$RUNS/pop" \
  --ckpt-closet "$RUNS/closet" --ckpt-hybrid "$RUNS/hybrid"
for split in test heldout; do
  for model in pocoloco pop closet hybrid; do
    $PY benchmarks/compare_quality.py "$RUNS/quality_shipped/$split/quality.json:$model" \
      "$RUNS/quality_finetuned/$split/quality.json:$model" --json "$RUNS/compare_${split}_$model.json" \
      > "$RUNS/compare_${split}_$model.md"
  done
done
echo "finetune_medium ($CLOTH): done ($RUNS)"
