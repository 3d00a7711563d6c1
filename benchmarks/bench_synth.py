"""Seconds per generated frame of the synthetic capture pipeline, and scaling with workers.

For each worker count, generates a fresh dataset with the `small` preset's
settings (cut to a few frames per sequence so the benchmark takes minutes) and
reports wall seconds per stored frame plus the per-stage CPU breakdown
(motion+posing, cloth simulation, capture, writing) from the dataset card.
Median of --repeats runs per worker count.

    python benchmarks/bench_synth.py --workers 1 2 --frames 16 --repeats 1
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path

from pocoloco.synth.config import synth_preset
from pocoloco.synth.pipeline import synthesize


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="small")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--frames", type=int, default=16, help="stored frames per sequence")
    p.add_argument("--train-sequences", type=int, default=1)
    p.add_argument("--test-sequences", type=int, default=1)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--out", default="benchmarks/results/synth.json")
    args = p.parse_args()

    config = dataclasses.replace(
        synth_preset(args.preset),
        frames_per_sequence=args.frames,
        train_sequences=args.train_sequences,
        test_sequences=args.test_sequences,
    )
    rows = []
    for workers in args.workers:
        walls, cards = [], []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                card = synthesize(config, Path(tmp) / "d", workers=workers)
                walls.append(time.perf_counter() - t0)
                cards.append(card)
        frames = sum(c[split]["frames"] for c in cards[0]["counts"].values() for split in ("train", "test"))
        simulated = len(config.subjects) * (config.train_sequences + config.test_sequences) * config.frames_per_sequence
        per_stage = cards[0]["generation"]["cpu_seconds_per_frame"]
        rows.append(
            {
                "workers": workers,
                "wall_seconds": statistics.median(walls),
                "frames": frames,
                "wall_seconds_per_frame": statistics.median(walls) / simulated,
                "cpu_seconds_per_frame": per_stage,
                "penetration": {s: v.get("penetration") for s, v in cards[0]["subjects"].items()},
            }
        )
    base = rows[0]["wall_seconds_per_frame"]
    print(f"preset={args.preset} frames/sequence={args.frames} subjects={len(config.subjects)} "
          f"sequences/subject={config.train_sequences + config.test_sequences} points={config.num_points}")  # fmt: skip
    print(f"{'workers':>7} {'wall s':>8} {'s/frame':>8} {'speed-up':>8} | per-stage CPU s/frame: motion sim capture write")
    for r in rows:
        st = r["cpu_seconds_per_frame"]
        print(
            f"{r['workers']:>7} {r['wall_seconds']:>8.1f} {r['wall_seconds_per_frame']:>8.3f} "
            f"{base / r['wall_seconds_per_frame']:>8.2f} | {st['motion']:.3f} {st['simulation']:.3f} "
            f"{st['capture']:.3f} {st['write']:.3f}"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"config": config.to_dict(), "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
