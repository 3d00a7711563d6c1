"""A distilled few-step student against its 25-call teacher (issue 42): quality and speed, one table.

Quality comes from ``pocoloco bench quality`` reports of the same frames, points and seeds (the
teacher's row and one report per student setting), paired per frame: Chamfer, loose-garment M2S,
the share of points > 10 cm from the scan, and the spread between a pose's samples (diversity);
each as the student's mean, its paired difference to the teacher +- standard error, and the ratio.

Speed is measured here, in one process, for every model at each point count: seconds per cloud
(median of ``--repeats`` rounds, every setting drawing one cloud per round in turn, ``--threads``
torch threads), as a ratio to the teacher's in the same run; the network's peak memory is the same
for the student and its teacher (the same network), so the ratio is time only. ``--models A B ...``
times checkpoints of any kind the same way on the seven demo poses (e.g. ``default:hybrid`` and
``default:hybrid-fast``), each with its default sampler (``NAME@STEPS``: that many steps).

    python benchmarks/bench_fast.py --teacher default --student RUN/model --calls 1 2 4 \\
        --points 2048 10000 50000 --threads 1 \\
        --quality test=REF/test/quality.json:pocoloco \\
        --student-quality test:4=FAST4/test/quality.json:pocoloco ... --json fast.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from motion_gain import paired, rows  # noqa: E402

from pocoloco.evaluation.judge import same_reference_set  # noqa: E402

METRICS = (("chamfer_cm", "Chamfer cm"), ("m2s_garment_cm", "garment M2S cm"),
           ("outlier_10cm_pct", "> 10 cm %"), ("diversity_cm", "spread cm"))  # fmt: skip


def interleaved_medians(settings: list[tuple], pose_spec: str, n: int, repeats: int) -> dict[str, float]:
    """Median seconds per cloud of n points at ``pose_spec`` for each ``(label, method, options)``
    of ``settings``: one warm-up each, then ``repeats`` rounds in which every setting draws one cloud
    in turn (interleaved, so that a busy machine slows them alike)."""
    times: dict[str, list[float]] = {label: [] for label, _, _ in settings}
    for _, m, opts in settings:
        m.predict(m.load_pose(pose_spec), 256, seeds=[0], options=opts)  # warm-up
    for r in range(repeats):
        for label, m, opts in settings:
            pose = m.load_pose(pose_spec)
            t0 = time.perf_counter()
            m.predict(pose, n, seeds=[r + 1], options=opts)
            times[label].append(time.perf_counter() - t0)
    return {label: statistics.median(t) for label, t in times.items()}


def speed(teacher: str, student: str, calls: list[int], points: list[int], repeats: int,
          pose_spec: str = "demo:skirt") -> list[dict]:  # fmt: skip
    """Seconds per cloud of the teacher (its default sampler) and the student at each call count,
    all models loaded once and timed by :func:`interleaved_medians`; the ratio to the teacher's."""
    from pocoloco.engine.shipped import resolve_ckpt_arg
    from pocoloco.methods import load_method
    from pocoloco.methods.base import SamplerOptions

    settings = [("teacher (dpm++sde 25)", load_method(resolve_ckpt_arg(teacher)), SamplerOptions())]
    fast = load_method(resolve_ckpt_arg(student))
    settings += [(f"student, {c} call(s)", fast, SamplerOptions(steps=c)) for c in calls]
    out = []
    for n in points:
        med = interleaved_medians(settings, pose_spec, n, repeats)
        base = med[settings[0][0]]
        for label, _, _ in settings:
            out.append({"points": n, "model": label, "seconds": med[label], "speedup": base / med[label]})
            print(f"{n:>6} {label:<24} {med[label]:8.3f} s  {base / med[label]:6.1f}x", flush=True)
    return out


