"""Shared machinery of the applications: partial reverse chains under a pose, input checks, output
folders.

The core is :func:`denoise_from`: run a method's :class:`~pocoloco.methods.base.PointPrior` from an
intermediate step, starting from a *renoised* clean cloud (SDEdit) or from pure noise, optionally
keeping known points (RePaint), under one pose; the chains themselves are
:mod:`pocoloco.diffusion.chains` (its module docstring gives the step convention: ``t`` is 1-based,
``t = T`` is pure noise).
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pocoloco.data.dataset import Normalisation, rotate_z
from pocoloco.data.format import read_frame
from pocoloco.data.published import MAX_CLOUD_EXTENT_M, check_cloud, read_ply
from pocoloco.diffusion.few_step import polish as teacher_polish, student_grid
from pocoloco.diffusion.chains import chain_timesteps, renoise, repaint_resampling
from pocoloco.diffusion.samplers import PerSampleRNG, sample
from pocoloco.methods.base import PointPrior
from pocoloco.utils.atomic import atomic_write, no_file_reason, output_folder
from pocoloco.utils.npfile import numpy_file_problem

#: a scan whose bounding box is larger than this (metres) is taken to be in the wrong unit
MAX_EXTENT_M = MAX_CLOUD_EXTENT_M
#: a scan whose centroid is farther than this from the pose's root joint is refused
MAX_ROOT_DISTANCE_M = 1.0


# ------------------------------------------------------------------------------------ chains
@torch.no_grad()
def denoise_from(
    prior: PointPrior,
    joints: np.ndarray,
    x0: np.ndarray | None,
    t: int,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seeds: Sequence[int] = (0,),
    known: tuple[np.ndarray, np.ndarray] | None = None,
    num_points: int | None = None,
    resample: int = 1,
    jump: int = 1,
    polish: bool = True,
) -> np.ndarray:
    """Run the reverse chain from step ``t`` under one pose, in the *normalised* frame.

    Args:
        prior: the method's generative point model (``method.point_prior(outfit)``).
        joints: (J, 3) target pose in metres (its root defines the normalised frame).
        x0: (B, N, C) clean clouds, normalised with ``joints``' root, to renoise to step t
            (SDEdit, :func:`~pocoloco.diffusion.chains.renoise`); None, or ``t = T``: pure noise.
        t: 1-based start step. sampler, steps: see :func:`~pocoloco.diffusion.chains.chain_timesteps`.
        seeds: B seeds; sample b's initial noise, the renoising noise and any sampler noise come
            from one generator seeded ``seeds[b]`` (``PerSampleRNG``), so with ``t = T`` and no
            ``known`` the result equals ``sample_clouds`` with the same seeds and steps.
        known: (mask (B, N) bool, x0_known (B, N, C) normalised) points kept (RePaint without
            resampling: known points are replaced by q(x_s | x0_known) after every step).
        num_points: N when neither x0 nor known is given.
        resample, jump: RePaint's resampling (:func:`~pocoloco.diffusion.chains.repaint_resampling`;
            1: off, the default). With resample > 1 every step is an ancestral DDPM step whatever
            ``sampler`` is; denoiser calls = steps x resample.
        polish: a distilled student whose teacher makes the last call (``prior.polish``): end the
            chain with that call (:func:`~pocoloco.diffusion.few_step.polish`: one more network
            call; ``known`` points are kept). False: the student's calls alone.
    Returns:
        (B, N, C) float32 normalised clouds (:func:`to_metres` maps them back).
    """

    C, J, T = prior.point_channels, prior.num_joints, prior.schedule.num_timesteps
    if getattr(prior, "student_calls", 0):
        sampler, steps, timesteps = student_chain(prior, t, steps, resample)
    else:
        timesteps = chain_timesteps(t, T, sampler, steps)
    if resample < 1 or jump < 1:
        raise ValueError(f"resample and jump must be >= 1, got {resample} and {jump}")
    seeds = [int(s) for s in seeds]
    if x0 is not None:
        x0 = np.asarray(x0, np.float32)
        if x0.ndim != 3 or x0.shape[0] != len(seeds) or x0.shape[2] != C:
            raise ValueError(f"x0 must have shape ({len(seeds)}, N, {C}), got {x0.shape}")
        N = x0.shape[1]
    elif known is not None:
        N = np.asarray(known[0]).shape[1]
    elif num_points is not None:
        N = int(num_points)
    else:
        raise ValueError("denoise_from needs x0, known or num_points (to know N)")
    model = prior.denoiser
    param = next(model.parameters())
    device, dtype = param.device, param.dtype
    _, joints_n = prior.normalisation.normalise(np.zeros((1, 3), np.float32), np.asarray(joints, np.float32))
    rng = PerSampleRNG(seeds, device=device)
    noise = rng.randn((N, C), dtype=dtype, device=device)  # (B, N, C)
    if x0 is not None and t < T:
        noise = renoise(prior.schedule, x0, noise, t)  # (B, N, C) x at index t - 1 (SDEdit's renoised source)
    kw: dict[str, Any] = {}
    if known is not None:
        mask, xk = known
        kw["known"] = (torch.as_tensor(np.asarray(mask, bool), device=device),
                       torch.as_tensor(np.asarray(xk, np.float32), dtype=dtype, device=device))  # fmt: skip
    cond = torch.as_tensor(joints_n, dtype=dtype, device=device).expand(len(seeds), J, 3)  # (B, J, 3)
    was_training = model.training
    model.eval()
    try:
        if resample > 1:
            out = repaint_resampling(model, prior.schedule, noise, cond, timesteps, rng, prior.prediction_type,
                                     kw.get("known"), resample, jump)  # fmt: skip
        else:
            if sampler == "few-step":
                kw["renoise"] = prior.student_renoise
            out = sample(sampler, model, prior.schedule, noise, cond, timesteps=timesteps, rng=rng,
                         prediction_type=prior.prediction_type, **kw)  # fmt: skip
            if polish and sampler == "few-step" and prior.polish is not None:
                teacher, t_polish = prior.polish
                if hasattr(teacher, "motion") and hasattr(model, "motion"):
                    teacher.motion = model.motion  # the same motion window as the student's
                out = teacher_polish(teacher, prior.schedule, out, cond, t_polish, rng,
                                     prediction_type=prior.prediction_type)  # fmt: skip
                if "known" in kw:
                    mask, xk = kw["known"]
                    out = torch.where(mask[..., None], xk.to(out.dtype), out)
    finally:
        model.train(was_training)
    return out.float().cpu().numpy()


def student_chain_start(prior: PointPrior) -> int:
    """Where a distilled model's chains start unless told (editing, completion's harmonising chain,
    each new animation frame): its least noisy grid step, one network call (t = 250 for the 4-call
    grid)."""
    return student_grid(prior.schedule.num_timesteps, prior.student_calls)[-1] + 1


def student_chain(prior: PointPrior, t: int, steps: int | None, resample: int = 1) -> tuple[str, int, list[int]]:
    """A distilled student's chain from step t: the few-step sampler over its grid timesteps below t
    (``steps`` None: all of them; t = 250 / 500 / 750 / 1000 give 1 / 2 / 3 / 4 calls with the
    4-call grid). One-line errors for a t or steps off the grid, and for RePaint resampling."""
    T = prior.schedule.num_timesteps
    grid = student_grid(T, prior.student_calls)
    if resample > 1:
        raise ValueError("--resample: a distilled model has no ancestral steps to resample; use its teacher")
    below = [g for g in grid if g < t]
    if steps is None:
        steps = len(below)
    timesteps = chain_timesteps(t, T, "few-step", steps) if below else []
    if not below or not set(timesteps) <= set(grid):
        starts = ", ".join(str(g + 1) for g in sorted(grid))
        raise ValueError(f"a distilled model denoises from its grid steps only: t in {{{starts}}} with as many calls "
                         f"as grid steps below t (got t={t}, steps={steps})")  # fmt: skip
    return "few-step", steps, timesteps


def sample_prior(prior: PointPrior, joints: np.ndarray, num_points: int, seeds: Sequence[int],
                 sampler: str = "dpm++sde", steps: int | None = None, batch_size: int = 8) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
    """Fresh samples of the pose (J, 3), one per seed, ``batch_size`` at a time: points (K, N, 3)
    metres in ``joints``' frame and unit normals (K, N, 3) or None (the chain from t = T)."""
    seeds = [int(s) for s in seeds]
    T = prior.schedule.num_timesteps
    parts = [denoise_from(prior, joints, None, T, sampler, steps, seeds[b : b + batch_size], num_points=num_points)
             for b in range(0, len(seeds), batch_size)]  # fmt: skip
    return to_metres(prior.normalisation, np.concatenate(parts), joints)


