"""POP (Ma et al. 2021) behind the :class:`~pocoloco.methods.base.Method` interface, and its training
task for the shared loop.

Prediction: the query points are the valid pixels of the UV query map; to give N points POP uses
the training map (resolution Rq) if it has >= N valid pixels, else the smallest finer map that
does, and keeps N of them drawn without replacement (seeded). On a finer map the displacements
and normals are interpolated from those decoded at the training pixels
(:meth:`~pocoloco.models.pop.POP.decode_interpolated`): the decoder takes any UV, but only the
training pixels' are as accurate.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from pocoloco.body.surface import BodySurface, largest_component_faces
from pocoloco.data.dataset import frame_history
from pocoloco.data.motion_window import augmented_window
from pocoloco.data.poses import Pose, dataset_frame_path, demo_motion, subject_of_spec
from pocoloco.methods.pop.data import collate_pop, make_optimizer, pop_motion_features, pop_sample_from_frame
from pocoloco.methods.pop.fitting import POPFit, fit_unseen_outfit
from pocoloco.methods.pop.losses import check_scan, normal_weight_at, pop_losses
from pocoloco.methods.skinned import SkinnedMethod, SkinnedTask, SkinnedTrainConfig
from pocoloco.models.pop import POP, POPBatch, POPQuery

__all__ = ["POPMethod", "POPTask", "pop_query_for"]


def pop_query_for(model: POP, num_points: int, seed: int) -> tuple[POPQuery, int]:
    """N POP query points: the valid pixels of the training UV query map, or of the smallest
    finer map with >= N valid pixels, of which N are drawn without replacement (seeded).
    Returns the query and the map resolution used."""
    q = model.query_points()
    R = model.config.query_resolution
    while len(q) < num_points:
        if R >= 4096:
            raise ValueError(f"--points {num_points}: POP's UV map gives at most {len(q)} points")
        R = int(math.ceil(R * math.sqrt(num_points / max(len(q), 1)) * 1.02))
        q = model.query_points(R)
    idx = np.sort(np.random.default_rng([int(seed), 5]).choice(len(q), num_points, replace=False))
    return q.subset(idx), R


class POPMethod(SkinnedMethod):
    """A trained POP: UV position-map UNet + geometric feature tensor per outfit + point decoder."""

    kind = "pop"
    trains_in_bf16 = False  # the fused BatchNorm + softplus decoder runs in float32
    #: points off the training UV map (N > its valid pixels): ``"interpolate"`` the displacements
    #: decoded at the training pixels, or ``"decode"`` at the finer map's UVs (before 2026-11-27;
    #: ~13 % farther from the scan per point, BENCHMARKS "POP at more points than its UV map")
    finer_map: str = "interpolate"

    @classmethod
    def _model_from_state(cls, config: SkinnedTrainConfig, state: dict[str, torch.Tensor], meta: dict[str, Any]) -> POP:
        return POP.from_state(config.net_config(), state, int(meta["num_vertices"]))

    @classmethod
    def training_task(cls, config: SkinnedTrainConfig, data: str | Path) -> POPTask:
        return POPTask(config, data)

    @property
    def title(self) -> str:
        return "POP"

    @property
    def needs_mean_shape(self) -> bool:
        return self.config.net.get("pose_input") == "mean_shape"

    def query_surface(self, num_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        q, _ = pop_query_for(self.model, num_points, seed)
        return q.face_idx, q.barycentric

    def _predict_one(self, pose: Pose, outfit: int, num_points: int, seed: int, code: torch.Tensor | None = None):
        body, vt = self.body_tensors(pose)
        outfit_t = torch.tensor([int(outfit)], dtype=torch.long, device=body.device)
        if self.needs_mean_shape:
            if pose.mean_shape is None:
                raise ValueError(f"{pose.source}: POP needs the posed mean-shape body for its pose input")
            pv = torch.from_numpy(np.asarray(pose.mean_shape, np.float32))[None].to(body.device)
        else:
            pv = body
        query, resolution = pop_query_for(self.model, num_points, seed)
        if self.finer_map not in ("interpolate", "decode"):
            raise ValueError(f"finer_map must be 'interpolate' or 'decode', got {self.finer_map!r}")
        interpolate = self.finer_map == "interpolate" and resolution != self.model.config.query_resolution
        motion = None
        if self.motion_window and pose.motion is not None:
            motion = torch.from_numpy(pop_motion_features(pose.motion, np.asarray(pose.joints)))[None].to(body.device)
        return self.model(POPBatch(pv, body, vt, outfit_t, motion=motion), geom=code, query=query,
                          interpolate=interpolate)  # fmt: skip

    @property
    def motion_window(self) -> float:  # type: ignore[override]
        return float(self.config.net.get("motion_window", 0.0))

    def pose_from_frame(self, path, subject: str, frame=None, cache=None) -> Pose:
        pose = super().pose_from_frame(path, subject, frame=frame, cache=cache)
        pose.motion = self.motion_of_frame(path)
        return pose

    def load_pose(self, spec: str, outfit: int | None = None, frame_id: int | None = None,
                  any_pose: bool = False) -> Pose:  # fmt: skip
        pose = super().load_pose(spec, outfit, frame_id, any_pose)
        if self.motion_window and subject_of_spec(str(spec)):  # a DATASET: frame: its motion before it
            pose.motion = self.motion_of_frame(dataset_frame_path(str(spec)))
        else:  # a demo pose ships its motion
            pose.motion = demo_motion(str(spec), self.motion_window)
        return pose

    # ------------------------------------------------------------------- unseen outfits (Eq. 7)
    fits_outfits = True
    fit_needs_normals = True

    def fit_points(self) -> int:
        """Scan points the fit uses by default: as many as the model saw per frame in training."""
        return int(self.config.num_points)

    def fit_outfit(self, scans, steps: int = 400, lr: float | None = None, progress=None, shape=None,
                   seed: int = 0, init: torch.Tensor | None = None, anchor: float = 0.0,
                   labels=None) -> POPFit:  # fmt: skip
        """Fit a new outfit to one scan ``scans = [(points (P, 3), unit normals (P, 3), pose)]`` (world
        frame of the pose): only a new geometric feature tensor is optimised, from ``init`` (default:
        the mean of the trained outfits); the network is frozen. POP's Eq. 7 has no pull to the
        start: ``anchor`` must be 0 (:func:`~pocoloco.methods.pop.fitting.fit_unseen_outfit`,
        paper Eq. 7 fits one scan). ``labels`` (the scans' point labels) are not used."""
        if len(scans) != 1:
            raise ValueError(f"POP fits an outfit to one scan (paper Eq. 7), got {len(scans)}")
        if anchor:
            raise ValueError("POP's fit (paper Eq. 7) has no pull to the start: --anchor is for PocoLoco")
        scan_points, scan_normals, pose = scans[0]
        root = np.asarray(pose.joints[0], np.float32)
        pv = pose.mean_shape if self.needs_mean_shape else pose.body_vertices - root
        return fit_unseen_outfit(self.model, scan_points - root, scan_normals, pv, pose.body_vertices - root,
                                 pose.vtransf, steps=steps, lr=self.config.lr_codes if lr is None else lr, init=init,
                                 progress=progress, weights=self.config.pop_loss_weights())  # fmt: skip

    def mean_outfit_code(self) -> torch.Tensor:
        """The mean of the trained outfits' feature tensors (1, Cg, Ri, Ri): ``fit --start mean``."""
        return self.model.geom.detach().mean(0, keepdim=True)

    def outfit_code(self, outfit: int) -> torch.Tensor:
        """Outfit ``outfit``'s feature tensor (1, Cg, Ri, Ri): ``fit --start nearest``."""
        i = self.outfit_id(outfit)
        return self.model.geom.detach()[i:i + 1].clone()

    def add_outfit(self, code: torch.Tensor, entry: dict[str, Any]) -> int:
        """Append a fitted outfit (its features and its ``meta.json`` entry); returns its id."""
        new_id = self.model.add_outfit(code)
        self.outfits.append({"id": new_id, **entry})
        self.meta["outfits"] = self.outfits
        return new_id

    def sample_settings(self, options, num_points: int) -> dict[str, Any]:
        if options.even and self.even_candidates(num_points) > num_points:  # what predict_clouds keeps by FPS
            return {"query_points": "every valid pixel of the training UV map, N of them kept by farthest-point sampling "
                                    "of their spots on the posed body"}  # fmt: skip
        return {"query_points": "N of the valid pixels of the UV query map (finer than the training map if needed, "
                                "displacements interpolated from the training pixels), without replacement"}  # fmt: skip

    def even_candidates(self, num_points: int) -> int:
        """Every pixel of the training map while N fits in it; beyond it N: the finer map's pixels
        POP draws are already ~96 % of a grid, and farthest-point sampling over more of them reaches
        their worst-decoded rims first (M2S +0.2 cm; BENCHMARKS "Evenly spread clouds")."""
        pixels = len(self.model.query_points())
        return pixels if num_points <= pixels else int(num_points)


class POPTask(SkinnedTask):
    """POP's training: paper Eq. 3 (:func:`~pocoloco.methods.pop.losses.pop_losses`), Adam 3e-4 for
    the network and 5e-4 for the geometric features; the normal term from ``normal_start``. The pose
    encoder sees the posed mean-shape body (presets ``small`` / ``paper``; ``tiny`` feeds the
    subject's own body so tests need no anny)."""

    method = POPMethod

    def build_model(self) -> nn.Module:
        first = self.assets[next(iter(self.assets))]
        faces = np.asarray(first.faces, np.int64)
        surface = BodySurface(faces, first.uv, np.asarray(first.uv_faces, np.int64), largest_component_faces(faces))
        return POP(self.config.net_config(), surface, len(self.assets), int(first.template.shape[0]))

    def make_optimizer(self, model: nn.Module) -> torch.optim.Optimizer:
        c = self.config
        return make_optimizer(model, c.lr, c.lr_codes, c.lr * c.motion_lr_scale if c.motion_lr_scale != 1.0 else None)

    @property
    def needs_mean_shape(self) -> bool:
        return self.config.net.get("pose_input") == "mean_shape"

    def make_batch(self, items, step: int):
        c = self.config
        samples = []
        for it in items:
            rng = np.random.default_rng([c.seed, 1, it.position])
            motion = self.motion_features(it) if c.motion_window else None
            samples.append(pop_sample_from_frame(it.frame, self.outfits[it.subject], c.num_points, rng, it.mean_shape,
                                                 num_vertices=int(self.model.num_vertices), src=os.fspath(it.path),
                                                 motion=motion))  # fmt: skip
        return collate_pop(samples)

    def motion_features(self, item) -> np.ndarray:
        """(J, F) the step frame's motion window, augmented, or at rest (zeros) for a
        ``history_dropout`` share of frames; all from (seed, 4, position)."""
        c = self.config
        rng = np.random.default_rng([c.seed, 4, item.position])
        history, frame = frame_history(item.path)
        window = augmented_window(history, frame, c.motion_window, rng)
        features = pop_motion_features(window, np.asarray(item.frame.joints))
        return features * 0.0 if rng.random() < c.history_dropout else features

    def fresh_keys(self, missing: list[str]) -> bool:
        """``--init-from`` a pose-only POP into a ``--motion-window`` run: the zero-initialised motion
        encoder keeps its own weights, so the run starts at that POP."""
        return bool(self.config.motion_window) and all(k.startswith("motion_in.") for k in missing)

    def loss(self, net: nn.Module, batch: POPBatch, step: int, rank: int):
        weights = self.config.pop_loss_weights()
        wn = normal_weight_at(weights, self.config.normal_start, step)
        check_scan(batch.scan_points, batch.scan_normals, batch.body_vertices.shape[0], need_normals=True)
        out = net(batch)
        losses = pop_losses(out, batch.scan_points, batch.scan_normals, weights, normal_weight=wn)
        logs = losses.as_floats()
        total = losses.total
        if wn == 0 and isinstance(net, DistributedDataParallel):
            # DDP all-reduces every parameter's gradient: before the normal term is on, the normal
            # head gets an explicit zero one (single-process runs leave it None, as they always did)
            total = total + 0.0 * out.normals.sum()
        return total, {"loss": logs.pop("total"), **logs}
