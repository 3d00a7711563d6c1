"""PocoLoco conditioned on the posed body (``--body-points K``): the network's checks, the vertex
ids, training, sampling from dataset frames, eval, fitting, and one-line errors where a body is
missing (bare joints, the apps)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pocoloco.cli import main
from pocoloco.data.format import DatasetLayout, read_frame, read_subject
from pocoloco.data.published import write_ply
from pocoloco.methods import load_method, train
from pocoloco.methods.base import SamplerOptions
from pocoloco.methods.pocoloco import train_preset
from pocoloco.models import LatentDenoiser, denoiser_preset, latent_preset
from pocoloco.models.conditioning import PoseCondition
from pocoloco.models.pocoloco import PocoLocoDenoiser
from pocoloco.ops.sampling import farthest_point_sampling_reference

pytestmark = pytest.mark.usefixtures("torch_single_thread")

K = 12


def _one_line_error(capsys, code):
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.fixture(scope="module")
def body_run(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("body") / "run"
    cfg = train_preset("latent_tiny", steps=2, batch_size=2, num_points=64, ckpt_every=0, sample_every=0, log_every=1,
                       outfit_codes=True, body_points=K)  # fmt: skip
    train(cfg, tiny_dataset, out, progress=False)
    return out


@pytest.fixture(scope="module")
def skirt_frame(tiny_dataset):
    subject, seq, path = next(f for f in DatasetLayout(tiny_dataset).iter_frames("test") if f[0] == "skirt")
    idx = int(read_frame(path, ["frame_index"]).frame_index)
    return f"{tiny_dataset}:{subject}/test/{seq}/{idx}", path


def test_network_reads_the_body_and_checks_it():
    torch.manual_seed(0)
    model = LatentDenoiser(latent_preset("tiny", body_points=4)).eval()
    torch.nn.init.normal_(model.out.weight, std=0.2)
    x, t, joints = torch.randn(2, 30, 3), torch.tensor([5, 500]), torch.randn(2, 24, 3)
    body = torch.randn(2, 4, 3)
    with torch.no_grad():
        a = model(x, t, PoseCondition(joints, body=body))
        b = model(x, t, PoseCondition(joints, body=body + 0.5))
    assert a.shape == x.shape and not torch.allclose(a, b)  # the output depends on the body
    assert model.config.num_tokens == 8 + 1 + 24 + 4
    for cond, match in [
        (joints, r"needs the posed body \(4 vertices\)"),
        (PoseCondition(joints, body=body[:, :3]), r"body must have shape \(2, 4, 3\)"),
        (PoseCondition(joints, body=body.masked_fill(body > 1, float("nan"))), "body contains NaN"),
    ]:
        with pytest.raises(ValueError, match=match):
            model(x, t, cond)
    with pytest.raises(ValueError, match="takes no posed body"):
        LatentDenoiser(latent_preset("tiny"))(x, t, PoseCondition(joints, body=body))
    with pytest.raises(ValueError, match="takes no posed body"):  # the transformer refuses it too
        PocoLocoDenoiser(denoiser_preset("tiny"))(x, t, PoseCondition(joints, body=body))
    with pytest.raises(ValueError, match="needs the latent denoiser"):
        train_preset("tiny", body_points=4)


def test_training_stores_farthest_point_ids_and_samples_dataset_frames(body_run, tiny_dataset, skirt_frame):
    meta = json.loads((body_run / "checkpoints" / "step_000002" / "meta.json").read_text())
    ids = meta["body_point_ids"]
    template = read_subject(DatasetLayout(tiny_dataset).subject_path("skirt")).template
    want = farthest_point_sampling_reference(torch.from_numpy(np.asarray(template, np.float32))[None], K)[0]
    assert ids == want.tolist() and len(set(ids)) == K
    method = load_method(body_run)
    assert method.needs_body and method.config.denoiser.body_points == K
    spec, path = skirt_frame
    pose = method.load_pose(spec, method.outfit_id("skirt"))
    body = method.body_points_of(pose)
    np.testing.assert_allclose(body, read_frame(path, ["body_vertices"]).body_vertices[ids])
    clouds = method.predict(pose, 50, (0, 1), None, SamplerOptions(sampler="ddim", steps=2))
    assert clouds.points.shape == (2, 50, 3) and np.isfinite(clouds.points).all()
    # the body matters: the same noise with the body moved gives other points
    moved = type(pose)(pose.joints, pose.body_vertices + np.float32(0.3), pose.vtransf, None, pose.subject, pose.source)
    other = method.predict(moved, 50, (0, 1), None, SamplerOptions(sampler="ddim", steps=2))
    assert not np.allclose(other.points, clouds.points)


def test_cli_sample_eval_and_clear_errors(body_run, tiny_dataset, skirt_frame, tmp_path, capsys):
    spec, path = skirt_frame
    assert main(["sample", "--ckpt", str(body_run), "--joints", spec, "--points", "40", "--num", "1", "--steps", "2",
                 "--sampler", "ddim", "--no-render", "--out", str(tmp_path / "s")]) == 0, capsys.readouterr().err  # fmt: skip
    assert (tmp_path / "s").is_dir()
    assert main(["eval", "--ckpt", str(body_run), "--data", str(tiny_dataset), "--frames", "2", "--points", "40",
                 "--seeds", "0", "--sampler", "ddim", "--steps", "2", "--no-baselines",
                 "--out", str(tmp_path / "e")]) == 0, capsys.readouterr().err  # fmt: skip
    capsys.readouterr()
    np.save(tmp_path / "joints.npy", read_frame(path).joints)  # bare joints: no body to condition on
    err = _one_line_error(capsys, main(["sample", "--ckpt", str(body_run), "--joints", str(tmp_path / "joints.npy"),
                                        "--outfit", "skirt", "--out", str(tmp_path / "x")]))  # fmt: skip
    assert "need the posed body, not only joints" in err
    assert main(["sample", "--ckpt", str(body_run), "--joints", "demo:skirt", "--outfit", "skirt", "--points", "40",
                 "--num", "1", "--steps", "2", "--no-render", "--out", str(tmp_path / "d")]) == 0  # demo poses carry the body
    fr = read_frame(path)
    write_ply(tmp_path / "partial.ply", fr.points[:3000], fr.normals[:3000])
    err = _one_line_error(capsys, main(["complete", "--ckpt", str(body_run), "--partial", str(tmp_path / "partial.ply"),
                                        "--joints", spec, "--outfit", "skirt", "--out", str(tmp_path / "c")]))  # fmt: skip
    assert "needs the posed body (--body-points)" in err


def test_fit_passes_the_body(body_run, tiny_dataset, skirt_frame, tmp_path, capsys):
    spec, path = skirt_frame
    fr = read_frame(path)
    scan = tmp_path / "scan.ply"
    write_ply(scan, fr.points[:2000], fr.normals[:2000])
    assert main(["fit", "--ckpt", str(body_run), "--scan", str(scan), "--frame", spec, "--steps", "2", "--name",
                 "new_skirt", "--out", str(tmp_path / "fitted")]) == 0, capsys.readouterr().err  # fmt: skip
    fitted = load_method(tmp_path / "fitted")
    assert fitted.outfit_names()[-1] == "new_skirt" and fitted.needs_body
