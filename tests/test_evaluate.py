"""pocoloco eval: frame selection, the two baselines, per-frame scores vs. metrics, CLI output and bad input."""

import json
import math

import numpy as np
import pytest
from conftest import run_cli
from test_metrics import _brute_split, _chamfer_ref, _energy_ref

from pocoloco.data.format import DatasetLayout, read_frame
from pocoloco.evaluation.baselines import NearestFrameBaseline, select_frames
from pocoloco.evaluation.evaluate import EvalSettings, evaluate, markdown_tables
from pocoloco.evaluation.metrics import evaluate_frame

pytestmark = pytest.mark.usefixtures("torch_single_thread")


@pytest.fixture(scope="module")
def run(tiny_run):
    """A tiny model trained for 2 steps (its run folder; conftest.tiny_run)."""
    return tiny_run


def test_select_frames_even_and_all():
    assert select_frames(list(range(10)), 0) == list(range(10))
    assert select_frames(list(range(10)), 20) == list(range(10))
    assert select_frames(list(range(10)), 3) == [0, 4, 9]  # round(4.5) = 4 (banker's rounding)
    assert select_frames(list(range(10)), 1) == [0]


def test_nearest_frame_finds_itself_and_follows_the_root(tiny_dataset):
    base = NearestFrameBaseline(tiny_dataset)
    frames = DatasetLayout(tiny_dataset).iter_frames("train")
    k = len(frames) // 2
    fr = read_frame(frames[k][2], ["joints", "points"])
    i, rms, yaw = base.nearest(fr.joints)
    assert rms == 0.0 and yaw == 0.0 and base.joints[i].tolist() == base.joints[k].tolist()
    # a translated pose finds the same frame; its points move with the root (exactly)
    shift = np.array([1.5, -0.25, 0.1])
    i2, rms2, _ = base.nearest(fr.joints + shift)
    assert i2 == i and rms2 < 1e-6
    a = base.predict(fr.joints, 50, (1, 0))
    b = base.predict(fr.joints + shift, 50, (1, 0))
    np.testing.assert_allclose(b["points"] - a["points"], np.broadcast_to(shift, (50, 3)), atol=1e-5)
    # brute force over every training frame agrees with the vectorised search
    q = fr.joints + np.random.default_rng(0).normal(scale=0.05, size=fr.joints.shape)
    q = q - q[0]
    brute = [((read_frame(p, ["joints"]).joints - read_frame(p, ["joints"]).joints[0] - q) ** 2).sum() for _, _, p in frames]
    assert base.nearest(q)[0] == int(np.argmin(brute))
    # restricted to one subject: the nearest among that subject's frames only
    other = next(s for s, _, _ in frames if s != frames[k][0])
    j = base.nearest(fr.joints, subject=other)[0]
    assert frames[j][0] == other
    own = [b for b, (s, _, _) in zip(brute, frames) if s == other]
    assert brute[j] == min(own)
    with pytest.raises(ValueError, match="no training frames of subject"):
        base.nearest(fr.joints, subject="nobody")


def _turn(x: np.ndarray, deg: float, about: np.ndarray) -> np.ndarray:
    """x (..., 3) turned by deg about the vertical (y) axis through ``about``, via a rotation matrix."""
    t = np.radians(deg)
    rot = np.array([[np.cos(t), 0.0, np.sin(t)], [0.0, 1.0, 0.0], [-np.sin(t), 0.0, np.cos(t)]])
    return (x - about) @ rot.T + about


def test_nearest_frame_yaw_alignment_against_a_grid_search(tiny_dataset):
    """``align="yaw"``: a training pose turned about the vertical axis and moved is found again with
    the turn recovered, its scan turned onto the query; the closed-form yaw matches a 0.1-degree
    grid search; root alignment alone misses the turned pose."""
    frames = DatasetLayout(tiny_dataset).iter_frames("train")
    k = len(frames) // 3
    fr = read_frame(frames[k][2], ["joints", "points", "normals"])
    shift = np.array([0.3, 0.0, -0.2])
    q = _turn(fr.joints.astype(np.float64), 150.0, fr.joints[0]) + shift
    yaw = NearestFrameBaseline(tiny_dataset, align="yaw")
    i, rms, theta = yaw.nearest(q)
    assert yaw.joints[i].tolist() == yaw.joints[k].tolist() and rms < 1e-6
    assert abs(np.degrees(theta) - 150.0) < 1e-6
    pred = yaw.predict(q, 40, (1, 0))
    plain = NearestFrameBaseline(tiny_dataset).predict(fr.joints, 40, (1, 0))  # same subset, unturned
    np.testing.assert_allclose(pred["points"], _turn(plain["points"], 150.0, fr.joints[0]) + shift, atol=1e-4)
    np.testing.assert_allclose(pred["normals"], _turn(plain["normals"], 150.0, np.zeros(3)), atol=1e-5)
    assert NearestFrameBaseline(tiny_dataset).nearest(q)[1] > 10 * rms + 0.05  # root-only: a far pose
    # closed form vs grid search over the angle, for a noisy query against every frame
    noisy = q + np.random.default_rng(1).normal(scale=0.03, size=q.shape)
    i, rms, theta = yaw.nearest(noisy)
    qa = noisy - noisy[0]
    best = []
    for f in range(len(frames)):
        src = yaw.joints[f] - yaw.joints[f, 0]
        errs = [((_turn(src, d, np.zeros(3)) - qa) ** 2).sum(-1).mean() for d in np.arange(-180, 180, 0.1)]
        best.append(min(errs))
    assert i == int(np.argmin(best)) and abs(rms - np.sqrt(min(best))) < 1e-3
    with pytest.raises(ValueError, match="must be one of root, yaw"):
        NearestFrameBaseline(tiny_dataset, align="pitch")


