"""Does the simulated cloth come to rest? Hem speed after an abrupt stop, history
distance at a held pose, and the hem's lag and flare while the body moves.

Each garment kind (on its ``medium`` "_a" subject) performs each motion kind (spin,
walk, kick, run: 1.6 s of the pipeline's own motion, from the rest pose; ``still``: no
motion at all, the body held in the rest pose throughout), blends into
the rest pose in 0.48 s and holds it until the last of ``--delays`` (default 4 s), simulated with the dataset
pipeline's cloth settings under each damping model (``none``: data v1 / v2; ``physical``:
data v3, ``synth.fabric``). Reported per garment, model and motion:

- ``hem_speed_cm_s@T``: mean speed of the hem (lowest fifth of the garment's rest
  vertices) relative to the body (the velocity of its nearest body vertex subtracted),
  T seconds after the body arrived in the held pose;
- ``history_cm@T``: mean distance between the garments of two histories at the same
  held pose (root-relative), averaged over the pairs of motions;
- in motion: ``motion_hem_speed_cm_s`` (mean hem speed relative to the body over the
  motion's frames), ``lag_cm`` (mean horizontal offset of the hem's centroid from the
  pelvis axis), ``flare_cm`` (mean gain of the hem's horizontal distance to the pelvis
  axis over the settled rest value: how far it swings out);
- ``seconds_per_frame``: the solver's wall-clock time per frame (1 thread per run).

    python benchmarks/bench_settle.py [--garments skirt ...] [--kinds spin walk kick run]
        [--damping none physical] [--set KEY=VALUE ...] [--delays 0.5 1 2 3 4] [--workers 2]
        [--out benchmarks/results/settle.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

DELAYS_S = (0.5, 1.0, 2.0, 3.0, 4.0)
SUBJECT_OF_KIND = {"skirt": "skirt_a", "maxi_skirt": "maxi_a", "dress": "dress_a", "long_shirt": "shirt_a",
                   "sleeved_shirt": "sleeves_a", "wide_trousers": "trousers_a"}  # fmt: skip


def history_then_rest(body, kind: str, seed: int, frames: int, blend: int, hold: int, fps: float):
    """(T, 24, 3) rotations, (T, 3) translations: rest -> motion -> smooth blend to rest -> hold;
    the index of the first frame of the held pose, and that of the motion's first frame."""
    from pocoloco.synth.motion import generate_motion, rest_to_motion

    lead = 12
    if kind == "still":  # no motion at all: the rest pose from the first frame (what the solver does alone)
        n = lead + frames + blend + hold
        return np.zeros((n, 24, 3), np.float32), np.zeros((n, 3), np.float32), lead + frames + blend - 1, lead
    m = rest_to_motion(generate_motion(seed, frames, "train", fps=fps, kinds=(kind,), body=body), lead, body)
    rot, trans = m.joint_rotvecs, m.root_translation
    w = 0.5 - 0.5 * np.cos(np.linspace(0, np.pi, blend))[:, None, None]  # smooth 0 -> 1
    back = (1 - w) * rot[-1][None]  # into the zero pose
    rot = np.concatenate([rot, back, np.zeros((hold, 24, 3), np.float32)]).astype(np.float32)
    trans = np.concatenate([trans, np.repeat(trans[-1:], blend + hold, 0)]).astype(np.float32)
    return rot, trans, len(m.joint_rotvecs) + blend - 1, lead


