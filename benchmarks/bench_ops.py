"""Benchmark of the point ops: knn, Chamfer and farthest point sampling, fast vs reference.

Usage:
    python benchmarks/bench_ops.py [--points 2000 10000 50000] [--reference-max 2000]
                                   [--repeats 3] [--out benchmarks/results/ops.json]

For each cloud size N (batch 1, float32, uniform in a 1 m cube):
* knn k=1: ``ops.knn`` (torch, chunked) vs ``ops.knn_numpy`` (scipy cKDTree) vs
  ``ops.knn_reference`` (python loop over queries);
* Chamfer both ways (N vs N): ``ops.chamfer_distance`` vs scipy vs the reference;
* FPS N -> min(2048, N / 4) (``--fps-quarter``: N / 4, what ``--even`` keeps of 4 N candidates):
  ``backend="torch"``, ``backend="fpsample"`` (only if that optional package is installed) vs the
  python-loop reference.
References run only for N <= --reference-max. Median wall time of --repeats runs
(after one warm-up), with torch limited to the threads given by OMP_NUM_THREADS.
"""

from __future__ import annotations

import argparse
import os
import platform
from collections.abc import Callable

import torch

from pocoloco.ops import (
    chamfer_distance,
    chamfer_distance_reference,
    farthest_point_sampling,
    farthest_point_sampling_reference,
    knn,
    knn_numpy,
    knn_reference,
)
from pocoloco.ops.sampling import fpsample_available
from pocoloco.utils.atomic import write_json_atomic
from pocoloco.utils.timing import median_seconds


def _scipy_chamfer(x, y) -> float:
    return float(knn_numpy(x, y).dists.mean() + knn_numpy(y, x).dists.mean())


def bench(n: int, reference_max: int, repeats: int, fps_quarter: bool = False,
          ops: tuple[str, ...] = ("knn", "chamfer", "fps")) -> list[dict]:  # fmt: skip
    g = torch.Generator().manual_seed(n)
    x, y = torch.rand(1, n, 3, generator=g), torch.rand(1, n, 3, generator=g)
    xn, yn = x[0].double().numpy(), y[0].double().numpy()
    num = n // 4 if fps_quarter else min(2048, n // 4)
    ref = n <= reference_max
    cases: list[tuple[str, str, Callable[[], object]]] = [
        ("knn k=1", "torch", lambda: knn(x, y, 1)),
        ("knn k=1", "scipy", lambda: knn_numpy(xn, yn, 1)),
        ("chamfer", "torch", lambda: chamfer_distance(x, y).chamfer_sq),
        ("chamfer", "scipy", lambda: _scipy_chamfer(xn, yn)),
        (f"fps ->{num}", "torch", lambda: farthest_point_sampling(x, num, backend="torch")),
    ]
    if fpsample_available():
        cases.append((f"fps ->{num}", "fpsample", lambda: farthest_point_sampling(x, num, backend="fpsample")))
    if ref:
        cases += [
            ("knn k=1", "reference", lambda: knn_reference(x, y, 1)),
            ("chamfer", "reference", lambda: chamfer_distance_reference(x, y).chamfer_sq),
            (f"fps ->{num}", "reference", lambda: farthest_point_sampling_reference(x, num)),
        ]
    rows = []
    for op, impl, fn in (c for c in cases if c[0].split()[0] in ops):
        r = repeats if impl != "reference" else 1
        rows.append({"op": op, "impl": impl, "num_points": n, "median_s": median_seconds(fn, r), "repeats": r})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, nargs="+", default=[2000, 10000, 50000])
    parser.add_argument("--reference-max", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fps-quarter", action="store_true", help="FPS keeps N / 4 (not capped at 2048)")
    parser.add_argument("--ops", nargs="+", choices=["knn", "chamfer", "fps"], default=["knn", "chamfer", "fps"])
    parser.add_argument("--out", default=os.path.join("benchmarks", "results", "ops.json"))
    args = parser.parse_args()
    if args.repeats < 1 or min(args.points) < 8:
        raise SystemExit("--repeats must be >= 1 and --points >= 8")

    rows = [row for n in args.points for row in bench(n, args.reference_max, args.repeats, args.fps_quarter, tuple(args.ops))]
    print(f"{'op':<12} {'impl':<10} {'points':>7} {'median s':>10}")
    for r in rows:
        print(f"{r['op']:<12} {r['impl']:<10} {r['num_points']:>7} {r['median_s']:>10.4f}")
    result = {
        "benchmark": "pocoloco.ops knn / chamfer / fps, batch 1, float32 (scipy: float64), uniform cube",
        "torch_threads": torch.get_num_threads(), "fpsample": fpsample_available(),
        "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "load_avg_1min": os.getloadavg()[0], "rows": rows,
    }
    write_json_atomic(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