def test_evaluate_rows_match_the_metrics(run, tiny_dataset):
    settings = EvalSettings(split="test", num_frames=2, num_points=96, seeds=(0, 1), sampler="ddim", steps=3)
    result, examples = evaluate(run, tiny_dataset, settings, keep_examples=1)
    assert len(result.frames) == 2 and len(examples) == 1
    assert set(result.means) == {"model", "nearest_frame", "posed_body", "gt_resample"}
    row = result.frames[0]
    # the GT resample row recomputed by hand: same subsets, same metric function
    subject, split, sequence, idx = row["key"].split("/")
    fr = read_frame(DatasetLayout(tiny_dataset).frame_path(subject, split, sequence, int(idx)))
    rng_gt = np.sort(np.random.default_rng([0, 0]).choice(fr.num_points, 96, replace=False))
    rng_other = np.sort(np.random.default_rng([2, 0]).choice(fr.num_points, 96, replace=False))
    ref = evaluate_frame(fr.points[rng_other], fr.normals[rng_other], fr.points[rng_gt], fr.normals[rng_gt],
                         fr.labels[rng_gt])  # fmt: skip
    for k, v in ref.items():
        assert row["gt_resample"][k] == pytest.approx(v, rel=1e-9, abs=1e-12), k
    # an (almost) untrained model is far worse than the scan's own resampling noise and than the body
    m = result.means
    assert m["model"]["chamfer_cm"] > 3 * m["gt_resample"]["chamfer_cm"]
    assert m["model"]["chamfer_cm"] > m["posed_body"]["chamfer_cm"]
    assert m["model"]["diversity_cm"] > 0 and "diversity_garment_cm" in m["model"]
    assert m["model"]["seconds_per_sample"] > 0
    assert m["nearest_frame"]["pose_rms_cm"] > 0  # test poses are not in the training set
    text = markdown_tables(result)
    assert "| PocoLoco (this checkpoint) |" in text and "nearest training frame" in text
    assert "Chamfer ES (not proper) cm" in text and "best-of-K Chamfer" in text and "S2M garment cm" in text and "F garment@2cm %" in text


def test_evaluate_scores_the_sample_set_and_the_garment(run, tiny_dataset):
    """Per frame: best of K and the energy score of the model's K samples, and the garment / rest split
    averaged over them, against slow references on the clouds evaluate scored; K = 1 rows (baselines)
    have ES = best of K = Chamfer; the tight subject has no garment frame and NaN garment columns."""
    settings = EvalSettings(split="test", num_frames=4, num_points=80, seeds=(0, 1, 2), sampler="ddim", steps=2)
    result, examples = evaluate(run, tiny_dataset, settings, keep_examples=4)
    assert [e["key"] for e in examples] == [r["key"] for r in result.frames]
    for row, ex in zip(result.frames, examples):
        gt, lab = ex["gt"]
        samples = [np.asarray(x, np.float64) for x in ex["model"]]
        m = row["model"]
        assert m["num_samples"] == 3
        assert m["best_of_k_chamfer_cm"] == pytest.approx(min(_chamfer_ref(x, gt) for x in samples), rel=1e-6)
        assert m["energy_score_cm"] == pytest.approx(_energy_ref(samples, gt), rel=1e-6)
        refs = [_brute_split(x, gt, lab) for x in samples]
        for k in ("s2m_garment_cm", "s2m_rest_cm", "m2s_garment_cm", "fscore_garment_2cm_pct", "recall_2cm_pct"):
            vals = [r[k] for r in refs if not math.isnan(r[k])]
            assert (math.isnan(m[k]) and not vals) or m[k] == pytest.approx(np.mean(vals), rel=1e-6), k
        for b in ("nearest_frame", "posed_body", "gt_resample"):
            assert row[b]["num_samples"] == 1
            assert row[b]["energy_score_cm"] == row[b]["best_of_k_chamfer_cm"] == row[b]["chamfer_cm"]
    loose = {s: [r for r in result.frames if r["subject"] == s] for s in result.per_subject}
    assert set(loose) == {"skirt", "tight"}
    for subject, rows in loose.items():
        means = result.per_subject[subject]["model"]
        with_garment = sum(r["model"]["loose_gt_pct"] > 0 for r in rows)
        assert means["num_frames_garment"] == with_garment
        assert (with_garment == 0) == math.isnan(means["s2m_garment_cm"])
    assert result.per_subject["tight"]["model"]["num_frames_garment"] == 0
    assert result.means["model"]["num_frames_garment"] == result.per_subject["skirt"]["model"]["num_frames_garment"] > 0
    assert result.means["model"]["num_samples"] == 3 and result.means["posed_body"]["num_samples"] == 1


