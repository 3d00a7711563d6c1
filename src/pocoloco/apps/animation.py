"""Animation: a sequence of clouds for a motion (T poses), and a flicker metric.

Methods (frame k has pose joints[k]; ``seed`` the base seed):

* ``independent``: frame k is sampled from scratch with seed ``seed + k`` (no coherence);
* ``shared-noise``: every frame is sampled from the same initial noise (seed ``seed``), so the
  deterministic sampler maps nearby poses to nearby clouds;
* ``chain``: frame 0 is sampled from scratch; frame k starts from frame k-1's result, renoised
  to step ``t`` (SDEdit, Meng et al. 2022; default t = 200 of 1000) and denoised under pose k
  (seed ``seed + k``). Point i of frame k descends from point i of frame k-1, so the sequence
  is coherent. ``anchor="root"`` (default) carries frame k-1 root-relative (it moves with the
  root: normalised with frame k-1's root, denormalised with frame k's); ``anchor="world"``
  keeps its world position (normalised with frame k's root) and lets the denoiser follow.

Flicker metric (:func:`flicker_cm`): for consecutive frames, frame k's points are moved by the
body motion, each with the displacement of its nearest posed-body vertex from frame k to k+1
(:func:`warp_by_body`), and compared with frame k+1 (PocoLoco Chamfer, cm). 0 for a cloud that
moves exactly like the body; the ground truth's own value (different scan subsets per frame) is
the floor to compare with.

Public API: :func:`load_motion`, :func:`animate`, :func:`warp_by_body`, :func:`flicker_cm`,
:func:`render_gif`, :func:`evaluate_animation`; CLI pieces :func:`add_animate_arguments` /
:func:`cmd_animate` (``pocoloco animate``).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pocoloco.apps.common import denoise_from, subset, to_metres, to_normalised
from pocoloco.data import format as fmt
from pocoloco.data.format import read_frame
from pocoloco.data.motion_window import MotionWindow
from pocoloco.data.poses import check_joints, check_skeleton
from pocoloco.diffusion.samplers import check_sampler
from pocoloco.evaluation.metrics import chamfer_cm, nearest
from pocoloco.methods.base import PointPrior
from pocoloco.utils.npfile import numpy_file_kind, numpy_file_problem

__all__ = ["METHODS", "Animation", "MotionInput", "animate",
           "evaluate_animation", "flicker_cm", "load_motion", "warp_by_body"]  # fmt: skip

METHODS = ("independent", "shared-noise", "chain")
ANCHORS = ("root", "world")


@dataclass
class MotionInput:
    """joints: (T, J, 3) float32 metres. frames: the dataset frame file of each pose, or None
    (a joints array was given). name: the spec it was read from."""

    joints: np.ndarray
    frames: list[Path] | None
    name: str


@dataclass
class Animation:
    """points: (T, N, 3) float32 metres. normals: (T, N, 3) or None. seeds: (T,) seed of each frame."""

    points: np.ndarray
    normals: np.ndarray | None
    seeds: list[int]


# --------------------------------------------------------------------------------------- motion
def load_motion(spec: str | os.PathLike, num_joints: int = 24, any_pose: bool = False) -> MotionInput:
    """Read a motion: a (T, J, 3) joints ``.npy`` (or ``.npz`` with a ``joints`` array), or a
    dataset sequence ``DATASET:subject/split/sequence`` (the joints of every stored frame).

    Raises one-line ValueErrors: no such file / sequence, wrong shape, a skeleton with another
    joint count than the model's, NaN / inf, and (unless ``any_pose``) a frame whose skeleton is
    not a human body in metres (:func:`~pocoloco.data.poses.check_skeleton`).
    """

    spec = os.fspath(spec)
    path = Path(spec)
    if path.is_file():
        if numpy_file_kind(path) is None:
            raise ValueError(f"{spec}: {numpy_file_problem(path)}; a motion is a (T, J, 3) joints .npy, an .npz "
                             "with 'joints', or DATASET:subject/split/sequence")  # fmt: skip
        try:
            loaded = np.load(path, allow_pickle=False)
            if hasattr(loaded, "files"):
                with loaded as z:
                    if "joints" not in z.files:
                        raise ValueError(f"{spec}: npz has no 'joints' array")
                    arr = z["joints"]
            else:
                arr = np.asarray(loaded)
        except ValueError as e:
            if str(e).startswith(spec):
                raise
            raise ValueError(f"{spec}: not a (T, J, 3) joints .npy or an .npz with 'joints' "
                             f"({' '.join(str(e).split())[:120]})") from None  # fmt: skip
        except Exception as e:
            raise ValueError(f"{spec}: not a (T, J, 3) joints .npy or an .npz with 'joints' "
                             f"({type(e).__name__}{': ' if str(e) else ''}{' '.join(str(e).split())[:120]})") from None  # fmt: skip
        frames = None
    elif ":" in spec:
        root, _, key = spec.rpartition(":")
        parts = key.strip("/").split("/")
        if len(parts) != 3:
            raise ValueError(f"{spec}: expected DATASET:subject/split/sequence, got {key!r}")
        subject, split, sequence = parts
        fmt.read_card(root)
        if split not in fmt.SPLITS:
            raise ValueError(f"{spec}: unknown split {split!r}; expected one of {fmt.SPLITS}")
        layout = fmt.DatasetLayout(root)
        idx = layout.frame_indices(subject, split, sequence)
        if not idx:
            raise ValueError(f"{spec}: no such sequence (or it has no frames)")
        frames = [layout.frame_path(subject, split, sequence, i) for i in idx]
        arr = np.stack([fmt.read_frame(p, ["joints"]).joints for p in frames])
    else:
        raise ValueError(f"{spec}: no such motion file (or DATASET:subject/split/sequence)")
    if arr.dtype.kind not in "fiu" or arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1:
        raise ValueError(f"{spec}: expected joints of shape (T, {num_joints}, 3), got {arr.shape}")
    if arr.shape[1] != num_joints:
        raise ValueError(f"{spec}: the skeleton has {arr.shape[1]} joints, the model expects {num_joints}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{spec}: joints contain NaN or inf")
    if not any_pose:
        for k, joints in enumerate(arr):
            check_skeleton(f"{spec} frame {k}", joints)
    return MotionInput(arr.astype(np.float32), frames, spec)


# -------------------------------------------------------------------------------------- animate
def animate(
    prior: PointPrior,
    joints: np.ndarray,
    num_points: int,
    *,
    method: str = "chain",
    t: int = 200,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seed: int = 0,
    seeds: Sequence[int] | None = None,
    anchor: str = "root",
    finish: Callable[[int, np.ndarray, int], np.ndarray] | None = None,
    progress: Callable[[int, int], None] | None = None,
    windows: Sequence[MotionWindow | None] | None = None,
    polish: bool = True,
) -> Animation:
    """Clouds (T, N, 3) for the poses ``joints`` (T, J, 3) (module docstring for the methods).

    seeds: per-frame seeds overriding the method's (``seed + k``, or ``seed`` for every frame
    with shared-noise). t: chain's renoising step in [1, T_train] (steps: that chain's steps,
    at most t; from-scratch frames use the sampler's default or ``steps``). finish: ``(k,
    points (num_points, 3) metres, seed) -> (N, 3)``, frame k's cloud made from the prior's (the
    chain still carries the prior's clouds; :class:`~pocoloco.methods.base.AnimationPrior`); the
    frames then have no normals. windows: each frame's motion window (issue 41), given to a prior
    whose denoiser takes one (``prior.denoiser.motion``, a motion-aware model): the hems lag and
    swing with the motion before each frame; None: every frame at rest. polish: a distilled
    student with a finishing teacher (``prior.polish``) ends every frame with the teacher's call
    (two calls per chained frame); False: the student's one call alone.
    """

    if method not in METHODS:
        raise ValueError(f"unknown animation method {method!r}; choose one of: {', '.join(METHODS)}")
    if anchor not in ANCHORS:
        raise ValueError(f"unknown anchor {anchor!r}; choose one of: {', '.join(ANCHORS)}")
    C, J, T = prior.point_channels, prior.num_joints, prior.schedule.num_timesteps
    normalisation = prior.normalisation
    joints = np.asarray(joints)
    if joints.ndim != 3 or joints.shape[0] < 1:
        raise ValueError(f"joints must have shape (T, {J}, 3), got {joints.shape}")
    joints = np.stack([check_joints(f"joints[{k}]", j, J) for k, j in enumerate(joints)])
    check_sampler(sampler, steps, T)
    if not 1 <= t <= T:
        raise ValueError(f"t must be in [1, {T}] (the model's training timesteps), got {t}")
    if num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {num_points}")
    F = len(joints)
    if seeds is None:
        seeds = [seed] * F if method == "shared-noise" else [seed + k for k in range(F)]
    seeds = [int(s) for s in seeds]
    if len(seeds) != F:
        raise ValueError(f"seeds must have one entry per frame ({F}), got {len(seeds)}")
    points = np.empty((F, num_points, 3), np.float32)
    normals = np.empty((F, num_points, 3), np.float32) if C == 6 else None
    finished: list[np.ndarray] = []
    if windows is not None and len(windows) != F:
        raise ValueError(f"windows must have one entry per frame ({F}), got {len(windows)}")
    takes_motion = hasattr(prior.denoiser, "motion") and getattr(prior.denoiser.config, "motion_window", 0)
    for k in range(F):
        if takes_motion:
            window = None if windows is None else windows[k]
            prior.denoiser.motion = None if window is None else torch.from_numpy(normalisation.normalise_motion(window, joints[k]))
        if method != "chain" or k == 0:
            x = denoise_from(prior, joints[k], None, T, sampler, steps, [seeds[k]],
                             num_points=num_points, polish=polish)  # fmt: skip
        else:
            ref = joints[k - 1] if anchor == "root" else joints[k]
            prev_n = None if normals is None else normals[k - 1]
            x0 = to_normalised(normalisation, points[k - 1], prev_n, ref, C)[None]  # (1, N, C)
            x = denoise_from(prior, joints[k], x0, t, sampler,
                             None if steps is None else min(steps, t), [seeds[k]], polish=polish)  # fmt: skip
        p, n = to_metres(normalisation, x, joints[k])
        points[k] = p[0]
        if normals is not None:
            normals[k] = n[0]
        if finish is not None:
            finished.append(np.asarray(finish(k, points[k], seeds[k]), np.float32))
        if progress is not None:
            progress(k + 1, F)
    if takes_motion:
        prior.denoiser.motion = None
    if finish is not None:
        return Animation(np.stack(finished), None, seeds)
    return Animation(points, normals, seeds)


# -------------------------------------------------------------------------------------- flicker
def warp_by_body(points: np.ndarray, body_from: np.ndarray, body_to: np.ndarray) -> np.ndarray:
    """Move each point (N, 3) by the displacement of its nearest vertex of ``body_from`` (V, 3)
    to the same vertex of ``body_to`` (V, 3): ``p + body_to[i] - body_from[i]``, i = nearest."""

    body_from, body_to = np.asarray(body_from, np.float64), np.asarray(body_to, np.float64)
    if body_from.shape != body_to.shape:
        raise ValueError(f"body vertices must have the same shape, got {body_from.shape} and {body_to.shape}")
    _, idx = nearest(points, body_from)
    return np.asarray(points, np.float64) + (body_to - body_from)[idx]


def flicker_cm(clouds: Sequence[np.ndarray], bodies: Sequence[np.ndarray]) -> np.ndarray:
    """(T-1,) PocoLoco Chamfer (cm) between frame k warped by the body motion (:func:`warp_by_body`)
    and frame k+1, for T clouds (N_k, 3) and their posed bodies (V, 3)."""

    if len(clouds) != len(bodies):
        raise ValueError(f"{len(clouds)} clouds but {len(bodies)} bodies")
    return np.array([chamfer_cm(warp_by_body(clouds[k], bodies[k], bodies[k + 1]), clouds[k + 1])
                     for k in range(len(clouds) - 1)])  # fmt: skip


def evaluate_animation(anim_points: np.ndarray, frames: Sequence[os.PathLike], num_points: int,
                       seed: int = 0) -> dict[str, Any]:  # fmt: skip
    """Flicker and accuracy of generated clouds (T, N, 3) for a dataset sequence's frame files.

    Returns ``flicker_cm`` (T-1,) and its mean, ``gt_flicker_cm`` (the same on N-point subsets of
    the GT scans, the floor), ``chamfer_to_gt_cm`` (T,) (each frame vs. its GT subset) and mean.
    """

    gts, bodies = [], []
    for k, p in enumerate(frames):
        fr = read_frame(p, ["points", "body_vertices"], allow_missing=True)
        if fr.body_vertices is None:
            raise ValueError(f"{p}: no body_vertices (imported data?): the flicker metric needs the posed body")
        gts.append(fr.points[subset(fr.num_points, num_points, [seed, k])])
        bodies.append(fr.body_vertices)
    fl = flicker_cm(list(anim_points), bodies)
    gfl = flicker_cm(gts, bodies)
    acc = np.array([chamfer_cm(a, g) for a, g in zip(anim_points, gts, strict=True)])
    nan = float("nan")
    return {"flicker_cm": fl.tolist(), "flicker_mean_cm": float(fl.mean()) if len(fl) else nan,
            "gt_flicker_cm": gfl.tolist(), "gt_flicker_mean_cm": float(gfl.mean()) if len(gfl) else nan,
            "chamfer_to_gt_cm": acc.tolist(), "chamfer_to_gt_mean_cm": float(acc.mean())}  # fmt: skip
