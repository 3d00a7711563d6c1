"""Pose editing: move a clothed-body point cloud to a new pose with a PocoLoco model.

Two modes:

* ``renoise`` (SDEdit, Meng et al. 2022): the source cloud, normalised with the *source* pose's
  root (the target's if no source pose is given), is noised to step ``t`` with the forward
  process ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps`` (DDPM eq. 4) and denoised under the
  *target* pose over the timesteps below t; the result is denormalised with the target's root.
  Small t keeps the source's detail (and its pose), t = T (the model's training steps) forgets
  the source entirely and equals sampling from scratch. Default t = 100 of 1000.
* ``region`` (RePaint inpainting, Lugmayr et al. 2022, without resampling): needs the source pose.
  Joints whose root-relative position moved more than ``threshold`` between the two poses mark
  their bones (a bone = joint and parent, :data:`pocoloco.body.skeleton.JOINT_PARENTS`) as
  moving; source points whose nearest bone moves are regenerated, the other points are kept
  (moved with the root). By default the moving points start from pure noise (t = T); a smaller
  ``t`` starts them from the renoised source instead.

Point i of an edited cloud descends from point i of the (subsampled) source cloud.

Public API: :func:`edit` -> :class:`Edit`, :func:`moving_region`, :func:`nearest_bone`,
:func:`evaluate_edit` (the benchmark's metrics); the command is ``pocoloco edit`` (:mod:`pocoloco.cli.apps`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pocoloco.apps.common import (
    check_scan,
    denoise_from,
    sample_prior,
    subset,
    to_metres,
    to_normalised,
)
from pocoloco.body.skeleton import JOINT_PARENTS
from pocoloco.data.dataset import rotate_z
from pocoloco.data.poses import check_joints
from pocoloco.diffusion.samplers import check_sampler
from pocoloco.evaluation.metrics import chamfer_cm
from pocoloco.methods.base import PointPrior

__all__ = ["Edit", "MODES", "edit", "evaluate_edit", "moved_joints", "moving_region",
           "nearest_bone"]  # fmt: skip

MODES = ("renoise", "region")
DEFAULT_T = {"renoise": 100, "region": None}  # None: T (pure noise)
#: root-relative joint displacement (m) above which a joint counts as moved (region mode)
DEFAULT_THRESHOLD_M = 0.05


@dataclass
class Edit:
    """What :func:`edit` returns.

    points: (K, N, 3) float32 metres, in the target pose's frame. normals: (K, N, 3) or None.
    regenerated: (K, N) bool, True for points that were generated (region mode; all True for
    renoise, where every point is denoised). t: the start step used. moved_joints: (J,) bool
    (region mode) or None.
    """

    points: np.ndarray
    normals: np.ndarray | None
    regenerated: np.ndarray
    t: int
    moved_joints: np.ndarray | None


# ------------------------------------------------------------------------------------- regions
def _bones(num_joints: int) -> list[tuple[int, int]]:
    """(parent, child) joint pairs, one bone per non-root joint."""
    return [(JOINT_PARENTS[j], j) for j in range(num_joints) if JOINT_PARENTS[j] >= 0]


def nearest_bone(points: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(N,) index into the bone list (``(parent, child)`` per non-root joint, in joint order) of the
    bone segment nearest to each point (N, 3), joints (J, 3)."""
    p = np.asarray(points, np.float64)[:, None, :]  # (N, 1, 3)
    jt = np.asarray(joints, np.float64)
    bones = _bones(len(jt))
    a = jt[[b[0] for b in bones]][None]  # (1, B, 3)
    ab = jt[[b[1] for b in bones]][None] - a  # (1, B, 3)
    s = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)  # (N, B)
    d2 = ((p - (a + s[..., None] * ab)) ** 2).sum(-1)  # (N, B)
    return np.argmin(d2, axis=1)