def test_nearest_frame_on_the_train_split_is_the_frame_itself(tiny_dataset):
    settings = EvalSettings(split="train", num_frames=2, num_points=200, baselines=("nearest_frame", "gt_resample"))
    result, _ = evaluate(None, tiny_dataset, settings, keep_examples=0)
    m = result.means
    assert "model" not in m and m["nearest_frame"]["pose_rms_cm"] == 0.0
    # the same scan subsampled twice: within 30 % of the GT-resample noise floor
    assert m["nearest_frame"]["chamfer_cm"] == pytest.approx(m["gt_resample"]["chamfer_cm"], rel=0.3)


def test_cli_writes_everything(run, tiny_dataset, tmp_path):
    out = tmp_path / "ev"
    r = run_cli("eval", "--ckpt", str(run), "--data", str(tiny_dataset), "--frames", "1", "--points", "64",
                "--seeds", "0", "1", "--sampler", "ddim", "--steps", "2", "--out", str(out))  # fmt: skip
    assert r.returncode == 0, r.stderr
    for name in ("eval.json", "eval.md", "chamfer_per_frame.png", "examples.png"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "eval.json").read_text())
    assert doc["settings"]["num_points"] == 64 and len(doc["frames"]) == 1 and "model" in doc["means"]
    assert "Chamfer cm" in r.stdout
    # the new columns: printed, in eval.md, and in the per-frame rows (to compare two runs frame by frame)
    for header in ("best-of-K Chamfer", "Chamfer ES (not proper) cm", "| K |", "S2M garment cm", "M2S rest cm", "F@1cm %", "F@2cm %",
                   "P@2cm %", "R@2cm %", "F garment@2cm %", "garment frames"):  # fmt: skip
        assert header in r.stdout and header in (out / "eval.md").read_text(), header
    frame = doc["frames"][0]["model"]
    assert frame["num_samples"] == 2 and frame["best_of_k_chamfer_cm"] <= frame["chamfer_cm"]
    assert {"energy_score_cm", "s2m_garment_cm", "fscore_garment_2cm_pct", "precision_2cm_pct"} <= set(frame)
    assert doc["means"]["model"]["num_frames_garment"] in (0, 1)


def test_eval_even_scores_the_evenly_spread_clouds(run, tiny_dataset):
    """``EvalSettings.even`` (``eval`` / ``bench quality --even``): the model's clouds are
    ``predict_clouds(..., even=True)``'s (the frame's Chamfer recomputed from them), the GT subset
    stays random, and the settings record it."""
    from pocoloco.evaluation.baselines import subset
    from pocoloco.evaluation.metrics import chamfer_cm
    from pocoloco.methods import SamplerOptions, load_method, predict_clouds

    settings = EvalSettings(num_frames=1, num_points=64, seeds=(0,), sampler="ddim", steps=2, baselines=(), even=True)
    result, _ = evaluate(run, tiny_dataset, settings, keep_examples=0)
    assert result.settings["even"] is True and "evenly spread (`--even`)" in markdown_tables(result)
    frame = result.frames[0]
    subject, seq, path = next(f for f in DatasetLayout(tiny_dataset).iter_frames("test")
                              if f"{f[0]}/test/{f[1]}/" in frame["key"])  # fmt: skip
    method = load_method(run)
    fr = read_frame(path, ["points"])
    gt = fr.points[subset(fr.num_points, 64, (0, 0))].astype(np.float64)
    pose = method.pose_from_frame(path, subject)
    cloud = predict_clouds(method, pose, 64, (0,), None, SamplerOptions(sampler="ddim", steps=2, even=True)).points[0]
    assert frame["model"]["chamfer_cm"] == pytest.approx(chamfer_cm(cloud.astype(np.float64), gt), rel=1e-5)


