"""How much the last seconds of motion close the gap (issue 41): a motion-aware model against the
pose-only model it was fine-tuned from, on the same frames, paired per frame.

Inputs are ``pocoloco bench quality`` reports (``quality.json``) of one split with the same frames,
points and seeds: the pose-only reference row, the motion-aware row given each frame's own window
(``--history dataset``), none (``--history rest``) and another frame's (``--history shuffled``), and
optionally a pose-only peer (POP) to reach. Per split it prints and writes:

* Chamfer and loose-garment M2S (the loose subjects' garment points to the scan), each paired with
  the reference (mean difference +- standard error);
* ``shuffled_lost_pct``: the share of the gain over the reference that a shuffled window loses
  ((shuffled - dataset) / (reference - dataset), Chamfer); 100 % = it was all the motion's;
* ``worst_tenth``: the frames in the reference's worst tenth by Chamfer (the flaring ones), their
  mean Chamfer before and after, and the improvement in %;
* the peer's Chamfer overall and on the loose subjects, on the same frames.

    python benchmarks/motion_gain.py --reference REF/test/quality.json:pocoloco \\
        --dataset MOTION/dataset/test/quality.json:pocoloco --rest MOTION/rest/test/quality.json:pocoloco \\
        --shuffled MOTION/shuffled/test/quality.json:pocoloco --peer REF/test/quality.json:pop --json gain.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

#: subjects whose garment hangs free of the body (the loose-garment columns are defined on them)
TIGHT_PREFIX = "tight"


def rows(spec: str) -> dict[str, dict]:
    """``FILE:ROW`` -> {frame key: {"subject", metrics...}}."""
    path, _, row = spec.rpartition(":")
    data = json.loads(Path(path).read_text())
    frames = data["frames"]
    if row not in frames:
        raise SystemExit(f"{path}: no row {row!r} (it has {', '.join(frames)})")
    return {r["key"]: {"subject": r["subject"], **r["model"]} for r in frames[row]}


def mean(xs: list[float]) -> float:
    return sum(xs) / len(xs) if xs else float("nan")


def paired(ref: dict, other: dict, metric: str, keys: list[str]) -> dict[str, float]:
    keys = [k for k in keys if ref[k].get(metric) is not None and other[k].get(metric) is not None]
    d = [float(other[k][metric]) - float(ref[k][metric]) for k in keys]
    n = len(d)
    m = mean(d)
    se = math.sqrt(sum((v - m) ** 2 for v in d) / (n - 1) / n) if n > 1 else float("nan")
    return {"n": n, "reference": mean([float(ref[k][metric]) for k in keys]),
            "model": mean([float(other[k][metric]) for k in keys]), "diff": m, "se": se}  # fmt: skip


def gain(reference: str, dataset: str, rest: str | None, shuffled: str | None, peer: str | None) -> dict:
    ref, mot = rows(reference), rows(dataset)
    keys = sorted(k for k in ref if k in mot)
    if not keys:
        raise SystemExit(f"{reference} and {dataset} share no frames")
    loose = [k for k in keys if not ref[k]["subject"].startswith(TIGHT_PREFIX)]
    out: dict = {"frames": len(keys), "loose_frames": len(loose)}
    for name, spec in (("dataset", dataset), ("rest", rest), ("shuffled", shuffled)):
        if spec is None:
            continue
        other = rows(spec)
        out[name] = {"chamfer_cm": paired(ref, other, "chamfer_cm", keys),
                     "chamfer_loose_cm": paired(ref, other, "chamfer_cm", loose),
                     "m2s_garment_loose_cm": paired(ref, other, "m2s_garment_cm", loose)}  # fmt: skip
    if "shuffled" in out:
        g = out["dataset"]["chamfer_cm"]["diff"]
        lost = out["shuffled"]["chamfer_cm"]["diff"] - g
        out["shuffled_lost_pct"] = 100.0 * lost / -g if g < 0 else float("nan")
    worst = sorted(keys, key=lambda k: ref[k]["chamfer_cm"], reverse=True)[: max(1, round(len(keys) / 10))]
    before = mean([ref[k]["chamfer_cm"] for k in worst])
    after = mean([mot[k]["chamfer_cm"] for k in worst])
    out["worst_tenth"] = {"frames": worst, "reference_cm": before, "model_cm": after,
                          "improvement_pct": 100.0 * (before - after) / before}  # fmt: skip
    if peer is not None:
        p = rows(peer)
        out["peer"] = {"chamfer_cm": mean([p[k]["chamfer_cm"] for k in keys if k in p]),
                       "chamfer_loose_cm": mean([p[k]["chamfer_cm"] for k in loose if k in p]),
                       "m2s_garment_loose_cm": mean([p[k]["m2s_garment_cm"] for k in loose
                                                     if k in p and p[k].get("m2s_garment_cm") is not None])}  # fmt: skip
    return out


def markdown(result: dict) -> str:
    lines = ["| given | Chamfer cm (paired diff) | loose subjects: Chamfer | loose garment M2S |", "|---|---|---|---|"]
    first = True
    for name in ("dataset", "rest", "shuffled"):
        if name not in result:
            continue
        r = result[name]
        if first:
            lines.append(f"| pose-only reference | {r['chamfer_cm']['reference']:.2f} | {r['chamfer_loose_cm']['reference']:.2f} "
                         f"| {r['m2s_garment_loose_cm']['reference']:.2f} |")  # fmt: skip
            first = False
        cells = [f"{r[m]['model']:.2f} ({r[m]['diff']:+.2f} +- {r[m]['se']:.2f})"
                 for m in ("chamfer_cm", "chamfer_loose_cm", "m2s_garment_loose_cm")]  # fmt: skip
        lines.append(f"| window: {name} | " + " | ".join(cells) + " |")
    if "peer" in result:
        p = result["peer"]
        lines.append(f"| peer (pose-only) | {p['chamfer_cm']:.2f} | {p['chamfer_loose_cm']:.2f} | {p['m2s_garment_loose_cm']:.2f} |")
    w = result["worst_tenth"]
    lines.append("")
    lines.append(f"worst tenth of the reference's frames ({len(w['frames'])}): {w['reference_cm']:.2f} -> "
                 f"{w['model_cm']:.2f} cm ({w['improvement_pct']:+.1f} %)")  # fmt: skip
    if "shuffled_lost_pct" in result:
        lines.append(f"a shuffled window loses {result['shuffled_lost_pct']:.0f} % of the Chamfer gain")
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", required=True, help="FILE:ROW of the pose-only model")
    ap.add_argument("--dataset", required=True, help="FILE:ROW of the motion-aware model, --history dataset")
    ap.add_argument("--rest", help="FILE:ROW, --history rest")
    ap.add_argument("--shuffled", help="FILE:ROW, --history shuffled")
    ap.add_argument("--peer", help="FILE:ROW of a pose-only peer to reach (POP)")
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args(argv)
    result = gain(args.reference, args.dataset, args.rest, args.shuffled, args.peer)
    print(markdown(result))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
