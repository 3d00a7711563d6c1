"""Reference sets of true garment states: many cloth states at exactly one frame's body.

A pose has many true garment states; a dataset frame is one draw. ``make_histories`` draws
more: for N frames of a synthetic dataset's split (spread over its subjects), K cloth states at
**exactly that frame's body**, each reached by another motion of the same pipeline — a
procedural motion of another kind and seed (``prefix_seconds`` long, from the rest pose, the
cloth settled there as usual), blended in ``blend_frames`` into the frame's own motion
``shared`` seconds before the frame, then the frame's own motion up to it — and captured as the
dataset's frames are (same point count, cameras, normals, labels).

``shared = 0``: only the pose is shared (the question a pose-only model answers); ``shared =
2``: the last two seconds of motion are shared too (what a motion-aware model can know). Each
history's prefix motion is the same for every window, so the windows differ only in where it
joins the frame's motion: the prefix's cloth is simulated once (from the subject's cloth settled
at rest) and each window continues it, turned to face where its join faces.

The result is a dataset in the usual format (``docs/reference/formats.md``; ``data verify`` /
``data info`` read it): one *sequence* per (pose, window), named
``<sequence>_f<frame>_s<shared>``, whose frames ``0 .. K-1`` are the K histories' states and frame
``K`` a copy of the frame's own scan; every frame has the same body. Its ``sequence.json`` lists
each reference's prefix motion; the card's ``histories`` section the run's settings.
Resumable: each reference's frame file is written atomically. Cost: ~50 simulated frames of
prefix per history, then blend + shared frames per window (``medium``'s cloth: 0.5-0.9 CPU s per
frame on a 2-core AVX2 machine).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data.format import (
    DatasetLayout,
    Frame,
    StoredMotion,
    card_from_disk,
    read_card,
    read_frame,
    read_motion,
    read_sequence_meta,
    write_card,
    write_frame,
    write_motion,
    write_sequence_meta,
)
from ..utils.atomic import atomic_open, output_folder
from ..utils.seeding import torch_threads
from .config import SynthConfig, config_of_card

#: the standard reference set (``pocoloco data histories``' defaults): 24 poses x 8 histories
STANDARD_POSES = 24
STANDARD_HISTORIES = 8
STANDARD_SHARED_SECONDS = (0.0, 2.0)
#: how long each history's own motion lasts before it blends into the frame's (seconds)
PREFIX_SECONDS = 1.6


@dataclass(frozen=True)
class HistoriesSpec:
    """What to draw: ``poses`` frames of ``split``, ``histories`` states each, for every window of
    ``shared_seconds``; ``seed`` fixes the frames, the prefix motions and the capture noise;
    ``subjects`` limits the frames to those subjects (empty: every subject)."""

    split: str = "test"
    poses: int = STANDARD_POSES
    histories: int = STANDARD_HISTORIES
    shared_seconds: tuple[float, ...] = STANDARD_SHARED_SECONDS
    prefix_seconds: float = PREFIX_SECONDS
    seed: int = 0
    subjects: tuple[str, ...] = ()  # () = every subject of the dataset

    def check(self) -> None:
        if self.split not in ("test", "heldout", "train"):
            raise ValueError(f"--split must be test, heldout or train, got {self.split!r}")
        if self.poses < 1:
            raise ValueError(f"--poses must be >= 1, got {self.poses}")
        if self.histories < 2:
            raise ValueError(f"--histories must be >= 2, got {self.histories}")
        if not self.shared_seconds or any(not (0.0 <= s <= 10.0) for s in self.shared_seconds):
            raise ValueError(f"--shared-seconds must be in [0, 10], got {list(self.shared_seconds)}")
        if len(set(self.shared_seconds)) != len(self.shared_seconds):
            raise ValueError(f"--shared-seconds has repeats: {list(self.shared_seconds)}")
        if not (0.4 <= self.prefix_seconds <= 20.0):
            raise ValueError(f"prefix_seconds must be in [0.4, 20], got {self.prefix_seconds}")
        if self.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {self.seed}")


@dataclass(frozen=True)
class RefPose:
    """One frame of the source dataset: ``subject/split/sequence`` frame ``frame`` (stored index)."""

    subject: str
    sequence: str
    frame: int


def window_name(pose: RefPose, shared: float) -> str:
    """The reference set's sequence name of (pose, window): ``<sequence>_f<frame>_s<shared>``."""
    return f"{pose.sequence}_f{pose.frame:04d}_s{shared:g}".replace(".", "p")


