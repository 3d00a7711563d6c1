"""Scan completion: fill the holes of a partial scan with a pose-conditioned PocoLoco model.

Of the N output points, ``n_known`` are taken from the partial scan and held fixed; the other
``N - n_known`` are generated. Two ways to generate them (``init=``):

* ``"sample"`` (default; *sample-initialised inpainting*):

  1. draw ``candidates`` full clouds of the pose (K, default 4; the first uses the output's
     seed, the others seeds derived from it, :func:`candidate_seeds`) and keep the one that
     best explains the *visible* scan: the lowest mean distance from the scan's points to
     their nearest sample point (:func:`choose_candidate`; best-of-K, no ground truth used);
  2. its *hole points* (:func:`hole_points`) are where it has surface that the scan lacks: the
     points farther than ``radius`` (default 3 cm) from the scan *whose offset from their
     nearest scan point lies sideways* (|cos| to that point's normal < ``max_cos``, default
     0.8). The nearest scan point of a point in a hole is on the hole's rim and the offset runs
     along the surface; a sample point that is merely off the scanned surface (a wider skirt,
     a leg behind the shirt) has its nearest scan point inside the surface, offset along the
     normal, and is not a hole. Stray sample points (distance to their 8th neighbour in the
     sample more than 3x the median) never are. Normals: the scan's (``partial_normals``) or
     estimated from its points (PCA of 16 neighbours, :func:`estimate_normals`);
  3. the coverage c = 1 - (hole points) / N, ``n_known = round(c N)``; the cloud [scan subset;
     hole points] is renoised to step ``t`` (default 100 of 1000, SDEdit, DDPM eq. 4) and
     denoised under the pose with the scan points kept (RePaint, Lugmayr et al. 2022: known
     points replaced by ``q(x_s | x0_known)`` after every step, the samplers' ``known=``), so
     the generated points settle on the surface continuing the scan's. ``t=0``: no chain, the
     hole points as they are. ``resample`` / ``jump``: RePaint's resampling in that chain
     (:func:`pocoloco.apps.common.repaint_resampling`; off by default).

  Network calls per output: K x steps (the candidates) + min(steps, t) x resample (the chain);
  the default (dpm++sde, 25 steps, K = 4, t = 100) is 125 (the measured app numbers in
  BENCHMARKS.md used 10 steps: 50).
* ``"noise"`` (plain RePaint): the generated points start from pure noise (``t`` = T) and only
  the known-point replacement steers them; c comes from a quick probe sample (``probe_steps``
  dpm++ steps) with the same hole test. With the shipped model the generated points land
  anywhere on the body, mostly on surface the scan already covers (the point-set denoiser does
  not know which surface is covered). Kept for comparison.

Known points are returned bit-exact (copied from the scan); ``coverage=`` overrides c.
Measured on held-out frames in ``benchmarks/results/COMPLETION.md``
(``benchmarks/bench_completion.py``).

Public API: :func:`complete` -> :class:`Completion`, :func:`draw_candidates` ->
:class:`CandidateSamples` (reusable across partial scans of one pose), :func:`candidate_seeds`,
:func:`choose_candidate`, :func:`visible_distance`, :func:`hole_points`,
:func:`estimate_normals`, :func:`estimate_coverage`; for the benchmark :class:`Region`,
:data:`REGIONS`, :func:`region_mask`, :func:`score_hole`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pocoloco.apps.common import (
    check_scan,
    denoise_from,
    sample_prior,
    subset,
    to_metres,
    to_normalised,
)
from pocoloco.data.poses import check_joints
from pocoloco.diffusion.samplers import check_sampler
from pocoloco.evaluation.metrics import nearest
from pocoloco.methods.base import PointPrior
from pocoloco.ops.knn import knn_numpy

__all__ = [
    "DEFAULT_CANDIDATES",
    "DEFAULT_MAX_COS",
    "DEFAULT_RADIUS_M",
    "DEFAULT_SAMPLE_T",
    "INITS",
    "REGIONS",
    "CandidateSamples",
    "Completion",
    "Region",
    "candidate_seeds",
    "choose_candidate",
    "complete",
    "draw_candidates",
    "estimate_coverage",
    "estimate_normals",
    "hole_points",
    "region_mask",
    "score_hole",
    "visible_distance",
]  # fmt: skip

INITS = ("sample", "noise")
#: default start step of the harmonising chain for init="sample" (0 = no chain)
DEFAULT_SAMPLE_T = 100
#: default number of full samples to choose from (best-of-K by the visible part)
DEFAULT_CANDIDATES = 4
#: a sample point is a stray if its distance to its STRAY_K-th neighbour exceeds STRAY_FACTOR x the median
STRAY_K, STRAY_FACTOR = 8, 3.0
#: default hole radius (m): sample points closer than this to the scan are on the scanned surface
DEFAULT_RADIUS_M = 0.03
#: default cone test: a sample point is a hole point only if |cos| between its offset from its nearest
#: scan point and that point's normal is below this (1 = no test: every point beyond the radius)
DEFAULT_MAX_COS = 0.8
#: neighbours of the PCA normal estimate
NORMAL_K = 16
#: a generated point farther than this (m) from the full scan counts as off the surface (score_hole)
FAR_M = 0.05


@dataclass
class CandidateSamples:
    """K full samples of one pose for each of B outputs (:func:`draw_candidates`).

    points: (B, K, N, 3) float32 metres; normals: (B, K, N, 3) or None (models without normals);
    seeds: (B, K) int64, ``seeds[b] == candidate_seeds(seed of output b, K)``.
    """

    points: np.ndarray
    normals: np.ndarray | None
    seeds: np.ndarray


@dataclass
class Completion:
    """What :func:`complete` returns.

    points: (B, N, 3) float32 completed clouds in metres. normals: (B, N, 3) or None.
    known: (B, N) bool, True for points copied from the scan (the first ``num_known`` of each
    cloud), False for generated ones. coverage: the c of output 0 (or the given one);
    num_known: round(c N), capped by the scan's size (output 0's; ``known`` has each output's).
    coverage_estimated: whether c was estimated (not given). init, t: how the generated points
    started (module docstring) and the chain's start step (0: no chain). chosen: (B,) index of
    the candidate each output used (init "sample"; -1 for "noise"); visible_cm: (B, K) each
    candidate's :func:`visible_distance` in cm (empty for "noise"). normals_estimated: whether the
    scan's normals for the hole test were estimated from its points.
    """

    points: np.ndarray
    normals: np.ndarray | None
    known: np.ndarray
    coverage: float
    num_known: int
    coverage_estimated: bool
    init: str = "sample"
    t: int = DEFAULT_SAMPLE_T
    chosen: np.ndarray | None = None
    visible_cm: np.ndarray | None = None
    normals_estimated: bool = False


# --------------------------------------------------------------------------------- geometry
def estimate_normals(points: np.ndarray, k: int = NORMAL_K, at: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (unoriented) of the cloud ``points`` (M, 3): the direction of least variance
    of each point's ``k`` nearest neighbours (itself included; PCA, Hoppe et al. 1992).
    at: indices (A,) of the points to estimate them for (default all). Returns (A, 3) float64."""

    pts = np.asarray(points, np.float64)
    at = np.arange(len(pts)) if at is None else np.asarray(at, np.int64)
    k = min(int(k), len(pts))
    if k < 3:
        raise ValueError(f"need at least 3 points to estimate normals, got {len(pts)}")
    _, nb = knn_numpy(pts[at].astype(np.float32), pts.astype(np.float32), k)  # (A, k)
    q = pts[nb] - pts[nb].mean(1, keepdims=True)  # (A, k, 3)
    _, vecs = np.linalg.eigh(np.einsum("aki,akj->aij", q, q))  # eigenvalues ascending
    return vecs[:, :, 0]


