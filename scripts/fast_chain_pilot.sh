#!/usr/bin/env bash
# Issue 42, 2 calls: does training the student on its own 2-call chain (`distill --chain-weight`:
# each pair's noise to its answer at 999, re-noised to 249, the last call scored against the
# teacher's answer) close the 2-call gap (+11 % / +9 % Chamfer against the 25-call teacher, target
# 6 %)? A paired pilot at equal wall-clock: both arms go on from the shipped `default:fast` on the
# same new teacher pairs, one thread each, side by side: `chain` with the chain term at weight 2,
# `plain` without (the control: what the same minutes of the shipped recipe give). Then each arm,
# the shipped student and the teacher are scored by `bench quality` at 2 and 4 calls on both
# splits (28 frames x 2 seeds, 2,048 points) and paired per frame against the teacher.
#
#   bash scripts/fast_chain_pilot.sh                 # 60 min per arm, both at once on 2 cores
#   MINUTES=90 ARMS="chain:1 chain3:3 plain:0" bash scripts/fast_chain_pilot.sh
#   ARMS="lo_last:2:last lo_all:2:all" CONTROL=lo_last LR=3e-5 bash scripts/fast_chain_pilot.sh   # the gradient's reach
#   DRAWS=4 PAIRS_N=1024 ARMS="cs:2:last:20 c:2:last" CONTROL=c LR=3e-5 bash scripts/fast_chain_pilot.sh
#       # the chain term with the set-level term on the same 2-call chain (4th field: its weight, --set-calls 2)
#
# $DATA: `medium` v4 with a train split; the evaluation copy (`--train-sequences 1`) serves, its
# poses taken in the teacher's frame (`--teacher-frame`). Every step skips what is done; rerun to go on.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
PL=.venv/bin/pocoloco
DATA=${DATA:-$HOME/.cache/pocoloco/data/medium_v4_eval}
OUT=${OUT:-$HOME/.cache/pocoloco/runs/fast_chain}
MINUTES=${MINUTES:-60}
read -r -a ARMS <<< "${ARMS:-chain:2 plain:0}"  # NAME:WEIGHT[:GRAD[:SET]] ... (GRAD: --chain-grad, default last; SET: --set-weight on 2 calls)
CONTROL=${CONTROL:-plain}  # the arm the others are paired against on the same clock
LR=${LR:-1e-4}
THREADS=${THREADS:-1}
PAIRS=(--pairs "${PAIRS_N:-512}" --seed 2 --teacher-frame)
[ "${DRAWS:-1}" -gt 1 ] && PAIRS+=(--draws-per-frame "$DRAWS")  # frames of several draws, for the set term
RESULTS=${RESULTS:-benchmarks/results/fast_chain_pilot}
mkdir -p "$OUT" "$RESULTS"

# 1. the teacher pairs, once (a one-step run makes them), shared by the arms
if [ ! -f "$OUT/pairs_run/model/meta.json" ]; then
  again=(); [ -d "$OUT/pairs_run/pairs" ] && again=(--resume)
  nice $PL distill --ckpt default --data "$DATA" --out "$OUT/pairs_run" --init-from default:fast "${PAIRS[@]}" \
    --steps 1 --threads 2 "${again[@]}" >> "$OUT/pairs.log" 2>&1
fi
# 2. the arms, side by side
arm() {  # arm NAME WEIGHT [GRAD [SET]]
  local run=$OUT/$1 again=() setargs=()
  [ -n "${4:-}" ] && setargs=(--set-weight "$4" --set-calls 2)
  [ -f "$run/model/meta.json" ] && return 0
  if [ -d "$run/checkpoints" ]; then again=(--resume); else mkdir -p "$run"; cp -rn "$OUT/pairs_run/pairs" "$run/"; fi
  nice $PL distill --ckpt default --data "$DATA" --out "$run" --init-from default:fast "${PAIRS[@]}" \
    --chain-weight "$2" --chain-grad "${3:-last}" "${setargs[@]}" --steps 100000 --batch-size 16 --lr "$LR" --renoised-share 0.5 \
    --time-budget "$MINUTES" \
    --threads "$THREADS" "${again[@]}" >> "$run.log" 2>&1
}
for a in "${ARMS[@]}"; do IFS=: read -r name weight grad setw <<< "$a"; arm "$name" "$weight" "$grad" "$setw" & done
wait
NAMES=("${ARMS[@]%%:*}")
for a in "${NAMES[@]}"; do
  [ -f "$OUT/fast_$a/meta.json" ] || $PL export-model --ckpt "$OUT/$a/checkpoints" --dtype int8 --polish-with default \
    --out "$OUT/fast_$a"
done
# 3. quality: the teacher (25 calls), the shipped student and each arm at 4 and 2 calls, both splits
q() {  # q NAME CKPT [STEPS]
  local dir=$OUT/quality_$1
  for split in test heldout; do
    [ -f "$dir/$split/quality.json" ] || $PL bench quality --data "$DATA" --split "$split" --frames 28 --seeds 0 1 \
      --points 2048 --ckpt-pocoloco "$2" ${3:+--steps "$3"} --threads 2 --out "$dir/$split" >> "$OUT/quality.log" 2>&1
  done
}
q teacher default
for calls in 2 4; do
  q "shipped_$calls" default:fast "$calls"
  for a in "${NAMES[@]}"; do q "${a}_$calls" "$OUT/fast_$a" "$calls"; done
done
# 4. paired per frame against the teacher (and each arm against the shipped student)
for who in shipped "${NAMES[@]}"; do
  args=()
  for split in test heldout; do
    for calls in 4 2; do args+=("$split:$calls=$OUT/quality_${who}_$calls/$split/quality.json:pocoloco"); done
  done
  $PY benchmarks/bench_fast.py --no-speed --student "$who" --quality "test=$OUT/quality_teacher/test/quality.json:pocoloco" \
    "heldout=$OUT/quality_teacher/heldout/quality.json:pocoloco" --student-quality "${args[@]}" \
    --json "$RESULTS/${who}_vs_teacher.json" > "$RESULTS/${who}_vs_teacher.txt"
done
# ... and each arm against the control on the same clock and against the shipped student, per call count
for who in "${NAMES[@]}"; do
  [ "$who" = "$CONTROL" ] && continue
  for base in "$CONTROL" shipped; do
    for calls in 4 2; do
      $PY benchmarks/bench_fast.py --no-speed --student "$who" --teacher "$base" \
        --quality "test=$OUT/quality_${base}_$calls/test/quality.json:pocoloco" \
        "heldout=$OUT/quality_${base}_$calls/heldout/quality.json:pocoloco" \
        --student-quality "test:$calls=$OUT/quality_${who}_$calls/test/quality.json:pocoloco" \
        "heldout:$calls=$OUT/quality_${who}_$calls/heldout/quality.json:pocoloco" \
        --json "$RESULTS/${who}_vs_${base}_$calls.json" > "$RESULTS/${who}_vs_${base}_$calls.txt"
    done
  done
done
echo "fast_chain_pilot: done ($OUT, $RESULTS)"
