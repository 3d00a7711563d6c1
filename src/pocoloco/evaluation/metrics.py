"""Evaluation metrics for generated / predicted clothed-human point clouds (numpy + scipy).

Inputs are unbatched numpy clouds in metres: ``pred`` (N, 3) predicted / generated
points, ``gt`` (M, 3) ground-truth scan points with unit normals ``gt_normals`` (M, 3)
and labels ``gt_labels`` (M,) (0 body, 1 garment, 255 unknown: ``data.format``).
Nearest neighbours use scipy's cKDTree (``ops.knn_numpy``).

Two conventions, never mixed; every key of ``evaluate_frame`` names its unit.

PocoLoco (Seth et al., Table 2: "Chamfer, S2M, M2S in cm", 10K points)::

    S2M (scan-to-model)  = mean over GT points of the distance to the nearest predicted point,
    M2S (model-to-scan)  = mean over predicted points of the distance to the nearest GT point,
    Chamfer              = S2M + M2S,
  unsquared Euclidean distances, in cm. Chamfer is the *sum*, not the mean: every row of
  Table 2 satisfies Cham = M2S + S2M (2.48 = 1.22 + 1.26, 4.22 = 2.12 + 2.1, 6.4 = 2.27 +
  4.13, 3.63 = 1.92 + 1.71, ...).

POP (Ma et al. 2021, Eq. 4, 5 and Tables: "Chamfer-L2 (x1e-4 m^2)", "Normal diff. (x1e-1)")::

    S2M = mean over GT points of the squared distance to the nearest predicted point,
    M2S = mean over predicted points of the squared point-to-plane distance
          ((x - y) . n_y)^2 to the nearest GT point y with GT normal n_y (what the POP
          code evaluates; Eq. 4 writes it point-to-point, available with gt_normals=None),
    CD  = S2M + M2S, reported in units of 1e-4 m^2 (value = m^2 * 1e4).
    Normal error = mean over predicted points of the L1 norm |n_pred - n_gt(nearest)|_1
          (sum over the 3 components) of unit normals, reported x 10 (units of 1e-1).

Metrics fair to a generative model (PocoLoco convention, cm):

* **Garment / rest split.** The scan's labels split it into the loose garment (``LABEL_GARMENT``)
  and the rest (body, unknown). S2M garment = mean over GT garment points of the distance to the
  nearest predicted point (S2M rest likewise over the other GT points); a predicted point takes
  the label of its nearest GT point, and M2S garment = mean over the predicted points so labelled
  of that distance (M2S rest likewise). The whole-cloud Chamfer is dominated by the body, which
  covers most of the scan; a model that drops the skirt shows it here, as a large S2M garment.
  A frame without garment points (a tight subject) gives NaN garment values, which the
  summaries skip (nanmean) and count (``num_frames_garment``).
* **F-score at 1 cm and 2 cm** (Tanks and Temples), overall and on the garment (precision over the
  predicted points labelled garment as above, recall over the GT garment points): the share of
  the surface reproduced within a tolerance, robust to a few far points that dominate a mean.
* **Best of K and energy score.** A regressor trained on Chamfer approaches the conditional mean
  surface given the pose, which minimises the expected distance to the scan; a sample from a
  calibrated generative model is as spread as the data, so its expected Chamfer to the scan
  carries an extra variance term (two independent draws are further apart than a draw and the
  mean). Averaging Chamfer over samples therefore ranks the generative model below a blurry mean
  even when it is the better model of the data. Best of K (min Chamfer over the K samples of a
  frame) shows whether the scan lies near the samples, but rewards spread without bound. The
  energy score (Gneiting & Raftery 2007, JASA 102:359) pays for both bias and spread::

      ES = mean_k d(X_k, y) - 1 / (2 K (K - 1)) * sum_{k != l} d(X_k, X_l),   d = chamfer_cm,

  (the unbiased "fair" form over K samples; the second term is half the mean pairwise Chamfer,
  i.e. half of ``diversity_cm``). For a deterministic model or K = 1, ES = d(x, y), so one column
  ranks regressors and samplers alike; lower is better. ES is strictly proper for the Euclidean
  distance; Chamfer is not known to be a negative-definite kernel, so here it is a kernel score
  of the same form that rewards a calibrated spread over a biased point (tested on toy cases),
  not a proven proper score. **Caveat, measured (BENCHMARKS.md, "PocoLoco on a GPU"):** between
  two finite point sets, Chamfer also counts the point resampling (two 2,048-point resamples of
  one scan are 2.82 cm apart), so the spread term of a sampler includes about half that noise
  floor, which a deterministic row (scored once, K = 1) never subtracts: raw ES favours the
  sampler by up to ~1.4 cm at 2,048 points. ``energy_score_adj_cm`` adds half of each frame's
  noise floor (its Chamfer between two resamples of the scan, the GT-resample row) back to a
  sampler's ES (:func:`energy_score_adjusted`); that is the column that ranks a sampler against
  POP / CloSET. It assumes the resampling noise adds to the pairwise Chamfer, which holds to first
  order (tested: two samplers of the same surface get the deterministic Chamfer back within noise).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from pocoloco.data.format import LABEL_GARMENT
from pocoloco.ops.knn import knn_numpy

#: Default F-score threshold in metres (1 cm).
FSCORE_THRESHOLD_M = 0.01
#: thresholds (cm) of the named F-scores of ``evaluate_frame`` (``fscore_1cm_pct``, ``fscore_garment_2cm_pct``, ...)
FSCORE_THRESHOLDS_CM: tuple[int, ...] = (1, 2)

_CM = 100.0  # metres -> cm
_POP_SQ = 1e4  # m^2 -> 1e-4 m^2
_POP_NORMAL = 10.0  # -> 1e-1


# ---------------------------------------------------------------------------
# validation and nearest neighbours
# ---------------------------------------------------------------------------


def _cloud(x, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty (N, 3) array, got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"{name} contains non-finite values")
    return x


def _normals(n, points: np.ndarray, name: str) -> np.ndarray:
    n = _cloud(n, name)
    if n.shape != points.shape:
        raise ValueError(f"{name} must have the shape of its points {points.shape}, got {n.shape}")
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    if (norm < 1e-12).any():
        raise ValueError(f"{name} contains zero-length normals")
    return n / norm


def _labels(labels, points: np.ndarray) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.shape != (points.shape[0],):
        raise ValueError(f"gt_labels must have shape ({points.shape[0]},), got {labels.shape}")
    return labels


def nearest(src, dst) -> tuple[np.ndarray, np.ndarray]:
    """For each point of ``src`` (N, 3): (distance (N,) in metres, unsquared; index (N,) into ``dst`` (M, 3))."""
    src, dst = _cloud(src, "src"), _cloud(dst, "dst")
    d2, idx = knn_numpy(src, dst, 1)
    return np.sqrt(d2[:, 0]), idx[:, 0]


# ---------------------------------------------------------------------------
# PocoLoco convention (cm, unsquared)
# ---------------------------------------------------------------------------


def s2m_cm(pred, gt) -> float:
    """Scan-to-model: mean over GT points of the distance to the nearest predicted point, in cm."""
    return float(nearest(gt, pred)[0].mean() * _CM)


def m2s_cm(pred, gt) -> float:
    """Model-to-scan: mean over predicted points of the distance to the nearest GT point, in cm."""
    return float(nearest(pred, gt)[0].mean() * _CM)


def chamfer_cm(pred, gt) -> float:
    """PocoLoco Chamfer: ``s2m_cm + m2s_cm`` (sum of the two unsquared means), in cm."""
    return s2m_cm(pred, gt) + m2s_cm(pred, gt)


# ---------------------------------------------------------------------------
# POP convention (squared, 1e-4 m^2)
# ---------------------------------------------------------------------------


def pop_s2m(pred, gt) -> float:
    """POP S2M: mean over GT points of the squared distance to the nearest predicted point, in 1e-4 m^2."""
    d, _ = nearest(gt, pred)
    return float(np.mean(d * d) * _POP_SQ)


def pop_m2s(pred, gt, gt_normals=None) -> float:
    """POP M2S: mean over predicted points of ((x - y) . n_y)^2, y the nearest GT point, in 1e-4 m^2.

    gt_normals: (M, 3) GT normals (normalised here). None -> point-to-point ``|x - y|^2`` (POP Eq. 4).
    """
    pred, gt = _cloud(pred, "pred"), _cloud(gt, "gt")
    d, idx = nearest(pred, gt)
    if gt_normals is None:
        return float(np.mean(d * d) * _POP_SQ)
    n = _normals(gt_normals, gt, "gt_normals")
    return float(np.mean(_point_to_plane_sq(pred, gt, n, idx)) * _POP_SQ)


def pop_chamfer(pred, gt, gt_normals=None) -> float:
    """POP Chamfer: ``pop_s2m + pop_m2s`` in 1e-4 m^2 (point-to-plane M2S when gt_normals is given)."""
    return pop_s2m(pred, gt) + pop_m2s(pred, gt, gt_normals)


def _point_to_plane_sq(pred: np.ndarray, gt: np.ndarray, gt_n: np.ndarray, idx: np.ndarray) -> np.ndarray:
    return np.einsum("nc,nc->n", pred - gt[idx], gt_n[idx]) ** 2  # (N,)


def normal_l1(pred, pred_normals, gt, gt_normals) -> float:
    """POP normal error (Eq. 5): mean over predicted points of ``|n_pred - n_gt(nearest GT point)|_1``, x 10.

    Both normal sets are normalised to unit length first; the L1 norm sums the 3
    components, so the raw value is in [0, 2 sqrt(3)] and the result in [0, 20 sqrt(3)].
    """
    pred, gt = _cloud(pred, "pred"), _cloud(gt, "gt")
    pn, gn = _normals(pred_normals, pred, "pred_normals"), _normals(gt_normals, gt, "gt_normals")
    _, idx = nearest(pred, gt)
    return float(np.abs(pn - gn[idx]).sum(1).mean() * _POP_NORMAL)


# ---------------------------------------------------------------------------
# F-score, loose-region share, diversity
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class FScore:
    """F-score at a distance threshold (Knapitsch et al. 2017, Tanks and Temples), in percent.

    precision: % of predicted points whose nearest GT point is closer than the threshold.
    recall:    % of GT points whose nearest predicted point is closer than the threshold.
    fscore:    harmonic mean 2 P R / (P + R) (0 when P = R = 0).
    """

    precision: float
    recall: float
    fscore: float


def _fscore(d_pred: np.ndarray, d_gt: np.ndarray, threshold_m: float) -> FScore:
    p = 100.0 * float(np.mean(d_pred < threshold_m))
    r = 100.0 * float(np.mean(d_gt < threshold_m))
    return FScore(p, r, 0.0 if p + r == 0 else 2 * p * r / (p + r))


def fscore(pred, gt, threshold_m: float = FSCORE_THRESHOLD_M) -> FScore:
    """F-score of ``pred`` (N, 3) against ``gt`` (M, 3) at ``threshold_m`` metres (strict <), in percent."""
    if not threshold_m > 0:
        raise ValueError(f"threshold_m must be > 0, got {threshold_m}")
    return _fscore(nearest(pred, gt)[0], nearest(gt, pred)[0], threshold_m)


@dataclass(frozen=True)
class LooseShare:
    """Share of points in the garment region, in percent.

    pred_pct: % of predicted points whose nearest GT point has a garment label.
    gt_pct:   % of GT points with a garment label (the target share; unknown labels count as not garment).
    """

    pred_pct: float
    gt_pct: float


def _is_garment(labels: np.ndarray, garment_labels: Sequence[int]) -> np.ndarray:
    return np.isin(labels, np.asarray(list(garment_labels)))


def loose_share(pred, gt, gt_labels, garment_labels: Sequence[int] = (LABEL_GARMENT,)) -> LooseShare:
    """Percent of predicted points in the loose-garment region (PocoLoco supp. A.1, "points sparsity").

    Each predicted point takes the label of its nearest GT point; garment_labels are the
    label values that count as the garment region (default: ``capture.LABEL_GARMENT``).
    """
    pred, gt = _cloud(pred, "pred"), _cloud(gt, "gt")
    lab = _labels(gt_labels, gt)
    _, idx = nearest(pred, gt)
    garment = _is_garment(lab, garment_labels)
    return LooseShare(100.0 * float(garment[idx].mean()), 100.0 * float(garment.mean()))


def diversity_cm(
    samples: Sequence[np.ndarray] | np.ndarray,
    gt=None,
    gt_labels=None,
    region: str = "all",
    garment_labels: Sequence[int] = (LABEL_GARMENT,),
) -> float:
    """Mean pairwise PocoLoco Chamfer (cm, ``chamfer_cm``) among K >= 2 samples for one pose.

    samples: K clouds (N_k, 3). region: "all" (whole clouds), "garment" or "body": keep in
    each sample only the points whose nearest GT point (``gt`` (M, 3), ``gt_labels`` (M,))
    is / is not a garment label, then compare. Pairs where a restricted cloud is empty are
    skipped; NaN if no pair is left. Higher = more diverse samples.
    """
    if region not in ("all", "garment", "body"):
        raise ValueError(f"region must be 'all', 'garment' or 'body', got {region!r}")
    clouds = [_cloud(s, f"samples[{i}]") for i, s in enumerate(samples)]
    if len(clouds) < 2:
        raise ValueError(f"diversity needs at least 2 samples, got {len(clouds)}")
    if region != "all":
        if gt is None or gt_labels is None:
            raise ValueError(f"region={region!r} needs gt and gt_labels")
        gt = _cloud(gt, "gt")
        garment = _is_garment(_labels(gt_labels, gt), garment_labels)
        keep = garment if region == "garment" else ~garment
        clouds = [c[keep[nearest(c, gt)[1]]] for c in clouds]
    vals = [chamfer_cm(a, b) for a, b in combinations(clouds, 2) if len(a) and len(b)]
    return float(np.mean(vals)) if vals else float("nan")


# ---------------------------------------------------------------------------
# garment / rest split, garment F-score
# ---------------------------------------------------------------------------


def _masked_mean(x: np.ndarray, mask: np.ndarray) -> float:
    """Mean of ``x[mask]``; NaN (no warning) when the mask is empty."""
    return float(x[mask].mean()) if mask.any() else float("nan")


@dataclass(frozen=True)
class SplitDistances:
    """S2M / M2S in cm on the loose garment and on the rest of the scan (body, unknown labels).

    s2m_garment / s2m_rest: mean over the GT garment / other points of the distance to the nearest
    predicted point (NaN when the scan has no such point: a tight subject has no garment).
    m2s_garment / m2s_rest: mean over the predicted points whose nearest GT point is garment / other
    of the distance to that point (NaN when no predicted point is so labelled).
    """

    s2m_garment: float
    s2m_rest: float
    m2s_garment: float
    m2s_rest: float


def split_distances_cm(pred, gt, gt_labels, garment_labels: Sequence[int] = (LABEL_GARMENT,)) -> SplitDistances:
    """S2M and M2S of ``pred`` (N, 3) against ``gt`` (M, 3) split by ``gt_labels`` (M,) into garment / rest, in cm."""
    pred, gt = _cloud(pred, "pred"), _cloud(gt, "gt")
    garment = _is_garment(_labels(gt_labels, gt), garment_labels)
    d_gt, _ = nearest(gt, pred)
    d_pred, idx = nearest(pred, gt)
    return SplitDistances(_masked_mean(d_gt, garment) * _CM, _masked_mean(d_gt, ~garment) * _CM,
                          _masked_mean(d_pred, garment[idx]) * _CM, _masked_mean(d_pred, ~garment[idx]) * _CM)  # fmt: skip


def _garment_fscore(d_pred: np.ndarray, d_gt: np.ndarray, pred_garment: np.ndarray, gt_garment: np.ndarray,
                    threshold_m: float) -> FScore:  # fmt: skip
    if not gt_garment.any():
        return FScore(float("nan"), float("nan"), float("nan"))
    r = 100.0 * float(np.mean(d_gt[gt_garment] < threshold_m))
    p = 100.0 * float(np.mean(d_pred[pred_garment] < threshold_m)) if pred_garment.any() else 0.0
    return FScore(p, r, 0.0 if p + r == 0 else 2 * p * r / (p + r))


def garment_fscore(pred, gt, gt_labels, threshold_m: float = FSCORE_THRESHOLD_M,
                   garment_labels: Sequence[int] = (LABEL_GARMENT,)) -> FScore:  # fmt: skip
    """F-score on the loose garment, in percent: precision over the predicted points whose nearest GT
    point (``gt`` (M, 3), ``gt_labels`` (M,)) is garment, recall over the GT garment points.

    All NaN when the scan has no garment point; precision 0 (so F 0) when it has but no predicted
    point lands on it (the garment was dropped).
    """
    if not threshold_m > 0:
        raise ValueError(f"threshold_m must be > 0, got {threshold_m}")
    pred, gt = _cloud(pred, "pred"), _cloud(gt, "gt")
    garment = _is_garment(_labels(gt_labels, gt), garment_labels)
    d_pred, idx = nearest(pred, gt)
    return _garment_fscore(d_pred, nearest(gt, pred)[0], garment[idx], garment, threshold_m)


# ---------------------------------------------------------------------------
# several samples per frame: best of K, energy score
# ---------------------------------------------------------------------------


def _samples(samples: Sequence[np.ndarray] | np.ndarray) -> list[np.ndarray]:
    clouds = [_cloud(s, f"samples[{i}]") for i, s in enumerate(samples)]
    if not clouds:
        raise ValueError("at least one sample is needed")
    return clouds


def best_of_k_cm(samples: Sequence[np.ndarray] | np.ndarray, gt) -> float:
    """Best of K: the smallest ``chamfer_cm`` of K >= 1 clouds (N_k, 3) against ``gt`` (M, 3), in cm."""
    gt = _cloud(gt, "gt")
    return float(min(chamfer_cm(c, gt) for c in _samples(samples)))


def energy_score_from_chamfers(to_gt: Sequence[float], pairwise_mean_cm: float | None) -> float:
    """ES from the K Chamfers to the scan and the mean Chamfer over the K (K - 1) / 2 sample pairs
    (``diversity_cm``; None or ignored for K = 1): mean(to_gt) - pairwise_mean_cm / 2, in cm."""
    to_gt = np.asarray(to_gt, dtype=np.float64)
    if to_gt.ndim != 1 or len(to_gt) == 0:
        raise ValueError(f"to_gt must be a non-empty (K,) sequence, got shape {to_gt.shape}")
    if len(to_gt) == 1:
        return float(to_gt[0])
    if pairwise_mean_cm is None:
        raise ValueError(f"K = {len(to_gt)} samples need their mean pairwise Chamfer")
    # 1 / (2K(K-1)) * sum over ordered pairs = 1 / (K(K-1)) * sum over unordered pairs = mean pair / 2
    return float(to_gt.mean() - 0.5 * pairwise_mean_cm)


def energy_score_cm(samples: Sequence[np.ndarray] | np.ndarray, gt) -> float:
    """Energy score (Gneiting & Raftery 2007) of K >= 1 clouds (N_k, 3) for the scan ``gt`` (M, 3), in cm:

    ES = mean_k d(X_k, y) - 1 / (2 K (K - 1)) * sum_{k != l} d(X_k, X_l), d = ``chamfer_cm``;
    K = 1 (a deterministic model): d(X_1, y). Lower is better.
    """
    gt = _cloud(gt, "gt")
    clouds = _samples(samples)
    to_gt = [chamfer_cm(c, gt) for c in clouds]
    return energy_score_from_chamfers(to_gt, diversity_cm(clouds) if len(clouds) >= 2 else None)


# ---------------------------------------------------------------------------
# per frame and summary
# ---------------------------------------------------------------------------


#: thresholds (cm) of the outlier shares: generated points this far from every scan point
OUTLIER_CM: tuple[int, ...] = (5, 10)
#: keys whose worst value over frames (and seeds) :func:`summarise` reports as ``<key>_max``
MAX_KEYS: tuple[str, ...] = tuple(f"outlier_{cm}cm_pct" for cm in OUTLIER_CM)
#: frame counts :func:`summarise` reports: count key -> the key whose finite entries it counts (the
#: garment columns are NaN on frames without garment points, and their means skip those frames)
FRAME_COUNTS: dict[str, str] = {"num_frames_garment": "s2m_garment_cm", "num_frames_m2s_garment": "m2s_garment_cm"}


def evaluate_frame(
    pred_points,
    pred_normals,
    gt_points,
    gt_normals,
    gt_labels=None,
    *,
    garment_labels: Sequence[int] = (LABEL_GARMENT,),
    fscore_threshold_m: float = FSCORE_THRESHOLD_M,
) -> dict[str, float]:
    """All per-frame metrics of one predicted cloud against one GT scan (one KD-tree each way).

    pred_points: (N, 3) m; pred_normals: (N, 3) or None (skips normal_l1_e-1);
    gt_points: (M, 3) m; gt_normals: (M, 3) (None: POP M2S falls back to point-to-point);
    gt_labels: (M,) or None (skips the loose-share keys).
    Keys (units in the name): s2m_cm, m2s_cm, chamfer_cm (PocoLoco);
    pop_s2m_e-4m2, pop_m2s_e-4m2, pop_chamfer_e-4m2 (POP); normal_l1_e-1 (POP);
    fscore_pct, precision_pct, recall_pct (at fscore_threshold_m); fscore_{c}cm_pct,
    precision_{c}cm_pct, recall_{c}cm_pct for c in ``FSCORE_THRESHOLDS_CM`` (1, 2); outlier_5cm_pct,
    outlier_10cm_pct (share of predicted points farther than 5 / 10 cm from every GT point);
    with gt_labels: loose_pred_pct, loose_gt_pct; s2m_garment_cm, s2m_rest_cm, m2s_garment_cm,
    m2s_rest_cm (``split_distances_cm``, NaN where a part is empty); fscore_garment_{c}cm_pct,
    precision_garment_{c}cm_pct, recall_garment_{c}cm_pct (``garment_fscore``, NaN without GT
    garment points); always num_pred, num_gt.
    """
    pred, gt = _cloud(pred_points, "pred_points"), _cloud(gt_points, "gt_points")
    if not fscore_threshold_m > 0:
        raise ValueError(f"fscore_threshold_m must be > 0, got {fscore_threshold_m}")
    d_gt, _ = nearest(gt, pred)  # (M,) GT -> pred
    d_pred, idx_pred = nearest(pred, gt)  # (N,) pred -> GT

    out: dict[str, float] = {}
    out["s2m_cm"] = float(d_gt.mean() * _CM)
    out["m2s_cm"] = float(d_pred.mean() * _CM)
    out["chamfer_cm"] = out["s2m_cm"] + out["m2s_cm"]

    out["pop_s2m_e-4m2"] = float(np.mean(d_gt**2) * _POP_SQ)
    if gt_normals is not None:
        gn = _normals(gt_normals, gt, "gt_normals")
        m2s_sq = _point_to_plane_sq(pred, gt, gn, idx_pred)
    else:
        gn, m2s_sq = None, d_pred**2
    out["pop_m2s_e-4m2"] = float(np.mean(m2s_sq) * _POP_SQ)
    out["pop_chamfer_e-4m2"] = out["pop_s2m_e-4m2"] + out["pop_m2s_e-4m2"]
    if pred_normals is not None and gn is not None:
        pn = _normals(pred_normals, pred, "pred_normals")
        out["normal_l1_e-1"] = float(np.abs(pn - gn[idx_pred]).sum(1).mean() * _POP_NORMAL)

    for cm in OUTLIER_CM:  # generated points far from the scan: an invented garment shows up here
        out[f"outlier_{cm}cm_pct"] = 100.0 * float((d_pred > cm / _CM).mean())

    f = _fscore(d_pred, d_gt, fscore_threshold_m)
    out["fscore_pct"], out["precision_pct"], out["recall_pct"] = f.fscore, f.precision, f.recall
    for cm in FSCORE_THRESHOLDS_CM:
        f = _fscore(d_pred, d_gt, cm / _CM)
        out[f"fscore_{cm}cm_pct"], out[f"precision_{cm}cm_pct"], out[f"recall_{cm}cm_pct"] = f.fscore, f.precision, f.recall

    if gt_labels is not None:
        garment = _is_garment(_labels(gt_labels, gt), garment_labels)  # (M,)
        pred_garment = garment[idx_pred]  # (N,) the label of the nearest GT point
        out["loose_pred_pct"] = 100.0 * float(pred_garment.mean())
        out["loose_gt_pct"] = 100.0 * float(garment.mean())
        out["s2m_garment_cm"] = _masked_mean(d_gt, garment) * _CM
        out["s2m_rest_cm"] = _masked_mean(d_gt, ~garment) * _CM
        out["m2s_garment_cm"] = _masked_mean(d_pred, pred_garment) * _CM
        out["m2s_rest_cm"] = _masked_mean(d_pred, ~pred_garment) * _CM
        for cm in FSCORE_THRESHOLDS_CM:
            g = _garment_fscore(d_pred, d_gt, pred_garment, garment, cm / _CM)
            out[f"fscore_garment_{cm}cm_pct"] = g.fscore
            out[f"precision_garment_{cm}cm_pct"], out[f"recall_garment_{cm}cm_pct"] = g.precision, g.recall
    out["num_pred"], out["num_gt"] = float(len(pred)), float(len(gt))
    return out


def summarise(frames: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Mean of every key over a list of ``evaluate_frame`` dicts (NaNs and missing keys skipped).

    Adds ``num_frames``. Keys missing from some frames (or NaN there) are averaged over the frames
    that have them, and ``FRAME_COUNTS`` says over how many: ``num_frames_garment`` = entries with a
    finite ``s2m_garment_cm`` (the scan has garment points), ``num_frames_m2s_garment`` = entries
    with a finite ``m2s_garment_cm`` (reported when any entry has the key; an entry that is itself a
    summary adds its own count). The outlier shares (``MAX_KEYS``) also get ``<key>_max``, their
    worst value: the maximum over the entries (or over the entries' own ``_max`` when they are
    summaries themselves, so a mean over seeds, then over frames, still reports the single worst cloud).
    """
    frames = list(frames)
    if not frames:
        raise ValueError("summarise needs at least one frame")
    keys: dict[str, None] = {}
    for f in frames:
        keys.update(dict.fromkeys(f))
    out = {}
    for k in keys:
        vals = np.array([f[k] for f in frames if k in f], dtype=np.float64)
        vals = vals[~np.isnan(vals)]
        out[k] = float(vals.mean()) if len(vals) else float("nan")
    for k in MAX_KEYS:
        worst = [f.get(f"{k}_max", f.get(k)) for f in frames]
        worst = [w for w in worst if w is not None and not np.isnan(w)]
        if worst:
            out[f"{k}_max"] = float(max(worst))
    for count, k in FRAME_COUNTS.items():
        if any(k in f or count in f for f in frames):
            out[count] = float(sum(f[count] if count in f else float(k in f and not np.isnan(f[k])) for f in frames))
    out["num_frames"] = float(len(frames))
    return out


