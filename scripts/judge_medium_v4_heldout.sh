#!/usr/bin/env bash
# The distribution judge on the v4 standard *held-out* reference set (24 held-out poses x 8 true
# states + the frame's own scan; `pocoloco data histories DATA --split heldout`, ~50 min on 2 cores):
# the shipped models (as on the test set, docs/lab/judge.md), the fast ones paired against the
# default, and, where its run folder exists, issue 41's motion model (its own window, and none)
# paired against the shipped default and against itself without the window. Rerun to resume.
#
#   bash scripts/judge_medium_v4_heldout.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
REFS=${REFS:-$HOME/.cache/pocoloco/data/medium_v4_std_heldout}
RES=benchmarks/results/distribution_medium_v4_std
MOTION=${MOTION:-$HOME/.cache/pocoloco/runs/v4motion}

[ -f "$RES/heldout/distribution.json" ] || nice $PL bench distribution --refs "$REFS" --ckpt-pocoloco default \
  --ckpt-pop default:pop --ckpt-closet default:closet --ckpt-hybrid default:hybrid --out "$RES/heldout"
[ -f "$RES/heldout_fast/distribution.json" ] || nice $PL bench distribution --refs "$REFS" \
  --ckpt-pocoloco default:fast --ckpt-hybrid default:hybrid-fast --out "$RES/heldout_fast"
$PY benchmarks/bench_fast.py --no-speed --teacher default --student default:fast --json "$RES/fast_vs_default_heldout.json" \
  --distribution "heldout=$RES/heldout/distribution.json:pocoloco,$RES/heldout_fast/distribution.json:pocoloco"

if [ -f "$MOTION/pocoloco_motion/model/meta.json" ] || [ -d "$MOTION/pocoloco_motion/checkpoints" ]; then
  for history in dataset rest; do
    judge=$MOTION/judge_heldout_pocoloco_motion$([ $history = rest ] && echo _rest || true)
    [ -f "$judge/distribution.json" ] || nice $PL bench distribution --refs "$REFS" \
      --ckpt-pocoloco "$MOTION/pocoloco_motion" --history $history --out "$judge"
  done
  $PY benchmarks/bench_fast.py --no-speed --teacher default --student "$MOTION/pocoloco_motion" \
    --json "$MOTION/judge_heldout_pocoloco_motion_vs_shipped.json" --distribution \
    "heldout=$RES/heldout/distribution.json:pocoloco,$MOTION/judge_heldout_pocoloco_motion/distribution.json:pocoloco" \
    > "$MOTION/judge_heldout_pocoloco_motion_vs_shipped.md"
  $PY benchmarks/bench_fast.py --no-speed --teacher "$MOTION/pocoloco_motion (rest)" --student "$MOTION/pocoloco_motion" \
    --json "$MOTION/judge_heldout_pocoloco_motion_vs_rest.json" --distribution \
    "heldout=$MOTION/judge_heldout_pocoloco_motion_rest/distribution.json:pocoloco,$MOTION/judge_heldout_pocoloco_motion/distribution.json:pocoloco" \
    > "$MOTION/judge_heldout_pocoloco_motion_vs_rest.md"
fi
echo "judge_medium_v4_heldout: done"
