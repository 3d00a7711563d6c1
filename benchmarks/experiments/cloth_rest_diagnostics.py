"""Where does a hanging skirt's motion come from? The ``skirt_a`` garment on a body that never
moves, simulated with the pipeline's cloth settings plus overrides, and three numbers per time:

- ``speed_cm_s``: the hem's mean speed (lowest fifth of the rest vertices), frame to frame;
- ``net_1s_cm``: how far the hem moved in one second (net): a swing of mean speed v and period T
  moves ~v T / pi net in T / 2; jitter moves little net;
- ``lag1_cos``: cosine between consecutive frames' hem velocities (1: smooth, < 0: jitter).

A physical garment with nothing driving it can only lose energy: a hem that speeds up on a still
body (``--damping none``, contact off) is energy the solver puts in.

Over the last 4 s it also says where and how the hem moves (``where``): its mean speed by distance
to the body (does the contact with the legs move it, or the free cloth?), its rms speed radially
(about the pelvis axis), tangentially and vertically, how much neighbouring hem vertices move
together (velocity cosine along hem edges: near 1 a smooth mode, below 0 mesh-scale jitter), and
the frequencies that hold most of its position variance.

    python benchmarks/experiments/cloth_rest_diagnostics.py --tessellation isotropic_achiral \
        --damping none --set contact_ke=0 contact_kd=0 [--seconds 8] --out OUT.json
    python benchmarks/experiments/cloth_rest_diagnostics.py --cloth v4 --out OUT.json   # a data version's cloth
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cloth", default=None, help="a data version's cloth (synth.config.CLOTH_VERSIONS); "
                    "replaces --tessellation and --damping")  # fmt: skip
    ap.add_argument("--tessellation", default="isotropic_achiral")
    ap.add_argument("--damping", default="physical")
    ap.add_argument("--garment", default="skirt", help="garment kind (its medium '_a' subject)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="ClothSimSettings overrides")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from bench_settle import SUBJECT_OF_KIND, history_then_rest

    from pocoloco.body import AnnyBody
    from pocoloco.synth.cloth_sim import ClothSimSettings, simulate_garment
    from pocoloco.synth.config import CLOTH_VERSIONS, MEDIUM_SUBJECTS, SynthConfig
    from pocoloco.synth.garments import make_garment
    from pocoloco.synth.pipeline import cloth_settings

    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        default = getattr(ClothSimSettings(), key)
        overrides[key] = value == "True" if isinstance(default, bool) else type(default)(value)
    subject = next(s for s in MEDIUM_SUBJECTS if s.name == SUBJECT_OF_KIND[args.garment])
    # the v3 cloth with --damping and --tessellation (plain sweeps unless --set chebyshev_rho=...), or --cloth's
    config = dataclasses.replace(SynthConfig(), **{**CLOTH_VERSIONS["v3"], "cloth_damping": args.damping,
                                                   "garment_tessellation": args.tessellation})  # fmt: skip
    if args.cloth is not None:
        config = dataclasses.replace(SynthConfig(), **CLOTH_VERSIONS[args.cloth])
        args.tessellation, args.damping = config.garment_tessellation, config.cloth_damping
    body = AnnyBody(subject.phenotype)
    garment = make_garment(subject.garment, body, resolution=config.garment_resolution,
                           tessellation=args.tessellation, **subject.garment_params)  # fmt: skip
    fps = config.fps
    rot, trans, _, _ = history_then_rest(body, "still", 0, 40, 12, int(args.seconds * fps) - 64, fps)
    posed = body.pose(rot, trans)
    settings = dataclasses.replace(cloth_settings(config, subject.garment), **overrides)
    t0 = time.perf_counter()
    seq = simulate_garment(body, garment, posed, settings)
    wall = time.perf_counter() - t0
    rest = garment.rest_vertices
    hem = np.flatnonzero(rest[:, 2] <= np.quantile(rest[:, 2], 0.2))
    x = seq.vertices[:, hem].astype(np.float64)
    dv = np.diff(x, axis=0)  # (T-1, H, 3) per frame
    speed = np.linalg.norm(dv, axis=-1).mean(1) * fps * 100
    step = int(round(fps))
    net = np.linalg.norm(x[step:] - x[:-step], axis=-1).mean(1) * 100
    cos = (dv[1:] * dv[:-1]).sum(-1) / (np.linalg.norm(dv[1:], axis=-1) * np.linalg.norm(dv[:-1], axis=-1) + 1e-12)
    rows = []
    for t in range(step, len(speed), step // 2):
        rows.append({"t_s": t / fps, "speed_cm_s": float(speed[t]), "net_1s_cm": float(net[min(t, len(net) - 1)]),
                     "lag1_cos": float(cos[min(t, len(cos) - 1)].mean())})  # fmt: skip
    where = hem_breakdown(seq.vertices, garment, hem, posed.vertices[-1], posed.joints[-1, 0], fps)
    result = {"garment": args.garment, "subject": subject.name, "tessellation": args.tessellation,
              "damping": args.damping, "cloth": args.cloth, "set": overrides,
              "command": " ".join(["python", "benchmarks/experiments/cloth_rest_diagnostics.py", *sys.argv[1:]]),
              "seconds_per_frame": seq.seconds_per_frame, "wall_s": wall,
              "invalid_frames": int((~seq.valid).sum()), "rows": rows, "where": where}  # fmt: skip
    print(f"{args.garment} {args.tessellation} {args.damping} {overrides}: {seq.seconds_per_frame:.3f} s/frame")
    for r in rows:
        print(f"  t {r['t_s']:4.1f} s  speed {r['speed_cm_s']:6.2f} cm/s  net over 1 s {r['net_1s_cm']:5.2f} cm"
              f"  lag-1 cos {r['lag1_cos']:5.2f}")  # fmt: skip
    print("  last 4 s: hem speed by distance to the body (cm: cm/s, vertices) "
          + ", ".join(f"{k}: {v['speed_cm_s']:.1f} ({v['vertices']})" for k, v in where["by_distance_cm"].items()))
    print(f"  rms radial / tangential / vertical {where['radial_rms_cm_s']:.1f} / {where['tangential_rms_cm_s']:.1f} / "
          f"{where['vertical_rms_cm_s']:.1f} cm/s; neighbour cosine {where['neighbour_cosine']:.2f}; "
          f"frequencies {where['top_frequencies_hz']} Hz hold {where['top_share']:.0%} of the variance")  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result))


def hem_breakdown(x: np.ndarray, garment, hem: np.ndarray, body: np.ndarray, pelvis: np.ndarray, fps: float,
                  seconds: float = 4.0) -> dict:
    """Where and how the hem moves over the last ``seconds``: x (T, Vg, 3) cloth, hem (H,) indices,
    body (V, 3) and pelvis (3,) at the held pose (the body does not move)."""
    from scipy.spatial import cKDTree

    from pocoloco.synth.cloth_sim import mesh_edges

    x = x[-int(seconds * fps):, hem].astype(np.float64)  # (t, H, 3)
    v = np.diff(x, axis=0) * fps * 100  # cm/s
    speed = np.linalg.norm(v, axis=-1).mean(0)  # (H,)
    dist, _ = cKDTree(body).query(x[-1])
    bands = {"0-1": (0, 0.01), "1-2": (0.01, 0.02), "2-4": (0.02, 0.04), ">4": (0.04, np.inf)}
    by_distance = {}
    for name, (a, b) in bands.items():
        band = (dist >= a) & (dist < b)
        by_distance[name] = {"vertices": int(band.sum()), "speed_cm_s": float(speed[band].mean()) if band.any() else float("nan")}
    r = x[:-1, :, :2] - pelvis[:2]
    rn = r / np.linalg.norm(r, axis=-1, keepdims=True)
    tn = np.stack([-rn[..., 1], rn[..., 0]], -1)
    vr, vt = (v[..., :2] * rn).sum(-1), (v[..., :2] * tn).sum(-1)
    edges = mesh_edges(garment.faces)
    e = np.searchsorted(hem, edges[np.isin(edges, hem).all(1)])  # hem edges as positions in hem (sorted)
    va, vb = v[:, e[:, 0]], v[:, e[:, 1]]
    cos = (va * vb).sum(-1) / (np.linalg.norm(va, axis=-1) * np.linalg.norm(vb, axis=-1) + 1e-9)
    xc = x - x.mean(0)
    power = (np.abs(np.fft.rfft(xc, axis=0)) ** 2).sum((1, 2))
    freqs = np.fft.rfftfreq(len(xc), 1 / fps)
    top = np.argsort(power[1:])[::-1][:5] + 1
    return {"by_distance_cm": by_distance, "radial_rms_cm_s": float(np.sqrt((vr**2).mean())),
            "tangential_rms_cm_s": float(np.sqrt((vt**2).mean())), "vertical_rms_cm_s": float(np.sqrt((v[..., 2] ** 2).mean())),
            "neighbour_cosine": float(cos.mean()), "top_frequencies_hz": [round(float(freqs[i]), 2) for i in top],
            "top_share": float(power[top].sum() / power[1:].sum())}  # fmt: skip


if __name__ == "__main__":
    main()
