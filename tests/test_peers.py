"""POP and CloSET in the shared harness (pocoloco.methods.pop / closet / skinned, evaluation.quality): training + exact resume,
checkpoint kinds, sample / eval / fit through the CLI, bench quality end to end. Tiny presets."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pocoloco.cli import main
from pocoloco.data.format import DatasetLayout, read_frame
from pocoloco.data.poses import pose_from_frame
from pocoloco.data.published import read_ply, write_ply
from pocoloco.engine import checkpoint as ckpt_io
from pocoloco.methods import load_method, train
from pocoloco.methods.pocoloco import load_denoiser
from pocoloco.methods.skinned import SKINNED_PRESETS, SkinnedTrainConfig, skinned_preset
from pocoloco.models.pop import LEGACY_TRAINING_FIELDS, POPLossWeights

pytestmark = pytest.mark.usefixtures("torch_single_thread")


def tiny(model: str, **kw) -> SkinnedTrainConfig:
    base = dict(steps=4, ckpt_every=2, sample_every=0, log_every=1)
    return skinned_preset(model, "tiny", **{**base, **kw})


@pytest.fixture(scope="module")
def runs(tiny_dataset, tmp_path_factory):
    """Tiny POP and CloSET runs, 4 steps each (normal loss from step 2)."""
    root = tmp_path_factory.mktemp("peers")
    out = {}
    for m in ("pop", "closet"):
        train(tiny(m), tiny_dataset, root / m, progress=False)
        out[m] = root / m
    return out


@pytest.fixture(scope="module")
def test_frame(tiny_dataset):
    """(spec, subject, path) of a test frame of the loose subject."""
    subject, seq, path = next(f for f in DatasetLayout(tiny_dataset).iter_frames("test") if f[0] == "skirt")
    idx = int(read_frame(path, ["frame_index"]).frame_index)
    return f"{tiny_dataset}:{subject}/test/{seq}/{idx}", subject, path


def _one_line_error(capsys, code):
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


# ---------------------------------------------------------------------------------- config
def test_presets_roundtrip_and_schedule():
    for (model, name), cfg in SKINNED_PRESETS.items():
        assert cfg.model == model and cfg.preset == name
        assert SkinnedTrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    c = skinned_preset("pop", "small", steps=800)
    assert c.normal_start == 500  # the paper's epoch 250 of 400
    assert c.pop_loss_weights() == POPLossWeights()  # the paper's (Eq. 3); the network config has none
    assert not LEGACY_TRAINING_FIELDS & set(c.net)
    assert skinned_preset("closet", "tiny", decomposition=False).net_config().decomposition is False
    with pytest.raises(ValueError, match="closet only"):
        skinned_preset("pop", "tiny", decomposition=False)
    with pytest.raises(ValueError, match="unknown training preset 'huge' for pop"):
        skinned_preset("pop", "huge")
    # a cool-down (wsd): constant, then linear to 0 over the last decay_steps; constant by default
    from pocoloco.engine.trainer import lr_at

    cool = skinned_preset("pop", "small", steps=10, lr_schedule="wsd", decay_steps=4).loop()
    assert [round(lr_at(cool, s) / 3e-4, 6) for s in (0, 5, 6, 7, 9)] == [1, 1, 1, 0.75, 0.25]
    assert {lr_at(skinned_preset("pop", "small").loop(), s) for s in (0, 9999)} == {3e-4}
    with pytest.raises(ValueError, match="wsd needs 0 < decay_steps"):
        skinned_preset("pop", "small", lr_schedule="wsd")


def test_a_pop_run_stored_with_training_fields_in_its_network_config_still_loads():
    """Checkpoints written before the split kept lr, batch, scan points and loss weights in ``net``:
    they load with the weights moved to ``pop_weights`` and the rest dropped (the run's own fields
    always held the same values); an unknown field is still refused."""
    new = skinned_preset("pop", "small", steps=800)
    old = new.to_dict()
    del old["pop_weights"]
    old["net"] = {**old["net"], "lr": new.lr, "lr_features": new.lr_codes, "batch_size": new.batch_size,
                  "num_scan_points": new.num_points, "normal_start": new.normal_start, "w_s2m": 2e4, "w_m2s": 1e4,
                  "w_normal": 0.1, "w_displacement": 2e3, "w_feature": 1.0}  # fmt: skip
    loaded = SkinnedTrainConfig.from_dict(old)
    assert loaded == new.replace(pop_weights={**new.pop_weights, "s2m": 2e4})
    assert SkinnedTrainConfig.from_dict(loaded.to_dict()) == loaded
    with pytest.raises(ValueError, match="unknown POPConfig field"):
        SkinnedTrainConfig.from_dict({**old, "net": {**old["net"], "w_bogus": 1.0}})
    with pytest.raises(ValueError, match="POPLossWeights.s2m"):
        new.replace(pop_weights={"s2m": -1.0})


# -------------------------------------------------------------------------------- training
@pytest.mark.parametrize("model", ["pop", "closet"])
def test_resume_equals_uninterrupted(runs, tiny_dataset, tmp_path, model):
    out = tmp_path / "run"
    train(tiny(model).replace(steps=2), tiny_dataset, out, progress=False)
    train(tiny(model), tiny_dataset, out, progress=False, resume=True)
    a = ckpt_io.load_checkpoint(runs[model], expect_model=model)
    b = ckpt_io.load_checkpoint(out, expect_model=model)
    assert a.step == b.step == 4
    assert a.model_state.keys() == b.model_state.keys()
    for k in a.model_state:  # weights, outfit codes and BatchNorm statistics: bit-exact
        assert torch.equal(a.model_state[k], b.model_state[k]), k
    recs = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    ref = [json.loads(x) for x in (runs[model] / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in recs] == [1, 2, 3, 4] and [r["loss"] for r in recs] == [r["loss"] for r in ref]
    assert [r["normal_on"] for r in recs] == [False, False, True, True]
    assert (out / "loss.png").is_file() and (out / "config.json").is_file()
    meta = b.meta
    assert [o["name"] for o in meta["outfits"]] == ["skirt", "tight"] and meta["model_kind"] == model
    assert meta["has_ema"] is False and "phenotype" in meta["outfits"][0]


def test_cli_trains_closet_without_decomposition_and_resumes(tiny_dataset, tmp_path, capsys):
    out = str(tmp_path / "run")
    base = ["train", "--model", "closet", "--data", str(tiny_dataset), "--out", out, "--no-progress", "--threads", "1"]
    assert main([*base, "--preset", "tiny", "--steps", "1", "--no-decomposition"]) == 0
    assert main([*base, "--resume", "--steps", "2"]) == 0  # config from the checkpoint
    ck = ckpt_io.load_checkpoint(out, expect_model="closet")
    assert ck.step == 2 and ck.config["net"]["decomposition"] is False
    assert not any(k.startswith(("garment_decoder", "pose_decoder")) for k in ck.model_state)
    capsys.readouterr()
    err = _one_line_error(capsys, main(["train", "--model", "pop", "--data", str(tiny_dataset), "--out", out,
                                        "--resume", "--no-progress"]))  # fmt: skip
    assert "checkpoint is of model 'closet', expected 'pop'" in err
    err = _one_line_error(capsys, main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "x"),
                                        "--no-decomposition", "--preset", "tiny"]))  # fmt: skip
    assert "--no-decomposition applies to --model closet only" in err


# ------------------------------------------------------------------------------ kinds
def test_checkpoint_kind_mismatch_is_one_line(runs, tiny_run, tiny_dataset, test_frame, tmp_path, capsys):
    with pytest.raises(ValueError, match="checkpoint is of model 'pop', expected 'closet'"):
        load_method(runs["pop"], expect="closet")
    with pytest.raises(ValueError, match="checkpoint is of model 'pocoloco', expected 'pop' or 'closet'"):
        load_method(tiny_run, expect=("pop", "closet"))
    with pytest.raises(ValueError, match="checkpoint is of model 'closet', expected 'pocoloco'"):
        load_denoiser(runs["closet"])
    # a CloSET checkpoint given to an app that needs a generative point model (the Method hook), and to POP's fit
    scan = tmp_path / "scan.ply"
    write_ply(scan, np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32) * 0.2,
              normals=np.tile([0, 0, 1.0], (300, 1)).astype(np.float32))
    err = _one_line_error(capsys, main(["complete", "--ckpt", str(runs["closet"]), "--partial", str(scan), "--joints",
                                        "demo:skirt", "--out", str(tmp_path / "c")]))  # fmt: skip
    assert "CloSET cannot complete, edit or animate point clouds" in err
    err = _one_line_error(capsys, main(["fit", "--ckpt", str(runs["closet"]), "--scan", str(scan), "--frame",
                                        test_frame[0], "--out", str(tmp_path / "f")]))  # fmt: skip
    assert "this CloSET checkpoint cannot fit a new outfit" in err
    err = _one_line_error(capsys, main(["fit", "--model", "pop", "--ckpt", str(runs["closet"]), "--scan", str(scan),
                                        "--frame", test_frame[0], "--out", str(tmp_path / "f")]))  # fmt: skip
    assert "checkpoint is of model 'closet', expected 'pop'" in err
    assert not (tmp_path / "f").exists() and not (tmp_path / "c").exists()


# ---------------------------------------------------------------------------------- sample
@pytest.mark.parametrize("model", ["pop", "closet"])
def test_sample_cli_one_deterministic_cloud(runs, test_frame, tmp_path, capsys, model):
    spec, subject, path = test_frame
    argv = ["sample", "--ckpt", str(runs[model]), "--joints", spec, "--points", "300", "--out", str(tmp_path / "a")]
    assert main(argv) == 0, capsys.readouterr().err
    out = tmp_path / "a"
    assert sorted(p.name for p in out.iterdir()) == ["hypotheses.png", "sample.json", "sample_000.ply"]
    meta = json.loads((out / "sample.json").read_text())
    assert meta["model_kind"] == model and meta["outfit"] == subject and meta["num"] == 1 and meta["deterministic"]
    ply = read_ply(out / "sample_000.ply")
    assert ply.points.shape == (300, 3) and ply.normals is not None
    # the same as the library call, and in the world frame of the frame (close to the body)
    loaded = load_method(runs[model])
    pose = pose_from_frame(path, subject, loaded.needs_mean_shape)
    ref = loaded.predict(pose, 300, (0,), loaded.outfit_id(subject))
    np.testing.assert_allclose(ply.points, ref.points[0], atol=1e-5)
    assert np.abs(ply.points.mean(0) - pose.body_vertices.mean(0)).max() < 0.3
    # by id, into a second folder: identical
    assert main([*argv[:-1], str(tmp_path / "b"), "--outfit", "0"]) == 0
    np.testing.assert_array_equal(read_ply(tmp_path / "b" / "sample_000.ply").points, ply.points)


def test_pop_gives_more_points_than_its_query_map(runs, test_frame):
    spec, subject, path = test_frame
    loaded = load_method(runs["pop"])
    P = loaded.model.num_query_points
    pose = pose_from_frame(path, subject, loaded.needs_mean_shape)
    pts = loaded.predict(pose, 2 * P + 7, (1,), 0).points[0]
    assert pts.shape == (2 * P + 7, 3) and len(np.unique(pts.round(7), axis=0)) == 2 * P + 7
    # a subset of the training map for N <= P: same points as the full map's prediction
    full = loaded.predict(pose, P, (0,), 0).points[0]
    part = loaded.predict(pose, 50, (3,), 0).points[0]
    d = np.linalg.norm(part[:, None] - full[None], axis=-1).min(1)
    assert d.max() < 1e-5


@pytest.mark.parametrize("model", ["pop", "closet"])
def test_even_cloud_is_the_farthest_point_subset_of_a_denser_draw(runs, test_frame, model):
    """``SamplerOptions.even`` / ``--even``: the cloud drawn at ``even_candidates(N)`` points (POP: every
    pixel of its training map while N fits in it, else its own N; CloSET: 4 N), cut to N by farthest-point
    sampling of the spots on the posed body they are decoded from (checked against the plain-loop
    reference), normals kept with their points; those spots cover the body better than N random
    ones do; off, it is ``predict``."""
    from scipy.spatial import cKDTree

    from pocoloco.body.surface import barycentric_interpolate
    from pocoloco.methods import SamplerOptions, predict_clouds
    from pocoloco.ops.sampling import farthest_point_sampling_reference

    spec, subject, path = test_frame
    loaded = load_method(runs[model])
    pose = pose_from_frame(path, subject, loaded.needs_mean_shape)
    o, n = loaded.outfit_id(subject), 40
    pixels = loaded.model.num_query_points if model == "pop" else None
    assert loaded.even_candidates(n) == (pixels if model == "pop" else 4 * n)
    if model == "pop":
        # beyond its training map POP's finer map is already near a grid: --even keeps its own layout
        assert pixels > n and loaded.even_candidates(pixels + 1) == pixels + 1
        np.testing.assert_array_equal(predict_clouds(loaded, pose, pixels + 1, (2,), o, SamplerOptions(even=True)).points,
                                      loaded.predict(pose, pixels + 1, (2,), o).points)  # fmt: skip
    m = loaded.even_candidates(n)
    dense = loaded.predict(pose, m, (2,), o)

    def spots(count):  # the query points of predict(pose, count, (2,)) on the posed body, by hand
        face_idx, bary = loaded.query_surface(count, 2)
        body = torch.from_numpy(pose.body_vertices.astype(np.float32))[None]
        return barycentric_interpolate(body, loaded.model.faces, torch.as_tensor(face_idx), torch.as_tensor(bary))[0].numpy()

    dense_spots = spots(m)
    np.testing.assert_allclose(loaded.even_layout_points(pose, m, (2,))[0], dense_spots, atol=1e-6)
    # the decoded points belong to those spots: each is its own spot's nearest decoded point more often than not
    assert (cKDTree(dense.points[0]).query(dense_spots)[1] == np.arange(m)).mean() > 0.5
    even = predict_clouds(loaded, pose, n, (2,), o, SamplerOptions(even=True))
    idx = farthest_point_sampling_reference(torch.from_numpy(dense_spots)[None], n)[0].numpy()
    np.testing.assert_array_equal(even.points[0], dense.points[0][idx])
    np.testing.assert_array_equal(even.normals[0], dense.normals[0][idx])
    at_random = loaded.predict(pose, n, (2,), o)
    np.testing.assert_array_equal(predict_clouds(loaded, pose, n, (2,), o).points, at_random.points)

    def covering_radius(points):  # the farthest any dense spot is from the set
        return cKDTree(points).query(dense_spots)[0].max()

    assert covering_radius(dense_spots[idx]) < 0.8 * covering_radius(spots(n))


def test_even_warns_when_farthest_point_sampling_will_be_slow(runs, test_frame, monkeypatch):
    """Past SLOW_FPS_WORK kept x candidate points, on a CPU: one warning saying so."""
    import warnings

    from pocoloco.methods import SamplerOptions, base, predict_clouds

    spec, subject, path = test_frame
    loaded = load_method(runs["closet"])
    pose = pose_from_frame(path, subject, loaded.needs_mean_shape)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # below the threshold: silent
        predict_clouds(loaded, pose, 30, (0,), 0, SamplerOptions(even=True))
    monkeypatch.setattr(base, "SLOW_FPS_WORK", 30 * 120 - 1)
    with pytest.warns(UserWarning, match="farthest-point sampling of 30 of 120 points a cloud may take a minute or more"):
        predict_clouds(loaded, pose, 30, (0,), 0, SamplerOptions(even=True))


def test_sample_cli_even(runs, test_frame, tmp_path, capsys):
    """``sample --even`` writes the library's evenly spread cloud and says so in sample.json."""
    from pocoloco.methods import SamplerOptions, predict_clouds

    spec, subject, path = test_frame
    out = tmp_path / "e"
    assert main(["sample", "--ckpt", str(runs["pop"]), "--joints", spec, "--points", "50", "--even", "--no-render",
                 "--out", str(out)]) == 0, capsys.readouterr().err  # fmt: skip
    meta = json.loads((out / "sample.json").read_text())
    assert meta["even"] is True and "farthest-point" in meta["query_points"]
    loaded = load_method(runs["pop"])
    pose = pose_from_frame(path, subject, loaded.needs_mean_shape)
    ref = predict_clouds(loaded, pose, 50, (0,), loaded.outfit_id(subject), SamplerOptions(even=True))
    np.testing.assert_allclose(read_ply(out / "sample_000.ply").points, ref.points[0], atol=1e-5)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"--outfit": "nobody"}, "outfit 'nobody' was never trained"),
        ({"--outfit": "7"}, "outfit '7' was never trained"),
        ({"--joints": "demo:nobody"}, "no such demo pose"),
        ({"--joints": "JOINTS"}, "need the posed body, not only joints"),
        ({"--num": "3"}, "deterministic"),
        ({"--points": "0"}, "--points must be >= 1"),
    ],
)
def test_sample_cli_bad_input(runs, test_frame, tmp_path, capsys, change, message):
    np.save(tmp_path / "joints.npy", np.zeros((24, 3), np.float32))
    opts = {"--ckpt": str(runs["pop"]), "--joints": test_frame[0], "--points": "50", "--out": str(tmp_path / "o")}
    opts.update({k: str(tmp_path / "joints.npy") if v == "JOINTS" else v for k, v in change.items()})
    err = _one_line_error(capsys, main(["sample", *[x for kv in opts.items() for x in kv]]))
    assert message in err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------ eval