def synth_source(source: str | os.PathLike) -> tuple[dict, SynthConfig]:
    """(card, generation config) of a dataset made by ``pocoloco data synth`` (not a reference set);
    a one-line error for anything else (imported data has no motions to redraw)."""
    card = read_card(source)
    if not card.get("generation_config"):
        raise ValueError(f"{source}: not generated by `pocoloco data synth` (imported data has no motions to redraw)")
    if "histories" in card:
        raise ValueError(f"{source}: is itself a reference set; give the dataset it was drawn from")
    return card, config_of_card(card["generation_config"])


def _lead_frames(config: SynthConfig) -> int:
    """Simulated frames before a sequence's first stored frame (blend from rest + warm-up)."""
    return config.blend_frames + config.warmup_frames


def select_poses(source: str | os.PathLike, spec: HistoriesSpec) -> list[RefPose]:
    """``spec.poses`` stored frames of ``spec.split``, spread over every subject in turn (subjects
    in a seeded order, each frame drawn at random without repeats), each with enough of its own
    motion before it for the longest window (``max(shared_seconds)`` seconds)."""
    spec.check()
    card, config = synth_source(source)
    layout = DatasetLayout(source)
    need = int(round(max(spec.shared_seconds) * config.fps))
    first = max(0, need + 1 - _lead_frames(config))  # first stored frame with `need` frames before it
    rng = np.random.default_rng([spec.seed, 7])
    candidates: dict[str, list[RefPose]] = {}
    unknown = sorted(set(spec.subjects) - set(card["subjects"]))
    if unknown:
        raise ValueError(f"{source}: no subject {', '.join(unknown)} (it has {', '.join(card['subjects'])})")
    for subject in spec.subjects or card["subjects"]:
        pool = [RefPose(subject, seq, i) for seq in layout.sequences(subject, spec.split)
                for i in layout.frame_indices(subject, spec.split, seq) if i >= first]  # fmt: skip
        if pool:
            candidates[subject] = [pool[j] for j in rng.permutation(len(pool))]
    if not candidates:
        raise ValueError(f"{source}: no {spec.split} frame has {max(spec.shared_seconds):g} s of its own motion "
                         f"before it (stored frames from index {first} on)")  # fmt: skip
    order = [list(candidates)[j] for j in rng.permutation(len(candidates))]
    chosen: list[RefPose] = []
    while len(chosen) < spec.poses and any(candidates.values()):
        for subject in order:
            if candidates[subject] and len(chosen) < spec.poses:
                chosen.append(candidates[subject].pop())
    return chosen


def own_motion(config: SynthConfig, body, split: str, record: dict, stored: StoredMotion | None = None):
    """The full simulated motion of a stored sequence (rest blend + warm-up + stored frames), redrawn
    from its seed as ``synth.pipeline`` drew it; checked against the stored ``motion.npz`` rows."""
    from .motion import generate_motion, rest_to_motion
    from .pipeline import motion_split

    motion = generate_motion(record["seed"], config.frames_per_sequence + config.warmup_frames,
                             split=motion_split(split), fps=config.fps, kinds=config.motion_kinds, body=body)  # fmt: skip
    full = rest_to_motion(motion, config.blend_frames, body=body)
    if stored is not None:
        start = full.num_frames - config.frames_per_sequence
        same = np.allclose(full.joint_rotvecs[start:], stored.joint_rotvecs, atol=1e-5) and np.allclose(
            full.root_translation[start:], stored.root_translation, atol=1e-5)  # fmt: skip
        if not same:
            raise ValueError(f"sequence {record.get('name')}: its motion cannot be redrawn from seed {record['seed']} "
                             f"(generated by another pocoloco version?)")  # fmt: skip
    return full


def _yaw(rotvec: np.ndarray) -> float:
    from scipy.spatial.transform import Rotation

    fwd = Rotation.from_rotvec(rotvec).apply([0.0, -1.0, 0.0])  # the body faces -y at rest
    return math.atan2(fwd[1], fwd[0])


