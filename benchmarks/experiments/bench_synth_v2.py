"""The data-v2 pipeline against the first one, on the same sequences: speed and quality.

Generates the same dataset (a preset's subjects, motions and seeds, cut to ``--frames``
stored frames per sequence) once per setting and repeat, settings interleaved (v1, v2,
v1, v2, ...) so both see the same load on a shared machine, each with ``--workers``
worker processes. "v1" is the preset with ``config.SYNTH_V1`` (grid garments, no
self-contact, every candidate ray-tested); each ``--variant`` is the preset with
``key=value`` overrides (``SynthConfig`` fields; the default "v2" is the preset as is).

Reports wall seconds (median over repeats), stored frames per second, the speed-up
against v1, the per-stage CPU seconds per frame measured inside the workers (from the
dataset card), and the card's quality statistics: rejected frames, cloth penetration
into the body (max / mean mm, % of garment vertices inside), cloth self-intersection
(crossing triangle pairs on every 10th stored frame, counted after generation, outside the
timings), loose-garment share of the points.

    python benchmarks/experiments/bench_synth_v2.py --preset small --frames 24 --workers 2 --repeats 3 \\
        [--variant v2 "v2 sc: cloth_self_contact=True"] [--out benchmarks/results/synth_v2.json] \\
        [--before-src /path/to/an/older/checkout/src]

``--before-src``: also time the pipeline as an older checkout of pocoloco has it ("before": its
code and its preset, e.g. ``git worktree add /tmp/before dd882a9`` = main before data v2). Every
setting then runs in its own Python process (``PYTHONPATH`` = that checkout's ``src``), timed
inside it around ``synthesize`` only, so imports and start-up count for none of them.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import statistics
import tempfile
import time
from pathlib import Path


def parse_variant(text: str) -> tuple[str, dict]:
    """ "name: key=value key=value" -> (name, overrides)."""
    name, _, rest = text.partition(":")
    over = {}
    for item in rest.split():
        k, v = item.split("=", 1)
        over[k] = ast.literal_eval(v)
    return name.strip(), over


def self_intersection_stats(root: Path, every: int = 10) -> dict:
    """Per subject: mean crossing garment-triangle pairs per frame and % of frames with
    any, on every ``every``-th stored frame of every sequence (the same frames whatever
    the setting; computed here, outside the timed generation)."""
    import numpy as np

    from pocoloco.data.format import DatasetLayout, read_frame, read_subject
    from pocoloco.synth.garments import self_intersections

    layout = DatasetLayout(root)
    out = {}
    for subject in sorted(p.name for p in (root / "subjects").iterdir() if p.is_dir()):
        faces = read_subject(layout.subject_path(subject)).garment_faces
        if faces is None:
            continue
        counts = []
        for split in ("train", "test"):
            for _, seq, path in layout.iter_frames(split, subjects=[subject]):
                index = int(Path(path).stem)
                if index % every == 0:
                    counts.append(self_intersections(read_frame(path, keys=["garment_vertices"]).garment_vertices,
                                                     faces))  # fmt: skip
        out[subject] = dict(pairs_mean=float(np.mean(counts)), frames_percent=float(100 * np.mean(np.array(counts) > 0)),
                            frames=len(counts))  # fmt: skip
    return out


def summarise(card: dict, wall: float, inter: dict) -> dict:
    """Speed and quality figures of one generated dataset's card."""
    counts = card["counts"]
    stored = sum(c[s]["frames"] for c in counts.values() for s in ("train", "test"))
    rejected = sum(c[s]["rejected_frames"] for c in counts.values() for s in ("train", "test"))
    subjects = {}
    for name, sub in card["subjects"].items():
        pen = sub.get("penetration") or {}
        subjects[name] = dict(
            garment=sub["garment_kind"], loose_share_percent=sub.get("loose_share_percent"),
            rejected=sum(counts[name][s]["rejected_frames"] for s in ("train", "test")),
            pen_max_mm=pen.get("max_mm"), pen_mean_mm=pen.get("mean_mm"), inside_percent=pen.get("fraction_percent"),
            stretch_max=pen.get("stretch_max"), self_intersection_pairs=inter.get(name, {}).get("pairs_mean"),
            self_intersection_frames_percent=inter.get(name, {}).get("frames_percent"),
        )  # fmt: skip
    return dict(wall_seconds=wall, stored_frames=stored, rejected_frames=rejected,
                cpu_seconds_per_frame=card["generation"]["cpu_seconds_per_frame"], subjects=subjects)  # fmt: skip


_DRIVER = """
import dataclasses, json, sys, time
from pocoloco.synth.config import synth_preset
from pocoloco.synth.pipeline import synthesize
a = json.loads(sys.argv[1])
config = dataclasses.replace(synth_preset(a["preset"]), frames_per_sequence=a["frames"],
                             train_sequences=a["train"], test_sequences=a["test"], **a["overrides"])
t0 = time.perf_counter()
synthesize(config, a["out"], workers=a["workers"])
print(json.dumps({"wall": time.perf_counter() - t0}))
"""