def _unit(n: np.ndarray) -> np.ndarray:
    n = np.asarray(n, np.float64)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def hole_points(sample: np.ndarray, partial: np.ndarray, radius: float = DEFAULT_RADIUS_M,
                num: int | None = None, *, normals: np.ndarray | None = None,
                max_cos: float | None = None) -> tuple[np.ndarray, float]:  # fmt: skip
    """Where a full sample (N, 3) has surface that the partial scan (M, 3) lacks.

    Stray sample points (distance to their ``STRAY_K``-th neighbour in the sample more than
    ``STRAY_FACTOR`` x the median of that distance) are dropped. A kept point is a *hole point*
    if it is at least ``radius`` from the scan and, with ``max_cos`` (< 1), its offset from its
    nearest scan point q makes |cos| < max_cos with q's normal (``normals`` (M, 3); None:
    estimated with :func:`estimate_normals`): off-surface points lie along the normal, hole
    points sideways of the hole's rim (module docstring). ``max_cos=None`` (or >= 1): distance only.

    Returns ``(indices into sample, coverage)``. Without ``max_cos`` coverage c is the share of the
    kept points within ``radius`` of the scan (as before the cone test existed); with it, 1 - (hole
    points) / N. The indices are the hole points farthest first (``num=None``), or ``num`` points:
    the hole points farthest first, then, if more are asked for, the other kept points farthest first.
    """

    sample = np.asarray(sample, np.float32)
    k = min(STRAY_K, len(sample) - 1)
    if k >= 1:
        d2, _ = knn_numpy(sample, sample, k + 1)  # (N, k+1), column 0 = the point itself
        spread = np.sqrt(d2[:, k])
        keep = spread <= STRAY_FACTOR * max(float(np.median(spread)), 1e-12)
    else:
        keep = np.ones(len(sample), bool)
    d, q = nearest(sample, partial)
    kept = np.flatnonzero(keep)
    hole = keep & (d >= radius)
    cone = max_cos is not None and max_cos < 1.0
    if cone:
        idx = np.flatnonzero(hole)
        if len(idx):
            if normals is None:
                u, inv = np.unique(q[idx], return_inverse=True)
                n = estimate_normals(partial, at=u)[inv.reshape(-1)]
            else:
                n = _unit(np.asarray(normals)[q[idx]])
            off = sample[idx].astype(np.float64) - np.asarray(partial, np.float64)[q[idx]]
            cos = np.abs((off * n).sum(1)) / np.maximum(d[idx].astype(np.float64), 1e-12)
            hole[idx[cos >= max_cos]] = False
        coverage = 1.0 - float(hole.sum()) / len(sample)
    else:
        coverage = float((d[kept] < radius).mean()) if len(kept) else 0.0
    order = kept[np.argsort(-d[kept], kind="stable")]
    first = order[hole[order]]
    if num is None:
        return first, coverage
    return np.concatenate([first, order[~hole[order]]])[: max(int(num), 0)], coverage


