"""Sample quality over training time: evaluate a run's checkpoints as they appear.

For every checkpoint ``step_XXXXXX`` of RUN whose step is a multiple of ``--every`` (and not yet
in the JSON), samples are drawn from the EMA weights and the raw weights for ``--frames`` test
frames (``pocoloco.evaluation.evaluate.evaluate``, ``--seeds`` one sample per seed, ``--points`` points)
and scored; the nearest-frame, posed-body and GT-resample baselines are computed once with the
same frames and points. Writes ``--out`` (JSON) and a plot next to it: Chamfer (cm) vs. step
for EMA and raw weights, with the baselines as horizontal lines, next to the training loss.

    python benchmarks/experiments/quality_over_training.py runs/small --watch      # keep polling (Ctrl-C to stop)
    python benchmarks/experiments/quality_over_training.py runs/small              # evaluate what is there, then exit

Checkpoints are deleted by training (``keep_checkpoints``); with ``--watch`` each is evaluated
soon after it is written.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from pocoloco.engine.checkpoint import _step_dirs
from pocoloco.evaluation.evaluate import EvalSettings, evaluate
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.viz.render import plot_curves


def _settings(args, baselines=()) -> EvalSettings:
    return EvalSettings(split=args.split, num_frames=args.frames, num_points=args.points, seeds=tuple(args.seeds),
                        sampler=args.sampler, steps=args.steps, baselines=tuple(baselines),
                        clip=args.clip or None)  # fmt: skip


def _plot(doc: dict, run: Path, path: Path) -> None:
    rows = sorted(doc["checkpoints"], key=lambda r: r["step"])
    if not rows:
        return
    steps = [r["step"] for r in rows]
    curves = {f"{w} weights": (steps, [r[w]["chamfer_cm"] for r in rows]) for w in ("ema", "raw") if w in rows[0]}
    for name, m in doc.get("baselines", {}).items():
        curves[name.replace("_", " ")] = ([0, max(steps)], [m["chamfer_cm"]] * 2)
    plot_curves(curves, path, xlabel="training step", ylabel=f"Chamfer cm ({doc['settings'].get('split', 'test')})", logy=True,
                title=f"sample quality over training ({run.name})")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, help="training run folder")
    p.add_argument("--data", default="data/small")
    p.add_argument("--every", type=int, default=500, help="evaluate checkpoints whose step is a multiple of this")
    p.add_argument("--split", default="test", help="split scored (test, or heldout: motions drawn with other seeds)")
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--sampler", default="dpm++")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--clip", type=float, default=5.0, help="sampler x0 clamp (0 = off), as pocoloco eval")
    p.add_argument("--no-raw", action="store_true", help="only the EMA weights")
    p.add_argument("--watch", action="store_true", help="keep polling for new checkpoints")
    p.add_argument("--poll", type=float, default=60.0, help="seconds between polls")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=None, help="default RUN/quality_over_training.json")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = args.out or args.run / "quality_over_training.json"
    doc = json.loads(out.read_text()) if out.is_file() else {"settings": vars(args) | {"run": str(args.run)},
                                                             "checkpoints": []}  # fmt: skip
    doc["settings"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    if "baselines" not in doc:
        base, _ = evaluate(None, args.data, _settings(args, ("nearest_frame", "posed_body", "gt_resample")),
                           keep_examples=0)  # fmt: skip
        doc["baselines"] = {k: {"chamfer_cm": v["chamfer_cm"], "s2m_cm": v["s2m_cm"], "m2s_cm": v["m2s_cm"]}
                            for k, v in base.means.items()}  # fmt: skip
        write_json_atomic(out, doc)
    done = {r["step"] for r in doc["checkpoints"]}
    while True:
        ckpts = [d for d in _step_dirs(args.run / "checkpoints") if (d / "meta.json").is_file()]
        todo = [d for d in ckpts if int(d.name[5:]) % args.every == 0 and int(d.name[5:]) not in done]
        for d in todo:
            step = int(d.name[5:])
            row = {"step": step, "time": time.time()}
            try:
                for weights in ("ema",) if args.no_raw else ("ema", "raw"):
                    s = _settings(args)
                    s = EvalSettings(**{**s.__dict__, "use_ema": weights == "ema"})
                    res, _ = evaluate(d, args.data, s, keep_examples=0)
                    m = res.means["model"]
                    row[weights] = {k: m[k] for k in ("chamfer_cm", "s2m_cm", "m2s_cm", "fscore_pct", "loose_pred_pct",
                                                      "loose_gt_pct", "diversity_garment_cm", "diversity_body_cm")
                                    if k in m}  # fmt: skip
            except ValueError as e:  # the checkpoint was deleted by training while we read it
                print(f"step {step}: skipped ({e})", flush=True)
                continue
            doc["checkpoints"].append(row)
            done.add(step)
            write_json_atomic(out, doc)
            _plot(doc, args.run, out.with_suffix(".png"))
            print(f"step {step}: " + "  ".join(f"{w} Chamfer {row[w]['chamfer_cm']:.2f} cm" for w in ("ema", "raw")
                                               if w in row), flush=True)  # fmt: skip
        if not args.watch:
            break
        time.sleep(args.poll)
    _plot(doc, args.run, out.with_suffix(".png"))
    print(json.dumps({r["step"]: {w: round(r[w]["chamfer_cm"], 2) for w in ("ema", "raw") if w in r}
                      for r in sorted(doc["checkpoints"], key=lambda r: r["step"])}))  # fmt: skip


if __name__ == "__main__":
    main()
