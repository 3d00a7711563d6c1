"""Evaluation metrics: known answers and a brute-force reference."""

import math

import numpy as np
import pytest

from pocoloco.evaluation import metrics as M


def _sphere(n: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Fibonacci sphere: (n, 3) near-uniform points and their outward unit normals."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    r = np.sqrt(1 - z * z)
    nrm = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return radius * nrm, nrm


def _brute(pred, pred_n, gt, gt_n, labels):
    """Every metric from the full (N, M) distance matrix, written out directly."""
    d = np.linalg.norm(pred[:, None] - gt[None], axis=-1)  # (N, M)
    j = d.argmin(1)  # pred -> GT
    s2m, m2s = d.min(0), d.min(1)
    p2p = np.array([np.dot(pred[i] - gt[j[i]], gt_n[j[i]]) ** 2 for i in range(len(pred))])
    prec, rec = 100 * np.mean(m2s < 0.01), 100 * np.mean(s2m < 0.01)
    return {
        "s2m_cm": 100 * s2m.mean(),
        "m2s_cm": 100 * m2s.mean(),
        "chamfer_cm": 100 * (s2m.mean() + m2s.mean()),
        "pop_s2m_e-4m2": 1e4 * np.mean(s2m**2),
        "pop_m2s_e-4m2": 1e4 * p2p.mean(),
        "pop_chamfer_e-4m2": 1e4 * (np.mean(s2m**2) + p2p.mean()),
        "normal_l1_e-1": 10 * np.mean([np.abs(pred_n[i] - gt_n[j[i]]).sum() for i in range(len(pred))]),
        "precision_pct": prec,
        "recall_pct": rec,
        "fscore_pct": 2 * prec * rec / (prec + rec),
        "loose_pred_pct": 100 * np.mean(labels[j] == 1),
        "loose_gt_pct": 100 * np.mean(labels == 1),
    }


def test_evaluate_frame_matches_brute_force():
    rng = np.random.default_rng(0)
    gt, gt_n = _sphere(400, 0.3)
    labels = (gt[:, 2] < 0).astype(np.uint8)  # lower half = garment
    pred = gt[rng.permutation(400)[:300]] + rng.normal(0, 0.01, (300, 3))
    pred_n = rng.normal(size=(300, 3))
    pred_n /= np.linalg.norm(pred_n, axis=1, keepdims=True)
    got = M.evaluate_frame(pred, pred_n, gt, gt_n, labels)
    want = _brute(pred, pred_n, gt, gt_n, labels)
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-9, abs=1e-12), k
    assert 0 < got["fscore_pct"] < 100  # the threshold actually splits this case
    # the per-metric functions agree with evaluate_frame
    assert M.s2m_cm(pred, gt) == pytest.approx(got["s2m_cm"])
    assert M.m2s_cm(pred, gt) == pytest.approx(got["m2s_cm"])
    assert M.chamfer_cm(pred, gt) == pytest.approx(got["chamfer_cm"])
    assert M.pop_chamfer(pred, gt, gt_n) == pytest.approx(got["pop_chamfer_e-4m2"])
    assert M.normal_l1(pred, pred_n, gt, gt_n) == pytest.approx(got["normal_l1_e-1"])
    assert M.fscore(pred, gt).fscore == pytest.approx(got["fscore_pct"])
    assert M.loose_share(pred, gt, labels).pred_pct == pytest.approx(got["loose_pred_pct"])


def test_identical_clouds_are_zero():
    gt, gt_n = _sphere(500, 0.5)
    out = M.evaluate_frame(gt, gt_n, gt, gt_n, np.zeros(500, np.uint8))
    for k in ("s2m_cm", "m2s_cm", "chamfer_cm", "pop_chamfer_e-4m2", "normal_l1_e-1", "loose_pred_pct"):
        assert out[k] == 0, k
    assert out["fscore_pct"] == 100


def test_shift_along_normal_gives_point_to_plane_d_squared():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 1, (2000, 2))
    gt = np.c_[xy, np.zeros(2000)]
    gt_n = np.tile([0.0, 0, 1], (2000, 1))
    d = 0.004
    pred = gt + np.c_[rng.uniform(-0.01, 0.01, (2000, 2)), np.full(2000, d)]  # lateral jitter + normal shift
    assert M.pop_m2s(pred, gt, gt_n) == pytest.approx(d**2 * 1e4, rel=1e-9)
    assert M.pop_m2s(pred, gt) > 1.5 * d**2 * 1e4  # point-to-point also sees the jitter
    assert M.m2s_cm(gt + [0, 0, d], gt) == pytest.approx(100 * d)


def test_concentric_spheres():
    r1, r2 = 0.4, 0.5
    gt, gt_n = _sphere(20000, r1)
    pred, _ = _sphere(15000, r2)
    gap_cm = 100 * (r2 - r1)
    assert M.s2m_cm(pred, gt) == pytest.approx(gap_cm, rel=0.02)
    assert M.m2s_cm(pred, gt) == pytest.approx(gap_cm, rel=0.02)
    assert M.chamfer_cm(pred, gt) == pytest.approx(2 * gap_cm, rel=0.02)
    assert M.pop_s2m(pred, gt) == pytest.approx((r2 - r1) ** 2 * 1e4, rel=0.03)
    assert M.pop_m2s(pred, gt, gt_n) == pytest.approx((r2 - r1) ** 2 * 1e4, rel=0.03)
    # normals of pred are outward too: normal error small; flipped normals: |2n|_1 ~ 2 * E|n|_1 = 3
    pn = pred / r2
    assert M.normal_l1(pred, pn, gt, gt_n) < 0.5
    assert M.normal_l1(pred, -pn, gt, gt_n) == pytest.approx(30.0, rel=0.02)


