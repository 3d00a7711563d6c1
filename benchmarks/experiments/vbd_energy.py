"""Does newton's VBD solver keep a swinging cloth's energy? A hanging sheet, kicked.

A 0.5 m square sheet of the data's fabric (0.15 kg/m^2, membrane 1e4, bending 1e-3, as
``ClothSimSettings``), pinned along its top edge, gets a 0.5 m/s kick normal to itself and
swings freely (no air, no body) for ``--frames`` frames at 25 fps. Backward Euler solved
exactly can only lose energy; the table reports the sheet's kinetic + gravitational energy
over time and the bottom edge's speed for each iteration count. At the pipeline's 5
iterations the energy *grows* (the block Gauss-Seidel sweeps start from the inertial
prediction and stop long before the sheet's tension has crossed it), which is why no
physical damping brings the data's skirts to rest (benchmarks/bench_settle.py).

A cleaner repro, ``--tube``: a 0.5 m tube of the same fabric (radius 0.15 m, 48 x 24 vertices,
the top ring pinned) hangs in free space from rest, no kick, no body, no air: it should hang
still. Reported for variants of the solve (graph colouring that includes the bending
neighbours, colour order reversed every substep (symmetric Gauss-Seidel), no bending, more
iterations): the bottom ring's mean speed, its mean tangential speed (a spin about the axis),
the centroid's swing and the radial flapping after ``--frames`` frames.

``--init`` starts the sheet's sweeps at another initial guess (``vbd_init.py``: the VBD paper's
adaptive one), ``--chebyshev RHO`` accelerates them (``pocoloco.synth.vbd_chebyshev``); the tube
has the same as variants.

    python benchmarks/experiments/vbd_energy.py [--iterations 5 20 100] [--frames 100]
        [--init adaptive velocity inertia] [--chebyshev 0.9 ...] [--out ...]
    python benchmarks/experiments/vbd_energy.py --tube [--frames 250] [--out ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def _solver(model, iterations: int, init: str | None, chebyshev: float | None = None):  # noqa: ANN001, ANN202
    """newton's VBD solver (init and chebyshev None); or one whose iterations start at another initial
    guess (``vbd_init.INIT_MODES``: the VBD paper's adaptive one, x + h v, or newton's own inertia);
    or newton's with Chebyshev-accelerated iterations of spectral radius estimate ``chebyshev``."""
    import newton

    if chebyshev is not None:
        from pocoloco.synth.vbd_chebyshev import SolverVBDChebyshev

        return SolverVBDChebyshev(model, rho=chebyshev, iterations=iterations)
    if init is not None:
        import sys

        sys.path.insert(0, str(Path(__file__).parent))
        from vbd_init import INIT_MODES, SolverVBDInit

        return SolverVBDInit(model, init_mode=INIT_MODES[init], iterations=iterations)
    return newton.solvers.SolverVBD(model, iterations=iterations)


def hanging_sheet(iterations: int, substeps: int, frames: int, n: int = 24, size: float = 0.5, kick: float = 0.5,
                  tri_kd: float = 1e-5, init: str | None = None, chebyshev: float | None = None) -> dict:  # fmt: skip
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
    solver = _solver(model, iterations, init, chebyshev)
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


