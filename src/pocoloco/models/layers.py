"""Shared network layers: positional encodings, timestep embedding, attention blocks.

Shapes use the project letters: B batch, N points (queries), J joints (keys of the
cross-attention), H heads, C channels, D model width.

Attention has two implementations with identical maths (``attention``):

* ``"sdpa"``: ``torch.nn.functional.scaled_dot_product_attention``. Never
  materialises the N x N score matrix on kernels that support it (flash /
  memory-efficient on GPUs, the flash-style CPU kernel on CPUs), so memory is
  linear in N.
* ``"dense"``: the score matrix is materialised with ``einsum`` and soft-maxed in
  float32, the way the original PocoLoco code computes it. Kept as the slow,
  obviously-correct reference for tests and as the benchmark baseline.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

ATTENTION_IMPLS = ("sdpa", "dense")
POSENC_KINDS = ("nerf", "transformer")


# ---------------------------------------------------------------------------
# positional encodings (stateless)
# ---------------------------------------------------------------------------


def check_finite_inputs(x: torch.Tensor, joints: torch.Tensor, t: torch.Tensor) -> None:
    """A denoiser's inputs (points (B, N, C), joints (B, J, 3), timesteps (B,)) hold no NaN / inf
    (one-line ValueError). CPU tensors only: on a GPU each check would wait for the device on every
    call; inputs are checked where they enter (poses, frames, packs), and the trainer checks its
    logged loss."""
    if x.device.type != "cpu":
        return
    if not torch.isfinite(x).all():
        raise ValueError("x contains NaN or infinite values")
    if not torch.isfinite(joints).all():
        raise ValueError("joints contain NaN or infinite values")
    if t.is_floating_point() and not torch.isfinite(t).all():
        raise ValueError("t contains NaN or infinite values")


def nerf_encoding(x: torch.Tensor, num_freqs: int, include_input: bool = False) -> torch.Tensor:
    """NeRF-style encoding, PocoLoco paper Sec. 3.2 (the equation after Eq. 3).

    gamma(x) = (sin(2^0 pi x), ..., sin(2^{L-1} pi x), cos(2^0 pi x), ..., cos(2^{L-1} pi x))
    for every coordinate. Layout of the last axis: all sines (coordinate-major:
    x at frequencies 0..L-1, then y, then z), then all cosines, then the raw input
    if ``include_input``.

    x: (..., A) coordinates (A = 3 for points and joints).
    Returns (..., 2*A*L [+ A]).
    """
    freqs = (2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)) * math.pi  # (L,)
    args = (x[..., :, None] * freqs).flatten(-2)  # (..., A*L)
    parts = [torch.sin(args), torch.cos(args)]
    if include_input:
        parts.append(x)
    return torch.cat(parts, dim=-1)


def transformer_encoding(x: torch.Tensor, num_freqs: int, include_input: bool = False) -> torch.Tensor:
    """Transformer-style (Vaswani et al. 2017, Sec. 3.5) encoding applied per axis.

    This is what the original PocoLoco code uses. Each coordinate gets d = 2L
    channels with frequencies w_i = 10000^(-2i/d), i = 0..L-1, interleaved
    (sin(w_0 x), cos(w_0 x), sin(w_1 x), ...); the three axes are concatenated, so
    "L = 7" gives 6L = 42 channels in total (the "d = 42" of the code). The
    frequencies lie in [10000^(-(L-1)/L), 1]: coarse compared with the NeRF form,
    which suits coordinates of order 1.

    x: (..., A). Returns (..., 2*A*L [+ A]); raw input appended if ``include_input``.
    """
    i = torch.arange(num_freqs, device=x.device, dtype=x.dtype)
    freqs = torch.exp(-math.log(10000.0) * (2.0 * i) / (2.0 * num_freqs))  # (L,)
    args = x[..., :, None] * freqs  # (..., A, L)
    enc = torch.stack([torch.sin(args), torch.cos(args)], dim=-1).flatten(-3)  # (..., A*L*2)
    if include_input:
        enc = torch.cat([enc, x], dim=-1)
    return enc


def positional_encoding(
    x: torch.Tensor, kind: str, num_freqs: int, include_input: bool = False
) -> torch.Tensor:
    """Dispatch to ``nerf_encoding`` or ``transformer_encoding``; (..., A) -> (..., 2AL [+A])."""
    if kind == "nerf":
        return nerf_encoding(x, num_freqs, include_input)
    if kind == "transformer":
        return transformer_encoding(x, num_freqs, include_input)
    raise ValueError(f"unknown positional encoding {kind!r}; choose one of: {', '.join(POSENC_KINDS)}")


def positional_encoding_dim(in_channels: int, num_freqs: int, include_input: bool = False) -> int:
    """Output channels of either encoding for ``in_channels`` coordinates."""
    return 2 * in_channels * num_freqs + (in_channels if include_input else 0)


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of (possibly fractional) diffusion timesteps (DDPM / ADM).

    t: (B,). Returns (B, dim) float32: [cos(t w_0..w_{h-1}), sin(t w_0..w_{h-1})],
    w_i = max_period^(-i/h), h = dim // 2 (a zero column is appended for odd dim).
    """
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]  # (B, h)
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