def shared_fraction(samples: Sequence[np.ndarray] | np.ndarray) -> float:
    """Mean over ordered pairs (k, l) of K >= 2 clouds of the fraction of X_k's points that X_l
    holds exactly (the same coordinates): 0 for independent samples, 1 for identical clouds, in
    between for hypotheses that share a part (the hybrid's attached points)."""
    clouds = [_cloud(s, f"samples[{i}]") for i, s in enumerate(samples)]
    if len(clouds) < 2:
        raise ValueError(f"the shared fraction needs at least 2 samples, got {len(clouds)}")
    shares = [float(np.mean(nearest(a, b)[0] == 0.0)) for a in clouds for b in clouds if a is not b]
    return float(np.mean(shares))


def partly_shared_floor_cm(gt: np.ndarray, other: np.ndarray, shared: float, seed: Sequence[int]) -> float:
    """The Chamfer (cm) between the N-point scan subset ``gt`` (N, 3) and a second subset that
    keeps a ``shared`` fraction of its points (drawn with ``seed``) and takes the rest from the
    independent subset ``other`` (N, 3): the resampling floor of hypotheses that share that
    fraction of their points (= the plain floor for ``shared`` 0, 0 for 1)."""
    if not 0.0 <= shared <= 1.0:
        raise ValueError(f"shared must be in [0, 1], got {shared}")
    n = len(gt)
    keep = int(round(shared * n))
    if keep >= n:
        return 0.0
    rng = np.random.default_rng(list(seed))
    mixed = np.concatenate([gt[rng.choice(n, keep, replace=False)], other[rng.choice(len(other), n - keep, replace=False)]])
    return chamfer_cm(mixed, gt)


