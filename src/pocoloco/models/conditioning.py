"""Who wears what: the conditioning a PocoLoco denoiser can take besides the skeleton.

The paper trains one model per subject and conditions on the 3D joints K only. One model for many
subjects must otherwise guess the outfit from the skeleton's proportions and the pose (and gets it
wrong: a tight subject with the arms held forward was dressed in an ankle-length dress). So the
denoisers accept a :class:`PoseCondition`: the joints (B, J, 3) and, when their config asks for them,

* ``outfit`` (B,) int64: an outfit id; a learned embedding (num_outfits, D) gives one token
  (auto-decoded like POP's geometric features and CloSET's garment codes: a new outfit is fitted
  by optimising only its embedding, :meth:`WhoWearsWhat.add_outfit`);
* ``shape`` (B, S) float: the body shape, here anny's phenotype parameters in [0, 1]
  (``pocoloco.body.anny_body.PHENOTYPE_KEYS`` order); an MLP gives one token;
* ``body`` (B, K, 3) float: K fixed vertices of the *posed* body surface, normalised like the
  points (latent denoiser with ``body_points = K``; one token each). Not in the paper, which is
  template-free and sees the skeleton only: the posed body is what POP and CloSET are given.

The tokens join the joint tokens: keys of the cross-attention (transformer) or members of the
latent stream (latent). A plain (B, J, 3) joints tensor is still accepted where the config has
neither (``num_outfits = shape_dim = 0``, what every model trained before had).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

__all__ = ["SHAPE_KEYS", "MotionEncoder", "OutfitBound", "PoseCondition", "WhoWearsWhat", "body_of", "phenotype_vector",
           "motion_of", "split_condition"]

#: anny's phenotype parameters, in the order of a body-shape vector (``body.anny_body.PHENOTYPE_KEYS``;
#: repeated here so the networks do not import the body model)
SHAPE_KEYS: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")


def phenotype_vector(phenotype: dict[str, float] | None) -> list[float]:
    """An anny phenotype dict (missing keys: anny's default 0.5) -> the (S,) body-shape vector."""
    phenotype = phenotype or {}
    unknown = sorted(set(phenotype) - set(SHAPE_KEYS))
    if unknown:
        raise ValueError(f"unknown phenotype keys {unknown}; expected some of {SHAPE_KEYS}")
    return [float(phenotype.get(k, 0.5)) for k in SHAPE_KEYS]


@dataclass
class PoseCondition:
    """joints (B, J, 3) normalised; outfit (B,) int64 or None; shape (B, S) or None; code (B, D) or
    None: an outfit embedding given directly instead of an id (fitting a new outfit); body (B, K, 3)
    normalised posed-body vertices or None; velocity (B, J, 3) normalised joint velocities or None
    (a model trained with them then takes the body as at rest); motion (B, J, F) motion-window
    features (:func:`pocoloco.data.motion_window.motion_features`) or None (a model trained with
    them then takes the body as at rest: all zeros)."""

    joints: torch.Tensor
    outfit: torch.Tensor | None = None
    shape: torch.Tensor | None = None
    code: torch.Tensor | None = None
    body: torch.Tensor | None = None
    velocity: torch.Tensor | None = None
    motion: torch.Tensor | None = None


def split_condition(cond) -> tuple[torch.Tensor, torch.Tensor | torch.Tensor | None, torch.Tensor | None]:
    """(joints, outfit, shape) of a :class:`PoseCondition` or of a bare joints tensor; ``outfit`` is
    the (B, D) code instead of the (B,) ids when the condition carries one."""
    if isinstance(cond, PoseCondition):
        return cond.joints, (cond.code if cond.code is not None else cond.outfit), cond.shape
    return cond, None, None


def body_of(cond) -> torch.Tensor | None:
    """The (B, K, 3) posed-body vertices of a condition, or None."""
    return cond.body if isinstance(cond, PoseCondition) else None


def velocity_of(cond) -> torch.Tensor | None:
    """The (B, J, 3) joint velocities of a condition, or None."""
    return cond.velocity if isinstance(cond, PoseCondition) else None


def motion_of(cond) -> torch.Tensor | None:
    """The (B, J, F) motion-window features of a condition, or None."""
    return cond.motion if isinstance(cond, PoseCondition) else None


class MotionEncoder(nn.Module):
    """The last seconds of motion -> one (B, J, D) update per joint token (issue 41).

    Localised per body part like Dyco (Zhou et al., ECCV 2024: pose deltas per part through a small
    bottleneck): joint j's features (its past positions relative to its current one, the root's
    velocity and yaw rate; F values) and a learned embedding of j go through a shared MLP
    F -> H -> ``bottleneck`` -> D. The last layer is zero-initialised, so a model given it starts
    exactly as the model without it (a fine-tune from a pose-only checkpoint starts at that model),
    and all-zero features (a body at rest) give a constant the training's history dropout teaches.
    """

    def __init__(self, feature_dim: int, num_joints: int, width: int, hidden: int = 128, bottleneck: int = 32):
        super().__init__()
        self.feature_dim = int(feature_dim)
        self.inp = nn.Linear(feature_dim, hidden)
        self.joint_embed = nn.Parameter(torch.randn(num_joints, hidden) * 0.02)  # (J, H)
        self.mid = nn.Linear(hidden, bottleneck)
        self.out = nn.Linear(bottleneck, width)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, motion: torch.Tensor) -> torch.Tensor:
        """motion (B, J, F) -> (B, J, D)."""
        h = torch.nn.functional.gelu(self.inp(motion) + self.joint_embed)
        return self.out(torch.nn.functional.gelu(self.mid(h)))