def hanging_sheet_style3d(iterations: int, linear_iterations: int, substeps: int, frames: int, n: int = 24,
                          size: float = 0.5, kick: float = 0.5, membrane: float = 1e3) -> dict:  # fmt: skip
    """The kicked sheet of :func:`hanging_sheet` with newton's other cloth solver, Style3D (projective
    dynamics, a PCG solve per iteration; its anisotropic membrane ``membrane`` along both threads and
    a tenth of it in shear): energy [mJ] and bottom-edge speed [cm/s] per frame."""
    from pocoloco.body.anny_body import quiet_warp

    quiet_warp()
    import warp as wp

    import newton
    from newton.solvers import SolverStyle3D, style3d

    b = newton.ModelBuilder()
    SolverStyle3D.register_custom_attributes(b)
    style3d.add_cloth_grid(b, pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), float(-np.pi / 2)),
                           vel=wp.vec3(0.0, 0.0, 0.0), dim_x=n - 1, dim_y=n - 1, cell_x=size / (n - 1),
                           cell_y=size / (n - 1), mass=0.15 * size * size / (n * n),
                           tri_aniso_ke=wp.vec3(membrane, membrane, membrane / 10), edge_aniso_ke=wp.vec3(1e-5, 1e-5, 1e-5),
                           particle_radius=0.004)  # fmt: skip
    q = np.array(b.particle_q)
    for j in np.where(q[:, 2] > -1e-6)[0]:  # the top edge is pinned
        b.particle_mass[j] = 0.0
    model = b.finalize(device="cpu")
    solver = SolverStyle3D(model, config=SolverStyle3D.Config(iterations=iterations, linear_iterations=linear_iterations))
    s0, s1, control = model.state(), model.state(), model.control()
    mass = model.particle_mass.numpy()
    qd = s0.particle_qd.numpy()
    qd[mass > 0, 1] = kick
    s0.particle_qd.assign(qd)
    bottom = np.where(q[:, 2] < q[:, 2].min() + 1e-6)[0]
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    dt = 1.0 / 25.0 / substeps
    energy, speed = [], []
    t0 = time.perf_counter()
    for _ in range(frames):
        for _ in range(substeps):
            pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        v = np.linalg.norm(s0.particle_qd.numpy(), axis=1)
        qq = s0.particle_q.numpy()
        energy.append(float(((0.5 * mass * v**2).sum() + (mass * 9.81 * qq[:, 2]).sum()) * 1000))
        speed.append(float(v[bottom].mean() * 100))
    return {"iterations": iterations, "linear_iterations": linear_iterations, "substeps": substeps,
            "seconds": time.perf_counter() - t0, "energy_mJ": energy, "bottom_speed_cm_s": speed,
            "init": "style3d"}  # fmt: skip


TUBE_VARIANTS = {
    "as the pipeline (5 iterations)": {},
    "colouring includes bending": {"bend_colour": True},
    "colour order reversed every substep": {"symmetric": True},
    "both": {"bend_colour": True, "symmetric": True},
    "no bending (edge_ke 0)": {"edge_ke": 0.0},
    "20 iterations": {"iterations": 20},
    "20 iterations, bending colouring": {"iterations": 20, "bend_colour": True},
    "diagonals alternating (achiral)": {"achiral": True},
    "achiral, bending colouring": {"achiral": True, "bend_colour": True},
    "adaptive initial guess (VBD paper)": {"init": "adaptive"},
    "adaptive initial guess, achiral": {"init": "adaptive", "achiral": True},
    "Chebyshev rho 0.9": {"chebyshev": 0.9},
    "Chebyshev rho 0.9, achiral": {"chebyshev": 0.9, "achiral": True},
    "cone 0.15 -> 0.3 m, achiral": {"achiral": True, "bottom_radius": 0.3},
    "cone, achiral, Chebyshev rho 0.9": {"achiral": True, "bottom_radius": 0.3, "chebyshev": 0.9},
    "cone, achiral, Chebyshev rho 0.9, membrane 1e3, no area term": {"achiral": True, "bottom_radius": 0.3,
                                                                      "chebyshev": 0.9, "tri_ke": 1e3, "tri_ka": 0.0},
    "cone, achiral, tension field": {"achiral": True, "bottom_radius": 0.3, "tension_field": True},
    "cone, achiral, tension field, Chebyshev rho 0.9": {"achiral": True, "bottom_radius": 0.3, "tension_field": True,
                                                        "chebyshev": 0.9},
    "cone, achiral, 2x finer": {"achiral": True, "bottom_radius": 0.3, "around": 96, "rows": 48},
    "cone, achiral, 2x finer, Chebyshev rho 0.9": {"achiral": True, "bottom_radius": 0.3, "around": 96, "rows": 48,
                                                   "chebyshev": 0.9},
}


