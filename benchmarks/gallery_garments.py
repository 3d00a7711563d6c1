"""Gallery of the garment library: every kind on a body, a few poses, points coloured by label.

For each garment kind (and the ``tight`` control) the garment is built on a subject,
simulated with the pipeline's cloth settings (``synth.cloth_settings`` of the `small`
preset: root frame, 7 x 5; ``--self-contact`` turns self-contact on) on one procedural
motion (rest -> walk and arm swing), and frames are captured as the pipeline does (points
labelled body / garment). Rows are poses (frames), columns are kinds.

    python benchmarks/gallery_garments.py [--out docs/images/garment_gallery.png] [--frames 0 24 47]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

#: (kind, phenotype) per column: the skirts and the dress on a woman, the rest on a man
COLUMNS = (
    ("skirt", {"gender": 1.0, "age": 0.45, "weight": 0.45, "height": 0.5}),
    ("maxi_skirt", {"gender": 1.0, "age": 0.45, "weight": 0.45, "height": 0.5}),
    ("dress", {"gender": 1.0, "age": 0.4, "weight": 0.6, "height": 0.4}),
    ("long_shirt", {"gender": 0.0, "age": 0.5, "weight": 0.5, "height": 0.55}),
    ("sleeved_shirt", {"gender": 0.0, "age": 0.5, "weight": 0.7, "height": 0.6}),
    ("wide_trousers", {"gender": 0.5, "age": 0.5, "weight": 0.5, "height": 0.5}),
    ("tight", {"gender": 0.6, "age": 0.4, "weight": 0.55, "height": 0.45}),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/images/garment_gallery.png")
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 26, 47], help="frames shown (after the lead-in)")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--self-contact", action=argparse.BooleanOptionalAction, default=False)
    args = ap.parse_args()

    from pocoloco.body import AnnyBody
    from pocoloco.synth.capture import LABEL_BODY, LABEL_GARMENT, CaptureMesh, CaptureSettings, capture_frame
    from pocoloco.synth.cloth_sim import simulate_garment
    from pocoloco.synth.config import synth_preset
    from pocoloco.synth.pipeline import cloth_settings
    from pocoloco.synth.garments import make_garment
    from pocoloco.synth.motion import generate_motion, rest_to_motion
    from pocoloco.viz.render import render_grid

    lead = 12
    count = max(args.frames) + 1
    cells = {}
    for kind, phenotype in COLUMNS:
        t0 = time.perf_counter()
        body = AnnyBody(phenotype)
        motion = rest_to_motion(generate_motion(args.seed, count, "train", kinds=("walk", "arm_swing"), body=body),
                                lead, body)  # fmt: skip
        posed = body.pose(motion.joint_rotvecs, motion.root_translation)
        cloth = garment = None
        if kind != "tight":
            garment = make_garment(kind, body, tessellation="isotropic")
            settings = dataclasses.replace(cloth_settings(synth_preset("small")), self_contact=args.self_contact)
            if args.self_contact:
                settings = dataclasses.replace(settings, substeps=10)
            cloth = simulate_garment(body, garment, posed, settings).vertices
        part = body.vertex_joint[body.faces[:, 0]]
        for f in args.frames:
            t = lead + f
            meshes = [CaptureMesh(posed.vertices[t], body.faces, LABEL_BODY, part)]
            if cloth is not None:
                meshes.append(CaptureMesh(cloth[t], garment.faces, LABEL_GARMENT))
            scan = capture_frame(meshes, CaptureSettings(num_points=args.points, num_cameras=24, seed=t))
            centre = posed.joints[t, 0] * np.array([1.0, 1.0, 0.0])  # each panel centred on its pelvis
            title = f"{kind}" + (f" {len(garment.rest_vertices)}v" if garment is not None else "") + f" f{f}"
            cells[(kind, f)] = (scan.points - centre, scan.labels, scan.normals, title)
        print(f"{kind}: {time.perf_counter() - t0:.0f} s", flush=True)
    clouds = [cells[(kind, f)] for f in args.frames for kind, _ in COLUMNS]
    render_grid(clouds, args.out, views=("front",), ncols=len(COLUMNS), mode="label", panel_size=2.6, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