class WhoWearsWhat(nn.Module):
    """Outfit embedding and body-shape MLP -> (B, K, D) condition tokens (K = 0, 1 or 2).

    num_outfits: rows of the outfit embedding (0: no outfit token). shape_dim: S (0: no shape
    token). Each token also gets a learned type embedding so the attention can tell them apart.
    """

    def __init__(self, width: int, num_outfits: int = 0, shape_dim: int = 0):
        super().__init__()
        self.num_outfits, self.shape_dim = int(num_outfits), int(shape_dim)
        self.outfit_embed = nn.Embedding(num_outfits, width) if num_outfits else None
        if self.outfit_embed is not None:
            nn.init.normal_(self.outfit_embed.weight, std=0.02)
        self.shape_in = (nn.Sequential(nn.Linear(shape_dim, width), nn.GELU(), nn.Linear(width, width))
                         if shape_dim else None)  # fmt: skip

    @property
    def num_tokens(self) -> int:
        return int(self.outfit_embed is not None) + int(self.shape_in is not None)

    def forward(self, outfit: torch.Tensor | None, shape: torch.Tensor | None, batch: int,
                dtype: torch.dtype) -> torch.Tensor | None:  # fmt: skip
        """(B, K, D) tokens, or None when the model takes no such conditioning; one-line errors when
        the model needs an input it was not given (or is given one it has no use for)."""
        tokens = []
        if self.outfit_embed is None:
            if outfit is not None:
                raise ValueError("this model has no outfit codes (trained without outfits); pass no outfit")
        else:
            if outfit is None:
                raise ValueError(f"this model needs an outfit id (it knows {self.num_outfits} outfits)")
            if torch.is_tensor(outfit) and outfit.is_floating_point():  # (B, D) codes given directly
                if outfit.shape != (batch, self.outfit_embed.embedding_dim):
                    raise ValueError(f"outfit codes must have shape ({batch}, {self.outfit_embed.embedding_dim}), "
                                     f"got {tuple(outfit.shape)}")  # fmt: skip
                tokens.append(outfit)
            else:
                outfit = torch.as_tensor(outfit, device=self.outfit_embed.weight.device).long().reshape(-1)
                if outfit.shape != (batch,):
                    raise ValueError(f"outfit must have shape ({batch},), got {tuple(outfit.shape)}")
                if int(outfit.min()) < 0 or int(outfit.max()) >= self.num_outfits:
                    raise ValueError(f"outfit ids must be in [0, {self.num_outfits}), got {outfit.tolist()}")
                tokens.append(self.outfit_embed(outfit))
        if self.shape_in is None:
            if shape is not None:
                raise ValueError("this model takes no body shape (trained without it); pass no shape")
        else:
            if shape is None:
                raise ValueError(f"this model needs the body shape ({self.shape_dim} phenotype values)")
            if shape.shape != (batch, self.shape_dim):
                raise ValueError(f"shape must have shape ({batch}, {self.shape_dim}), got {tuple(shape.shape)}")
            if not torch.isfinite(shape).all():
                raise ValueError("shape contains NaN or infinite values")
            tokens.append(self.shape_in(shape.to(self.shape_in[0].weight.dtype)))
        if not tokens:
            return None
        return torch.stack(tokens, dim=1).to(dtype)  # (B, K, D)

    @torch.no_grad()
    def add_outfit(self, code: torch.Tensor | None = None) -> int:
        """Append one outfit (its embedding: ``code`` (D,), default the mean of the known ones);
        returns its id. Rebuild any optimiser afterwards (the Parameter is replaced)."""
        if self.outfit_embed is None:
            raise ValueError("this model has no outfit codes to add to")
        w = self.outfit_embed.weight
        new = w.mean(0) if code is None else torch.as_tensor(code, dtype=w.dtype, device=w.device).reshape(-1)
        if new.shape != (w.shape[1],):
            raise ValueError(f"an outfit code has {w.shape[1]} values, got {tuple(new.shape)}")
        grown = nn.Embedding(w.shape[0] + 1, w.shape[1]).to(device=w.device, dtype=w.dtype)
        grown.weight.copy_(torch.cat([w, new[None]], 0))
        self.outfit_embed = grown
        self.num_outfits += 1
        return self.num_outfits - 1


class OutfitBound(nn.Module):
    """A conditioned denoiser with one outfit and body shape bound in: ``forward(x, t, joints)`` like a
    joints-only model, so code written for those (samplers, completion, editing, animation) runs
    unchanged. outfit: an id or None; shape: (S,) or None; code: (D,) an outfit embedding instead of
    an id (a fitted outfit, before it is added to the model)."""

    def __init__(self, model: nn.Module, outfit: int | None, shape=None, code: torch.Tensor | None = None):
        super().__init__()
        self.model, self.outfit = model, outfit
        self.register_buffer("shape", None if shape is None else torch.as_tensor(shape, dtype=torch.float32),
                             persistent=False)  # fmt: skip
        self.code = code  # (D,): an outfit embedding used instead of ``outfit``
        #: (J, F) motion-window features of the pose being drawn (a ``motion_window`` model; None: at
        #: rest). The apps set it per pose (animation: each frame its own window).
        self.motion: torch.Tensor | None = None

    @property
    def config(self):
        return self.model.config

    def forward(self, x: torch.Tensor, t: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        B = joints.shape[0]
        outfit = None if self.outfit is None else torch.full((B,), int(self.outfit), device=joints.device)
        shape = None if self.shape is None else self.shape.to(device=joints.device, dtype=joints.dtype).expand(B, -1)
        code = None if self.code is None else self.code.to(device=joints.device, dtype=joints.dtype).reshape(1, -1).expand(B, -1)
        motion = None if self.motion is None else self.motion.to(device=joints.device, dtype=joints.dtype).expand(B, -1, -1)
        return self.model(x, t, PoseCondition(joints, outfit, shape, code, motion=motion))
