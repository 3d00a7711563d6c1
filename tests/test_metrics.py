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


# ------------------------------------------------------------- garment / rest split, F-scores at 1 / 2 cm
def _labelled_clouds(seed: int):
    """Small random GT cloud with labels 0 body / 1 garment / 255 unknown, and a noisy partial prediction."""
    rng = np.random.default_rng(seed)
    gt = rng.normal(size=(220, 3)) * 0.15
    labels = np.where(gt[:, 1] < -0.05, 1, 0).astype(np.uint8)
    labels[rng.random(220) < 0.05] = 255
    pred = np.r_[gt[rng.permutation(220)[:150]] + rng.normal(size=(150, 3)) * 0.012, rng.normal(size=(20, 3)) * 0.3]
    return pred, gt, labels


def _brute_split(pred, gt, labels):
    """The split metrics with explicit loops over points: each predicted point takes the label of its
    nearest GT point; garment = label 1, rest = everything else (body and unknown)."""
    dist = lambda a, b: math.sqrt(sum((a[c] - b[c]) ** 2 for c in range(3)))  # noqa: E731
    to_pred = [min(dist(g, p) for p in pred) for g in gt]  # GT point -> nearest predicted point
    near = [min(range(len(gt)), key=lambda j: dist(p, gt[j])) for p in pred]  # predicted point -> nearest GT index
    to_gt = [dist(p, gt[j]) for p, j in zip(pred, near)]
    out = {}
    for part, is_part in (("garment", lambda lab: lab == 1), ("rest", lambda lab: lab != 1)):
        g = [to_pred[j] for j in range(len(gt)) if is_part(labels[j])]
        p = [to_gt[i] for i in range(len(pred)) if is_part(labels[near[i]])]
        out[f"s2m_{part}_cm"] = 100 * sum(g) / len(g) if g else float("nan")
        out[f"m2s_{part}_cm"] = 100 * sum(p) / len(p) if p else float("nan")
    garment_gt = [to_pred[j] for j in range(len(gt)) if labels[j] == 1]
    garment_pred = [to_gt[i] for i in range(len(pred)) if labels[near[i]] == 1]
    for cm in (1, 2):
        t = cm / 100
        for name, dp, dg in (("", to_gt, to_pred), ("garment_", garment_pred, garment_gt)):
            if not dg:
                prec = rec = f = float("nan")
            else:
                prec = 100 * sum(d < t for d in dp) / len(dp) if dp else 0.0
                rec = 100 * sum(d < t for d in dg) / len(dg)
                f = 0.0 if prec + rec == 0 else 2 * prec * rec / (prec + rec)
            out[f"precision_{name}{cm}cm_pct"], out[f"recall_{name}{cm}cm_pct"], out[f"fscore_{name}{cm}cm_pct"] = prec, rec, f
    return out


