#!/usr/bin/env bash
# The distribution judge on the v4 standard *held-out* reference set (24 held-out poses x 8 true
# states + the frame's own scan; `pocoloco data histories DATA --split heldout`, ~50 min on 2 cores):
# the shipped models (as on the test set, docs/lab/judge.md) and the fast ones paired against the
# default. Issue 41's motion model is judged on it by scripts/motion_medium_v4.sh. Rerun to resume.
#
#   bash scripts/judge_medium_v4_heldout.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
REFS=${REFS:-$HOME/.cache/pocoloco/data/medium_v4_std_heldout}
RES=benchmarks/results/distribution_medium_v4_std

[ -f "$RES/heldout/distribution.json" ] || nice $PL bench distribution --refs "$REFS" --ckpt-pocoloco default \
  --ckpt-pop default:pop --ckpt-closet default:closet --ckpt-hybrid default:hybrid --out "$RES/heldout"
[ -f "$RES/heldout_fast/distribution.json" ] || nice $PL bench distribution --refs "$REFS" \
  --ckpt-pocoloco default:fast --ckpt-hybrid default:hybrid-fast --out "$RES/heldout_fast"
$PY benchmarks/bench_fast.py --no-speed --teacher default --student default:fast --json "$RES/fast_vs_default_heldout.json" \
  --distribution "heldout=$RES/heldout/distribution.json:pocoloco,$RES/heldout_fast/distribution.json:pocoloco"

# issue 41's motion run on this set: scripts/motion_medium_v4.sh (its judge block, both splits)
echo "judge_medium_v4_heldout: done"