# ---------------------------------------------------------------------------
# attention (stateless)
# ---------------------------------------------------------------------------


def dense_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, dropout_p: float = 0.0) -> torch.Tensor:
    """Reference multi-head attention with a materialised score matrix.

    softmax(Q K^T / sqrt(C)) V (Vaswani et al. 2017, Eq. 1; PocoLoco Eq. 4), the
    softmax computed in float32 as in the original code. Memory O(B H N M).

    q: (B, H, N, C); k, v: (B, H, M, C). Returns (B, H, N, C).
    """
    scale = q.shape[-1] ** -0.5
    weight = torch.einsum("bhnc,bhmc->bhnm", q * scale, k)  # (B, H, N, M)
    weight = torch.softmax(weight.float(), dim=-1).to(v.dtype)
    if dropout_p > 0.0:
        weight = F.dropout(weight, p=dropout_p)
    return torch.einsum("bhnm,bhmc->bhnc", weight, v)


def attention(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, impl: str = "sdpa", dropout_p: float = 0.0
) -> torch.Tensor:
    """Multi-head attention, (B, H, N, C) x (B, H, M, C)^2 -> (B, H, N, C).

    impl: ``"sdpa"`` (fused kernel, memory linear in N) or ``"dense"`` (``dense_attention``).
    """
    if impl == "sdpa":
        return F.scaled_dot_product_attention(q, k, v, dropout_p=dropout_p)
    if impl == "dense":
        return dense_attention(q, k, v, dropout_p=dropout_p)
    raise ValueError(f"unknown attention impl {impl!r}; choose one of: {', '.join(ATTENTION_IMPLS)}")


# ---------------------------------------------------------------------------
# modules
# ---------------------------------------------------------------------------


class TimestepEmbedder(nn.Module):
    """Timestep t (B,) -> one token (B, D): sinusoidal(D) -> Linear -> GELU -> Linear."""

    def __init__(self, width: int):
        super().__init__()
        self.width = width
        self.mlp = nn.Sequential(nn.Linear(width, width), nn.GELU(), nn.Linear(width, width))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        emb = timestep_embedding(t, self.width)  # (B, D) float32
        return self.mlp(emb.to(self.mlp[0].weight.dtype))


class MultiHeadAttention(nn.Module):
    """Multi-head attention with its own projections.

    Self-attention when ``context`` is None (Q, K, V from x), cross-attention
    otherwise (Q from x, K and V from ``context``), PocoLoco Eqs. 4-5.
    ``impl`` selects the kernel (see module docstring); set it with
    ``PocoLocoDenoiser.set_attention_impl``.
    """

    def __init__(
        self,
        width: int,
        heads: int,
        head_dim: int,
        context_width: int | None = None,
        dropout: float = 0.0,
        impl: str = "sdpa",
    ):
        super().__init__()
        inner = heads * head_dim
        self.heads, self.head_dim, self.dropout, self.impl = heads, head_dim, dropout, impl
        self.is_cross = context_width is not None
        self.to_q = nn.Linear(width, inner)
        self.to_kv = nn.Linear(context_width if self.is_cross else width, 2 * inner)
        self.proj = nn.Linear(inner, width)

    def _split(self, h: torch.Tensor) -> torch.Tensor:
        B, M, _ = h.shape
        return h.view(B, M, self.heads, self.head_dim).transpose(1, 2)  # (B, H, M, C)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """x: (B, N, D); context: (B, M, Dc) or None. Returns (B, N, D)."""
        B, N, _ = x.shape
        src = context if self.is_cross else x
        q = self._split(self.to_q(x))  # (B, H, N, C)
        k, v = self.to_kv(src).chunk(2, dim=-1)  # (B, M, H*C) each
        k, v = self._split(k), self._split(v)  # (B, H, M, C)
        p = self.dropout if self.training else 0.0
        out = attention(q, k, v, impl=self.impl, dropout_p=p)  # (B, H, N, C)
        out = out.transpose(1, 2).reshape(B, N, self.heads * self.head_dim)
        return self.proj(out)


