#!/usr/bin/env bash
# Issue 42: distil the shipped default into a few-step student on the quarter `medium` v3 data and
# score it against its teacher (resumable: every step skips what is done).
#   DATA=~/.cache/pocoloco/data/medium_v3 RUNS=~/.cache/pocoloco/runs/fast bash scripts/fast_medium_v3.sh
# Needs the teacher's own report (REF: `bench quality` of the shipped models on the same data,
# CLOTH=v3 scripts/finetune_medium.sh's quality_finetuned).
set -euo pipefail
PL=${PL:-.venv/bin/pocoloco}
DATA=${DATA:-$HOME/.cache/pocoloco/data/medium_v3}
RUNS=${RUNS:-$HOME/.cache/pocoloco/runs/fast}
REF=${REF:-$HOME/.cache/pocoloco/runs/v3/quality_finetuned}
RUN=$RUNS/d4r
resume() { [ -f "$1/checkpoints/latest" ] && echo --resume || true; }

# 1. teacher pairs (512 x 512 points, DPM-Solver++(2M) ODE 20 steps) and the student, 35 CPU minutes
#    (what ships as default:fast: `pocoloco export-model --ckpt $RUN/checkpoints --dtype int8`)
[ -f "$RUN/model/meta.json" ] || nice $PL distill --ckpt default --data "$DATA" --out "$RUN" --pairs 512 \
  --steps 1500 --batch-size 16 --lr 1e-4 --renoised-share 0.5 --time-budget 35 --threads 2 $(resume "$RUN")

# 2. quality, the teacher's standard frames and seeds: the student at 1 / 2 / 4 calls, the teacher's ODE
for split in test heldout; do
  for calls in 1 2 4; do
    out=$RUNS/quality_calls$calls/$split
    [ -f "$out/quality.json" ] || $PL bench quality --data "$DATA" --split $split --frames 28 --seeds 0 1 \
      --points 2048 --ckpt-pocoloco "$RUN/model" --steps $calls --threads 2 --out "$out"
  done
  out=$RUNS/quality_teacher_ode/$split
  [ -f "$out/quality.json" ] || $PL bench quality --data "$DATA" --split $split --frames 28 --seeds 0 1 \
    --points 2048 --ckpt-pocoloco default --sampler dpm++ --steps 20 --threads 2 --out "$out"
done

# 3. the judge on the reference sets of `pocoloco data histories` (REFS_test, REFS_heldout), then the table:
#    paired with the teacher's 25-call reports, speed at 2K / 10K / 50K points, animate frames/s
REFS=${REFS:-$HOME/.cache/pocoloco/refs/medium_v3}
for split in test heldout; do
  [ -f "$RUNS/dist_fast/$split/distribution.json" ] || $PL bench distribution --refs "${REFS}_$split" \
    --ckpt-pocoloco "$RUN/model" --out "$RUNS/dist_fast/$split"
done
S=""; for split in test heldout; do for calls in 1 2 4; do
  S="$S $split:$calls=$RUNS/quality_calls$calls/$split/quality.json:pocoloco"; done
  S="$S $split:ode20=$RUNS/quality_teacher_ode/$split/quality.json:pocoloco"; done
.venv/bin/python benchmarks/bench_fast.py --student "$RUN/model" --threads 1 \
  --quality test=$REF/test/quality.json:pocoloco heldout=$REF/heldout/quality.json:pocoloco \
  --student-quality $S --animate "$DATA:skirt_a/test/test_0000" \
  --distribution test=benchmarks/results/distribution_medium_v3/test/distribution.json:pocoloco,$RUNS/dist_fast/test/distribution.json:pocoloco \
  heldout=benchmarks/results/distribution_medium_v3/heldout/distribution.json:pocoloco,$RUNS/dist_fast/heldout/distribution.json:pocoloco \
  --json benchmarks/results/fast_medium_v3/fast.json

# 4. the hybrid with the fast generator (what ships as default:hybrid-fast: `pocoloco export-model --ckpt
#    $RUNS/hybrid_fast --out src/pocoloco/assets/hybrid_fast_medium`), both hybrids scored on the standard
#    frames, paired, and timed with every shipped model on the demo poses (interleaved)
[ -d "$RUNS/hybrid_fast/checkpoints" ] || $PL hybrid --attached default:pop --free default:fast --maps default:hybrid \
  --inside-tolerance 0.01 --trust 0.03 --link --data "$DATA" --out "$RUNS/hybrid_fast"
for split in test heldout; do
  for h in hybrid hybrid-fast; do
    out=$RUNS/quality_$h/$split
    [ -f "$out/quality.json" ] || $PL bench quality --data "$DATA" --split $split --frames 28 --seeds 0 1 \
      --points 2048 --ckpt-hybrid default:$h --threads 1 --out "$out"
  done
  out=$RUNS/quality_hybrid-fast_2calls/$split
  [ -f "$out/quality.json" ] || $PL bench quality --data "$DATA" --split $split --frames 28 --seeds 0 1 \
    --points 2048 --ckpt-hybrid default:hybrid-fast --steps 2 --threads 1 --out "$out"
  for fast in hybrid-fast hybrid-fast_2calls; do
    .venv/bin/python benchmarks/compare_quality.py "$RUNS/quality_hybrid/$split/quality.json:hybrid" \
      "$RUNS/quality_$fast/$split/quality.json:hybrid" --metrics chamfer_cm s2m_garment_cm m2s_garment_cm \
      loose_pred_pct outlier_10cm_pct energy_score_adj_cm \
      --json "benchmarks/results/fast_medium_v3/hybrid/$split/hybrid_vs_${fast//-/_}.json"
  done
done
.venv/bin/python benchmarks/bench_fast.py --student default:fast --calls 1 2 4 --points 2048 10000 50000 --repeats 5 \
  --threads 1 --models default:hybrid default:hybrid-fast --json benchmarks/results/fast_medium_v3/speed.json
.venv/bin/python benchmarks/bench_fast.py --student default:fast --no-speed --repeats 3 --threads 1 \
  --models default default:fast default:pop default:closet default:hybrid default:hybrid-fast default:hybrid-fast@2 \
  --json benchmarks/results/fast_medium_v3/models_speed.json