def test_fscore_constructed():
    gt = np.c_[np.arange(10.0), np.zeros((10, 2))]  # 1 m apart
    pred = np.r_[gt[:6] + [0, 0.005, 0], [[50.0, 0, 0], [60.0, 0, 0]]]  # 6 close, 2 far
    f = M.fscore(pred, gt, threshold_m=0.01)
    assert (f.precision, f.recall) == pytest.approx((75.0, 60.0))
    assert f.fscore == pytest.approx(2 * 75 * 60 / 135)
    assert M.fscore(pred, gt, threshold_m=0.004).fscore == 0


def test_loose_share_toy():
    gt = np.c_[np.r_[np.arange(4.0), np.arange(10.0, 16.0)], np.zeros((10, 2))]
    labels = np.array([0] * 4 + [1] * 6, np.uint8)
    pred = np.c_[np.r_[[10.1, 12.2, 15.3], [0.1, 0.2, 1.1, 2.0, 3.3, 2.9, 1.4]], np.zeros((10, 2))]
    s = M.loose_share(pred, gt, labels)
    assert (s.pred_pct, s.gt_pct) == pytest.approx((30.0, 60.0))
    assert M.loose_share(pred, gt, labels, garment_labels=(0,)).pred_pct == pytest.approx(70.0)
    with pytest.raises(ValueError, match="gt_labels"):
        M.loose_share(pred, gt, labels[:5])


def test_diversity():
    gt, _ = _sphere(2000, 0.5)
    labels = (gt[:, 2] < 0).astype(np.uint8)  # lower half garment
    a = gt.copy()
    b = gt.copy()
    b[gt[:, 2] < -0.1] *= 1.02  # only (most of) the garment differs
    assert M.diversity_cm([a, a, a]) == 0
    assert M.diversity_cm([a, b]) == pytest.approx(M.chamfer_cm(a, b))
    assert M.diversity_cm([a, a, b]) == pytest.approx(2 * M.chamfer_cm(a, b) / 3)
    assert M.diversity_cm([a, b], gt, labels, region="body") == 0
    assert M.diversity_cm([a, b], gt, labels, region="garment") > M.diversity_cm([a, b])
    with pytest.raises(ValueError, match="needs gt"):
        M.diversity_cm([a, b], region="garment")


def test_summarise():
    s = M.summarise([{"a": 1.0, "b": 2.0}, {"a": 3.0, "b": float("nan")}, {"a": 5.0, "c": 7.0}])
    assert s == {"a": 3.0, "b": 2.0, "c": 7.0, "num_frames": 3.0}
    with pytest.raises(ValueError):
        M.summarise([])


def test_optional_inputs_and_validation():
    gt, gt_n = _sphere(100, 0.5)
    out = M.evaluate_frame(gt * 1.01, None, gt, None, None)
    assert "normal_l1_e-1" not in out and "loose_pred_pct" not in out
    assert out["pop_m2s_e-4m2"] == pytest.approx(M.pop_m2s(gt * 1.01, gt))
    with pytest.raises(ValueError, match="pred_points"):
        M.evaluate_frame(np.zeros((0, 3)), None, gt, gt_n)
    with pytest.raises(ValueError, match="gt_normals"):
        M.evaluate_frame(gt, None, gt, gt_n[:50])
    with pytest.raises(ValueError, match="non-finite"):
        M.s2m_cm(np.full((3, 3), np.nan), gt)


def test_outlier_shares_and_their_worst_cloud():
    """outlier_5/10cm_pct: generated points farther than 5 / 10 cm from every GT point (checked by
    brute force); summarise keeps the worst cloud as _max through nested means (seeds, then frames)."""
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(500, 3)) * 0.2
    pred = gt[:400] + rng.normal(size=(400, 3)) * 0.01
    pred[:40] += np.array([0.0, 0.0, 0.5])  # 10 % invented far away
    pred[40:60] += np.array([0.07, 0.0, 0.0])  # 5 % moderately off
    m = M.evaluate_frame(pred, None, gt, None)
    d = np.sqrt(((pred[:, None] - gt[None]) ** 2).sum(-1)).min(1)
    assert m["outlier_10cm_pct"] == pytest.approx(100 * (d > 0.10).mean())
    assert m["outlier_5cm_pct"] == pytest.approx(100 * (d > 0.05).mean())
    assert m["outlier_10cm_pct"] > 5.0 and m["outlier_5cm_pct"] > m["outlier_10cm_pct"]
    clean = M.evaluate_frame(gt[:400], None, gt, None)
    assert clean["outlier_5cm_pct"] == 0.0
    frame_a = M.summarise([m, clean])  # two seeds of one frame
    frame_b = M.summarise([clean, clean])
    assert frame_a["outlier_10cm_pct"] == pytest.approx(m["outlier_10cm_pct"] / 2)
    overall = M.summarise([frame_a, frame_b])
    assert overall["outlier_10cm_pct_max"] == pytest.approx(m["outlier_10cm_pct"])  # the worst cloud, not a mean
