"""Paired training pilots at equal wall-clock: which recipe learns most in the same time?

Each ``--arm NAME="TRAIN ARGS"`` is one ``pocoloco train`` run on ``--data``; all arms start
together, side by side, one thread each (so they share the machine alike), and each is stopped
after ``--minutes`` of wall-clock. Its last checkpoint (written every ``--ckpt-every`` steps, so at
most that many steps before the deadline) is then scored with ``pocoloco eval`` on every split of
``--splits`` (the same frames and seeds for every arm), without baselines. Prints a table (overall
and per-subject Chamfer, M2S, far outliers, loose share against the ground truth's) and writes JSON.

    python benchmarks/experiments/pilot.py --data data/medium --minutes 35 --out ~/.cache/pocoloco/runs/pilot_who \\
        --arm joints="--preset latent_small" \\
        --arm who="--preset latent_small --outfit-codes --body-shape" \\
        --splits test heldout --frames 28 --seeds 0 1 --json benchmarks/results/pilot_who.json

A pilot stopped half-way (a killed session) is not resumed: its arms would no longer share the
machine alike. Rerunning with the same ``--out`` only re-scores arms whose training finished
(``pilot_arm.json`` in the arm's folder); ``--fresh`` starts every arm again.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from pocoloco.engine.checkpoint import latest_checkpoint, read_meta
from pocoloco.utils.atomic import write_json_atomic


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "pocoloco", *args]


def parse_arm(text: str) -> tuple[str, list[str]]:
    name, sep, rest = text.partition("=")
    if not sep or not name.strip():
        raise SystemExit(f"error: --arm must be NAME=\"TRAIN ARGS\", got {text!r}")
    return name.strip(), shlex.split(rest)


def train_arms(arms: dict[str, list[str]], args) -> dict[str, dict]:
    """Run every arm side by side for ``args.minutes``; returns {name: {step, seconds, checkpoint}}."""
    procs: dict[str, tuple[subprocess.Popen, float, object]] = {}
    for name, extra in arms.items():
        run = args.out / name
        if args.fresh and run.exists():
            shutil.rmtree(run)
        if (run / "pilot_arm.json").exists():
            continue
        if run.exists():
            shutil.rmtree(run)  # a half-finished arm: restart it (see the module docstring)
        run.mkdir(parents=True)
        cmd = cli("train", "--data", str(args.data), "--out", str(run), "--threads", "1", "--steps", "1000000",
                  "--ckpt-every", str(args.ckpt_every), "--sample-every", "0", "--no-progress", *extra)  # fmt: skip
        log = open(run / "pilot_train.log", "w")
        print(f"[{name}] {shlex.join(cmd)}", flush=True)
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"}), time.time(), log)  # fmt: skip
    deadline = args.minutes * 60.0
    while procs:
        time.sleep(5.0)
        for name in list(procs):
            proc, start, log = procs[name]
            elapsed = time.time() - start
            if proc.poll() is not None and proc.returncode != 0:
                raise SystemExit(f"error: arm {name} failed (exit {proc.returncode}); see {args.out / name / 'pilot_train.log'}")
            if elapsed >= deadline or proc.poll() is not None:
                proc.terminate()
                try:
                    proc.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                log.close()
                ckpt = latest_checkpoint(args.out / name / "checkpoints")
                if ckpt is None:
                    raise SystemExit(f"error: arm {name} wrote no checkpoint in {args.minutes} min")
                info = {"step": int(read_meta(ckpt)["step"]), "seconds": round(elapsed, 1),
                        "checkpoint": str(ckpt.resolve()), "train_args": arms[name]}  # fmt: skip
                write_json_atomic(args.out / name / "pilot_arm.json", info, indent=1)  # the arm's "finished" mark
                print(f"[{name}] stopped after {elapsed / 60:.1f} min at step {info['step']}", flush=True)
                del procs[name]
    return {name: json.loads((args.out / name / "pilot_arm.json").read_text()) for name in arms}


def evaluate_arm(name: str, info: dict, split: str, args) -> dict:
    out = args.out / name / f"eval_{split}"
    if not (out / "eval.json").exists():
        cmd = cli("eval", "--ckpt", info["checkpoint"], "--data", str(args.data), "--split", split,
                  "--frames", str(args.frames), "--points", str(args.points), "--seeds", *map(str, args.seeds),
                  "--no-baselines", "--threads", str(args.eval_threads), "--out", str(out))  # fmt: skip
        print(f"[{name}] eval {split}", flush=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    ev = json.loads((out / "eval.json").read_text())

    def pick(m: dict) -> dict:
        keys = ("chamfer_cm", "m2s_cm", "s2m_cm", "outlier_10cm_pct", "outlier_10cm_pct_max", "loose_pred_pct", "loose_gt_pct")
        return {k: m[k] for k in keys if k in m}

    return {"overall": pick(ev["means"]["model"]),
            "per_subject": {s: pick(v["model"]) for s, v in ev["per_subject"].items()},
            "per_frame": {f["key"]: f["model"]["chamfer_cm"] for f in ev["frames"]}}  # fmt: skip


def paired(base: dict[str, float], other: dict[str, float]) -> dict[str, float]:
    """Per-frame Chamfer differences other - base on the frames both scored: mean, standard error,
    share of frames where ``other`` is at least as good."""
    keys = sorted(set(base) & set(other))
    d = [other[k] - base[k] for k in keys]
    n = len(d)
    mean = sum(d) / n
    se = (sum((x - mean) ** 2 for x in d) / (n - 1) / n) ** 0.5 if n > 1 else float("nan")
    return {"frames": n, "mean_cm": mean, "se_cm": se, "not_worse_pct": 100.0 * sum(x <= 0 for x in d) / n}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path, help="dataset folder (train split for training)")
    ap.add_argument("--arm", action="append", required=True, metavar='NAME="TRAIN ARGS"',
                    help="one pilot arm: a name and the extra `pocoloco train` arguments")  # fmt: skip
    ap.add_argument("--minutes", type=float, default=35.0, help="training wall-clock per arm")
    ap.add_argument("--ckpt-every", type=int, default=50)
    ap.add_argument("--out", required=True, type=Path, help="folder of the arms' runs (outside the work tree)")
    ap.add_argument("--splits", nargs="+", default=["test", "heldout"])
    ap.add_argument("--frames", type=int, default=28)
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--eval-threads", type=int, default=2)
    ap.add_argument("--fresh", action="store_true", help="train every arm again")
    ap.add_argument("--json", type=Path, default=None, help="results JSON")
    args = ap.parse_args()
    arms = dict(parse_arm(a) for a in args.arm)
    if len(arms) != len(args.arm):
        raise SystemExit("error: two arms share a name")
    args.out = args.out.expanduser()
    trained = train_arms(arms, args)
    results = {name: {**info, "eval": {s: evaluate_arm(name, info, s, args) for s in args.splits}}
               for name, info in trained.items()}  # fmt: skip

    subjects = sorted({s for r in results.values() for e in r["eval"].values() for s in e["per_subject"]})
    for split in args.splits:
        print(f"\n{split}: Chamfer cm (M2S), > 10 cm % (worst cloud), loose % pred / GT; {args.frames} frames x {len(args.seeds)} seeds")
        print(f"{'arm':<16} {'steps':>6}  {'Chamfer':>8} {'M2S':>6} {'>10cm':>6} {'worst':>6} {'loose':>11}")
        for name, r in results.items():
            m = r["eval"][split]["overall"]
            print(f"{name:<16} {r['step']:>6}  {m['chamfer_cm']:>8.2f} {m['m2s_cm']:>6.2f} {m['outlier_10cm_pct']:>6.2f} "
                  f"{m.get('outlier_10cm_pct_max', float('nan')):>6.1f} {m['loose_pred_pct']:>5.1f}/{m['loose_gt_pct']:<5.1f}")  # fmt: skip
        names = list(results)
        base = names[0]
        for name in names[1:]:
            pr = paired(results[base]["eval"][split]["per_frame"], results[name]["eval"][split]["per_frame"])
            results[name]["eval"][split][f"paired_vs_{base}"] = pr
            print(f"paired, {name} - {base}: {pr['mean_cm']:+.2f} +- {pr['se_cm']:.2f} cm over {pr['frames']} frames "
                  f"({pr['not_worse_pct']:.0f} % of frames not worse)")  # fmt: skip
        print("per subject, Chamfer cm: " + " ".join(f"{s}" for s in subjects))
        for name, r in results.items():
            per = r["eval"][split]["per_subject"]
            print(f"{name:<16} " + " ".join(f"{per[s]['chamfer_cm']:.2f}" if s in per else "-" for s in subjects))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
        args.json.write_text(json.dumps({"settings": settings, "arms": results}, indent=1))
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