def _same(got: float, want: float) -> bool:
    return (math.isnan(got) and math.isnan(want)) or got == pytest.approx(want, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_split_and_fscores_match_loops(seed):
    pred, gt, labels = _labelled_clouds(seed)
    got = M.evaluate_frame(pred, None, gt, None, labels)
    want = _brute_split(pred, gt, labels)
    for k, v in want.items():
        assert _same(got[k], v), (k, got[k], v)
    assert 0 < got["fscore_garment_2cm_pct"] < 100 and got["fscore_2cm_pct"] > got["fscore_1cm_pct"]
    assert got["fscore_1cm_pct"] == got["fscore_pct"]  # the default threshold is 1 cm
    # the standalone functions agree with evaluate_frame
    s = M.split_distances_cm(pred, gt, labels)
    assert (s.s2m_garment, s.s2m_rest, s.m2s_garment, s.m2s_rest) == pytest.approx(
        (got["s2m_garment_cm"], got["s2m_rest_cm"], got["m2s_garment_cm"], got["m2s_rest_cm"]))
    g = M.garment_fscore(pred, gt, labels, threshold_m=0.02)
    assert (g.precision, g.recall, g.fscore) == pytest.approx(
        (got["precision_garment_2cm_pct"], got["recall_garment_2cm_pct"], got["fscore_garment_2cm_pct"]))
    f = M.fscore(pred, gt, threshold_m=0.02)
    assert f.fscore == pytest.approx(got["fscore_2cm_pct"])
    # the scan without labels: no split keys; the overall F-scores stay
    plain = M.evaluate_frame(pred, None, gt, None)
    assert "s2m_garment_cm" not in plain and "fscore_garment_2cm_pct" not in plain and "fscore_2cm_pct" in plain


def test_no_garment_points_give_nan_and_summaries_skip_them():
    """A tight subject (no GT garment point): the garment keys are NaN, the rest equals the whole
    cloud, and summarise averages the garment keys over the frames that have them and counts them."""
    pred, gt, labels = _labelled_clouds(3)
    tight = M.evaluate_frame(pred, None, gt, None, np.zeros(len(gt), np.uint8))
    for k in ("s2m_garment_cm", "m2s_garment_cm", "fscore_garment_1cm_pct", "precision_garment_2cm_pct",
              "recall_garment_2cm_pct"):  # fmt: skip
        assert math.isnan(tight[k]), k
    assert tight["s2m_rest_cm"] == pytest.approx(tight["s2m_cm"]) and tight["m2s_rest_cm"] == pytest.approx(tight["m2s_cm"])
    loose = M.evaluate_frame(pred, None, gt, None, labels)
    s = M.summarise([loose, tight, loose])
    assert s["s2m_garment_cm"] == pytest.approx(loose["s2m_garment_cm"])  # nanmean: the tight frame skipped
    assert s["s2m_rest_cm"] == pytest.approx((2 * loose["s2m_rest_cm"] + tight["s2m_rest_cm"]) / 3)
    assert s["num_frames_garment"] == 2 and s["num_frames_m2s_garment"] == 2 and s["num_frames"] == 3
    assert math.isnan(M.summarise([tight])["s2m_garment_cm"]) and M.summarise([tight])["num_frames_garment"] == 0
    # the counts add up through nested summaries; a frame without labels reports none
    assert M.summarise([s, M.summarise([tight])])["num_frames_garment"] == 2
    assert "num_frames_garment" not in M.summarise([M.evaluate_frame(pred, None, gt, None)])


def _body_and_skirt(n_body: int, n_skirt: int, seed: int = 0):
    """A sphere 'body' (radius 15 cm) above a cylinder 'skirt' (radius 30 cm, 40 cm long); labels 0 / 1."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n_body, 3))
    body = 0.15 * u / np.linalg.norm(u, axis=1, keepdims=True)
    t = rng.uniform(0, 2 * math.pi, n_skirt)
    skirt = np.c_[0.3 * np.cos(t), rng.uniform(-0.6, -0.2, n_skirt), 0.3 * np.sin(t)]
    return np.r_[body, skirt], np.r_[np.zeros(n_body, np.uint8), np.ones(n_skirt, np.uint8)]


def test_garment_s2m_blows_up_when_the_skirt_is_dropped():
    gt, labels = _body_and_skirt(1500, 1500, seed=0)
    full, _ = _body_and_skirt(1500, 1500, seed=1)  # another sampling of the same clothed shape
    no_skirt = full[:1500]  # only the body
    good = M.evaluate_frame(full, None, gt, None, labels)
    bad = M.evaluate_frame(no_skirt, None, gt, None, labels)
    assert bad["s2m_garment_cm"] > 15.0 and good["s2m_garment_cm"] < 1.5  # the skirt is >= 15 cm from the body
    assert bad["s2m_rest_cm"] == pytest.approx(good["s2m_rest_cm"], abs=0.3)  # the body is as good as before
    assert bad["s2m_garment_cm"] > 1.8 * bad["s2m_cm"]  # the whole-cloud S2M dilutes it with the body
    assert math.isnan(bad["m2s_garment_cm"])  # no predicted point lands on the skirt...
    assert bad["fscore_garment_2cm_pct"] == 0 and bad["precision_garment_2cm_pct"] == 0  # ... F 0, not NaN
    assert good["fscore_garment_2cm_pct"] > 50


# ---------------------------------------------------------------------------- best of K, energy score
def _chamfer_ref(a, b) -> float:
    """PocoLoco Chamfer in cm from scipy's cKDTree directly: mean NN distance both ways, summed."""
    from scipy.spatial import cKDTree

    return 100 * (cKDTree(a).query(b)[0].mean() + cKDTree(b).query(a)[0].mean())


def _energy_ref(samples, gt) -> float:
    """ES = mean_k d(X_k, y) - 1 / (2 K (K - 1)) * sum over ordered pairs k != l of d(X_k, X_l); K = 1: d(X, y)."""
    k = len(samples)
    to_gt = sum(_chamfer_ref(x, gt) for x in samples) / k
    if k == 1:
        return to_gt
    spread = sum(_chamfer_ref(samples[i], samples[j]) for i in range(k) for j in range(k) if i != j)
    return to_gt - spread / (2 * k * (k - 1))


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_energy_score_and_best_of_k_match_the_reference(k):
    rng = np.random.default_rng(k)
    gt = rng.normal(size=(200, 3)) * 0.2
    samples = [gt[rng.permutation(200)[:150]] * rng.uniform(0.9, 1.1) + rng.normal(size=(150, 3)) * 0.02 for _ in range(k)]
    want = _energy_ref(samples, gt)
    assert M.energy_score_cm(samples, gt) == pytest.approx(want, rel=1e-9)
    assert M.best_of_k_cm(samples, gt) == pytest.approx(min(_chamfer_ref(x, gt) for x in samples), rel=1e-9)
    # the per-frame path of evaluate: evaluate_frame per sample + the samples' diversity
    labels = (gt[:, 1] < 0).astype(np.uint8)
    scores = [M.evaluate_frame(x, None, gt, None, labels) for x in samples]
    m = M.summarise_samples(scores, M.diversity_cm(samples) if k >= 2 else None)
    assert m["energy_score_cm"] == pytest.approx(want, rel=1e-9)
    assert m["best_of_k_chamfer_cm"] == pytest.approx(M.best_of_k_cm(samples, gt), rel=1e-9)
    assert m["num_samples"] == k and "num_frames" not in m and "num_frames_garment" not in m
    assert m["chamfer_cm"] == pytest.approx(np.mean([s["chamfer_cm"] for s in scores]))  # the mean over samples stays
    assert m["best_of_k_chamfer_cm"] <= m["chamfer_cm"] + 1e-12 and m["energy_score_cm"] <= m["chamfer_cm"] + 1e-12


def test_energy_score_of_one_or_identical_samples_is_the_chamfer():
    rng = np.random.default_rng(7)
    gt = rng.normal(size=(150, 3)) * 0.2
    x = gt + rng.normal(size=(150, 3)) * 0.01
    d = M.chamfer_cm(x, gt)
    assert M.energy_score_cm([x], gt) == pytest.approx(d, rel=1e-12)
    assert M.energy_score_cm([x, x, x], gt) == pytest.approx(d, rel=1e-12)
    assert M.best_of_k_cm([x], gt) == pytest.approx(d, rel=1e-12)
    one = M.summarise_samples([M.evaluate_frame(x, None, gt, None)])
    assert one["energy_score_cm"] == one["best_of_k_chamfer_cm"] == one["chamfer_cm"] and one["num_samples"] == 1
    with pytest.raises(ValueError, match="at least one sample"):
        M.energy_score_cm([], gt)
    with pytest.raises(ValueError, match="mean pairwise Chamfer"):
        M.energy_score_from_chamfers([1.0, 2.0], None)


def test_energy_score_prefers_a_calibrated_spread():
    """The scan's 'garment' is a sphere of radius 25, 30 or 35 cm (equally likely). A regressor predicts
    the middle one (the conditional median); a calibrated sampler draws the three; a biased sampler
    draws them 5 cm too wide. Mean Chamfer over samples favours the regressor (the sampler pays a
    spread term); the energy score ranks the calibrated sampler first and the biased one below it."""
    radii = (0.25, 0.30, 0.35)
    gt_dirs, _ = _sphere(1500, 1.0)
    pred_dirs, _ = _sphere(1000, 1.0)
    pred_dirs = pred_dirs @ np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # another sampling of the sphere

    def mean_over_scans(score):
        return np.mean([score(r * gt_dirs) for r in radii])

    calibrated = [r * pred_dirs for r in radii]
    biased = [(r + 0.05) * pred_dirs for r in radii]
    regressor = [0.30 * pred_dirs]
    es = {name: mean_over_scans(lambda y, s=s: M.energy_score_cm(s, y))
          for name, s in (("calibrated", calibrated), ("biased", biased), ("regressor", regressor))}  # fmt: skip
    mean_chamfer = {name: mean_over_scans(lambda y, s=s: np.mean([M.chamfer_cm(x, y) for x in s]))
                    for name, s in (("calibrated", calibrated), ("regressor", regressor))}  # fmt: skip
    assert mean_chamfer["regressor"] < mean_chamfer["calibrated"] - 1.0  # the unfair ranking: 7.7 vs 9.8 cm
    assert es["calibrated"] < es["biased"] - 1.0 and es["calibrated"] < es["regressor"] - 1.0  # 3.2 vs 6.3 vs 7.7
    # the regressor's ES is its Chamfer
    assert es["regressor"] == pytest.approx(mean_chamfer["regressor"])


def test_adjusted_energy_score_takes_the_resampling_noise_out_of_the_spread():
    """K samplers that are all resamples of the true surface (a perfect, spread-free model): raw ES
    lands about half a noise floor below the deterministic Chamfer of one resample; the adjusted ES
    gives that Chamfer back (within the noise of 4 samples); K = 1 is unchanged."""
    rng = np.random.default_rng(0)
    surface = rng.normal(size=(40_000, 3))
    surface /= np.linalg.norm(surface, axis=1, keepdims=True)  # a unit sphere, densely sampled
    gt = surface[rng.choice(len(surface), 1024, replace=False)]
    samples = [surface[rng.choice(len(surface), 1024, replace=False)] for _ in range(4)]
    floor = M.chamfer_cm(surface[rng.choice(len(surface), 1024, replace=False)], gt)
    to_gt = [M.chamfer_cm(x, gt) for x in samples]
    raw = M.energy_score_from_chamfers(to_gt, M.diversity_cm(samples))
    adj = M.energy_score_adjusted(raw, len(samples), floor)
    assert raw < 0.7 * np.mean(to_gt)  # the artefact: a perfect sampler "beats" its own Chamfer
    assert adj == pytest.approx(np.mean(to_gt), rel=0.05)
    assert M.energy_score_adjusted(3.0, 1, floor) == 3.0 and M.energy_score_adjusted(3.0, 4, None) == 3.0
    m = M.summarise_samples([M.evaluate_frame(x, None, gt, None) for x in samples], M.diversity_cm(samples), floor)
    assert m["energy_score_adj_cm"] == pytest.approx(adj, rel=1e-9)


def test_hypotheses_that_share_points_get_the_floor_of_resamples_sharing_as_many():
    """A perfect hybrid-like sampler: every hypothesis keeps the same 75 % of one resample of the
    surface and redraws 25 %. Its pairwise term holds only a quarter of the resampling noise, so
    adding the whole floor back over-corrects (ES adj. far above its own Chamfer); the floor of
    resamples sharing 75 % gives the Chamfer back. Independent samples: the plain floor, unchanged."""
    rng = np.random.default_rng(1)
    surface = rng.normal(size=(40_000, 3))
    surface /= np.linalg.norm(surface, axis=1, keepdims=True)
    n = 1024
    gt = surface[rng.choice(len(surface), n, replace=False)]
    other = surface[rng.choice(len(surface), n, replace=False)]
    order = rng.permutation(len(surface))  # disjoint draws: a redrawn point never repeats a kept one
    base = surface[order[:768]]
    samples = [np.concatenate([base, surface[order[768 + 256 * k: 1024 + 256 * k]]]) for k in range(4)]
    assert M.shared_fraction(samples) == pytest.approx(0.75, abs=1e-9)
    assert M.shared_fraction([gt, gt.copy()]) == 1.0
    assert M.shared_fraction([gt + 1e-6, gt]) == 0.0  # exact coordinates only
    overlap = len(set(map(tuple, gt)) & set(map(tuple, other))) / n  # two subsets of one scan overlap by chance
    assert M.shared_fraction([gt, other]) == pytest.approx(overlap, abs=1e-12)
    to_gt = [M.chamfer_cm(x, gt) for x in samples]
    raw = M.energy_score_from_chamfers(to_gt, M.diversity_cm(samples))
    plain = M.chamfer_cm(other, gt)
    assert M.partly_shared_floor_cm(gt, other, 0.0, (0,)) == pytest.approx(plain, rel=1e-12)  # a permutation of other
    assert M.partly_shared_floor_cm(gt, other, 1.0, (0,)) == 0.0
    shared_floor = M.partly_shared_floor_cm(gt, other, M.shared_fraction(samples), (0,))
    assert 0.1 * plain < shared_floor < 0.6 * plain
    assert M.energy_score_adjusted(raw, 4, plain) > 1.15 * np.mean(to_gt)  # the whole floor over-corrects
    assert M.energy_score_adjusted(raw, 4, shared_floor) == pytest.approx(np.mean(to_gt), rel=0.08)
    with pytest.raises(ValueError, match="shared"):
        M.partly_shared_floor_cm(gt, other, 1.5, (0,))
