"""POP's shape decoder (SupMat A.1) and its fast CPU paths: an 8-layer MLP over the query points
(width 256, input skip into layer 4, Softplus(beta=20) + BatchNorm on all but the last layer),
branching into a displacement head and a normal head.

Fast paths (same weights and outputs as plain ``nn.Linear`` + ``BatchNorm1d`` + ``Softplus``):

* training: BatchNorm and softplus run as one autograd node (``_BatchNormSoftplus``) in row
  chunks through one scratch buffer, with a vectorised in-place softplus whose backward keeps
  PyTorch's threshold exactly;
* inference: BatchNorm is folded into the linear weights and the MLP runs per row chunk in
  reused buffers; the skip layer does not concatenate.

``forward_conv1d`` is the reference structure of the public code (1x1 convolutions over all
pixels of the query map). Shapes: R rows (B x P valid query points), C channels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ShapeDecoder"]


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