def models_speed(names: list[str], repeats: int, n: int = 2048) -> list[dict]:
    """Seconds per cloud of each model (any kind, its default sampler: e.g. ``default:hybrid`` and
    ``default:hybrid-fast``; ``NAME@STEPS`` with that many steps or calls) over the seven garment
    kinds' demo poses, each pose timed by :func:`interleaved_medians`: their mean, and the ratio to
    the first model's."""
    from pocoloco.engine.shipped import resolve_ckpt_arg
    from pocoloco.methods import load_method
    from pocoloco.methods.base import SamplerOptions

    settings = []
    for name in names:
        ckpt, _, steps = name.partition("@")
        settings.append((name, load_method(resolve_ckpt_arg(ckpt)), SamplerOptions(steps=int(steps) if steps else None)))
    per_pose: dict[str, dict[str, float]] = {name: {} for name in names}
    for demo in ("skirt", "dress", "maxi", "shirt", "sleeves", "trousers", "tight"):
        for name, seconds in interleaved_medians(settings, f"demo:{demo}", n, repeats).items():
            per_pose[name][demo] = seconds
    base = statistics.mean(per_pose[names[0]].values())
    out = []
    for name in names:
        mean = statistics.mean(per_pose[name].values())
        out.append({"points": n, "model": name, "seconds_mean": mean, "seconds_per_pose": per_pose[name],
                    "speedup": base / mean})  # fmt: skip
        print(f"{n:>6} {name:<40} {mean:8.3f} s  {base / mean:6.1f}x  " +
              " ".join(f"{k} {v:.2f}" for k, v in per_pose[name].items()), flush=True)  # fmt: skip
    return out


def animation(teacher: str, student: str, motion: str, frames: int, threads: int, points: int = 2048,
              no_polish: bool = False) -> list[dict]:  # fmt: skip
    """``pocoloco animate`` (chain, its defaults: the teacher renoises each frame to t = 200 and runs
    25 SDE steps; the student to t = 250, one call, and its teacher's finishing call if it has one)
    of ``frames`` frames: frames per second of the animation itself (no rendering), flicker and
    Chamfer to the scans. ``no_polish``: also the student with ``--no-polish`` (its call alone)."""
    import subprocess
    import tempfile

    out = []
    runs = [("teacher", teacher, []), ("student", student, [])]
    if no_polish:
        runs.append(("student, --no-polish", student, ["--no-polish"]))
    for name, ckpt, extra in runs:
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, "-m", "pocoloco", "animate", "--ckpt", ckpt, "--motion", motion, "--frames",
                   f"0:{frames}", "--points", str(points), "--threads", str(threads), "--no-render", "--out", tmp,
                   *extra]  # fmt: skip
            subprocess.run(cmd, check=True, capture_output=True)
            info = json.loads((Path(tmp) / "animation.json").read_text())
        m = info["metrics"]
        out.append({"model": name, "frames": frames, "points": points, "threads": threads,
                    "frames_per_s": frames / info["seconds_total"], "flicker_cm": m["flicker_mean_cm"],
                    "gt_flicker_cm": m["gt_flicker_mean_cm"], "chamfer_to_gt_cm": m["chamfer_to_gt_mean_cm"]})  # fmt: skip
        r = out[-1]
        print(f"animate {name:<20} {r['frames_per_s']:6.2f} frames/s  flicker {r['flicker_cm']:.2f} cm "
              f"(scans {r['gt_flicker_cm']:.2f})  Chamfer to scans {r['chamfer_to_gt_cm']:.2f} cm", flush=True)
    return out


def distribution(pairs: list[tuple[str, str]]) -> list[dict]:
    """Paired per pose, per shared window: the student's energy score (the judge's proper score) and
    spread between samples against the teacher's, from ``bench distribution`` reports (``FILE:ROW``
    each), one (teacher, student) pair per reference set; several sets are pooled pose by pose (a
    pose is keyed by its set, so two sets may hold the same frame)."""
    def load(index, report, row):
        return {(index, p["subject"], p["sequence"], p["frame"], p["window"]): p["rows"][row]
                for p in report["per_pose"] if row in p["rows"]}  # fmt: skip

    ref, stu = {}, {}
    for index, (teacher, student) in enumerate(pairs):
        (t_path, _, t_row), (s_path, _, s_row) = teacher.rpartition(":"), student.rpartition(":")
        t_report, s_report = (json.loads(Path(path).read_text()) for path in (t_path, s_path))
        if (why := same_reference_set(t_report, s_report)) is not None:  # pairing two copies would be silently wrong
            raise SystemExit(f"bench_fast --distribution: {teacher} and {student}: {why}")
        ref.update(load(index, t_report, t_row))
        stu.update(load(index, s_report, s_row))
    out = []
    for window in sorted({k[4] for k in ref}):
        keys = sorted(k for k in ref if k[4] == window and k in stu)
        row: dict = {"window": window, "poses": len(keys), "sets": len(pairs)}
        for metric in ("energy_score", "spread_samples"):
            p = paired({k: ref[k] for k in keys}, {k: stu[k] for k in keys}, metric, keys)
            row[metric] = {**p, "ratio": p["model"] / p["reference"] if p["reference"] else float("nan")}
        out.append(row)
        es, sp = row["energy_score"], row["spread_samples"]
        print(f"judge, {window} s shared, {len(keys)} poses: energy score x{es['ratio']:.3f} the teacher's (paired "
              f"{100 * es['diff'] / es['reference']:+.1f} +- {100 * es['se'] / es['reference']:.1f} %); spread between "
              f"samples x{sp['ratio']:.3f}")  # fmt: skip
    return out


