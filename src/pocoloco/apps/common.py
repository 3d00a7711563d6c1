"""Shared machinery of the applications: partial reverse chains, input checks, output folders.

The core is :func:`denoise_from`: start the reverse process at an intermediate step from a
*renoised* clean cloud (SDEdit, Meng et al. 2022: ``x_t ~ q(x_t | x0) = N(sqrt(abar_t) x0,
(1 - abar_t) I)``, DDPM eq. 4) or from pure noise, optionally keeping known points (RePaint,
Lugmayr et al. 2022, via the samplers' ``known=``), and denoise under one pose.

Step convention (``t`` everywhere in :mod:`pocoloco.apps`): ``t`` is the 1-based step of the
paper, ``1 <= t <= T``. The chain starts at timestep index ``t - 1`` (the samplers' 0-based
index): ``t = 1`` is the least noisy step (one denoiser call at abar_0 = 1 - beta_0), ``t = T``
means *pure noise*, exactly what :func:`pocoloco.methods.pocoloco.sampling.sample_clouds` does (the samplers treat
N(0, I) as x at index T - 1, although abar_{T-1} = 0.004 > 0 for the "four" schedule), so
``t = T`` forgets the source entirely.
"""

from __future__ import annotations

import math
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
from pocoloco.data.published import read_ply
from pocoloco.diffusion.sampler_base import SamplerRun
from pocoloco.diffusion.samplers import (
    SAMPLER_STEPS,
    PerSampleRNG,
    check_sampler,
    sample,
)
from pocoloco.diffusion.schedules import NoiseSchedule
from pocoloco.utils.atomic import atomic_write, no_file_reason, output_folder

#: a scan whose bounding box is larger than this (metres) is taken to be in the wrong unit
MAX_EXTENT_M = 5.0
#: a scan whose centroid is farther than this from the pose's root joint is refused
MAX_ROOT_DISTANCE_M = 1.0


# ------------------------------------------------------------------------------------ chains
def chain_timesteps(t: int, num_timesteps: int, sampler: str, steps: int | None = None) -> list[int]:
    """Descending timestep indices of a reverse chain that starts at step ``t`` (1-based, see the
    module docstring): ``steps`` of them with the samplers' "trailing" spacing over the first
    ``t`` indices, ``round(t - k t / steps) - 1`` for ``k = 0 .. steps-1`` (so the first is
    ``t - 1`` and, for ``t = T``, the list equals the from-scratch sampler's).

    ``steps=None``: every index for ddpm, else ``min(t, default)`` (dpm++ 20, ddim 50).
    """

    check_sampler(sampler, None, num_timesteps)
    if not 1 <= t <= num_timesteps:
        raise ValueError(f"t must be in [1, {num_timesteps}] (the model's training timesteps), got {t}")
    if steps is None:
        default = SAMPLER_STEPS[sampler]
        steps = t if default is None else min(t, default)
    if not 1 <= steps <= t:
        raise ValueError(f"steps must be in [1, t={t}] for a chain starting at step t, got {steps}")
    ts = np.round(t - np.arange(steps) * (t / steps)).astype(np.int64) - 1
    return [int(x) for x in ts]


