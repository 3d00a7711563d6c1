"""Evaluation metrics for generated / predicted clothed-human point clouds (numpy + scipy).

Inputs are unbatched numpy clouds in metres: ``pred`` (N, 3) predicted / generated
points, ``gt`` (M, 3) ground-truth scan points with unit normals ``gt_normals`` (M, 3)
and labels ``gt_labels`` (M,) (0 body, 1 garment, 255 unknown: ``data.capture``).
Nearest neighbours use scipy's cKDTree (``ops.knn_numpy``).

Two conventions, never mixed; every key of ``evaluate_frame`` names its unit.

PocoLoco (Seth et al., Table 2: "Chamfer, S2M, M2S in cm", 10K points):
    S2M (scan-to-model)  = mean over GT points of the distance to the nearest predicted point,
    M2S (model-to-scan)  = mean over predicted points of the distance to the nearest GT point,
    Chamfer              = S2M + M2S,
  unsquared Euclidean distances, in cm. Chamfer is the *sum*, not the mean: every row of
  Table 2 satisfies Cham = M2S + S2M (2.48 = 1.22 + 1.26, 4.22 = 2.12 + 2.1, 6.4 = 2.27 +
  4.13, 3.63 = 1.92 + 1.71, ...).

POP (Ma et al. 2021, Eq. 4, 5 and Tables: "Chamfer-L2 (x1e-4 m^2)", "Normal diff. (x1e-1)"):
    S2M = mean over GT points of the squared distance to the nearest predicted point,
    M2S = mean over predicted points of the squared point-to-plane distance
          ((x - y) . n_y)^2 to the nearest GT point y with GT normal n_y (what the POP
          code evaluates; Eq. 4 writes it point-to-point, available with gt_normals=None),
    CD  = S2M + M2S, reported in units of 1e-4 m^2 (value = m^2 * 1e4).
    Normal error = mean over predicted points of the L1 norm |n_pred - n_gt(nearest)|_1
          (sum over the 3 components) of unit normals, reported x 10 (units of 1e-1).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from pocoloco.data.capture import LABEL_GARMENT
from pocoloco.ops.knn import knn_numpy

#: Default F-score threshold in metres (1 cm).
FSCORE_THRESHOLD_M = 0.01

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

    gt_normals: (M, 3) GT normals (normalised here). None -> point-to-point |x - y|^2 (POP Eq. 4).
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
    """POP normal error (Eq. 5): mean over predicted points of |n_pred - n_gt(nearest GT point)|_1, x 10.

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
# per frame and summary
# ---------------------------------------------------------------------------


#: thresholds (cm) of the outlier shares: generated points this far from every scan point
OUTLIER_CM: tuple[int, ...] = (5, 10)
#: keys whose worst value over frames (and seeds) :func:`summarise` reports as ``<key>_max``
MAX_KEYS: tuple[str, ...] = tuple(f"outlier_{cm}cm_pct" for cm in OUTLIER_CM)


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
    fscore_pct, precision_pct, recall_pct (at fscore_threshold_m); outlier_5cm_pct,
    outlier_10cm_pct (share of predicted points farther than 5 / 10 cm from every GT point);
    loose_pred_pct, loose_gt_pct; num_pred, num_gt.
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

    if gt_labels is not None:
        garment = _is_garment(_labels(gt_labels, gt), garment_labels)
        out["loose_pred_pct"] = 100.0 * float(garment[idx_pred].mean())
        out["loose_gt_pct"] = 100.0 * float(garment.mean())
    out["num_pred"], out["num_gt"] = float(len(pred)), float(len(gt))
    return out


def summarise(frames: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """Mean of every key over a list of ``evaluate_frame`` dicts (NaNs and missing keys skipped).

    Adds ``num_frames``. Keys missing from some frames are averaged over the frames that have them.
    The outlier shares (``MAX_KEYS``) also get ``<key>_max``, their worst value: the maximum over
    the entries (or over the entries' own ``_max`` when they are summaries themselves, so a mean
    over seeds, then over frames, still reports the single worst cloud).
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
    out["num_frames"] = float(len(frames))
    return out