def join_motions(prefix_rot: np.ndarray, prefix_trans: np.ndarray, own_rot: np.ndarray, own_trans: np.ndarray,
                 join: int, end: int, blend: int) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """A history: ``prefix`` (T_p frames from the rest pose) turned about the vertical and moved so
    it arrives where the own motion is at frame ``join``, ``blend`` frames that carry it into that
    frame (cubic Hermite per joint rotation and per translation, matching both ends' velocities; the
    root's orientation by slerp), then the own motion's frames ``join .. end`` unchanged (the last
    frame is exactly the own motion's frame ``end``). Arrays: rotations (T, 24, 3), translations
    (T, 3); returns (T_p + blend + end - join + 1) frames."""
    from scipy.spatial.transform import Rotation, Slerp

    from .motion import clamp_to_limits

    if not (0 <= join <= end < len(own_rot)):
        raise ValueError(f"need 0 <= join <= end < {len(own_rot)}, got join {join}, end {end}")
    p_rot, p_trans = prefix_rot.astype(np.float64).copy(), prefix_trans.astype(np.float64).copy()
    o_rot, o_trans = own_rot.astype(np.float64), own_trans.astype(np.float64)
    turn = join_turn(p_rot, o_rot, join)
    p_rot[:, 0] = (turn * Rotation.from_rotvec(p_rot[:, 0])).as_rotvec()
    p_trans = turn.apply(p_trans)
    v_a = p_trans[-1] - p_trans[-2] if len(p_trans) > 1 else np.zeros(3)
    v_b = o_trans[min(join + 1, len(o_trans) - 1)] - o_trans[join] if join + 1 < len(o_trans) else np.zeros(3)
    gap = blend + 1
    shift = o_trans[join] - 0.5 * (v_a + v_b) * gap - p_trans[-1]  # arrive with the mean speed of both ends
    shift[2] = 0.0  # both are grounded: heights are blended, not shifted
    p_trans += shift
    u = (np.arange(1, gap) / gap)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    vr_a = p_rot[-1] - p_rot[-2] if len(p_rot) > 1 else np.zeros_like(p_rot[-1])
    vr_b = o_rot[join + 1] - o_rot[join] if join + 1 < len(o_rot) else np.zeros_like(o_rot[join])
    b_rot = (h00[:, :, None] * p_rot[-1] + h10[:, :, None] * gap * vr_a + h01[:, :, None] * o_rot[join]
             + h11[:, :, None] * gap * vr_b)  # fmt: skip
    slerp = Slerp([0.0, 1.0], Rotation.from_rotvec(np.stack([p_rot[-1, 0], o_rot[join, 0]])))
    b_rot[:, 0] = slerp(u[:, 0]).as_rotvec()
    b_rot[:, 1:] = clamp_to_limits(b_rot)[:, 1:]
    b_trans = h00 * p_trans[-1] + h10 * gap * v_a + h01 * o_trans[join] + h11 * gap * v_b
    rot = np.concatenate([p_rot, b_rot, o_rot[join : end + 1]]).astype(np.float32)
    trans = np.concatenate([p_trans, b_trans, o_trans[join : end + 1]]).astype(np.float32)
    return rot, trans


def join_turn(prefix_rot: np.ndarray, own_rot: np.ndarray, join: int):
    """The turn about the vertical (a scipy ``Rotation``) that :func:`join_motions` gives the prefix so
    its last frame faces where the own motion's frame ``join`` faces."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("z", _yaw(np.asarray(own_rot, np.float64)[join, 0])
                               - _yaw(np.asarray(prefix_rot, np.float64)[-1, 0]))  # fmt: skip


def _reference_seed(spec: HistoriesSpec, pose_index: int, k: int, attempt: int = 0) -> int:
    return int(np.random.SeedSequence([spec.seed, pose_index, k, attempt]).generate_state(1)[0] & 0x7FFFFFFF)


def _prefix(config: SynthConfig, body, spec: HistoriesSpec, pose_index: int, k: int, attempt: int):
    """(kind, seed, Motion) of history k of a pose: a ``prefix_seconds`` motion of a kind drawn from
    the dataset's kinds, from the rest pose."""
    from .motion import generate_motion, rest_to_motion

    seed = _reference_seed(spec, pose_index, k, attempt)
    kinds = config.motion_kinds
    kind = kinds[(seed >> 8) % len(kinds)]
    frames = max(2, int(round(spec.prefix_seconds * config.fps)))
    motion = generate_motion(seed, frames, split="train", fps=config.fps, kinds=(kind,), body=body)
    return kind, seed, rest_to_motion(motion, config.blend_frames, body=body)


