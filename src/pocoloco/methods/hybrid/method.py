"""The hybrid method behind the :class:`~pocoloco.methods.base.Method` interface: skinned where the
cloth follows the body, generated where it hangs free (the idea of FreeCloth, Ye et al. CVPR 2025,
with a learnt map and a generative free region; implemented from the idea, no code copied).

A hybrid checkpoint holds a POP network (the attached region: a deterministic residual on the
posed body), a PocoLoco point denoiser (the free region) and the per-outfit free-region maps
(:mod:`pocoloco.methods.hybrid.regions`). For N points of outfit o it draws
``round(point_share[o] * N)`` points from the denoiser that fall in the outfit's free region (their
nearest posed body vertex is free) and the rest from POP's points in the attached region, so the
hypotheses of one pose differ in the free region only.

A hybrid is *assembled* from trained checkpoints (``pocoloco hybrid``): the denoiser may be one
trained on the whole body or one fine-tuned on a pack of free-region points
(:mod:`pocoloco.methods.hybrid.training`, ``pocoloco hybrid --fine-tune MINUTES``); the two networks
share no parameter and are trained apart (POP on the whole body, whose free-region points the
hybrid also uses).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn

from pocoloco.body.surface import vertex_normals
from pocoloco.data.poses import MeanShapeCache, Pose, dataset_frame_path, demo_motion, subject_of_spec
from pocoloco.engine.checkpoint import Checkpoint, one_line
from pocoloco.engine.links import load_linked
from pocoloco.engine.trainer import TrainingTask
from pocoloco.methods.base import AnimationPrior, Method, SampledClouds, SamplerOptions
from pocoloco.methods.hybrid.regions import (MIN_FREE_SHARE, FreeRegionMaps, inside_depth, point_regions,
                                             scan_vertex_votes, stored_vertex_share)
from pocoloco.methods.pocoloco.config import PocoLocoTrainConfig
from pocoloco.methods.pocoloco.method import PocoLocoMethod
from pocoloco.methods.pop.method import POPMethod, pop_query_for
from pocoloco.methods.skinned import SkinnedTrainConfig
from pocoloco.models.denoisers import build_denoiser
from pocoloco.utils.config import Config

__all__ = ["HybridConfig", "HybridMethod", "HybridModel"]

#: draws of the free-region generator per cloud before its points are topped up by repetition
FREE_DRAWS = 4
#: POP is queried at most at this many times its training pixels (or the points asked) per region
MAX_QUERY_FACTOR = 8
#: the fewest points the animation's generator draws per frame (an outfit with no free region)
ANIMATION_MIN_PRIOR_POINTS = 64


@dataclass(frozen=True)
class HybridConfig(Config):
    """What a hybrid checkpoint was made of. attached / free: the POP and PocoLoco training configs
    (``to_dict``) of its two networks; margin / threshold: the free-region rule; sources: the
    checkpoints it was assembled from (provenance). generator_share: the share of the free region's
    points the denoiser draws; POP draws the rest there (its own points in that region); 1 = the
    free region is wholly generated. inside_tolerance: generated points deeper inside the posed
    body than this (metres) are drawn again (None: kept; the scans hold none). area_weighted: POP's
    points are drawn by the body area their UV pixels stand for (False: every pixel alike). far:
    points farther than this from the posed body (metres) belong to the free region whatever their
    nearest vertex (a hem swinging past an attached hand or foot; None: the nearest vertex alone).
    trust: generated points farther than this (metres) from POP's own points in the free region are
    drawn again: the generator's hypotheses stay within that distance of the regressor's (None: off)."""

    model: str = "hybrid"
    preset: str = "assembled"
    attached: dict[str, Any] = field(default_factory=dict)
    free: dict[str, Any] = field(default_factory=dict)
    margin: float = 0.03
    threshold: float = 0.5
    sources: dict[str, str] = field(default_factory=dict)
    generator_share: float = 1.0
    inside_tolerance: float | None = None
    area_weighted: bool = True
    far: float | None = None
    trust: float | None = None

    def __post_init__(self):
        if self.model != "hybrid":
            raise ValueError(f"a HybridConfig is of model 'hybrid', got {self.model!r}")
        if not 0.0 <= self.generator_share <= 1.0:
            raise ValueError(f"generator share must be in [0, 1], got {self.generator_share}")
        if self.inside_tolerance is not None and not 0.0 <= self.inside_tolerance < math.inf:
            raise ValueError(f"inside tolerance must be a distance >= 0 (metres), got {self.inside_tolerance}")
        if self.far is not None and not 0.0 < self.far < math.inf:
            raise ValueError(f"far must be a distance > 0 (metres), got {self.far}")
        if self.trust is not None and not 0.0 < self.trust < math.inf:
            raise ValueError(f"trust must be a distance > 0 (metres), got {self.trust}")

    def attached_config(self) -> SkinnedTrainConfig:
        return SkinnedTrainConfig.from_dict(self.attached)

    def free_config(self) -> PocoLocoTrainConfig:
        return PocoLocoTrainConfig.from_dict(self.free)


class HybridModel(nn.Module):
    """The hybrid's networks and maps: ``attached`` (POP), ``free`` (a PocoLoco denoiser), buffers
    ``vertex_share`` (O, V) and ``point_share`` (O,) of :class:`FreeRegionMaps`."""

    def __init__(self, attached: nn.Module, free: nn.Module, vertex_share: torch.Tensor, point_share: torch.Tensor):
        super().__init__()
        self.attached, self.free = attached, free
        self.register_buffer("vertex_share", torch.as_tensor(vertex_share, dtype=torch.float32))
        self.register_buffer("point_share", torch.as_tensor(point_share, dtype=torch.float32))


@dataclass
class HybridCode:
    """One hybrid outfit as ``pocoloco fit`` handles it: POP's geometric features ``attached``
    (1, Cg, Ri, Ri), the generator's outfit code ``free`` (D,) (None for a joints-only generator),
    and the outfit's free-region map: ``vertex_share`` (V,) and ``point_share``."""

    attached: torch.Tensor
    free: torch.Tensor | None
    vertex_share: np.ndarray
    point_share: float