def energy_score_adjusted(energy_score: float, num_samples: int, noise_floor_cm: float | None) -> float:
    """The energy score with the point-resampling noise taken out of its pairwise term, in cm.

    Between finite point sets, Chamfer carries a floor: two independent N-point resamples of one
    surface are ``noise_floor_cm`` apart (the GT-resample row). The pairwise term of ES counts that
    floor as the model's spread and subtracts half of it, which flatters any sampler against a
    deterministic model; this adds it back: ES + floor / 2 for K >= 2 samples, ES (= Chamfer) for K = 1.
    For hypotheses that share part of their points the floor is that of resamples sharing as much
    (:func:`partly_shared_floor_cm`): their pairwise term holds less resampling noise.
    """
    if num_samples < 2 or noise_floor_cm is None:
        return float(energy_score)
    return float(energy_score + 0.5 * noise_floor_cm)


def summarise_samples(scores: Sequence[Mapping[str, float]], pairwise_mean_cm: float | None = None,
                      noise_floor_cm: float | None = None) -> dict[str, float]:  # fmt: skip
    """One frame's metrics from the ``evaluate_frame`` dicts of its K >= 1 clouds (one per seed).

    Every key is the mean over the K clouds (NaN skipped, ``summarise``; K = 1: the cloud's own
    dict), plus best_of_k_chamfer_cm (min ``chamfer_cm`` over the K), energy_score_cm
    (``energy_score_from_chamfers``; pairwise_mean_cm = ``diversity_cm`` of the K clouds, needed for
    K >= 2), energy_score_adj_cm (``energy_score_adjusted`` with ``noise_floor_cm``, the frame's
    Chamfer between two resamples of the scan; = energy_score_cm without it) and num_samples = K.
    The seed-level counts (num_frames, ``FRAME_COUNTS``) are dropped, so a summary over frames counts
    frames.
    """
    if not scores:
        raise ValueError("summarise_samples needs at least one sample")
    to_gt = [s["chamfer_cm"] for s in scores]
    if len(scores) == 1:
        out = dict(scores[0])
    else:
        out = summarise(scores)
        for k in ("num_frames", *FRAME_COUNTS):
            out.pop(k, None)
    out["best_of_k_chamfer_cm"] = float(min(to_gt))
    out["energy_score_cm"] = energy_score_from_chamfers(to_gt, pairwise_mean_cm)
    out["energy_score_adj_cm"] = energy_score_adjusted(out["energy_score_cm"], len(scores), noise_floor_cm)
    out["num_samples"] = float(len(scores))
    return out