def to_metres(normalisation: Normalisation, x: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(B, N, C) normalised -> points (B, N, 3) metres in ``joints``' frame, unit normals or None."""
    joints = np.asarray(joints, np.float32)
    root, angle = normalisation.root(joints).astype(np.float32), normalisation.angle(joints)
    points = normalisation.denormalise(x[..., :3], root, angle).astype(np.float32)
    normals = None
    if x.shape[-1] == 6:
        n = rotate_z(x[..., 3:6], angle)
        normals = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)).astype(np.float32)
    return points, normals


def to_normalised(normalisation: Normalisation, points: np.ndarray, normals: np.ndarray | None,
                  joints: np.ndarray, channels: int) -> np.ndarray:  # fmt: skip
    """(..., N, 3) metres (+ normals) -> (..., N, C) normalised with ``joints``' root (C = 3 or 6)."""
    p, _ = normalisation.normalise(np.asarray(points, np.float32), np.asarray(joints, np.float32))
    if channels == 3:
        return p.astype(np.float32)
    if normals is None:
        raise ValueError("the model predicts normals (point_channels 6) but the input cloud has none")
    n = rotate_z(np.asarray(normals, np.float32), -normalisation.angle(np.asarray(joints, np.float32)))
    return np.concatenate([p, n], axis=-1).astype(np.float32)


