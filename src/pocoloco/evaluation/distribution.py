"""A proper score for clouds drawn from a distribution: the energy score of a fixed embedding.

A pose has many true garment states. Scoring a sampler against them needs a *proper*
scoring rule: one whose expected value is best when the forecast distribution is the
truth's. The energy score (Gneiting & Raftery 2007, JASA 102:359, eq. 22)::

    ES(P, y) = E d(X, y) - 1/2 E d(X, X'),     X, X' ~ P independent

is proper when d is the Euclidean distance of a fixed map of the outcome into R^P (and
strictly proper for beta in (0, 2) of ||.||^beta; a proper score of a fixed transform of the
outcome stays proper: Pic et al. 2024). With d = Chamfer distance it is **not**: Chamfer is
not conditionally negative definite, and :func:`chamfer_energy_counterexamples` gives two
1-D forecasts that beat the truth itself (why ``pocoloco eval``'s Chamfer ES is not the
headline).

Here a cloud is mapped to its **unsigned distance at P fixed probe points** placed in the
body's root / heading frame (:func:`canonical_frame`, :func:`probe_points`,
:func:`embed_cloud`); every cloud is embedded at the same point count so the resampling
noise is alike. On the embeddings, :func:`energy_score` (unbiased over sample pairs) and
:func:`energy_distance` (``2 to_refs - spread_samples - spread_refs``) are plain Euclidean
statistics. A deterministic model is one point mass: one embedding, spread 0.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .metrics import chamfer_cm

#: the probe box around the pelvis in the heading frame (metres): x left, y back, z up
PROBE_BOX = ((-0.55, 0.55), (-0.55, 0.55), (-1.05, 0.85))


def canonical_frame(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root (3,) and rotation (3, 3) of the body's heading frame from SMPL-order joints (24, 3).

    Columns of the rotation: x from the right hip to the left hip projected on the ground plane
    (Z up), z up, y = z x x (the body faces -y). ``(p - root) @ R`` maps world points into it."""
    j = np.asarray(joints, np.float64)
    if j.ndim != 2 or j.shape[1] != 3 or len(j) < 3:
        raise ValueError(f"joints must have shape (J >= 3, 3), got {j.shape}")
    x = j[1] - j[2]
    x[2] = 0.0
    n = np.linalg.norm(x)
    if not n > 1e-9:
        raise ValueError("joints: the hips are vertically aligned; no heading")
    x /= n
    z = np.array([0.0, 0.0, 1.0])
    y = np.cross(z, x)
    return j[0].copy(), np.stack([x, y, z], axis=1)


def probe_points(num: int = 512, seed: int = 0, box=PROBE_BOX) -> np.ndarray:
    """(num, 3) fixed probe points, uniform in ``box`` of the heading frame (the same for every
    cloud of an evaluation: the embedding is a fixed map)."""
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    rng = np.random.default_rng(seed)
    lo = np.array([b[0] for b in box])
    hi = np.array([b[1] for b in box])
    return lo + rng.random((num, 3)) * (hi - lo)


def embed_cloud(points: np.ndarray, joints: np.ndarray | None, probes: np.ndarray) -> np.ndarray:
    """(P,) unsigned distance [m] from each probe to the nearest point of a cloud (N, 3).

    joints: the cloud's pose (24, 3), whose heading frame the probes live in; None: the probes
    are in the cloud's own frame already."""
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"points must have shape (N >= 1, 3), got {p.shape}")
    if joints is not None:
        root, rot = canonical_frame(joints)
        p = (p - root) @ rot
    d, _ = cKDTree(p).query(np.asarray(probes, np.float64))
    return d


def _pairwise_mean(a: np.ndarray, b: np.ndarray | None = None) -> float:
    """Mean Euclidean distance between rows of a and b (b None: between distinct rows of a)."""
    if b is None:
        if len(a) < 2:
            return 0.0
        d = np.linalg.norm(a[:, None] - a[None], axis=-1)
        return float(d.sum() / (len(a) * (len(a) - 1)))
    return float(np.linalg.norm(a[:, None] - b[None], axis=-1).mean())


def energy_score(samples: np.ndarray, truth: np.ndarray) -> float:
    """Energy score of M forecast embeddings (M, P) for one true embedding (P,), lower is better:
    mean ||X_i - y|| minus half the mean over distinct pairs ||X_i - X_j|| (unbiased; M = 1, a
    point mass, has no spread term)."""
    s = np.atleast_2d(np.asarray(samples, np.float64))
    y = np.asarray(truth, np.float64).reshape(1, -1)
    if s.shape[1] != y.shape[1]:
        raise ValueError(f"samples have {s.shape[1]} features, the truth {y.shape[1]}")
    return _pairwise_mean(s, y) - 0.5 * _pairwise_mean(s)


