"""A latent read / compute / write denoiser whose cost is linear in the number of points N.

Drop-in for :class:`~pocoloco.models.pocoloco.PocoLocoDenoiser` (same ``forward(x, t, joints)``,
same config conventions), built on the idea of PointInfinity (Huang et al., CVPR 2024: the
"two-stream block", a fixed-size latent stream and a variable-size data stream joined by
lightweight read / write modules) and Perceiver IO (Jaegle et al., ICLR 2022: encode, process,
decode through a latent array): instead of N point tokens attending to each other (O(N^2) per
layer, PocoLoco paper Sec. 5.1), a fixed set of M learned latent tokens does the global reasoning
and the points talk only to the latents. Written from the papers' descriptions; no code of those
projects (their licences forbid it).

Two streams (shape letters: B batch, N points, J joints, M latents, L = M + 1 + J latent-stream
tokens, D latent width, P = ``point_width`` point width, C point channels):

* point stream  p = LN(Linear(posenc(x_i)) [+ MLP(joint offsets)])              (B, N, P)
  (the point tokens of PocoLoco; ``joint_offsets`` as in the ``small`` PocoLoco preset, see
  :func:`~pocoloco.models.pocoloco.joint_offset_features`)
* latent stream z = LN([Z; tau(t); Linear(posenc(k_j)) + E_j])                   (B, L, D)
  Z (M, D) learned latents, tau(t) the timestep token, the J joint tokens of PocoLoco: the time
  and the skeleton are ordinary members of the latent self-attention ("the latents see time and
  joints"), like the conditioning tokens RIN (Jabri et al., ICML 2023) appends to its latents.
  They also read and are read like the latents, so every point can attend to the joints directly
  in each write (PocoLoco's per-layer cross-attention to the joints, at no extra cost).
* ``depth`` blocks, each with pre-LayerNorm residual updates:

    read     z <- z + CrossAttn(LN(z), LN(p))                  latents attend to points, O(N L)
    compute  ``compute_layers`` x [z <- z + SelfAttn(LN(z)); z <- z + MLP(LN(z))]      O(L^2)
    write    p <- p + CrossAttn(LN(p), LN(z))                  points attend to latents, O(N L)
             p <- p + MLP(LN(p))                               per point, O(N)

* output = Linear(LN(p)) to C channels, zero-initialised (point-e / DiT), so the untrained model
  predicts 0.

Cost per block is O(N L P + N P^2 + L^2 D + L D^2) (read / write attention and projections,
per-point MLP, latent self-attention, latent MLP): linear in N. Memory is linear in N as well:
attention uses SDPA (no N x L score matrix is kept on the CPU flash kernel), and even the
``"dense"`` reference only materialises (B, H, N, L) scores, linear in N since L is fixed. The
per-point work (write attention and MLP) is independent across points and narrow (P <= D), so it
is not chunked: the (B, N, 4P) MLP hidden of ``small`` at B = 1, N = 50K is 100 MB, and a no-grad
50K-point forward of ``small`` peaks at 0.4 GiB above the process's resting RSS
(``benchmarks/bench_latent.py``).

The two streams may have different widths (``point_width`` P < D; our choice, in the spirit of
PointInfinity's "lightweight" read / write modules): the point stream is the part whose cost grows
with N, so it is kept narrow (P = 128 in ``paper``), while the latents, where the depth and most
parameters are, keep the paper's width 512. With P = D the speed-ups roughly halve
(``benchmarks/bench_latent.py --ablation`` times P = 256).

Why the network is resolution-free in practice (trained on 1-2K points, sampled at 10K-50K):

* Every per-point operation (encoding, write attention over the L latent tokens, MLP, head) sees
  one point and the latent stream only, so it does not depend on N.
* The only place where points are pooled is the read, a softmax over the N points: each latent
  receives a convex combination sum_i a_i v_i of point values with sum_i a_i = 1, i.e. an
  attention-weighted mean over the cloud, not a sum. For N points drawn i.i.d. from one surface
  density, sum_i exp(s_i) v_i / sum_i exp(s_i) converges (as N -> inf) to the ratio of the two
  expectations E[exp(s) v] / E[exp(s)], so the latent statistics do not grow with N; more points
  only shrink the Monte-Carlo noise of the read (PointInfinity's observation that test-time
  resolution can exceed training resolution, and quality even improves with it). A sum pooling or
  a 1/N-less aggregation would drift with N instead.
* No positional index or learned per-point embedding: the network is permutation-equivariant over
  points and accepts any N >= 1.
* What N does change is the Monte-Carlo noise of the read: a model trained on 1-2K points sees
  noisier latents than it meets when sampling 50K; PointInfinity finds this shift harmless, even
  helpful. The exact invariance is tested: feeding every point twice changes no output.

Parameter counts (3-channel points, ``LATENT_PRESETS``): ``paper`` 29,655,043 (PocoLoco ``paper``
34,218,499), ``base`` 9,100,227 (one GPU), ``small`` 3,806,723 (PocoLoco ``small`` 1,135,491), ``tiny`` 43,747.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import nn

from pocoloco.data.motion_window import motion_feature_dim, window_samples
from pocoloco.models.conditioning import (
    MotionEncoder,
    PoseCondition,
    WhoWearsWhat,
    body_of,
    motion_of,
    split_condition,
    velocity_of,
)
from pocoloco.models.layers import (
    ATTENTION_IMPLS,
    MLP,
    POSENC_KINDS,
    MultiHeadAttention,
    PointDenoiserBase,
    TimestepEmbedder,
    positional_encoding_dim,
)
from pocoloco.models.pocoloco import joint_offset_features
from pocoloco.utils.config import Config


@dataclass(frozen=True)
class LatentDenoiserConfig(Config):
    """Architecture of :class:`LatentDenoiser`; defaults are the paper-width preset (``paper``).

    width: latent width D (latents, time and joint tokens). depth: number of read / compute / write
    blocks. compute_layers: self-attention + MLP layers over the latent stream per block.
    num_latents: M learned latent tokens. point_width: width P of the point stream (None = width).
    heads / head_dim: heads and channels per head of the latent self-attention (head_dim None =
    width // heads). rw_heads: heads of the read and write cross-attentions; their inner width is
    P, i.e. P // rw_heads channels per head. mlp_ratio / point_mlp_ratio: hidden width of the
    latent and per-point MLPs, in multiples of D and P.
    posenc, num_freqs, posenc_include_input, point_channels, num_joints, dropout,
    attention, joint_offsets, num_outfits, shape_dim: as in
    :class:`~pocoloco.models.pocoloco.PocoLocoDenoiserConfig` (outfit and body-shape tokens join the
    latent stream). body_points: K posed-body vertices given with the condition, one token each in
    the latent stream (0: none, the paper's template-free input); with ``joint_offsets`` every point
    also gets its offsets to them, as to the joints. joint_velocity: the joint tokens also get an
    MLP of each joint's velocity (:class:`~pocoloco.models.conditioning.PoseCondition` ``velocity``;
    not in the paper: the cloth follows the motion, not only the pose); zero-initialised, and zero
    velocity (a body at rest) when the condition has none. motion_window: seconds of past motion
    the joint tokens also see (0: none; :class:`~pocoloco.models.conditioning.MotionEncoder` of the
    condition's ``motion`` features, sampled at ``motion_hz``; not in the paper; zero-initialised,
    and a body at rest when the condition has none)
    (``attention="dense"`` is the materialised-softmax reference, same weights and maths).
    """

    width: int = 512
    depth: int = 8
    compute_layers: int = 1
    num_latents: int = 256
    point_width: int | None = 128
    heads: int = 4
    head_dim: int | None = 128
    rw_heads: int = 4
    mlp_ratio: float = 4.0
    point_mlp_ratio: float = 4.0
    posenc: str = "transformer"
    num_freqs: int = 7
    posenc_include_input: bool = False
    point_channels: int = 3
    num_joints: int = 24
    dropout: float = 0.0
    attention: str = "sdpa"
    joint_offsets: bool = True
    num_outfits: int = 0
    shape_dim: int = 0
    body_points: int = 0
    joint_velocity: bool = False
    motion_window: float = 0.0
    motion_hz: float = 8.0

    #: older checkpoints stored the diffusion parametrisation here; it is the training config's
    legacy_fields: ClassVar[frozenset[str]] = frozenset({"prediction_type"})

    def __post_init__(self):
        if self.posenc not in POSENC_KINDS:
            raise ValueError(f"posenc must be one of {POSENC_KINDS}, got {self.posenc!r}")
        if self.attention not in ATTENTION_IMPLS:
            raise ValueError(f"attention must be one of {ATTENTION_IMPLS}, got {self.attention!r}")
        if self.point_channels not in (3, 6):
            raise ValueError(f"point_channels must be 3 (xyz) or 6 (xyz + normals), got {self.point_channels}")
        for name in ("width", "depth", "compute_layers", "num_latents", "heads", "rw_heads", "num_freqs", "num_joints"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("num_outfits", "shape_dim", "body_points"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.point_width is not None and self.point_width < 1:
            raise ValueError(f"point_width must be >= 1 or None, got {self.point_width}")
        if self.head_dim is not None and self.head_dim < 1:
            raise ValueError(f"head_dim must be >= 1 or None, got {self.head_dim}")
        if self.head_dim is None and self.width % self.heads:
            raise ValueError(f"width {self.width} is not divisible by heads {self.heads}; set head_dim")
        if self.point_dim % self.rw_heads:
            raise ValueError(f"point_width {self.point_dim} is not divisible by rw_heads {self.rw_heads}")
        for name in ("mlp_ratio", "point_mlp_ratio"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not (self.motion_window >= 0 and self.motion_hz > 0):
            raise ValueError(f"motion_window must be >= 0 and motion_hz > 0, got {self.motion_window}, {self.motion_hz}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")

    @property
    def attn_head_dim(self) -> int:
        """Channels per head of the latent self-attention."""
        return self.head_dim if self.head_dim is not None else self.width // self.heads

    @property
    def point_dim(self) -> int:
        """Width P of the point stream."""
        return self.point_width if self.point_width is not None else self.width

    @property
    def motion_feature_dim(self) -> int:
        """F of the motion features the model takes (0: none; 116 for 2 s at 8 Hz)."""
        if not self.motion_window:
            return 0
        return motion_feature_dim(window_samples(self.motion_window, self.motion_hz))

    @property
    def num_tokens(self) -> int:
        """L = M latents + 1 time token + J joint tokens (+ outfit, shape, K body tokens) in the latent stream."""
        return (self.num_latents + 1 + self.num_joints + int(self.num_outfits > 0) + int(self.shape_dim > 0)
                + self.body_points)  # fmt: skip



LATENT_PRESETS: dict[str, LatentDenoiserConfig] = {
    # the paper's width and depth budget (latent width 512, 8 blocks, 4 heads x 128) for the speed
    # comparison with PocoLoco's ``paper`` preset; 256 latents, a 128-wide point stream
    "paper": LatentDenoiserConfig(),
    # CPU-sized: a fraction of a second per network call at 10K points. 64 latents and a 64-wide
    # point stream (the 128 / 128 of the first version cost 2x more per training step and learned
    # no faster per step): a training step at 16 x 512 points is ~0.6x PocoLoco ``small``'s
    "small": LatentDenoiserConfig(width=256, depth=4, num_latents=64, point_width=64, heads=4, head_dim=None),
    # GPU-sized, still small enough to ship (9.2M parameters with outfit codes and body shape, 18 MB
    # as fp16): 1.5x ``small``'s depth, 1.25x its width, 1.5x its latents and point width
    "base": LatentDenoiserConfig(width=320, depth=6, num_latents=96, point_width=96, heads=5, head_dim=None),
    # tests and smoke runs
    "tiny": LatentDenoiserConfig(width=32, depth=2, num_latents=8, point_width=16, heads=2, head_dim=None,
                                 rw_heads=2),
}


def latent_preset(name: str, **overrides: Any) -> LatentDenoiserConfig:
    """A named preset with field overrides; a one-line error naming the known presets otherwise."""
    if name not in LATENT_PRESETS:
        raise ValueError(f"unknown latent denoiser preset {name!r}; choose one of: {', '.join(LATENT_PRESETS)}")
    return LATENT_PRESETS[name].replace(**overrides)


class LatentBlock(nn.Module):
    """One read / compute / write block (module docstring), pre-LayerNorm residuals.

    z: (B, L, D) latent stream, p: (B, N, P) point stream -> (z, p) of the same shapes.
    """

    def __init__(self, cfg: LatentDenoiserConfig):
        super().__init__()
        D, P = cfg.width, cfg.point_dim
        rw_head_dim = P // cfg.rw_heads
        # read: queries from the latents (D), keys / values from the points (P), inner width P
        self.ln_read_z = nn.LayerNorm(D)
        self.ln_read_p = nn.LayerNorm(P)
        self.read = MultiHeadAttention(D, cfg.rw_heads, rw_head_dim, context_width=P, dropout=cfg.dropout)
        # compute: a small transformer over the L tokens of the latent stream
        self.compute = nn.ModuleList()
        for _ in range(cfg.compute_layers):
            layer = nn.ModuleDict({
                "ln_attn": nn.LayerNorm(D),
                "attn": MultiHeadAttention(D, cfg.heads, cfg.attn_head_dim, dropout=cfg.dropout),
                "ln_mlp": nn.LayerNorm(D),
                "mlp": MLP(D, cfg.mlp_ratio, cfg.dropout),
            })  # fmt: skip
            self.compute.append(layer)
        # write: queries from the points (P), keys / values from the latent stream (D), inner width P
        self.ln_write_p = nn.LayerNorm(P)
        self.ln_write_z = nn.LayerNorm(D)
        self.write = MultiHeadAttention(P, cfg.rw_heads, rw_head_dim, context_width=D, dropout=cfg.dropout)
        self.ln_point_mlp = nn.LayerNorm(P)
        self.point_mlp = MLP(P, cfg.point_mlp_ratio, cfg.dropout)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, z: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = z + self.drop(self.read(self.ln_read_z(z), self.ln_read_p(p)))  # (B, L, D)
        for layer in self.compute:
            z = z + self.drop(layer["attn"](layer["ln_attn"](z)))
            z = z + layer["mlp"](layer["ln_mlp"](z))
        p = p + self.drop(self.write(self.ln_write_p(p), self.ln_write_z(z)))  # (B, N, P)
        p = p + self.point_mlp(self.ln_point_mlp(p))
        return z, p


class LatentDenoiser(PointDenoiserBase):
    """Pose-conditioned point-cloud denoiser f(X_t, t, K) with cost linear in N (module docstring)."""

    def __init__(self, config: LatentDenoiserConfig | None = None):
        super().__init__()
        cfg = config if config is not None else LatentDenoiserConfig()
        self.config = cfg
        D, P = cfg.width, cfg.point_dim
        enc_dim = positional_encoding_dim(3, cfg.num_freqs, cfg.posenc_include_input)
        # point stream
        self.point_in = nn.Linear(enc_dim + cfg.point_channels - 3, P)
        self.offset_in = (
            nn.Sequential(nn.Linear(4 * cfg.num_joints, P), nn.GELU(), nn.Linear(P, P)) if cfg.joint_offsets else None
        )
        self.ln_points = nn.LayerNorm(P)
        # latent stream: learned latents, time token, joint tokens
        self.latents = nn.Parameter(torch.randn(cfg.num_latents, D) * 0.02)  # (M, D), ViT / Perceiver init
        self.time_embed = TimestepEmbedder(D)
        self.joint_in = nn.Linear(enc_dim, D)
        self.joint_embed = nn.Parameter(torch.randn(cfg.num_joints, D) * 0.02)  # (J, D)
        self.who = WhoWearsWhat(D, cfg.num_outfits, cfg.shape_dim) if cfg.num_outfits or cfg.shape_dim else None
        self.velocity_in = (nn.Sequential(nn.Linear(3, D), nn.GELU(), nn.Linear(D, D)) if cfg.joint_velocity
                            else None)  # fmt: skip
        if self.velocity_in is not None:  # starts as the model without motion
            nn.init.zeros_(self.velocity_in[2].weight)
            nn.init.zeros_(self.velocity_in[2].bias)
        self.motion_in = (MotionEncoder(cfg.motion_feature_dim, cfg.num_joints, D) if cfg.motion_window
                          else None)  # fmt: skip
        # posed-body tokens: Linear(posenc(b_k)) + E_k, like the joints (K fixed vertex ids)
        self.body_in = nn.Linear(enc_dim, D) if cfg.body_points else None
        self.body_embed = nn.Parameter(torch.randn(cfg.body_points, D) * 0.02) if cfg.body_points else None
        self.body_offset_in = (nn.Sequential(nn.Linear(4 * cfg.body_points, P), nn.GELU(), nn.Linear(P, P))
                               if cfg.body_points and cfg.joint_offsets else None)  # fmt: skip
        self.ln_latents = nn.LayerNorm(D)
        self.blocks = nn.ModuleList(LatentBlock(cfg) for _ in range(cfg.depth))
        self.ln_out = nn.LayerNorm(P)
        self.out = nn.Linear(P, cfg.point_channels)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self.set_attention_impl(cfg.attention)

    def _check_body(self, body: torch.Tensor | None, B: int) -> torch.Tensor | None:
        """The (B, K, 3) posed body the config asks for (one-line errors otherwise)."""
        K = self.config.body_points
        if not K:
            if body is not None:
                raise ValueError("this model takes no posed body (trained without --body-points)")
            return None
        if body is None:
            raise ValueError(f"this model needs the posed body ({K} vertices) besides the joints")
        if body.shape != (B, K, 3):
            raise ValueError(f"body must have shape ({B}, {K}, 3), got {tuple(body.shape)}")
        if not torch.isfinite(body).all():
            raise ValueError("body contains NaN or infinite values")
        return body

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor | PoseCondition) -> torch.Tensor:
        """Predict the noise (or x0 or v: the training config's ``prediction_type``) for every point.

        x: (B, N, C) noisy points (C = config.point_channels), any N >= 1.
        t: (B,) diffusion timesteps (integer or float), or a scalar for the whole batch.
        cond: (B, J, 3) skeleton joints in the same normalised frame as x, or a
        :class:`~pocoloco.models.conditioning.PoseCondition` (joints + outfit + body shape [+ posed
        body (B, K, 3) when ``config.body_points = K``]).
        Returns (B, N, C) in x's dtype (also under autocast).
        """
        joints, outfit, shape = split_condition(cond)
        body = body_of(cond)
        t = self._validate(x, t, joints)
        B = x.shape[0]
        feats = self._encode(x[..., :3])
        if x.shape[-1] > 3:
            feats = torch.cat([feats, x[..., 3:]], dim=-1)  # normals enter raw
        p = self.point_in(feats)  # (B, N, P)
        if self.offset_in is not None:
            p = p + self.offset_in(joint_offset_features(x[..., :3], joints))
        body = self._check_body(body, B)
        if self.body_offset_in is not None:
            p = p + self.body_offset_in(joint_offset_features(x[..., :3], body))  # (B, N, 4K) -> (B, N, P)
        p = self.ln_points(p)
        time = self.time_embed(t)[:, None].to(p.dtype)  # (B, 1, D)
        joint_tokens = self.joint_in(self._encode(joints.to(x.dtype))) + self.joint_embed  # (B, J, D)
        velocity = velocity_of(cond)
        if self.velocity_in is not None:
            if velocity is None:  # a body at rest
                velocity = torch.zeros_like(joints)
            if velocity.shape != joints.shape or not torch.isfinite(velocity).all():
                raise ValueError(f"velocity must be finite with the joints' shape {tuple(joints.shape)}, "
                                 f"got {tuple(velocity.shape)}")  # fmt: skip
            joint_tokens = joint_tokens + self.velocity_in(velocity.to(joint_tokens.dtype))
        elif velocity is not None:
            raise ValueError("this model takes no joint velocities (trained without --joint-velocity)")
        motion = motion_of(cond)
        if self.motion_in is not None:
            if motion is not None:
                want = (B, self.config.num_joints, self.config.motion_feature_dim)
                if tuple(motion.shape) != want or not torch.isfinite(motion).all():
                    raise ValueError(f"motion must be finite features of shape {want}, got {tuple(motion.shape)}")
                joint_tokens = joint_tokens + self.motion_in(motion.to(joint_tokens.dtype))
            else:  # a body at rest: all-zero features
                joint_tokens = joint_tokens + self.motion_in(joint_tokens.new_zeros(
                    B, self.config.num_joints, self.config.motion_feature_dim))  # fmt: skip
        elif motion is not None:
            raise ValueError("this model takes no motion window (trained without --motion-window)")
        latents = self.latents.expand(B, -1, -1).to(joint_tokens.dtype)  # (B, M, D)
        stream = [latents, time.to(joint_tokens.dtype), joint_tokens]
        if self.who is not None:
            stream.append(self.who(outfit, shape, B, joint_tokens.dtype))  # (B, K, D)
        elif outfit is not None or shape is not None:
            raise ValueError("this model takes no outfit or body shape (trained on joints only)")
        if self.body_in is not None:
            stream.append(self.body_in(self._encode(body.to(x.dtype))) + self.body_embed)  # (B, K, D)
        z = self.ln_latents(torch.cat(stream, dim=1))  # (B, L, D)
        for block in self.blocks:
            z, p = block(z, p)
        return self.out(self.ln_out(p)).to(x.dtype)  # (B, N, C)
