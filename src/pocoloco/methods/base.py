"""The one interface every method is seen through: :class:`Method` (a trained model, loaded from a
checkpoint) and its training side (a config class, named presets and a
:class:`~pocoloco.engine.trainer.TrainingTask`).

Sampling, evaluation, the quality bench, the apps and the command line never ask which method
they hold: they load a checkpoint with :func:`pocoloco.methods.load_method` and call

* ``method.load_pose(spec, outfit)`` -> :class:`~pocoloco.data.poses.Pose` (joints, and the posed
  body for methods that need it, ``needs_body``);
* ``method.predict(pose, num_points, seeds, outfit, options)`` -> :class:`SampledClouds`
  (one cloud per seed; a deterministic method (``deterministic``) takes one seed, which only
  picks its query points), through :func:`predict_clouds`, which adds what every method shares
  (``options.even``: evenly spread points, via ``method.even_candidates``);
* ``method.outfit_id(name)`` / ``outfit_names()`` (methods with outfit codes; PocoLoco has none);
* ``method.info()`` (what reports say about the checkpoint);
* ``method.point_prior(outfit)`` -> :class:`PointPrior`, the hook completion, editing and animation
  run on (a generative point model under one pose); a method without one answers with a one-line
  error, so a new generative method gets the apps by implementing this one hook.

Adding a method = one folder under ``methods/`` with a :class:`Method` subclass, and one line in
:data:`pocoloco.methods.registry.METHODS`.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np
import torch
from torch import nn

from pocoloco.data.dataset import Normalisation, frame_motion_window
from pocoloco.data.frame import read_frame
from pocoloco.data.poses import (
    MeanShapeCache,
    Pose,
    demo_pose_outfit,
    outfit_of_spec,
    pose_from_anny_params,
    pose_spec_kind,
    subject_of_spec,
)
from pocoloco.diffusion import SAMPLER_STEPS
from pocoloco.diffusion.schedules import NoiseSchedule
from pocoloco.engine.checkpoint import Checkpoint, save_checkpoint
from pocoloco.engine.trainer import TrainingTask
from pocoloco.ops.sampling import farthest_point_sampling
from pocoloco.utils.hardware import available_memory_bytes

__all__ = ["MEMORY_SHARE", "AnimationPrior", "Method", "PointPrior", "SampledClouds", "SamplerOptions", "check_memory", "fit_to_memory", "predict_clouds"]

#: meta.json entries that ``save_checkpoint`` writes itself
_META_OWN = frozenset({"format", "version", "model_kind", "preset", "step", "config", "normalisation", "has_ema",
                       "has_training_state", "torch_version"})  # fmt: skip


class SampledClouds(NamedTuple):
    """What :meth:`Method.predict` returns; unpacks as ``points, normals``.

    points: (K, N, 3) float32 metres, in the frame of the input pose.
    normals: (K, N, 3) float32 unit normals, or None (a model without normals).
    """

    points: np.ndarray
    normals: np.ndarray | None


@dataclass(frozen=True)
class SamplerOptions:
    """How a generative method samples (deterministic methods ignore all but ``even``).

    sampler / steps: see :data:`pocoloco.diffusion.SAMPLER_STEPS` (steps None: the sampler's
    default). clip: clamp of the sampler's x0 estimates in normalised units (None: off).
    bf16: the network under bf16 autocast. batch_size: clouds denoised together (speed and
    memory only). progress: optional ``callable(done_clouds, K)``. even: spread each cloud's
    points evenly over its surface (:func:`predict_clouds`; every method). finish_t: after the
    sampler's chain, the cloud re-noised to 1-based step ``finish_t`` and the network's own x0
    estimate there, one call more (SDEdit's last step, as a distilled student's teacher finishes
    it; None: off). The chain's last x0 estimate comes from a step whose noise is larger than the
    cloth's detail and shrinks the cloud a little; step 5 takes that back.
    """

    sampler: str = "dpm++sde"
    steps: int | None = None
    clip: float | None = None
    bf16: bool = False
    batch_size: int = 8
    progress: Callable[[int, int], None] | None = None
    even: bool = False
    finish_t: int | None = None


@dataclass(frozen=True)
class PointPrior:
    """A generative point model under one pose, as the apps (completion, editing, animation) run it:
    ``denoiser(x (B, N, C), t (B,), joints (B, J, 3)) -> (B, N, C)`` in the normalised frame of
    ``normalisation`` (joints normalised with their own root), trained on ``schedule`` to predict
    ``prediction_type``; C = ``point_channels`` (3, or 6 with unit normals), J = ``num_joints``.
    The SDEdit / RePaint chains over it are :mod:`pocoloco.diffusion.chains`."""

    denoiser: nn.Module
    normalisation: Normalisation
    schedule: NoiseSchedule
    prediction_type: str
    point_channels: int
    num_joints: int
    #: a distilled student's grid (``pocoloco distill``): its chains visit only those timesteps
    student_calls: int = 0
    student_renoise: float = 1.0
    #: (teacher denoiser bound like ``denoiser``, 1-based t): a student whose teacher makes the last
    #: call (``export-model --polish-with``); its chains end with it (``apps.common.denoise_from``)
    polish: tuple[nn.Module, int] | None = None


@dataclass(frozen=True)
class AnimationPrior:
    """What the animation app runs for a method: ``prior`` carries ``prior_points`` points from
    frame to frame (the chain's state), and ``finish(pose, points (prior_points, 3) metres, seed)
    -> (N, 3)`` makes a frame's cloud from them (None: the prior's cloud is the frame's cloud). A
    method with a ``finish`` needs each frame's posed body (:attr:`Method.needs_body`)."""

    prior: PointPrior
    prior_points: int
    finish: Callable[[Pose, np.ndarray, int], np.ndarray] | None = None


class Method(ABC):
    """A trained model of one method, ready to predict (network in eval mode).

    Class attributes: ``kind`` (the checkpoints' ``model_kind``), ``deterministic`` (one cloud
    per pose and outfit), ``needs_body`` (conditioned on the posed body, not only joints),
    ``train_config`` (the method's train config class), ``presets`` (preset name -> config).
    Instance attributes: ``model`` (the network), ``config`` (the train config it was trained
    with), ``normalisation``, ``path`` (checkpoint folder), ``step``, ``meta`` (``meta.json``).
    """

    kind: ClassVar[str]
    deterministic: ClassVar[bool] = False
    needs_body: ClassVar[bool] = False
    #: can fit a new outfit to scans (``fit_outfit``, ``fit_points``, ``mean_outfit_code``, ``outfit_code``,
    #: ``add_outfit``; ``predict(..., code=...)``); a model may decide per checkpoint (a property)
    fits_outfits: ClassVar[bool] = False
    #: the fit needs the scans' normals (POP's point-to-plane loss)
    fit_needs_normals: ClassVar[bool] = False
    #: keyword options of :meth:`preset` beyond the config's fields (CloSET: ``decomposition``)
    train_options: ClassVar[frozenset[str]] = frozenset()
    #: trains under bf16 autocast when asked (POP: no; its decoder runs in float32), so a fine-tune
    #: may take the machine's bf16 default
    trains_in_bf16: ClassVar[bool] = True
    train_config: ClassVar[type]

    def __init__(self, model: nn.Module, config: Any, normalisation: Normalisation, path: Path, step: int,
                 meta: dict[str, Any]):  # fmt: skip
        self.model, self.config, self.normalisation = model, config, normalisation
        self.path, self.step, self.meta = Path(path), int(step), dict(meta)

    # ------------------------------------------------------------------ loading and training
    @classmethod
    @abstractmethod
    def from_checkpoint(cls, ck: Checkpoint, device: str = "cpu", use_ema: bool = True) -> Method:
        """Build the trained model of a loaded checkpoint (one-line ValueError if it is corrupt)."""

    @classmethod
    @abstractmethod
    def presets(cls) -> dict[str, Any]:
        """Named training presets (``tiny`` for tests, ``small`` for this CPU, ``paper``)."""

    @classmethod
    def preset(cls, name: str, **overrides) -> Any:
        """A named training preset with field overrides; a one-line error for unknown names."""
        presets = cls.presets()
        if name not in presets:
            raise ValueError(f"unknown training preset {name!r} for {cls.kind}; choose one of: {', '.join(presets)}")
        fields = {f.name for f in dataclasses.fields(cls.train_config)}
        unknown = sorted(set(overrides) - fields)
        if unknown:
            raise ValueError(f"{cls.kind} has no training option {', '.join(unknown)}")
        return presets[name].replace(**overrides)

    @classmethod
    @abstractmethod
    def training_task(cls, config: Any, data: str | Path) -> TrainingTask:
        """The training run of ``config`` on the train split of ``data`` (validated: one-line errors)."""

    # -------------------------------------------------------------------------- description
    @property
    def title(self) -> str:
        """Display name (``PocoLoco``, ``POP``, ``CloSET``, ...)."""
        return self.kind

    @property
    def num_parameters(self) -> int:
        return int(sum(p.numel() for p in self.model.parameters()))

    @property
    def device(self):
        return next(self.model.parameters()).device

    def info(self) -> dict[str, Any]:
        """What reports say about this checkpoint."""
        return {"checkpoint": str(self.path), "step": self.step, "preset": self.config.preset, "model_kind": self.kind,
                "model_title": self.title, "num_parameters": self.num_parameters,
                "deterministic": self.deterministic}  # fmt: skip

    # ------------------------------------------------------------------------------ outfits
    def outfit_names(self) -> list[str]:
        """Names of the outfits the model knows (ids in this order); [] without outfit codes."""
        return []

    def outfit_id(self, outfit: str | int | None) -> int | None:
        """An outfit name or id (as given on the command line) -> its id (None -> None); a one-line
        error if the model never learnt it, or if it has no outfits at all."""
        if outfit is None:
            return None
        names = self.outfit_names()
        if not names:
            raise ValueError(f"--outfit applies to models with outfit codes; this {self.title} checkpoint has none")
        s = str(outfit)
        if s in names:
            return names.index(s)
        if s.lstrip("-").isdigit() and 0 <= int(s) < len(names):
            return int(s)
        raise ValueError(f"{self.path}: outfit {s!r} was never trained (this {self.kind} checkpoint has "
                         f"{', '.join(f'{i}={n}' for i, n in enumerate(names))})")  # fmt: skip

    def default_outfit(self, pose: Pose) -> int | None:
        """The outfit to use when none is given: the pose's dataset subject (models with outfits;
        None for the others); a one-line error when the pose has no known subject."""
        names = self.outfit_names()
        if not names:
            return None
        if pose.subject is None or pose.subject not in names:
            raise ValueError(f"--outfit is required (this {self.kind} checkpoint has outfits {', '.join(names)})")
        return names.index(pose.subject)

    def outfit_of_pose_spec(self, spec: str, outfit: int | None) -> int | None:
        """``outfit`` if given, else the outfit a pose spec belongs to (a ``DATASET:...`` frame's
        subject, a ``demo:NAME`` pose's outfit) when this model has it, else None: the body a spec
        is posed with when no outfit is named."""
        if outfit is not None:
            return outfit
        name = outfit_of_spec(spec)
        return self.outfit_names().index(name) if name in self.outfit_names() else None

    def choose_outfit(self, outfit: str | int | None, spec: str | os.PathLike | None) -> int | None:
        """The outfit id to sample: ``outfit`` (a name or id) if given, else the subject of a
        ``DATASET:...`` spec, else for ``demo:NAME`` the outfit NAME if the model has it, else the
        one the pose was captured on; None for models without outfits (which refuse an outfit); a
        one-line error when none can be chosen."""
        names = self.outfit_names()
        if not names:
            self.outfit_id(outfit)  # refuses a given outfit
            return None
        name = outfit
        if name is None and spec is not None:
            spec = os.fspath(spec)
            name = subject_of_spec(spec)
            if spec.startswith("demo:"):  # the outfit of that name if the model has one, else the pose's own
                typed = spec[len("demo:"):]
                name = typed if typed in names else demo_pose_outfit(typed)
        if name is None or (outfit is None and name not in names):
            raise ValueError(f"--outfit is required (library: outfit=NAME; this {self.kind} checkpoint has outfits "
                             f"{', '.join(names)})")  # fmt: skip
        return self.outfit_id(name)

    # -------------------------------------------------------------------------------- poses
    @abstractmethod
    def load_pose(self, spec: str, outfit: int | None = None, frame_id: int | None = None,
                  any_pose: bool = False) -> Pose:  # fmt: skip
        """The pose ``--joints`` names (see :mod:`pocoloco.data.poses`); ``outfit`` picks the body
        an anny pose file is posed with (methods that need the body); joints that are not a human
        skeleton in metres are a one-line error unless ``any_pose``."""

    def pose_from_frame(self, path: str | Path, subject: str, frame=None, cache: MeanShapeCache | None = None) -> Pose:
        """The pose of a dataset frame file (``frame``: the already read ``Frame``, if any)."""
        joints = (frame if frame is not None else read_frame(path, ["joints"])).joints
        return Pose(np.asarray(joints, np.float32), subject=subject, source=str(path))

    @property
    def motion_window(self) -> float:
        """Seconds of past motion the model is conditioned on (0: the pose alone, every method of
        the papers)."""
        return 0.0

    def motion_of_frame(self, path: str | Path):
        """The motion window this model takes for the dataset frame file ``path``
        (:class:`~pocoloco.data.motion_window.MotionWindow`), or None for a pose-only model."""
        if not self.motion_window:
            return None
        return frame_motion_window(path, self.motion_window)

    def pose_from_anny(self, pose: Pose, outfit: int | None) -> Pose:
        """``pose``'s anny pose parameters (``joint_rotvecs``) posed on ``outfit``'s body shape (the
        subject's phenotype; the mean body without an outfit), for a method that needs the body."""
        if pose.joint_rotvecs is None:
            raise ValueError(f"{pose.source or 'pose'}: no anny pose parameters to pose a body with")
        outfits = getattr(self, "outfits", None) or []
        pheno = outfits[outfit].get("phenotype", {}) if outfit is not None and outfit < len(outfits) else {}
        return pose_from_anny_params(pose.joint_rotvecs, pose.root_translation, pheno,
                                     bool(getattr(self, "needs_mean_shape", False)), pose.source)  # fmt: skip

    def save(self, root: str | Path, extra: dict[str, Any] | None = None) -> Path:
        """Write the model as a new checkpoint (weights only, no training state) into the
        checkpoints folder ``root``, atomically; ``extra``: more ``meta.json`` entries."""
        keep = {k: v for k, v in self._meta_to_save().items() if k not in _META_OWN}
        return save_checkpoint(root, self.step, model_kind=self.kind, preset=self.config.preset,
                               config=self.config.to_dict(), normalisation=self.normalisation,
                               model_state=self.model.state_dict(), extra={**keep, **(extra or {})})  # fmt: skip

    def _meta_to_save(self) -> dict[str, Any]:
        """The ``meta.json`` entries :meth:`save` carries over from this model's own."""
        return self.meta

    # ---------------------------------------------------------------------------- predicting
    @abstractmethod
    def predict(self, pose: Pose, num_points: int, seeds: Sequence[int] = (0,), outfit: int | None = None,
                options: SamplerOptions = SamplerOptions()) -> SampledClouds:  # fmt: skip
        """One cloud of ``num_points`` points per seed for ``pose`` (and ``outfit``), in the frame
        of the pose (metres). Cloud k depends only on ``seeds[k]``."""

    def sample(self, pose: Pose | str | os.PathLike | np.ndarray, num_points: int = 2048,
               seeds: int | Sequence[int] = (0,), outfit: str | int | None = None, *, sampler: str = "dpm++sde",
               steps: int | None = None, even: bool = False, bf16: bool = False, batch_size: int = 8,
               frame_id: int | None = None, finish_t: int | None = None) -> SampledClouds:  # fmt: skip
        """Point clouds of a clothed body in ``pose``, one per seed: the library's one call (what
        ``pocoloco sample`` runs).

        Args:
            pose: a :class:`~pocoloco.data.poses.Pose` (``pocoloco.Pose.load(...)``), anything
                ``--joints`` takes (``demo:NAME``, ``DATASET:subject/split/sequence/index``, a
                joints file), or joints (24, 3) in metres. Methods that need the posed body (POP,
                CloSET, the hybrid) pose it from the spec or anny pose parameters with the outfit's
                body shape; bare joints are a one-line error for them.
            num_points: N, the points of a cloud.
            seeds: an int or a sequence of K ints (K clouds); a deterministic method takes one.
            outfit: name or id (models with outfits; default: the pose's own subject).
            sampler: the diffusion sampler (:data:`pocoloco.diffusion.SAMPLER_STEPS`).
            steps: its network calls (None: the sampler's default).
            even: spread each cloud's points evenly over its surface (:func:`predict_clouds`).
            bf16: the network under bf16 autocast (speed only).
            batch_size: clouds denoised together (speed and memory only).
            frame_id: the line of a joints text file.
            finish_t: one more network call at this 1-based step after the chain
                (:class:`SamplerOptions`; None: off).

        Returns:
            :class:`SampledClouds`: points (K, N, 3) float32 metres in the pose's frame, normals
            (K, N, 3) or None.
        """
        seeds = [int(seeds)] if isinstance(seeds, (int, np.integer)) else [int(k) for k in seeds]
        if not seeds:
            raise ValueError("seeds: give at least one seed")
        if int(num_points) < 1:
            raise ValueError(f"num_points must be >= 1, got {num_points}")
        if self.deterministic and len(seeds) != 1:
            raise ValueError(f"{self.title} is deterministic (one cloud per pose and outfit): give one seed, "
                             f"got {len(seeds)}")  # fmt: skip
        if not self.deterministic and sampler not in SAMPLER_STEPS:
            raise ValueError(f"unknown sampler {sampler!r}; choose one of: {', '.join(SAMPLER_STEPS)}")
        pose, outfit_id = self._resolve_pose(pose, outfit, frame_id)
        options = SamplerOptions(sampler=sampler, steps=steps, bf16=bf16, batch_size=int(batch_size), even=even,
                                 finish_t=finish_t)  # fmt: skip
        self.check_options(options)
        options = fit_to_memory(self, int(num_points), len(seeds), options)
        return predict_clouds(self, pose, int(num_points), seeds, outfit_id, options)

    def _resolve_pose(self, pose: Any, outfit: str | int | None, frame_id: int | None) -> tuple[Pose, int | None]:
        """(the Pose this method samples, the outfit id) for :meth:`sample`'s ``pose``."""
        if isinstance(pose, (str, os.PathLike)):
            spec = os.fspath(pose)
            if self.needs_body:  # the body is posed with the outfit's phenotype
                pose_spec_kind(spec)  # bare joints: the one-line error first
                chosen = self.choose_outfit(outfit, spec)
                return self.load_pose(spec, chosen, frame_id), chosen
            loaded = self.load_pose(spec, None, frame_id)  # a bad joints file is named before a missing outfit
            return loaded, self.choose_outfit(outfit, spec)
        if frame_id is not None:
            raise ValueError("frame_id applies to a pose spec (a joints text file), not to a Pose or an array")
        if not isinstance(pose, Pose):
            pose = Pose.from_joints(pose)
        spec = pose.source if pose.source and (pose.source.startswith("demo:") or ":" in pose.source) else None
        if self.needs_body and not pose.has_body:
            if pose.joint_rotvecs is not None:
                chosen = self.choose_outfit(outfit, None)
                return self.pose_from_anny(pose, chosen), chosen
            if spec is not None or (pose.source and Path(pose.source).is_file()):
                return self._resolve_pose(pose.source, outfit, None)
            raise ValueError(f"{self.title} needs the posed body, not bare joints: give a dataset frame, a demo:NAME "
                             "pose or an anny pose file (pocoloco.Pose.load)")  # fmt: skip
        if outfit is None and pose.subject is not None and pose.subject in self.outfit_names():
            return pose, self.outfit_id(pose.subject)
        return pose, self.choose_outfit(outfit, spec)

    def point_prior(self, outfit: int | None) -> PointPrior:
        """The hook the apps run on (:class:`PointPrior`), for outfit id ``outfit``; methods that are
        not generative point models answer with a one-line error."""
        raise ValueError(f"{self.title} cannot complete, edit or animate point clouds: these apps need a generative "
                         "point model (PocoLoco)")  # fmt: skip

    def animation_prior(self, outfit: int | None, num_points: int) -> AnimationPrior:
        """The animation app's hook (:class:`AnimationPrior`) for clouds of ``num_points``: by
        default :meth:`point_prior`, whose clouds are the frames."""
        return AnimationPrior(self.point_prior(outfit), int(num_points))

    def check_options(self, options: SamplerOptions) -> None:
        """One-line ValueError if ``options`` cannot be used with this model (before any work)."""

    def bytes_per_point(self) -> int:
        """A conservative estimate of the working memory one output point of one cloud takes in
        :meth:`predict` (float32 activations of the widest per-point layers); 4 KiB unless a method
        knows better. Used to refuse or split requests that cannot fit before any work."""
        return 4096

    def sample_settings(self, options: SamplerOptions, num_points: int) -> dict[str, Any]:
        """Method-specific entries of ``sample.json``."""
        return {}

    def even_candidates(self, num_points: int) -> int:
        """How many points a cloud is drawn with when its ``num_points`` are to be spread evenly
        (``SamplerOptions.even``, :func:`predict_clouds`): 4 N unless a method knows better."""
        return EVEN_FACTOR * int(num_points)

    def even_layout_points(self, pose: Pose, num_points: int, seeds: Sequence[int]) -> np.ndarray | None:
        """(K, M, 3): the points by whose spread :func:`predict_clouds` picks an even subset of the
        clouds ``predict(pose, M, seeds)`` draws, point for point; None (the default): the clouds'
        own points. A method that decodes points from spots on a surface (POP, CloSET) answers with
        those spots, so a point flung off the surface is not favoured for being far from the rest."""
        return None


#: candidates per kept point of an evenly spread cloud (:meth:`Method.even_candidates`)
EVEN_FACTOR = 4
#: kept x candidate points beyond which farthest-point sampling on a CPU is worth a warning (10,000
#: of 40,000: ~4 s on one core here, 1 s with fpsample; 50,000 of 200,000: ~2 min with either)
SLOW_FPS_WORK = 5e9


def predict_clouds(method: Method, pose: Pose, num_points: int, seeds: Sequence[int] = (0,), outfit: int | None = None,
                   options: SamplerOptions = SamplerOptions()) -> SampledClouds:  # fmt: skip
    """:meth:`Method.predict`, with the options every method shares: with ``options.even`` each
    cloud is drawn at ``method.even_candidates(N)`` points and cut to N by farthest-point sampling
    of its points (Eldar et al. 1997; PointNet++ Sec. 3.2) — or of the spots they are decoded from,
    :meth:`Method.even_layout_points` — normals kept with their points. The same surface, evenly
    covered instead of sampled at random; the points come in farthest-point order, so any prefix of
    a cloud is evenly spread too (unless the method draws no more than N: its own layout, as
    drawn). Returns (K, N, 3) points (and normals)."""
    if not options.even:
        return method.predict(pose, num_points, seeds, outfit, options)
    drawn = method.even_candidates(num_points)
    dense = method.predict(pose, drawn, seeds, outfit, options)
    if drawn == num_points:  # the method's own layout is already even at this N (POP beyond its UV map)
        return dense
    space = method.even_layout_points(pose, drawn, seeds)
    space = dense.points if space is None else np.broadcast_to(space, dense.points.shape)
    space_t = torch.from_numpy(np.array(space, np.float32)).to(method.device)  # a GPU runs the loop faster
    if space_t.device.type == "cpu" and num_points * drawn > SLOW_FPS_WORK:
        warnings.warn(f"--even: farthest-point sampling of {num_points:,} of {drawn:,} points a cloud may take a minute "
                      "or more on a CPU (~2 min for 50,000 of 200,000 on one core); --even is meant for a few thousand "
                      "points")  # fmt: skip
    idx = farthest_point_sampling(space_t, num_points).cpu().numpy()  # (K, N)

    def keep(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(a, idx[:, :, None], axis=1)

    return SampledClouds(keep(dense.points), None if dense.normals is None else keep(dense.normals))


#: share of the free memory one request may plan to use
MEMORY_SHARE = 0.8


#: bytes an output point keeps while its cloud waits to be written: float32 points, normals and the
#: normalised (B, N, C <= 6) array the samplers return
OUTPUT_BYTES_PER_POINT = 4 * (3 + 3 + 6)


def check_memory(method: Method, num_points: int, num_clouds: int) -> tuple[int, int] | None:
    """A one-line error naming the most points that fit when even one cloud of ``num_points`` does not
    fit in the free memory of the model's device, or the most clouds whose outputs fit together;
    else (free bytes, bytes of one cloud in flight), or None where free memory cannot be told."""
    free = available_memory_bytes(method.device)
    if free is None:
        return None
    budget = MEMORY_SHARE * free
    per_cloud = num_points * method.bytes_per_point()
    if per_cloud > budget:
        most = int(budget // method.bytes_per_point())
        raise ValueError(f"--points {num_points:,}: one cloud needs ~{per_cloud / 2**30:.1f} GiB and "
                         f"{free / 2**30:.1f} GiB are free; at most ~{most:,} points fit (draw several clouds "
                         "with other seeds and merge them)")  # fmt: skip
    kept = OUTPUT_BYTES_PER_POINT * num_points * num_clouds  # every cloud's output is kept until it is written
    if kept > budget:
        most = max(int(budget // (OUTPUT_BYTES_PER_POINT * num_points)), 0)
        raise ValueError(f"--num {num_clouds:,} clouds of {num_points:,} points: the clouds alone need ~{kept / 2**30:.3g} GiB "
                         f"and {free / 2**30:.1f} GiB are free; at most ~{most:,} clouds of that size fit")  # fmt: skip
    return free, per_cloud


def fit_to_memory(method: Method, num_points: int, num_clouds: int, options: SamplerOptions) -> SamplerOptions:
    """``options`` with a batch size (clouds denoised together) that fits in the free memory of the
    model's device (a one-line warning when it had to be lowered), after :func:`check_memory`."""
    if options.even:  # the candidates are what is drawn
        drawn = method.even_candidates(num_points)
        try:
            known = check_memory(method, drawn, num_clouds)
        except ValueError as e:
            raise ValueError(f"--even draws {drawn:,} points a cloud to keep {num_points:,}: {e}") from None
    else:
        known = check_memory(method, num_points, num_clouds)
    if known is None:
        return options
    free, per_cloud = known
    fits = max(1, int(MEMORY_SHARE * free // per_cloud))
    batch = min(options.batch_size, num_clouds)
    if fits < batch:
        warnings.warn(f"denoising {fits} of the {num_clouds} clouds at a time to fit in {free / 2**30:.1f} GiB of free memory")
        return dataclasses.replace(options, batch_size=fits)
    return options