@torch.no_grad()
def denoise_from(
    model: torch.nn.Module,
    normalisation: Normalisation,
    config: Any,
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
) -> np.ndarray:
    """Run the reverse chain from step ``t`` under one pose, in the *normalised* frame.

    Args:
        model, normalisation, config: as returned by ``load_denoiser``.
        joints: (J, 3) target pose in metres (its root defines the normalised frame).
        x0: (B, N, C) clean clouds, normalised with ``joints``' root, to renoise to step t
            (SDEdit); None, or ``t = T``: start from pure noise.
        t: 1-based start step (module docstring).
        sampler, steps: see :func:`chain_timesteps`.
        seeds: B seeds; sample b's initial noise, the renoising noise and any sampler noise come
            from one generator seeded ``seeds[b]`` (``PerSampleRNG``), so with ``t = T`` and no
            ``known`` the result equals ``sample_clouds`` with the same seeds and steps.
        known: (mask (B, N) bool, x0_known (B, N, C) normalised) points kept (RePaint without
            resampling: known points are replaced by q(x_s | x0_known) after every step).
        num_points: N when neither x0 nor known is given.
        resample, jump: RePaint's resampling (Lugmayr et al. 2022, Algorithm 1 and its jump
            schedule): after every ``jump`` steps of the chain, go back up over them (x_a ~
            q(x_a | x_b) = N(sqrt(abar_a / abar_b) x_b, (1 - abar_a / abar_b) I)) and redo them,
            ``resample`` passes in all (1: off, the default). With resample > 1 every step is an
            ancestral DDPM step whatever ``sampler`` is; denoiser calls = steps x resample.
    Returns:
        (B, N, C) float32 normalised clouds (:func:`to_metres` maps them back).
    """

    den = config.denoiser
    C, J, T = int(den.point_channels), int(den.num_joints), int(config.num_timesteps)
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
    param = next(model.parameters())
    device, dtype = param.device, param.dtype
    _, joints_n = normalisation.normalise(np.zeros((1, 3), np.float32), np.asarray(joints, np.float32))
    schedule = NoiseSchedule.from_kind(config.schedule, T)
    rng = PerSampleRNG(seeds, device=device)
    noise = rng.randn((N, C), dtype=dtype, device=device)  # (B, N, C)
    if x0 is not None and t < T:
        ab = schedule.alpha_bar(t - 1)
        x = math.sqrt(ab) * torch.as_tensor(x0, dtype=torch.float64, device=device) + math.sqrt(1 - ab) * noise.double()
        noise = x.to(dtype)  # (B, N, C) x at index t - 1 (SDEdit's renoised source)
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
            out = repaint_resampling(model, schedule, noise, cond, timesteps, rng, config.prediction_type,
                                     kw.get("known"), resample, jump)  # fmt: skip
        else:
            out = sample(sampler, model, schedule, noise, cond, timesteps=timesteps, rng=rng,
                         prediction_type=config.prediction_type, **kw)  # fmt: skip
    finally:
        model.train(was_training)
    return out.float().cpu().numpy()


def repaint_resampling(model: torch.nn.Module, schedule: NoiseSchedule, noise: torch.Tensor, cond: Any,
                       timesteps: list[int], rng: PerSampleRNG | None, prediction_type: str | None,
                       known: tuple[torch.Tensor, torch.Tensor] | None, resample: int,
                       jump: int) -> torch.Tensor:  # fmt: skip
    """Ancestral DDPM over ``timesteps`` (descending) with RePaint's resampling (Lugmayr et al.
    2022, Algorithm 1): the chain is cut into segments of ``jump`` steps; each segment is run,
    then the state is diffused back to the segment's start with q(x_a | x_b) (all points; the
    known ones are then re-imposed at a) and the segment is run again, ``resample`` passes in all.
    noise: (B, N, C) the state at ``timesteps[0]``; returns (B, N, C) in noise.dtype.
    Denoiser calls: ``len(timesteps) * resample``.
    """

    run = SamplerRun(model, schedule, noise, cond, prediction_type, list(timesteps), None, rng, known, None)
    x = run.start(noise)
    S = len(run.timesteps)
    for a in range(0, S, jump):
        b = min(a + jump, S)
        for rep in range(resample):
            for i in range(a, b):  # ancestral steps, as sample_ddpm
                x, _ = run.ancestral_step(x, i)
            if rep < resample - 1:  # jump back up from the segment's end b to its start a
                ratio = run.ab[a] / run.ab_prev[b - 1]
                x = ratio**0.5 * x + (1.0 - ratio) ** 0.5 * run.randn_like(x)
                x = run.impose_known(x, run.ab[a])
    return x.to(run.dtype)


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
    """Points (N, 3) and normals (N, 3) or None of a .ply, or of a dataset frame .npz / .npy (N, 3)."""

    src = os.fspath(path)
    if not os.path.isfile(src):
        raise ValueError(f"{src}: {no_file_reason(src)}")
    if src.endswith(".npz"):

        fr = read_frame(src, ["points", "normals"], allow_missing=True)
        return fr.points, fr.normals
    if src.endswith(".npy"):
        try:
            arr = np.load(src, allow_pickle=False)
        except Exception as e:
            raise ValueError(f"{src}: cannot read ({type(e).__name__})") from None
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
