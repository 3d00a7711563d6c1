"""Where the time of the synthetic capture pipeline goes, per stored frame.

Runs ``synth.run_sequence`` (the real pipeline: motion, posing, cloth simulation, capture,
writing) on one sequence per subject of a preset, cut to ``--frames`` stored frames, with
timers wrapped around its stages and around every warp kernel launch. Reports process CPU
seconds per *stored* frame (robust to other jobs on a shared machine; wall seconds are in the
JSON), split into:

- motion + posing (``generate_motion``, ``rest_to_motion``, ``AnnyBody.pose``);
- simulation set-up (model build, graph colouring, solver construction);
- simulation per substep: the VBD elasticity sweep kernel, the cloth-body contact kernels,
  the collision detection (``CollisionPipeline.collide``), the self-contact kernels, warp
  launch overhead (Python time in ``SolverVBD.step``/``collide`` outside kernels) and the
  collider update (mesh points/velocities + BVH refit);
- the per-frame cloth checks (penetration signed distance, stretch);
- capture: candidate sampling, the ray-casting scene build, the visibility bookkeeping in
  numpy and the occlusion rays themselves (with the number of rays);
- writing the frame file.

    python benchmarks/experiments/profile_synth.py --preset small --frames 24 [--v1] [--set capture_cameras=24 ...]
        [--out benchmarks/results/profile_synth.json]

``--v1`` applies ``config.SYNTH_V1`` (the first pipeline's settings; the profile of
``benchmarks/results/profile_synth_before.json`` was taken before those settings existed,
with the code of that time).

The simulation includes the sequence's settle, blend and warm-up frames (as the pipeline
does), so per-stored-frame figures depend on ``--frames``; with the ``small`` preset's 80
stored frames the simulation share is lower than with 24.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


class Timers:
    """Accumulated (cpu, wall) seconds and call counts per name."""

    def __init__(self):
        self.cpu = collections.Counter()
        self.wall = collections.Counter()
        self.calls = collections.Counter()
        self.extra = collections.Counter()

    def wrap(self, owner, attr: str, name: str):
        """Replace ``owner.attr`` by a timed version (returns the original)."""
        orig = getattr(owner, attr)
        depth = [0]  # recursive calls (visibility splits big batches) are timed once

        def timed(*a, **k):
            if depth[0]:
                return orig(*a, **k)
            depth[0] += 1
            c, w = time.process_time(), time.perf_counter()
            try:
                return orig(*a, **k)
            finally:
                depth[0] -= 1
                self.cpu[name] += time.process_time() - c
                self.wall[name] += time.perf_counter() - w
                self.calls[name] += 1

        setattr(owner, attr, timed)
        return orig


def instrument(t: Timers) -> None:
    """Wrap the pipeline's stages (module attributes, looked up at call time)."""
    from pocoloco.body.anny_body import AnnyBody, quiet_warp
    from pocoloco.synth import capture, cloth_sim, motion
    from pocoloco.synth import pipeline as synth

    quiet_warp()
    import open3d as o3d
    import warp as wp
    import warp._src.context as wctx

    import newton

    t.wrap(motion, "generate_motion", "motion")
    t.wrap(motion, "rest_to_motion", "motion")
    t.wrap(AnnyBody, "pose", "posing")
    t.wrap(cloth_sim, "frame_stats", "sim: per-frame checks (penetration, stretch)")
    t.wrap(newton.ModelBuilder, "finalize", "sim: set-up (build, colour, solver)")
    t.wrap(newton.ModelBuilder, "color", "sim: set-up (build, colour, solver)")
    t.wrap(newton.solvers.SolverVBD, "__init__", "sim: set-up (build, colour, solver)")
    t.wrap(newton.CollisionPipeline, "__init__", "sim: set-up (build, colour, solver)")
    t.wrap(newton.solvers.SolverVBD, "step", "_step")
    t.wrap(newton.CollisionPipeline, "collide", "_collide")
    t.wrap(wp.Mesh, "refit", "sim: collider update (mesh points, BVH refit)")
    t.wrap(capture._Surface, "__init__", "capture: candidates (surface set-up)")
    t.wrap(capture._Surface, "sample", "capture: candidates (sampling)")
    t.wrap(capture, "visibility", "_visibility")
    t.wrap(synth, "write_frame", "write")
    t.wrap(synth, "_written_labels", "write")

    kernels = {
        "solve_elasticity": "sim: VBD elasticity sweep (kernel)",
        "create_soft_contacts": "sim: collision detection (kernels)",
        "scatter_particle_body_contact_force_and_hessian": "sim: body contact forces (kernels)",
        "update_duals_body_particle_contacts": "sim: body contact forces (kernels)",
        "accumulate_self_contact_force_and_hessian": "sim: self-contact forces (kernel)",
    }
    orig_invoke = wctx.invoke

    def invoke(kernel, hooks, params, adjoint):
        c, w = time.process_time(), time.perf_counter()
        try:
            return orig_invoke(kernel, hooks, params, adjoint)
        finally:
            key = kernels.get(kernel.key)
            if key is None:
                key = "sim: self-contact detection (kernels)" if ("collision" in kernel.key.lower() and "self" in kernel.key.lower()) or "vertex_triangle" in kernel.key or "edge_edge" in kernel.key or "triangle_triangle" in kernel.key else "sim: other kernels"
            t.cpu["_kernel:" + key] += time.process_time() - c
            t.wall["_kernel:" + key] += time.perf_counter() - w
            t.calls["_kernel:" + key] += 1
            t.extra[kernel.key] += time.process_time() - c

    wctx.invoke = invoke

    base = o3d.t.geometry.RaycastingScene

    class TimedScene(base):
        def add_triangles(self, *a, **k):
            c, w = time.process_time(), time.perf_counter()
            r = super().add_triangles(*a, **k)
            t.cpu["_scene_add"] += time.process_time() - c
            t.wall["_scene_add"] += time.perf_counter() - w
            return r

        def test_occlusions(self, rays, *a, **k):
            c, w = time.process_time(), time.perf_counter()
            r = super().test_occlusions(rays, *a, **k)
            t.cpu["_occlusion"] += time.process_time() - c
            t.wall["_occlusion"] += time.perf_counter() - w
            t.extra["rays"] += int(rays.shape[0])
            return r

        def compute_signed_distance(self, *a, **k):
            c, w = time.process_time(), time.perf_counter()
            r = super().compute_signed_distance(*a, **k)
            t.cpu["_sdf"] += time.process_time() - c
            t.wall["_sdf"] += time.perf_counter() - w
            return r

    o3d.t.geometry.RaycastingScene = TimedScene


