"""Frame file storage: ``"float32"`` against ``"compact"`` (``format.FRAME_STORAGES``).

Takes ``--frames`` frames spread evenly over a dataset (every subject and split), reads each
once, writes it to a temporary folder both ways and reports per storage: bytes per frame,
``write_frame`` seconds, ``read_frame`` seconds for the whole frame and for what a training
batch reads (points, joints, labels), each the median over frames of the median of
``--repeats`` runs, and, for compact, the largest absolute error of every key read back
(against the float32 values; ``format.COMPACT_MAX_ERROR`` is the documented bound). Reads come
from the page cache: they time decoding, not the disk.

For reference it also measures the scheme compact does not use for positions: float16 offsets
from the pelvis joint (error grows with the distance to the pelvis: 0.24 mm within 1 m, 0.49 mm
within 2 m).

    python benchmarks/bench_frame_storage.py /work/main/data/small [--frames 20] [--repeats 5] \\
        [--out benchmarks/results/frame_storage.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from pathlib import Path

import numpy as np

from pocoloco.data import format as fmt
from pocoloco.utils.atomic import jsonable
from pocoloco.utils.timing import median_seconds

TRAIN_KEYS = ["points", "joints", "labels"]  # what PointCloudDataset reads per item


def pick_frames(root: Path, count: int) -> list[Path]:
    """``count`` frame files evenly spaced over all frames of every subject and split."""
    layout = fmt.DatasetLayout(root)
    paths = [p for split in fmt.SPLITS for _, _, p in layout.iter_frames(split)]
    if not paths:
        raise ValueError(f"{root}: no frame files")
    idx = np.unique(np.linspace(0, len(paths) - 1, min(count, len(paths))).round().astype(int))
    return [paths[i] for i in idx]


def pelvis_float16_error(frame: fmt.Frame) -> dict[str, float]:
    """Max abs error (m) of positions stored as float16 offsets from the pelvis (joint 0)."""
    out = {}
    pelvis = frame.joints[0]
    for key in ("points", "body_vertices", "garment_vertices"):
        x = getattr(frame, key)
        if x is not None:
            back = (x - pelvis).astype(np.float16).astype(np.float32) + pelvis
            out[key] = float(np.abs(back.astype(np.float64) - x).max())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="dataset folder (holds card.json); only read")
    ap.add_argument("--frames", type=int, default=20, help="frames measured (default 20)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per frame and operation (default 5)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "frame_storage.json")
    args = ap.parse_args()
    fmt.read_card(args.dataset)
    frames = pick_frames(args.dataset, args.frames)

    per: dict[str, dict[str, list[float]]] = {s: {"bytes": [], "write": [], "read": [], "read_train": []}
                                              for s in fmt.FRAME_STORAGES}  # fmt: skip
    errors: dict[str, float] = {}
    pelvis_errors: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n, src in enumerate(frames):
            frame = fmt.read_frame(src)
            for key, err in pelvis_float16_error(frame).items():
                pelvis_errors[key] = max(pelvis_errors.get(key, 0.0), err)
            for storage in fmt.FRAME_STORAGES:
                dst = Path(tmp) / f"{n:03d}_{storage}.npz"
                per[storage]["write"].append(median_seconds(lambda: fmt.write_frame(dst, frame, storage=storage),
                                                            args.repeats, warmup=0))  # fmt: skip
                per[storage]["bytes"].append(os.path.getsize(dst))
                per[storage]["read"].append(median_seconds(lambda: fmt.read_frame(dst), args.repeats, warmup=0))
                read_train = lambda: fmt.read_frame(dst, TRAIN_KEYS, allow_missing=True)  # noqa: E731
                per[storage]["read_train"].append(median_seconds(read_train, args.repeats, warmup=0))
                back = fmt.read_frame(dst)
                for key in fmt.FRAME_KEYS:
                    a, b = getattr(frame, key), getattr(back, key)
                    if isinstance(a, np.ndarray):
                        assert b.dtype == a.dtype, (key, b.dtype)
                        if storage == "compact":
                            err = float(np.abs(a.astype(np.float64) - b.astype(np.float64)).max())
                            errors[key] = max(errors.get(key, 0.0), err)
                        else:
                            assert np.array_equal(a, b), key

    summary = {}
    for storage, m in per.items():
        summary[storage] = {
            "bytes_per_frame_mean": float(np.mean(m["bytes"])),
            "bytes_per_frame_min": int(min(m["bytes"])),
            "bytes_per_frame_max": int(max(m["bytes"])),
            "write_seconds_median": statistics.median(m["write"]),
            "read_seconds_median": statistics.median(m["read"]),
            "read_train_keys_seconds_median": statistics.median(m["read_train"]),
        }
    ratio = summary["compact"]["bytes_per_frame_mean"] / summary["float32"]["bytes_per_frame_mean"]
    result = {
        "dataset": os.fspath(args.dataset),
        "frames": [os.path.relpath(p, args.dataset) for p in frames],
        "repeats": args.repeats,
        "load_average": os.getloadavg(),
        "storage": summary,
        "compact_size_ratio": ratio,
        "compact_max_abs_error": errors,
        "compact_documented_bound": fmt.COMPACT_MAX_ERROR,
        "float16_pelvis_offsets_max_abs_error": pelvis_errors,
    }

    print(f"{len(frames)} frames of {args.dataset}, median of {args.repeats} runs each "
          f"(load {os.getloadavg()[0]:.1f})")  # fmt: skip
    print(f"{'storage':<9} {'KB/frame':>9} {'write ms':>9} {'read ms':>8} {'read train keys ms':>19}")
    for storage, s in summary.items():
        print(f"{storage:<9} {s['bytes_per_frame_mean'] / 1e3:9.0f} {1e3 * s['write_seconds_median']:9.1f} "
              f"{1e3 * s['read_seconds_median']:8.1f} {1e3 * s['read_train_keys_seconds_median']:19.1f}")  # fmt: skip
    print(f"compact / float32 bytes: {ratio:.3f}")
    print(f"{'key':<17} {'compact max abs err':>20} {'bound':>9} {'f16 pelvis offsets':>19}")
    for key in fmt.FRAME_KEYS:
        if key in errors:
            bound = fmt.COMPACT_MAX_ERROR.get(key, 0.0)
            pel = f"{pelvis_errors[key]:.3g}" if key in pelvis_errors else "-"
            print(f"{key:<17} {errors[key]:20.3g} {bound:9.3g} {pel:>19}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(jsonable(result), indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