def visible_distance(sample: np.ndarray, partial: np.ndarray) -> float:
    """How well a full sample (N, 3) explains the visible scan (M, 3): the mean distance (m) from
    the scan's points to their nearest sample point. Points of the sample in the scan's holes do
    not count against it (no scan point is there), points missing where the scan has surface do."""
    return float(nearest(partial, sample)[0].mean())


def choose_candidate(samples: np.ndarray, partial: np.ndarray) -> tuple[int, np.ndarray]:
    """Best-of-K by the visible part: ``(index, distances (K,) m)`` of the candidate (K, N, 3) with
    the lowest :func:`visible_distance` to the scan (M, 3); the first of equal ones."""
    scores = np.array([visible_distance(s, partial) for s in np.asarray(samples)])
    return int(np.argmin(scores)), scores


# ------------------------------------------------------------------------------- candidates
def candidate_seeds(seed: int, k: int) -> list[int]:
    """The seeds of the ``k`` candidate samples of the output with seed ``seed``: ``seed`` itself
    (so k = 1 is the plain sample of that seed), then ``SeedSequence([seed, j]).generate_state(1)``
    for j = 1 .. k-1 (32-bit, independent of the other outputs' seeds)."""
    if k < 1:
        raise ValueError(f"candidates must be >= 1, got {k}")
    return [int(seed)] + [int(np.random.SeedSequence([int(seed), j]).generate_state(1)[0]) for j in range(1, k)]


def draw_candidates(prior: PointPrior, joints: np.ndarray, num_points: int,
                    seeds: Sequence[int], candidates: int = DEFAULT_CANDIDATES, sampler: str = "dpm++sde",
                    steps: int | None = None) -> CandidateSamples:  # fmt: skip
    """``candidates`` full samples of the pose (J, 3) for each output seed (:func:`candidate_seeds`),
    ``num_points`` points each; ``len(seeds) x candidates x steps`` denoiser calls."""
    seeds = [int(s) for s in seeds]
    all_seeds = np.array([candidate_seeds(s, candidates) for s in seeds], np.int64)  # (B, K)
    joints = check_joints("joints", joints, prior.num_joints)
    points, normals = sample_prior(prior, joints, num_points, all_seeds.reshape(-1).tolist(), sampler, steps)
    B, K = all_seeds.shape
    normals = None if normals is None else normals.reshape(B, K, num_points, 3)
    return CandidateSamples(points.reshape(B, K, num_points, 3), normals, all_seeds)


