#!/usr/bin/env bash
# Train PocoLoco on a leased GPU in one go (issue 27): throughput benchmark (GPU rows + one CPU row),
# a short measured search for the network and batch, then the final run with what is left of the
# lease, exported and packed into OUT for the trip back. Every stage writes into OUT as it goes.
#
#   bash scripts/gpu_job.sh PACK OUT [SECONDS]      # SECONDS: wall-clock for the whole job (default 560)
#
# Needs only torch, numpy, safetensors, rich and matplotlib (pocoloco runs from src/, not installed).
# Environment: SEARCH_SECONDS (per candidate, default 30), CANDIDATES (default below), SKIP_BENCH=1,
# BEST="PRESET BATCH STEPS_PER_S" (skip the search), INIT_FROM=CKPT (fine-tune from that checkpoint
# with its config, e.g. the hybrid's free-region generator from src/pocoloco/assets/pocoloco_medium on
# a free-region pack), LR (the run's peak learning rate).
# RUNS="NAME:TRAIN ARGS;NAME:TRAIN ARGS": no search and no single run: train these side by side on the
# one GPU, each on the whole budget's clock (--time-budget), with its own log NAME.log and export
# NAME/model. The runs share the GPU by time-slicing: on one H100 four runs kept it 100 % busy and
# together made about the steps of one run (BENCHMARKS.md, "Five recipes side by side"), so RUNS
# compares recipes at an equal share of the budget; it does not buy extra runs. E.g.
#   RUNS="s256:--preset latent_small --batch-size 256 --lr 2e-3;s1024:--preset latent_small --batch-size 1024"
# A run's own --steps / --decay-steps win over the defaults (100,000 steps, wsd over the last fifth:
# the clock ends it, cooled down).
# MODEL=distill distils TEACHER (default: default) into a few-step student on the pack (`pocoloco distill
# --data PACK`: the teacher pairs made there, then the student, on the budget's clock), RUNS of distill
# options (default one run, 2,048 pairs, batch 128); each student comes back as NAME/model and, with its
# teacher's finishing call, NAME/polished (int8, what `default:fast` ships as).
# MODEL=pop (or closet) trains that method on a `pocoloco data pack --bodies` pack instead: no bench and
# no search, the RUNS given (default: one run continuing the shipped model at batch 16 on all the
# pack's points of each frame, its learning rate cooled down to 0 over the last fifth of the clock,
# which ends it: on this CPU a cool-down was worth -0.08 cm to both, BENCHMARKS.md "POP from a pack"). Expect
# no gain: POP's curve is flat on this CPU and it over-fits a pack's 1,288 frames when passed over them
# many times (BENCHMARKS.md "Longer cool-downs, and how many frames POP needs"); e.g.
#   MODEL=pop RUNS="b16:--init-from default:pop --normal-start 0 --steps 1000000 --lr-schedule wsd --decay-steps 200000 --batch-size 16 --num-points 3840"
set -uo pipefail
cd "$(dirname "$0")/.."
PACK=$1
OUT=$2
TOTAL=${3:-560}
START=$(date +%s)
PY=${PY:-python3}
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
DEVICE=${DEVICE:-cuda}
SEARCH_SECONDS=${SEARCH_SECONDS:-30}
CANDIDATES=${CANDIDATES:-latent_small:256 latent_base:256 latent_base:1024}
BENCH_ARGS=${BENCH_ARGS:---device cuda cpu --cpu-rows latent_small:16 --cpu-sample-points --compile latent_small:256}
WORKERS=${WORKERS:-8}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/job.log") 2>&1
elapsed() { echo $(( $(date +%s) - START )); }
# seconds left for training after HEADROOM (start-up, final checkpoints, exports, packing), at least 30
left_seconds() { local left=$(( TOTAL - $(elapsed) - $1 )); echo $(( left < 30 ? 30 : left )); }
MODEL=${MODEL:-pocoloco}
if [ "$MODEL" = pocoloco ]; then
  # what every training run here shares: the full recipe (outfit codes + body shape, bf16), no previews
  TRAIN=($PY -m pocoloco train --data "$PACK" --outfit-codes --body-shape --bf16 --device "$DEVICE" --ckpt-every 1000
         --sample-every 0 --log-every 50 --no-progress)
  RUN_DEFAULTS="--steps 100000 --lr-schedule wsd --decay-steps 20000"
elif [ "$MODEL" = distill ]; then  # a few-step student of TEACHER (default: default) on the pack (issue 42)
  TRAIN=($PY -m pocoloco distill --ckpt "${TEACHER:-default}" --data "$PACK" --device "$DEVICE")
  RUN_DEFAULTS="--steps 1000000"
  SKIP_BENCH=1
  RUNS=${RUNS:-"d:--pairs 2048 --pair-points 512 --batch-size 128 --lr 1e-4 --renoised-share 0.5"}
else  # POP / CloSET: the run's own --steps and learning-rate schedule
  TRAIN=($PY -m pocoloco train --model "$MODEL" --data "$PACK" --device "$DEVICE" --ckpt-every 1000 --sample-every 0
         --log-every 50 --no-progress)
  RUN_DEFAULTS=""
  SKIP_BENCH=1
  POINTS=$($PY -c "import sys; from pocoloco.data.pack import read_pack_meta; print(read_pack_meta(sys.argv[1])['points_per_frame'])" "$PACK")
  RUNS=${RUNS:-"cont:--init-from default:$MODEL --normal-start 0 --steps 1000000 --lr-schedule wsd --decay-steps 200000 --batch-size 16 --num-points $POINTS"}