@dataclass(frozen=True)
class _Job:
    """History ``k`` of the ``pose_index``-th pose, for every window of the spec."""

    pose_index: int
    pose: RefPose
    k: int


@dataclass(frozen=True)
class _Simulated:
    """One window's reference before its capture: the prefix motion drawn (kind, seed, redraws), the
    frames of the whole history and of its prefix, the posed body from the prefix's last frame on,
    the cloth at the frame ((Vg, 3), None for a tight body) with its stats, the simulation seconds."""

    kind: str
    seed: int
    redraws: int
    frames: int
    prefix_frames: int
    posed: object
    cloth: np.ndarray | None = None
    stats: dict | None = None
    seconds: float = 0.0


def _run_history(source: str, out: str, spec_dict: dict, job_dict: dict) -> list[dict]:
    """Simulate and capture history k of one pose for every window (one frame file per window,
    written atomically). Returns their records (kept by the caller for ``sequence.json``)."""
    with torch_threads(1):
        return _run_history_inner(Path(source), Path(out), HistoriesSpec(**spec_dict), _Job(
            job_dict["pose_index"], RefPose(**job_dict["pose"]), job_dict["k"]))  # fmt: skip


def _read_record(path: Path) -> dict | None:
    """A reference already made (its frame readable and its record written), or None."""
    record_path = path.with_suffix(".json")
    if path.exists() and record_path.exists():
        try:
            read_frame(path, keys=["labels"])
            return json.loads(record_path.read_text())
        except (ValueError, OSError, json.JSONDecodeError):
            pass  # damaged: made again
    return None


def _made_record(layout: DatasetLayout, spec: HistoriesSpec, job: _Job, shared: float) -> dict | None:
    """History ``job``'s reference for the window of ``shared`` seconds, if made before: its record,
    or ``{"k": k}`` where the window's sequence is finished (the records moved into sequence.json;
    whoever needs them reads them from there); None: still to make."""
    name = window_name(job.pose, shared)
    if layout.sequence_meta_path(job.pose.subject, spec.split, name).exists():
        return {"k": job.k}
    return _read_record(layout.frame_path(job.pose.subject, spec.split, name, job.k))


