"""Write the shipped demo poses (``--joints demo:NAME``): one per outfit of a dataset.

For every subject (outfit) of DATASET, the last frame of its first test sequence with frames: its joints, the
anny pose parameters of that frame (so POP and CloSET, which need the posed body, take it too), the
outfit's name, the frame it came from and the scan's loose-garment share. The rule is fixed (no
frame is picked by how well a model does on it).

    python benchmarks/make_demo_poses.py --data ~/.cache/pocoloco/data/medium --out src/pocoloco/assets/poses
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pocoloco.data.format import DatasetLayout, read_card, read_frame, read_motion
from pocoloco.evaluation.metrics import LABEL_GARMENT
from pocoloco.utils.atomic import save_npz_atomic


def demo_pose(data: Path, subject: str) -> dict[str, np.ndarray]:
    layout = DatasetLayout(data)
    seq = next(q for q in layout.sequences(subject, "test") if layout.frame_indices(subject, "test", q))
    index = layout.frame_indices(subject, "test", seq)[-1]
    frame = read_frame(layout.frame_path(subject, "test", seq, index), ["joints", "frame_index", "labels"])
    motion = read_motion(layout.motion_path(subject, "test", seq))
    row = int(frame.frame_index)
    return {
        "joints": frame.joints.astype(np.float32),
        "joint_rotvecs": motion.joint_rotvecs[row].astype(np.float32),
        "root_translation": motion.root_translation[row].astype(np.float32),
        "outfit": np.array(subject),
        "source": np.array(f"{data.name}:{subject}/test/{seq}/{index}"),
        "loose_pct": np.float32(100.0 * np.mean(frame.labels == LABEL_GARMENT)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()
    card = read_card(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    for subject in sorted(card["subjects"]):
        pose = demo_pose(args.data, subject)
        save_npz_atomic(args.out / f"{subject}.npz", compress=True, **pose)
        print(f"{subject}: {pose['source']}  loose {float(pose['loose_pct']):.1f} %")


if __name__ == "__main__":
    main()
