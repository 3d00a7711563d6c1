"""A differentiable energy distance between two sets of clouds, on their probe-distance embedding.

The distribution judge (:mod:`pocoloco.evaluation.distribution`) maps a cloud to its unsigned
distance at P fixed probe points and scores sets of clouds by the energy distance of those
embeddings (Székely & Rizzo 2013; the energy score of Gneiting & Raftery 2007, eq. 22, is its
one-reference case): ``2 E||X - Y|| - E||X - X'|| - E||Y - Y'||``, zero iff the two distributions
agree. The same statistic written in torch, so a loss can match a *set* of draws to a set of
targets (a distilled student's spread, issue 42) instead of each draw to its own target, which
pulls the draws to their mean.
"""

from __future__ import annotations

import torch

__all__ = ["box_probes", "probe_embedding", "set_energy_distance"]


def probe_embedding(points: torch.Tensor, probes: torch.Tensor) -> torch.Tensor:
    """(..., P) distance from each probe (..., P, 3) to the nearest point of its cloud (..., N, 3)."""
    if points.shape[-1] != 3 or probes.shape[-1] != 3:
        raise ValueError(f"points and probes must end in 3 coordinates, got {tuple(points.shape)}, {tuple(probes.shape)}")
    d2 = (probes.unsqueeze(-2) - points.unsqueeze(-3)).square().sum(-1)  # (..., P, N)
    return (d2.amin(-1) + 1e-12).sqrt()


def box_probes(clouds: torch.Tensor, num: int, generator: torch.Generator | None = None,
               margin: float = 0.05) -> torch.Tensor:  # fmt: skip
    """(G, num, 3) probes uniform in the bounding box of each group of clouds (G, M, N, 3), grown by
    ``margin`` of its size on every side (the same probes for every cloud of a group: a fixed map)."""
    flat = clouds.detach().flatten(1, 2)  # (G, M N, 3)
    lo, hi = flat.amin(1), flat.amax(1)
    pad = margin * (hi - lo)
    lo, hi = lo - pad, hi + pad
    u = torch.rand(clouds.shape[0], num, 3, generator=generator, device=clouds.device, dtype=clouds.dtype)
    return lo.unsqueeze(1) + u * (hi - lo).unsqueeze(1)


def _pair_mean(a: torch.Tensor, b: torch.Tensor | None = None) -> torch.Tensor:
    """(G,) mean Euclidean distance between rows of a (G, M, P) and b (G, K, P); b None: between
    the distinct rows of a (0 for a single row)."""
    other = a if b is None else b
    d = ((a.unsqueeze(2) - other.unsqueeze(1)).square().sum(-1) + 1e-12).sqrt()  # (G, M, K)
    if b is not None:
        return d.mean((1, 2))
    m = a.shape[1]
    if m < 2:
        return a.new_zeros(a.shape[0])
    off = ~torch.eye(m, dtype=torch.bool, device=a.device)
    return (d * off).sum((1, 2)) / (m * (m - 1))


def set_energy_distance(samples: torch.Tensor, refs: torch.Tensor) -> dict[str, torch.Tensor]:
    """Energy distance per group of sample embeddings (G, M, P) against reference embeddings
    (G, K, P), as the judge's :func:`~pocoloco.evaluation.distribution.energy_distance` computes it
    (cross term over all pairs, spreads over distinct pairs): ``energy_distance`` (G,) =
    2 ``to_refs`` - ``spread_samples`` - ``spread_refs``, and ``energy_score`` (G,) = ``to_refs`` -
    ``spread_samples`` / 2, the mean energy score of the samples over the references (a proper
    score: its expectation is least when the samples' distribution is the references'; never
    negative, by the triangle inequality)."""
    if samples.ndim != 3 or refs.ndim != 3 or samples.shape[::2] != refs.shape[::2]:
        raise ValueError(f"samples (G, M, P) and refs (G, K, P) must share G and P, got {tuple(samples.shape)}, "
                         f"{tuple(refs.shape)}")  # fmt: skip
    to_refs, spread_s, spread_r = _pair_mean(samples, refs), _pair_mean(samples), _pair_mean(refs)
    return {"to_refs": to_refs, "spread_samples": spread_s, "spread_refs": spread_r,
            "energy_distance": 2.0 * to_refs - spread_s - spread_r, "energy_score": to_refs - 0.5 * spread_s}  # fmt: skip