def _run_history_inner(source: Path, out: Path, spec: HistoriesSpec, job: _Job) -> list[dict]:
    """History k's prefix motion is simulated once, from the subject's cloth settled at rest, in the
    orientation it was drawn in; each window then continues that cloth state, turned about the
    vertical to where the window's join faces (``SettledCloth.turned``: the physics has no preferred
    heading), through the blend and the frame's own motion. A window whose cloth fails (explodes,
    ends in the body) draws another prefix motion, up to three."""
    from .cloth_sim import simulate_garment
    from .pipeline import cloth_settings, simulate_settling_once, subject_assets, subject_key

    _, config = synth_source(source)
    subject = next(s for s in config.subjects if s.name == job.pose.subject)
    src, layout = DatasetLayout(source), DatasetLayout(out)
    paths = {w: layout.frame_path(subject.name, spec.split, window_name(job.pose, w), job.k)
             for w in spec.shared_seconds}  # fmt: skip
    records = {w: _made_record(layout, spec, job, w) for w in spec.shared_seconds}
    pending = [w for w in spec.shared_seconds if records[w] is None]
    if not pending:
        return [records[w] for w in spec.shared_seconds]
    record = read_sequence_meta(src.sequence_meta_path(subject.name, spec.split, job.pose.sequence))
    stored = read_motion(src.motion_path(subject.name, spec.split, job.pose.sequence))
    body, garment = subject_assets(subject, config)
    settings = cloth_settings(config, subject.garment) if garment is not None else None
    own = own_motion(config, body, spec.split, {**record, "name": job.pose.sequence}, stored)
    t = own.num_frames - config.frames_per_sequence + job.pose.frame
    joins = {}
    for w in pending:
        joins[w] = t - int(round(w * config.fps))
        if joins[w] < 1:
            raise ValueError(f"{window_name(job.pose, w)}: the frame has only {t} frames of its own motion, "
                             f"{t - joins[w]} needed")  # fmt: skip
    results: dict[float, _Simulated] = {}
    for attempt in range(3):  # a history whose cloth fails (explodes, enters the body) is drawn again
        t0 = time.perf_counter()
        kind, seed, prefix = _prefix(config, body, spec, job.pose_index, job.k, attempt)
        n_prefix = len(prefix.joint_rotvecs)
        head = None
        if garment is not None:
            # every prefix starts at rest at the origin (``rest_to_motion``): its settle is reused;
            # hard failures only here, the windows are judged
            head = simulate_settling_once(body, garment, body.pose(prefix.joint_rotvecs, prefix.root_translation),
                                          settings, subject_key(subject, config), judge_from=n_prefix)  # fmt: skip
        prefix_time = (time.perf_counter() - t0) / len(pending)
        for w in pending:
            t1 = time.perf_counter()
            rot, trans = join_motions(prefix.joint_rotvecs, prefix.root_translation, own.joint_rotvecs,
                                      own.root_translation, joins[w], t, config.blend_frames)  # fmt: skip
            posed = body.pose(rot[n_prefix - 1 :], trans[n_prefix - 1 :])  # from the prefix's last frame on
            if head is None:
                results[w] = _Simulated(kind, seed, attempt, len(rot), n_prefix, posed)
                continue
            turn = join_turn(prefix.joint_rotvecs, own.joint_rotvecs, joins[w]).as_matrix()
            state = head.final.turned(turn, posed.vertices[0])
            seq = simulate_garment(body, garment, posed, settings, settled=state,
                                   judge_from=posed.vertices.shape[0] - 1)  # fmt: skip
            stats = dataclasses.asdict(seq.stats[-1])
            if stats["valid"]:
                results[w] = _Simulated(kind, seed, attempt, len(rot), n_prefix, posed,
                                        seq.vertices[-1].astype(np.float32), stats,
                                        prefix_time + time.perf_counter() - t1)  # fmt: skip
        pending = [w for w in pending if w not in results]
        if not pending:
            break
    if pending:
        raise RuntimeError(f"{window_name(job.pose, pending[0])}: history {job.k}: the cloth failed in 3 prefix "
                           "motions")  # fmt: skip
    for w, result in results.items():
        records[w] = _capture_reference(src, paths[w], config, spec, job, subject, body, garment, w, result)
    return [records[w] for w in spec.shared_seconds]


def _capture_reference(src: DatasetLayout, path: Path, config: SynthConfig, spec: HistoriesSpec, job: _Job,
                       subject, body, garment, shared: float, result: _Simulated) -> dict:  # fmt: skip
    """Capture one simulated reference as the dataset's frames are captured; write its frame file and
    record (atomically)."""
    from .capture import LABEL_BODY, LABEL_GARMENT, CaptureMesh, CaptureSettings, capture_frame

    posed, cloth, stats = result.posed, result.cloth, result.stats
    name = window_name(job.pose, shared)
    own_frame = read_frame(src.frame_path(subject.name, spec.split, job.pose.sequence, job.pose.frame))
    body_diff = float(np.abs(posed.vertices[-1] - own_frame.body_vertices).max())
    if body_diff > 1e-4:
        raise RuntimeError(f"{name}: history {job.k} ends {body_diff * 100:.3f} cm off the frame's body")
    settings = CaptureSettings(num_points=config.num_points, num_cameras=config.capture_cameras,
                               noise_std=config.scanner_noise, cull_hidden_faces=config.capture_cull_hidden_faces,
                               seed=_reference_seed(spec, job.pose_index, 1000 + job.k))  # fmt: skip
    meshes = [CaptureMesh(posed.vertices[-1], body.faces, label=LABEL_BODY,
                          face_part=body.vertex_joint[body.faces[:, 0]])]  # fmt: skip
    if cloth is not None:
        meshes.append(CaptureMesh(cloth, garment.faces, label=LABEL_GARMENT, face_part=np.full(len(garment.faces), -1)))
    scan = capture_frame(meshes, settings)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_frame(path, Frame(points=scan.points, normals=scan.normals, labels=scan.labels, parts=scan.parts,
                            joints=posed.joints[-1], body_vertices=posed.vertices[-1], vtransf=posed.vtransf[-1],
                            garment_vertices=cloth, frame_index=job.k), storage=config.frame_storage)  # fmt: skip
    out_record = {"k": job.k, "prefix_kind": result.kind, "prefix_seed": result.seed,
                  "prefix_frames": int(result.prefix_frames), "blend_frames": config.blend_frames,
                  "shared_frames": int(round(shared * config.fps)), "redraws": result.redraws,
                  "simulated_frames": int(result.frames), "simulation_seconds": result.seconds,
                  "penetration_max_mm": None if stats is None else 1000.0 * float(stats["penetration_max"])}  # fmt: skip
    with atomic_open(path.with_suffix(".json"), "w") as fh:
        json.dump(out_record, fh)
    return out_record