def moved_joints(source_joints: np.ndarray, target_joints: np.ndarray, threshold: float = DEFAULT_THRESHOLD_M,
                 root_joint: int = 0) -> np.ndarray:  # fmt: skip
    """(J,) bool: joints whose root-relative position differs by more than ``threshold`` metres."""
    s = np.asarray(source_joints, np.float64)
    t = np.asarray(target_joints, np.float64)
    d = np.linalg.norm((t - t[root_joint]) - (s - s[root_joint]), axis=1)
    return d > threshold


def moving_region(points: np.ndarray, source_joints: np.ndarray, target_joints: np.ndarray,
                  threshold: float = DEFAULT_THRESHOLD_M,
                  root_joint: int = 0) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Which points (N, 3) of a cloud in the source pose move: ``(mask (N,) bool, moved (J,) bool)``.

    A bone moves if one of its two joints moved (:func:`moved_joints`); a point moves if its
    nearest bone in the source pose (:func:`nearest_bone`) moves.
    """
    moved = moved_joints(source_joints, target_joints, threshold, root_joint)
    bone_moves = np.array([moved[a] or moved[b] for a, b in _bones(len(moved))])
    return bone_moves[nearest_bone(points, source_joints)], moved


# ---------------------------------------------------------------------------------------- edit
def edit(
    prior: PointPrior,
    source: np.ndarray,
    target_joints: np.ndarray,
    *,
    source_joints: np.ndarray | None = None,
    source_normals: np.ndarray | None = None,
    mode: str = "renoise",
    t: int | None = None,
    num_points: int | None = None,
    num: int = 1,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seeds: Sequence[int] | None = None,
    threshold: float = DEFAULT_THRESHOLD_M,
    name: str = "source",
) -> Edit:
    """Move ``source`` (M, 3) metres to ``target_joints`` (J, 3) (module docstring for the modes).

    num_points: N (default min(M, 4096)); the source is subsampled to N points per output (from
    its seed), and must have at least N. t: start step in [1, T] (default: renoise 100, region T).
    Output k depends only on ``seeds[k]`` (default 0..K-1).
    """

    C, J, T = prior.point_channels, prior.num_joints, prior.schedule.num_timesteps
    normalisation = prior.normalisation
    if mode not in MODES:
        raise ValueError(f"unknown edit mode {mode!r}; choose one of: {', '.join(MODES)}")
    target_joints = check_joints("target joints", target_joints, J)
    if source_joints is not None:
        source_joints = check_joints("source joints", source_joints, J)
    elif mode == "region":
        raise ValueError("region mode needs the source pose (--source-joints)")
    src_pose = source_joints if source_joints is not None else target_joints
    source = check_scan(name, source, src_pose, normalisation.root_joint)
    check_sampler(sampler, steps, T)
    t = (DEFAULT_T[mode] or T) if t is None else int(t)
    if not 1 <= t <= T:
        raise ValueError(f"t must be in [1, {T}] (the model's training timesteps), got {t}")
    M = len(source)
    N = min(M, 4096) if num_points is None else int(num_points)
    if N < 1:
        raise ValueError(f"num_points must be >= 1, got {N}")
    if N > M:
        raise ValueError(f"{name}: has {M} points, fewer than the {N} requested (lower --points)")
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    seeds = list(range(num)) if seeds is None else [int(s) for s in seeds]
    if len(seeds) != num:
        raise ValueError(f"seeds must have num={num} entries, got {len(seeds)}")
    if C == 6 and source_normals is None:
        raise ValueError(f"{name}: the model predicts normals (point_channels 6) but the source has none")

    picks = [subset(M, N, [s, 3]) for s in seeds]
    src = np.stack([source[i] for i in picks])  # (K, N, 3)
    nrm = None if source_normals is None else np.stack([np.asarray(source_normals, np.float32)[i] for i in picks])
    x0 = to_normalised(normalisation, src, nrm, src_pose, C)  # (K, N, C) in the source root's frame
    moved = None
    if mode == "renoise":
        regen = np.ones((num, N), bool)
        x = denoise_from(prior, target_joints, x0, t, sampler, steps, seeds)
    else:
        regen = np.stack([moving_region(s, source_joints, target_joints, threshold, normalisation.root_joint)[0]
                          for s in src])  # fmt: skip
        moved = moved_joints(source_joints, target_joints, threshold, normalisation.root_joint)
        x = denoise_from(prior, target_joints, x0 if t < T else None, t, sampler, steps,
                         seeds, known=(~regen, x0))  # fmt: skip
    points, normals = to_metres(normalisation, x, target_joints)
    if mode == "region":  # kept points exactly: the source moved with the root (and turned with it, with heading)
        j_s, j_t = np.asarray(src_pose, np.float64), np.asarray(target_joints, np.float64)
        turn, root_s, root_t = normalisation.angle(j_t) - normalisation.angle(j_s), normalisation.root(j_s), normalisation.root(j_t)
        kept = (rotate_z(src.astype(np.float64) - root_s, turn) + root_t).astype(np.float32)
        points = np.where(regen[..., None], points, kept)
        if normals is not None:
            normals = np.where(regen[..., None], normals, to_metres(normalisation, x0, target_joints)[1])
    return Edit(points, normals, regen, t, moved)


# ------------------------------------------------------------------------------------ benchmark
def evaluate_edit(prior: PointPrior, source: np.ndarray, source_joints: np.ndarray,
                  target: np.ndarray, target_joints: np.ndarray, num_points: int, seed: int = 0,
                  sampler: str = "dpm++sde", steps: int | None = None, renoise_ts: Sequence[int] = (100, 300),
                  threshold: float = DEFAULT_THRESHOLD_M) -> dict[str, dict[str, float]]:  # fmt: skip
    """Edit frame ``source`` (M, 3) to the pose of frame ``target`` and score every method.

    Methods: ``renoise_t{t}`` for each t, ``region``, ``scratch`` (``sample_clouds`` under the
    target pose, same seed), ``copy`` (the source moved with the root; reference).
    Metrics (cm, PocoLoco Chamfer = S2M + M2S):

    * ``unchanged_chamfer_cm``: output points whose nearest *target* bone is static vs. source
      points (N-subset) whose nearest *source* bone is static, moved with the root: how much of
      the source's detail survives where the pose did not change (NaN if nothing is static);
    * ``target_chamfer_cm``: the whole output vs. an N-point subset of the GT target frame.
    Plus ``moved_joints`` (count) and ``static_share`` (share of source points kept static).
    """

    normalisation = prior.normalisation
    root = normalisation.root_joint
    gsel = subset(len(target), num_points, [seed, 4])
    gt = target[gsel]
    src = source[subset(len(source), num_points, [seed, 5])]
    shift = normalisation.root(np.asarray(target_joints, np.float64)) - normalisation.root(
        np.asarray(source_joints, np.float64))  # fmt: skip
    moving_src, moved = moving_region(src, source_joints, target_joints, threshold, root)
    src_static = src[~moving_src] + shift
    bone_moves = np.array([moved[a] or moved[b] for a, b in _bones(len(moved))])

    def score(points: np.ndarray) -> dict[str, float]:
        static = points[~bone_moves[nearest_bone(points, target_joints)]]
        ok = len(static) and len(src_static)
        return {"unchanged_chamfer_cm": chamfer_cm(static, src_static) if ok else float("nan"),
                "target_chamfer_cm": chamfer_cm(points, gt)}  # fmt: skip

    out: dict[str, dict[str, float]] = {}
    kw = dict(source_joints=source_joints, num_points=num_points, sampler=sampler, steps=steps, seeds=[seed],
              threshold=threshold)  # fmt: skip
    for t in renoise_ts:
        out[f"renoise_t{t}"] = score(edit(prior, source, target_joints, mode="renoise", t=t,
                                          **kw).points[0])  # fmt: skip
    out["region"] = score(edit(prior, source, target_joints, mode="region", **kw).points[0])
    out["scratch"] = score(sample_prior(prior, target_joints, num_points, [seed], sampler, steps)[0][0])
    out["copy"] = score((src + shift).astype(np.float32))
    for m in out.values():
        m["moved_joints"] = float(moved.sum())
        m["static_share"] = float((~moving_src).mean())
    return out