def hanging_tube(frames: int, iterations: int = 5, substeps: int = 7, edge_ke: float = 1e-3, bend_colour: bool = False,
                 symmetric: bool = False, achiral: bool = False, around: int = 48,
                 rows: int = 24, init: str | None = None, chebyshev: float | None = None,
                 bottom_radius: float = 0.15, tri_ke: float = 1e4, tri_ka: float = 1e4,
                 tension_field: bool = False) -> dict:  # fmt: skip
    """A tube pinned at its top ring hanging from rest: bottom-ring speed over time and, at the end,
    its spin (mean tangential speed), radial flapping and the centroid's offset / speed (cm, cm/s)."""
    from pocoloco.body.anny_body import quiet_warp

    quiet_warp()
    import warp as wp

    import newton

    b = newton.ModelBuilder()
    verts = []
    for i in range(rows):
        z = -0.5 * i / (rows - 1)
        for j in range(around):
            t = 2 * np.pi * j / around
            r = 0.15 + (bottom_radius - 0.15) * i / (rows - 1)  # a cone (a flared skirt) when wider below
            verts.append(wp.vec3(r * np.cos(t), r * np.sin(t), z))
    faces = []
    for i in range(rows - 1):
        for j in range(around):
            a, c = i * around + j, (i + 1) * around + j
            bb, d = i * around + (j + 1) % around, (i + 1) * around + (j + 1) % around
            if achiral and (i + j) % 2:  # checkerboard of diagonals: no handedness
                faces += [a, bb, d, a, d, c]
            else:
                faces += [a, bb, c, bb, d, c]
    b.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                     vertices=verts, indices=faces, density=0.15, tri_ke=tri_ke, tri_ka=tri_ka, tri_kd=1e-5,
                     edge_ke=edge_ke, edge_kd=0.0, particle_radius=0.004)  # fmt: skip
    for j in range(around):
        b.particle_mass[j] = 0.0
    b.color(include_bending=bend_colour)
    model = b.finalize(device="cpu")
    solver = _solver(model, iterations, init, chebyshev)
    tension = None
    if tension_field:  # the membrane carries no compression (pocoloco.synth.tension_field)
        from pocoloco.synth.tension_field import TensionField

        tension = TensionField(model, model.device)
    s0, s1, control = model.state(), model.state(), model.control()
    dt = 1.0 / 25.0 / substeps
    speed = []
    t0 = time.perf_counter()
    for _ in range(frames):
        for _ in range(substeps):
            if tension is not None:
                tension.apply(s0.particle_q)
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0
            if symmetric:  # the next substep sweeps the colours in the reverse order
                n = len(model.particle_color_groups)
                model.particle_color_groups.reverse()
                model.particle_colors.assign((n - 1 - model.particle_colors.numpy()).astype(np.int32))
        speed.append(float(np.linalg.norm(s0.particle_qd.numpy()[-around:], axis=1).mean() * 100))
    q, v = s0.particle_q.numpy()[-around:], s0.particle_qd.numpy()[-around:]
    radial = q[:, :2] / np.linalg.norm(q[:, :2], axis=1, keepdims=True)
    tangent = np.stack([-radial[:, 1], radial[:, 0]], 1)
    return {"seconds": time.perf_counter() - t0, "bottom_speed_cm_s": speed,
            "spin_cm_s": float(abs((v[:, :2] * tangent).sum(1).mean()) * 100),
            "radial_flap_cm_s": float(np.abs((v[:, :2] * radial).sum(1)).mean() * 100),
            "centroid_offset_cm": float(np.linalg.norm(q[:, :2].mean(0)) * 100),
            "centroid_speed_cm_s": float(np.linalg.norm(v.mean(0)) * 100)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, nargs="+", default=[5, 20, 100])
    ap.add_argument("--substeps", type=int, default=7)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--tube", action="store_true", help="the hanging tube and its solver variants instead")
    ap.add_argument("--variants", nargs="+", help="--tube: only these variants (names of TUBE_VARIANTS)")
    ap.add_argument("--init", nargs="+", choices=["adaptive", "velocity", "inertia"],
                    help="the sheet: also each iteration count with these initial guesses of the iterations "
                         "(vbd_init.py: the VBD paper's adaptive one, x + h v, or newton's inertia re-written)")
    ap.add_argument("--chebyshev", type=float, nargs="+",
                    help="the sheet: also each iteration count with Chebyshev-accelerated sweeps of these rho")
    ap.add_argument("--style3d", type=int, nargs="+", metavar="ITERATIONS",
                    help="the sheet with newton's Style3D solver instead, at these iteration counts (as many "
                         "PCG iterations each)")  # fmt: skip
    ap.add_argument("--out", default="benchmarks/results/vbd_energy.json")
    args = ap.parse_args()
    if args.tube:
        chosen = args.variants or list(TUBE_VARIANTS)
        rows = {name: hanging_tube(args.frames, **TUBE_VARIANTS[name]) for name in chosen}
        print(f"{'variant':38s} {'bottom cm/s: 1 s':>16s} {'end':>6s} {'spin':>6s} {'flap':>6s} {'swing cm':>8s} {'s':>6s}")
        for name, r in rows.items():
            sp = r["bottom_speed_cm_s"]
            print(f"{name:38s} {sp[min(24, len(sp) - 1)]:16.1f} {sp[-1]:6.1f} {r['spin_cm_s']:6.1f} "
                  f"{r['radial_flap_cm_s']:6.1f} {r['centroid_offset_cm']:8.1f} {r['seconds']:6.1f}")  # fmt: skip
            r["bottom_speed_cm_s"] = [round(x, 2) for x in sp[::25]]
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"command": f"python benchmarks/experiments/vbd_energy.py --tube --frames {args.frames}",
                                   "every": 25, "variants": rows}, indent=1))  # fmt: skip
        print(f"wrote {out}")
        return
    if args.style3d:
        runs = [hanging_sheet_style3d(it, it, args.substeps, args.frames) for it in args.style3d]
    else:
        runs = [hanging_sheet(it, args.substeps, args.frames) for it in args.iterations]
    for init in args.init or []:
        runs += [{**hanging_sheet(it, args.substeps, args.frames, init=init), "init": init} for it in args.iterations]
    for rho in args.chebyshev or []:
        runs += [{**hanging_sheet(it, args.substeps, args.frames, chebyshev=rho), "init": f"cheb {rho}"}
                 for it in args.iterations]  # fmt: skip
    print(f"{'init':>8s} {'iterations':>10s} {'E(0) mJ':>8s} {'E(end) mJ':>9s} {'E max':>8s} {'gain mJ':>8s} {'speed end':>9s} {'s':>7s}")
    for r in runs:
        e = np.array(r["energy_mJ"])
        print(f"{r.get('init', 'newton'):>8s} {r['iterations']:10d} {e[0]:8.2f} {e[-1]:9.2f} {e.max():8.2f} {e.max() - e[0]:8.2f} "
              f"{r['bottom_speed_cm_s'][-1]:9.1f} {r['seconds']:7.1f}")  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for r in runs:  # every 5th frame keeps the file small
        r["energy_mJ"] = [round(x, 3) for x in r["energy_mJ"][::5]]
        r["bottom_speed_cm_s"] = [round(x, 2) for x in r["bottom_speed_cm_s"][::5]]
    out.write_text(json.dumps({"command": "python benchmarks/experiments/vbd_energy.py " + " ".join(
        f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}" for k, v in vars(args).items()
        if k not in ("out", "init", "tube", "variants", "chebyshev", "style3d"))
        + (" --style3d " + " ".join(map(str, args.style3d)) if args.style3d else "")
        + (" --init " + " ".join(args.init) if args.init else "")
        + (" --chebyshev " + " ".join(map(str, args.chebyshev)) if args.chebyshev else ""),
        "every": 5, "runs": runs}, indent=1))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