@dataclass
class HybridFit:
    """A fitted hybrid outfit (``features``: :class:`HybridCode`) and the losses of both fits,
    POP's steps then the generator's."""

    features: HybridCode
    losses: list[float]


class HybridMethod(Method):
    """A hybrid model (module docstring): ``attached`` (a :class:`POPMethod`) and ``free`` (a
    :class:`PocoLocoMethod`) over the networks of :class:`HybridModel`, and the maps."""

    kind = "hybrid"
    needs_body = True
    train_config = HybridConfig

    def __init__(self, model: HybridModel, config: HybridConfig, normalisation, path: Path, step: int,
                 meta: dict[str, Any]):  # fmt: skip
        super().__init__(model, config, normalisation, path, step, meta)
        self.outfits = list(meta.get("outfits", []))
        self.attached = POPMethod(model.attached, config.attached_config(), normalisation, path, step,
                                  {"outfits": self.outfits, "num_vertices": meta.get("num_vertices")})  # fmt: skip
        self.free = PocoLocoMethod(model.free, config.free_config(), normalisation, path, step,
                                   {k: meta[k] for k in ("free_outfits", "body_point_ids") if k in meta}
                                   | {"outfits": meta.get("free_outfits", [])})  # fmt: skip
        self.maps = FreeRegionMaps(tuple(o["name"] for o in self.outfits), model.vertex_share.cpu().numpy(),
                                   model.point_share.cpu().numpy(), config.margin, config.threshold,
                                   np.asarray(meta.get("map_frames", [0] * len(self.outfits)), np.int32),
                                   config.far)  # fmt: skip

    # ------------------------------------------------------------------ loading and training
    @classmethod
    def from_checkpoint(cls, ck: Checkpoint, device: str = "cpu", use_ema: bool = True) -> HybridMethod:
        state = ck.ema_state if (use_ema and ck.ema_state is not None) else ck.model_state
        if ck.meta.get("linked"):
            state = {**state, **_linked_state(ck)}
        try:
            config = HybridConfig.from_dict(ck.config)
            att_cfg, free_cfg = config.attached_config(), config.free_config()
            part = lambda prefix: {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}  # noqa: E731
            attached = POPMethod._model_from_state(att_cfg, part("attached."), ck.meta)
            free = build_denoiser(free_cfg.architecture, free_cfg.denoiser)
            free.load_state_dict({k: v.float() for k, v in part("free.").items()})
            vertex_share = torch.from_numpy(stored_vertex_share(state, int(ck.meta["num_vertices"])))
            model = HybridModel(attached, free, vertex_share, state["point_share"].float())
        except (KeyError, TypeError, RuntimeError, ValueError) as e:
            raise ValueError(f"{ck.path}: corrupt hybrid checkpoint ({one_line(e)})") from None
        if len(ck.meta.get("outfits", [])) != model.vertex_share.shape[0]:
            raise ValueError(f"{ck.path}: meta lists {len(ck.meta.get('outfits', []))} outfits but the maps hold "
                             f"{model.vertex_share.shape[0]}")  # fmt: skip
        return cls(model.to(device).eval(), config, ck.normalisation, ck.path, ck.step, ck.meta)

    @classmethod
    def presets(cls) -> dict[str, Any]:
        return {}

    @classmethod
    def preset(cls, name: str, **overrides) -> Any:
        raise ValueError("a hybrid model is assembled from a trained POP and a trained PocoLoco: "
                         "`pocoloco hybrid --attached POP_CKPT --free POCOLOCO_CKPT --data DATA --out DIR`")  # fmt: skip

    @classmethod
    def training_task(cls, config: Any, data: str | Path) -> TrainingTask:
        cls.preset("")
        raise AssertionError  # pragma: no cover - preset raises

    # -------------------------------------------------------------------------- description
    @property
    def title(self) -> str:
        return "Hybrid"

    def info(self) -> dict[str, Any]:
        return {**super().info(), "free_point_share": {o["name"]: round(float(s), 4)
                                                       for o, s in zip(self.outfits, self.maps.point_share, strict=True)}}  # fmt: skip

    def outfit_names(self) -> list[str]:
        return [o["name"] for o in self.outfits]

    # -------------------------------------------------------------------------------- poses
    @property
    def motion_window(self) -> float:  # type: ignore[override]
        """The free generator's motion window, else the attached model's (a hybrid of two motion-aware
        models needs the same window for both: :meth:`assemble_hybrid` checks)."""
        return self.free.motion_window or self.attached.motion_window

    def load_pose(self, spec: str, outfit: int | None = None, frame_id: int | None = None,
                  any_pose: bool = False) -> Pose:  # fmt: skip
        pose = self.attached.load_pose(spec, outfit, frame_id, any_pose)
        if self.motion_window and pose.motion is None:
            pose.motion = (self.motion_of_frame(dataset_frame_path(str(spec))) if subject_of_spec(str(spec))
                           else demo_motion(str(spec), self.motion_window))  # fmt: skip
        return pose

    def pose_from_frame(self, path: str | Path, subject: str, frame=None, cache: MeanShapeCache | None = None) -> Pose:
        pose = self.attached.pose_from_frame(path, subject, frame=frame, cache=cache)
        pose.motion = self.motion_of_frame(path)
        return pose

    def pose_from_anny(self, pose: Pose, outfit: int | None) -> Pose:
        return self.attached.pose_from_anny(pose, outfit)

    # ------------------------------------------------------------------------- unseen outfits
    fits_outfits = True
    fit_needs_normals = True  # POP's point-to-plane loss

    def fit_points(self) -> int:
        return self.attached.fit_points()

    def outfit_code(self, outfit: int) -> HybridCode:
        """Outfit ``outfit``'s features, generator code and map: ``fit --start nearest``."""
        o = self.outfit_id(outfit)
        return HybridCode(self.attached.outfit_code(o), self._generator_code(o), self.maps.vertex_share[o].copy(),
                          self.maps.free_share_of(o))  # fmt: skip

    def mean_outfit_code(self) -> HybridCode:
        """The mean of the trained outfits' features, codes and maps: ``fit --start mean``."""
        return HybridCode(self.attached.mean_outfit_code(),
                          self.free.mean_outfit_code() if self.free.outfit_names() else None,
                          self.maps.vertex_share.mean(0), float(self.maps.point_share.mean()))  # fmt: skip

    def _generator_code(self, outfit: int) -> torch.Tensor | None:
        """The generator's code (D,) of ``outfit``; the mean of its codes when it never learnt this
        one (an outfit without a free region); None for a joints-only generator."""
        names = self.free.outfit_names()
        if not names:
            return None
        name = self.outfits[outfit]["name"]
        return self.free.outfit_code(names.index(name)) if name in names else self.free.mean_outfit_code()

    def fit_outfit(self, scans, steps: int = 400, lr: float | None = None, progress=None, shape=None,
                   seed: int = 0, init: HybridCode | None = None, anchor: float = 0.0,
                   labels=None) -> HybridFit:  # fmt: skip
        """Fit a new outfit to one scan ``[(points (P, 3), unit normals (P, 3), pose)]``, both networks
        frozen: POP's geometric features to the whole scan (POP Eq. 7; ``lr`` applies to it), and
        the generator's outfit code (diffusion loss, its own learning rate, ``anchor``) to the scan's
        points in the free region. The free-region map comes from the scan's labels (``labels``:
        [(P,) or None]; a body vertex is free when its nearest scan point is loose garment or
        farther than the maps' margin, the rule of :func:`learn_free_maps` on one frame), else it
        is the start's (``init``: the nearest trained outfit's, or the mean map); the free point
        share is the scan's own. ``steps`` each."""
        if len(scans) != 1:
            raise ValueError(f"the hybrid fits an outfit to one scan (its POP part, paper Eq. 7), got {len(scans)}")
        init = self.mean_outfit_code() if init is None else init
        points, normals, pose = scans[0]
        scan_labels = None if labels is None else labels[0]
        if scan_labels is not None:
            if len(scan_labels) != len(points):
                raise ValueError(f"the scan has {len(points)} points but {len(scan_labels)} labels")
            init = dataclasses.replace(init, vertex_share=scan_vertex_votes(points, scan_labels, pose.body_vertices,
                                                                            self.maps.margin))  # fmt: skip
        total = 2 * steps if init.free is not None else steps

        def phase(offset: int):
            if progress is None:
                return None
            return lambda done, n, loss: progress(offset + done, total, loss)

        attached = self.attached.fit_outfit([(points, normals, pose)], steps=steps, lr=lr, progress=phase(0),
                                            init=init.attached)  # fmt: skip
        free_mask = init.vertex_share > self.maps.threshold
        region = point_regions(points, pose.body_vertices, free_mask, self.config.far)
        share = float(region.mean())
        if share < MIN_FREE_SHARE:
            share = 0.0
        losses, code = list(attached.losses), init.free
        if init.free is not None and share > 0:
            fit = self.free.fit_outfit([(points[region], None, pose)], steps=steps, progress=phase(steps), shape=shape,
                                       seed=seed, init=init.free, anchor=anchor)  # fmt: skip
            losses += fit.losses
            code = fit.features
        return HybridFit(HybridCode(attached.features, code, np.asarray(init.vertex_share, np.float32), share), losses)

    def _meta_to_save(self) -> dict[str, Any]:
        """A saved hybrid holds both networks' weights: a linked one (``pocoloco hybrid --link``) is
        saved as a copy, since its networks (a fitted outfit's code, say) are no longer the linked
        checkpoints' (``unlinked_from`` names those)."""
        linked = self.meta.get("linked")
        if not linked:
            return self.meta
        return {**{k: v for k, v in self.meta.items() if k != "linked"},
                "unlinked_from": {part: ref.get("ckpt") for part, ref in linked.items()}}

    def add_outfit(self, code: HybridCode, entry: dict[str, Any]) -> int:
        """Append a fitted outfit to both networks and the maps; returns its id."""
        new_id = self.attached.add_outfit(code.attached, dict(entry))
        if code.free is not None:
            self.free.add_outfit(code.free, dict(entry))
            self.meta["free_outfits"] = self.free.outfits
            self.config = self.config.replace(free=self.free.config.to_dict())
        self.outfits = self.attached.outfits
        self.meta["outfits"] = self.outfits
        m = self.model
        m.vertex_share = torch.cat([m.vertex_share, torch.as_tensor(code.vertex_share, dtype=torch.float32)[None]])
        m.point_share = torch.cat([m.point_share, torch.tensor([code.point_share], dtype=torch.float32)])
        self.meta["map_frames"] = [*self.meta.get("map_frames", [0] * new_id), 1]
        self.maps = FreeRegionMaps(tuple(self.outfit_names()), m.vertex_share.cpu().numpy(),
                                   m.point_share.cpu().numpy(), self.maps.margin, self.maps.threshold,
                                   np.asarray(self.meta["map_frames"], np.int32), self.maps.far)  # fmt: skip
        return new_id

    # ---------------------------------------------------------------------------- predicting
    def check_options(self, options: SamplerOptions) -> None:
        self.free.check_options(options)

    def bytes_per_point(self) -> int:
        return max(self.attached.bytes_per_point(), self.free.bytes_per_point())

    def split(self, outfit: int, num_points: int, code: HybridCode | None = None) -> tuple[int, int]:
        """(attached, free) point counts of a cloud of ``num_points`` of ``outfit`` (or of a fitted
        ``code``)."""
        share = self.maps.free_share_of(outfit) if code is None else code.point_share
        free = int(round(share * num_points))
        return num_points - free, free

    def _free_mask(self, outfit: int, code: HybridCode | None = None) -> np.ndarray:
        """(V,) bool: the free region of ``outfit`` (or of a fitted ``code``)."""
        return self.maps.free(outfit) if code is None else code.vertex_share > self.maps.threshold

    def _free_outfit(self, outfit: int) -> int | None:
        names = self.free.outfit_names()
        if not names:
            return None  # a joints-only denoiser serves every outfit
        name = self.outfits[outfit]["name"]
        if name not in names:
            raise ValueError(f"{self.path}: outfit {name!r} has a free region but the free-region model never learnt it")
        return names.index(name)

    @torch.no_grad()
    def predict(self, pose: Pose, num_points: int, seeds: Sequence[int] = (0,), outfit: int | None = None,
                options: SamplerOptions = SamplerOptions(), code: HybridCode | None = None) -> SampledClouds:  # fmt: skip
        """One cloud per seed: the attached points (the same for every seed) and the free points of
        that seed, in the frame of ``pose`` (metres); no normals (the free region has none).
        ``code``: a fitted outfit (:class:`HybridCode`) in place of ``outfit``'s features and map
        (the body shape still comes from ``outfit``)."""
        outfit, n_gen = self._plan(pose, outfit, num_points, code)
        pop: dict[int, np.ndarray] = {}  # POP's clouds at this pose, shared by the parts below
        skinned = self._skinned_for(pose, outfit, num_points, code, pop=pop)  # shared by the hypotheses
        clouds = [skinned] * len(seeds)
        if n_gen:
            region = self._free_points(pose, outfit, self._free_mask(outfit, code), n_gen, seeds, options,
                                       None if code is None else code.free,
                                       None if code is None else code.attached, pop=pop,
                                       expected_rate=self.split(outfit, num_points, code)[1] / num_points)  # fmt: skip
            clouds = [np.concatenate([skinned, r]) for r in region]
        return SampledClouds(np.stack(clouds).astype(np.float32), None)

    def _plan(self, pose: Pose, outfit: int | None, num_points: int, code: HybridCode | None = None) -> tuple[int, int]:
        """(outfit id, points the generator draws) of a cloud, after the input checks."""
        if num_points < 1:
            raise ValueError(f"num_points must be >= 1, got {num_points}")
        if not pose.has_body:
            raise ValueError(f"{pose.source}: the hybrid needs the posed body (body_vertices / vtransf)")
        outfit = self.default_outfit(pose) if outfit is None else self.outfit_id(outfit)
        return outfit, int(round(self.config.generator_share * self.split(outfit, num_points, code)[1]))

    def _skinned_for(self, pose: Pose, outfit: int, num_points: int, code: HybridCode | None = None,
                     pop: dict[int, np.ndarray] | None = None) -> np.ndarray:  # fmt: skip
        """The POP part of a cloud of ``num_points``: the attached region's points and the free
        region's share POP draws (:meth:`_skinned_points`)."""
        n_att, n_free = self.split(outfit, num_points, code)
        n_gen = int(round(self.config.generator_share * n_free))
        return self._skinned_points(pose, outfit, self._free_mask(outfit, code), n_att, n_free - n_gen,
                                    None if code is None else code.attached, pop=pop)  # fmt: skip

    def _pop_points(self, pose: Pose, outfit: int, m: int, code: torch.Tensor | None,
                    pop: dict[int, np.ndarray] | None) -> np.ndarray:  # fmt: skip
        """POP's (m, 3) points at ``m`` query pixels (seed 0) for ``pose``; ``pop``: the clouds
        already predicted for this pose, outfit and code, by pixel count (filled here)."""
        if pop is not None and m in pop:
            return pop[m]
        pts = self.attached.predict(pose, m, seeds=(0,), outfit=outfit, code=code).points[0]
        if pop is not None:
            pop[m] = pts
        return pts

    def _kept(self, pose: Pose, free: np.ndarray, points: np.ndarray, normals: np.ndarray | None,
              reference: cKDTree | None = None) -> np.ndarray:  # fmt: skip
        """(M,) bool: which generated points (M, 3) the free region keeps (their nearest posed body
        vertex is free, or they lie farther than ``far`` from the body; with ``inside_tolerance``,
        they are no deeper inside the body; with ``trust``, they lie within it of ``reference``,
        POP's points in the region: :meth:`_reference`)."""
        keep = point_regions(points, pose.body_vertices, free, self.config.far)
        if normals is not None:
            keep &= inside_depth(points, pose.body_vertices, normals) <= self.config.inside_tolerance
        if reference is not None:
            keep &= reference.query(np.asarray(points, np.float64))[0] <= self.config.trust
        return keep

    def _reference(self, pose: Pose, outfit: int, free: np.ndarray, code: torch.Tensor | None = None,
                   pop: dict[int, np.ndarray] | None = None) -> cKDTree | None:  # fmt: skip
        """With ``trust``: a search tree over POP's points (at its training UV pixels) that fall in
        the free region, which the generated points must stay near; None without ``trust`` or when
        POP puts no point there. ``pop``: as in :meth:`_pop_points`."""
        if self.config.trust is None:
            return None
        pts = self._pop_points(pose, outfit, len(self.attached.model.query_points()), code, pop)
        ref = pts[point_regions(pts, pose.body_vertices, free, self.config.far)]
        return cKDTree(np.asarray(ref, np.float64)) if len(ref) else None

    def _normals(self, pose: Pose) -> np.ndarray | None:
        """The posed body's vertex normals when the inside test is on, else None."""
        if self.config.inside_tolerance is None:
            return None
        return vertex_normals(pose.body_vertices, self.attached.model.faces_np)

    def point_prior(self, outfit: int | None):
        raise ValueError("the hybrid cannot complete or edit point clouds (its generator draws the free region only); "
                         "it samples, scores and animates dataset sequences")  # fmt: skip

    def animation_prior(self, outfit: int | None, num_points: int) -> AnimationPrior:
        """The free-region generator as the animation's prior (its chain carries the generated
        points from frame to frame) and, per frame, the cloud made of its points that fall in the
        free region (drawn to the free share) and POP's points for that frame's posed body."""
        outfit = 0 if outfit is None else self.outfit_id(outfit)
        _, n_free = self.split(outfit, num_points)
        n_gen = int(round(self.config.generator_share * n_free))
        free = self.maps.free(outfit)

        def finish(pose: Pose, generated: np.ndarray, seed: int) -> np.ndarray:
            self._plan(pose, outfit, num_points)
            pop: dict[int, np.ndarray] = {}
            skinned = self._skinned_for(pose, outfit, num_points, pop=pop)
            if not n_gen:
                return skinned
            reference = self._reference(pose, outfit, free, pop=pop)
            kept = generated[self._kept(pose, free, generated, self._normals(pose), reference)]
            return np.concatenate([skinned, _exactly(kept, n_gen, np.random.default_rng([int(seed), 8]), generated)])

        # the generator draws half as many again as the free region keeps (it strays a little)
        prior_points = max(math.ceil(1.5 * n_gen), ANIMATION_MIN_PRIOR_POINTS)
        return AnimationPrior(self.free.point_prior(self._free_outfit(outfit)), prior_points, finish)

    def _skinned_points(self, pose: Pose, outfit: int, free: np.ndarray, n_att: int, n_free: int,
                        code: torch.Tensor | None = None, pop: dict[int, np.ndarray] | None = None) -> np.ndarray:  # fmt: skip
        """(n_att + n_free, 3) POP points (deterministic): n_att whose nearest posed body vertex is
        attached, then n_free whose nearest one is free. POP is queried at its training UV map's
        pixels (or more, when that is too few): N of them spread more evenly than N of a finer
        map's (BENCHMARKS, "Is PocoLoco's gap surface noise or point layout?"). With
        ``area_weighted`` the points are drawn with weights = the posed surface area each pixel
        stands for (its face's area / the face's pixels), so they cover the body as a scan does
        rather than as the UV layout does (hands and face have more pixels per cm^2)."""
        parts = []
        pop = {} if pop is None else pop  # both regions start from the same POP cloud
        pixels = len(self.attached.model.query_points())
        m = pixels
        for want, region in ((n_att, False), (n_free, True)):
            if want == 0:
                continue
            for _ in range(FREE_DRAWS):
                pts = self._pop_points(pose, outfit, m, code, pop)
                inside = point_regions(pts, pose.body_vertices, free, self.config.far) == region
                if inside.sum() >= want or m >= MAX_QUERY_FACTOR * max(pixels, want):
                    break
                # a finer map until the region holds enough (bounded: a region POP hardly reaches
                # would otherwise ask for millions of points)
                m = min(math.ceil(1.5 * m * want / max(int(inside.sum()), 1)), MAX_QUERY_FACTOR * max(pixels, want))
            weights = self._pixel_areas(pose, m)[inside] if self.config.area_weighted else None
            parts.append(_exactly(pts[inside], want, np.random.default_rng([0, 7, int(region)]), pts, weights))
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)

    def _pixel_areas(self, pose: Pose, m: int) -> np.ndarray:
        """(m,) the posed body surface area (m^2) each of POP's m query points stands for, in the
        order :meth:`predict` returns them (``pop_query_for`` with seed 0)."""
        faces = np.asarray(self.attached.model.faces_np, np.int64)
        face_idx = pop_query_for(self.attached.model, m, 0)[0].face_idx.cpu().numpy()
        v = np.asarray(pose.body_vertices, np.float64)
        area = 0.5 * np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)
        return area[face_idx] / np.bincount(face_idx, minlength=len(faces))[face_idx]

    def _free_points(self, pose: Pose, outfit: int, free: np.ndarray, n: int, seeds: Sequence[int],
                     options: SamplerOptions, code: torch.Tensor | None = None,
                     attached_code: torch.Tensor | None = None, pop: dict[int, np.ndarray] | None = None,
                     expected_rate: float = 1.0) -> list[np.ndarray]:  # fmt: skip
        """Per seed, (n, 3) generated points whose nearest posed body vertex is free (and, with an
        ``inside_tolerance``, that lie no deeper inside the body): the generator's clouds are
        filtered and drawn again (new seeds derived from the seed) until n. Each draw is sized for
        the points still missing at the keep rate expected: first ``expected_rate`` (the free
        region's share of a scan's points, what a generator that draws the whole outfit leaves
        there), then the rate seen so far, so that one draw usually suffices."""
        fo = self._free_outfit(outfit)
        normals = self._normals(pose)
        reference = self._reference(pose, outfit, free, attached_code, pop)
        found: list[list[np.ndarray]] = [[] for _ in seeds]
        last: list[np.ndarray] = [np.zeros((0, 3), np.float32)] * len(seeds)
        rate = min(max(float(expected_rate), 0.05), 1.0)
        for attempt in range(FREE_DRAWS):
            missing = [n - sum(len(x) for x in found[k]) for k in range(len(seeds))]
            todo = [k for k in range(len(seeds)) if missing[k] > 0]
            if not todo:
                break
            m = math.ceil(1.3 * max(missing[k] for k in todo) / max(rate, 0.05))
            draw = [int(seeds[k]) if attempt == 0 else int(seeds[k]) * 1000 + attempt for k in todo]
            clouds = self.free.predict(pose, m, seeds=draw, outfit=fo, options=options, code=code).points
            kept = 0
            for k, pts in zip(todo, clouds, strict=True):
                keep = self._kept(pose, free, pts, normals, reference)
                found[k].append(pts[keep])
                last[k] = pts
                kept += int(keep.sum())
            rate = kept / (m * len(todo))
        return [_exactly(np.concatenate(f), n, np.random.default_rng([int(s), 8]), x)
                for f, s, x in zip(found, seeds, last, strict=True)]  # fmt: skip

    def even_candidates(self, num_points: int) -> int:
        """N: ``--even`` keeps the hybrid's own layout (POP's points by body area, the generator's in
        the free region). Farthest-point sampling of 4 N of its points was worse on ``medium`` (+0.06
        / +0.17 cm Chamfer, twice the points beyond 10 cm: the generator's strays are kept first;
        BENCHMARKS "Evenly spread clouds")."""
        return int(num_points)

    def sample_settings(self, options: SamplerOptions, num_points: int) -> dict[str, Any]:
        return {"free": self.free.sample_settings(options, num_points), "margin": self.config.margin,
                "threshold": self.config.threshold, "generator_share": self.config.generator_share,
                "inside_tolerance": self.config.inside_tolerance, "area_weighted": self.config.area_weighted,
                "far": self.config.far, "trust": self.config.trust,
                **({"even": "the hybrid keeps its own layout"} if options.even else {})}  # fmt: skip


