"""Which finishing step of the teacher, seen by the judge: the proper score and the probe bias (issue 42).

For every pose of a reference set (``pocoloco data histories``), the teacher draws ``--samples``
clouds and the distilled student draws as many with its teacher's finishing call re-noised to each
``--ts`` step (``default:fast`` samples 3 calls of its own, then the teacher's at t; the weights are
the same, only the step changes). Every set of clouds is scored as ``pocoloco bench distribution``
scores it (:func:`pocoloco.evaluation.distribution.pose_statistics` on the same probes and the true
states cut to the same point count), and by its **probe bias**: the mean over samples and probes of
the probe-distance embedding minus the true states' mean embedding (mm). A positive bias is a cloud
that lies inside the true surface on average (the probes are farther from it). The teacher's x0
estimate at step t is a posterior mean over a noise of ~13 mm at t = 20, ~6 mm at t = 5: it
smooths the student's fuzz and shrinks the cloud with it. ``--teacher-ts T ...`` adds rows of
the teacher's own clouds given one more call of its own the same way (its 25 calls end on an x0
estimate from step 40 too).

    python benchmarks/experiments/polish_probe_bias.py --refs data/medium_v4_std_test --ts 20 10 5 \\
        --samples 8 --json polish_probe_bias_test.json

Prints the energy score of each row as a ratio to the teacher's (the mean of per-pose ratios,
with its standard error), the distance to the true states, the spread and the bias, per window of
shared motion. One seed set for every row (paired).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def own_finishing_call(method, subject: str, joints: np.ndarray, clouds, t: int, seeds) -> list[np.ndarray]:
    """``clouds`` (M of (N, 3), metres, drawn under ``joints``) re-noised to step t and ``method``'s
    own x0 there: one DDIM call from t, the renoising noise from seeds + 7919 (what a student's
    finishing call does, here a model's after its own chain; ``teacher_finish.py`` uses it too).
    The library's ``--finish-t`` does the same with the sampler's own generator."""
    from pocoloco.apps.common import denoise_from, to_metres, to_normalised

    prior = method.point_prior(method.outfit_id(subject))
    joints = np.asarray(joints)
    x0 = to_normalised(method.normalisation, np.stack([np.asarray(c) for c in clouds]), None, joints, 3)
    x = denoise_from(prior, joints, x0, t, sampler="ddim", steps=1, seeds=[s + 7919 for s in seeds])
    return list(to_metres(method.normalisation, x, joints)[0])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refs", required=True, help="a reference set (pocoloco data histories)")
    ap.add_argument("--student", default="default:fast")
    ap.add_argument("--teacher", default="default")
    ap.add_argument("--ts", type=int, nargs="+", default=[20, 5], help="the teacher's finishing steps to compare")
    ap.add_argument("--teacher-ts", type=int, nargs="*", default=[],
                    help="also the teacher's own clouds given one more call of its own at these steps")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--probes", type=int, default=512)
    ap.add_argument("--subjects", nargs="*", default=None, help="only these subjects (default: all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from pocoloco.data.format import read_card, read_frame
    from pocoloco.data.poses import Pose
    from pocoloco.engine.shipped import resolve_ckpt_arg
    from pocoloco.evaluation.distribution import embed_cloud, pose_statistics, probe_points
    from pocoloco.evaluation.judge import _subsample
    from pocoloco.methods import load_method
    from pocoloco.synth.histories import reference_sets

    refs = Path(args.refs)
    hist = read_card(refs)["histories"]
    teacher = load_method(resolve_ckpt_arg(args.teacher))
    student = load_method(resolve_ckpt_arg(args.student))
    if student.polish is None:
        raise SystemExit(f"{args.student} has no finishing teacher (export it with --polish-with)")
    network = student.polish[0]
    probe = probe_points(args.probes, seed=0)
    seeds = list(range(args.samples))
    poses: dict[tuple, list[dict]] = {}
    for p in reference_sets(refs):
        if args.subjects is None or p["subject"] in args.subjects:
            poses.setdefault((p["subject"], p["source"]["sequence"], p["source"]["frame"]), []).append(p)
    rows: dict[str, dict[str, list]] = {}  # row -> window -> [per pose statistics]
    for i, ((subject, _, _), windows) in enumerate(poses.items()):
        joints = read_frame(windows[0]["own"]).joints
        pose = Pose.load(f"{refs}:{subject}/{windows[0]['split']}/{windows[0]['sequence']}/{hist['histories']}")
        truths = {f"{w['shared_seconds']:g}": [_subsample(read_frame(f, ["points"]).points, args.points, 7 * k)
                                               for k, f in enumerate([*w["refs"], w["own"]])] for w in windows}  # fmt: skip
        drawn = {"teacher": teacher.sample(pose, args.points, seeds).points}
        for t in args.teacher_ts:  # the teacher's answer, re-noised to t and its own x0 there (one call more)
            drawn[f"teacher_t{t}"] = own_finishing_call(teacher, pose.subject, pose.joints, drawn["teacher"], t, seeds)
        for t in args.ts:
            student.polish = (network, t)
            drawn[f"student_t{t}"] = student.sample(pose, args.points, seeds).points
        for name, clouds in drawn.items():
            clouds = [np.asarray(c, np.float64) for c in clouds]
            emb = np.stack([embed_cloud(c, joints, probe) for c in clouds])
            for window, truth in truths.items():
                mean_truth = np.mean([embed_cloud(c, joints, probe) for c in truth], axis=0)
                s = pose_statistics(clouds, truth, joints, probe)
                rows.setdefault(name, {}).setdefault(window, []).append(
                    {"subject": subject, "energy_score": s["energy_score"], "to_refs": s["to_refs"],
                     "spread_samples": s["spread_samples"], "bias_mm": float((emb - mean_truth).mean() * 1000)})  # fmt: skip
        print(f"pose {i + 1} / {len(poses)} ({subject})", file=sys.stderr, flush=True)

    cm = 100.0 / np.sqrt(args.probes)  # raw embedding distance (m over P probes) -> cm per probe
    summary = []
    print("| row | window s | ES / teacher's - 1 (paired) | to the truth cm | spread cm | probe bias mm |")
    print("|---|---|---|---|---|---|")
    for window in rows["teacher"]:
        base = np.array([r["energy_score"] for r in rows["teacher"][window]])
        for name in rows:
            v = rows[name][window]
            ratio = np.array([r["energy_score"] for r in v]) / base - 1.0
            line = {"row": name, "window": window, "es_ratio_minus_1": float(ratio.mean()),
                    "es_ratio_se": float(ratio.std(ddof=1) / np.sqrt(len(ratio))),
                    "to_refs_cm": float(np.mean([r["to_refs"] for r in v]) * cm),
                    "spread_cm": float(np.mean([r["spread_samples"] for r in v]) * cm),
                    "bias_mm": float(np.mean([r["bias_mm"] for r in v]))}  # fmt: skip
            summary.append(line)
            print(f"| {name} | {window} | {100 * line['es_ratio_minus_1']:+.1f} +- {100 * line['es_ratio_se']:.1f} % | "
                  f"{line['to_refs_cm']:.2f} | {line['spread_cm']:.2f} | {line['bias_mm']:.2f} |")  # fmt: skip
    out = {"settings": {k: v for k, v in vars(args).items() if k != "json"}, "summary": summary, "per_pose": rows}
    Path(args.json).write_text(json.dumps(out, separators=(",", ":")))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
