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
:func:`evaluate_edit` (the benchmark's metrics); CLI pieces :func:`add_edit_arguments` /
:func:`cmd_edit` (``pocoloco edit``).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.apps._common import (add_common_arguments, check_common_args, check_scan, denoise_from, jsonable,
                                   load_model_from_args, read_cloud, save_npy, subset, to_metres, to_normalised,
                                   write_folder)  # fmt: skip
from pocoloco.body.skeleton import JOINT_PARENTS
from pocoloco.data.dataset import Normalisation

__all__ = ["Edit", "MODES", "add_edit_arguments", "cmd_edit", "edit", "evaluate_edit", "moved_joints", "moving_region",
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
    model,
    normalisation: Normalisation,
    config: Any,
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
    from pocoloco.sample import _check_joints, _check_sampler

    C, J, T = int(config.denoiser.point_channels), int(config.denoiser.num_joints), int(config.num_timesteps)
    if mode not in MODES:
        raise ValueError(f"unknown edit mode {mode!r}; choose one of: {', '.join(MODES)}")
    target_joints = _check_joints("target joints", target_joints, J)
    if source_joints is not None:
        source_joints = _check_joints("source joints", source_joints, J)
    elif mode == "region":
        raise ValueError("region mode needs the source pose (--source-joints)")
    src_pose = source_joints if source_joints is not None else target_joints
    source = check_scan(name, source, src_pose, normalisation.root_joint)
    _check_sampler(sampler, steps, T)
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
        x = denoise_from(model, normalisation, config, target_joints, x0, t, sampler, steps, seeds)
    else:
        regen = np.stack([moving_region(s, source_joints, target_joints, threshold, normalisation.root_joint)[0]
                          for s in src])  # fmt: skip
        moved = moved_joints(source_joints, target_joints, threshold, normalisation.root_joint)
        x = denoise_from(model, normalisation, config, target_joints, x0 if t < T else None, t, sampler, steps,
                         seeds, known=(~regen, x0))  # fmt: skip
    points, normals = to_metres(normalisation, x, target_joints)
    if mode == "region":  # kept points exactly: the source moved with the root
        shift = (normalisation.root(target_joints).astype(np.float64) - normalisation.root(src_pose))
        kept = (src.astype(np.float64) + shift).astype(np.float32)
        points = np.where(regen[..., None], points, kept)
        if normals is not None:
            normals = np.where(regen[..., None], normals, to_metres(normalisation, x0, target_joints)[1])
    return Edit(points, normals, regen, t, moved)


# ------------------------------------------------------------------------------------ benchmark
def evaluate_edit(model, normalisation: Normalisation, config: Any, source: np.ndarray, source_joints: np.ndarray,
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
    from pocoloco.metrics import chamfer_cm
    from pocoloco.sample import sample_clouds

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
        out[f"renoise_t{t}"] = score(edit(model, normalisation, config, source, target_joints, mode="renoise", t=t,
                                          **kw).points[0])  # fmt: skip
    out["region"] = score(edit(model, normalisation, config, source, target_joints, mode="region", **kw).points[0])
    out["scratch"] = score(sample_clouds(model, normalisation, config, target_joints, 1, num_points, sampler=sampler,
                                         steps=steps, seeds=[seed]).points[0])  # fmt: skip
    out["copy"] = score((src + shift).astype(np.float32))
    for m in out.values():
        m["moved_joints"] = float(moved.sum())
        m["static_share"] = float((~moving_src).mean())
    return out


# ------------------------------------------------------------------------------------------ CLI
def add_edit_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco edit`` options (handler :func:`cmd_edit`)."""
    parser.add_argument("--source", required=True, help="source cloud: .ply (or a dataset frame .npz / (M, 3) .npy)")
    parser.add_argument("--joints", required=True, help="TARGET pose, as for `pocoloco sample --joints`")
    parser.add_argument("--source-joints", help="the source's pose (same forms; needed by --mode region)")
    parser.add_argument("--mode", default="renoise", help="renoise (SDEdit) or region (inpaint the moving parts)")
    parser.add_argument("--t", type=int, help="start step in [1, T]: renoise default 100; region default T "
                                              "(moving points from pure noise)")  # fmt: skip
    parser.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD_M,
                        help=f"region: a joint moved if its root-relative position changed more (m; default "
                             f"{DEFAULT_THRESHOLD_M})")  # fmt: skip
    parser.add_argument("--points", type=int, help="N points per edited cloud (default min(source points, 4096))")
    parser.add_argument("--num", type=int, default=1, help="K edits to draw (default 1)")
    add_common_arguments(parser, "output folder (edited_000.ply ..., regenerated.npy, edit.png, edit.json)")


def cmd_edit(args: argparse.Namespace) -> None:
    """``pocoloco edit``: validate, edit, write the output folder (nothing on error)."""
    from pocoloco.data.published import write_ply
    from pocoloco.sample import _check_sampler, load_joints
    from pocoloco.utils.atomic import write_json_atomic

    check_common_args(args)
    if args.mode not in MODES:
        raise ValueError(f"unknown --mode {args.mode!r}; choose one of: {', '.join(MODES)}")
    if args.mode == "region" and args.source_joints is None:
        raise ValueError("--mode region needs --source-joints (the source cloud's pose)")
    for name in ("points", "num"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise ValueError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not args.threshold > 0:
        raise ValueError(f"--threshold must be > 0, got {args.threshold}")
    source, normals = read_cloud(args.source)
    model, normalisation, config, ckpt, step = load_model_from_args(args)
    J = config.denoiser.num_joints
    target = load_joints(args.joints, None, J)
    src_joints = None if args.source_joints is None else load_joints(args.source_joints, None, J)
    _check_sampler(args.sampler, args.steps, config.num_timesteps)
    if args.t is not None and not 1 <= args.t <= config.num_timesteps:
        raise ValueError(f"--t must be in [1, {config.num_timesteps}] (the model's training timesteps), got {args.t}")
    seeds = [args.seed + k for k in range(args.num)]
    t0 = time.perf_counter()
    res = edit(model, normalisation, config, source, target, source_joints=src_joints, source_normals=normals,
               mode=args.mode, t=args.t, num_points=args.points, num=args.num, sampler=args.sampler, steps=args.steps,
               seeds=seeds, threshold=args.threshold, name=os.fspath(args.source))  # fmt: skip
    seconds = time.perf_counter() - t0
    N = res.points.shape[1]
    settings = {
        "checkpoint": str(ckpt), "step": step, "source": os.fspath(args.source), "joints": os.fspath(args.joints),
        "source_joints": args.source_joints, "mode": args.mode, "t": res.t, "points": N, "num": args.num,
        "sampler": args.sampler, "steps": args.steps, "seeds": seeds, "threshold_m": args.threshold,
        "moved_joints": None if res.moved_joints is None else np.flatnonzero(res.moved_joints).tolist(),
        "regenerated_share": float(res.regenerated.mean()), "seconds_total": seconds,
        "regenerated_flags": "regenerated.npy: (K, N) bool, True = generated, False = kept from the source",
    }  # fmt: skip

    def fill(folder: Path) -> set[str]:
        names = {"regenerated.npy", "edit.json"}
        for k in range(args.num):
            nrm = None if res.normals is None else res.normals[k]
            write_ply(folder / f"edited_{k:03d}.ply", res.points[k], normals=nrm)
            names.add(f"edited_{k:03d}.ply")
        save_npy(folder / "regenerated.npy", res.regenerated)
        if not args.no_render:
            from pocoloco.render import render_grid

            show = source[subset(len(source), 4 * N, [0])]
            panels = [(show, None, None, "source")]
            for k in range(min(args.num, 4)):
                lab = np.where(res.regenerated[k], 2, 0) if args.mode == "region" else None
                panels.append((res.points[k], lab, None, f"edit {k}" + (" (orange: new)" if lab is not None else "")))
            render_grid(panels, folder / "edit.png", views=("front", "side"), ncols=len(panels))
            names.add("edit.png")
        write_json_atomic(folder / "edit.json", jsonable(settings))
        return names

    write_folder(args.out, fill, stale=lambda n: n.startswith("edited_") and n.endswith(".ply"))
    print(f"wrote {args.num} {args.mode} edits of {N} points (t={res.t}, {100 * res.regenerated.mean():.0f}% "
          f"regenerated) to {args.out} ({seconds:.1f} s)")  # fmt: skip