def subset(n: int, k: int, seed: int | Sequence[int]) -> np.ndarray:
    """Sorted indices of min(k, n) of n items drawn without replacement from ``default_rng(seed)``."""
    return np.sort(np.random.default_rng(seed).choice(n, size=min(k, n), replace=False))


# ------------------------------------------------------------------------------------- inputs
def check_scan(name: str, points: np.ndarray, joints: np.ndarray, root_joint: int = 0) -> np.ndarray:
    """(N, 3) float32 scan points that plausibly belong to ``joints`` or a one-line ValueError:
    empty, NaN / inf, larger than MAX_EXTENT_M (millimetres?), centroid farther than
    MAX_ROOT_DISTANCE_M from the root joint."""
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected points of shape (N, 3), got {p.shape}")
    if p.shape[0] == 0:
        raise ValueError(f"{name}: the scan is empty (0 points)")
    if not np.isfinite(p).all():
        raise ValueError(f"{name}: the scan contains NaN or inf coordinates")
    p = p.astype(np.float32)
    extent = float(np.ptp(p, axis=0).max())
    if extent > MAX_EXTENT_M:
        raise ValueError(f"{name}: the scan is {extent:.3g} units across, more than {MAX_EXTENT_M:g} m "
                         "(not in metres? millimetres must be divided by 1000)")  # fmt: skip
    dist = float(np.linalg.norm(p.mean(0) - np.asarray(joints, np.float64)[root_joint]))
    if dist > MAX_ROOT_DISTANCE_M:
        raise ValueError(f"{name}: the scan's centroid is {dist:.2f} m from the pose's root joint (more than "
                         f"{MAX_ROOT_DISTANCE_M:g} m): wrong pose or another coordinate frame?")  # fmt: skip
    return p


def read_cloud(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) and normals (N, 3) or None of a .ply, or of a dataset frame .npz / .npy (N, 3);
    degenerate clouds are refused in one line (``data.published.check_cloud``)."""
    points, normals = _read_cloud(path)
    return check_cloud(os.fspath(path), points), normals


def _read_cloud(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:

    src = os.fspath(path)
    if not os.path.isfile(src):
        raise ValueError(f"{src}: {no_file_reason(src)}")
    if src.endswith(".npz"):

        fr = read_frame(src, ["points", "normals"], allow_missing=True)
        return fr.points, fr.normals
    if src.endswith(".npy"):
        try:
            arr = np.load(src, allow_pickle=False)
        except Exception as e:  # ValueError, EOFError, OSError ...
            problem = numpy_file_problem(src, "npy") or f"{type(e).__name__}: {' '.join(str(e).split())}"
            raise ValueError(f"{src}: cannot read a (N, 3) points array: {problem}") from None
        return arr, None
    ply = read_ply(src)
    return ply.points, ply.normals


# ------------------------------------------------------------------------------------- output
def write_folder(out: str | os.PathLike, fill: Callable[[Path], set[str]],
                 stale: Callable[[str], bool] | None = None) -> Path:  # fmt: skip
    """Create ``out`` with ``fill(folder) -> names written``. A new folder is filled under a
    temporary name and renamed into place (complete or absent); an existing one gets its files
    replaced (each written atomically by ``fill``), then files matching ``stale(name)`` that
    this run did not write (e.g. frames of an earlier, longer run) are removed."""
    out = output_folder(out)
    if out.exists():
        written = fill(out)
        if stale is not None:
            for p in out.iterdir():
                if stale(p.name) and p.name not in written:
                    p.unlink()
        return out
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir(parents=True)
        fill(tmp)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def save_npy(path: str | os.PathLike, arr: np.ndarray) -> None:
    """``np.save`` to ``path`` atomically."""

    atomic_write(path, lambda f: np.save(f, np.asarray(arr)))