def estimate_coverage(prior: PointPrior, partial: np.ndarray, joints: np.ndarray,
                      num_points: int, radius: float = DEFAULT_RADIUS_M, seed: int = 0, probe_steps: int = 5,
                      normals: np.ndarray | None = None, max_cos: float | None = None) -> float:  # fmt: skip
    """Coverage c in [0, 1] of a quick probe sample (``probe_steps`` dpm++ steps) of N points: the
    share of its points within ``radius`` metres of ``partial`` (M, 3), or with ``max_cos`` 1 - its
    hole points (:func:`hole_points`) / N."""

    if not radius > 0:
        raise ValueError(f"coverage radius must be > 0, got {radius}")
    probe = sample_prior(prior, joints, num_points, [seed], "dpm++", probe_steps)[0][0]
    if max_cos is not None and max_cos < 1.0:
        return hole_points(probe, partial, radius, normals=normals, max_cos=max_cos)[1]
    d, _ = nearest(probe, partial)
    return float((d < radius).mean())


# ------------------------------------------------------------------------------- completion
def complete(
    prior: PointPrior,
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
    max_cos: float | None = DEFAULT_MAX_COS,
    candidates: int = DEFAULT_CANDIDATES,
    samples: CandidateSamples | None = None,
    probe_steps: int = 5,
    init: str = "sample",
    t: int | None = None,
    resample: int = 1,
    jump: int = 10,
    name: str = "partial scan",
) -> Completion:
    """Complete a partial scan ``partial`` (M, 3) metres of the pose ``joints`` (J, 3) into ``num``
    clouds of ``num_points`` points (module docstring). Output b depends only on ``seeds[b]``
    (default 0..B-1) and the options.

    partial_normals: (M, 3) the scan's normals: needed by models with normals (point_channels 6);
        used by the hole test (estimated from the points if None).
    radius, max_cos: the hole test (:func:`hole_points`); max_cos None or 1: distance only.
    candidates: K full samples to choose from (init "sample"; 1 = the output seed's sample).
    samples: the K candidates, already drawn (:func:`draw_candidates` with the same seeds, K >=
        candidates, N = num_points), e.g. to complete several partial scans of one pose.
    init: "sample" (default) or "noise". t: start step in [0, T] of init "sample"'s harmonising
        chain (default 100; 0: none); "noise" always starts at T. steps: sampler steps of the
        candidates and of the chain (capped at t). resample, jump: RePaint's resampling in the
        chain (:func:`pocoloco.apps.common.denoise_from`; resample 1 = off).

    Raises one-line ValueErrors for an empty / non-finite scan, a scan in the wrong unit or far
    from the pose, and bad options.
    """

    C, T, normalisation = prior.point_channels, prior.schedule.num_timesteps, prior.normalisation
    joints = check_joints("joints", joints, prior.num_joints)
    partial = check_scan(name, partial, joints, normalisation.root_joint)
    M = partial.shape[0]
    if num < 1 or num_points < 1:
        raise ValueError(f"num and num_points must be >= 1, got {num} and {num_points}")
    check_sampler(sampler, steps, T)
    if init not in INITS:
        raise ValueError(f"unknown completion init {init!r}; choose one of: {', '.join(INITS)}")
    t = (DEFAULT_SAMPLE_T if init == "sample" else T) if t is None else int(t)
    if init == "sample" and not 0 <= t <= T:
        raise ValueError(f"t must be in [0, {T}] (0: no harmonising chain), got {t}")
    if init == "noise" and not 1 <= t <= T:
        raise ValueError(f"t must be in [1, {T}] (the model's training timesteps), got {t}")
    seeds = list(range(num)) if seeds is None else [int(s) for s in seeds]
    if len(seeds) != num:
        raise ValueError(f"seeds must have num={num} entries, got {len(seeds)}")
    if partial_normals is not None:
        partial_normals = np.asarray(partial_normals, np.float32)
        if partial_normals.shape != partial.shape or not np.isfinite(partial_normals).all():
            raise ValueError(f"{name}: normals must be finite and of the points' shape {partial.shape}, "
                             f"got {partial_normals.shape}")  # fmt: skip
    if C == 6 and partial_normals is None:
        raise ValueError(f"{name}: the model predicts normals (point_channels 6) but the scan has none")
    if not radius > 0:
        raise ValueError(f"coverage radius must be > 0, got {radius}")
    if max_cos is not None and not 0.0 < max_cos <= 1.0:
        raise ValueError(f"max_cos must be in (0, 1] (1: no normal test), got {max_cos}")
    if coverage is not None and not 0.0 <= coverage <= 1.0:
        raise ValueError(f"coverage must be in [0, 1], got {coverage}")
    if candidates < 1:
        raise ValueError(f"candidates must be >= 1, got {candidates}")
    if resample < 1 or jump < 1:
        raise ValueError(f"resample and jump must be >= 1, got {resample} and {jump}")
    if samples is not None:
        want = np.array([candidate_seeds(s, candidates) for s in seeds], np.int64)
        sp = np.asarray(samples.points)
        if (sp.ndim != 4 or sp.shape[0] != num or sp.shape[1] < candidates or sp.shape[2] != num_points
                or not np.array_equal(np.asarray(samples.seeds)[:, :candidates], want)):  # fmt: skip
            raise ValueError(f"samples must be draw_candidates(..., num_points={num_points}, seeds={seeds}, "
                             f"candidates>={candidates}), got points {sp.shape}")  # fmt: skip
    cone = max_cos is not None and max_cos < 1.0
    normals_estimated = cone and partial_normals is None
    estimated = coverage is None
    chosen = np.full(num, -1, np.int64)
    visible = np.zeros((num, 0))
    pick = None  # (B, N, 3 [+3]) the chosen full samples
    if init == "sample":
        if samples is None:
            samples = draw_candidates(prior, joints, num_points, seeds, candidates,
                                      sampler, steps)  # fmt: skip
        visible = np.zeros((num, candidates))
        for b in range(num):
            chosen[b], visible[b] = choose_candidate(samples.points[b, :candidates], partial)
        pick_pts = samples.points[np.arange(num), chosen]
        pick_nrm = None if samples.normals is None else samples.normals[np.arange(num), chosen]
        holes = [hole_points(pick_pts[b], partial, radius, normals=partial_normals, max_cos=max_cos)
                 for b in range(num)]  # fmt: skip
        covs = [1.0 - len(h) / num_points if cone else c for h, c in holes]
        pick = (pick_pts, pick_nrm)
    else:
        c0 = coverage if not estimated else estimate_coverage(
            prior, partial, joints, num_points, radius, seeds[0], probe_steps,
            normals=partial_normals, max_cos=max_cos)  # fmt: skip
        covs = [c0] * num
    if not estimated:
        covs = [float(coverage)] * num
    n_known = [min(round(c * num_points), M) for c in covs]
    mask = np.zeros((num, num_points), bool)
    xk = np.zeros((num, num_points, C), np.float32)
    picks = [subset(M, n_known[b], [seeds[b], 1]) for b in range(num)]
    for b, idx in enumerate(picks):
        mask[b, : n_known[b]] = True
        nrm = None if partial_normals is None else partial_normals[idx]
        xk[b, : n_known[b]] = to_normalised(normalisation, partial[idx], nrm, joints, C)
    if pick is None:  # plain RePaint from pure noise
        x = denoise_from(prior, joints, None, T, sampler, steps, seeds, known=(mask, xk),
                         resample=resample, jump=jump)  # fmt: skip
        t_used = T
    else:
        x0 = xk.copy()
        for b in range(num):
            n_gen = num_points - n_known[b]
            if n_gen == 0:
                continue
            hole = hole_points(pick[0][b], partial, radius, num=n_gen, normals=partial_normals, max_cos=max_cos)[0]
            if len(hole) < n_gen:  # more strays than spare points: fill up with the sample's others
                rest = np.setdiff1d(np.arange(num_points), hole)
                hole = np.concatenate([hole, rest[: n_gen - len(hole)]])
            nrm = None if pick[1] is None else pick[1][b][hole]
            x0[b, n_known[b]:] = to_normalised(normalisation, pick[0][b][hole], nrm, joints, C)
        t_used = 0 if mask.all() else t
        if t_used > 0:
            chain_seeds = [int(samples.seeds[b, chosen[b]]) for b in range(num)]
            x = denoise_from(prior, joints, x0, t_used, sampler,
                             None if steps is None else min(steps, t_used), chain_seeds, known=(mask, xk),
                             resample=resample, jump=jump)  # fmt: skip
        else:
            x = x0
    points, normals = to_metres(normalisation, x, joints)
    for b, idx in enumerate(picks):  # bit-exact known points (the sampler keeps them up to round-off)
        points[b, : n_known[b]] = partial[idx]
        if normals is not None:
            normals[b, : n_known[b]] = _unit(partial_normals[idx]).astype(np.float32)
    return Completion(points, normals, mask, float(covs[0]), n_known[0], estimated, init, t_used, chosen,
                      100.0 * visible, normals_estimated)  # fmt: skip