def table(t: Timers, frames: int) -> list[tuple[str, float, float]]:
    """(stage, CPU s per stored frame, wall s per stored frame) rows, derived stages resolved."""
    cpu, wall = dict(t.cpu), dict(t.wall)
    rows: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0])

    def add(name, c, w):
        rows[name][0] += c
        rows[name][1] += w

    kern_c = sum(v for k, v in cpu.items() if k.startswith("_kernel:"))
    kern_w = sum(v for k, v in wall.items() if k.startswith("_kernel:"))
    for k in cpu:
        if k.startswith("_kernel:"):
            add(k[len("_kernel:"):], cpu[k], wall[k])
    # Python-side launch overhead inside the solver step and the collision pipeline
    add("sim: warp launch overhead (Python)", cpu.get("_step", 0) + cpu.get("_collide", 0) - kern_c,
        wall.get("_step", 0) + wall.get("_collide", 0) - kern_w)
    # visibility = numpy bookkeeping + rays; the scene build happens in capture_frame
    add("capture: occlusion rays (open3d)", cpu.get("_occlusion", 0), wall.get("_occlusion", 0))
    add("capture: visibility bookkeeping (numpy)", cpu.get("_visibility", 0) - cpu.get("_occlusion", 0),
        wall.get("_visibility", 0) - wall.get("_occlusion", 0))
    add("capture: ray-casting scene build", cpu.get("_scene_add", 0), wall.get("_scene_add", 0))
    for k in cpu:
        if not k.startswith("_"):
            add(k, cpu[k], wall[k])
    return [(k, c / frames, w / frames) for k, (c, w) in rows.items()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--frames", type=int, default=24, help="stored frames per sequence")
    ap.add_argument("--subjects", nargs="*", default=None, help="subject names (default: all of the preset)")
    ap.add_argument("--set", nargs="*", default=[], help="SynthConfig overrides key=value (python literals)")
    ap.add_argument("--v1", action="store_true", help="the first pipeline's settings (config.SYNTH_V1)")
    ap.add_argument("--out", default="benchmarks/results/profile_synth.json")
    args = ap.parse_args()

    import ast

    from pocoloco.synth import pipeline as synth
    from pocoloco.synth.config import synth_preset

    from pocoloco.synth.config import SYNTH_V1

    over = {**(SYNTH_V1 if args.v1 else {}), **{k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}}
    config = dataclasses.replace(synth_preset(args.preset), frames_per_sequence=args.frames, train_sequences=1,
                                 test_sequences=0, **over)  # fmt: skip
    if args.subjects:
        config = dataclasses.replace(config, subjects=tuple(s for s in config.subjects if s.name in args.subjects))
    t = Timers()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "d"
        synth.prepare_output(config, out)
        # warm-up outside the timers: body/garment build, open3d import, kernel compilation
        for s in config.subjects:
            synth.write_subject(config, out, s)
        warm = dataclasses.replace(config, frames_per_sequence=1, blend_frames=1, warmup_frames=1)
        for s in config.subjects:
            synth.run_sequence(warm, Path(tmp) / "warm", synth.SequenceJob(s, "train", 99))
        instrument(t)
        for s in config.subjects:
            before = (dict(t.cpu), dict(t.wall), dict(t.extra))
            c0, w0 = time.process_time(), time.perf_counter()
            rec = synth.run_sequence(config, out, synth.SequenceJob(s, "train", 0))
            total_c, total_w = time.process_time() - c0, time.perf_counter() - w0
            sub = Timers()
            sub.cpu = collections.Counter({k: v - before[0].get(k, 0.0) for k, v in t.cpu.items()})
            sub.wall = collections.Counter({k: v - before[1].get(k, 0.0) for k, v in t.wall.items()})
            rows = table(sub, config.frames_per_sequence)
            accounted = sum(r[1] for r in rows)
            rows.append(("other (Python glue, stats, pins)", total_c / config.frames_per_sequence - accounted,
                         total_w / config.frames_per_sequence - sum(r[2] for r in rows)))
            results[s.name] = dict(
                garment=s.garment, total_cpu_s_per_frame=total_c / config.frames_per_sequence,
                total_wall_s_per_frame=total_w / config.frames_per_sequence,
                rays_per_frame=(t.extra["rays"] - before[2].get("rays", 0)) / config.frames_per_sequence,
                rows=[dict(stage=k, cpu_s_per_frame=c, wall_s_per_frame=w) for k, c, w in rows],
                rejected=len(rec["rejected_frames"]), loose_share_percent=rec["loose_share_percent"],
                penetration=rec["penetration"],
            )  # fmt: skip
    # one table: stages x subjects, CPU seconds per stored frame
    stages = []
    for r in results.values():
        for row in r["rows"]:
            if row["stage"] not in stages:
                stages.append(row["stage"])
    stages.sort(key=lambda s: (s.split(":")[0] if ":" in s else "z" + s, s))
    names = list(results)
    print(f"preset {args.preset}, {args.frames} stored frames per sequence, overrides {over or '-'}; "
          f"CPU s per stored frame (load avg {os.getloadavg()[0]:.1f})")  # fmt: skip
    print("| stage | " + " | ".join(names) + " | mean |")
    print("|---|" + "---|" * (len(names) + 1))
    for st in stages:
        vals = [next((row["cpu_s_per_frame"] for row in results[n]["rows"] if row["stage"] == st), 0.0) for n in names]
        if max(abs(v) for v in vals) < 5e-4:
            continue
        print(f"| {st} | " + " | ".join(f"{v:.3f}" for v in vals) + f" | {np.mean(vals):.3f} |")
    tot = [results[n]["total_cpu_s_per_frame"] for n in names]
    print("| **total** | " + " | ".join(f"**{v:.3f}**" for v in tot) + f" | **{np.mean(tot):.3f}** |")
    print("rays per frame: " + ", ".join(f"{n} {results[n]['rays_per_frame']:.0f}" for n in names))
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(dict(preset=args.preset, frames=args.frames, overrides=over, config=config.to_dict(),
                       load_avg_1min=os.getloadavg()[0], subjects=results,
                       kernels_cpu_s={k: v for k, v in t.extra.most_common() if k != "rays"}), f, indent=1)  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
