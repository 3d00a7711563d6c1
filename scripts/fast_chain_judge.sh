#!/usr/bin/env bash
# Issue 42: the proper score of the chain-term students (scripts/fast_chain_pilot.sh) before any of
# them could replace `default:fast`. On one reference set of `pocoloco data histories` (REFS), the
# judge (`bench distribution`, 16 draws per pose, 0 and 2 s shared) scores the 25-call teacher, the
# shipped student and each arm, at 4 calls (the shipped sampler: 3 student calls and the teacher's
# finishing call) and at 2 (the student alone); each is then paired per pose against the teacher
# and against the shipped student at the same calls (`benchmarks/bench_fast.py --distribution`).
#
#   REFS=~/.cache/pocoloco/refs/v4_std_test SET=test ARMS="chain_lo=RUNS/fast_chain_lo ..." bash scripts/fast_chain_judge.sh
#
# Reports go to $OUT/judge_$SET (too large to track), the pairings and each report's .md to
# $RESULTS. Rerun to resume: a finished report is kept.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
REFS=${REFS:?REFS: a reference set of pocoloco data histories}
SET=${SET:?SET: a name for the set, e.g. test or heldout}
OUT=${OUT:-$HOME/.cache/pocoloco/runs/fast_chain_grad}/judge_$SET
RESULTS=${RESULTS:-benchmarks/results/fast_chain_grad_pilot}/judge_$SET
read -r -a ARMS <<< "${ARMS:?ARMS: NAME=STUDENT_MODEL ...}"
mkdir -p "$OUT" "$RESULTS"

judge() {  # NAME ARGS...: one report, skipped when it exists
  local name=$1; shift
  [ -f "$OUT/$name/distribution.json" ] || nice $PL bench distribution --refs "$REFS" "$@" --out "$OUT/$name"
  cp "$OUT/$name/distribution.md" "$RESULTS/$name.md"
}
pair() {  # JSON NAME BASE: NAME's report paired per pose against BASE's
  $PY benchmarks/bench_fast.py --no-speed --teacher "$3" --student "$2" --json "$1" \
    --distribution "$SET=$OUT/$3/distribution.json:pocoloco,$OUT/$2/distribution.json:pocoloco" | grep -v "^wrote"
}

judge teacher --ckpt-pocoloco default
for calls in 4 2; do
  judge "shipped_$calls" --ckpt-pocoloco default:fast --steps "$calls"
  pair "$RESULTS/shipped_${calls}_vs_teacher.json" "shipped_$calls" teacher
  for arm in "${ARMS[@]}"; do
    name=${arm%%=*}
    judge "${name}_$calls" --ckpt-pocoloco "${arm#*=}" --steps "$calls"
    pair "$RESULTS/${name}_${calls}_vs_teacher.json" "${name}_$calls" teacher
    pair "$RESULTS/${name}_${calls}_vs_shipped.json" "${name}_$calls" "shipped_$calls"
  done
done
echo "fast_chain_judge: done ($OUT, $RESULTS)"