# ------------------------------------------------------------------------------------ benchmark
@dataclass(frozen=True)
class Region:
    """A region removed from a scan by the benchmark: the points within ``radius`` m of the mean
    of ``joints``, or (``below=True``) the points below the mean height of ``joints`` (z, the
    synthetic data's up axis)."""

    joints: tuple[int, ...]
    radius: float | None = None
    below: bool = False


#: named regions of the benchmark (SMPL joint order: 4 / 5 left / right knee, 22 left hand)
REGIONS: dict[str, Region] = {
    "left_hand": Region((22,), 0.12),
    "right_knee": Region((5,), 0.15),  # one knee
    "hem": Region((4, 5), 0.22),  # between the knees: the hem of a skirt / the lower legs
    "below_knees": Region((4, 5), below=True),  # everything below the knees
}


def region_mask(points: np.ndarray, joints: np.ndarray, region: str | Region | tuple[Sequence[int], float]) -> np.ndarray:
    """(M,) bool: the points of ``points`` (M, 3) in the region (:class:`Region`).

    region: a name of :data:`REGIONS`, a :class:`Region` or ``(joint indices, radius m)``.
    """
    if isinstance(region, str):
        if region not in REGIONS:
            raise ValueError(f"unknown region {region!r}; choose one of: {', '.join(REGIONS)}")
        region = REGIONS[region]
    if not isinstance(region, Region):
        region = Region(tuple(region[0]), float(region[1]))
    centre = np.asarray(joints, np.float64)[list(region.joints)].mean(0)
    pts = np.asarray(points, np.float64)
    if region.below:
        return pts[:, 2] < centre[2]
    return np.linalg.norm(pts - centre, axis=1) < region.radius


