"""POP: the Power of Points (Ma et al. 2021, "The Power of Points for Modeling Humans in
Clothing", ICCV), re-implemented from the paper and REFERENCE.md ("POP").

Pipeline (paper Fig. 2, Sec. 3.1-3.2, SupMat A.1):

1. Pose encoder: a UV position map I (B, 3, Ri, Ri) of the posed *mean-shape* body
   (Ri = 128) -> UNet (7 stride-2 4x4 convs + BatchNorm + LeakyReLU(0.2); 7 mirrored
   [ReLU, ConvTranspose2d, BatchNorm] ups with skips; no BatchNorm on the last) ->
   pose features P (B, Cp=64, Ri, Ri).
2. Geometric feature tensor G (n_outfits, Cg=64, Ri, Ri), init N(0, 0.01^2),
   auto-decoded (one per outfit, shared by all its frames), smoothed by three
   bias-free 5x5 convolutions.
3. Query points: the valid pixels of an Rq x Rq UV map (Rq = 256) of the subject's
   posed body: UV u_i, position p_i, local frame T_i (barycentric blend of the
   per-vertex skinning transforms, LoopReg-style).
4. Shape decoder f_w([u_i, z_i^P, z_i^G]) with z = bilinear lookup at u_i: 8-layer MLP
   (width 256, input skip into layer 4 as DeepSDF, Softplus(beta=20) + BatchNorm on
   all but the last layer), branching after layer 5 into a displacement head and a
   normal head.
5. Eq. (2): x_i = T_i (s r_i) + p_i with s = 0.02 (the scaling of the public code,
   REFERENCE.md); n_i = normalize(T_i n~_i).

Decoder implementations (same weights, same outputs at the valid query pixels):

* ``"linear_valid"`` (default, fast): features are sampled only at the P valid query
  UVs (``grid_sample``, border padding = the bilinear up-sampling's edge clamp) and
  the MLP is ``nn.Linear`` + ``BatchNorm1d`` over the B*P valid points.
* ``"conv1d_all_pixels"`` (reference, the structure of the public code): the feature
  tensors are bilinearly up-sampled to Rq x Rq and the MLP runs as 1x1 ``Conv1d`` over
  all Rq^2 pixels, valid or not; the valid pixels are picked at the end. Its
  BatchNorm statistics are taken over the valid pixels only (so the two paths agree
  in training mode too; the public code also averages over the empty pixels).

Losses (paper Eq. 3-6 with REFERENCE.md weights): ``pop_losses``. Training step,
optimiser and unseen-outfit fitting (Eq. 7): ``train_step``, ``make_optimizer``,
``fit_unseen_outfit``. Data: ``pop_sample_from_frame``, ``collate_pop``,
``POPDataset``.

Shapes: B batch, V body vertices, P valid query points, N scan points, C channels,
Ri input map resolution, Rq query map resolution.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pocoloco.body.surface import (
    BodySurface,
    barycentric_interpolate,
    blend_transforms,
    pixel_uv,
    uv_to_grid,
)

__all__ = [
    "DECODER_IMPLS",
    "POP",
    "POPBatch",
    "POPConfig",
    "POPDataset",
    "POPFit",
    "POPLosses",
    "POPOutput",
    "POPQuery",
    "POP_PRESETS",
    "POPSample",
    "collate_pop",
    "fit_unseen_outfit",
    "make_optimizer",
    "normal_weight_at",
    "pop_losses",
    "pop_losses_reference",
    "pop_preset",
    "pop_sample_from_frame",
    "train_step",
]

DECODER_IMPLS = ("linear_valid", "conv1d_all_pixels")


# ---------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class POPConfig:
    """POP hyper-parameters (paper SupMat A.1-A.2; REFERENCE.md "POP").

    unet_channels: output channels of the stride-2 down convolutions (their number is
        the UNet depth; ``input_resolution`` must be divisible by 2**depth).
    decoder_layers / skip_layer / branch_layer: 1-based MLP layer indices; layer
        ``skip_layer`` takes [hidden, input]; layers >= ``branch_layer`` are duplicated
        into the displacement and normal heads; the last layer has no BN/activation.
    displacement_scale: s in x = T (s r) + p (0.02 in the public code).
    pose_input: "mean_shape" = the UNet sees the posed mean-shape body (paper Sec. 3.2,
        body-shape agnostic), "subject" = the subject's own posed body.
    Loss weights: s2m and m2s 1e4 each, normal 0.1 from ``normal_start`` (training
        steps; the paper switches at epoch 250 of 400), displacement 2e3, feature 1.
    """

    input_resolution: int = 128
    query_resolution: int = 256
    unet_channels: tuple[int, ...] = (32, 64, 128, 256, 256, 256, 256)
    pose_channels: int = 64
    geom_channels: int = 64
    geom_smooth_layers: int = 3
    geom_kernel: int = 5
    geom_init_std: float = 0.01
    decoder_width: int = 256
    decoder_layers: int = 8
    skip_layer: int = 4
    branch_layer: int = 6
    softplus_beta: float = 20.0
    displacement_scale: float = 0.02
    decoder_impl: Literal["linear_valid", "conv1d_all_pixels"] = "linear_valid"
    transform_mode: Literal["blend", "polar"] = "blend"
    pose_input: Literal["mean_shape", "subject"] = "mean_shape"
    num_scan_points: int = 40000
    w_s2m: float = 1e4
    w_m2s: float = 1e4
    w_normal: float = 0.1
    normal_start: int = 0
    w_displacement: float = 2e3
    w_feature: float = 1.0
    lr: float = 3e-4
    lr_features: float = 5e-4
    batch_size: int = 4

    def __post_init__(self):
        def pos_int(name):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"POPConfig.{name} must be a positive integer, got {v!r}")

        for name in ("input_resolution", "query_resolution", "pose_channels", "geom_channels", "geom_kernel",
                     "decoder_width", "decoder_layers", "num_scan_points", "batch_size"):  # fmt: skip
            pos_int(name)
        if not self.unet_channels or any(int(c) < 1 for c in self.unet_channels):
            raise ValueError(f"POPConfig.unet_channels must be positive integers, got {self.unet_channels!r}")
        object.__setattr__(self, "unet_channels", tuple(int(c) for c in self.unet_channels))
        if self.input_resolution % (2 ** len(self.unet_channels)):
            raise ValueError(f"POPConfig.input_resolution={self.input_resolution} must be divisible by "
                             f"2**{len(self.unet_channels)} (one halving per UNet level)")  # fmt: skip
        if self.geom_kernel % 2 == 0:
            raise ValueError(f"POPConfig.geom_kernel must be odd, got {self.geom_kernel}")
        if not 2 <= self.skip_layer < self.branch_layer <= self.decoder_layers:
            raise ValueError("POPConfig needs 2 <= skip_layer < branch_layer <= decoder_layers, got "
                             f"{self.skip_layer}, {self.branch_layer}, {self.decoder_layers}")  # fmt: skip
        if self.decoder_impl not in DECODER_IMPLS:
            raise ValueError(f"POPConfig.decoder_impl must be one of {DECODER_IMPLS}, got {self.decoder_impl!r}")
        if self.transform_mode not in ("blend", "polar"):
            raise ValueError(f"POPConfig.transform_mode must be 'blend' or 'polar', got {self.transform_mode!r}")
        if self.pose_input not in ("mean_shape", "subject"):
            raise ValueError(f"POPConfig.pose_input must be 'mean_shape' or 'subject', got {self.pose_input!r}")
        for name in ("w_s2m", "w_m2s", "w_normal", "w_displacement", "w_feature", "geom_init_std"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"POPConfig.{name} must be >= 0, got {getattr(self, name)!r}")
        if not (self.lr > 0 and self.lr_features > 0 and self.displacement_scale > 0):
            raise ValueError("POPConfig.lr, lr_features and displacement_scale must be > 0")
        if self.normal_start < 0:
            raise ValueError(f"POPConfig.normal_start must be >= 0, got {self.normal_start}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["unet_channels"] = list(self.unet_channels)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> POPConfig:
        return cls(**{**d, "unet_channels": tuple(d["unet_channels"])})


POP_PRESETS: dict[str, POPConfig] = {
    # paper size: 128^2 UNet input, 256^2 query map, ~11.3M network parameters
    "paper": POPConfig(),
    # CPU presets: smaller maps and widths, same structure
    "small": POPConfig(input_resolution=64, query_resolution=128, unet_channels=(16, 32, 64, 128, 128, 128),
                       pose_channels=32, geom_channels=32, decoder_width=128, num_scan_points=8192),  # fmt: skip
    "tiny": POPConfig(input_resolution=32, query_resolution=32, unet_channels=(8, 16, 32, 32, 32),
                      pose_channels=8, geom_channels=8, geom_kernel=3, decoder_width=32, num_scan_points=1024),  # fmt: skip
}


def pop_preset(name: str, **overrides) -> POPConfig:
    """A named preset (``POP_PRESETS``), optionally with fields replaced."""
    if name not in POP_PRESETS:
        raise ValueError(f"unknown POP preset {name!r}; choose from {sorted(POP_PRESETS)}")
    return replace(POP_PRESETS[name], **overrides)


# ---------------------------------------------------------------------------
# data containers
# ---------------------------------------------------------------------------


@dataclass
class POPBatch:
    """One training/inference batch (torch), all pelvis-centred (root joint at 0).

    pose_vertices: (B, V, 3) body fed to the pose encoder (posed mean shape, or the
                   subject's body when ``pose_input="subject"``).
    body_vertices: (B, V, 3) the subject's posed body (query points p_i).
    vtransf:       (B, V, 3, 3) per-vertex skinning transforms relative to the bind pose.
    outfit:        (B,) int64 outfit id (row of the geometric feature tensor).
    scan_points:   (B, N, 3) ground-truth points, or None (inference).
    scan_normals:  (B, N, 3) their unit normals, or None.
    """

    pose_vertices: torch.Tensor
    body_vertices: torch.Tensor
    vtransf: torch.Tensor
    outfit: torch.Tensor
    scan_points: torch.Tensor | None = None
    scan_normals: torch.Tensor | None = None

    def to(self, device) -> POPBatch:
        return POPBatch(*(None if t is None else t.to(device) for t in
                          (self.pose_vertices, self.body_vertices, self.vtransf, self.outfit,
                           self.scan_points, self.scan_normals)))  # fmt: skip


@dataclass
class POPQuery:
    """P query points on the body surface: face_idx (P,) int64, barycentric (P, 3), uv (P, 2)."""

    face_idx: torch.Tensor
    barycentric: torch.Tensor
    uv: torch.Tensor

    def __len__(self) -> int:
        return int(self.face_idx.shape[0])

    def subset(self, idx) -> POPQuery:
        """The points ``idx`` (K,) of this query."""
        i = torch.as_tensor(idx, dtype=torch.long, device=self.face_idx.device)
        return POPQuery(self.face_idx[i], self.barycentric[i], self.uv[i])


@dataclass
class POPOutput:
    """Decoder outputs at the P valid query pixels (row-major pixel order).

    points:       (B, P, 3) x_i = T_i (s r_i) + p_i (Eq. 2).
    normals:      (B, P, 3) unit normals normalize(T_i n~_i).
    displacement: (B, P, 3) local displacement s r_i (metres, before T_i).
    base:         (B, P, 3) p_i on the posed body.
    geom:         (B, Cg, Ri, Ri) the raw (unsmoothed) geometric features used (for L_rg).
    """

    points: torch.Tensor
    normals: torch.Tensor
    displacement: torch.Tensor
    base: torch.Tensor
    geom: torch.Tensor


# ---------------------------------------------------------------------------
# network
# ---------------------------------------------------------------------------


class PoseUNet(nn.Module):
    """UNet pose encoder (SupMat A.1): (B, 3, R, R) -> (B, C_out, R, R).

    Down: [Conv2d 4x4 stride 2, BatchNorm, LeakyReLU(0.2)] per level (the innermost,
    1x1 at the paper size, has no BatchNorm so that batch 1 trains). Up: [ReLU,
    ConvTranspose2d 4x4 stride 2, BatchNorm] mirrored, each concatenated with the
    matching down output; the last up has no BatchNorm.
    """

    def __init__(self, in_channels: int, out_channels: int, channels: Sequence[int]):
        super().__init__()
        ch = list(channels)
        n = len(ch)
        self.down = nn.ModuleList()
        prev = in_channels
        for i, c in enumerate(ch):
            layers = [nn.Conv2d(prev, c, 4, 2, 1)]
            if i < n - 1:
                layers.append(nn.BatchNorm2d(c))
            layers.append(nn.LeakyReLU(0.2))
            self.down.append(nn.Sequential(*layers))
            prev = c
        self.up = nn.ModuleList()
        for j in range(n):
            src = n - 1 - j  # down level whose output feeds this up (with its skip)
            cin = ch[src] if j == 0 else 2 * ch[src]
            cout = out_channels if src == 0 else ch[src - 1]
            layers = [nn.ReLU(), nn.ConvTranspose2d(cin, cout, 4, 2, 1)]
            if src > 0:
                layers.append(nn.BatchNorm2d(cout))
            self.up.append(nn.Sequential(*layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for d in self.down:
            x = d(x)
            skips.append(x)
        x = self.up[0](skips[-1])
        for j in range(1, len(self.up)):
            x = self.up[j](torch.cat([x, skips[-1 - j]], dim=1))
        return x


_ROW_CHUNK = 8192  # rows per chunk of the element-wise passes (fast paths below)
_EXP_MINUS_20 = math.exp(-20.0)  # F.softplus's threshold 20, on the exp(-z) side


def _softplus_(z: torch.Tensor, beta: float, tmp: torch.Tensor) -> torch.Tensor:
    """z <- softplus(z) / beta, in place; ``tmp`` is scratch of z's shape. Returns z.

    ``F.softplus(x, beta)`` of x = z / beta, computed as max(z, log1p(exp(clamp(z, -60, 20))))
    / beta: z itself above PyTorch's threshold 20 (as F.softplus), no denormals below -60
    (an absolute error < 1e-26). Vectorised in-place kernels: several times faster on CPU
    than F.softplus with beta != 1, which is not vectorised. No autograd (callers own the
    backward: d softplus(z) / dz = 1 - exp(-softplus(z)))."""
    torch.clamp(z, -60.0, 20.0, out=tmp).exp_().log1p_()
    return torch.maximum(z, tmp, out=z).div_(beta)


class _BatchNormSoftplus(torch.autograd.Function):
    """softplus_beta(BatchNorm(y)) with batch statistics, as one autograd node.

    y (M, C), weight / bias (C,) -> out (M, C), mean (C,), biased var (C,). The values
    are those of ``F.softplus(F.batch_norm(y, training=True), beta)``; the point is
    speed on CPU. PyTorch's training-mode BatchNorm1d of an (M, C) tensor and
    Softplus(beta != 1) each cost several passes, copies and fresh (page-faulted)
    allocations over the activations, and dominate POP's decoder at paper size. Here
    every element-wise step runs over row chunks of ``_ROW_CHUNK`` rows into one
    reused scratch buffer, and only the output (forward) and the input gradient
    (backward) are allocated at full size; softplus is ``_softplus_``.
    tests/test_pop.py checks values, gradients and running statistics against the
    plain modules.
    """

    @staticmethod
    def forward(ctx, y, weight, bias, beta: float, eps: float):
        M = y.shape[0]
        tmp = y.new_empty(min(M, _ROW_CHUNK), y.shape[1])
        rows = y.split(_ROW_CHUNK)
        mean = torch.stack([r.sum(0) for r in rows]).sum(0) / M
        var = torch.stack([torch.sub(r, mean, out=tmp[: len(r)]).square_().sum(0) for r in rows]).sum(0) / M
        rstd = torch.rsqrt(var + eps)
        scale = (beta * weight) * rstd  # beta * BN(y) = scale * y + shift
        shift = beta * bias - mean * scale
        out = torch.empty_like(y)
        for r, o in zip(rows, out.split(_ROW_CHUNK)):
            _softplus_(torch.addcmul(shift, r, scale, out=o), beta, tmp[: len(r)])
        ctx.save_for_backward(y, out, weight, mean, rstd)
        ctx.beta = beta
        return out, mean, var

    @staticmethod
    def backward(ctx, g_out, _g_mean, _g_var):
        y, out, weight, mean, rstd = ctx.saved_tensors
        M, beta = y.shape[0], ctx.beta
        tmp = y.new_empty(min(M, _ROW_CHUNK), y.shape[1])
        g_y = torch.empty_like(y)
        chunks = list(zip(y.split(_ROW_CHUNK), out.split(_ROW_CHUNK), g_out.split(_ROW_CHUNK), g_y.split(_ROW_CHUNK)))
        g_bias = torch.zeros_like(mean)
        g_weight = torch.zeros_like(mean)
        for r, o, go, g in chunks:
            # g = dL / d BN(y) = g_out * sigmoid(beta BN(y)) = g_out * (1 - exp(-beta out)), and
            # g_out where the forward was linear (beta BN(y) > 20, exp(-beta out) < exp(-20)); kept in g_y
            F.threshold_(torch.mul(o, -beta, out=g).exp_(), _EXP_MINUS_20, 0.0).neg_().add_(1.0).mul_(go)
            g_bias += g.sum(0)
            g_weight += torch.sub(r, mean, out=tmp[: len(r)]).mul_(rstd).mul_(g).sum(0)
        k = weight * rstd
        k_x, k_0 = rstd * k * g_weight / M, k * g_bias / M
        for r, _, _, g in chunks:  # dL/dy = k (g - mean(g) - xhat mean(g xhat)), xhat = (y - mean) rstd
            g.mul_(k).sub_(torch.sub(r, mean, out=tmp[: len(r)]).mul_(k_x)).sub_(k_0)
        return g_y, g_weight, g_bias, None, None


class _MLPLayer(nn.Module):
    """Linear + BatchNorm1d + Softplus (weights shared by both decoder paths)."""

    def __init__(self, cin: int, cout: int, beta: float, last: bool = False):
        super().__init__()
        self.linear = nn.Linear(cin, cout)
        self.bn = None if last else nn.BatchNorm1d(cout)
        self.beta = beta

    def folded(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Weights (cout, cin), bias (cout,) of ``beta * BN(linear(x))`` with BatchNorm's
        running statistics (evaluation mode); ``linear``'s own for the last layer."""
        W, b, bn = self.linear.weight, self.linear.bias, self.bn
        if bn is None:
            return W, b
        a = bn.weight * torch.rsqrt(bn.running_var + bn.eps)
        return W * (self.beta * a)[:, None], self.beta * ((b - bn.running_mean) * a + bn.bias)

    def forward(self, *parts: torch.Tensor) -> torch.Tensor:
        """(M, c_1), ..., (M, c_k) with sum c_k = cin (the pieces of the input, in order,
        so a skip connection needs no concatenation) -> (M, cout).

        ``softplus(bn(linear(cat(parts))), beta)``. Training mode: BatchNorm and Softplus
        run as one fused node (``_BatchNormSoftplus``). Evaluation mode: BatchNorm is
        folded into the linear weights. Other dtypes (e.g. bf16 autocast) take the
        plain modules."""
        bn = self.bn
        plain = parts[0].dtype not in (torch.float32, torch.float64) or torch.is_autocast_enabled(parts[0].device.type)
        fold = bn is not None and not bn.training and not plain
        W, b = self.folded() if fold else (self.linear.weight, self.linear.bias)
        y = _linear_parts(parts, W, b)
        if bn is None:
            return y
        if plain:
            return F.softplus(bn(y), beta=self.beta)
        if fold:
            if torch.is_grad_enabled() and y.requires_grad:  # e.g. fitting an outfit in eval mode
                return F.softplus(y).div_(self.beta)
            return _softplus_(y, self.beta, torch.empty_like(y))
        if y.shape[0] < 2:
            raise ValueError(f"BatchNorm in training mode needs more than 1 point, got {y.shape[0]}")
        out, mean, var = _BatchNormSoftplus.apply(y, bn.weight, bn.bias, self.beta, bn.eps)
        if bn.track_running_stats:
            with torch.no_grad():
                bn.num_batches_tracked.add_(1)
                f = bn.momentum if bn.momentum is not None else 1.0 / float(bn.num_batches_tracked)
                M = y.shape[0]
                bn.running_mean.mul_(1 - f).add_(mean, alpha=f)
                bn.running_var.mul_(1 - f).add_(var * (M / (M - 1)), alpha=f)
        return out

    def forward_conv1d(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """(B, cin, L) over all pixels -> (B, cout, L); BN statistics over ``valid`` (L,) only."""
        x = F.conv1d(x, self.linear.weight[:, :, None], self.linear.bias)
        if self.bn is None:
            return x
        return F.softplus(_masked_batch_norm(x, valid, self.bn), beta=self.beta)


def _linear_parts(parts, W: torch.Tensor, b: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """W cat(parts, -1) + b without the concatenation: one addmm per part (M, c_k)."""
    y, col = None, 0
    for x in parts:
        w = W[:, col : col + x.shape[1]].t()
        y = torch.addmm(b, x, w, out=out) if y is None else y.addmm_(x, w)
        col += x.shape[1]
    if col != W.shape[1]:
        raise ValueError(f"layer expects {W.shape[1]} input channels, got {col}")
    return y


def _masked_batch_norm(x: torch.Tensor, valid: torch.Tensor, bn: nn.BatchNorm1d) -> torch.Tensor:
    """BatchNorm1d of (B, C, L) with training statistics over the columns ``valid`` (K,)
    only, updating ``bn``'s running statistics exactly as ``F.batch_norm`` does."""
    if bn.training:
        xv = x.index_select(2, valid)  # (B, C, K)
        n = xv.shape[0] * xv.shape[2]
        mean = xv.mean(dim=(0, 2))
        var = xv.var(dim=(0, 2), unbiased=False)
        with torch.no_grad():
            m = bn.momentum
            bn.running_mean.mul_(1 - m).add_(m * mean.detach())
            bn.running_var.mul_(1 - m).add_(m * var.detach() * n / max(n - 1, 1))
            bn.num_batches_tracked.add_(1)
    else:
        mean, var = bn.running_mean, bn.running_var
    scale = bn.weight / torch.sqrt(var + bn.eps)
    return x * scale[None, :, None] + (bn.bias - mean * scale)[None, :, None]


class ShapeDecoder(nn.Module):
    """POP shape decoder (SupMat A.1): input [u, z^P, z^G] -> (displacement, normal).

    Layers 1..branch-1 are the trunk (layer ``skip`` takes [h, input]); layers
    branch..L are duplicated into two heads; the last layer of each head outputs 3
    channels with no BatchNorm or activation.
    """

    def __init__(self, cin: int, width: int, layers: int, skip: int, branch: int, beta: float):
        super().__init__()
        self.skip = skip
        self.trunk = nn.ModuleList()
        for i in range(1, branch):
            a = cin if i == 1 else width
            if i == skip:
                a = width + cin
            self.trunk.append(_MLPLayer(a, width, beta))

        def head():
            return nn.ModuleList(
                [_MLPLayer(width, 3 if i == layers else width, beta, last=i == layers) for i in range(branch, layers + 1)]
            )

        self.disp_head = head()
        self.normal_head = head()

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(M, cin) rows -> (M, 3) displacement, (M, 3) normal (unnormalised)."""
        if not self.training and not torch.is_grad_enabled() and x.dtype in (torch.float32, torch.float64) \
                and not torch.is_autocast_enabled(x.device.type):  # fmt: skip
            return self._forward_inference(x)
        h = x
        for i, layer in enumerate(self.trunk, start=1):
            h = layer(h, x) if i == self.skip else layer(h)  # skip: W [h, x] without the concatenation
        r, n = h, h
        for layer in self.disp_head:
            r = layer(r)
        for layer in self.normal_head:
            n = layer(n)
        return r, n

    @torch.no_grad()
    def _forward_inference(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Evaluation mode without autograd: BatchNorm folded into the weights, and the
        whole MLP run over chunks of ``_ROW_CHUNK`` rows in a few reused buffers, so a
        chunk's activations stay in cache from layer to layer and nothing of size M x
        width is allocated."""
        M, R = x.shape[0], min(x.shape[0], _ROW_CHUNK)
        width = self.trunk[0].linear.out_features
        trunk = [layer.folded() for layer in self.trunk]
        heads = [[layer.folded() for layer in head] for head in (self.disp_head, self.normal_head)]
        bufs = x.new_empty(5, R, width)  # two for the trunk, two for a head, one scratch
        outs = (x.new_empty(M, 3), x.new_empty(M, 3))
        beta = self.trunk[0].beta
        for i0 in range(0, M, R):
            xc = x[i0 : i0 + R]
            n = xc.shape[0]
            tmp = bufs[4, :n]
            h = xc
            for i, (W, b) in enumerate(trunk, start=1):
                dst = bufs[i % 2, :n]
                parts = (h, xc) if i == self.skip else (h,)
                h = _softplus_(_linear_parts(parts, W, b, out=dst), beta, tmp)
            for (layers, out) in zip(heads, outs):
                g = h
                for j, (W, b) in enumerate(layers[:-1]):
                    g = _softplus_(torch.addmm(b, g, W.t(), out=bufs[2 + j % 2, :n]), beta, tmp)
                W, b = layers[-1]
                torch.addmm(b, g, W.t(), out=out[i0 : i0 + n])
        return outs

    def forward_conv1d(self, x: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, cin, L) all pixels -> (B, 3, L), (B, 3, L) (the public code's layout)."""
        h = x
        for i, layer in enumerate(self.trunk, start=1):
            if i == self.skip:
                h = torch.cat([h, x], dim=1)
            h = layer.forward_conv1d(h, valid)
        r, n = h, h
        for layer in self.disp_head:
            r = layer.forward_conv1d(r, valid)
        for layer in self.normal_head:
            n = layer.forward_conv1d(n, valid)
        return r, n


class POP(nn.Module):
    """The POP model for one body mesh topology (e.g. anny) and ``num_outfits`` outfits.

    surface: ``BodySurface`` of the mesh (faces, UVs, which faces carry query points);
    its rasters at ``input_resolution`` and ``query_resolution`` are stored as buffers.
    num_vertices: V of the meshes passed in (checked).
    """

    def __init__(self, config: POPConfig, surface: BodySurface, num_outfits: int, num_vertices: int | None = None):
        super().__init__()
        if isinstance(num_outfits, bool) or not isinstance(num_outfits, int) or num_outfits < 1:
            raise ValueError(f"num_outfits must be a positive integer, got {num_outfits!r}")
        self.config = config
        self.faces_np = surface.faces
        self.num_vertices = int(num_vertices if num_vertices is not None else surface.faces.max() + 1)
        if self.num_vertices <= int(surface.faces.max()):
            raise ValueError(f"num_vertices={self.num_vertices} but faces index vertex {int(surface.faces.max())}")
        c = config
        self.surface = surface  # kept to build query rasters at other resolutions (``query_points``)
        self.register_buffer("faces", torch.from_numpy(surface.faces.astype(np.int64)), persistent=False)
        # the UV layout, saved with the weights so a checkpoint rebuilds the model alone (``from_state``)
        self.register_buffer("surface_uv", torch.from_numpy(np.asarray(surface.uv, np.float32)))
        self.register_buffer("surface_uv_faces", torch.from_numpy(np.asarray(surface.uv_faces, np.int64)))
        self.register_buffer("surface_faces", torch.from_numpy(surface.faces.astype(np.int64)))
        self.register_buffer("surface_face_mask", torch.from_numpy(np.asarray(surface.face_mask, bool)))
        rin = surface.raster(c.input_resolution)
        rq = surface.raster(c.query_resolution)
        if rin.num_valid == 0 or rq.num_valid == 0:
            raise ValueError("the UV layout covers no pixel at the configured resolutions")
        pin = rin.points()
        self.register_buffer("in_face", torch.from_numpy(pin.face_idx), persistent=False)
        self.register_buffer("in_bary", torch.from_numpy(pin.barycentric), persistent=False)
        self.register_buffer("in_flat", torch.from_numpy(np.flatnonzero(rin.mask)), persistent=False)
        pq = rq.points()
        self.register_buffer("q_face", torch.from_numpy(pq.face_idx), persistent=False)
        self.register_buffer("q_bary", torch.from_numpy(pq.barycentric), persistent=False)
        self.register_buffer("q_flat", torch.from_numpy(np.flatnonzero(rq.mask)), persistent=False)
        self.register_buffer("q_uv", torch.from_numpy(rq.uv()), persistent=False)  # (P, 2)
        all_pix = np.stack(np.meshgrid(np.arange(c.query_resolution), np.arange(c.query_resolution), indexing="ij"), -1)
        self.register_buffer("all_uv", torch.from_numpy(pixel_uv(all_pix.reshape(-1, 2), c.query_resolution)),
                             persistent=False)  # fmt: skip  (Rq*Rq, 2) row-major

        self.unet = PoseUNet(3, c.pose_channels, c.unet_channels)
        self.geom = nn.Parameter(torch.randn(num_outfits, c.geom_channels, c.input_resolution, c.input_resolution)
                                 * c.geom_init_std)  # fmt: skip
        pad = c.geom_kernel // 2
        self.geom_smooth = nn.Sequential(
            *[nn.Conv2d(c.geom_channels, c.geom_channels, c.geom_kernel, padding=pad, bias=False)
              for _ in range(c.geom_smooth_layers)]  # fmt: skip
        )
        self.decoder = ShapeDecoder(2 + c.pose_channels + c.geom_channels, c.decoder_width, c.decoder_layers,
                                    c.skip_layer, c.branch_layer, c.softplus_beta)  # fmt: skip

    # -- bookkeeping -------------------------------------------------------
    @classmethod
    def from_state(cls, config: POPConfig | dict, state: dict[str, torch.Tensor], num_vertices: int) -> POP:
        """Rebuild a model from ``config`` (or its ``to_dict()``) and a ``state_dict()``: the UV
        layout and the number of outfits are read from the state."""
        cfg = config if isinstance(config, POPConfig) else POPConfig.from_dict(config)
        for k in ("surface_uv", "surface_uv_faces", "surface_faces", "surface_face_mask", "geom"):
            if k not in state:
                raise ValueError(f"POP state is missing {k!r}")
        surface = BodySurface(state["surface_faces"].numpy(), state["surface_uv"].numpy(),
                              state["surface_uv_faces"].numpy(), state["surface_face_mask"].numpy().astype(bool))  # fmt: skip
        model = cls(cfg, surface, int(state["geom"].shape[0]), int(num_vertices))
        model.load_state_dict(state)
        return model

    def query_points(self, resolution: int | None = None) -> POPQuery:
        """The valid pixels of the R x R UV query map (default R = ``config.query_resolution``)
        as a :class:`POPQuery` (P points). POP's decoder takes any UV, so a map finer than the
        training one gives more points on the same surface (paper Sec. 3.1)."""
        R = self.config.query_resolution if resolution is None else int(resolution)
        if R == self.config.query_resolution:
            return POPQuery(self.q_face, self.q_bary, self.q_uv)
        r = self.surface.raster(R)
        pts = r.points()
        dev = self.q_face.device
        return POPQuery(torch.from_numpy(pts.face_idx).to(dev), torch.from_numpy(pts.barycentric).to(dev),
                        torch.from_numpy(r.uv()).to(dev))  # fmt: skip

    @property
    def num_outfits(self) -> int:
        return int(self.geom.shape[0])

    @property
    def num_query_points(self) -> int:
        return int(self.q_face.shape[0])

    def network_parameters(self) -> list[nn.Parameter]:
        """All parameters except the geometric feature tensor."""
        return [p for n, p in self.named_parameters() if n != "geom"]

    def num_network_parameters(self) -> int:
        return sum(p.numel() for p in self.network_parameters())

    @torch.no_grad()
    def add_outfit(self, features: torch.Tensor) -> int:
        """Append a fitted (1, Cg, Ri, Ri) feature tensor as a new outfit; returns its id.
        (Replaces the ``geom`` Parameter: rebuild any optimiser afterwards.)"""
        want = (1, *self.geom.shape[1:])
        if tuple(features.shape) != want:
            raise ValueError(f"features must have shape {want}, got {tuple(features.shape)}")
        self.geom = nn.Parameter(torch.cat([self.geom.data, features.to(self.geom)], 0))
        return self.num_outfits - 1

    def _check_body(self, name: str, t: torch.Tensor, tail: tuple[int, ...], B: int | None = None) -> None:
        if t.ndim != 2 + len(tail) or t.shape[1] != self.num_vertices or tuple(t.shape[2:]) != tail:
            raise ValueError(f"{name} must have shape (B, V={self.num_vertices}, {', '.join(map(str, tail))}), "
                             f"got {tuple(t.shape)}")  # fmt: skip
        if B is not None and t.shape[0] != B:
            raise ValueError(f"{name} has batch {t.shape[0]}, expected {B}")

    # -- pieces ------------------------------------------------------------
    def input_posmap(self, pose_vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) posed (mean-shape) bodies -> (B, 3, Ri, Ri) UV position maps (0 off the body)."""
        self._check_body("pose_vertices", pose_vertices, (3,))
        B, R = pose_vertices.shape[0], self.config.input_resolution
        p = barycentric_interpolate(pose_vertices, self.faces, self.in_face, self.in_bary)  # (B, Pi, 3)
        flat = pose_vertices.new_zeros(B, R * R, 3).index_copy(1, self.in_flat, p)
        return flat.reshape(B, R, R, 3).permute(0, 3, 1, 2)

    def feature_maps(self, posmap: torch.Tensor, geom: torch.Tensor) -> torch.Tensor:
        """(B, 3, Ri, Ri) posmap, (B, Cg, Ri, Ri) raw geometric features -> (B, Cp+Cg, Ri, Ri)."""
        return torch.cat([self.unet(posmap), self.geom_smooth(geom)], dim=1)

    def decode(self, feats: torch.Tensor, query_uv: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, Ri, Ri) feature maps -> raw (B, P, 3) displacement, (B, P, 3) normal at
        the valid query pixels, with the configured ``decoder_impl``; or at ``query_uv``
        (P, 2) (any UV points; ``linear_valid`` only)."""
        B = feats.shape[0]
        if query_uv is not None and self.config.decoder_impl != "linear_valid":
            raise ValueError("query points other than the training query map need decoder_impl='linear_valid'")
        q_uv = self.q_uv if query_uv is None else query_uv
        P = q_uv.shape[0]
        if self.config.decoder_impl == "linear_valid":
            grid = uv_to_grid(q_uv).to(feats.dtype)[None, None].expand(B, 1, P, 2)
            z = F.grid_sample(feats, grid, mode="bilinear", padding_mode="border", align_corners=False)  # (B, C, 1, P)
            z = z[:, :, 0].transpose(1, 2)  # (B, P, C)
            uv = q_uv.to(feats.dtype)[None].expand(B, P, 2)
            x = torch.cat([uv, z], dim=-1).reshape(B * P, -1)  # (B*P, 2+C)
            r, n = self.decoder(x)
            return r.reshape(B, P, 3), n.reshape(B, P, 3)
        # reference: up-sample to Rq x Rq, 1x1 convs over all pixels, pick the valid ones
        Rq = self.config.query_resolution
        up = F.interpolate(feats, size=(Rq, Rq), mode="bilinear", align_corners=False)  # (B, C, Rq, Rq)
        uv = self.all_uv.to(feats.dtype).t()[None].expand(B, 2, Rq * Rq)
        x = torch.cat([uv, up.reshape(B, -1, Rq * Rq)], dim=1)  # (B, 2+C, Rq*Rq)
        r, n = self.decoder.forward_conv1d(x, self.q_flat)
        return r.index_select(2, self.q_flat).transpose(1, 2), n.index_select(2, self.q_flat).transpose(1, 2)

    def forward(self, batch: POPBatch, geom: torch.Tensor | None = None, query: POPQuery | None = None) -> POPOutput:
        """Clothed points for a batch (Eq. 2). ``geom`` (B or 1, Cg, Ri, Ri) overrides the
        outfit rows (used when fitting an unseen outfit). ``query``: decode at these P surface
        points instead of the training query map (e.g. ``query_points(R)`` or a subset)."""
        pv, bv, vt = batch.pose_vertices, batch.body_vertices, batch.vtransf
        self._check_body("pose_vertices", pv, (3,))
        B = pv.shape[0]
        self._check_body("body_vertices", bv, (3,), B)
        self._check_body("vtransf", vt, (3, 3), B)
        if geom is None:
            outfit = torch.as_tensor(batch.outfit)
            if outfit.shape != (B,) or outfit.is_floating_point():
                raise ValueError(f"outfit must be an integer tensor of shape ({B},), got {tuple(outfit.shape)}")
            if B and (int(outfit.min()) < 0 or int(outfit.max()) >= self.num_outfits):
                raise ValueError(f"outfit ids must be in [0, {self.num_outfits}), got {outfit.tolist()}")
            geom = self.geom[outfit.to(self.geom.device)]
        else:
            want = tuple(self.geom.shape[1:])
            if geom.ndim != 4 or tuple(geom.shape[1:]) != want or geom.shape[0] not in (1, B):
                raise ValueError(f"geom must have shape (1 or B, {', '.join(map(str, want))}), got {tuple(geom.shape)}")
            geom = geom.expand(B, *want)
        feats = self.feature_maps(self.input_posmap(pv), geom)
        q_face, q_bary = (self.q_face, self.q_bary) if query is None else (query.face_idx, query.barycentric)
        r_raw, n_raw = self.decode(feats, None if query is None else query.uv)
        base = barycentric_interpolate(bv, self.faces, q_face, q_bary)  # (B, P, 3)
        T = blend_transforms(vt, self.faces, q_face, q_bary, self.config.transform_mode)  # (B, P, 3, 3)
        r = r_raw * self.config.displacement_scale
        x = torch.einsum("bpij,bpj->bpi", T, r) + base
        n = F.normalize(torch.einsum("bpij,bpj->bpi", T, n_raw), dim=-1, eps=1e-12)
        return POPOutput(points=x, normals=n, displacement=r, base=base, geom=geom)


# ---------------------------------------------------------------------------
# losses (paper Eq. 3-6, REFERENCE.md weights)
# ---------------------------------------------------------------------------


@dataclass
class POPLosses:
    """Weighted total and the unweighted terms (each a scalar tensor, batch-mean).

    s2m: mean over scan points of the squared distance to the nearest predicted point.
    m2s: mean over predicted points of ((x - y_nn) . n_y)^2 (point-to-plane).
    normal: mean over predicted points of |n_x - n_y_nn|_1 (0 when switched off).
    displacement: mean |s r_i|^2 (L_rd); feature: mean squared entry of G (L_rg).
    """

    total: torch.Tensor
    s2m: torch.Tensor
    m2s: torch.Tensor
    normal: torch.Tensor
    displacement: torch.Tensor
    feature: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k).detach()) for k in ("total", "s2m", "m2s", "normal", "displacement", "feature")}


def _check_scan(scan_points, scan_normals, B: int, need_normals: bool):
    if scan_points is None:
        raise ValueError("the batch has no scan_points (needed for the loss)")
    if scan_points.ndim != 3 or scan_points.shape[0] != B or scan_points.shape[2] != 3:
        raise ValueError(f"scan_points must have shape (B={B}, N, 3), got {tuple(scan_points.shape)}")
    if scan_points.shape[1] < 1:
        raise ValueError("scan_points is empty")
    if need_normals or scan_normals is not None:
        if scan_normals is None:
            raise ValueError("the loss needs scan_normals (point-to-plane / normal term) but the batch has none")
        if scan_normals.shape != scan_points.shape:
            raise ValueError(f"scan_normals {tuple(scan_normals.shape)} must match scan_points {tuple(scan_points.shape)}")


def _nearest(query: torch.Tensor, ref: torch.Tensor, backend: str) -> torch.Tensor:
    """(B, N, 3), (B, M, 3) -> (B, N) int64 index of the nearest ``ref`` point (no gradient).

    backend "kdtree": scipy cKDTree per frame (``pocoloco.ops.knn_numpy``; O(N log M), far
    faster than brute force on CPU); "brute": ``pocoloco.ops.knn`` (chunked matmul, any
    device); "auto": kdtree for CPU tensors, brute otherwise."""
    from pocoloco.ops import knn, knn_numpy

    if backend == "auto":
        backend = "kdtree" if query.device.type == "cpu" else "brute"
    if backend == "brute":
        return knn(query.detach(), ref.detach(), 1).idx[..., 0]
    if backend != "kdtree":
        raise ValueError(f"nn_backend must be 'auto', 'kdtree' or 'brute', got {backend!r}")
    q, r = query.detach().cpu().double().numpy(), ref.detach().cpu().double().numpy()
    idx = np.stack([knn_numpy(q[b], r[b], 1).idx[:, 0] for b in range(q.shape[0])])
    return torch.from_numpy(idx).to(query.device)


def pop_losses(out: POPOutput, scan_points, scan_normals, config: POPConfig, normal_weight: float | None = None,
               nn_backend: str = "auto") -> POPLosses:  # fmt: skip
    """POP training loss (Eq. 3): w_s2m L_s2m + w_m2s L_m2s + w_n L_n + w_rd L_rd + w_rg L_rg.

    out: model output (points (B, P, 3)); scan_points, scan_normals: (B, N, 3).
    normal_weight: w_n (None = ``config.w_normal``; 0 switches the normal term off).
    Nearest neighbours (``_nearest``: cKDTree on CPU, ``pocoloco.ops.knn`` otherwise) are
    chosen without gradient; distances are recomputed in torch for the chosen pairs, so
    gradients flow through them and the predicted normals, not the neighbour choice.
    """
    x, n = out.points, out.normals
    B = x.shape[0]
    wn = config.w_normal if normal_weight is None else float(normal_weight)
    _check_scan(scan_points, scan_normals, B, need_normals=True)
    y, ny = scan_points.to(x.dtype), scan_normals.to(x.dtype)
    idx_s = _nearest(y, x, nn_backend)  # (B, N) nearest predicted point of each scan point
    s2m = ((y - torch.gather(x, 1, idx_s[..., None].expand(-1, -1, 3))) ** 2).sum(-1).mean()
    idx = _nearest(x, y, nn_backend)  # (B, P) nearest scan point of each predicted point
    gather = idx[..., None].expand(-1, -1, 3)
    y_nn, n_nn = torch.gather(y, 1, gather), torch.gather(ny, 1, gather)
    m2s = (((x - y_nn) * n_nn).sum(-1) ** 2).mean()
    normal = (n - n_nn).abs().sum(-1).mean() if wn > 0 else x.new_zeros(())
    disp = (out.displacement**2).sum(-1).mean()
    feat = (out.geom**2).mean()
    total = config.w_s2m * s2m + config.w_m2s * m2s + wn * normal + config.w_displacement * disp + config.w_feature * feat
    return POPLosses(total, s2m, m2s, normal, disp, feat)


def pop_losses_reference(out: POPOutput, scan_points, scan_normals, config: POPConfig,
                         normal_weight: float | None = None) -> POPLosses:  # fmt: skip
    """Slow reference for ``pop_losses``: explicit loops over frames and points."""
    x, n = out.points, out.normals
    B, P, _ = x.shape
    wn = config.w_normal if normal_weight is None else float(normal_weight)
    s2m, m2s, normal = [], [], []
    for b in range(B):
        y, ny = scan_points[b].to(x.dtype), scan_normals[b].to(x.dtype)
        s2m += [((x[b] - y[j]) ** 2).sum(-1).min() for j in range(y.shape[0])]
        for i in range(P):
            j = int(((y - x[b, i].detach()) ** 2).sum(-1).argmin())
            m2s.append(((x[b, i] - y[j]) @ ny[j]) ** 2)
            normal.append((n[b, i] - ny[j]).abs().sum())
    s2m_t, m2s_t = torch.stack(s2m).mean(), torch.stack(m2s).mean()
    normal_t = torch.stack(normal).mean() if wn > 0 else x.new_zeros(())
    disp = torch.stack([(out.displacement[b, i] ** 2).sum() for b in range(B) for i in range(P)]).mean()
    feat = torch.stack([(g**2).sum() / g.numel() for g in out.geom]).mean()
    total = config.w_s2m * s2m_t + config.w_m2s * m2s_t + wn * normal_t + config.w_displacement * disp + config.w_feature * feat
    return POPLosses(total, s2m_t, m2s_t, normal_t, disp, feat)


# ---------------------------------------------------------------------------
# training, unseen-outfit fitting
# ---------------------------------------------------------------------------


def normal_weight_at(config: POPConfig, step: int) -> float:
    """w_n at a training step: 0 before ``config.normal_start``, ``config.w_normal`` after."""
    return config.w_normal if step >= config.normal_start else 0.0


def make_optimizer(model: POP) -> torch.optim.Adam:
    """Adam with lr ``config.lr`` for the network and ``config.lr_features`` for G (SupMat A.2)."""
    c = model.config
    return torch.optim.Adam([{"params": model.network_parameters(), "lr": c.lr},
                             {"params": [model.geom], "lr": c.lr_features}])  # fmt: skip


def train_step(model: POP, optimizer: torch.optim.Optimizer, batch: POPBatch, step: int) -> dict[str, float]:
    """One optimisation step on ``batch`` (model in training mode); returns the losses as floats.
    The normal term is on from ``config.normal_start`` and then needs ``scan_normals``."""
    model.train()
    wn = normal_weight_at(model.config, step)
    _check_scan(batch.scan_points, batch.scan_normals, batch.body_vertices.shape[0], need_normals=True)
    optimizer.zero_grad(set_to_none=True)
    out = model(batch)
    losses = pop_losses(out, batch.scan_points, batch.scan_normals, model.config, normal_weight=wn)
    losses.total.backward()
    optimizer.step()
    return losses.as_floats()


@dataclass
class POPFit:
    """Result of ``fit_unseen_outfit``: features (1, Cg, Ri, Ri) and the loss per step."""

    features: torch.Tensor
    losses: list[float] = field(default_factory=list)


def fit_unseen_outfit(model: POP, scan_points, scan_normals, pose_vertices, body_vertices, vtransf, steps: int = 400,
                      lr: float | None = None, normal_weight: float | None = None, init: torch.Tensor | None = None,
                      progress=None) -> POPFit:  # fmt: skip
    """Fit a new outfit to one scan (paper Eq. 7, Sec. 3.3): the network is frozen (eval
    mode, no gradients); only a new geometric feature tensor, initialised to the mean
    of the trained outfits' tensors, is optimised with Adam (lr ``config.lr_features``).

    scan_points, scan_normals: (N, 3) pelvis-centred scan; pose_vertices, body_vertices:
    (V, 3); vtransf: (V, 3, 3). Use ``model.add_outfit(fit.features)`` to animate it.
    init: (1, Cg, Ri, Ri) start instead of the mean outfit. progress: optional
    ``callable(done_steps, steps, loss)``.
    The model's parameters, buffers and training flag are left unchanged.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    ref = model.geom
    as_t = lambda a: torch.as_tensor(np.asarray(a) if not torch.is_tensor(a) else a, dtype=ref.dtype, device=ref.device)  # noqa: E731
    y = as_t(scan_points)
    if y.ndim != 2 or y.shape[1] != 3:
        raise ValueError(f"scan_points must have shape (N, 3), got {tuple(y.shape)}")
    ny = None if scan_normals is None else as_t(scan_normals)
    batch = POPBatch(as_t(pose_vertices)[None], as_t(body_vertices)[None], as_t(vtransf)[None],
                     torch.zeros(1, dtype=torch.long), y[None], None if ny is None else ny[None])  # fmt: skip
    was_training = model.training
    flags = {n: p.requires_grad for n, p in model.named_parameters()}
    start = model.geom.detach().mean(0, keepdim=True) if init is None else init.detach().to(model.geom)
    if tuple(start.shape) != (1, *model.geom.shape[1:]):
        raise ValueError(f"init must have shape {(1, *model.geom.shape[1:])}, got {tuple(start.shape)}")
    G = nn.Parameter(start.clone())
    opt = torch.optim.Adam([G], lr=model.config.lr_features if lr is None else lr)
    fit = POPFit(G.data)
    try:
        model.eval()
        for p in model.parameters():
            p.requires_grad_(False)
        for _ in range(steps):
            opt.zero_grad(set_to_none=True)
            out = model(batch, geom=G)
            loss = pop_losses(out, batch.scan_points, batch.scan_normals, model.config, normal_weight)
            loss.total.backward()
            opt.step()
            fit.losses.append(float(loss.total.detach()))
            if progress is not None:
                progress(len(fit.losses), steps, fit.losses[-1])
    finally:
        model.train(was_training)
        for n, p in model.named_parameters():
            p.requires_grad_(flags[n])
    fit.features = G.detach().clone()
    return fit


# ---------------------------------------------------------------------------
# data: frames -> samples -> batches
# ---------------------------------------------------------------------------


@dataclass
class POPSample:
    """One pelvis-centred training frame (numpy float32): pose_vertices (V, 3), body_vertices
    (V, 3), vtransf (V, 3, 3), scan_points (N, 3), scan_normals (N, 3), outfit id."""

    pose_vertices: np.ndarray
    body_vertices: np.ndarray
    vtransf: np.ndarray
    scan_points: np.ndarray
    scan_normals: np.ndarray
    outfit: int


def pop_sample_from_frame(frame, outfit: int, num_points: int, rng: np.random.Generator | None = None,
                          pose_vertices: np.ndarray | None = None, num_vertices: int | None = None,
                          src: str = "frame") -> POPSample:  # fmt: skip
    """A dataset ``Frame`` -> ``POPSample``: subtract the root joint (joints[0]) from the
    scan and body (POP's frames are pelvis-centred) and draw ``num_points`` scan points
    without replacement (all of them, in order, when ``rng`` is None and N == num_points).

    pose_vertices: (V, 3) body for the pose encoder, already centred on its own root
    joint (the posed mean shape); None = the subject's centred body.
    """
    from pocoloco.body.skeleton import NUM_JOINTS

    if frame.body_vertices is None or frame.vtransf is None:
        raise ValueError(f"{src}: POP needs body_vertices and vtransf (synthetic data); the frame has none")
    if frame.joints is None or np.shape(frame.joints) != (NUM_JOINTS, 3):
        raise ValueError(f"{src}: joints must have shape ({NUM_JOINTS}, 3), got {np.shape(frame.joints)}")
    V = frame.body_vertices.shape[0]
    if num_vertices is not None and V != num_vertices:
        raise ValueError(f"{src}: body has {V} vertices, the model expects {num_vertices}")
    if frame.vtransf.shape != (V, 3, 3):
        raise ValueError(f"{src}: vtransf must have shape ({V}, 3, 3), got {frame.vtransf.shape}")
    if frame.points is None or frame.normals is None:
        raise ValueError(f"{src}: POP needs scan points and normals")
    N = frame.points.shape[0]
    if N < num_points:
        raise ValueError(f"{src}: scan has {N} points, fewer than the {num_points} POP samples per frame")
    if rng is None:
        if N != num_points:
            raise ValueError(f"{src}: pass rng to subsample {N} scan points to {num_points}")
        sel = np.arange(N)
    else:
        sel = np.sort(rng.choice(N, num_points, replace=False))
    root = np.asarray(frame.joints[0], np.float32)
    body = (frame.body_vertices - root).astype(np.float32)
    if pose_vertices is None:
        pose = body
    else:
        pose = np.asarray(pose_vertices, np.float32)
        if pose.shape != (V, 3):
            raise ValueError(f"{src}: pose_vertices must have shape ({V}, 3), got {pose.shape}")
    return POPSample(pose, body, np.asarray(frame.vtransf, np.float32), (frame.points[sel] - root).astype(np.float32),
                     np.asarray(frame.normals[sel], np.float32), int(outfit))  # fmt: skip


def collate_pop(samples: Sequence[POPSample]) -> POPBatch:
    """Stack samples (same V and N) into a torch ``POPBatch``."""
    if not samples:
        raise ValueError("collate_pop needs at least one sample")
    st = lambda k: torch.from_numpy(np.stack([getattr(s, k) for s in samples]))  # noqa: E731
    try:
        return POPBatch(st("pose_vertices"), st("body_vertices"), st("vtransf"),
                        torch.tensor([s.outfit for s in samples], dtype=torch.long),
                        st("scan_points"), st("scan_normals"))  # fmt: skip
    except ValueError as e:
        raise ValueError(f"collate_pop: samples differ in shape ({e})") from None


class POPDataset(torch.utils.data.Dataset):
    """POP samples from a pocoloco dataset folder (``data/format.py``).

    Every subject is one outfit (ids in sorted subject order, or ``outfits`` given);
    frames need body_vertices and vtransf. With ``pose_input="mean_shape"`` the pose
    encoder's body is the anny mean shape posed with the sequence's ``motion.npz``
    (``pose_mean_shape``; posed once per sequence and cached), centred on its root joint.
    Item i draws ``num_points`` scan points with a generator seeded by (seed, i, epoch).
    """

    def __init__(self, root: str | os.PathLike, split: str = "train", subjects: Sequence[str] | None = None,
                 num_points: int = 40000, pose_input: str = "mean_shape", seed: int = 0,
                 outfits: dict[str, int] | None = None):  # fmt: skip
        from pocoloco.data.format import DatasetLayout, read_subject

        self.layout = DatasetLayout(root)
        subs = list(subjects) if subjects is not None else self.layout.subjects()
        if not subs:
            raise ValueError(f"{os.fspath(root)}: no subjects")
        if pose_input not in ("mean_shape", "subject"):
            raise ValueError(f"pose_input must be 'mean_shape' or 'subject', got {pose_input!r}")
        self.outfits = dict(outfits) if outfits is not None else {s: i for i, s in enumerate(sorted(subs))}
        missing = [s for s in subs if s not in self.outfits]
        if missing:
            raise ValueError(f"no outfit id for subjects {missing}")
        self.num_points, self.pose_input, self.seed, self.split, self.epoch = num_points, pose_input, seed, split, 0
        self.subject_assets = {s: read_subject(self.layout.subject_path(s)) for s in subs}
        self.items: list[tuple[str, str, int]] = []
        for s in subs:
            for q in self.layout.sequences(s, split):
                self.items += [(s, q, i) for i in self.layout.frame_indices(s, split, q)]
        if not self.items:
            raise ValueError(f"{os.fspath(root)}: no '{split}' frames for subjects {subs}")
        self._pose_cache: dict[tuple[str, str], np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.items)

    def _mean_shape_vertices(self, subject: str, seq: str, frame_index: int) -> np.ndarray:
        key = (subject, seq)
        if key not in self._pose_cache:
            from pocoloco.body.surface import pose_mean_shape
            from pocoloco.data.format import read_motion

            m = read_motion(self.layout.motion_path(subject, self.split, seq))
            posed = pose_mean_shape(m.joint_rotvecs)
            self._pose_cache[key] = (posed.vertices - posed.joints[:, :1]).astype(np.float32)  # (T, V, 3)
        verts = self._pose_cache[key]
        if frame_index >= len(verts):
            raise ValueError(f"{subject}/{seq}: frame {frame_index} is beyond motion.npz ({len(verts)} frames)")
        return verts[frame_index]

    def __getitem__(self, i: int) -> POPSample:
        from pocoloco.data.format import read_frame

        s, q, fi = self.items[i]
        path = self.layout.frame_path(s, self.split, q, fi)
        frame = read_frame(path, ("points", "normals", "joints", "frame_index", "body_vertices", "vtransf"),
                           allow_missing=True)  # fmt: skip
        pose = self._mean_shape_vertices(s, q, int(frame.frame_index)) if self.pose_input == "mean_shape" else None
        rng = np.random.default_rng([self.seed, i, self.epoch])
        return pop_sample_from_frame(frame, self.outfits[s], self.num_points, rng, pose, src=os.fspath(path))
