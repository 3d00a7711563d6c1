"""Scan completion: fill the holes of a partial scan with a pose-conditioned PocoLoco model.

Of the N output points, ``n_known`` are taken from the partial scan and held fixed; the other
``N - n_known`` are generated. Two ways to generate them (``init=``):

* ``"sample"`` (default; *sample-initialised inpainting*): draw one full cloud of the pose
  (the chosen sampler, the output's seed). Its points farther than ``radius`` (default 3 cm)
  from the partial scan lie where the scan has no surface: the hole. Stray points of the
  sample (isolated: distance to their 8th neighbour in the sample more than 3x the median) are
  ignored. The coverage c is the share of the remaining sample points within ``radius`` of the
  scan, ``n_known = round(c N)``, and the ``N - n_known`` non-stray sample points farthest from
  the scan initialise the generated points. The cloud [scan subset; hole points] is then
  renoised to step ``t`` (default 100 of 1000, SDEdit, DDPM eq. 4) and denoised under the pose
  with the scan points kept (RePaint, Lugmayr et al. 2022, without its resampling jumps: known
  points replaced by ``q(x_s | x0_known)`` after every step, the samplers' ``known=`` option),
  so the generated points are harmonised with the scan's.
* ``"noise"`` (plain RePaint without resampling): the generated points start from pure noise
  (``t`` = T) and only the known-point replacement steers them; c comes from a quick probe
  sample (``probe_steps`` dpm++ steps). With the shipped, undertrained model this fails: the
  generated points land anywhere on the body, mostly on surface the scan already covers (the
  point-set denoiser does not know which surface is covered), e.g. 77 cm Chamfer to a removed
  hand vs. 5 cm for a fresh sample (BENCHMARKS.md, "Applications"). Kept for comparison.

Known points are returned bit-exact (copied from the scan); ``coverage=`` overrides c.

Public API: :func:`complete` -> :class:`Completion`, :func:`estimate_coverage`,
:func:`hole_points`, :func:`evaluate_completion` (the benchmark's metric), :func:`region_mask`;
CLI pieces :func:`add_complete_arguments` / :func:`cmd_complete` (``pocoloco complete``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pocoloco.apps.common import (
    check_scan,
    denoise_from,
    subset,
    to_metres,
    to_normalised,
)
from pocoloco.data.dataset import Normalisation
from pocoloco.data.poses import check_joints
from pocoloco.diffusion.samplers import check_sampler
from pocoloco.evaluation.metrics import chamfer_cm, nearest
from pocoloco.methods.pocoloco.sampling import sample_clouds
from pocoloco.ops.knn import knn_numpy

__all__ = ["Completion", "INITS", "add_complete_arguments", "cmd_complete", "complete", "estimate_coverage",
           "evaluate_completion", "hole_points", "region_mask", "REGIONS"]  # fmt: skip

INITS = ("sample", "noise")
#: default start step of the harmonising chain for init="sample"
DEFAULT_SAMPLE_T = 100
#: a sample point is a stray if its distance to its STRAY_K-th neighbour exceeds STRAY_FACTOR x the median
STRAY_K, STRAY_FACTOR = 8, 3.0
#: default coverage radius (m): about 5 % of the shipped model's sample points lie farther than
#: 3-6 cm from a complete scan of the pose, so a smaller radius mistakes them for holes
DEFAULT_RADIUS_M = 0.06

#: named regions for the benchmark: name -> (joint indices whose mean is the centre, radius m)
REGIONS: dict[str, tuple[tuple[int, ...], float]] = {
    "left_hand": ((22,), 0.12),
    "right_knee": ((5,), 0.15),
    "hem": ((4, 5), 0.22),  # between the knees: the hem of a skirt / the lower legs
}


@dataclass
class Completion:
    """What :func:`complete` returns.

    points: (K, N, 3) float32 completed clouds in metres. normals: (K, N, 3) or None.
    known: (K, N) bool, True for points copied from the scan (the first ``num_known`` of each
    cloud), False for generated ones. coverage: the c used; num_known: round(c N), capped by the
    scan's size. coverage_estimated: whether c was estimated (not given). init, t: how the
    generated points started (module docstring) and the chain's start step.
    """

    points: np.ndarray
    normals: np.ndarray | None
    known: np.ndarray
    coverage: float
    num_known: int
    coverage_estimated: bool
    init: str = "sample"
    t: int = DEFAULT_SAMPLE_T


def estimate_coverage(model, normalisation: Normalisation, config: Any, partial: np.ndarray, joints: np.ndarray,
                      num_points: int, radius: float = DEFAULT_RADIUS_M, seed: int = 0,
                      probe_steps: int = 5) -> float:  # fmt: skip
    """Share c in [0, 1] of a quick probe sample's N points within ``radius`` metres of ``partial`` (M, 3)."""

    if not radius > 0:
        raise ValueError(f"coverage radius must be > 0, got {radius}")
    probe = sample_clouds(model, normalisation, config, joints, 1, num_points, sampler="dpm++",
                          steps=probe_steps, seeds=[seed]).points[0]  # fmt: skip
    d, _ = nearest(probe, partial)
    return float((d < radius).mean())