def _finish_sequence(source: Path, out: Path, spec: HistoriesSpec, pose: RefPose, shared: float,
                     records: list[dict]) -> None:  # fmt: skip
    """Frame K (the frame's own scan, renumbered K), motion.npz (the frame's body K + 1 times) and, last,
    sequence.json listing every reference's prefix motion; the per-reference records removed."""
    src, layout = DatasetLayout(source), DatasetLayout(out)
    name = window_name(pose, shared)
    k_own = spec.histories
    _, config = synth_source(source)
    own = read_frame(src.frame_path(pose.subject, spec.split, pose.sequence, pose.frame))
    write_frame(layout.frame_path(pose.subject, spec.split, name, k_own), dataclasses.replace(own, frame_index=k_own),
                storage=config.frame_storage)  # fmt: skip
    stored = read_motion(src.motion_path(pose.subject, spec.split, pose.sequence))
    n = spec.histories + 1
    write_motion(layout.motion_path(pose.subject, spec.split, name),
                 StoredMotion(np.repeat(stored.joint_rotvecs[pose.frame][None], n, 0),
                              np.repeat(stored.root_translation[pose.frame][None], n, 0)))  # fmt: skip
    write_sequence_meta(layout.sequence_meta_path(pose.subject, spec.split, name), {
        "subject": pose.subject, "split": spec.split, "name": name, "fps": config.fps, "num_frames": n,
        "num_stored": n, "rejected_frames": [], "segments": [["histories", 0, n]],
        "source": {"sequence": pose.sequence, "frame": pose.frame}, "shared_seconds": shared,
        "references": sorted(records, key=lambda r: r["k"]) + [{"k": k_own, "own_scan": True}],
    })  # fmt: skip
    for k in range(spec.histories):
        layout.frame_path(pose.subject, spec.split, name, k).with_suffix(".json").unlink(missing_ok=True)


