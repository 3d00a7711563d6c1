"""PocoLoco (Seth et al.) behind the :class:`~pocoloco.methods.base.Method` interface: a template-free,
pose-conditioned point-cloud diffusion model, p(X | K) with K the 24 joints only."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from pocoloco.data.dataset import frame_velocity
from pocoloco.data.poses import (
    MeanShapeCache,
    demo_motion,
    Pose,
    dataset_frame_path,
    load_body_pose,
    load_joints,
    outfit_of_spec,
    pose_from_frame,
    subject_of_spec,
)
from pocoloco.diffusion.few_step import polished_grid, sampling_grid
from pocoloco.diffusion.schedules import NoiseSchedule

from pocoloco.engine.checkpoint import META_FILE, Checkpoint, check_model_kind, load_checkpoint, one_line
from pocoloco.engine.links import link_to, load_linked
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.engine.trainer import TrainingTask
from pocoloco.methods.base import Method, PointPrior, SampledClouds, SamplerOptions
from pocoloco.methods.pocoloco.config import TRAIN_PRESETS, PocoLocoTrainConfig, point_bytes
from pocoloco.methods.pocoloco.fitting import CodeFit, fit_outfit_code
from pocoloco.methods.pocoloco.sampling import check_finish, sample_clouds, sampler_for
from pocoloco.methods.pocoloco.training import PocoLocoTask
from pocoloco.models.conditioning import OutfitBound, phenotype_vector
from pocoloco.models.denoisers import build_denoiser

__all__ = ["DEFAULT_POLISH_T", "LoadedDenoiser", "PocoLocoMethod", "load_denoiser", "polish_link"]

#: the step a distilled model's teacher re-noises its answer to for the last call (1-based). Chamfer
#: hardly tells 5 to 30 apart (quarter ``medium`` v3, t = 10 / 20 / 30 / 50: x1.016 / 1.008 / 1.009 /
#: 1.022 of the 25-call teacher on test); the proper score does: on the v4 standard reference sets
#: t = 5 beats 20 by 2.0 / 1.7 % (test / held out, paired per pose, 0 s shared) at +0.3 % Chamfer, the
#: teacher's x0 estimate at t = 20 (a noise of ~13 mm) shrinking the cloud by ~1 mm
#: (docs/lab/fast.md; benchmarks/results/fast_polish_t/)
DEFAULT_POLISH_T = 5


class PocoLocoMethod(Method):
    """A trained PocoLoco denoiser (EMA weights by default) with its normalisation and train config
    (``config.denoiser`` the architecture, ``config.schedule`` / ``prediction_type`` what the
    samplers need). ``weights``: "ema" or "raw"."""

    kind = "pocoloco"
    deterministic = False
    train_config = PocoLocoTrainConfig

    def __init__(self, *args, weights: str = "ema", **kwargs):
        super().__init__(*args, **kwargs)
        self.weights = weights
        self.outfits = list(self.meta.get("outfits", []))
        #: (teacher denoiser, t) of a distilled student whose teacher makes the last call, or None
        self.polish: tuple[torch.nn.Module, int] | None = None

    @property
    def needs_body(self) -> bool:  # type: ignore[override]
        """Trained with ``--body-points``: sampling needs the posed body, not only the joints."""
        return bool(self.config.body_points)

    def body_points_of(self, pose: Pose) -> np.ndarray | None:
        """The (K, 3) posed-body vertices this model reads from ``pose`` (None: a model without them)."""
        if not self.needs_body:
            return None
        if pose.body_vertices is None:
            raise ValueError(f"{pose.source}: this PocoLoco model (--body-points) needs the posed body, not only joints")
        ids = self.meta.get("body_point_ids")
        if not ids or len(ids) != self.config.body_points:
            raise ValueError(f"{self.path / META_FILE}: body_point_ids missing or not {self.config.body_points} long")
        return np.asarray(pose.body_vertices, np.float32)[np.asarray(ids)]

    # ------------------------------------------------------------------------------ outfits
    @property
    def knows_who_wears_what(self) -> bool:
        """Conditioned on an outfit code and / or the body shape (else: the paper's joints only)."""
        return bool(self.config.outfit_codes or self.config.body_shape)

    def outfit_names(self) -> list[str]:
        return [o["name"] for o in self.outfits] if self.knows_who_wears_what else []

    # ------------------------------------------------------------------- unseen outfits
    @property
    def fits_outfits(self) -> bool:  # type: ignore[override]
        """Outfit codes, and a diffusion model: a fit uses the diffusion loss, which a distilled
        student (``student_calls``) was not trained on."""
        return bool(self.config.outfit_codes) and not self.config.student_calls

    def fit_points(self) -> int:
        """Scan points per cloud the fit uses by default: the training N."""
        return int(self.config.num_points)

    def fit_outfit(self, scans: Sequence[tuple[np.ndarray, np.ndarray | None, Pose]], steps: int = 400,
                   lr: float | None = None, progress=None, shape: Sequence[float] | None = None,
                   seed: int = 0, init: torch.Tensor | None = None, anchor: float = 0.0,
                   labels=None) -> CodeFit:  # fmt: skip
        """Fit a new outfit code to ``scans`` [(points (P, 3), normals or None, pose)], the network
        frozen, from ``init`` (default the mean code) with an optional pull ``anchor`` to it
        (:func:`~pocoloco.methods.pocoloco.fitting.fit_outfit_code`). ``labels`` are not used."""
        return fit_outfit_code(self.model, self.normalisation, self.config,
                               [(points, pose.joints, self.body_points_of(pose)) for points, _, pose in scans],
                               shape=shape if self.config.body_shape else None, steps=steps,
                               lr=1e-2 if lr is None else lr, seed=seed, init=init, anchor=anchor,
                               progress=progress)  # fmt: skip

    def mean_outfit_code(self) -> torch.Tensor:
        """The mean of the trained outfits' codes (D,): where ``fit --start mean`` starts."""
        return self.model.who.outfit_embed.weight.detach().mean(0)

    def outfit_code(self, outfit: int) -> torch.Tensor:
        """Outfit ``outfit``'s code (D,): where ``fit --start nearest`` starts."""
        return self.model.who.outfit_embed.weight.detach()[self.outfit_id(outfit)].clone()

    def add_outfit(self, code: torch.Tensor, entry: dict[str, Any]) -> int:
        """Append a fitted outfit (its code and its ``meta.json`` entry); returns its id."""
        new_id = self.model.who.add_outfit(code)
        self.model.config = self.config.denoiser.replace(num_outfits=new_id + 1)
        self.config = self.config.replace(denoiser=self.model.config)
        self.outfits.append({"id": new_id, **entry})
        self.meta["outfits"] = self.outfits
        return new_id

    def denoiser_for(self, outfit: int | None, code: torch.Tensor | None = None, network: torch.nn.Module | None = None):
        """The network (``network``: another of the same conditioning, e.g. the finishing teacher)
        with ``outfit`` (its code and body shape) bound in, called like a joints-only denoiser (what
        the apps run); the network itself for a joints-only model."""
        model = self.model if network is None else network
        if self.needs_body:
            raise ValueError("this PocoLoco model also needs the posed body (--body-points): completion, editing and "
                             "animation take models conditioned on joints (and outfit) only; use pocoloco sample / eval")  # fmt: skip
        if not self.knows_who_wears_what:
            self.outfit_id(outfit)  # any outfit is a one-line error
            return OutfitBound(model, None) if self.motion_window else model  # (its motion is set per pose)
        if outfit is None:
            raise ValueError(f"--outfit is required (this PocoLoco checkpoint knows outfits {', '.join(self.outfit_names())})")
        kw = self.condition(outfit)
        return OutfitBound(model, None if code is not None else kw["outfit"], kw["shape"], code=code)

    def point_prior(self, outfit: int | None) -> PointPrior:
        """The apps' hook: the denoiser with ``outfit`` bound in (:meth:`denoiser_for`), its
        normalisation, schedule and parametrisation (and a distilled student's finishing teacher,
        bound the same way)."""
        c = self.config
        polish = None if self.polish is None else (self.denoiser_for(outfit, network=self.polish[0]), self.polish[1])
        return PointPrior(self.denoiser_for(outfit), self.normalisation, NoiseSchedule.from_kind(c.schedule, c.num_timesteps),
                          c.prediction_type, int(c.denoiser.point_channels), int(c.denoiser.num_joints),
                          int(c.student_calls), float(c.student_renoise), polish)  # fmt: skip

    def condition(self, outfit: int | None) -> dict[str, Any]:
        """``sample_clouds`` keyword arguments (``outfit``, ``shape``) for outfit id ``outfit``."""
        if not self.knows_who_wears_what:
            return {}
        return {"outfit": outfit if self.config.outfit_codes else None,
                "shape": phenotype_vector(self.outfits[outfit].get("phenotype")) if self.config.body_shape else None}  # fmt: skip

    @classmethod
    def from_checkpoint(cls, ck: Checkpoint, device: str = "cpu", use_ema: bool = True) -> PocoLocoMethod:
        try:
            config = PocoLocoTrainConfig.from_dict(ck.config)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{ck.path / META_FILE}: corrupt train config ({e})") from None
        model = build_denoiser(config.architecture, config.denoiser)
        ema = use_ema and ck.ema_state is not None
        try:
            model.load_state_dict(ck.ema_state if ema else ck.model_state)
        except RuntimeError as e:
            raise ValueError(f"{ck.path}: weights do not match the stored config ({one_line(e)})") from None
        weights = "ema" if use_ema else "raw"
        method = cls(model.to(device).eval(), config, ck.normalisation, ck.path, ck.step, ck.meta, weights=weights)
        if ck.meta.get("polish"):
            method.polish = _polishing_teacher(ck, config, device)
        return method

    @classmethod
    def presets(cls) -> dict[str, PocoLocoTrainConfig]:
        return TRAIN_PRESETS

    @classmethod
    def training_task(cls, config: PocoLocoTrainConfig, data: str | Path) -> TrainingTask:
        return PocoLocoTask(config, data)

    @property
    def title(self) -> str:
        return "PocoLoco"

    def check_options(self, options: SamplerOptions) -> None:
        sampler_for(self.config, options.sampler, options.steps, self.polish is not None)
        check_finish(self.config, options.finish_t)

    def bytes_per_point(self) -> int:
        """The latent denoiser's point stream: ``point_width`` x (``point_mlp_ratio`` + 2) float32
        activations plus the position encoding per point (measured: ~1.4 KiB at ``latent_small``'s
        64 x 4, estimated 1.8 KiB); the all-points transformer keeps the default."""
        per_point = point_bytes(self.config)
        return super().bytes_per_point() if per_point is None else per_point

    def load_pose(self, spec: str, outfit: int | None = None, frame_id: int | None = None,
                  any_pose: bool = False) -> Pose:  # fmt: skip
        if self.needs_body:  # the posed body, as POP and CloSET take it
            if frame_id is not None:
                raise ValueError(f"{spec}: --frame-id does not apply to a model that needs the posed body")
            outfit = self.outfit_of_pose_spec(spec, outfit)  # demo:NAME: posed as its outfit
            pheno = self.outfits[outfit].get("phenotype", {}) if outfit is not None else {}
            return load_body_pose(spec, pheno, False)
        joints = load_joints(spec, frame_id, self.config.denoiser.num_joints, any_pose=any_pose)
        subject = subject_of_spec(str(spec))  # None unless a DATASET:... frame
        velocity = frame_velocity(dataset_frame_path(str(spec)), joints) if self.config.joint_velocity and subject else None
        motion = self.motion_of_frame(dataset_frame_path(str(spec))) if subject else demo_motion(str(spec), self.motion_window)
        return Pose(joints, subject=outfit_of_spec(str(spec)), source=str(spec), velocity=velocity, motion=motion)

    def pose_from_frame(self, path: str | Path, subject: str, frame=None, cache: MeanShapeCache | None = None) -> Pose:
        if self.needs_body:
            pose = pose_from_frame(path, subject, False, frame=frame)
        else:
            pose = super().pose_from_frame(path, subject, frame=frame, cache=cache)
        if self.config.joint_velocity:  # the motion, from the neighbouring frame of the sequence
            pose.velocity = frame_velocity(path, pose.joints)
        pose.motion = self.motion_of_frame(path)
        return pose

    @property
    def motion_window(self) -> float:  # type: ignore[override]
        return float(self.config.motion_window)

    def predict(self, pose: Pose, num_points: int, seeds: Sequence[int] = (0,), outfit: int | None = None,
                options: SamplerOptions = SamplerOptions(), code: torch.Tensor | None = None) -> SampledClouds:  # fmt: skip
        """``code``: an outfit code (D,) to use instead of ``outfit``'s (a fit; the body shape still
        comes from ``outfit``)."""
        if self.knows_who_wears_what:
            outfit = self.default_outfit(pose) if outfit is None else self.outfit_id(outfit)
        else:
            self.outfit_id(outfit)  # a joints-only model: any outfit is a one-line error
        kw = self.condition(outfit)
        if code is not None:
            if not self.fits_outfits:
                raise ValueError("this PocoLoco model has no outfit codes (train it with --outfit-codes)")
            kw = {**kw, "outfit": None, "code": torch.as_tensor(code).reshape(-1)}
        return sample_clouds(self.model, self.normalisation, self.config, np.asarray(pose.joints), len(seeds),
                             num_points, sampler=options.sampler, steps=options.steps, seeds=list(seeds),
                             batch_size=options.batch_size, progress=options.progress, clip=options.clip,
                             bf16=options.bf16, body=self.body_points_of(pose),
                             velocity=pose.velocity if self.config.joint_velocity else None,
                             motion=pose.motion if self.config.motion_window else None, polish=self.polish,
                             finish=options.finish_t, **kw)  # fmt: skip

    def sample_settings(self, options: SamplerOptions, num_points: int) -> dict[str, Any]:
        sampler, steps = sampler_for(self.config, options.sampler, options.steps, self.polish is not None)
        c = self.config
        grid = polished_grid(c.num_timesteps, steps, int(c.student_calls)) if self.polish else None
        own = grid or (sampling_grid(c.num_timesteps, steps, int(c.student_calls)) if c.student_calls else None)
        return {"preset": self.config.preset, "weights": self.weights, "sampler": sampler, "steps": steps,
                **({"student_timesteps": own} if own else {}),
                **({"polish": {"with": self.meta["polish"].get("ckpt"), "t": self.polish[1]}} if grid else {}),
                **({"finish_t": options.finish_t} if options.finish_t is not None else {}),
                "batch_size": options.batch_size, "clip": options.clip, "bf16": options.bf16,
                **({"even_candidates": self.even_candidates(num_points)} if options.even else {})}  # fmt: skip

    def even_candidates(self, num_points: int) -> int:
        """4 N up to 4,096 points, 2 N beyond: farthest-point sampling keeps stray samples first, and
        more candidates hold more of them (against the whole scan at 10K, test frames: 2 N -0.08 cm,
        4 N +0.00, at half the time; held out 2 N +0.10; at 2,048: 4 N -0.37, 2 N -0.27; BENCHMARKS
        "Evenly spread clouds")."""
        return (4 if num_points <= 4096 else 2) * int(num_points)


def _polishing_teacher(ck: Checkpoint, config: PocoLocoTrainConfig, device: str) -> tuple[torch.nn.Module, int]:
    """(teacher denoiser, t) from a student's ``meta["polish"]`` = {ckpt, meta_sha256, t}
    (``pocoloco export-model --polish-with``): the teacher loaded by its name (a shipped model) or
    folder, checked against the digest recorded at export and against the student's network
    (the same conditioning, so that it reads the student's condition); one-line errors."""
    ref = ck.meta["polish"]
    name, t = ref.get("ckpt"), ref.get("t")
    if not name or not isinstance(t, int) or not 1 <= t <= config.num_timesteps or not config.student_calls:
        raise ValueError(f"{ck.path / META_FILE}: corrupt polish entry {ref!r} (a distilled model's teacher, by name, "
                         f"with t in [1, {config.num_timesteps}])")  # fmt: skip
    source = load_linked(ck.path, ref, "pocoloco", "its teacher", "the export",
                         "export it again with `pocoloco export-model --polish-with`")  # fmt: skip
    teacher = PocoLocoMethod.from_checkpoint(source, device=device)
    if teacher.config.student_calls or teacher.config.denoiser != config.denoiser or \
            teacher.normalisation != ck.normalisation:  # fmt: skip
        raise ValueError(f"{ck.path}: {name} is not this student's teacher (another network, conditioning or "
                         f"normalisation)")  # fmt: skip
    return teacher.model, int(t)


def polish_link(student: str | Path | Checkpoint, teacher: str, t: int = DEFAULT_POLISH_T) -> dict[str, Any]:
    """The ``meta["polish"]`` entry that makes ``teacher`` finish a distilled ``student``'s clouds at
    1-based step ``t`` (``pocoloco export-model --polish-with``): the teacher's name (``default`` for
    a shipped model, else its folder's absolute path), its meta.json digest and t; checked as at load.
    ``student``: its path or its loaded checkpoint."""
    if isinstance(student, Checkpoint):
        check_model_kind(student.path, student.model_kind, "pocoloco")
        ck = student
    else:
        ck = load_checkpoint(student, expect_model="pocoloco", training_state=False)
    config = PocoLocoTrainConfig.from_dict(ck.config)
    if not config.student_calls:
        raise ValueError(f"{ck.path}: --polish-with is for a distilled model (pocoloco distill); this one is a "
                         f"diffusion model")  # fmt: skip
    teacher_ck = load_checkpoint(resolve_ckpt_arg(teacher), expect_model="pocoloco", training_state=False)
    entry = {**link_to(teacher_ck.path, teacher_ck.meta, "export it first"), "t": int(t)}
    _polishing_teacher(replace(ck, meta={**ck.meta, "polish": entry}), config, "cpu")  # the checks of loading
    return entry


class LoadedDenoiser(NamedTuple):
    """What :func:`load_denoiser` returns; unpacks as ``model, normalisation, config``."""

    model: Any
    normalisation: Any
    config: PocoLocoTrainConfig


def load_denoiser(path: str | Path, use_ema: bool = True, device: str = "cpu") -> LoadedDenoiser:
    """The trained PocoLoco denoiser of a checkpoint / run folder (EMA weights by default), its
    normalisation and train config: the three things :func:`~pocoloco.methods.pocoloco.sample_clouds`
    and the apps take. (``pocoloco.methods.load_method`` gives the same as a :class:`PocoLocoMethod`.)"""
    m = PocoLocoMethod.from_checkpoint(load_checkpoint(path, expect_model="pocoloco", training_state=False),
                                       device=device, use_ema=use_ema)  # fmt: skip
    return LoadedDenoiser(m.model, m.normalisation, m.config)
