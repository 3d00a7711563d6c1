"""Sampling PocoLoco: K point-cloud hypotheses of a clothed body in one pose.

Pipeline (the inverse of the training data path, :mod:`pocoloco.data.dataset`)::

    joints (J, 3) metres --normalise--> (J, 3) normalised  = (joints - root - mean) / std
    noise (K, N, C) per-sample seeds --sampler(denoiser, schedule, cond=joints)--> x0 (K, N, C)
    x0[..., :3] --denormalise--> points (K, N, 3) metres   = x0 * std + mean + root

``root = joints[normalisation.root_joint]`` of the *input* joints, so the samples come out in the
frame the joints were given in. C = 6 models also predict normals (channels 3:6), returned as unit
vectors. The denoiser is resolution-agnostic: N need not match the training ``num_points``.

Every sample k owns a ``torch.Generator`` seeded ``seeds[k]`` whose stream provides its initial
noise and any sampler noise (:class:`~pocoloco.diffusion.samplers.PerSampleRNG`), so sample k is
the same whatever the batch size.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from pocoloco.data.dataset import Normalisation, rotate_z
from pocoloco.data.motion_window import MotionWindow, window_samples
from pocoloco.data.poses import check_joints
from pocoloco.diffusion.few_step import check_student_calls, polish as teacher_polish, polished_grid, sampling_grid
from pocoloco.diffusion.samplers import (
    SAMPLER_STEPS,
    PerSampleRNG,
    check_sampler,
    sample,
)
from pocoloco.diffusion.schedules import NoiseSchedule
from pocoloco.methods.base import SampledClouds
from pocoloco.models.conditioning import PoseCondition

__all__ = ["DEFAULT_CLIP", "check_finish", "condition_for", "sample_clouds", "sampler_for"]

#: default x0 clamp of the CLI (normalised units); the ``small`` data stay within +-3.52
DEFAULT_CLIP = 5.0


def condition_for(joints: torch.Tensor, outfit: int | None = None, shape: Sequence[float] | None = None,
                  body: torch.Tensor | None = None, code: torch.Tensor | None = None,
                  velocity: torch.Tensor | None = None, motion: torch.Tensor | None = None
                  ) -> torch.Tensor | PoseCondition:  # fmt: skip
    """The denoiser's conditioning for B copies of one pose: the (B, J, 3) joints alone, or a
    :class:`~pocoloco.models.conditioning.PoseCondition` with the outfit id (or an outfit code (D,)
    instead), the body shape, the (1, K, 3) normalised posed-body vertices and the (1, J, 3)
    normalised joint velocities and the (1, J, F) motion-window features."""
    if outfit is None and shape is None and body is None and code is None and velocity is None and motion is None:
        return joints
    B = joints.shape[0]
    return PoseCondition(joints, None if outfit is None else torch.full((B,), int(outfit), device=joints.device),
                         None if shape is None else torch.as_tensor(np.asarray(shape, np.float32), device=joints.device)
                         .expand(B, -1).to(joints.dtype),
                         code=None if code is None else code.to(joints.device, joints.dtype).reshape(1, -1).expand(B, -1),
                         body=None if body is None else body.to(joints.device, joints.dtype).expand(B, -1, -1),
                         velocity=None if velocity is None else velocity.to(joints.device, joints.dtype).expand(B, -1, -1),
                         motion=None if motion is None else motion.to(joints.device, joints.dtype).expand(B, -1, -1))  # fmt: skip


def sampler_for(config: Any, sampler: str, steps: int | None, polish: bool = False) -> tuple[str, int]:
    """The sampler and number of network calls a model of ``config`` samples with when asked for
    ``sampler`` / ``steps`` (None: the sampler's default). A distilled student
    (``config.student_calls`` > 0) samples with the few-step sampler only: the default "dpm++sde"
    means it, ``steps`` None its trained number of calls, and another sampler or a number of calls
    beyond its grid is a one-line error (``polish``: its teacher makes the last of 3 or more calls,
    and one more than the grid is allowed, :func:`~pocoloco.diffusion.few_step.polished_grid`). A
    diffusion model keeps what was asked."""
    calls = int(getattr(config, "student_calls", 0) or 0)
    if not calls:
        if sampler == "few-step":
            raise ValueError("--sampler few-step is for a distilled model (pocoloco distill, e.g. --ckpt default:fast); "
                             "this one is a diffusion model")  # fmt: skip
        check_sampler(sampler, steps, config.num_timesteps)
        return sampler, int(steps if steps is not None else SAMPLER_STEPS[sampler])
    if sampler not in ("dpm++sde", "few-step"):
        raise ValueError(f"--sampler {sampler}: this distilled model samples with its own few-step sampler only "
                         f"(--steps 1 .. {calls}); the diffusion samplers are for its teacher")  # fmt: skip
    steps = calls if steps is None else int(steps)
    check_student_calls(steps, calls, config.num_timesteps, polish)
    return "few-step", steps


def check_finish(config: Any, finish: int | None) -> None:
    """One-line ValueError unless ``finish`` (a 1-based step for one more call of the model's own
    after its chain, or None) suits a model of ``config``: a step of its schedule, and not a
    distilled student (whose last call is its teacher's: ``export-model --polish-t``)."""
    if finish is None:
        return
    if isinstance(finish, bool) or not isinstance(finish, (int, np.integer)) or not 1 <= finish <= config.num_timesteps:
        raise ValueError(f"--finish-t must be a step in [1, {config.num_timesteps}], got {finish!r}")
    if int(getattr(config, "student_calls", 0) or 0):
        raise ValueError("--finish-t is for a diffusion model; a distilled model's last call is its teacher's "
                         "(export-model --polish-with TEACHER --polish-t T)")  # fmt: skip


@torch.no_grad()
def sample_clouds(
    model: torch.nn.Module,
    normalisation: Normalisation,
    config: Any,
    joints: np.ndarray,
    num: int,
    num_points: int,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seeds: Sequence[int] | None = None,
    batch_size: int = 8,
    progress: Any = None,
    clip: float | None = None,
    bf16: bool = False,
    outfit: int | None = None,
    shape: Sequence[float] | None = None,
    body: np.ndarray | None = None,
    code: torch.Tensor | None = None,
    velocity: np.ndarray | None = None,
    motion: MotionWindow | None = None,
    polish: tuple[torch.nn.Module, int] | None = None,
    finish: int | None = None,
) -> SampledClouds:
    """Draw ``num`` clouds of ``num_points`` points from the denoiser, conditioned on one pose.

    Args:
        model: the trained denoiser ``model(x (B, N, C), t (B,), joints (B, J, 3))`` (its device and
            dtype are used for everything).
        normalisation: the dataset normalisation the model was trained with.
        config: the ``TrainConfig`` (``schedule``, ``num_timesteps``, ``prediction_type``,
            ``denoiser.point_channels`` / ``num_joints``), as returned by ``load_denoiser``.
        joints: (J, 3) joints in metres, any frame (the samples come out in the same frame).
        num: K clouds. num_points: N points per cloud (any N >= 1).
        sampler: "dpm++" (DPM-Solver++ 2M), "dpm++sde" (its SDE form), "ddim" (eta 0) or "ddpm"
            (ancestral); a distilled student samples with "few-step" (:func:`sampler_for`).
        steps: sampler steps (None: ``SAMPLER_STEPS[sampler]``: 20 for dpm++, 25 for dpm++sde, 50 for
            ddim, 100 for ddpm).
        seeds: K seeds, one per cloud (None: 0 .. K-1). Cloud k depends only on seeds[k].
        batch_size: clouds denoised together (memory / speed only; results do not depend on it
            beyond float round-off of batched matrix products).
        progress: optional ``callable(done_clouds, K)`` called after each batch.
        clip: clamp the sampler's x0 estimates to [-clip, clip] in normalised units (None: off).
            The data fill about [-4.5, 4.5] (a 1.2 m reach over the 0.26 m std of ``small``), so
            ``clip=5`` only stops stray points of an undertrained model from flying away.
        outfit / shape: the outfit id and the (S,) body shape for models conditioned on who wears
            what (``config.outfit_codes`` / ``config.body_shape``); None for joints-only models.
        body: (K, 3) posed-body vertices in metres, same frame as ``joints`` (models trained with
            ``body_points = K``; None for the others).
        code: an outfit code (D,) used instead of ``outfit``'s embedding (a fitted outfit).
        velocity: (J, 3) joint velocities in m/s, same frame as ``joints`` (models trained with
            ``joint_velocity``; None: the body at rest).
        motion: the last seconds of the motion before the pose (models trained with a
            ``motion_window``: a :class:`~pocoloco.data.motion_window.MotionWindow` of as many
            samples; None: the body at rest).
        polish: (teacher denoiser, t) of a distilled student whose teacher makes its last call,
            re-noising the student's answer to 1-based step t (:func:`~pocoloco.diffusion.few_step.polish`)
            when ``steps`` >= 3 (:func:`~pocoloco.diffusion.few_step.polished_grid`); None: off.
        finish: a diffusion model's own finishing call: after the chain, each cloud re-noised to
            1-based step ``finish`` with fresh noise from its generator and the model's x0 estimate
            there (:func:`~pocoloco.diffusion.few_step.polish` with the model as its own teacher);
            None: off. The chain's last estimate comes from its grid's last step (40 of 1,000 for
            25 dpm++sde steps), a noise larger than the cloth's detail, and shrinks the cloud a
            little; one more call at step 5 takes it back (docs/lab/fast.md).
        bf16: run the denoiser under bf16 autocast (its matmuls and attention in bfloat16; the
            sampler's arithmetic and the returned points stay float32). Several times faster on
            CPUs with AMX / avx512_bf16 and on recent GPUs; slower on CPUs without them.
    Returns:
        :class:`SampledClouds` (points (K, N, 3), normals (K, N, 3) or None).
    """
    den = config.denoiser
    C, J = int(den.point_channels), int(den.num_joints)
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    if num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {num_points}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    seeds = list(range(num)) if seeds is None else [int(s) for s in seeds]
    if len(seeds) != num:
        raise ValueError(f"seeds must have num={num} entries, got {len(seeds)}")
    sampler, steps = sampler_for(config, sampler, steps, polish is not None)
    check_finish(config, finish)
    joints = check_joints("joints", joints, J)
    param = next(model.parameters())
    device, dtype = param.device, param.dtype

    _, joints_n = normalisation.normalise(np.zeros((1, 3), np.float32), joints)  # (J, 3) normalised
    body_t = None
    if body is not None:
        body = np.asarray(body, np.float32)
        if body.ndim != 2 or body.shape[1] != 3 or not np.isfinite(body).all():
            raise ValueError(f"body must be a finite (K, 3) array of posed-body vertices, got shape {body.shape}")
        body_t = torch.as_tensor(normalisation.normalise(body, joints)[0], dtype=dtype, device=device)[None]
    velocity_t = None
    if velocity is not None:
        velocity = np.asarray(velocity, np.float32)
        if velocity.shape != joints.shape or not np.isfinite(velocity).all():
            raise ValueError(f"velocity must be a finite {joints.shape} array of joint velocities (m/s), got "
                             f"shape {velocity.shape}")  # fmt: skip
        velocity_t = torch.as_tensor(normalisation.normalise_velocity(velocity, joints), dtype=dtype, device=device)[None]
    motion_t = None
    if motion is not None:
        want = window_samples(den.motion_window, den.motion_hz) if getattr(den, "motion_window", 0) else 0
        if not want:
            raise ValueError("this model takes no motion window (trained without --motion-window)")
        if motion.joints.shape != (want, J, 3):
            raise ValueError(f"motion: the model takes {want} samples of {J} joints, got {motion.joints.shape[:2]}")
        motion_t = torch.as_tensor(normalisation.normalise_motion(motion, joints), dtype=dtype, device=device)[None]
    root = normalisation.root(joints)  # (3,) metres
    schedule = NoiseSchedule.from_kind(config.schedule, config.num_timesteps)
    kwargs: dict[str, Any] = {"prediction_type": config.prediction_type, "clip": clip}
    kwargs["steps"] = steps
    grid = None  # the student's calls when its teacher makes the last
    if sampler == "few-step":
        kwargs["renoise"] = float(getattr(config, "student_renoise", 1.0))
        if polish is not None:
            grid = polished_grid(config.num_timesteps, steps, int(config.student_calls))
        own = grid or sampling_grid(config.num_timesteps, steps, int(config.student_calls))
        kwargs["timesteps"], kwargs["steps"] = own, len(own)

    # the last call after the chain (one network, one step): a student's teacher, or a diffusion
    # model's own (check_finish refuses a student, so at most one of the two applies)
    finisher = polish if grid is not None else (model, int(finish)) if finish is not None else None

    was_training = model.training
    model.eval()
    out = np.empty((num, num_points, C), np.float32)  # (K, N, C) normalised
    try:
        for b0 in range(0, num, batch_size):
            chunk = seeds[b0 : b0 + batch_size]
            rng = PerSampleRNG(chunk, device=device)
            noise = rng.randn((num_points, C), dtype=dtype, device=device)  # (B, N, C)
            cond = condition_for(torch.as_tensor(joints_n, dtype=dtype, device=device).expand(len(chunk), J, 3),
                                 outfit, shape, body_t, code, velocity_t, motion_t)  # fmt: skip
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                x = sample(sampler, model, schedule, noise, cond, rng=rng, **kwargs)  # (B, N, C)
                if finisher is not None:
                    x = teacher_polish(finisher[0], schedule, x, cond, finisher[1], rng,
                                       prediction_type=config.prediction_type, clip=clip)  # fmt: skip
            out[b0 : b0 + len(chunk)] = x.float().cpu().numpy()
            if progress is not None:
                progress(b0 + len(chunk), num)
    finally:
        model.train(was_training)

    angle = normalisation.angle(joints)  # the heading turned away (0 without canonical_heading)
    points = normalisation.denormalise(out[..., :3], root.astype(np.float32), angle).astype(np.float32)  # (K, N, 3)
    normals = None
    if C == 6:
        n = rotate_z(out[..., 3:6], angle)  # directions turn back with the body
        normals = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)).astype(np.float32)
    return SampledClouds(points, normals)
