"""A skirt through a spin and a stop, data v2's cloth beside v3's and the v4 cloth's: the GIF of issue 39.

The ``medium`` subject ``skirt_a`` spins (the pipeline's own motion, 1.6 s from the rest pose),
blends into the rest pose and holds it; the same body motion is simulated with the v2 cloth
(isotropic mesh, undamped), the v3 cloth (checkerboard mesh, physical damping) and the v4 cloth
(v3 and the drag of small oscillations, Chebyshev sweeps), and every
``--stride``-th frame is drawn front-on, body in skin and garment in blue, with the hem's speed
relative to the body in each panel's title.

    python benchmarks/experiments/settle_gif.py [--hold 2.0] [--stride 4] [--versions v2 v3 v4] \
        --out docs/images/settle_spin_v2_v3_v4.gif
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hold", type=float, default=2.0, help="seconds held after the stop")
    ap.add_argument("--stride", type=int, default=4, help="draw every k-th frame")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--versions", nargs="+", default=["v2", "v3", "v4"], help="cloth versions, one panel each")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    import torch
    from PIL import Image

    torch.set_num_threads(1)
    from bench_settle import history_then_rest

    from pocoloco.body import AnnyBody
    from pocoloco.body.surface import vertex_normals
    from pocoloco.synth.cloth_sim import simulate_garment
    from pocoloco.synth.config import CLOTH_VERSIONS, MEDIUM_SUBJECTS, SynthConfig
    from pocoloco.synth.garments import make_garment
    from pocoloco.synth.pipeline import cloth_settings
    from pocoloco.utils.atomic import atomic_open
    from pocoloco.viz.render import LABEL_COLORS, new_figure, render_points

    subject = next(s for s in MEDIUM_SUBJECTS if s.name == "skirt_a")
    body = AnnyBody(subject.phenotype)
    fps = SynthConfig().fps
    rot, trans, arrive, start = history_then_rest(body, "spin", args.seed, 40, 12, int(args.hold * fps), fps)
    posed = body.pose(rot, trans)
    runs = {}
    for version in args.versions:
        config = dataclasses.replace(SynthConfig(), **CLOTH_VERSIONS[version])
        garment = make_garment(subject.garment, body, resolution=config.garment_resolution,
                               tessellation=config.garment_tessellation, **subject.garment_params)  # fmt: skip
        seq = simulate_garment(body, garment, posed, cloth_settings(config, subject.garment))
        rest = garment.rest_vertices
        hem = np.flatnonzero(rest[:, 2] <= np.quantile(rest[:, 2], 0.2))
        # hem speed relative to the body: minus the velocity of each hem vertex's nearest body vertex
        from scipy.spatial import cKDTree

        near = cKDTree(posed.vertices[0]).query(seq.vertices[0][hem])[1]
        rel = seq.vertices[:, hem] - posed.vertices[:, near]
        speed = np.r_[0.0, np.linalg.norm(np.diff(rel, axis=0), axis=-1).mean(1) * fps * 100]
        runs[version] = (seq.vertices, garment.faces, speed)
        print(f"{version}: hem {speed[arrive + int(fps)]:.1f} cm/s 1 s after the stop, "
              f"{speed[arrive + int(2 * fps) - 1]:.1f} at 2 s")  # fmt: skip
    rng = np.random.default_rng(0)
    body_idx = rng.choice(posed.vertices.shape[1], 5000, replace=False)
    frames = list(range(start, len(rot), args.stride))
    allpts = np.concatenate([posed.vertices[frames][:, body_idx].reshape(-1, 3),
                             *(runs[v][0][frames].reshape(-1, 3) for v in runs)])  # fmt: skip
    u, w = allpts[:, 0], allpts[:, 2]
    half = 0.52 * max(np.ptp(u), np.ptp(w))
    extent = ((u.min() + u.max()) / 2 - half, (u.min() + u.max()) / 2 + half,
              (w.min() + w.max()) / 2 - half, (w.min() + w.max()) / 2 + half)  # fmt: skip
    images = []
    for t in frames:
        k = len(runs)
        fig = new_figure(2.5 * k, 2.8, 72)
        fig.patch.set_facecolor("white")
        for i, version in enumerate(runs):
            verts, faces, speed = runs[version]
            bv, bn = posed.vertices[t], vertex_normals(posed.vertices[t], body.faces)
            gv, gn = verts[t], vertex_normals(verts[t], faces)
            pts = np.concatenate([bv[body_idx], gv])
            nrm = np.concatenate([bn[body_idx], gn])
            col = np.concatenate([np.repeat(LABEL_COLORS[:1], len(body_idx), 0), np.repeat(LABEL_COLORS[1:2], len(gv), 0)])
            ax = fig.add_axes((i / k, 0.0, 1 / k, 0.86))
            render_points(ax, pts, colors=col, normals=nrm, view="front", extent=extent, cull=False)
            phase = "moving" if t <= arrive else f"stopped {(t - arrive) / fps:.1f} s"
            name = {"v1": "v1 undamped", "v2": "v2 undamped", "v3": "v3 damped", "v4": "v4 + unsteady drag"}[version]
            fig.text((i + 0.5) / k, 0.95, f"{name}\nhem {speed[t]:.0f} cm/s", ha="center", va="top", fontsize=7)
            fig.text(0.5, 0.02, phase, ha="center", va="bottom", fontsize=8)
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
        images.append(Image.fromarray(rgb).convert("P", palette=Image.ADAPTIVE, colors=32))
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 * args.stride / fps),
                   loop=0, optimize=True)  # fmt: skip
    with atomic_open(args.out, "wb") as fh:
        fh.write(buf.getvalue())
    print(f"wrote {args.out} ({len(images)} frames, {len(buf.getvalue()) / 1e3:.0f} KB)")


if __name__ == "__main__":
    main()