def test_bench_quality_even(run, tiny_dataset, tmp_path):
    """``bench quality --even`` reaches the settings and says so in quality.md."""
    from pocoloco.cli import main

    out = tmp_path / "qe"
    assert main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pocoloco", str(run), "--frames", "1",
                 "--points", "64", "--seeds", "0", "--sampler", "ddim", "--steps", "2", "--even", "--out", str(out)]) == 0  # fmt: skip
    assert json.loads((out / "quality.json").read_text())["settings"]["even"] is True
    assert "evenly spread (`--even`" in (out / "quality.md").read_text()


def test_bench_quality_prints_the_new_columns(run, tiny_dataset, tmp_path):
    out = tmp_path / "q"
    r = run_cli("bench", "quality", "--data", str(tiny_dataset), "--ckpt-pocoloco", str(run), "--frames", "2",
                "--points", "64", "--seeds", "0", "1", "--sampler", "ddim", "--steps", "2", "--out", str(out))  # fmt: skip
    assert r.returncode == 0, r.stderr
    md = (out / "quality.md").read_text()
    for header in ("best-of-K Chamfer", "Chamfer ES (not proper) cm", "| K |", "S2M garment cm", "S2M rest cm", "F@2cm %",
                   "F garment@1cm %", "garment frames"):  # fmt: skip
        assert header in r.stdout and header in md, header
    assert md.count("S2M garment cm") == 3  # all frames, skirt, tight
    doc = json.loads((out / "quality.json").read_text())
    poco, body = doc["means"]["pocoloco"], doc["means"]["posed_body"]
    assert poco["num_samples"] == 2 and body["num_samples"] == 1
    assert body["energy_score_cm"] == pytest.approx(body["chamfer_cm"])
    assert poco["energy_score_cm"] < poco["chamfer_cm"] and poco["best_of_k_chamfer_cm"] <= poco["chamfer_cm"]
    assert doc["per_subject"]["tight"]["pocoloco"]["s2m_garment_cm"] is None  # NaN -> null: no garment frame
    assert doc["per_subject"]["tight"]["pocoloco"]["num_frames_garment"] == 0
    rows = doc["frames"]["pocoloco"]
    assert all("energy_score_cm" in f["model"] and "best_of_k_chamfer_cm" in f["model"] for f in rows)


def test_a_deterministic_model_has_one_sample_and_es_equal_to_its_chamfer(run, tiny_dataset, monkeypatch):
    """POP / CloSET path (here the tiny model flagged deterministic): one cloud per frame, K = 1,
    best of K = energy score = Chamfer, diversity 0."""
    import pocoloco.evaluation.evaluate as E

    real = E.load_method

    def deterministic(*args, **kwargs):
        method = real(*args, **kwargs)
        method.deterministic = True
        return method

    monkeypatch.setattr(E, "load_method", deterministic)
    settings = EvalSettings(num_frames=2, num_points=64, seeds=(0, 1, 2), sampler="ddim", steps=2, baselines=())
    result, _ = E.evaluate(run, tiny_dataset, settings, keep_examples=0)
    for row in result.frames:
        m = row["model"]
        assert m["num_samples"] == 1 and m["diversity_cm"] == 0.0
        assert m["energy_score_cm"] == m["best_of_k_chamfer_cm"] == m["chamfer_cm"]
    assert result.means["model"]["num_samples"] == 1


def test_old_tables_without_the_new_keys_still_render():
    from pocoloco.evaluation.quality import garment_table_markdown, table_markdown

    old = {"pop": {"chamfer_cm": 3.0, "s2m_cm": 1.5, "m2s_cm": 1.5, "fscore_pct": 40.0}}
    assert garment_table_markdown(old) == "" and "| POP | 3.00 | 1.50 | 1.50 |" in table_markdown(old)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--points", "0"], "num_points must be >= 1"),
        (["--sampler", "euler"], "unknown sampler"),
        (["--seeds", "1", "1"], "seeds must be distinct"),
        (["--split", "val"], "unknown split"),
        (["--subjects", "nobody"], "unknown subjects"),
    ],
)
def test_cli_bad_input_is_one_line_and_writes_nothing(run, tiny_dataset, tmp_path, args, message):
    out = tmp_path / "ev"
    r = run_cli("eval", "--ckpt", str(run), "--data", str(tiny_dataset), "--frames", "1", "--points", "32",
                "--out", str(out), *args)  # fmt: skip
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not out.exists()


def test_cli_not_a_dataset_and_wrong_checkpoint(run, tmp_path):
    (tmp_path / "nodata").mkdir()
    r = run_cli("eval", "--ckpt", str(run), "--data", str(tmp_path / "nodata"), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "card.json" in r.stderr and not (tmp_path / "o").exists()
    r = run_cli("eval", "--ckpt", str(tmp_path / "nodata"), "--data", str(tmp_path / "nodata"), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
