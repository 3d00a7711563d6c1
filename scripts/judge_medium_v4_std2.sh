#!/usr/bin/env bash
# The distribution judge on a *second* v4 standard reference set of a split (seed 1): 48 other
# held-out poses x 8 true states + the frame's own scan (`pocoloco data histories DATA --split heldout
# --seed 1 --poses 48`, ~1.3 h on 2 cores), or 24 other test poses (`--split test --seed 1 --poses
# 24`), so that the numbers of issues 41 and 42 rest on 72 held-out and 48 test poses. Judged, most
# wanted first: the shipped default with POP and CloSET, default:fast, the default with its own
# finishing call (--finish-t 5), other students (EXTRA), issue 41's motion run (its own window, then
# none), the hybrids. Each pairing is made on this set and pooled with the split's first set
# (benchmarks/results/distribution_medium_v4_std/SPLIT*). Rerun to resume: a finished report is kept.
#
#   bash scripts/judge_medium_v4_std2.sh [SPLIT]      # heldout (default) or test
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
SPLIT=${1:-heldout}
REFS=${REFS:-$HOME/.cache/pocoloco/data/medium_v4_std2_$SPLIT}
MOTION=${MOTION:-$HOME/.cache/pocoloco/runs/v4motion/pocoloco_motion}
ONE=benchmarks/results/distribution_medium_v4_std
RES=benchmarks/results/distribution_medium_v4_std2
MRES=benchmarks/results/motion_medium_v4
RUNS=${RUNS:-$HOME/.cache/pocoloco/runs/judge_std2}  # reports too large to track: only their .md is copied

judge() {  # OUT ARGS...: one report, skipped when it exists
  local out=$1; shift
  [ -f "$out/distribution.json" ] || nice $PL bench distribution --refs "$REFS" "$@" --out "$out"
}
judge_untracked() {  # NAME TRACKED_DIR ARGS...: the report in RUNS, its .md into TRACKED_DIR/NAME.md
  local name=$1 tracked=$2; shift 2
  judge "$RUNS/$name" "$@"
  mkdir -p "$tracked" && cp "$RUNS/$name/distribution.md" "$tracked/$name.md"
}
pair() {  # JSON STUDENT STUDENT_FIRST STUDENT_SECOND TEACHER_FIRST TEACHER_SECOND: on this set, and pooled
  local json=$1 student=$2 s1=$3 s2=$4 t1=$5 t2=$6
  [ -f "$s1" ] && [ -f "$t1" ] || { echo "$json: a report of the first set is missing; skipped"; return 0; }
  $PY benchmarks/bench_fast.py --no-speed --teacher default --student "$student" --json "$json" \
    --distribution "${SPLIT}2=$t2:pocoloco,$s2:pocoloco" \
    "${SPLIT}_pooled=$t1:pocoloco,$s1:pocoloco" "${SPLIT}_pooled=$t2:pocoloco,$s2:pocoloco" | grep -v "^wrote"
}

judge "$RES/$SPLIT" --ckpt-pocoloco default --ckpt-pop default:pop --ckpt-closet default:closet
judge "$RES/${SPLIT}_fast" --ckpt-pocoloco default:fast
pair "$RES/fast_vs_default_$SPLIT.json" default:fast "$ONE/${SPLIT}_fast/distribution.json" "$RES/${SPLIT}_fast/distribution.json" \
  "$ONE/$SPLIT/distribution.json" "$RES/$SPLIT/distribution.json"

judge_untracked "${SPLIT}_finish5" "$RES" --ckpt-pocoloco default --finish-t 5
pair "$RES/default_finish5_vs_default_$SPLIT.json" default "$ONE/${SPLIT}_finish5/distribution.json" \
  "$RUNS/${SPLIT}_finish5/distribution.json" "$ONE/$SPLIT/distribution.json" "$RES/$SPLIT/distribution.json"

# EXTRA="NAME=CKPT ...": other students, judged into RUNS (NAME_SPLIT2) and paired against
# default:fast, pooled with their first-set report RUNS/NAME_SPLIT1/distribution.json
for extra in ${EXTRA:-}; do
  name=${extra%%=*} ckpt=${extra#*=}
  judge_untracked "${name}_${SPLIT}2" "$RUNS" --ckpt-pocoloco "$ckpt"
  pair "$RUNS/${name}_vs_fast_$SPLIT.json" "$ckpt" "$RUNS/${name}_${SPLIT}1/distribution.json" \
    "$RUNS/${name}_${SPLIT}2/distribution.json" "$ONE/${SPLIT}_fast/distribution.json" "$RES/${SPLIT}_fast/distribution.json"
done

if [ -d "$MOTION" ]; then  # the first set's reports are in the motion run's folder (scripts/motion_medium_v4.sh)
  judge_untracked judge_${SPLIT}2_pocoloco_motion "$MRES" --ckpt-pocoloco "$MOTION" --history dataset
  judge_untracked judge_${SPLIT}2_pocoloco_motion_rest "$MRES" --ckpt-pocoloco "$MOTION" --history rest
  M1=$(dirname "$MOTION") PRE=$([ "$SPLIT" = heldout ] && echo heldout_ || true)
  pair "$MRES/judge_${SPLIT}2_motion_vs_rest.json" "$MOTION" "$M1/judge_${PRE}pocoloco_motion/distribution.json" \
    "$RUNS/judge_${SPLIT}2_pocoloco_motion/distribution.json" "$M1/judge_${PRE}pocoloco_motion_rest/distribution.json" \
    "$RUNS/judge_${SPLIT}2_pocoloco_motion_rest/distribution.json"
  pair "$MRES/judge_${SPLIT}2_motion_vs_shipped.json" "$MOTION" "$M1/judge_${PRE}pocoloco_motion/distribution.json" \
    "$RUNS/judge_${SPLIT}2_pocoloco_motion/distribution.json" "$ONE/$SPLIT/distribution.json" "$RES/$SPLIT/distribution.json"
else
  echo "judge_medium_v4_std2 $SPLIT: no motion run at $MOTION; skipped (MOTION=RUN)"
fi

judge_untracked ${SPLIT}_hybrid "$RES" --ckpt-hybrid default:hybrid
judge_untracked ${SPLIT}_hybrid_fast "$RES" --ckpt-hybrid default:hybrid-fast
echo "judge_medium_v4_std2 $SPLIT: done"