def score_hole(generated: np.ndarray, scan: np.ndarray, inside: np.ndarray, far: float = FAR_M) -> dict[str, float]:
    """How well generated points (G, 3) fill a region removed from a full scan (M, 3) (``inside``
    (M,) bool marks the removed points): ``s2m_cm``, the mean distance from the removed scan points
    to their nearest generated point (is the hole covered?); ``m2s_cm``, the mean distance from the
    generated points to their nearest point of the *full* scan (are they on the surface?);
    ``far_share``, the share of generated points farther than ``far`` m from it; ``num``: G.
    With no generated point, s2m is measured to the partial scan (the hole stays open) and the
    other two are NaN."""

    scan = np.asarray(scan, np.float32)
    gt = scan[np.asarray(inside, bool)]
    gen = np.asarray(generated, np.float32).reshape(-1, 3)
    if len(gt) == 0:
        raise ValueError("the region holds no scan point")
    if len(gen) == 0:
        return {"s2m_cm": 100.0 * float(nearest(gt, scan[~np.asarray(inside, bool)])[0].mean()),
                "m2s_cm": float("nan"), "far_share": float("nan"), "num": 0.0}  # fmt: skip
    d, _ = nearest(gen, scan)
    return {"s2m_cm": 100.0 * float(nearest(gt, gen)[0].mean()), "m2s_cm": 100.0 * float(d.mean()),
            "far_share": float((d > far).mean()), "num": float(len(gen))}  # fmt: skip