def _exactly(points: np.ndarray, n: int, rng: np.random.Generator, fallback: np.ndarray,
             weights: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """n of ``points`` without replacement (with replacement only when there are fewer), with
    probabilities proportional to ``weights`` (N,) when given; of ``fallback`` (the unfiltered
    draw) when a region caught no point at all (a sliver of a region, e.g. a fitted outfit's mean
    map)."""
    if len(points) == 0:
        points, weights = fallback, None
    p = None
    if weights is not None and weights.sum() > 0 and np.count_nonzero(weights) >= min(n, len(points)):
        p = weights / weights.sum()
    return points[np.sort(rng.choice(len(points), n, replace=len(points) < n, p=p))].astype(np.float32)


def _linked_state(ck: Checkpoint) -> dict[str, torch.Tensor]:
    """The weights a linked hybrid (``pocoloco hybrid --link``) refers to, as ``attached.*`` /
    ``free.*``: each source checkpoint loaded by its name (a shipped model) or folder and checked
    against the digest recorded at assembly; one-line errors when it is missing or changed."""
    state: dict[str, torch.Tensor] = {}
    for part, kind in (("attached", "pop"), ("free", "pocoloco")):
        ref = ck.meta["linked"].get(part) or {}
        if not ref.get("ckpt"):
            raise ValueError(f"{ck.path}: corrupt hybrid checkpoint (no linked {part} model)")
        source = load_linked(ck.path, ref, kind, f"the {part} model", "the hybrid was assembled",
                             "assemble the hybrid again with `pocoloco hybrid`")  # fmt: skip
        weights = source.ema_state if source.ema_state is not None else source.model_state
        state.update({f"{part}.{k}": v for k, v in weights.items()})
    return state