def quality(teacher_specs: dict[str, str], student_specs: dict[tuple[str, str], str]) -> list[dict]:
    out = []
    for (split, calls), spec in sorted(student_specs.items()):
        ref, stu = rows(teacher_specs[split]), rows(spec)
        keys = sorted(k for k in ref if k in stu)
        row: dict = {"split": split, "calls": calls, "frames": len(keys)}
        for metric, _ in METRICS:
            p = paired(ref, stu, metric, keys)
            row[metric] = {**p, "ratio": p["model"] / p["reference"] if p["reference"] else float("nan")}
        out.append(row)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--teacher", default="default")
    ap.add_argument("--student", required=True)
    ap.add_argument("--calls", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--points", type=int, nargs="+", default=[2048, 10000, 50000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--models", nargs="*", default=[], help="checkpoints of any kind to time on the seven demo "
                    "poses (the first is the baseline), e.g. default:hybrid default:hybrid-fast")  # fmt: skip
    ap.add_argument("--quality", nargs="*", default=[], help="SPLIT=FILE:ROW, the teacher's report per split")
    ap.add_argument("--student-quality", nargs="*", default=[], help="SPLIT:CALLS=FILE:ROW")
    ap.add_argument("--animate", default=None, help="a DATASET:subject/split/sequence to animate with both models")
    ap.add_argument("--animate-frames", type=int, default=40)
    ap.add_argument("--animate-threads", type=int, default=2)
    ap.add_argument("--animate-no-polish", action="store_true",
                    help="--animate: also the student without its teacher's finishing call")
    ap.add_argument("--distribution", nargs="*", default=[], help="SPLIT=TEACHER_FILE:ROW,STUDENT_FILE:ROW "
                    "(bench distribution reports of one reference set; a SPLIT given twice pools its sets)")  # fmt: skip
    ap.add_argument("--json", required=True)
    a = ap.parse_args()
    import torch

    torch.set_num_threads(a.threads)
    result: dict = {"teacher": a.teacher, "student": a.student, "threads": a.threads, "repeats": a.repeats}
    teacher_specs = dict(s.split("=", 1) for s in a.quality)
    student_specs = {tuple(k.split(":", 1)): v for k, v in (s.split("=", 1) for s in a.student_quality)}
    if student_specs:
        result["quality"] = quality(teacher_specs, student_specs)
        print("| split | calls | " + " | ".join(f"{t} (paired diff, ratio)" for _, t in METRICS) + " |")
        print("|---|---|" + "---|" * len(METRICS))
        for r in result["quality"]:
            cells = [f"{r[m]['model']:.2f} ({r[m]['diff']:+.2f} +- {r[m]['se']:.2f}, {r[m]['ratio']:.3f})" for m, _ in METRICS]
            print(f"| {r['split']} | {r['calls']} | " + " | ".join(cells) + " |")
    if not a.no_speed:
        result["speed"] = speed(a.teacher, a.student, a.calls, a.points, a.repeats)
    if a.models:
        result["models_speed"] = models_speed(a.models, a.repeats)
    if a.distribution:
        result["distribution"] = {}
        sets: dict[str, list[tuple[str, str]]] = {}
        for spec in a.distribution:  # a split named twice: its reference sets pooled
            split, pair = spec.split("=", 1)
            sets.setdefault(split, []).append(tuple(pair.split(",", 1)))
        for split, pairs in sets.items():
            print(f"[{split}, {len(pairs)} reference set{'s' if len(pairs) > 1 else ''}]")
            result["distribution"][split] = distribution(pairs)
    if a.animate:
        result["animation"] = animation(a.teacher, a.student, a.animate, a.animate_frames, a.animate_threads,
                                        no_polish=a.animate_no_polish)  # fmt: skip
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(result, indent=1))
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
