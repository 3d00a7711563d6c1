"""PocoLoco's training configuration and named presets (``paper``, ``small``, ``tiny``).

What the paper's recipe is (Adam 2e-4, batch 16, fp32, constant lr, 10K points) and what the
``small`` preset changes so the model trains in hours on a 2-core CPU are in the presets' comments.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from pocoloco.data.motion_window import check_motion_training
from pocoloco.diffusion.schedules import PREDICTION_TYPES
from pocoloco.engine.trainer import LR_SCHEDULES, LoopSettings, check_lr_schedule
from pocoloco.models.denoisers import ARCHITECTURES, denoiser_config_from_dict
from pocoloco.models.latent import LATENT_PRESETS, LatentDenoiserConfig
from pocoloco.models.pocoloco import DENOISER_PRESETS, PocoLocoDenoiserConfig
from pocoloco.utils.config import Config

__all__ = ["LR_SCHEDULES", "SCHEDULE_KINDS", "TRAIN_PRESETS", "PocoLocoTrainConfig", "train_preset"]

SCHEDULE_KINDS = ("four", "linear", "cosine")
#: TrainConfig fields that may change when resuming (they do not affect the optimisation; the
#: learning-rate curve's fields may too, if the steps already taken keep their rates: trainer.LR_FIELDS).
RESUMABLE_CHANGES = frozenset({"steps", "ckpt_every", "sample_every", "log_every", "sample_steps", "keep_checkpoints",
                               "num_workers"})  # fmt: skip


@dataclass(frozen=True)
class PocoLocoTrainConfig(Config):
    """Everything that defines a training run (the data folder and the device excepted).

    preset: name of the denoiser preset (``tiny`` / ``small`` / ``paper``); denoiser: its config
    (with any overrides). steps: total optimiser steps. batch_size: clouds per step *per process*.
    num_points: N points per cloud. lr / weight_decay / adam_betas / adam_eps: AdamW.
    warmup_steps: linear LR warm-up; lr_schedule: ``constant``, ``cosine`` (to 0 at ``steps``) or
    ``wsd`` (warm-up, stable, decay: constant, then linear to 0 over the last ``decay_steps``; a
    constant run resumed as ``wsd`` is the same run until its decay starts, so a long constant run
    can be cooled down from any checkpoint).
    grad_clip: max gradient L2 norm (None: no clipping). ema_decay: EMA decay (warm-up applied).
    schedule / num_timesteps: the beta schedule ("four" = PocoLoco's quartic). prediction_type:
    what the network predicts. min_snr_gamma: min-SNR-gamma weighting (None: plain L_simple).
    bf16: bf16 autocast for the forward pass. seed: everything random derives from it.
    ckpt_every / sample_every / log_every: periods in steps (0 disables checkpoints / samples).
    sample_steps: DDIM steps of the periodic samples. keep_checkpoints: how many step folders to
    keep. num_workers: DataLoader worker processes (0 = load in the main process).
    architecture: the denoiser network (:mod:`pocoloco.models.denoisers`): ``"transformer"`` (the
    paper's, O(N^2) attention over points) or ``"latent"`` (read / compute / write through latent
    tokens, linear in N); ``denoiser`` is that network's config.
    outfit_codes / body_shape: condition on who wears what (:mod:`pocoloco.models.conditioning`):
    one learned code per subject of the dataset (its outfit) and / or the subject's anny
    phenotype; False / False is the paper's joints-only model. subjects: train on these subjects
    only (None: all), e.g. one model per subject as in the paper. body_points: K vertices of the
    posed body (fixed ids, farthest-point sampled on the first subject's template) given to the
    latent denoiser besides the joints (0: none, the paper's template-free input; the model then
    needs a posed body to sample, like POP and CloSET). canonical_heading: turn every frame about
    the vertical axis to face one way before normalising (:class:`pocoloco.data.dataset.Normalisation`;
    not in the paper), so the model need not learn each facing direction; sampling turns the result
    back. joint_velocity: latent presets: also condition on the joints' velocities (difference to the
    neighbouring frame of the sequence; not in the paper: the cloth follows the motion); sampling
    takes them from a dataset frame, else the body is taken at rest. motion_window: latent presets:
    also condition on the last this-many seconds of the body's motion (issue 41: 8 samples per
    second, :func:`pocoloco.data.motion_window.motion_features`; 0: the pose alone); training
    augments the windows (time-warp, jitter, noise) and replaces a ``history_dropout`` share of them
    by a body at rest, so the same model also samples without motion. motion_lr_scale: the motion
    encoder's learning rate in multiples of ``lr`` (a fine-tune from a pose-only model: its
    zero-initialised encoder has everything to learn, the rest little). freeze_trunk: with
    ``motion_window``, train the motion encoder alone and keep every other weight as initialised (a
    fine-tune from a pose-only model that cannot over-fit its trunk: what it gains over that model
    is the window's alone).
    student_calls: 0 for a diffusion model; N > 0 for a student distilled from one
    (``pocoloco distill``, issue 42, :mod:`pocoloco.methods.pocoloco.distill`): its x0 estimate at the
    timesteps of the N-call grid is the teacher's deterministic answer, and it samples with the
    few-step sampler (:mod:`pocoloco.diffusion.few_step`) in N or fewer calls. distill_chamfer /
    distill_huber: the student's loss, per-point pseudo-Huber (``distill_huber``: its c, normalised
    units) plus ``distill_chamfer`` x the Chamfer distance to the teacher's cloud. distill_renoised:
    the share of a batch's later-grid draws made as the re-noising sampler makes them (the
    teacher's answer noised afresh to the grid time). distill_renoised_targets: their target,
    "answer" (the teacher's answer itself, scored by Chamfer alone) or "ode" (the teacher's
    deterministic answer from the re-noised state, made once with the pairs). distill_set: weight
    of the set-level term (teacher pairs made with several draws per frame): the energy distance
    between a frame's student answers and the teacher's, on the judge's probe-distance embedding
    (per-draw regression pulls the draws to their mean; this keeps their spread). distill_chain:
    weight of the chain term: each pair's initial noise taken down the student's own
    ``distill_chain_calls``-call sampler (fresh re-noising between calls), its answer scored
    against the teacher's answer for that noise by Chamfer (the last call learns to mend what the
    earlier ones left, as the few-call sampler hands it). distill_chain_grad: "last" (a gradient
    through the chain's last call) or "all" (through every call: the earlier calls also learn to
    hand the last a state it can mend). distill_set_calls: the calls of the chain the set-level
    term runs (0, the default: the grid the student samples with by default, a teacher's finishing
    call after it; 1 .. student_calls: its sampling grid of that many calls, e.g. 2 to keep the
    2-call draws' spread; shared with the chain term's chain where the two grids are the same).
    student_renoise: the few-step sampler's share of fresh noise when re-noising (1: the
    consistency models' multistep sampler, 0: deterministic; :mod:`pocoloco.diffusion.few_step`).
    """

    preset: str = "small"
    denoiser: PocoLocoDenoiserConfig | LatentDenoiserConfig = dataclasses.field(
        default_factory=lambda: DENOISER_PRESETS["small"])
    model: str = "pocoloco"
    steps: int = 20_000
    batch_size: int = 16
    num_points: int = 1024
    lr: float = 2e-4
    weight_decay: float = 0.0
    adam_betas: tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8
    warmup_steps: int = 500
    lr_schedule: str = "constant"
    decay_steps: int = 0
    grad_clip: float | None = 1.0
    ema_decay: float = 0.999
    schedule: str = "four"
    num_timesteps: int = 1000
    prediction_type: str = "epsilon"
    min_snr_gamma: float | None = None
    bf16: bool = False
    seed: int = 0
    ckpt_every: int = 1000
    sample_every: int = 1000
    log_every: int = 10
    sample_steps: int = 25
    keep_checkpoints: int = 3
    num_workers: int = 0
    architecture: str = "transformer"
    outfit_codes: bool = False
    body_shape: bool = False
    subjects: tuple[str, ...] | None = None
    body_points: int = 0
    canonical_heading: bool = False
    joint_velocity: bool = False
    motion_window: float = 0.0
    history_dropout: float = 0.15
    motion_lr_scale: float = 1.0
    freeze_trunk: bool = False
    student_calls: int = 0
    distill_chamfer: float = 1.0
    distill_huber: float = 0.01
    distill_renoised: float = 0.0
    distill_renoised_targets: str = "answer"
    distill_set: float = 0.0
    distill_chain: float = 0.0
    distill_chain_calls: int = 2
    distill_chain_grad: str = "last"
    distill_set_calls: int = 0
    student_renoise: float = 1.0

    def __post_init__(self):
        if self.model != "pocoloco":
            raise ValueError(f"model must be 'pocoloco' for a PocoLocoTrainConfig, got {self.model!r}")
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"architecture must be one of {tuple(ARCHITECTURES)}, got {self.architecture!r}")
        want = ARCHITECTURES[self.architecture][0]
        if not isinstance(self.denoiser, want):
            raise ValueError(f"denoiser must be a {want.__name__} for architecture {self.architecture!r}, "
                             f"got {type(self.denoiser).__name__}")  # fmt: skip
        positive = ("steps", "batch_size", "num_points", "num_timesteps", "log_every", "sample_steps",
                    "keep_checkpoints")
        for name in positive:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.body_points and self.architecture != "latent":
            raise ValueError("body_points (--body-points) needs the latent denoiser (e.g. --preset latent_small)")
        if self.joint_velocity and self.architecture != "latent":
            raise ValueError("joint_velocity (--joint-velocity) needs the latent denoiser (e.g. --preset latent_small)")
        if self.motion_window and self.architecture != "latent":
            raise ValueError("motion_window (--motion-window) needs the latent denoiser (e.g. --preset latent_small)")
        check_motion_training(self.motion_window, self.history_dropout, self.motion_lr_scale)
        if self.freeze_trunk and not self.motion_window:
            raise ValueError("freeze_trunk (--freeze-trunk) trains the motion encoder alone: it needs --motion-window")
        if not (0 <= self.distill_renoised <= 1 and 0 <= self.student_renoise <= 1):
            raise ValueError(f"distill_renoised and student_renoise must be in [0, 1], got {self.distill_renoised}, "
                             f"{self.student_renoise}")  # fmt: skip
        if self.distill_renoised_targets not in ("answer", "ode"):
            raise ValueError(f"distill_renoised_targets (--renoised-targets) must be answer or ode, got "
                             f"{self.distill_renoised_targets!r}")  # fmt: skip
        if self.distill_renoised_targets == "ode" and not self.distill_renoised > 0:
            raise ValueError("--renoised-targets ode: no re-noised draws to give them to; set --renoised-share > 0")
        if not (self.distill_set >= 0 and math.isfinite(self.distill_set)):
            raise ValueError(f"distill_set (--set-weight) must be a number >= 0, got {self.distill_set}")
        if not (self.distill_chain >= 0 and math.isfinite(self.distill_chain)):
            raise ValueError(f"distill_chain (--chain-weight) must be a number >= 0, got {self.distill_chain}")
        if self.distill_chain and not 2 <= self.distill_chain_calls <= max(self.student_calls, 2):
            raise ValueError(f"distill_chain_calls (--chain-calls) must be in [2, {max(self.student_calls, 2)}] (the "
                             f"student's calls), got {self.distill_chain_calls}")  # fmt: skip
        if self.distill_set and not 0 <= self.distill_set_calls <= self.student_calls:
            raise ValueError(f"distill_set_calls (--set-calls) must be in [1, {self.student_calls}] (the student's "
                             f"calls) or 0 (its default sampler), got {self.distill_set_calls}")  # fmt: skip
        if self.distill_chain_grad not in ("last", "all"):
            raise ValueError(f"distill_chain_grad (--chain-grad) must be last or all, got {self.distill_chain_grad!r}")
        if self.student_calls < 0 or self.distill_chamfer < 0 or not self.distill_huber > 0:
            raise ValueError(f"student_calls and distill_chamfer must be >= 0 and distill_huber > 0, got "
                             f"{self.student_calls}, {self.distill_chamfer}, {self.distill_huber}")  # fmt: skip
        for name in ("warmup_steps", "ckpt_every", "sample_every", "num_workers", "body_points"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ValueError(f"lr must be a positive number, got {self.lr}")
        if self.weight_decay < 0:
            raise ValueError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if len(self.adam_betas) != 2 or not all(0 <= b < 1 for b in self.adam_betas):
            raise ValueError(f"adam_betas must be two numbers in [0, 1), got {self.adam_betas}")
        check_lr_schedule(self.lr_schedule, self.decay_steps, self.steps)
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ValueError(f"grad_clip must be > 0 or None, got {self.grad_clip}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.schedule not in SCHEDULE_KINDS:
            raise ValueError(f"schedule must be one of {SCHEDULE_KINDS}, got {self.schedule!r}")
        if self.prediction_type not in PREDICTION_TYPES:
            raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {self.prediction_type!r}")
        if self.min_snr_gamma is not None and not self.min_snr_gamma > 0:
            raise ValueError(f"min_snr_gamma must be > 0 or None, got {self.min_snr_gamma}")
        if self.sample_steps > self.num_timesteps:
            raise ValueError(f"sample_steps ({self.sample_steps}) must be <= num_timesteps ({self.num_timesteps})")
        object.__setattr__(self, "adam_betas", tuple(float(b) for b in self.adam_betas))
        if self.subjects is not None:
            if isinstance(self.subjects, str) or not self.subjects or len(set(self.subjects)) != len(self.subjects):
                raise ValueError(f"subjects must be distinct names, got {self.subjects!r}")
            object.__setattr__(self, "subjects", tuple(sorted(str(s) for s in self.subjects)))

    def loop(self) -> LoopSettings:
        """What the training loop reads (:class:`pocoloco.engine.trainer.LoopSettings`)."""
        return LoopSettings(
            preset=self.preset, steps=self.steps, lr=self.lr, seed=self.seed, warmup_steps=self.warmup_steps,
            lr_schedule=self.lr_schedule, decay_steps=self.decay_steps, ema_decay=self.ema_decay,
            grad_clip=self.grad_clip, bf16=self.bf16, ckpt_every=self.ckpt_every, sample_every=self.sample_every,
            log_every=self.log_every, keep_checkpoints=self.keep_checkpoints, num_workers=self.num_workers,
        )  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PocoLocoTrainConfig:
        """Inverse of :meth:`to_dict` (:class:`~pocoloco.utils.config.Config`); the denoiser's config
        class follows ``architecture`` (checkpoints written before it existed hold the transformer)."""
        d = dict(d)
        if isinstance(d.get("denoiser"), dict):
            d["denoiser"] = denoiser_config_from_dict(d.get("architecture", "transformer"), d["denoiser"])
        return super().from_dict(d)


def point_bytes(config: PocoLocoTrainConfig) -> int | None:
    """Working memory of one output point while sampling with the latent denoiser: its point stream,
    ``point_width`` x (``point_mlp_ratio`` + 2) float32 activations plus the position encoding
    (measured: ~1.4 KiB at ``latent_small``'s 64 x 4, estimated 1.8 KiB); None for the all-points
    transformer (its attention is not linear in N)."""
    d = config.denoiser
    if config.architecture != "latent":
        return None
    return int(4 * (d.point_width * (d.point_mlp_ratio + 2) + 64))


def training_point_bytes(config: PocoLocoTrainConfig) -> int | None:
    """Memory one training point takes in a step (forward activations kept for backward): about
    3 x depth x :func:`point_bytes` (measured peak RSS of one step at B = 8, N = 16K: 20.9 KB for
    ``latent_small``, estimated 21.5; 44.4 KB for ``latent_base``, estimated 46.1)."""
    per_point = point_bytes(config)
    return None if per_point is None else 3 * config.denoiser.depth * per_point


TRAIN_PRESETS: dict[str, PocoLocoTrainConfig] = {
    # the paper's settings (Sec. 5.1 + the authors' code): width 512, 8 layers, Adam 2e-4,
    # batch 16, 10K points, constant lr, no clipping; EMA is ours (it does not change training)
    "paper": PocoLocoTrainConfig(
        preset="paper", denoiser=DENOISER_PRESETS["paper"], steps=1_000_000, batch_size=16, num_points=10_000,
        lr=2e-4, weight_decay=0.0, warmup_steps=0, grad_clip=None, ema_decay=0.9999, ckpt_every=5000,
        sample_every=5000, log_every=50, sample_steps=50,
    ),
    # what this 2-core CPU can train in hours
    "small": PocoLocoTrainConfig(
        preset="small", denoiser=DENOISER_PRESETS["small"], steps=20_000, batch_size=16, num_points=512,
        lr=5e-4, weight_decay=0.01, warmup_steps=200, lr_schedule="constant", grad_clip=1.0, ema_decay=0.999,
        ckpt_every=250, sample_every=1000, log_every=10, sample_steps=25,
    ),
    # the latent read / compute / write network (linear in N) at the paper's width and depth budget,
    # trained at 2K points (it samples any N)
    "latent_paper": PocoLocoTrainConfig(
        preset="latent_paper", architecture="latent", denoiser=LATENT_PRESETS["paper"], steps=1_000_000,
        batch_size=16, num_points=2048, lr=2e-4, weight_decay=0.0, warmup_steps=0, grad_clip=None,
        ema_decay=0.9999, ckpt_every=5000, sample_every=5000, log_every=50, sample_steps=50,
    ),
    # the latent network sized for this CPU, trained at 512 points (it samples any N: at equal
    # wall-clock 512 beat 1,024 training points at 2K and 10K sampled points, BENCHMARKS.md)
    "latent_small": PocoLocoTrainConfig(
        preset="latent_small", architecture="latent", denoiser=LATENT_PRESETS["small"], steps=20_000,
        batch_size=16, num_points=512, lr=5e-4, weight_decay=0.01, warmup_steps=200, lr_schedule="constant",
        grad_clip=1.0, ema_decay=0.999, ckpt_every=250, sample_every=1000, log_every=10, sample_steps=25,
    ),
    # the latent network sized for one GPU and still shippable (``LATENT_PRESETS["base"]``): batch 64
    # (larger batches: --batch-size, whose learning rate follows the sqrt rule, `pocoloco train --lr-scaling`)
    "latent_base": PocoLocoTrainConfig(
        preset="latent_base", architecture="latent", denoiser=LATENT_PRESETS["base"], steps=20_000,
        batch_size=64, num_points=512, lr=5e-4, weight_decay=0.01, warmup_steps=300, lr_schedule="constant",
        grad_clip=1.0, ema_decay=0.999, ckpt_every=1000, sample_every=2000, log_every=25, sample_steps=25,
    ),
    "latent_tiny": PocoLocoTrainConfig(
        preset="latent_tiny", architecture="latent", denoiser=LATENT_PRESETS["tiny"], steps=20, batch_size=2,
        num_points=256, lr=1e-3, weight_decay=0.0, warmup_steps=2, grad_clip=1.0, ema_decay=0.99, ckpt_every=10,
        sample_every=10, log_every=1, sample_steps=3,
    ),
    # tests and smoke runs: seconds
    "tiny": PocoLocoTrainConfig(
        preset="tiny", denoiser=DENOISER_PRESETS["tiny"], steps=20, batch_size=2, num_points=256,
        lr=1e-3, weight_decay=0.0, warmup_steps=2, grad_clip=1.0, ema_decay=0.99, ckpt_every=10,
        sample_every=10, log_every=1, sample_steps=3,
    ),
}  # fmt: skip


def train_preset(name: str, **overrides) -> PocoLocoTrainConfig:
    """A named training preset with field overrides; a one-line error for unknown names."""
    if name not in TRAIN_PRESETS:
        raise ValueError(f"unknown training preset {name!r}; choose one of: {', '.join(TRAIN_PRESETS)}")
    return TRAIN_PRESETS[name].replace(**overrides)
