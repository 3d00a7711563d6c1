"""Where a distilled student loses its spread (issue 42): per call on the teacher's path, or down its own chain.

For F training frames of a teacher-pairs folder made with D draws per frame (``pocoloco distill
--draws-per-frame D``), each student answer set of a frame (D clouds) is scored against the
teacher's D answers on the judge's probe-distance embedding (:mod:`pocoloco.ops.probe_energy`;
256 probes in each frame's bounding box, normalised units): the spread between the student's
answers as a ratio to the teacher's, and the energy distance. Rows: one call at each grid time
from the teacher's own state there ("teacher's path"), from the teacher's answer noised afresh to
that time ("re-noised", what the re-noising sampler hands the next call when the previous answer
was right), and the student's sampler itself from the pairs' initial noises (1 / 2 / 4 calls of
its grid, and the 3-call grid the teacher finishes, with and without that finishing call). Where
the pairs folder also holds the re-noised pairs (``distill --renoised-targets ode``), the
teacher's own deterministic answers from its answers noised afresh to each later grid time: what
a student taught the consistency condition on the sampler's states would learn.

    python benchmarks/fast_chain_spread.py --pairs RUN/pairs --data DATA --student default:fast --frames 12 \\
        --json chain_spread.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from pocoloco.diffusion import PerSampleRNG
from pocoloco.diffusion.few_step import polish, sample_few_step
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.methods import load_method
from pocoloco.methods.pocoloco.distill import DistillTask, chain_grid, distill_config, read_teacher_pairs
from pocoloco.methods.pocoloco.method import DEFAULT_POLISH_T
from pocoloco.ops.probe_energy import box_probes, probe_embedding, set_energy_distance


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", required=True, help="a teacher-pairs folder with >= 2 draws per frame")
    ap.add_argument("--data", required=True, help="the dataset the pairs were made from")
    ap.add_argument("--student", default="default:fast", help="the student (default default:fast)")
    ap.add_argument("--teacher", default="default", help="its teacher, for the finishing call (default default)")
    ap.add_argument("--frames", type=int, default=12, help="frames scored (the pairs' first F; default 12)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None, help="write the rows here")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    pairs = read_teacher_pairs(a.pairs, renoised=None)  # without re-noised pairs, their rows are left out
    D = pairs.settings.draws
    if D < 2:
        sys.exit(f"{a.pairs}: one draw per frame; make pairs with --draws-per-frame >= 2")
    student = load_method(resolve_ckpt_arg(a.student))
    teacher = load_method(resolve_ckpt_arg(a.teacher))
    cfg, net = student.config, student.model.float().eval()
    if not cfg.student_calls:
        sys.exit(f"--student {a.student}: not a distilled student")
    # the pairs' conditioning (outfit ids, body shapes) from the teacher's dataset, as distill made it
    task = DistillTask(distill_config(teacher.config, cfg.student_calls), a.data)
    schedule = task.schedule
    G = min(a.frames, len(pairs.targets) // D)
    idx = np.arange(G * D)
    gen = torch.Generator().manual_seed(0)
    cond = task.condition(torch.from_numpy(pairs.joints[idx]), torch.from_numpy(pairs.subject[idx]))
    target = torch.from_numpy(pairs.targets[idx]).float()
    t_sets = target[..., :3].reshape(G, D, -1, 3)
    probes = box_probes(t_sets, 256, gen).unsqueeze(1)
    e_teacher = probe_embedding(t_sets, probes)
    rows: list[dict] = []

    def score(x0: torch.Tensor, name: str) -> None:
        stats = set_energy_distance(probe_embedding(x0[..., :3].reshape(G, D, -1, 3), probes), e_teacher)
        ratio = (stats["spread_samples"] / stats["spread_refs"]).mean().item()
        rows.append({"row": name, "spread_ratio": ratio, "energy_distance": stats["energy_distance"].mean().item()})
        print(f"| {name} | {ratio:.2f} | {rows[-1]['energy_distance']:+.3f} |", flush=True)

    def x0_at(x: torch.Tensor, t: int) -> torch.Tensor:
        tt = torch.full((len(x),), t)
        return schedule.pred_to_eps_x0(net(x, tt, cond).float(), x, tt, cfg.prediction_type)[1]

    print(f"{G} frames x {D} draws, {a.student} against the teacher's ODE answers\n")
    print("| row | spread, student / teacher | energy distance |\n|---|---|---|")
    ab = schedule.alphas_cumprod.double()
    with torch.no_grad():
        for k, t in enumerate(pairs.grid):
            score(x0_at(torch.from_numpy(pairs.states[idx, k]).float(), t), f"one call at t = {t}, teacher's path")
            if k:
                z = torch.randn(target.shape, generator=gen)
                score(x0_at((ab[t].sqrt() * target + (1 - ab[t]).sqrt() * z).float(), t),
                      f"one call at t = {t}, re-noised teacher answer")  # fmt: skip
        if pairs.renoised_targets is not None:
            for k, t in enumerate(pairs.grid[1:]):
                score(torch.from_numpy(pairs.renoised_targets[idx, k]).float(),
                      f"the teacher's ODE from its answer re-noised to t = {t}")  # fmt: skip
        noise = torch.from_numpy(pairs.states[idx, 0]).float()
        kw = {"prediction_type": cfg.prediction_type, "renoise": cfg.student_renoise}
        for calls in (1, 2, cfg.student_calls):
            out = sample_few_step(net, schedule, noise, cond, steps=calls, rng=PerSampleRNG(list(idx)), **kw)
            score(out, f"sampler, {calls} calls")
        grid = chain_grid(schedule.num_timesteps, cfg.student_calls)  # the grid it ships with
        rng = PerSampleRNG(list(idx))
        out = sample_few_step(net, schedule, noise, cond, timesteps=grid, rng=rng, **kw)
        score(out, f"sampler, grid {grid}")
        t_polish = student.polish[1] if student.polish is not None else DEFAULT_POLISH_T
        out = polish(teacher.model.float().eval(), schedule, out, cond, t_polish, rng, prediction_type=cfg.prediction_type)
        score(out, f"sampler, grid {grid} + the teacher's finishing call")
    if a.json:
        Path(a.json).write_text(json.dumps({"pairs": str(a.pairs), "student": a.student, "frames": G, "draws": D,
                                            "rows": rows}, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
