"""How much the simulated cloth depends on motion history, not only on the pose.

Several motions of different kinds (spin, walk, kick, ...) are each followed by
a smooth blend into the same rest pose, which is then held. At fixed times
after arrival the *body* is identical across histories (checked), so any
difference in the garment is history: momentum still swinging, folds that
stay. Reported: mean / max distance (cm) between the garments of every pair
of histories, root-relative, at 0, 0.2, 0.5 and 1 s after arrival. This is why
PocoLoco models p(cloth | pose) as a distribution.

    python benchmarks/experiments/bench_history.py [--garment skirt] [--kinds spin walk kick] [--out ...]
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from pocoloco.body import AnnyBody
from pocoloco.synth.cloth_sim import simulate_garment
from pocoloco.synth.config import DEFAULT_SUBJECTS
from pocoloco.synth.garments import make_garment
from pocoloco.synth.motion import generate_motion, rest_to_motion


def history_then_rest(body, kind: str, seed: int, frames: int, blend: int, hold: int):
    """(T, 24, 3) rotations, (T, 3) translations: rest -> motion -> blend to rest -> hold."""
    m = rest_to_motion(generate_motion(seed, frames, "train", kinds=(kind,), body=body), 12, body)
    rot, trans = m.joint_rotvecs, m.root_translation
    w = 0.5 - 0.5 * np.cos(np.linspace(0, np.pi, blend))[:, None, None]  # smooth 0 -> 1
    back = (1 - w) * rot[-1][None]  # into the zero pose
    rot = np.concatenate([rot, back, np.zeros((hold, 24, 3), np.float32)]).astype(np.float32)
    trans = np.concatenate([trans, np.repeat(trans[-1:], blend + hold, 0)]).astype(np.float32)
    return rot, trans, len(m.joint_rotvecs) + blend - 1  # index of arrival


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--garment", default="skirt", choices=["skirt", "long_shirt"])
    ap.add_argument("--kinds", nargs="+", default=["spin", "walk", "kick"])
    ap.add_argument("--frames", type=int, default=40, help="frames of motion before the blend")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/history.json")
    args = ap.parse_args()

    subject = next(s for s in DEFAULT_SUBJECTS if s.garment == args.garment)
    body = AnnyBody(subject.phenotype)
    garment = make_garment(args.garment, body)
    delays = {"0 s": 0, "0.2 s": 5, "0.5 s": 12, "1 s": 25}
    cloth, bodies = {}, {}
    for kind in args.kinds:
        rot, trans, arrive = history_then_rest(body, kind, args.seed, args.frames, blend=12, hold=26)
        posed = body.pose(rot, trans)
        seq = simulate_garment(body, garment, posed)
        root = posed.joints[:, :1]  # (T, 1, 3)
        idx = [arrive + d for d in delays.values()]
        cloth[kind] = (seq.vertices - root)[idx]
        bodies[kind] = (posed.vertices - root)[idx]
        print(f"{kind}: simulated {len(seq.stats)} frames, invalid {int((~seq.valid).sum())}")

    rows = []
    for a, b in itertools.combinations(args.kinds, 2):
        body_diff = float(np.abs(bodies[a] - bodies[b]).max() * 100)
        d = np.linalg.norm(cloth[a] - cloth[b], axis=-1) * 100  # (D, Vg) cm
        rows.append({"pair": f"{a} vs {b}", "body_max_cm": body_diff,
                     **{f"mean_cm@{k}": float(d[i].mean()) for i, k in enumerate(delays)},
                     **{f"max_cm@{k}": float(d[i].max()) for i, k in enumerate(delays)}})  # fmt: skip
    print(f"{args.garment}: garment distance between histories at the same pose (cm, mean / max)")
    print(f"{'pair':16s} {'body max':>9s} " + " ".join(f"{k:>14s}" for k in delays))
    for r in rows:
        cells = " ".join(f"{r[f'mean_cm@{k}']:6.2f} / {r[f'max_cm@{k}']:5.1f}" for k in delays)
        print(f"{r['pair']:16s} {r['body_max_cm']:9.4f} {cells}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"garment": args.garment, "kinds": args.kinds, "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