def make_histories(source: str | os.PathLike, out: str | os.PathLike, spec: HistoriesSpec, workers: int = 1,
                   shard: tuple[int, int] = (1, 1),
                   progress: Callable[[int, int], None] | None = None) -> dict:  # fmt: skip
    """Draw (or resume) the reference set of ``spec`` from the synthetic dataset ``source`` into
    ``out`` (shard ``k`` of ``n``: every n-th history from the k-th, each for every window; the card
    is written by the run that finds every reference done). Returns the card (``status`` "incomplete" until then)."""
    spec.check()
    source, out = Path(source), output_folder(out)
    card, config = synth_source(source)
    poses = select_poses(source, spec)
    layout = DatasetLayout(out)
    header = {"source": os.fspath(source.resolve()), "split": spec.split, "poses": [dataclasses.asdict(p) for p in poses],
              "histories": spec.histories, "shared_seconds": list(spec.shared_seconds),
              "prefix_seconds": spec.prefix_seconds, "seed": spec.seed, "subjects": list(spec.subjects),
              "prefix_shared_by_windows": True}  # fmt: skip
    if layout.card_path.exists():
        have = read_card(out).get("histories")
        if not isinstance(have, dict) or {k: v for k, v in have.items() if k != "source"} != {
                k: v for k, v in header.items() if k != "source"}:  # fmt: skip
            raise ValueError(f"{out}: holds another reference set (or not one); choose another --out")
    elif out.exists() and any(out.iterdir()):
        raise ValueError(f"{out}: folder exists, is not empty and is not a reference set")
    else:
        out.mkdir(parents=True, exist_ok=True)
        base = {k: v for k, v in card.items() if k not in ("counts", "frame_files", "pose_coverage",
                                                            "pose_coverage_heldout", "generation", "status")}  # fmt: skip
        base["subjects"] = {s: card["subjects"][s] for s in sorted({p.subject for p in poses})}
        write_card(out, {**base, "status": "incomplete", "histories": header})
    for subject in {p.subject for p in poses}:
        target = layout.subject_path(subject)
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(DatasetLayout(source).subject_path(subject), target)
    jobs = [_Job(i, p, k) for i, p in enumerate(poses) for k in range(spec.histories)]
    windows = len(spec.shared_seconds)

    def made(job: _Job) -> bool:  # every window of this history made before (a finished pose's included)
        return all(_made_record(layout, spec, job, w) is not None for w in spec.shared_seconds)

    k_shard, n_shard = shard
    # what was made before counts as done at once, so the time left is estimated from this run's work
    mine = [j for n, j in enumerate(jobs) if n % n_shard == k_shard - 1 and not made(j)]
    total, done = len(jobs) * windows, (len(jobs) - len(mine)) * windows
    if progress:
        progress(done, total)
    spec_dict = dataclasses.asdict(spec)

    def collect(recs: list[dict]) -> None:
        nonlocal done
        done += len(recs)
        if progress:
            progress(done, total)

    job_args = [(os.fspath(source), os.fspath(out), spec_dict,
                 {"pose_index": j.pose_index, "pose": dataclasses.asdict(j.pose), "k": j.k}) for j in mine]  # fmt: skip
    if workers <= 1:
        for a in job_args:
            collect(_run_history(*a))
    else:
        from .pipeline import init_worker

        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=init_worker,
                                 initargs=(os.getpid(), None)) as pool:  # fmt: skip
            futures = [pool.submit(_run_history, *a) for a in job_args]
            for f in as_completed(futures):
                collect(f.result())
    # a (pose, window) whose K references all exist is finished (whichever shard made them)
    for pose in poses:
        for shared in spec.shared_seconds:
            name = window_name(pose, shared)
            if layout.sequence_meta_path(pose.subject, spec.split, name).exists():
                continue
            recs = []
            for k in range(spec.histories):
                rec_path = layout.frame_path(pose.subject, spec.split, name, k).with_suffix(".json")
                if not rec_path.exists():
                    break
                recs.append(json.loads(rec_path.read_text()))
            if len(recs) == spec.histories:
                _finish_sequence(source, out, spec, pose, shared, recs)
    finished = all(layout.sequence_meta_path(p.subject, spec.split, window_name(p, s)).exists()
                   for p in poses for s in spec.shared_seconds)  # fmt: skip
    card_now = read_card(out)
    if finished and card_now.get("status") != "complete":
        card_now = card_from_disk(out, {**card_now, "status": "complete"})
        write_card(out, card_now)
    return card_now


def reference_sets(root: str | os.PathLike) -> list[dict]:
    """Every (pose, window) of a reference set: ``{"subject", "split", "sequence", "shared_seconds",
    "source", "refs": [frame paths of the K histories], "own": the frame's own scan}``."""
    card = read_card(root)
    hist = card.get("histories")
    if not isinstance(hist, dict):
        raise ValueError(f"{root}: not a reference set (its card has no 'histories'; `pocoloco data histories` makes one)")
    layout = DatasetLayout(root)
    out = []
    for p in hist["poses"]:
        pose = RefPose(**p)
        for shared in hist["shared_seconds"]:
            name = window_name(pose, shared)
            meta = layout.sequence_meta_path(pose.subject, hist["split"], name)
            if not meta.exists():
                raise ValueError(f"{root}: {pose.subject}/{hist['split']}/{name} is not finished (rerun `pocoloco data "
                                 f"histories` to resume)")  # fmt: skip
            k = hist["histories"]
            out.append({"subject": pose.subject, "split": hist["split"], "sequence": name, "shared_seconds": shared,
                        "source": dataclasses.asdict(pose),
                        "refs": [layout.frame_path(pose.subject, hist["split"], name, i) for i in range(k)],
                        "own": layout.frame_path(pose.subject, hist["split"], name, k)})  # fmt: skip
    return out


def windows_of(pairs: Sequence[dict]) -> list[float]:
    """The distinct windows (shared seconds) of :func:`reference_sets`' entries, in order."""
    return sorted({p["shared_seconds"] for p in pairs})