def hole_points(sample: np.ndarray, partial: np.ndarray, radius: float = DEFAULT_RADIUS_M,
                num: int | None = None) -> tuple[np.ndarray, float]:  # fmt: skip
    """Where a full sample (N, 3) has surface that the partial scan (M, 3) lacks.

    Stray sample points (distance to their ``STRAY_K``-th neighbour in the sample more than
    ``STRAY_FACTOR`` x the median of that distance) are dropped. Returns ``(indices into
    sample, coverage)``: coverage c = share of the kept points within ``radius`` of the scan;
    the indices are the kept points farther than ``radius`` (``num=None``), or the ``num`` kept
    points farthest from the scan (``num`` given; fewer if fewer are kept), farthest first.
    """

    sample = np.asarray(sample, np.float32)
    k = min(STRAY_K, len(sample) - 1)
    if k >= 1:
        d2, _ = knn_numpy(sample, sample, k + 1)  # (N, k+1), column 0 = the point itself
        spread = np.sqrt(d2[:, k])
        keep = spread <= STRAY_FACTOR * max(float(np.median(spread)), 1e-12)
    else:
        keep = np.ones(len(sample), bool)
    d, _ = nearest(sample, partial)
    kept = np.flatnonzero(keep)
    coverage = float((d[kept] < radius).mean()) if len(kept) else 0.0
    order = kept[np.argsort(-d[kept], kind="stable")]
    if num is None:
        return order[d[order] >= radius], coverage
    return order[: max(int(num), 0)], coverage


