"""Cloth solver settings (substeps, iterations, self-contact) on the pipeline's own sequences.

Simulates the garment of each chosen subject on the motions ``pocoloco data synth`` would
generate for it (same seeds, blend and warm-up frames, settle) and judges the *stored*
frames as the pipeline does: penetration into the full body mesh, stretch, rejected frames,
plus cloth self-intersection (pairs of garment triangles that cross each other, open3d's
``get_self_intersecting_triangles``; adjacent triangles do not count). Time is process CPU
seconds per simulated frame (settling and kernel compilation excluded), so other jobs on the
machine matter less; wall seconds are in the JSON.

    python benchmarks/experiments/bench_cloth_settings.py --preset small --sequences 2 --frames 40 \
        --variants "10x5" "10x3" "10x3 sc" [--subjects skirt shirt] [--out benchmarks/results/cloth_settings.json]

A variant is "SUBSTEPSxITERATIONS" optionally followed by "sc" (self-contact on), "iso"
(the garment in ``tessellation="isotropic"``, default: the kind's grid) and ``key=value``
overrides of ``ClothSimSettings`` (python literals).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import time

import numpy as np


def parse_variant(text: str):
    from pocoloco.synth.cloth_sim import ClothSimSettings

    parts = text.split()
    sub, it = (int(x) for x in parts[0].split("x"))
    over = dict(substeps=sub, iterations=it, self_contact=False)
    tess = "grid"
    for p in parts[1:]:
        if p == "sc":
            over["self_contact"] = True
        elif p == "iso":
            tess = "isotropic"
        else:
            k, v = p.split("=", 1)
            over[k] = ast.literal_eval(v)
    return dataclasses.replace(ClothSimSettings(), **over), tess


def sequences(config, subject, count: int, names: list[str] | None = None):
    """Body, garments {tessellation: Garment} and (name, posed body, first stored frame, motion
    kinds) for the first ``count`` jobs of a subject (or the jobs named in ``names``)."""
    from pocoloco.body import AnnyBody
    from pocoloco.synth.garments import make_garment
    from pocoloco.synth.motion import generate_motion, rest_to_motion
    from pocoloco.synth.pipeline import job_seed, list_jobs

    body = AnnyBody(subject.phenotype)
    tess = ("grid", "isotropic") if subject.garment in ("skirt", "long_shirt") else ("isotropic",)
    garment = {t: make_garment(subject.garment, body, config.garment_resolution, tessellation=t,
                               **dict(subject.garment_params)) for t in tess}  # fmt: skip
    out = []
    jobs = [j for j in list_jobs(config) if j.subject.name == subject.name]
    jobs = [j for j in jobs if j.name in names] if names else jobs[:count]
    for job in jobs:
        seed = job_seed(config, job)
        m = generate_motion(seed, config.frames_per_sequence + config.warmup_frames, split=job.split,
                            fps=config.fps, body=body)  # fmt: skip
        full = rest_to_motion(m, config.blend_frames, body=body)
        out.append((job.name, body.pose(full.joint_rotvecs, full.root_translation),
                    full.num_frames - config.frames_per_sequence, [s[0] for s in m.segments]))  # fmt: skip
    return body, garment, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--subjects", nargs="*", default=None)
    ap.add_argument("--sequences", type=int, default=2, help="sequences per subject (train first, then test)")
    ap.add_argument("--frames", type=int, default=40, help="stored frames per sequence")
    ap.add_argument("--variants", nargs="+", default=["10x5", "10x3", "10x3 sc"])
    ap.add_argument("--names", nargs="*", default=None, help="sequence names (e.g. train_0000) instead of the first N")
    ap.add_argument("--garment", default=None, help="dress the chosen subjects in this kind instead of theirs")
    ap.add_argument("--out", default="benchmarks/results/cloth_settings.json")
    args = ap.parse_args()

    from pocoloco.synth.cloth_sim import simulate_garment
    from pocoloco.synth.config import synth_preset
    from pocoloco.synth.garments import self_intersections

    config = dataclasses.replace(synth_preset(args.preset), frames_per_sequence=args.frames)
    subjects = [s for s in config.subjects if s.garment != "tight" and (not args.subjects or s.name in args.subjects)]
    if args.garment:
        subjects = [dataclasses.replace(s, garment=args.garment, garment_params={}) for s in subjects]
    variants = [(v, parse_variant(v)) for v in args.variants]
    data = [(s, *sequences(config, s, args.sequences, args.names)) for s in subjects]
    # warm-up: compile the kernels of every variant on a short clip
    for _, (settings, tess) in variants:
        s, body, garments, seqs = data[0]
        posed = seqs[0][1]
        short = type(posed)(posed.vertices[:2], posed.joints[:2], posed.vtransf[:2])
        simulate_garment(body, garments[tess], short, dataclasses.replace(settings, settle_frames=1))
    rows = []
    for name, (settings, tess) in variants:
        for s, body, garments, seqs in data:
            garment = garments[tess]
            for seq_name, posed, start, kinds in seqs:
                c0, w0 = time.process_time(), time.perf_counter()
                res = simulate_garment(body, garment, posed, settings)
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
                st = res.stats[start:]
                inter = [self_intersections(v, garment.faces) for v in res.vertices[start:]]
                pen = np.array([x.penetration_max for x in st])
                row = dict(
                    variant=name, subject=s.name, garment=s.garment, sequence=seq_name, motions=kinds,
                    vertices=int(len(garment.rest_vertices)), stored_frames=len(st),
                    cpu_s_per_frame=res.cpu_seconds_per_frame, wall_s_per_frame=res.seconds_per_frame,
                    cpu_s_total=cpu, wall_s_total=wall,
                    rejected=int(sum(not x.valid for x in st)), resets=res.reset_count,
                    reasons=sorted({x.reason for x in st if x.reason}),
                    pen_max_mm=float(1000 * pen.max()), pen_median_max_mm=float(1000 * np.median(pen)),
                    pen_mean_mm=float(1000 * np.mean([x.penetration_mean for x in st])),
                    inside_pct=float(100 * np.mean([x.penetration_fraction for x in st])),
                    stretch_max=float(max(x.stretch_max for x in st)),
                    self_intersections_mean=float(np.mean(inter)), self_intersections_max=int(max(inter)),
                    frames_with_self_intersection_pct=float(100 * np.mean(np.array(inter) > 0)),
                )  # fmt: skip
                rows.append(row)
                print(json.dumps(row), flush=True)
    # summary per variant (all subjects and sequences pooled)
    print(f"\n{args.sequences} sequences x {len(subjects)} subjects, {args.frames} stored frames each (+ lead-in)")
    print("| variant | CPU s / sim. frame | rejected | pen max mm | median frame max mm | mean mm | % inside | "
          "stretch max | self-int. pairs / frame | frames with self-int. % |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary = []
    for name, _ in variants:
        rs = [r for r in rows if r["variant"] == name]
        n = sum(r["stored_frames"] for r in rs)
        def w(k, rs=rs, n=n):
            return sum(r[k] * r["stored_frames"] for r in rs) / n

        srow = dict(variant=name, cpu_s_per_frame=float(np.mean([r["cpu_s_per_frame"] for r in rs])),
                    rejected=sum(r["rejected"] for r in rs), stored=n, pen_max_mm=max(r["pen_max_mm"] for r in rs),
                    pen_median_max_mm=w("pen_median_max_mm"), pen_mean_mm=w("pen_mean_mm"),
                    inside_pct=w("inside_pct"), stretch_max=max(r["stretch_max"] for r in rs),
                    self_intersections_mean=w("self_intersections_mean"),
                    frames_with_self_intersection_pct=w("frames_with_self_intersection_pct"))  # fmt: skip
        summary.append(srow)
        print(f"| {name} | {srow['cpu_s_per_frame']:.3f} | {srow['rejected']} / {n} | {srow['pen_max_mm']:.1f} | "
              f"{srow['pen_median_max_mm']:.2f} | {srow['pen_mean_mm']:.3f} | {srow['inside_pct']:.2f} | "
              f"{srow['stretch_max']:.2f} | {srow['self_intersections_mean']:.1f} | "
              f"{srow['frames_with_self_intersection_pct']:.0f} |")  # fmt: skip
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(dict(preset=args.preset, sequences=args.sequences, frames=args.frames, summary=summary, rows=rows,
                       load_avg_1min=os.getloadavg()[0]), f, indent=1)  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