def relative_hem_speed(cloth: np.ndarray, body: np.ndarray, hem: np.ndarray, fps: float) -> np.ndarray:
    """(T,) mean speed [m/s] of the hem vertices relative to their nearest body vertex.

    cloth: (T, Vg, 3); body: (T, V, 3) (world); hem: (H,) vertex indices. Frame 0 gets 0."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(cloth))
    for t in range(1, len(cloth)):
        _, nn = cKDTree(body[t]).query(cloth[t, hem])
        v_cloth = (cloth[t, hem] - cloth[t - 1, hem]) * fps
        v_body = (body[t, nn] - body[t - 1, nn]) * fps
        out[t] = np.linalg.norm(v_cloth - v_body, axis=1).mean()
    return out


def run_one(job: dict) -> dict:
    """Simulate one (garment, damping, motion) history; returns its measurements and the
    root-relative garment at each delay (for the history distances)."""
    import torch

    torch.set_num_threads(1)
    from pocoloco.body import AnnyBody
    from pocoloco.synth.cloth_sim import simulate_garment
    from pocoloco.synth.config import CLOTH_VERSIONS, MEDIUM_SUBJECTS, SynthConfig
    from pocoloco.synth.garments import make_garment
    from pocoloco.synth.pipeline import cloth_settings

    subject = next(s for s in MEDIUM_SUBJECTS if s.name == SUBJECT_OF_KIND[job["garment"]])
    # the v3 cloth (plain sweeps unless --set chebyshev_rho=...) with this run's damping and mesh: what
    # --damping meant before v4 became the default
    config = dataclasses.replace(SynthConfig(), **{**CLOTH_VERSIONS["v3"], "cloth_damping": job["damping"],
                                                   "garment_tessellation": job.get("tessellation", "isotropic")})  # fmt: skip
    body = AnnyBody(subject.phenotype)
    garment = make_garment(subject.garment, body, resolution=config.garment_resolution,
                           tessellation=config.garment_tessellation, **subject.garment_params)  # fmt: skip
    fps = config.fps
    delays = job.get("delays", DELAYS_S)
    hold = int(round(max(delays) * fps)) + 2
    rot, trans, arrive, start = history_then_rest(body, job["kind"], job["seed"], job["frames"], 12, hold, fps)
    posed = body.pose(rot, trans)
    settings = cloth_settings(config, subject.garment)
    if job.get("set"):  # ClothSimSettings overrides (--set KEY=VALUE)
        settings = dataclasses.replace(settings, **job["set"])
    t0 = time.perf_counter()
    seq = simulate_garment(body, garment, posed, settings)
    wall = time.perf_counter() - t0
    rest = garment.rest_vertices
    hem = np.flatnonzero(rest[:, 2] <= np.quantile(rest[:, 2], 0.2))
    speed = relative_hem_speed(seq.vertices, posed.vertices, hem, fps) * 100  # cm/s
    root = posed.joints[:, 0]  # (T, 3)
    rel = seq.vertices - root[:, None]  # root-relative
    radius = np.linalg.norm(rel[:, hem, :2], axis=-1).mean(1)  # (T,) hem distance to the pelvis axis
    centroid = np.linalg.norm(rel[:, hem, :2].mean(1), axis=-1)  # (T,) hem centroid's offset
    moving = slice(start, arrive + 1)
    idx = [arrive + int(round(d * fps)) for d in delays]
    return {
        **job,
        "subject": subject.name,
        "invalid_frames": int((~seq.valid).sum()),
        "frames": len(seq.stats),
        "seconds_per_frame": seq.seconds_per_frame,
        "cpu_seconds_per_frame": seq.cpu_seconds_per_frame,
        "wall_s": wall,
        "hem_speed_cm_s": speed.tolist(),
        "arrive": arrive,
        "motion_start": start,
        **{f"hem_speed_cm_s@{d:g}s": float(speed[i]) for d, i in zip(delays, idx)},
        "motion_hem_speed_cm_s": float(speed[moving].mean()),
        "lag_cm": float(centroid[moving].mean() * 100),
        "flare_cm": float((radius[moving] - radius[start]).mean() * 100),
        "flare_max_cm": float((radius[moving] - radius[start]).max() * 100),
        "penetration_max_mm": float(np.nanmax([s.penetration_max for s in seq.stats]) * 1000),
        "garment_at_delays": rel[idx].astype(np.float32),
        "body_at_delays": (posed.vertices - root[:, None])[idx].astype(np.float32),
    }


def summarise(results: list[dict], delays: tuple[float, ...] = DELAYS_S) -> list[dict]:
    """One row per (garment, damping): hem speeds and motion measures averaged over motions,
    history distances averaged over motion pairs, at ``delays`` (seconds after the stop)."""
    rows = []
    key = lambda r: (r["garment"], r["damping"])  # noqa: E731
    for (garment, damping), group in itertools.groupby(sorted(results, key=key), key=key):
        group = list(group)
        row = {"garment": garment, "damping": damping, "motions": [r["kind"] for r in group]}
        for d in delays:
            row[f"hem_speed_cm_s@{d:g}s"] = float(np.mean([r[f"hem_speed_cm_s@{d:g}s"] for r in group]))
            row[f"hem_speed_max_cm_s@{d:g}s"] = float(np.max([r[f"hem_speed_cm_s@{d:g}s"] for r in group]))
        for k in ("motion_hem_speed_cm_s", "lag_cm", "flare_cm", "flare_max_cm", "seconds_per_frame",
                  "cpu_seconds_per_frame", "penetration_max_mm"):  # fmt: skip
            row[k] = float(np.mean([r[k] for r in group]))
        row["invalid_frames"] = int(sum(r["invalid_frames"] for r in group))
        pairs = list(itertools.combinations(group, 2))
        for i, d in enumerate(delays):
            dist = [np.linalg.norm(a["garment_at_delays"][i] - b["garment_at_delays"][i], axis=-1).mean() * 100
                    for a, b in pairs]  # fmt: skip
            row[f"history_cm@{d:g}s"] = float(np.mean(dist)) if dist else float("nan")
        body_diff = [np.abs(a["body_at_delays"] - b["body_at_delays"]).max() * 100 for a, b in pairs]
        row["body_max_diff_cm"] = float(max(body_diff)) if body_diff else 0.0
        rows.append(row)
    return rows


def main() -> None:
    from pocoloco.synth.fabric import DAMPING_MODELS
    from pocoloco.synth.garments import GARMENT_KINDS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--garments", nargs="+", default=["skirt"], choices=GARMENT_KINDS)
    ap.add_argument("--kinds", nargs="+", default=["spin", "walk", "kick", "run"])
    ap.add_argument("--damping", nargs="+", default=list(DAMPING_MODELS[::-1]), choices=DAMPING_MODELS)
    ap.add_argument("--frames", type=int, default=40, help="frames of motion before the blend (25 fps)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--tessellation", default=None,
                    help="garment tessellation (garments.TESSELLATIONS; default: the pipeline's, data v3's)")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="override ClothSimSettings fields, e.g. iterations=15 tri_kd=1.0")
    ap.add_argument("--curves", action="store_true", help="keep each run's hem-speed curve in the JSON")
    ap.add_argument("--delays", type=float, nargs="+", default=list(DELAYS_S),
                    help="seconds after the stop at which to report (the body holds the pose until the last)")
    ap.add_argument("--out", default="benchmarks/results/settle.json")
    args = ap.parse_args()
    delays = tuple(sorted(args.delays))
    if not delays or delays[0] <= 0:
        ap.error(f"--delays must be positive seconds, got {args.delays}")

    from pocoloco.synth.cloth_sim import ClothSimSettings

    fields = {f.name: f.type for f in dataclasses.fields(ClothSimSettings)}
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in fields or not value:
            ap.error(f"--set {item}: expected KEY=VALUE with KEY a ClothSimSettings field")
        default = getattr(ClothSimSettings(), key)
        overrides[key] = value == "True" if isinstance(default, bool) else type(default)(value)
    from pocoloco.synth.config import SynthConfig

    tessellation = args.tessellation or SynthConfig().garment_tessellation
    jobs = [{"garment": g, "damping": d, "kind": k, "seed": args.seed, "frames": args.frames, "set": overrides,
             "tessellation": tessellation, "delays": delays}
            for g in args.garments for d in args.damping for k in args.kinds]  # fmt: skip
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        tqdm = lambda x, **_: x  # noqa: E731
    results = []
    with ProcessPoolExecutor(args.workers) as pool:
        for r in tqdm(pool.map(run_one, jobs), total=len(jobs), desc="histories"):
            results.append(r)
            print(f"{r['garment']:14s} {r['damping']:9s} {r['kind']:6s} hem +2 s {r['hem_speed_cm_s@2s']:6.2f} cm/s"
                  f"  in motion {r['motion_hem_speed_cm_s']:6.1f} cm/s  invalid {r['invalid_frames']}"
                  f"  {r['seconds_per_frame']:.3f} s/frame", flush=True)  # fmt: skip
    rows = summarise(results, delays)
    hist = [d for d in (0.5, 1, 2, 4) if d in delays]
    head = ["garment", "damping"] + [f"v@{d:g}s" for d in delays] + [f"hist@{d:g}s" for d in hist] \
        + ["v move", "lag", "flare", "s/frame", "invalid"]  # fmt: skip
    print("hem speed relative to the body after the stop (cm/s, mean over motions), garment distance between"
          " histories (cm), in motion: hem speed (cm/s), lag and flare (cm)")
    print(" ".join(f"{h:>9s}" for h in head))
    for r in rows:
        cells = [r["garment"][:9], r["damping"]] + [f"{r[f'hem_speed_cm_s@{d:g}s']:.2f}" for d in delays] \
            + [f"{r[f'history_cm@{d:g}s']:.2f}" for d in hist] \
            + [f"{r['motion_hem_speed_cm_s']:.1f}", f"{r['lag_cm']:.2f}", f"{r['flare_cm']:.2f}",
               f"{r['seconds_per_frame']:.3f}", str(r["invalid_frames"])]  # fmt: skip
        print(" ".join(f"{c:>9s}" for c in cells))
    runs = [{k: v for k, v in r.items() if k not in ("garment_at_delays", "body_at_delays")
             and (args.curves or k != "hem_speed_cm_s")} for r in results]  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"delays_s": delays, "kinds": args.kinds, "seed": args.seed, "rows": rows,
                               "runs": runs}, indent=1))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
