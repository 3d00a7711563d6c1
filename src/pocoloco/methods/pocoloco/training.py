"""PocoLoco's training task for the shared loop (:mod:`pocoloco.engine.trainer`).

The model learns p(X | K) with the DDPM objective (PocoLoco paper, Eq. 7; Ho et al. 2020,
Eq. 14): each step draws a batch of B clouds X (B, N, 3) with their joints K (B, J, 3), one
timestep t (B,) and noise per sample, and regresses the denoiser's output on the target of the
chosen parametrisation (:func:`pocoloco.diffusion.diffusion_loss`).

Randomness: the frames of step s and their point subsets come from
:class:`~pocoloco.data.step_batches.StepBatches`; t and the noise from a generator seeded by
``seed_of(seed, 2, step, rank)``. The optimiser is AdamW (weight decay only on matrices; 0 in the
``paper`` preset, i.e. Adam). Previews: DDIM samples of the EMA model for two test frames.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pocoloco.data.dataset import Normalisation, PointCloudDataset
from pocoloco.data.format import DatasetLayout, read_subject
from pocoloco.data.pack import PackedDataset, is_pack, open_point_clouds
from pocoloco.data.step_batches import StepBatches
from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, diffusion_loss, sample_ddim
from pocoloco.engine.checkpoint import Checkpoint
from pocoloco.engine.trainer import TrainingTask, fused_optimizer_options
from pocoloco.methods.pocoloco.config import RESUMABLE_CHANGES, PocoLocoTrainConfig, training_point_bytes
from pocoloco.models.conditioning import SHAPE_KEYS, PoseCondition, phenotype_vector
from pocoloco.models.denoisers import build_denoiser
from pocoloco.ops.sampling import farthest_point_sampling
from pocoloco.utils.seeding import seed_of
from pocoloco.viz.render import render_grid

__all__ = ["PocoLocoTask"]


class PocoLocoTask(TrainingTask):
    """Train the PocoLoco denoiser of ``config`` on the ``train`` split of the dataset at ``data``."""

    kind = "pocoloco"
    resumable_changes = RESUMABLE_CHANGES

    def __init__(self, config: PocoLocoTrainConfig, data: str | Path):
        self.data = data
        if config.body_points and is_pack(data):
            raise ValueError(f"{data}: a training pack holds no posed bodies: train --body-points on the dataset folder")
        self.body_point_ids = body_point_ids(data, config) if config.body_points else None
        # a dataset folder or a training pack (pocoloco.data.pack): the same items
        self.dataset = open_point_clouds(data, "train", num_points=None, with_normals=config.denoiser.point_channels == 6,
                                         random_subsample=False, subjects=config.subjects,
                                         body_point_ids=self.body_point_ids,
                                         heading=config.canonical_heading, velocity=config.joint_velocity,
                                         **({"motion_window": config.motion_window} if config.motion_window else {}))  # fmt: skip
        self.normalisation = self.dataset.normalisation
        # who wears what: one outfit per subject (ids in the dataset's sorted subject order) and its
        # anny phenotype; the denoiser's config is resolved here so the checkpoint records it
        names = sorted(config.subjects) if config.subjects else list(self.dataset.subject_names)
        # the dataset's subject ids (all subjects of the card) -> outfit ids (the trained subjects)
        self.outfit_of_subject = torch.tensor([names.index(s) if s in names else -1 for s in self.dataset.subject_names])
        card_subjects = self.dataset.card["subjects"]
        self.outfits = [{"id": i, "name": s, "phenotype": dict(card_subjects[s].get("phenotype") or {}),
                         "garment_kind": card_subjects[s].get("garment_kind")} for i, s in enumerate(names)]  # fmt: skip
        self.shapes = torch.tensor([phenotype_vector(o["phenotype"]) for o in self.outfits], dtype=torch.float32)
        self.config = config.replace(denoiser=config.denoiser.replace(
            num_outfits=len(names) if config.outfit_codes else 0,
            shape_dim=len(SHAPE_KEYS) if config.body_shape else 0,
            **({"body_points": config.body_points} if config.body_points else {}),
            **({"joint_velocity": True} if config.joint_velocity else {}),
            **({"motion_window": config.motion_window} if config.motion_window else {})))  # fmt: skip
        self.schedule = NoiseSchedule.from_kind(config.schedule, config.num_timesteps)
        self.generator: torch.Generator | None = None
        self._preview_frames: list[dict[str, Any]] | None = None

    def initial_state(self, state: dict[str, torch.Tensor], ck) -> dict[str, torch.Tensor]:
        """``--init-from`` a checkpoint with other outfits: the outfit codes of this run's outfits are
        the source's codes of the same names (new names: the source's mean code)."""
        source = [o["name"] for o in ck.meta.get("outfits", [])]
        mine = [o["name"] for o in self.outfits]
        out = dict(state)
        for key, codes in state.items():
            if key.endswith("outfit_embed.weight") and source != mine and len(codes) == len(source):
                out[key] = torch.stack([codes[source.index(n)] if n in source else codes.mean(0) for n in mine])
        return out

    def fresh_keys(self, missing: list[str]) -> bool:
        """``--init-from`` a pose-only checkpoint into a ``--motion-window`` run: the motion encoder
        keeps its own (zero-output) initialisation, so the run starts exactly at that model."""
        return bool(self.config.motion_window) and all(k.startswith("motion_in.") for k in missing)

    def step_bytes(self) -> int | None:
        per_point = training_point_bytes(self.config)
        return None if per_point is None else per_point * self.config.batch_size * self.config.num_points

    def build_model(self) -> nn.Module:
        return build_denoiser(self.config.architecture, self.config.denoiser)

    def make_optimizer(self, model: nn.Module) -> torch.optim.Optimizer:
        """AdamW; the motion encoder's parameters in their own groups at ``lr x motion_lr_scale``;
        with ``freeze_trunk`` only they are trained (every other parameter's ``requires_grad`` off)."""
        c = self.config
        groups: dict[tuple[bool, bool], list[nn.Parameter]] = {}
        for name, p in model.named_parameters():  # (motion encoder?, weight decay?) -> parameters
            motion = name.startswith("motion_in.")
            if c.freeze_trunk and not motion:
                p.requires_grad_(False)  # before any DDP wrap: the trunk keeps its initial weights
                continue
            groups.setdefault((motion and c.motion_lr_scale != 1.0, p.ndim >= 2), []).append(p)
        return torch.optim.AdamW([{"params": ps, "weight_decay": c.weight_decay if decay else 0.0,
                                   **({"lr": c.lr * c.motion_lr_scale} if motion else {})}
                                  for (motion, decay), ps in sorted(groups.items())],
                                 lr=c.lr, betas=c.adam_betas, eps=c.adam_eps, **fused_optimizer_options(model))  # fmt: skip

    def step_batches(self, model: nn.Module, rank: int, world: int) -> StepBatches:
        c = self.config
        return StepBatches(self.dataset, c.batch_size, c.num_points, c.seed, c.steps, rank, world)

    def condition(self, joints: torch.Tensor, subject: torch.Tensor, body: torch.Tensor | None = None,
                  velocity: torch.Tensor | None = None, motion: torch.Tensor | None = None
                  ) -> torch.Tensor | PoseCondition:  # fmt: skip
        """The denoiser's conditioning for frames of these subject ids (B,): the joints alone, or
        with the outfit ids, body shapes, posed bodies (B, K, 3), joint velocities (B, J, 3) and
        motion-window features (B, J, F) the config asks for."""
        c = self.config
        if not (c.outfit_codes or c.body_shape or c.body_points or c.joint_velocity or c.motion_window):
            return joints
        outfit = self.outfit_of_subject[subject.cpu()].to(joints.device)
        return PoseCondition(joints, outfit if c.outfit_codes else None,
                             self.shapes.to(joints.device)[outfit] if c.body_shape else None,
                             body=body if c.body_points else None,
                             velocity=velocity if c.joint_velocity else None,
                             motion=motion if c.motion_window else None)  # fmt: skip

    def loss(self, net: nn.Module, batch: dict[str, torch.Tensor], step: int, rank: int):
        c = self.config
        x0 = batch["points"]  # (B, N, C)
        if self.generator is None or self.generator.device != x0.device:
            self.generator = torch.Generator(x0.device)
        motion = batch.get("motion")
        if motion is not None and c.history_dropout:  # history dropout: some frames as at rest
            self.generator.manual_seed(seed_of(c.seed, 5, step, rank))
            keep = torch.rand(motion.shape[0], generator=self.generator, device=motion.device) >= c.history_dropout
            motion = motion * keep[:, None, None].to(motion.dtype)
        cond = self.condition(batch["joints"], batch["subject"], batch.get("body"), batch.get("velocity"), motion)
        self.generator.manual_seed(seed_of(c.seed, 2, step, rank))
        weighting = "min_snr" if c.min_snr_gamma is not None else "none"
        loss, logs = diffusion_loss(net, x0, cond, self.schedule, c.prediction_type, weighting,
                                    c.min_snr_gamma or 5.0, generator=self.generator,
                                    as_tensors=x0.device.type != "cpu")  # no per-step host sync on a GPU; fmt: skip
        return loss, {"loss": logs["loss"], **{k: v for k, v in logs.items() if k.startswith("mse")}}

    def check_resume(self, ck: Checkpoint) -> None:
        if ck.normalisation != self.normalisation:
            raise ValueError(f"{self.data}: dataset normalisation differs from the checkpoint's ({ck.path})")
        if ck.meta.get("body_point_ids") != self.body_point_ids:
            raise ValueError(f"{self.data}: the body point ids differ from the checkpoint's ({ck.path})")
        stored = [o["name"] for o in ck.meta.get("outfits", [])]
        if stored and stored != [o["name"] for o in self.outfits]:
            raise ValueError(f"{self.data}: subjects {[o['name'] for o in self.outfits]} differ from the checkpoint's "
                             f"outfits {stored} ({ck.path})")  # fmt: skip

    def checkpoint_extra(self, model: nn.Module) -> dict[str, Any]:
        return {"outfits": self.outfits, **({"body_point_ids": self.body_point_ids} if self.body_point_ids else {})}

    def preview(self, model: nn.Module, step: int, out: Path, device: torch.device) -> Path:
        if self._preview_frames is None:
            self._preview_frames = _sample_frames(self.data, self.config, self.dataset)
        return _render_samples(model, self.schedule, self.config, self.normalisation, self._preview_frames, out, step,
                               device, self.condition)  # fmt: skip


def body_point_ids(data, config: PocoLocoTrainConfig) -> list[int]:
    """``config.body_points`` vertex ids spread over the body: farthest-point sampled (torch backend,
    deterministic, first vertex 0) on the rest-pose template of the first trained subject (anny
    bodies share one topology, so the ids mean the same place on every subject)."""
    layout = DatasetLayout(data)
    subjects = sorted(config.subjects) if config.subjects else layout.subjects()
    template = read_subject(layout.subject_path(subjects[0])).template  # (V, 3)
    if config.body_points > len(template):
        raise ValueError(f"--body-points {config.body_points}: the body has only {len(template)} vertices")
    idx = farthest_point_sampling(torch.from_numpy(np.asarray(template, np.float32))[None], config.body_points,
                                  backend="torch")  # fmt: skip
    return [int(i) for i in idx[0]]


def _sample_frames(data, config: PocoLocoTrainConfig, train_set: PointCloudDataset | PackedDataset
                   ) -> list[dict[str, Any]]:  # fmt: skip
    """Two frames (test split if it has any, else train) with fixed point subsets, for the periodic samples."""
    try:
        ds = open_point_clouds(data, "test", num_points=None, random_subsample=False, subjects=train_set.subject_names,
                               body_point_ids=train_set.body_point_ids, heading=train_set.normalisation.heading,
                               velocity=train_set.velocity)  # fmt: skip
    except ValueError:
        ds = train_set
    picks = sorted({0, len(ds) // 2})
    frames = []
    for i in picks:
        item = ds[i]
        n = item["points"].shape[0]
        sel = np.random.default_rng([config.seed, 3, i]).choice(n, min(n, config.num_points), replace=False)
        frames.append({"points": item["points"][sel], "joints": item["joints"], "root": item["root"],
                       "angle": item["angle"], "velocity": item.get("velocity"), "key": item["frame_key"], "subject": item["subject"], "body": item.get("body")})  # fmt: skip
    return frames


@torch.no_grad()
def _render_samples(model: nn.Module, schedule: NoiseSchedule, config: PocoLocoTrainConfig, norm: Normalisation,
                    frames: list[dict[str, Any]], out: Path, step: int, device: torch.device,
                    condition=None) -> Path:  # fmt: skip
    """DDIM samples (``config.sample_steps`` steps, fixed seeds) from ``model`` for ``frames``; a PNG
    grid. ``condition(joints, subject ids)``: the conditioning (default: the joints alone)."""
    C = config.denoiser.point_channels
    joints = torch.stack([f["joints"] for f in frames]).to(device)  # (B, J, 3)
    body = torch.stack([f["body"] for f in frames]).to(device) if frames[0].get("body") is not None else None
    vel = torch.stack([f["velocity"] for f in frames]).to(device) if frames[0].get("velocity") is not None else None
    cond = joints if condition is None else condition(joints, torch.tensor([f["subject"] for f in frames]), body, vel)
    rng = PerSampleRNG([config.seed * 1000 + k for k in range(len(frames))], device=device)
    noise = rng.randn((config.num_points, C), device=device)  # (B, N, C)
    was_training = model.training
    model.eval()
    x = sample_ddim(model, schedule, noise, cond, prediction_type=config.prediction_type,
                    steps=config.sample_steps, rng=rng)  # fmt: skip
    model.train(was_training)
    clouds = []
    for k, f in enumerate(frames):
        root, angle = f["root"].numpy(), f["angle"].numpy()
        gt = norm.denormalise(f["points"].numpy(), root, angle)
        pred = norm.denormalise(x[k, :, :3].float().cpu().numpy(), root, angle)
        clouds += [(gt, None, None, f"data {f['key']}"), (pred, None, None, f"sample, step {step}")]
    return Path(render_grid(clouds, out / "samples" / f"step_{step:06d}.png", views=("front", "side"), ncols=2))
