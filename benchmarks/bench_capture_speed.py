"""Virtual capture, first implementation against today's, on simulated frames of the pipeline.

Frames: the `small` preset's skirt and shirt subjects (grid garments simulated on their first
training motion, every 6th frame after the lead-in) and the tight subject's body. Each frame
is captured with the preset's rig (40,000 points, 24 cameras) by

- ``v1``: the first implementation (``capture._visibility_reference``, whole candidate batches);
- ``exact``: today's visibility and early stop (the same points as v1, checked);
- ``cull``: + ``cull_hidden_faces`` (candidates only on faces whose vertex probes are seen).

Methods are interleaved per frame (same load); process CPU seconds per frame, median over
frames and repeats. For ``cull`` the share of the truly visible surface it cannot sample
(visible points of a 100K-candidate exact test that fall on dropped faces) and the change of
the loose-garment share are reported.

    python benchmarks/bench_capture_speed.py [--repeats 3] [--out benchmarks/results/capture_speed.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import time

import numpy as np


def frames(every: int = 6, count: int = 4):
    """(subject, list of CaptureMesh lists) for the skirt, shirt and tight subjects."""
    from pocoloco.body import AnnyBody
    from pocoloco.synth import capture as cap
    from pocoloco.synth.cloth_sim import ClothSimSettings, simulate_garment
    from pocoloco.synth.config import synth_preset
    from pocoloco.synth.garments import make_garment
    from pocoloco.synth.motion import generate_motion, rest_to_motion
    from pocoloco.synth.pipeline import job_seed, list_jobs

    config = synth_preset("small")
    out = []
    for subject in config.subjects:
        body = AnnyBody(subject.phenotype)
        job = next(j for j in list_jobs(config) if j.subject.name == subject.name)
        n = config.warmup_frames + every * count
        m = rest_to_motion(generate_motion(job_seed(config, job), n, job.split, body=body), config.blend_frames, body)
        posed = body.pose(m.joint_rotvecs, m.root_translation)
        start = config.blend_frames + config.warmup_frames
        cloth = None
        if subject.garment != "tight":
            garment = make_garment(subject.garment, body)
            cloth = simulate_garment(body, garment, posed, ClothSimSettings()).vertices
        part = body.vertex_joint[body.faces[:, 0]]
        scenes = []
        for t in range(start, start + every * count, every):
            meshes = [cap.CaptureMesh(posed.vertices[t], body.faces, cap.LABEL_BODY, part)]
            if cloth is not None:
                meshes.append(cap.CaptureMesh(cloth[t], garment.faces, cap.LABEL_GARMENT))
            scenes.append(meshes)
        out.append((subject.name, scenes))
    return out


def lost_visible(meshes, settings, candidates: int = 100_000) -> float:
    """Share of the visible surface on faces ``possibly_visible_faces`` drops."""
    from pocoloco.synth import capture as cap

    surface = cap._Surface(meshes)
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, np.uint32)))  # fmt: skip
    all_v = np.concatenate([np.asarray(m.vertices, np.float64) for m in meshes])
    lo, hi = all_v.min(0), all_v.max(0)
    cams = cap.camera_centres((lo + hi) / 2, settings.distance_factor * float(np.linalg.norm(hi - lo)) / 2,
                              settings.num_cameras, settings.min_elevation_deg, settings.max_elevation_deg)  # fmt: skip
    keep = cap.possibly_visible_faces(surface, scene, cams, settings.min_cos)
    face, p = surface.sample(candidates, np.random.default_rng(123))
    seen, _ = cap.visibility(scene, p, surface.normal[face], surface.side[face], cams, settings.min_cos,
                             settings.hit_tolerance)  # fmt: skip
    return float((seen & ~keep[face]).sum() / max(seen.sum(), 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/capture_speed.json")
    args = ap.parse_args()

    from pocoloco.synth import capture as cap

    base = cap.CaptureSettings(num_points=40_000, num_cameras=24)

    def v1(meshes, s):
        vis, chunk = cap.visibility, cap._CAPTURE_CHUNK
        cap.visibility, cap._CAPTURE_CHUNK = cap._visibility_reference, 10**9
        try:
            return cap.capture_frame(meshes, s)
        finally:
            cap.visibility, cap._CAPTURE_CHUNK = vis, chunk

    methods = {
        "v1": lambda m, s: v1(m, s),
        "exact": lambda m, s: cap.capture_frame(m, s),
        "cull": lambda m, s: cap.capture_frame(m, dataclasses.replace(s, cull_hidden_faces=True)),
    }
    data = frames()
    cap.capture_frame(data[0][1][0], dataclasses.replace(base, num_points=1000))  # warm-up (open3d import)
    rows = []
    for subject, scenes in data:
        times = {k: [] for k in methods}
        shares = {k: [] for k in methods}
        identical = True
        lost = []
        for i, meshes in enumerate(scenes):
            s = dataclasses.replace(base, seed=i)
            for _ in range(args.repeats):
                outs = {}
                for name, fn in methods.items():
                    c0 = time.process_time()
                    outs[name] = fn(meshes, s)
                    times[name].append(time.process_time() - c0)
            for name in methods:
                shares[name].append(cap.loose_share(outs[name].labels))
            identical &= all(np.array_equal(getattr(outs["v1"], k), getattr(outs["exact"], k))
                             for k in ("points", "normals", "labels", "parts"))  # fmt: skip
            lost.append(lost_visible(meshes, base))
        med = {k: statistics.median(v) for k, v in times.items()}
        row = dict(subject=subject, frames=len(scenes), repeats=args.repeats,
                   cpu_s_per_frame=med, speedup_vs_v1={k: med["v1"] / v for k, v in med.items()},
                   loose_share_percent={k: float(np.mean(v)) for k, v in shares.items()},
                   exact_identical_to_v1=bool(identical), cull_lost_visible_percent=100 * float(np.mean(lost)))  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| subject | v1 CPU s/frame | exact | + cull | speed-up | loose % v1 / cull | visible surface lost by cull |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        c, sp, ls = r["cpu_s_per_frame"], r["speedup_vs_v1"], r["loose_share_percent"]
        print(f"| {r['subject']} | {c['v1']:.3f} | {c['exact']:.3f} | {c['cull']:.3f} | {sp['exact']:.2f}x / "
              f"{sp['cull']:.2f}x | {ls['v1']:.2f} / {ls['cull']:.2f} | {r['cull_lost_visible_percent']:.3f} % |")
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(dict(settings=dataclasses.asdict(base), load_avg_1min=os.getloadavg()[0], rows=rows), f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
