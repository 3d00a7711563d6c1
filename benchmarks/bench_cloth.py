"""Cloth simulation speed vs faithfulness for several collider set-ups.

For each set-up, simulates a garment on one procedural motion (rest -> walk/spin)
and reports seconds per output frame (wall clock and process CPU time; the
machine may be shared) and penetration of the cloth into the *full* body mesh.

    python benchmarks/bench_cloth.py [--frames 40] [--out benchmarks/results/cloth.json] [--render /tmp/cloth]

Kernel compilation is excluded (a warm-up run first); settling is excluded.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import numpy as np

from pocoloco.body.anny_body import AnnyBody
from pocoloco.synth.config import DEFAULT_SUBJECTS
from pocoloco.synth.cloth_sim import ClothSimSettings, simulate_garment
from pocoloco.synth.garments import make_garment

#: (name, garment kind, settings overrides)
SETUPS: tuple[tuple[str, str, dict], ...] = (
    ("capsules 10x5", "skirt", dict(collider="capsules")),
    ("mesh 10x5, 2 cm margin, mu 0.2", "skirt", dict(collider="mesh", contact_margin=0.02, contact_mu=0.2, contact_ke=1e4)),
    ("mesh 10x5 (default)", "skirt", dict(collider="mesh")),
    ("mesh 5x5", "skirt", dict(collider="mesh", substeps=5)),
    ("mesh 10x3", "skirt", dict(collider="mesh", iterations=3)),
    ("mesh 10x5 (default)", "long_shirt", dict(collider="mesh")),
)


def make_motion_rotvecs(body: AnnyBody, frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(T, 24, 3) rotations and (T, 3) translations: 10 frames from rest, then walk/spin."""
    try:
        from pocoloco.synth.motion import generate_motion, rest_to_motion

        m = rest_to_motion(generate_motion(seed, frames - 10, "train", kinds=("spin", "walk"), body=body), 10, body)
        return m.joint_rotvecs, m.root_translation
    except ImportError:  # a hand-written walk with turning
        t = np.arange(frames) / 25.0
        w = np.clip(np.arange(frames) / 10, 0, 1)
        ph = 2 * np.pi * t
        r = np.zeros((frames, 24, 3), np.float32)
        r[:, 1, 0], r[:, 2, 0] = -0.5 * np.sin(ph) * w, 0.5 * np.sin(ph) * w
        r[:, 4, 0] = 0.6 * np.clip(np.sin(ph + 1.2), 0, None) * w
        r[:, 5, 0] = 0.6 * np.clip(-np.sin(ph + 1.2), 0, None) * w
        r[:, 0, 2] = 1.5 * t * w
        return r, np.zeros((frames, 3), np.float32)


def render(path: str, body_v: np.ndarray, cloth_v: np.ndarray, title: str) -> None:
    """Front and side views of the body's vertices (skin) and the cloth's (garment blue), drawn by
    the package's cloud renderer (shaded by estimated normals)."""
    from pocoloco.viz.render import render_grid

    body_v = body_v[::3]
    points = np.concatenate([body_v, cloth_v])
    labels = np.concatenate([np.zeros(len(body_v), np.int64), np.ones(len(cloth_v), np.int64)])
    render_grid([(points, labels, None, title)], path, views=("front", "side"), panel_size=4.0, dpi=80)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out", default="benchmarks/results/cloth.json")
    ap.add_argument("--render", default="", help="prefix for PNG renders of some frames (empty: none)")
    args = ap.parse_args()

    # each garment on the body of the `small` preset's subject wearing it
    phenotypes = {s.garment: s.phenotype for s in DEFAULT_SUBJECTS}
    bodies = {k: AnnyBody(phenotypes[k]) for k in {s[1] for s in SETUPS}}
    garments = {k: make_garment(k, b) for k, b in bodies.items()}
    poses = {}
    for k, b in bodies.items():
        rot, trans = make_motion_rotvecs(b, args.frames)
        poses[k] = b.pose(rot, trans)
    body = bodies["skirt"]
    t0 = time.perf_counter()  # warm-up: compile the kernels of both colliders
    for coll in ("capsules", "mesh"):
        simulate_garment(body, make_garment("skirt", body, resolution=0.3), body.pose(rot[:2], trans[:2]),
                         ClothSimSettings(collider=coll, settle_frames=1))  # fmt: skip
    print(f"warm-up (kernel compilation) {time.perf_counter() - t0:.1f} s")

    rows = []
    for name, kind, over in SETUPS:
        settings = dataclasses.replace(ClothSimSettings(), **over)
        posed = poses[kind]
        seq = simulate_garment(bodies[kind], garments[kind], posed, settings)
        pen_max = np.array([s.penetration_max for s in seq.stats])
        pen_mean = np.array([s.penetration_mean for s in seq.stats])
        frac = np.array([s.penetration_fraction for s in seq.stats])
        row = dict(
            setup=name, garment=kind, vertices=int(garments[kind].rest_vertices.shape[0]),
            frames=len(seq.stats), substeps=settings.substeps, iterations=settings.iterations,
            collider=settings.collider, seconds_per_frame=seq.seconds_per_frame,
            cpu_seconds_per_frame=seq.cpu_seconds_per_frame,
            penetration_max_cm=float(pen_max.max() * 100), penetration_max_median_cm=float(np.median(pen_max) * 100),
            penetration_mean_mm=float(pen_mean.mean() * 1000), penetration_fraction_pct=float(frac.mean() * 100),
            stretch_max=float(max(s.stretch_max for s in seq.stats)),
            invalid_frames=int((~seq.valid).sum()), resets=seq.reset_count,
            reasons=sorted({s.reason for s in seq.stats if s.reason}),
        )  # fmt: skip
        rows.append(row)
        print(json.dumps(row))
        if args.render:
            tag = f"{kind}_{settings.collider}_{settings.substeps}x{settings.iterations}"
            for t in (0, len(seq.stats) // 2, len(seq.stats) - 1):
                title = f"{name} {kind} frame {t}"
                render(f"{args.render}_{tag}_{t:03d}.png", posed.vertices[t], seq.vertices[t], title)

    cols = ("s/frame", "cpu s/f", "pen max cm", "med max cm", "mean mm", "% inside", "stretch", "invalid")
    print(f"{'setup':32s} {'garment':10s} " + " ".join(f"{c:>10s}" for c in cols))
    for r in rows:
        keys = ("seconds_per_frame", "cpu_seconds_per_frame", "penetration_max_cm", "penetration_max_median_cm",
                "penetration_mean_mm", "penetration_fraction_pct", "stretch_max")  # fmt: skip
        vals = " ".join(f"{r[k]:10.3f}" for k in keys)
        print(f"{r['setup']:32s} {r['garment']:10s} {vals} {r['invalid_frames']:10d}")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(dict(frames=args.frames, fps=25.0, rows=rows), f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
