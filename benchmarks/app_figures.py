"""The README / BENCHMARKS.md figures of the applications (issue 5), from the shipped model.

Fixed seeds, the benchmarks' sampler (ddpm, 50 strided steps). Writes to ``--out``
(default docs/images/):

* ``app_completion.png``: a test scan with the hem region removed, completed with
  ``init="sample"`` (default) and ``init="noise"`` (plain RePaint), and the full GT scan;
* ``app_editing.png``: a source scan, renoise (t = 100) and region edits to the pose 10 frames
  later, and that frame's GT scan;
* ``app_animation_strip.png`` / ``app_animation.gif``: independent vs. shared-noise vs.
  chain-world frames of a test sequence (and the GT), side by side;
* ``app_mesh_refined.png``: Poisson mesh of a generated cloud, the same after body refinement,
  and the fitted body (``pocoloco mesh --refine-body``; reads ``--mesh`` / ``--refined`` /
  ``--body`` PLYs when given, skipped otherwise);
* ``app_turntable.gif``: turntable of a generated cloud (``--cloud``, skipped if not given).

    python benchmarks/app_figures.py --data data/medium --threads 1 --cloud out/issue5/sample_skirt/sample_000.ply \\
        --cloud-joints demo:skirt \\
        --mesh out/issue5/sample_mesh.ply --refined out/issue5/sample_refined.ply \\
        --body out/issue5/sample_refined_body.ply
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from pocoloco.apps.animation import animate
from pocoloco.apps.common import subset
from pocoloco.apps.completion import complete, region_mask
from pocoloco.apps.editing import edit
from pocoloco.data import format as fmt
from pocoloco.data.poses import load_joints
from pocoloco.engine.checkpoint import resolve_checkpoint
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.methods import load_method
from pocoloco.viz.render import (
    LABEL_COLORS,
    render_gif,
    render_grid,
    render_meshes,
    turntable_gif,
)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", default="default")
    p.add_argument("--data", default="data/medium")
    p.add_argument("--sequence", default="skirt_a/test_0000", help="subject/sequence of the test split")
    p.add_argument("--points", type=int, default=2048)
    p.add_argument("--anim-points", type=int, default=1024)
    p.add_argument("--anim-frames", type=int, default=8)
    p.add_argument("--anim-stride", type=int, default=3)
    p.add_argument("--sampler", default="ddpm")
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--only", nargs="+", default=["completion", "editing", "animation", "mesh", "turntable"])
    p.add_argument("--cloud", help="generated cloud PLY for the turntable")
    p.add_argument("--cloud-joints", help="the --cloud's pose (as `pocoloco sample --joints`): its shading and garment tint")
    p.add_argument("--mesh", help="plain Poisson mesh PLY of --cloud")
    p.add_argument("--refined", help="refined mesh PLY (pocoloco mesh --refine-body)")
    p.add_argument("--body", help="fitted body PLY")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="docs/images")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    loaded = load_method(resolve_checkpoint(resolve_ckpt_arg(args.ckpt)), expect="pocoloco")
    layout = fmt.DatasetLayout(args.data)
    subject, sequence = args.sequence.split("/")
    # a model that knows who wears what draws the sequence's own outfit
    prior = loaded.point_prior(loaded.outfit_id(subject) if loaded.outfit_names() else None)
    idx = layout.frame_indices(subject, "test", sequence)

    def frame(i: int):
        return fmt.read_frame(layout.frame_path(subject, "test", sequence, i), ["points", "joints", "labels"])

    kw = dict(sampler=args.sampler, steps=args.steps)
    N = args.points
    if "completion" in args.only:
        t0 = time.perf_counter()
        fr = frame(idx[0])
        inside = region_mask(fr.points, fr.joints, "hem")
        partial = fr.points[~inside]
        panels = [(partial[subset(len(partial), N, [0])], None, None, "partial scan (hem removed)")]
        for init, title in (("sample", "completed"), ("noise", "plain RePaint")):
            c = complete(prior, partial, fr.joints, N, init=init, seeds=[0], **kw)
            panels.append((c.points[0], np.where(c.known[0], 0, 2), None, f"{title} (orange: generated)"))
        gsel = subset(len(fr.points), N, [0])
        panels.append((fr.points[gsel], fr.labels[gsel], None, "GT scan"))
        render_grid(panels, out / "app_completion.png", views=("front", "side"), ncols=2, panel_size=2.6,
                    joints=fr.joints)  # fmt: skip
        print(f"completion figure ({time.perf_counter() - t0:.0f} s)", flush=True)
    if "editing" in args.only:
        t0 = time.perf_counter()
        src, tgt = frame(idx[0]), frame(idx[10])
        panels = [(src.points[subset(len(src.points), N, [0])], None, None, "source")]
        for mode, t, title in (("renoise", 100, "renoise t=100"), ("region", None, "region")):
            e = edit(prior, src.points, tgt.joints, source_joints=src.joints, mode=mode, t=t,
                     num_points=N, seeds=[0], **kw)  # fmt: skip
            lab = np.where(e.regenerated[0], 2, 0) if mode == "region" else None
            panels.append((e.points[0], lab, None, title + (" (orange: new)" if lab is not None else "")))
        gsel = subset(len(tgt.points), N, [0])
        panels.append((tgt.points[gsel], None, None, "GT target frame"))
        render_grid(panels, out / "app_editing.png", views=("front", "side"), ncols=2, panel_size=2.6,
                    joints=[src.joints] + [tgt.joints] * (len(panels) - 1))  # fmt: skip
        print(f"editing figure ({time.perf_counter() - t0:.0f} s)", flush=True)
    if "animation" in args.only:
        t0 = time.perf_counter()
        sel = idx[:: args.anim_stride][: args.anim_frames]
        frames = [frame(i) for i in sel]
        joints = np.stack([f.joints for f in frames])
        rows = {}
        for method, anchor, title in (("independent", "root", "independent"), ("shared-noise", "root", "shared noise"),
                                      ("chain", "world", "chain (world)")):  # fmt: skip
            rows[title] = animate(prior, joints, args.anim_points, method=method, anchor=anchor,
                                  seed=0, **kw).points  # fmt: skip
        rows["GT"] = np.stack([f.points[subset(len(f.points), args.anim_points, [0, k])] for k, f in
                               enumerate(frames)])  # fmt: skip
        panels = [(rows[r][k], None, None, f"{r} {sel[k]}") for r in rows for k in range(len(sel))]
        render_grid(panels, out / "app_animation_strip.png", views=("front",), ncols=len(sel), panel_size=1.6, dpi=90,
                    joints=[joints[k] for _ in rows for k in range(len(sel))])  # fmt: skip
        # one GIF, the methods side by side (offset along x), one colour each
        width = 1.1 * float(np.ptp(rows["GT"][..., 0])) + 0.3
        palette = [LABEL_COLORS[0], LABEL_COLORS[1], LABEL_COLORS[2], np.array([0.4, 0.4, 0.4])]
        clouds = np.concatenate([rows[r] + np.array([j * width, 0, 0]) for j, r in enumerate(rows)], axis=1)
        colors = np.concatenate([np.broadcast_to(palette[j], rows[r].shape) for j, r in enumerate(rows)], axis=1)
        render_gif(clouds, out / "app_animation.gif", fps=4, size=6.0, colors=colors)
        print(f"animation figures ({time.perf_counter() - t0:.0f} s): left to right {', '.join(rows)}", flush=True)
    if "mesh" in args.only and args.mesh and args.refined and args.body:
        from pocoloco.data.published import read_ply

        meshes = [(read_ply(f).points, read_ply(f).faces, t) for f, t in
                  ((args.mesh, "Poisson mesh"), (args.refined, "refined (body head + hands)"),
                   (args.body, "fitted anny body"))]  # fmt: skip
        render_meshes(meshes, out / "app_mesh_refined.png", views=("front", "side"), panel_size=3.0)
        print("mesh figure", flush=True)
    if "turntable" in args.only and args.cloud:
        from pocoloco.data.published import read_ply

        ply = read_ply(args.cloud)
        joints = None if args.cloud_joints is None else load_joints(args.cloud_joints)
        turntable_gif(out / "app_turntable.gif", ply.points, ply.labels, ply.normals, num_frames=24, size=3.0,
                      joints=joints)  # fmt: skip
        print("turntable", flush=True)


if __name__ == "__main__":
    main()