class MLP(nn.Module):
    """Linear(D, rD) -> GELU -> Linear(rD, D) (-> dropout)."""

    def __init__(self, width: int, ratio: float = 4.0, dropout: float = 0.0):
        super().__init__()
        hidden = int(width * ratio)
        self.fc1 = nn.Linear(width, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, width)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.fc2(self.act(self.fc1(x))))


class DenoiserBlock(nn.Module):
    """One PocoLoco layer (paper Sec. 5.1 "Network Architecture"), pre-LayerNorm residuals:

    h = h + SelfAttn(LN(h));  h = h + CrossAttn(LN(h), joints);  h = h + MLP(LN(h)).

    h: (B, 1+N, D) time token and point tokens; joints: (B, J, D) joint tokens.
    """

    def __init__(self, width: int, heads: int, head_dim: int, mlp_ratio: float, dropout: float = 0.0):
        super().__init__()
        self.ln_self = nn.LayerNorm(width)
        self.self_attn = MultiHeadAttention(width, heads, head_dim, dropout=dropout)
        self.ln_cross = nn.LayerNorm(width)
        self.cross_attn = MultiHeadAttention(width, heads, head_dim, context_width=width, dropout=dropout)
        self.ln_mlp = nn.LayerNorm(width)
        self.mlp = MLP(width, mlp_ratio, dropout)
        self.drop = nn.Dropout(dropout)

    def forward(self, h: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        h = h + self.drop(self.self_attn(self.ln_self(h)))
        h = h + self.drop(self.cross_attn(self.ln_cross(h), joints))
        return h + self.mlp(self.ln_mlp(h))


class PointDenoiserBase(nn.Module):
    """What both point denoisers share (:mod:`pocoloco.models.denoisers`): the attention switch, the
    parameter count, the point encoding and the input checks. Subclasses set ``self.config`` with
    ``point_channels``, ``num_joints``, ``posenc``, ``num_freqs`` and ``posenc_include_input``."""

    config: Any

    def set_attention_impl(self, impl: str):
        """Switch every attention layer to ``"sdpa"`` or ``"dense"`` (same weights, same maths)."""
        if impl not in ATTENTION_IMPLS:
            raise ValueError(f"attention impl must be one of {ATTENTION_IMPLS}, got {impl!r}")
        for m in self.modules():
            if isinstance(m, MultiHeadAttention):
                m.impl = impl
        self.attention_impl = impl
        return self

    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    def _encode(self, xyz: torch.Tensor) -> torch.Tensor:
        """(..., 3) coordinates -> their positional encoding (``config.posenc``)."""
        cfg = self.config
        return positional_encoding(xyz, cfg.posenc, cfg.num_freqs, cfg.posenc_include_input)

    def _validate(self, x: torch.Tensor, t: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """Shapes of x (B, N, C), joints (B, J, 3), t (B,) or scalar (one-line errors); t as (B,)."""
        cfg = self.config
        if x.ndim != 3 or x.shape[-1] != cfg.point_channels or x.shape[1] < 1:
            raise ValueError(f"x must have shape (B, N, {cfg.point_channels}) with N >= 1, got {tuple(x.shape)}")
        B = x.shape[0]
        if joints.ndim != 3 or joints.shape[0] != B or joints.shape[2] != 3:
            raise ValueError(f"joints must have shape ({B}, {cfg.num_joints}, 3), got {tuple(joints.shape)}")
        if joints.shape[1] != cfg.num_joints:
            raise ValueError(f"joints must have {cfg.num_joints} joints (config.num_joints), got {joints.shape[1]}")
        t = torch.as_tensor(t, device=x.device)
        if t.ndim == 0:
            t = t.expand(B)
        if t.shape != (B,):
            raise ValueError(f"t must have shape ({B},) or be a scalar, got {tuple(t.shape)}")
        check_finite_inputs(x, joints, t)
        return t