def run_in_process(src: str, args, overrides: dict, out: Path) -> tuple[dict, float]:
    """Generate with the pocoloco under ``src`` in a fresh Python: (card, wall seconds of synthesize)."""
    import subprocess
    import sys

    spec = dict(preset=args.preset, frames=args.frames, train=args.train_sequences, test=args.test_sequences,
                overrides=overrides, out=str(out), workers=args.workers)  # fmt: skip
    env = {**os.environ, "PYTHONPATH": src}
    r = subprocess.run([sys.executable, "-c", _DRIVER, json.dumps(spec)], env=env, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"generation under {src} failed: {r.stderr[-2000:]}")
    wall = json.loads(r.stdout.strip().splitlines()[-1])["wall"]
    return json.loads((out / "card.json").read_text()), wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--frames", type=int, default=24, help="stored frames per sequence")
    ap.add_argument("--train-sequences", type=int, default=1)
    ap.add_argument("--test-sequences", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variant", nargs="*", default=["v2"], help='"name: key=value ..." (SynthConfig overrides)')
    ap.add_argument("--out", default="benchmarks/results/synth_v2.json")
    ap.add_argument("--before-src", help="src folder of an older pocoloco checkout, timed as 'before'")
    args = ap.parse_args()

    from pocoloco.synth.config import SYNTH_V1, synth_preset
    from pocoloco.synth.pipeline import synthesize

    base = dataclasses.replace(synth_preset(args.preset), frames_per_sequence=args.frames,
                               train_sequences=args.train_sequences, test_sequences=args.test_sequences)  # fmt: skip
    here = str(Path(__file__).resolve().parents[2] / "src")
    variants = [("v1", SYNTH_V1)] + list(map(parse_variant, args.variant))
    settings = [(n, dataclasses.replace(base, **o)) for n, o in variants]
    sources = {n: (here, o) for n, o in variants}
    if args.before_src:
        settings.insert(0, ("before", base))  # (its config is the older checkout's preset)
        sources["before"] = (str(Path(args.before_src).resolve()), {})
    runs: dict[str, list[dict]] = {name: [] for name, _ in settings}
    for rep in range(args.repeats):
        for name, config in settings:
            with tempfile.TemporaryDirectory() as tmp:
                if args.before_src:
                    card, wall = run_in_process(*sources[name][:1], args, sources[name][1], Path(tmp) / "d")
                else:
                    t0 = time.perf_counter()
                    card = synthesize(config, Path(tmp) / "d", workers=args.workers)
                    wall = time.perf_counter() - t0
                inter = self_intersection_stats(Path(tmp) / "d") if rep == 0 else {}
            runs[name].append(summarise(card, wall, inter))
            print(f"repeat {rep} {name}: {wall:.1f} s wall, {runs[name][-1]['stored_frames']} frames, "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip

    ref = settings[0][0]  # "before" when timed, else "v1"
    v1_wall = statistics.median(r["wall_seconds"] for r in runs[ref])
    rows = []
    for name, config in settings:
        rs = runs[name]
        wall = statistics.median(r["wall_seconds"] for r in rs)
        # per-repeat speed-up against the v1 run of the same repeat (same load), then the median
        ratios = [a["wall_seconds"] / b["wall_seconds"] for a, b in zip(runs[ref], rs)]
        first = rs[0]  # quality is deterministic: every repeat generates the same data
        rows.append(dict(
            setting=name, reference=ref,
            overrides=("the older checkout's preset" if name == "before" else
                       {k: v for k, v in config.to_dict().items() if k != "subjects"}),
            wall_seconds_median=wall, wall_seconds=[r["wall_seconds"] for r in rs],
            frames_per_second=first["stored_frames"] / wall, speedup_median=statistics.median(ratios),
            speedup_of_medians=v1_wall / wall, per_repeat_speedup=ratios,
            cpu_seconds_per_frame=first["cpu_seconds_per_frame"], stored_frames=first["stored_frames"],
            rejected_frames=first["rejected_frames"], subjects=first["subjects"],
        ))  # fmt: skip

    print(f"\npreset {args.preset}: {len(base.subjects)} subjects x {args.train_sequences + args.test_sequences} "
          f"sequences x {args.frames} stored frames, {args.workers} workers, median of {args.repeats} "
          f"(settings interleaved)")  # fmt: skip
    print(f"| setting | wall s | frames/s | speed-up vs {ref} | CPU s/frame: motion, sim, capture, write | rejected |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        c = r["cpu_seconds_per_frame"]
        print(f"| {r['setting']} | {r['wall_seconds_median']:.1f} | {r['frames_per_second']:.2f} | "
              f"{r['speedup_median']:.2f}x | {c['motion']:.3f}, {c['simulation']:.3f}, {c['capture']:.3f}, "
              f"{c['write']:.3f} | {r['rejected_frames']} / {r['stored_frames'] + r['rejected_frames']} |")  # fmt: skip
    print("\n| setting | subject | loose % | rejected | pen. max / mean mm | % inside | stretch max | "
          "self-int. pairs / frame | frames with self-int. % |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    def fmt(v, f):
        return "-" if v is None else format(v, f)

    for r in rows:
        for name, s in r["subjects"].items():
            print(f"| {r['setting']} | {name} ({s['garment']}) | {fmt(s['loose_share_percent'], '.1f')} | "
                  f"{s['rejected']} | {fmt(s['pen_max_mm'], '.1f')} / {fmt(s['pen_mean_mm'], '.3f')} | "
                  f"{fmt(s['inside_percent'], '.2f')} | {fmt(s['stretch_max'], '.2f')} | "
                  f"{fmt(s['self_intersection_pairs'], '.0f')} | {fmt(s['self_intersection_frames_percent'], '.0f')} |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(preset=args.preset, frames=args.frames, workers=args.workers,
                                   repeats=args.repeats, load_avg_1min_end=os.getloadavg()[0], rows=rows), indent=1))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