fi

echo "== $(date -u +%FT%TZ) job: $MODEL, pack $PACK, $TOTAL s"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
$PY -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'numpy', numpy.__version__)"

if [ -z "${SKIP_BENCH:-}" ]; then
  echo "== bench ($(elapsed) s)"
  # shellcheck disable=SC2086
  $PY benchmarks/bench_gpu_training.py --data "$PACK" $BENCH_ARGS --workers "$WORKERS" --json "$OUT/bench.json" \
    || echo "bench failed (going on)"
fi

if [ -n "${RUNS:-}" ]; then
  MINUTES=$($PY -c "print(round($(left_seconds 60) / 60, 3))")
  IFS=';' read -ra SPECS <<< "$RUNS"
  W=$(( WORKERS * 2 / ${#SPECS[@]} )); [ "$W" -lt 2 ] && W=2
  T=$(( $(nproc) / ${#SPECS[@]} )); [ "$T" -lt 1 ] && T=1  # torch threads each: the cores shared, not oversubscribed
  echo "== train ${#SPECS[@]} runs side by side, $W workers each, budget $MINUTES min ($(elapsed) s)"
  PIDS=()
  for spec in "${SPECS[@]}"; do
    NAME=${spec%%:*}
    ARGS=${spec#*:}
    echo "   $NAME: $ARGS"
    if [ "$MODEL" = distill ]; then LOADER=(); else LOADER=(--workers "$W"); fi  # distill reads its pairs, no loader
    # shellcheck disable=SC2086
    "${TRAIN[@]}" --out "$OUT/$NAME" "${LOADER[@]}" --threads "$T" $RUN_DEFAULTS --time-budget "$MINUTES" $ARGS \
      > "$OUT/$NAME.log" 2>&1 &
    PIDS+=($!)
  done
  for pid in "${PIDS[@]}"; do wait "$pid" || echo "a run failed (pid $pid)"; done
  for spec in "${SPECS[@]}"; do NAME=${spec%%:*}; echo "-- $NAME"; tail -n 3 "$OUT/$NAME.log"; done
  if [ "$MODEL" = distill ]; then  # each student also with its teacher's finishing call (export-model --polish-with)
    for spec in "${SPECS[@]}"; do
      NAME=${spec%%:*}
      $PY -m pocoloco export-model --ckpt "$OUT/$NAME/model" --dtype int8 --polish-with "${TEACHER:-default}" \
        --out "$OUT/$NAME/polished" || echo "export of $NAME failed"
    done
  fi
else  # one run, its network and batch from a search (or BEST)
if [ -n "${BEST:-}" ]; then  # "PRESET BATCH STEPS_PER_S" from an earlier search: no search now
  printf '{"best": {"preset": "%s", "batch": %s, "steps_per_s": %s}}' $BEST > "$OUT/search.json"
else
  echo "== search ($(elapsed) s)"
  # shellcheck disable=SC2086
  $PY benchmarks/search_gpu_recipe.py --data "$PACK" --device "$DEVICE" --seconds "$SEARCH_SECONDS" \
    --candidates $CANDIDATES --workers "$WORKERS" --json "$OUT/search.json" || echo "search failed (going on)"
fi
read -r PRESET BATCH SPS < <($PY - "$OUT/search.json" <<'EOF'
import json, sys
try:
    b = json.load(open(sys.argv[1]))["best"]
    print(b["preset"], b["batch"], b["steps_per_s"])
except Exception:
    print("latent_small", 256, 0)  # no search result: the CPU recipe's network at a GPU batch
EOF
)

LEFT=$(left_seconds 45)
# wsd with its cool-down over the last fifth, on the step count that fits at the searched rate (20 %
# headroom) and on the clock (--time-budget), whichever comes first: a machine slower than the search's
# still ends cooled down; without a measured rate the clock alone decides
SCHEDULE=$($PY -c "s=$SPS; n=max(200, int(s * $LEFT * 1.2)) if s > 0 else 1000000; print(f'--steps {n} --lr-schedule wsd --decay-steps {n // 5}')")
MINUTES=$($PY -c "print(round($LEFT / 60, 3))")
echo "== train $PRESET B=$BATCH: $SCHEDULE, budget $MINUTES min ($(elapsed) s)"
if [ -n "${INIT_FROM:-}" ]; then START_ARGS="--init-from $INIT_FROM"; else START_ARGS="--preset $PRESET"; fi
# shellcheck disable=SC2086
"${TRAIN[@]}" --out "$OUT/run" $START_ARGS ${LR:+--lr $LR} --batch-size "$BATCH" --workers "$WORKERS" $SCHEDULE \
  --time-budget "$MINUTES" || echo "train failed"

fi

echo "== pack results ($(elapsed) s)"
# the trip back takes at most 8 files of 16 MiB: one tar of everything but the full checkpoints and a
# distillation's teacher pairs, in 15 MB parts
tar -cf "$OUT/results.tar" -C "$OUT" --exclude=checkpoints --exclude=pairs --exclude=results.tar --exclude=job.log . 2>/dev/null
split -b 15000000 -d "$OUT/results.tar" "$OUT/results.tar.part"
rm -f "$OUT/results.tar"
find "$OUT" -mindepth 1 -maxdepth 1 ! -name 'results.tar.part*' ! -name job.log -exec rm -rf {} +
ls -la "$OUT"
echo "== done ($(elapsed) s)"