def energy_distance(samples: np.ndarray, refs: np.ndarray) -> dict[str, float]:
    """Spread and distance statistics of forecast embeddings (M, P) against true states (K, P):
    ``to_refs`` E||X - Y||, ``spread_samples`` E||X - X'||, ``spread_refs`` E||Y - Y'|| (distinct
    pairs), ``energy_distance`` = 2 to_refs - spread_samples - spread_refs (>= 0 in expectation,
    0 iff the distributions agree), and ``energy_score``: the mean over the true states of
    :func:`energy_score`."""
    s = np.atleast_2d(np.asarray(samples, np.float64))
    r = np.atleast_2d(np.asarray(refs, np.float64))
    to_refs, spread_s, spread_r = _pairwise_mean(s, r), _pairwise_mean(s), _pairwise_mean(r)
    return {
        "to_refs": to_refs,
        "spread_samples": spread_s,
        "spread_refs": spread_r,
        "energy_distance": 2.0 * to_refs - spread_s - spread_r,
        "energy_score": to_refs - 0.5 * spread_s,
    }


# ---------------------------------------------------------------------- one pose, many states
def chamfer_matrix(a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> np.ndarray:
    """(len(a), len(b)) Chamfer distances [cm] (``metrics.chamfer_cm``: S2M + M2S)."""
    return np.array([[chamfer_cm(x, y) for y in b] for x in a], np.float64).reshape(len(a), len(b))


def nearest_neighbour_accuracy(d_ss: np.ndarray, d_rr: np.ndarray, d_sr: np.ndarray) -> tuple[float, float]:
    """Leave-one-out 1-NN accuracy of telling samples from references (Lopez-Paz & Oquab 2017; as
    1-NNA in point-cloud generation, Yang et al. 2019), its two halves apart: ``nna_refs`` = share
    of references whose nearest other cloud is a reference, ``nna_samples`` likewise for samples
    (NaN with one sample: it has no other sample). 0.5 each is indistinguishable; a model whose
    samples all sit apart from the truth scores 1.0 on both. d_ss (M, M), d_rr (K, K), d_sr (M, K)."""
    m, k = len(d_ss), len(d_rr)
    inf = np.inf
    nna_samples = float("nan")
    if m >= 2:
        own = d_ss + np.diag(np.full(m, inf))
        nna_samples = float(np.mean(own.min(1) < d_sr.min(1)))
    own_r = d_rr + np.diag(np.full(k, inf))
    nna_refs = float(np.mean(own_r.min(1) < d_sr.min(0))) if k >= 2 else float("nan")
    return nna_refs, nna_samples


def embed_refs(refs: Sequence[np.ndarray], joints: np.ndarray | None, probes: np.ndarray) -> np.ndarray:
    """(K, E) the :func:`embed_cloud` embeddings of K clouds (a pose's true states), stacked."""
    return np.stack([embed_cloud(y, joints, probes) for y in refs])


def pose_statistics(samples: Sequence[np.ndarray], refs: Sequence[np.ndarray], joints: np.ndarray | None,
                    probes: np.ndarray, chamfer: bool = True, d_rr: np.ndarray | None = None,
                    e_rr: np.ndarray | None = None) -> dict[str, float]:  # fmt: skip
    """Every statistic of the distribution judge for one pose: M forecast clouds against K true
    states (clouds (N, 3) in metres; every cloud at the same point count). Embedding statistics
    (:func:`energy_distance`, metres) and, with ``chamfer``, the Chamfer ones (cm):
    ``chamfer_to_refs`` (mean over sample-reference pairs), ``cov`` (share of references that are
    some sample's nearest reference), ``mmd`` (mean over references of the nearest sample's
    Chamfer), ``nna_refs`` / ``nna_samples`` (:func:`nearest_neighbour_accuracy`). ``d_rr``: the
    true states' :func:`chamfer_matrix` and ``e_rr`` (K, E) their :func:`embed_cloud` embeddings when
    the caller has them (one per pose, shared by its rows)."""
    if len(samples) < 1 or len(refs) < 2:
        raise ValueError(f"need >= 1 sample and >= 2 true states, got {len(samples)} and {len(refs)}")
    es = np.stack([embed_cloud(x, joints, probes) for x in samples])
    er = embed_refs(refs, joints, probes) if e_rr is None else e_rr
    out = energy_distance(es, er)
    out["num_samples"], out["num_refs"] = float(len(samples)), float(len(refs))
    if chamfer:
        d_sr = chamfer_matrix(samples, refs)
        d_ss = chamfer_matrix(samples, samples)
        d_rr = chamfer_matrix(refs, refs) if d_rr is None else d_rr
        out["chamfer_to_refs"] = float(d_sr.mean())
        out["cov"] = float(len(set(d_sr.argmin(1).tolist())) / len(refs))
        out["mmd"] = float(d_sr.min(0).mean())
        out["nna_refs"], out["nna_samples"] = nearest_neighbour_accuracy(d_ss, d_rr, d_sr)
    return out


def truth_rows(refs: Sequence[np.ndarray], joints: np.ndarray | None, probes: np.ndarray,
               chamfer: bool = True, d_rr: np.ndarray | None = None,
               e_rr: np.ndarray | None = None) -> dict[str, dict]:  # fmt: skip
    """The two oracle rows of a pose's true states (K >= 3): ``truth_loo``, a perfect sampler (each
    true state in turn is the outcome and the other K - 1 are the forecast's samples; statistics
    averaged over the K), and ``refs_medoid``, the best single guess an oracle could make (the true
    state with the smallest summed embedding distance to the others, as a point mass scored against
    the other K - 1). With ``chamfer``, each row's ``chamfer_to_refs`` (cm) as for a model: the mean
    Chamfer between two distinct true states (what a perfect sampler scores against one scan), and
    the medoid's mean Chamfer to the others (``d_rr``: their :func:`chamfer_matrix`, ``e_rr``: their
    embeddings, if at hand)."""
    k = len(refs)
    if k < 3:
        raise ValueError(f"the oracle rows need >= 3 true states, got {k}")
    er = embed_refs(refs, joints, probes) if e_rr is None else e_rr
    loo = [energy_distance(np.delete(er, i, 0), er[i : i + 1]) for i in range(k)]
    d = np.linalg.norm(er[:, None] - er[None], axis=-1)
    medoid = int(d.sum(1).argmin())
    rest = np.delete(er, medoid, 0)
    rows = {
        "truth_loo": {key: float(np.mean([r[key] for r in loo])) for key in loo[0]},
        "refs_medoid": {**energy_distance(er[medoid : medoid + 1], rest), "medoid": float(medoid)},
    }
    if chamfer:
        d_rr = chamfer_matrix(refs, refs) if d_rr is None else d_rr
        off = ~np.eye(k, dtype=bool)
        rows["truth_loo"]["chamfer_to_refs"] = float(d_rr[off].mean())
        rows["refs_medoid"]["chamfer_to_refs"] = float(np.delete(d_rr[medoid], medoid).mean())
    return rows


# ------------------------------------------------------------------ why not Chamfer (documented)
def chamfer_1d(a: Sequence[float], b: Sequence[float], squared: bool) -> float:
    """Chamfer distance of two 1-D point sets: mean nearest distance a -> b plus b -> a (squared
    distances with ``squared``)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    d = np.abs(a[:, None] - b[None])
    if squared:
        d = d**2
    return float(d.min(1).mean() + d.min(0).mean())


def expected_energy_score(forecast: Sequence[tuple[float, Sequence[float]]], truth: Sequence[float],
                          d: Callable[[Sequence[float], Sequence[float]], float]) -> float:  # fmt: skip
    """The exact energy score E d(X, y) - 1/2 E d(X, X') of a discrete forecast
    [(probability, outcome), ...] for the outcome ``truth`` under the distance ``d``."""
    to_truth = sum(p * d(x, truth) for p, x in forecast)
    spread = sum(p * q * d(x, y) for p, x in forecast for q, y in forecast)
    return to_truth - 0.5 * spread


def chamfer_energy_counterexamples() -> list[dict]:
    """Two forecasts that beat the perfect forecast (always the truth, score 0) under the Chamfer
    energy score, so it is not proper: truth {0, 1} under squared Chamfer (``{0}`` or ``{1, 2}``,
    half each: -0.125) and truth {0, 2, 3} under unsquared Chamfer (``{0}`` with 0.4, ``{2, 3}``
    with 0.6: -0.0133)."""
    cases = [
        ((0.0, 1.0), [(0.5, (0.0,)), (0.5, (1.0, 2.0))], True),
        ((0.0, 2.0, 3.0), [(0.4, (0.0,)), (0.6, (2.0, 3.0))], False),
    ]
    out = []
    for truth, forecast, squared in cases:
        d = lambda a, b, s=squared: chamfer_1d(a, b, s)  # noqa: E731
        out.append({
            "truth": truth, "forecast": forecast, "squared": squared,
            "perfect": expected_energy_score([(1.0, truth)], truth, d),
            "wrong": expected_energy_score(forecast, truth, d),
        })  # fmt: skip
    return out