def test_eval_cli_scores_peer_through_evaluate(runs, tiny_dataset, tmp_path, capsys):
    from pocoloco.evaluation.evaluate import EvalSettings, evaluate
    from pocoloco.evaluation.metrics import evaluate_frame

    out = tmp_path / "ev"
    argv = ["eval", "--ckpt", str(runs["closet"]), "--data", str(tiny_dataset), "--frames", "2", "--points", "200",
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    doc = json.loads((out / "eval.json").read_text())
    m = doc["means"]["model"]
    assert doc["settings"]["model_kind"] == "closet" and doc["settings"]["deterministic"]
    assert m["diversity_cm"] == 0.0 and m["diversity_garment_cm"] == 0.0
    assert {"nearest_frame", "posed_body", "gt_resample"} <= set(doc["means"])
    assert "CloSET (this checkpoint)" in (out / "eval.md").read_text() and (out / "examples.png").is_file()
    # the row is the metrics of predict_peer's cloud against the same GT subset
    res, _ = evaluate(runs["closet"], tiny_dataset, EvalSettings(num_frames=1, num_points=200, baselines=()))
    row = res.frames[0]
    subject, seq, path = DatasetLayout(tiny_dataset).iter_frames("test")[0]
    fr = read_frame(path)
    from pocoloco.evaluation.baselines import subset as _subset

    g = _subset(fr.num_points, 200, (0, 0))
    loaded = load_method(runs["closet"])
    pred = loaded.predict(pose_from_frame(path, subject, False), 200, (0,), loaded.outfit_id(subject))
    ref = evaluate_frame(pred.points[0], pred.normals[0], fr.points[g], fr.normals[g], fr.labels[g])
    assert row["model"]["chamfer_cm"] == pytest.approx(ref["chamfer_cm"], rel=1e-6)


# ------------------------------------------------------------------------------------- fit
def _scan_of(path, tmp_path, n=None, normals=True):
    fr = read_frame(path)
    sel = slice(None) if n is None else slice(0, n)
    f = tmp_path / f"scan_{n}_{normals}.ply"
    write_ply(f, fr.points[sel], normals=fr.normals[sel] if normals else None)
    return f


def test_fit_cli_adds_an_outfit_and_sample_animates_it(runs, tiny_dataset, test_frame, tmp_path, capsys):
    spec, subject, path = test_frame
    scan = _scan_of(path, tmp_path)
    out = tmp_path / "fitted"
    argv = ["fit", "--ckpt", str(runs["pop"]), "--scan", str(scan), "--frame", spec, "--steps", "25", "--lr", "0.05",
            "--name", "dress", "--start", "mean", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert "fitted" in capsys.readouterr().out
    rep = json.loads((out / "fit.json").read_text())
    assert rep["outfit"] == "dress" and rep["outfit_id"] == 2 and rep["loss_last"] < rep["loss_first"]
    assert rep["start"] == "mean" and rep["after"]["chamfer_cm"] <= rep["before_start"]["chamfer_cm"] + 1e-6
    new = load_method(out, expect="pop")
    old = load_method(runs["pop"])
    assert new.outfit_names() == ["skirt", "tight", "dress"]
    for k, v in old.model.state_dict().items():  # only the feature tensor grew; the network is unchanged
        w = new.model.state_dict()[k]
        assert torch.equal(w[: v.shape[0]] if k == "geom" else w, v), k
    assert not torch.equal(new.model.geom[2], old.model.geom.mean(0))
    # animate the new outfit in another pose (another subject's test frame)
    other = next(f for f in DatasetLayout(tiny_dataset).iter_frames("test") if f[0] == "tight")
    idx = int(read_frame(other[2], ["frame_index"]).frame_index)
    assert main(["sample", "--ckpt", str(out), "--outfit", "dress", "--joints",
                 f"{tiny_dataset}:tight/test/{other[1]}/{idx}", "--points", "100", "--out", str(tmp_path / "s")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "s" / "sample.json").read_text())["outfit"] == "dress"
    # the original checkpoint does not know it
    err = _one_line_error(capsys, main(["sample", "--ckpt", str(runs["pop"]), "--outfit", "dress", "--joints", spec,
                                        "--out", str(tmp_path / "s2")]))  # fmt: skip
    assert "outfit 'dress' was never trained" in err


def test_fit_starts_from_the_nearest_trained_outfit(runs, test_frame, tmp_path, capsys):
    """The default start is the trained outfit whose prediction is closest to the scan: with a zero
    learning rate the fitted outfit is exactly that outfit's features (and scores what it scores)."""
    spec, subject, path = test_frame
    scan = _scan_of(path, tmp_path)
    out = tmp_path / "fitted"
    assert main(["fit", "--ckpt", str(runs["pop"]), "--scan", str(scan), "--frame", spec, "--steps", "1", "--lr", "0",
                 "--name", "copy", "--out", str(out)]) == 0, capsys.readouterr().err  # fmt: skip
    rep = json.loads((out / "fit.json").read_text())
    old, new = load_method(runs["pop"]), load_method(out)
    nearest = old.outfit_names().index(rep["before_nearest_outfit"]["outfit"])
    assert rep["start"] == "nearest" and torch.equal(new.model.geom[2], old.model.geom[nearest])
    assert rep["after"]["chamfer_cm"] == pytest.approx(rep["before_start"]["chamfer_cm"])
    assert "--anchor is for PocoLoco" in _one_line_error(capsys, main(
        ["fit", "--ckpt", str(runs["pop"]), "--scan", str(scan), "--frame", spec, "--steps", "1", "--anchor", "1",
         "--out", str(tmp_path / "f2")]))  # fmt: skip


@pytest.mark.parametrize("kind, message", [("few", "fitting needs at least 256"), ("nonormals", "has no normals"),
                                           ("exists", "already holds a checkpoint"),
                                           ("millimetres", "not in metres?")])  # fmt: skip
def test_fit_cli_bad_scans(runs, test_frame, tmp_path, capsys, kind, message):
    spec, _, path = test_frame
    scan = _scan_of(path, tmp_path, n=100 if kind == "few" else None, normals=kind != "nonormals")
    if kind == "millimetres":  # the same scan in mm: refused, as completion refuses it, before any fit
        fr = read_frame(path)
        write_ply(scan, fr.points * 1000.0, normals=fr.normals)
    out = tmp_path / "fitted"
    if kind == "exists":
        ckpt_io.save_checkpoint(out / "checkpoints", 1, model_kind="pop", preset="tiny", config={},
                                normalisation=load_method(runs["pop"]).normalisation, model_state={"x": torch.zeros(1)})  # fmt: skip
    err = _one_line_error(capsys, main(["fit", "--ckpt", str(runs["pop"]), "--scan", str(scan), "--frame", spec,
                                        "--steps", "2", "--out", str(out)]))  # fmt: skip
    assert message in err
    assert kind == "exists" or not out.exists()


# ------------------------------------------------------------------------------- bench quality
def test_bench_quality_end_to_end(runs, tiny_run, tiny_dataset, tmp_path, capsys):
    out, work = tmp_path / "q", tmp_path / "work"
    argv = ["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pocoloco", str(tiny_run), "--ckpt-pop",
            str(runs["pop"]), "--ckpt-closet", str(runs["closet"]), "--train-steps", "1", "--preset", "tiny", "--work",
            str(work), "--frames", "2", "--points", "128", "--seeds", "0", "1", "--sampler", "ddim", "--steps", "2",
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    for name in ("quality.json", "quality.md", "quality.png"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "quality.json").read_text())
    assert list(doc["means"])[:4] == ["pocoloco", "pop", "closet", "closet_nodecomp"]
    assert {"nearest_frame", "posed_body"} <= set(doc["means"]) and doc["settings"]["trained_here"] == ["closet_nodecomp"]
    assert ckpt_io.load_checkpoint(work / "closet_nodecomp", expect_model="closet").config["net"]["decomposition"] is False
    for key in ("pop", "closet", "closet_nodecomp"):
        assert doc["means"][key]["diversity_cm"] == 0.0 and doc["means"][key]["num_parameters"] > 0
    assert doc["means"]["pocoloco"]["diversity_cm"] > 0
    assert sorted(doc["per_subject"]) == ["skirt", "tight"]
    # every model was scored on the same frames
    keys = [[r["key"] for r in doc["frames"][k]] for k in ("pocoloco", "pop", "closet", "baselines")]
    assert all(k == keys[0] for k in keys)
    md = (out / "quality.md").read_text()
    assert "CloSET (no decomposition)" in md and "## skirt" in md and "claims" in md
    assert {c["subject"] for c in doc["claims"]} == {"skirt"} and len(doc["claims"]) == 2
    # PocoLoco's targets: against both peers overall and on the loose skirt, against the posed body
    # on the tight subject, far outliers everywhere; checked against the tables they come from
    targets = {(t["subject"], t["target"]): t for t in doc["targets"]}
    assert ("all", "Chamfer <= POP") in targets and ("skirt", "Chamfer <= CloSET") in targets
    tight = targets[("tight", "Chamfer <= posed body + 0.3 cm")]
    assert tight["bound"] == pytest.approx(doc["per_subject"]["tight"]["posed_body"]["chamfer_cm"] + 0.3)
    assert tight["value"] == pytest.approx(doc["per_subject"]["tight"]["pocoloco"]["chamfer_cm"])
    assert not any(k == ("tight", "Chamfer <= POP") for k in targets)
    for t in doc["targets"]:
        assert t["holds"] == (t["value"] <= t["bound"] + 1e-9)
    assert "PocoLoco's targets:" in md
    # a checkpoint of the wrong kind for its option: one line, before any work
    capsys.readouterr()
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pop",
                                        str(runs["closet"]), "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "checkpoint is of model 'closet', expected 'pop'" in err and not (tmp_path / "q2").exists()
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pop", str(runs["pop"]),
                                        "--split", "nope", "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "unknown split 'nope'" in err and not (tmp_path / "q2").exists()
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-closet-nodecomp",
                                        str(runs["closet"]), "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "pass it to --ckpt-closet" in err
    # shipped aliases work in every --ckpt-* option: an unknown name, or a shipped POP given as CloSET
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pop", "default:nope",
                                        "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "default:nope" in err and "default:closet" in err and not (tmp_path / "q2").exists()
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-closet",
                                        "default:pop", "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "expected 'closet'" in err and not (tmp_path / "q2").exists()


def test_per_subject_models_in_eval_and_bench_quality(tiny_dataset, tiny_run, tmp_path, capsys):
    """The paper's one-model-per-subject training as a comparison row: every frame is sampled by its
    subject's model, on the frames a single model sees; missing or mismatched models are one-line
    errors before any work."""
    from pocoloco.evaluation.evaluate import EvalSettings, evaluate
    from pocoloco.methods.pocoloco import train_preset

    per = {}
    for subject in ("skirt", "tight"):
        cfg = train_preset("tiny", steps=1, batch_size=2, num_points=64, ckpt_every=0, sample_every=0, log_every=1,
                           subjects=[subject])  # fmt: skip
        train(cfg, tiny_dataset, tmp_path / subject, progress=False)
        per[subject] = tmp_path / subject
    settings = EvalSettings(num_frames=2, num_points=64, seeds=(0,), sampler="ddim", steps=2, baselines=())
    single, _ = evaluate(tiny_run, tiny_dataset, settings)
    res, _ = evaluate(per, tiny_dataset, settings)
    assert [r["key"] for r in res.frames] == [r["key"] for r in single.frames]
    assert sorted({r["subject"] for r in res.frames}) == ["skirt", "tight"]
    assert res.settings["per_subject_models"] and set(res.settings["checkpoint"]) == {"skirt", "tight"}
    assert res.settings["num_parameters"] == 2 * load_method(per["skirt"]).num_parameters
    # skirt frames came from the skirt model: the same frames scored by that model alone match
    only_skirt = EvalSettings(**{**settings.__dict__, "subjects": ("skirt",)})
    mapped, _ = evaluate(per, tiny_dataset, only_skirt)
    alone, _ = evaluate(per["skirt"], tiny_dataset, only_skirt)
    assert [r["model"]["chamfer_cm"] for r in mapped.frames] == [r["model"]["chamfer_cm"] for r in alone.frames]
    with pytest.raises(ValueError, match=r"no per-subject model for subjects \['tight'\]"):
        evaluate({"skirt": per["skirt"]}, tiny_dataset, settings)
    with pytest.raises(ValueError, match="the model for 'tight' was trained on \\['skirt'\\] only"):
        evaluate({"skirt": per["skirt"], "tight": per["skirt"]}, tiny_dataset, settings)

    out = tmp_path / "q"
    argv = ["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pocoloco", str(tiny_run),
            "--ckpt-pocoloco-per-subject", str(per["skirt"]), str(per["tight"]), "--frames", "2", "--points", "64",
            "--seeds", "0", "--sampler", "ddim", "--steps", "2", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    doc = json.loads((out / "quality.json").read_text())
    assert {"pocoloco", "pocoloco_per_subject"} <= set(doc["means"])
    assert set(doc["checkpoints"]["pocoloco_per_subject"]["path"]) == {"skirt", "tight"}
    assert "a model per subject (paper)" in (out / "quality.md").read_text()
    capsys.readouterr()
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pocoloco-per-subject",
                                        str(tiny_run), "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "takes models trained with --subjects" in err and not (tmp_path / "q2").exists()
    err = _one_line_error(capsys, main(["bench", "quality", "--data", str(tiny_dataset), "--ckpt-pocoloco-per-subject",
                                        str(per["skirt"]), str(per["skirt"]), "--out", str(tmp_path / "q2")]))  # fmt: skip
    assert "two models for subject 'skirt'" in err


def test_check_targets_against_hand_made_tables():
    """Each target holds exactly when PocoLoco's number is within its bound; tight subjects are
    compared with the posed body only, loose ones with the peers and the GT loose share."""
    from pocoloco.evaluation.quality import check_targets

    def row(chamfer, loose=None, gt=None, far=None):
        r = {"chamfer_cm": chamfer}
        if loose is not None:
            r["loose_pred_pct"] = loose
        if gt is not None:
            r["loose_gt_pct"] = gt
        if far is not None:
            r["outlier_10cm_pct_max"] = far
        return r

    per_subject = {
        "skirt": {"pocoloco": row(4.0, 50.0, 54.0, 0.5), "pop": row(4.2, 20.0, 54.0), "closet": row(3.9, 30.0, 54.0),
                  "posed_body": row(6.0, 30.0, 54.0)},
        "tight": {"pocoloco": row(2.7, 0.0, 0.0, 2.0), "pop": row(2.4, 0.0, 0.0), "posed_body": row(2.45, 0.0, 0.0)},
    }  # fmt: skip
    means = {"pocoloco": row(3.5, far=2.0), "pop": row(3.6), "closet": row(3.4)}
    got = {(t["subject"], t["target"]): t["holds"] for t in check_targets(means, per_subject)}
    assert got == {
        ("all", "Chamfer <= POP"): True, ("all", "Chamfer <= CloSET"): False,
        ("all", "every cloud <= 1 % of points > 10 cm off"): False,
        ("skirt", "Chamfer <= POP"): True, ("skirt", "Chamfer <= CloSET"): False,
        ("skirt", "loose share within 3 points of GT"): False,  # |50 - 54| = 4
        ("skirt", "every cloud <= 1 % of points > 10 cm off"): True,
        ("tight", "Chamfer <= posed body + 0.3 cm"): True,  # 2.7 <= 2.75
        ("tight", "every cloud <= 1 % of points > 10 cm off"): False,
    }  # fmt: skip
    assert check_targets({"pop": row(1.0)}, {}) == []


def test_train_on_a_subset_of_subjects(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "run"
    train(tiny("pop", steps=1, subjects=["tight"]), tiny_dataset, out, progress=False)
    loaded = load_method(out, expect="pop")
    assert loaded.outfit_names() == ["tight"] and loaded.model.num_outfits == 1
    with pytest.raises(ValueError, match="outfit 'skirt' was never trained"):
        loaded.outfit_id("skirt")
    with pytest.raises(ValueError, match="unknown subjects"):
        train(tiny("pop", steps=1, subjects=["nobody"]), tiny_dataset, tmp_path / "x", progress=False)


@pytest.mark.parametrize("model", ["pop", "closet", "hybrid"])
def test_shipped_peer_samples_a_demo_pose(tmp_path, capsys, model):
    """``--ckpt default:pop`` / ``default:closet`` / ``default:hybrid``: the shipped peers load and dress the README's demo
    pose (its anny pose, posed with the outfit's body) near that body; an unknown ``default:`` name is a
    one-line error."""
    out = tmp_path / model
    argv = ["sample", "--ckpt", f"default:{model}", "--joints", "demo:skirt", "--points", "500", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    meta = json.loads((out / "sample.json").read_text())
    assert meta["model_kind"] == model and meta["outfit"].startswith("skirt")
    ply = read_ply(out / "sample_000.ply")
    assert ply.points.shape == (500, 3) and np.isfinite(ply.points).all()
    method = load_method(meta["checkpoint"])
    pose = method.load_pose("demo:skirt", method.outfit_id(meta["outfit"]))
    from scipy.spatial import cKDTree

    dist = cKDTree(pose.body_vertices).query(ply.points)[0]  # metres to the nearest posed-body vertex
    assert np.median(dist) < 0.05 and np.quantile(dist, 0.95) < 0.25, (np.median(dist), np.quantile(dist, 0.95))
    err = _one_line_error(capsys, main([*argv[:2], "default:nope", *argv[3:-1], str(tmp_path / "x")]))
    assert "default:pop" in err and "default:closet" in err and "default:hybrid" in err
    if model != "hybrid":  # a regressor told how to sample: it says it ignores that, once
        assert main([*argv[:-1], str(tmp_path / "steps"), "--steps", "5", "--finish-t", "5", "--no-render"]) == 0
        assert capsys.readouterr().err.count("is deterministic: --sampler / --steps / --finish-t do not apply") == 1


def test_describe_checkpoint_names_shipped_and_relative_paths(tmp_path, monkeypatch):
    from pocoloco.engine.shipped import ASSETS_DIR, describe_checkpoint

    assert describe_checkpoint(ASSETS_DIR / "pop_medium") == "default:pop"
    assert describe_checkpoint(ASSETS_DIR / "pocoloco_medium") == "default"
    (tmp_path / "runs" / "a").mkdir(parents=True)
    monkeypatch.chdir(tmp_path)
    assert describe_checkpoint(tmp_path / "runs" / "a") == "runs/a"
    assert describe_checkpoint("/elsewhere/ckpt") == "/elsewhere/ckpt"
    # a linked hybrid names shipped models by name, every other folder by its absolute path (even
    # one whose relative name starts like a shipped one)
    from pocoloco.engine.shipped import shipped_name
    from pocoloco.methods.hybrid.assemble import link_name

    (tmp_path / "default_run").mkdir()
    assert shipped_name(ASSETS_DIR / "hybrid_medium") == "default:hybrid" and shipped_name(tmp_path) is None
    assert link_name(ASSETS_DIR / "pop_medium") == "default:pop"
    assert link_name("default_run") == str(tmp_path / "default_run")


# ------------------------------------------------------------------ what the shared loop adds
def _ddp_peer_worker(rank: int, world: int, port: int, data: str, out: str, model: str) -> None:
    import os

    import torch.distributed as dist

    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        res = train(tiny(model, steps=3, ckpt_every=0, ema_decay=0.5), data, out, progress=False)
        # parameters (BatchNorm running statistics are each rank's own until rank 0's are broadcast
        # at the next forward; the checkpoint is rank 0's)
        params = lambda m: {k: v.detach().clone() for k, v in m.named_parameters()}  # noqa: E731
        torch.save({"model": params(res.model), "ema": params(res.ema)}, f"{out}.rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize("model", ["pop", "closet"])
def test_peers_train_with_ddp_and_ema_through_the_shared_loop(tiny_dataset, tmp_path, model):
    """POP and CloSET gain the loop's DDP and EMA: two gloo processes keep identical parameters, the
    checkpoint (rank 0) holds EMA weights that differ from the raw ones, and the EMA is what loads."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "run"
    torch.multiprocessing.spawn(_ddp_peer_worker, args=(2, port, str(tiny_dataset), str(out), model), nprocs=2)
    r0, r1 = (torch.load(f"{out}.rank{r}.pt", weights_only=True) for r in range(2))
    for key in ("model", "ema"):
        assert all(torch.equal(r0[key][k], r1[key][k]) for k in r0[key]), key
    ck = ckpt_io.load_checkpoint(out, expect_model=model)
    assert ck.step == 3 and ck.meta["world_size"] == 2 and ck.ema_state is not None
    assert max(float((ck.ema_state[k].float() - ck.model_state[k].float()).abs().max())
               for k in ck.model_state if ck.model_state[k].is_floating_point()) > 1e-6  # fmt: skip
    loaded = load_method(out)
    assert all(torch.equal(v.cpu(), ck.ema_state[k]) for k, v in loaded.model.state_dict().items())


def test_closet_trains_under_bf16_and_pop_refuses_it(tiny_dataset, tmp_path):
    res = train(tiny("closet", steps=2, ckpt_every=0, bf16=True), tiny_dataset, tmp_path / "c", progress=False)
    assert res.step == 2 and np.isfinite(res.final_loss)
    with pytest.raises(ValueError, match="bf16 is not available for POP"):
        tiny("pop", bf16=True)