def complete(
    model,
    normalisation: Normalisation,
    config: Any,
    partial: np.ndarray,
    joints: np.ndarray,
    num_points: int,
    *,
    partial_normals: np.ndarray | None = None,
    num: int = 1,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seeds: Sequence[int] | None = None,
    coverage: float | None = None,
    radius: float = DEFAULT_RADIUS_M,
    probe_steps: int = 5,
    init: str = "sample",
    t: int | None = None,
    name: str = "partial scan",
) -> Completion:
    """Complete a partial scan ``partial`` (M, 3) metres of the pose ``joints`` (J, 3) into ``num``
    clouds of ``num_points`` points (module docstring). ``partial_normals`` (M, 3) are needed by
    models with normals (point_channels 6). Output k depends only on ``seeds[k]`` (default 0..K-1).
    init: "sample" (default) or "noise"; t: start step in [1, T] of init="sample"'s harmonising
    chain (default 100; "noise" always starts at T). steps: sampler steps of the full sample and
    of the chain (capped at t).

    Raises one-line ValueErrors for an empty / non-finite scan, a scan in the wrong unit or far
    from the pose, and bad options.
    """

    C, T = int(config.denoiser.point_channels), int(config.num_timesteps)
    joints = check_joints("joints", joints, int(config.denoiser.num_joints))
    partial = check_scan(name, partial, joints, normalisation.root_joint)
    if num < 1 or num_points < 1:
        raise ValueError(f"num and num_points must be >= 1, got {num} and {num_points}")
    check_sampler(sampler, steps, T)
    if init not in INITS:
        raise ValueError(f"unknown completion init {init!r}; choose one of: {', '.join(INITS)}")
    t = (DEFAULT_SAMPLE_T if init == "sample" else T) if t is None else int(t)
    if not 1 <= t <= T:
        raise ValueError(f"t must be in [1, {T}] (the model's training timesteps), got {t}")
    seeds = list(range(num)) if seeds is None else [int(s) for s in seeds]
    if len(seeds) != num:
        raise ValueError(f"seeds must have num={num} entries, got {len(seeds)}")
    if C == 6 and partial_normals is None:
        raise ValueError(f"{name}: the model predicts normals (point_channels 6) but the scan has none")
    if not radius > 0:
        raise ValueError(f"coverage radius must be > 0, got {radius}")
    if coverage is not None and not 0.0 <= coverage <= 1.0:
        raise ValueError(f"coverage must be in [0, 1], got {coverage}")
    estimated = coverage is None
    M = partial.shape[0]
    full = None
    if init == "sample":  # one full sample per output: the hole's points and (output 0's) coverage
        full = sample_clouds(model, normalisation, config, joints, num, num_points, sampler=sampler, steps=steps,
                             seeds=seeds)  # fmt: skip
        if estimated:
            coverage = hole_points(full.points[0], partial, radius)[1]
    elif estimated:
        coverage = estimate_coverage(model, normalisation, config, partial, joints, num_points, radius, seeds[0],
                                     probe_steps)  # fmt: skip
    n_known = min(int(round(coverage * num_points)), M)
    n_gen = num_points - n_known
    mask = np.zeros((num, num_points), bool)
    mask[:, :n_known] = True
    xk = np.zeros((num, num_points, C), np.float32)
    picks = [subset(M, n_known, [seeds[k], 1]) for k in range(num)]
    for k, idx in enumerate(picks):
        nrm = None if partial_normals is None else partial_normals[idx]
        xk[k, :n_known] = to_normalised(normalisation, partial[idx], nrm, joints, C)
    x0 = None
    if full is not None and n_gen > 0:
        x0 = xk.copy()
        for k in range(num):
            hole = hole_points(full.points[k], partial, radius, num=n_gen)[0]
            if len(hole) < n_gen:  # more strays than spare points: fill up with the sample's others
                rest = np.setdiff1d(np.arange(num_points), hole)
                hole = np.concatenate([hole, rest[: n_gen - len(hole)]])
            nrm = None if full.normals is None else full.normals[k][hole]
            x0[k, n_known:] = to_normalised(normalisation, full.points[k][hole], nrm, joints, C)
    x = denoise_from(model, normalisation, config, joints, x0, t if x0 is not None else T, sampler,
                     None if steps is None else min(steps, t if x0 is not None else T), seeds,
                     known=(mask, xk))  # fmt: skip
    points, normals = to_metres(normalisation, x, joints)
    for k, idx in enumerate(picks):  # bit-exact known points (the sampler keeps them up to round-off)
        points[k, :n_known] = partial[idx]
        if normals is not None:
            n = np.asarray(partial_normals, np.float32)[idx]
            normals[k, :n_known] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return Completion(points, normals, mask, float(coverage), n_known, estimated, init, t if x0 is not None else T)


# ------------------------------------------------------------------------------------ benchmark
def region_mask(points: np.ndarray, joints: np.ndarray, region: str | tuple[Sequence[int], float]) -> np.ndarray:
    """(M,) bool: points within the region's radius of its centre (mean of its joints).

    region: a name of :data:`REGIONS` or ``(joint indices, radius m)``.
    """
    if isinstance(region, str):
        if region not in REGIONS:
            raise ValueError(f"unknown region {region!r}; choose one of: {', '.join(REGIONS)}")
        region = REGIONS[region]
    ids, radius = region
    centre = np.asarray(joints, np.float64)[list(ids)].mean(0)
    return np.linalg.norm(np.asarray(points, np.float64) - centre, axis=1) < radius


