"""Does newton's VBD solver keep a swinging cloth's energy? A hanging sheet, kicked.

A 0.5 m square sheet of the data's fabric (0.15 kg/m^2, membrane 1e4, bending 1e-3, as
``ClothSimSettings``), pinned along its top edge, gets a 0.5 m/s kick normal to itself and
swings freely (no air, no body) for ``--frames`` frames at 25 fps. Backward Euler solved
exactly can only lose energy; the table reports the sheet's kinetic + gravitational energy
over time and the bottom edge's speed for each iteration count. At the pipeline's 5
iterations the energy *grows* (the block Gauss-Seidel sweeps start from the inertial
prediction and stop long before the sheet's tension has crossed it), which is why no
physical damping brings the data's skirts to rest (benchmarks/bench_settle.py).

    python benchmarks/experiments/vbd_energy.py [--iterations 5 20 100] [--frames 100] [--out ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def hanging_sheet(iterations: int, substeps: int, frames: int, n: int = 24, size: float = 0.5, kick: float = 0.5,
                  tri_kd: float = 1e-5) -> dict:  # fmt: skip
    """Energy [mJ] and bottom-edge speed [cm/s] per frame of a kicked hanging sheet."""
    from pocoloco.body.anny_body import quiet_warp

    quiet_warp()
    import warp as wp

    import newton

    b = newton.ModelBuilder()
    xs = np.linspace(0.0, size, n)
    verts = [wp.vec3(x, 0.0, -z) for z in xs for x in xs]  # a vertical sheet in the x-z plane
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [a, a + 1, a + n, a + 1, a + n + 1, a + n]
    b.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                     vertices=verts, indices=faces, density=0.15, tri_ke=1e4, tri_ka=1e4, tri_kd=tri_kd,
                     edge_ke=1e-3, edge_kd=0.0, particle_radius=0.004)  # fmt: skip
    for j in range(n):
        b.particle_mass[j] = 0.0  # the top edge is pinned
    b.color()
    model = b.finalize(device="cpu")
    solver = newton.solvers.SolverVBD(model, iterations=iterations)
    s0, s1, control = model.state(), model.state(), model.control()
    qd = s0.particle_qd.numpy()
    qd[n:, 1] = kick
    s0.particle_qd.assign(qd)
    mass = model.particle_mass.numpy()
    dt = 1.0 / 25.0 / substeps
    energy, speed = [], []
    t0 = time.perf_counter()
    for _ in range(frames):
        for _ in range(substeps):
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0
        v = np.linalg.norm(s0.particle_qd.numpy(), axis=1)
        q = s0.particle_q.numpy()
        energy.append(float(((0.5 * mass * v**2).sum() + (mass * 9.81 * q[:, 2]).sum()) * 1000))
        speed.append(float(v[-n:].mean() * 100))
    return {"iterations": iterations, "substeps": substeps, "seconds": time.perf_counter() - t0,
            "energy_mJ": energy, "bottom_speed_cm_s": speed}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, nargs="+", default=[5, 20, 100])
    ap.add_argument("--substeps", type=int, default=7)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--out", default="benchmarks/results/vbd_energy.json")
    args = ap.parse_args()
    runs = [hanging_sheet(it, args.substeps, args.frames) for it in args.iterations]
    print(f"{'iterations':>10s} {'E(0) mJ':>8s} {'E(end) mJ':>9s} {'E max':>8s} {'gain mJ':>8s} {'speed end':>9s} {'s':>7s}")
    for r in runs:
        e = np.array(r["energy_mJ"])
        print(f"{r['iterations']:10d} {e[0]:8.2f} {e[-1]:9.2f} {e.max():8.2f} {e.max() - e[0]:8.2f} "
              f"{r['bottom_speed_cm_s'][-1]:9.1f} {r['seconds']:7.1f}")  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for r in runs:  # every 5th frame keeps the file small
        r["energy_mJ"] = [round(x, 3) for x in r["energy_mJ"][::5]]
        r["bottom_speed_cm_s"] = [round(x, 2) for x in r["bottom_speed_cm_s"][::5]]
    out.write_text(json.dumps({"command": "python benchmarks/experiments/vbd_energy.py " + " ".join(
        f"--{k} {' '.join(map(str, v)) if isinstance(v, list) else v}" for k, v in vars(args).items() if k != "out"),
        "every": 5, "runs": runs}, indent=1))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
