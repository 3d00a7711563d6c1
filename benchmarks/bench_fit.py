"""Fitting an outfit the model never saw (issue 15, item 2): PocoLoco next to POP and the hybrid, on the same scans.

For every subject of ``--data`` (a dataset whose garments the models never trained on, e.g. the
``unseen`` preset) and every number of scans k in ``--scans``: k frames of the subject's *train*
split (evenly spaced) are written as PLY scans (points + normals, world frame) and ``pocoloco fit``
fits a new outfit to them (PocoLoco: only a new outfit code, with the diffusion loss, on k scans;
POP: only its geometric feature tensor, on one scan, as its paper; the hybrid: POP's features to
the scan and its generator's code to the scan's free region, its map from the scan's labels). Then
each is scored at *new
poses*, the subject's *test* split (``--frames`` frames x ``--seeds``, ``--points`` points):

* **before**: the model in its nearest trained outfit (the best single one on the first scan);
* **after**: the model in the fitted outfit;
* and for reference the posed body (no clothes) and the GT resample (noise floor).

    python benchmarks/bench_fit.py --data data/unseen --ckpt-pocoloco RUN --ckpt-pop RUN_POP \\
        --scans 1 3 --frames 12 --seeds 0 1 --points 2048 --threads 1 \\
        --work ~/.cache/pocoloco/runs/bench_fit --json benchmarks/results/fit_unseen.json

Every fit and every evaluation is kept in ``--work`` and reused when the script runs again (a
killed run resumes); ``--fresh`` recomputes. Prints a markdown table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from pocoloco.apps.fitting import fit_outfit
from pocoloco.data import format as fmt
from pocoloco.data.published import export_frame
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.evaluation.evaluate import EvalSettings, evaluate
from pocoloco.methods import load_method
from pocoloco.utils.atomic import write_json_atomic

COLUMNS = ("chamfer_cm", "s2m_cm", "m2s_cm", "outlier_10cm_pct", "outlier_10cm_pct_max", "loose_pred_pct",
           "loose_gt_pct")


def scan_frames(data: Path, subject: str, k: int) -> list[tuple[str, str, Path]]:
    """k train frames of ``subject`` evenly spaced: [(spec, sequence, frame path)]."""
    frames = [f for f in fmt.DatasetLayout(data).iter_frames("train", [subject])]
    if len(frames) < k:
        raise SystemExit(f"error: {data}: {subject} has {len(frames)} train frames, fewer than --scans {k}")
    picked = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, k).round()]
    out = []
    for _, seq, path in picked:
        index = int(fmt.read_frame(path, ["frame_index"]).frame_index)
        out.append((f"{data}:{subject}/train/{seq}/{index}", seq, path))
    return out


def cached_eval(path: Path, ckpt, data: Path, settings: EvalSettings, fresh: bool) -> dict:
    """``evaluate`` once, its result kept in ``path`` (JSON)."""
    if path.exists() and not fresh:
        return json.loads(path.read_text())
    result, _ = evaluate(ckpt, data, settings)
    out = result.to_dict()
    write_json_atomic(path, out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--subjects", nargs="+", help="default: every subject of --data")
    ap.add_argument("--ckpt-pocoloco", help="PocoLoco trained with --outfit-codes (run folder, checkpoint or 'default')")
    ap.add_argument("--ckpt-pop", help="POP run folder or checkpoint")
    ap.add_argument("--ckpt-hybrid", help="hybrid checkpoint (pocoloco hybrid): fits one scan, as POP")
    ap.add_argument("--scans", type=int, nargs="+", default=[1, 3], help="numbers of scans fitted (POP: 1 only)")
    ap.add_argument("--fit-steps", type=int, default=400)
    ap.add_argument("--start", choices=("nearest", "mean"), default="nearest", help="fit start (pocoloco fit --start)")
    ap.add_argument("--anchor", type=float, default=0.0, help="PocoLoco's pull to the start (pocoloco fit --anchor)")
    ap.add_argument("--frames", type=int, default=12, help="test frames per subject")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--work", type=Path, required=True, help="scans, fitted checkpoints and evaluations (reused)")
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    models = {k: resolve_ckpt_arg(v) for k, v in (("pocoloco", args.ckpt_pocoloco), ("pop", args.ckpt_pop),
                                                    ("hybrid", args.ckpt_hybrid)) if v}  # shipped names: default, default:pop, ...
    if not models:
        raise SystemExit("error: give --ckpt-pocoloco, --ckpt-pop and / or --ckpt-hybrid")
    card = fmt.read_card(args.data)
    subjects = args.subjects or sorted(card["subjects"])
    if args.fresh and args.work.exists():
        shutil.rmtree(args.work)
    args.work.mkdir(parents=True, exist_ok=True)

    def settings(subject: str, outfit: str | None = None, baselines=()) -> EvalSettings:
        return EvalSettings(split="test", num_frames=args.frames, num_points=args.points, seeds=tuple(args.seeds),
                            subjects=(subject,), baselines=baselines, clip=5.0, outfit=outfit)  # fmt: skip

    rows: list[dict] = []
    for subject in subjects:
        ref = cached_eval(args.work / f"ref_{subject}.json", None, args.data,
                          settings(subject, baselines=("posed_body", "gt_resample")), False)  # fmt: skip
        for key, title in (("posed_body", "posed body (no clothes)"), ("gt_resample", "GT resample (noise floor)")):
            rows.append({"subject": subject, "model": title, "scans": None, "stage": "reference",
                         **{c: ref["means"][key].get(c) for c in COLUMNS}})  # fmt: skip
        for kind, ckpt in models.items():
            method = load_method(ckpt)
            if method.kind != kind:
                raise SystemExit(f"error: --ckpt-{kind} {ckpt} is a {method.kind} checkpoint")
            for k in sorted(set(args.scans)):
                if kind in ("pop", "hybrid") and k != 1:
                    continue  # POP fits one scan (its paper, Eq. 7), and so does the hybrid's POP part
                tag = f"{kind}_{subject}_k{k}"
                fitted = args.work / tag
                if not (fitted / "fit.json").exists():
                    if fitted.exists():
                        shutil.rmtree(fitted)  # a fit killed half-way: start it again
                    scans = []
                    for spec, seq, path in scan_frames(args.data, subject, k):
                        ply = args.work / "scans" / f"{subject}_{seq}_{spec.rsplit('/', 1)[1]}.ply"
                        if not ply.exists():
                            ply.parent.mkdir(parents=True, exist_ok=True)
                            export_frame(path, ply, "ply")
                        scans.append((ply, spec))
                    t0 = time.perf_counter()
                    fit_outfit(ckpt, scans, fitted, name=subject, steps=args.fit_steps, start=args.start,
                               anchor=args.anchor if kind != "pop" else 0.0)  # fmt: skip
                    print(f"fitted {tag} in {time.perf_counter() - t0:.0f} s", flush=True)
                rep = json.loads((fitted / "fit.json").read_text())
                nearest = rep["before_nearest_outfit"]["outfit"]
                if k == min(args.scans):  # 'before' does not depend on k
                    before = cached_eval(args.work / f"before_{kind}_{subject}.json", ckpt, args.data,
                                         settings(subject, outfit=nearest), False)  # fmt: skip
                    rows.append({"subject": subject, "model": kind, "scans": 0, "stage": f"before ({nearest})",
                                 **{c: before["means"]["model"].get(c) for c in COLUMNS}})  # fmt: skip
                after = cached_eval(args.work / f"after_{tag}.json", fitted, args.data, settings(subject), False)
                rows.append({"subject": subject, "model": kind, "scans": k, "stage": "after",
                             "fit_seconds": rep["seconds"], "on_scan_before_cm": rep["before_nearest_outfit"]["chamfer_cm"],
                             "on_scan_after_cm": rep["after"]["chamfer_cm"],
                             **{c: after["means"]["model"].get(c) for c in COLUMNS}})  # fmt: skip

    print("| subject | model | scans fitted | outfit | Chamfer cm | S2M | M2S | >10 cm % (max) | loose % (GT) | on scan cm | fit s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        def f(v, p="{:.2f}"):
            return "-" if v is None else p.format(v)

        on_scan = (f"{r['on_scan_before_cm']:.2f} -> {r['on_scan_after_cm']:.2f}" if "on_scan_after_cm" in r else "")
        print(f"| {r['subject']} | {r['model']} | {'' if r['scans'] is None else r['scans']} | {r['stage']} | "
              f"{f(r['chamfer_cm'])} | {f(r['s2m_cm'])} | {f(r['m2s_cm'])} | {f(r['outlier_10cm_pct'], '{:.1f}')} "
              f"({f(r['outlier_10cm_pct_max'], '{:.1f}')}) | {f(r['loose_pred_pct'], '{:.1f}')} ({f(r['loose_gt_pct'], '{:.1f}')}) | {on_scan} | "
              f"{f(r.get('fit_seconds'), '{:.0f}')} |")  # fmt: skip
    if args.json:
        write_json_atomic(args.json, {"data": str(args.data), "models": {k: str(v) for k, v in models.items()},
                                      "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                                      "rows": rows})  # fmt: skip
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