def evaluate_completion(model, normalisation: Normalisation, config: Any, scan: np.ndarray, joints: np.ndarray,
                        region, num_points: int, seed: int = 0, sampler: str = "dpm++sde", steps: int | None = None,
                        radius: float = DEFAULT_RADIUS_M, coverage: float | None = None, t: int | None = None,
                        noise: bool = True) -> dict[str, float] | None:  # fmt: skip
    """Remove ``region`` from a full scan (M, 3), complete it, score the generated points.

    The GT is an N-point subset of the scan (the density of an N-point cloud), the GT of the
    removed region its part inside the region. Reported (cm, PocoLoco Chamfer = S2M + M2S):

    * ``inpaint_chamfer_cm``: :func:`complete` (init "sample", start step ``t``): its generated
      points vs. the GT region; ``inpaint_full_chamfer_cm``: the whole completed cloud vs. the GT;
    * ``fresh_chamfer_cm``: a fresh full sample of the pose (same seed and sampler), restricted
      to its points whose nearest GT point lies in the region (an oracle selection: it uses the
      GT), vs. the GT region; ``fresh_full_chamfer_cm``: the whole fresh sample vs. the GT;
      ``fresh_hole_chamfer_cm``: the fresh sample's points that :func:`hole_points` picks (as
      many as were generated; no GT used), i.e. the completion's starting points, not harmonised;
    * with ``noise``, ``noise_chamfer_cm``: plain RePaint (init "noise", probe coverage) the same way.

    Also the estimated vs. true coverage (share of scan points outside the region) and point
    counts. None if the region holds no scan point (or all of them).
    """

    inside = region_mask(scan, joints, region)
    gsel = subset(len(scan), num_points, [seed, 2])
    gt = scan[gsel]
    gt_region = gt[inside[gsel]]
    if not inside.any() or len(gt_region) == 0 or inside.all():
        return None
    nan = float("nan")
    kw = dict(num=1, sampler=sampler, steps=steps, seeds=[seed], coverage=coverage, radius=radius)
    comp = complete(model, normalisation, config, scan[~inside], joints, num_points, init="sample", t=t, **kw)
    gen = comp.points[0][~comp.known[0]]
    fresh = sample_clouds(model, normalisation, config, joints, 1, num_points, sampler=sampler, steps=steps,
                          seeds=[seed]).points[0]  # fmt: skip
    fresh_region = fresh[inside[gsel][nearest(fresh, gt)[1]]]
    fresh_hole = fresh[hole_points(fresh, scan[~inside], radius, num=len(gen))[0]]
    out = {
        "fresh_hole_chamfer_cm": chamfer_cm(fresh_hole, gt_region) if len(fresh_hole) else nan,
        "inpaint_chamfer_cm": chamfer_cm(gen, gt_region) if len(gen) else nan,
        "inpaint_full_chamfer_cm": chamfer_cm(comp.points[0], gt),
        "fresh_chamfer_cm": chamfer_cm(fresh_region, gt_region) if len(fresh_region) else nan,
        "fresh_full_chamfer_cm": chamfer_cm(fresh, gt),
        "noise_chamfer_cm": nan, "noise_full_chamfer_cm": nan,
        "coverage_estimated": comp.coverage, "coverage_true": 1.0 - float(inside.mean()),
        "num_generated": float(len(gen)), "num_gt_region": float(len(gt_region)),
        "num_fresh_region": float(len(fresh_region)),
    }  # fmt: skip
    if noise:
        cn = complete(model, normalisation, config, scan[~inside], joints, num_points, init="noise", **kw)
        gen_n = cn.points[0][~cn.known[0]]
        out["noise_chamfer_cm"] = chamfer_cm(gen_n, gt_region) if len(gen_n) else nan
        out["noise_full_chamfer_cm"] = chamfer_cm(cn.points[0], gt)
        out["noise_coverage_estimated"] = cn.coverage
    return out
