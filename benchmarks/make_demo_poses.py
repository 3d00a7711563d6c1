"""Write the shipped demo poses (``--joints demo:NAME``): one per outfit of a dataset.

For every subject (outfit) of DATASET, the last frame of its first test sequence with frames: its joints, the
anny pose parameters of that frame (so POP and CloSET, which need the posed body, take it too), the
outfit's name, the frame it came from and the scan's loose-garment share. The rule is fixed (no
frame is picked by how well a model does on it). And the last 2 s of motion before it (issue 41):
its window at 8 Hz (``motion_window_joints`` (17, 24, 3) in the frame's heading frame,
``motion_root_velocity`` (17, 3), ``motion_yaw_rate`` (17,), float16), from the dataset's
``motion_history.npz`` (``pocoloco data motion-history``), so motion-aware models see how the body
moved into the pose.

    python benchmarks/make_demo_poses.py --data ~/.cache/pocoloco/data/medium --out src/pocoloco/assets/poses
    python benchmarks/make_demo_poses.py --data ~/.cache/pocoloco/data/medium_v3 --out src/pocoloco/assets/poses \
        --add-motion      # only add the windows to the poses there (their frames' joints must match)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pocoloco.data.dataset import frame_motion_window
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


def motion_arrays(data: Path, subject: str, seq: str, index: int, joints: np.ndarray) -> dict[str, np.ndarray]:
    """The frame's 2 s motion window at 8 Hz as float16 arrays (its current sample checked against
    ``joints``)."""
    layout = DatasetLayout(data)
    path = layout.frame_path(subject, "test", seq, index)
    if np.abs(read_frame(path, ["joints"]).joints - joints).max() > 1e-5:
        raise SystemExit(f"{path}: its joints are not the demo pose's")
    w = frame_motion_window(path, 2.0, 8.0)
    return {"motion_window_joints": w.joints.astype(np.float16), "motion_root_velocity": w.root_velocity.astype(np.float16),
            "motion_yaw_rate": w.yaw_rate.astype(np.float16), "motion_seconds": np.float32(2.0),
            "motion_hz": np.float32(8.0)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--add-motion", action="store_true",
                    help="only add the motion windows to the demo poses in --out, from --data")  # fmt: skip
    args = ap.parse_args()
    card = read_card(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.add_motion:
        for path in sorted(args.out.glob("*.npz")):
            with np.load(path, allow_pickle=False) as z:
                pose = {k: z[k] for k in z.files if not k.startswith("motion_")}
            subject, _, seq, index = str(pose["source"]).split(":", 1)[1].split("/")
            pose.update(motion_arrays(args.data, subject, seq, int(index), pose["joints"]))
            save_npz_atomic(path, compress=True, **pose)
            print(f"{path.name}: the 2 s before {pose['source']}")
        return
    for subject in sorted(card["subjects"]):
        pose = demo_pose(args.data, subject)
        seq, index = str(pose["source"]).rsplit("/", 2)[1:]
        pose.update(motion_arrays(args.data, subject, seq, int(index), pose["joints"]))
        save_npz_atomic(args.out / f"{subject}.npz", compress=True, **pose)
        print(f"{subject}: {pose['source']}  loose {float(pose['loose_pct']):.1f} %")


if __name__ == "__main__":
    main()
