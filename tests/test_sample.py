"""Sampling a trained checkpoint: shapes, frame, per-sample seeds, joints input, CLI and bad input."""

import json
import shutil

import numpy as np
import pytest
import torch

from pocoloco.cli import main as cli_main
from pocoloco.data.format import DatasetLayout, read_frame
from pocoloco.data.poses import load_joints
from pocoloco.data.published import read_ply, write_joints_txt
from pocoloco.methods.pocoloco import load_denoiser, sample_clouds
from pocoloco.models.pocoloco import PocoLocoDenoiser

# tiny models run fastest on one thread, and bit-exact comparisons need a fixed thread count
pytestmark = pytest.mark.usefixtures("torch_single_thread")


@pytest.fixture(scope="module")
def run(tiny_run):
    """A tiny model trained for 2 steps (its run folder; conftest.tiny_run)."""
    return tiny_run


@pytest.fixture(scope="module")
def frame(tiny_dataset):
    """(key, path) of the first train frame of the tiny dataset."""
    subject, sequence, path = DatasetLayout(tiny_dataset).iter_frames("train")[0]
    return f"{subject}/train/{sequence}/{int(path.stem)}", path


def _joints(frame) -> np.ndarray:
    return read_frame(frame[1], ["joints"]).joints  # (24, 3)


# ----------------------------------------------------------------------------------- library
def test_sample_clouds_shapes_and_input_frame(run, frame):
    model, norm, cfg = load_denoiser(run)
    joints = _joints(frame)
    pts, nrm = sample_clouds(model, norm, cfg, joints, 3, 64, sampler="dpm++", steps=3, seeds=[0, 1, 2])
    assert pts.shape == (3, 64, 3) and pts.dtype == np.float32 and nrm is None and np.isfinite(pts).all()
    # root-centred conditioning: moving the pose moves the samples by exactly the same offset
    offset = np.array([5.0, -3.0, 2.0], np.float32)
    moved, _ = sample_clouds(model, norm, cfg, joints + offset, 3, 64, sampler="dpm++", steps=3, seeds=[0, 1, 2])
    np.testing.assert_allclose(moved - offset, pts, atol=1e-4)
    # an untrained model gives (amplified) i.i.d. noise around root + mean: each cloud's centre is
    # within 5 standard errors of it (the 5 m offset makes a forgotten root fail this)
    centre = joints[norm.root_joint] + offset + np.asarray(norm.mean)  # (3,)
    z = (moved.mean(axis=1) - centre) / (moved.std(axis=1) / np.sqrt(64))  # (K, 3)
    assert np.abs(z).max() < 5, z


def test_per_sample_seeds_do_not_depend_on_batch(run, frame):
    model, norm, cfg = load_denoiser(run)
    joints = _joints(frame)
    for sampler in ("dpm++", "ddpm"):
        kw = dict(sampler=sampler, steps=3)
        all3 = sample_clouds(model, norm, cfg, joints, 3, 64, seeds=[7, 8, 9], batch_size=3, **kw).points
        one_by_one = sample_clouds(model, norm, cfg, joints, 3, 64, seeds=[7, 8, 9], batch_size=1, **kw).points
        alone = sample_clouds(model, norm, cfg, joints, 1, 64, seeds=[8], **kw).points
        np.testing.assert_allclose(all3, one_by_one, atol=1e-5)
        np.testing.assert_allclose(all3[1], alone[0], atol=1e-5)
        assert np.abs(all3[0] - all3[1]).max() > 1e-2  # different seeds, different clouds


def test_other_samplers_any_resolution_and_normals(run, frame):
    model, norm, cfg = load_denoiser(run)
    joints = _joints(frame)
    pts, _ = sample_clouds(model, norm, cfg, joints, 2, 37, sampler="ddim", steps=2)
    assert pts.shape == (2, 37, 3) and np.isfinite(pts).all()
    cfg6 = cfg.replace(denoiser=cfg.denoiser.replace(point_channels=6))
    torch.manual_seed(0)
    pts, nrm = sample_clouds(PocoLocoDenoiser(cfg6.denoiser), norm, cfg6, joints, 2, 16, steps=2)
    assert pts.shape == nrm.shape == (2, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=-1), 1.0, atol=1e-5)


@pytest.mark.parametrize(
    "kwargs, message",
    [(dict(sampler="euler"), "unknown sampler 'euler'"), (dict(num_points=0), "num_points must be >= 1"),
     (dict(steps=5000), "steps must be in [1, 1000]"), (dict(seeds=[1]), "seeds must have num=2")],
)  # fmt: skip
def test_sample_clouds_validation(run, frame, kwargs, message):
    model, norm, cfg = load_denoiser(run)
    args = {"num": 2, "num_points": 8, **kwargs}
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        sample_clouds(model, norm, cfg, _joints(frame), **args)


# ------------------------------------------------------------------------------------ joints
def test_load_joints_all_inputs(tiny_dataset, frame, tmp_path):
    joints = _joints(frame)
    np.save(tmp_path / "j.npy", joints)
    np.savez(tmp_path / "j.npz", joints=joints, other=np.zeros(2))
    np.savez(tmp_path / "single.npz", joints * 2)
    write_joints_txt(tmp_path / "j.txt", np.array([4, 9]), np.stack([joints, joints + 1]))
    np.testing.assert_array_equal(load_joints(tmp_path / "j.npy"), joints)
    np.testing.assert_array_equal(load_joints(tmp_path / "j.npz"), joints)
    np.testing.assert_array_equal(load_joints(tmp_path / "single.npz"), joints * 2)
    np.testing.assert_array_equal(load_joints(tmp_path / "j.txt"), joints)
    np.testing.assert_array_equal(load_joints(tmp_path / "j.txt", frame_id=9), joints + 1)
    np.testing.assert_array_equal(load_joints(frame[1]), joints)  # a dataset frame file
    np.testing.assert_array_equal(load_joints(f"{tiny_dataset}:{frame[0]}"), joints)


def test_load_joints_errors_name_the_file(tiny_dataset, frame, tmp_path):
    joints = _joints(frame)
    bad = joints.copy()
    bad[3, 1] = np.nan
    np.save(tmp_path / "short.npy", joints[:20])
    np.save(tmp_path / "nan.npy", bad)
    (tmp_path / "short.txt").write_text("0 " + " ".join(["0.1"] * 60) + "\n")
    write_joints_txt(tmp_path / "j.txt", np.array([4]), joints[None])
    cases = [
        (tmp_path / "short.npy", None, "short.npy: expected joints of shape (24, 3), got (20, 3)"),
        (tmp_path / "nan.npy", None, "nan.npy: joints contain NaN"),
        (tmp_path / "short.txt", None, "short.txt: line 1: expected 1 + 3*24 = 73 values, got 61"),
        (tmp_path / "j.txt", 5, "j.txt: no line with frame id 5"),
        (tmp_path / "missing.npy", None, "missing.npy: no such joints file"),
        (f"{tmp_path}:s/train/q/0", None, "not a pocoloco dataset"),
        (f"{tiny_dataset}:{frame[0]}9", None, "no such frame"),
    ]
    for spec, fid, message in cases:
        with pytest.raises(ValueError) as err:
            load_joints(spec, frame_id=fid)
        assert message in str(err.value) and len(str(err.value).splitlines()) == 1, str(err.value)


# --------------------------------------------------------------------------------------- CLI
def test_cli_writes_plys_png_and_json(run, frame, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["--ckpt", str(run), "--joints", str(frame[1]), "--num", "3", "--sampler", "dpm++", "--steps", "3",
            "--points", "64", "--seed", "5", "--out", str(out), "--device", "cpu", "--no-bf16"]  # fmt: skip
    assert cli_main(["sample", *argv]) == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["hypotheses.png", "sample.json"] + [
        f"sample_{k:03d}.ply" for k in range(3)
    ]
    meta = json.loads((out / "sample.json").read_text())
    assert meta["seeds"] == [5, 6, 7] and meta["steps"] == 3 and meta["points"] == 64 and meta["step"] == 2
    assert meta["seconds_per_sample"] > 0
    model, norm, cfg = load_denoiser(run)
    ref = sample_clouds(model, norm, cfg, _joints(frame), 3, 64, sampler="dpm++", steps=3, seeds=[5, 6, 7], clip=5.0).points
    np.testing.assert_allclose(read_ply(out / "sample_002.ply").points, ref[2], atol=1e-5)
    # rerun into the same folder with fewer samples: stale clouds are removed
    assert cli_main(["sample", *argv[:5], "2", *argv[6:], "--no-render"]) == 0
    assert sorted(p.name for p in out.glob("sample_*.ply")) == ["sample_000.ply", "sample_001.ply"]


def _other_model_ckpt(run, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(run / "checkpoints" / "step_000002", other)
    meta = json.loads((other / "meta.json").read_text())
    meta.pop("meta_sha256")  # a checkpoint of another model kind (its own seal: none, as older checkpoints)
    (other / "meta.json").write_text(json.dumps({**meta, "model_kind": "mystery"}))
    return other


@pytest.mark.parametrize(
    "change, message",
    [
        ({"--points": "0"}, "--points must be >= 1"),
        ({"--sampler": "euler"}, "unknown sampler 'euler'"),
        ({"--steps": "5000"}, "steps must be in [1, 1000]"),
        ({"--ckpt": "OTHER"}, "checkpoint is of model 'mystery', expected 'pocoloco'"),
        ({"--ckpt": "EMPTY"}, "no checkpoint found"),
        ({"--joints": "NOTDATA:s/train/q/0"}, "not a pocoloco dataset"),
        ({"--joints": "SHORT"}, "expected joints of shape (24, 3), got (23, 3)"),
    ],
)
def test_cli_bad_input_one_line_and_nothing_written(run, frame, tmp_path, capsys, change, message):
    np.save(tmp_path / "short.npy", _joints(frame)[:23])
    (tmp_path / "empty").mkdir()
    subst = {"OTHER": str(_other_model_ckpt(run, tmp_path)), "EMPTY": str(tmp_path / "empty"),
             "NOTDATA": str(tmp_path), "SHORT": str(tmp_path / "short.npy")}  # fmt: skip
    opts = {"--ckpt": str(run), "--joints": str(frame[1]), "--num": "2", "--steps": "2", "--points": "16",
            "--out": str(tmp_path / "out"), "--device": "cpu"}  # fmt: skip
    for k, v in change.items():
        opts[k] = v.replace(v.split(":")[0], subst[v.split(":")[0]]) if v.split(":")[0] in subst else v
    code = cli_main(["sample", *[x for kv in opts.items() for x in kv]])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_pocoloco_cli_has_sample_and_reports_a_missing_checkpoint(tmp_path):
    from conftest import run_cli

    joints = tmp_path / "j.npy"
    np.save(joints, np.zeros((24, 3), np.float32))
    r = run_cli("sample", "--ckpt", str(tmp_path / "no_run"), "--joints", str(joints), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------ shipped model + poses
def test_demo_poses_load_and_unknown_names_fail():
    """One demo pose per outfit of ``medium``; ``demo:KIND`` is the first outfit of that kind; each
    carries anny pose parameters that re-pose the outfit's body onto the stored joints."""
    from pocoloco.data.poses import demo_pose_names, demo_pose_outfit, demo_pose_path, load_body_pose

    names = demo_pose_names()
    assert len(names) == 14 and {"skirt_a", "dress_b", "tight_a", "trousers_b"} <= set(names)
    for name in names:
        j = load_joints(f"demo:{name}")
        assert j.shape == (24, 3) and np.isfinite(j).all()
        assert 0.5 < j[:, 2].max() - j[:, 2].min() < 2.5  # a standing human's height span, metres
        assert demo_pose_outfit(name) == name
    assert demo_pose_path("skirt") == demo_pose_path("skirt_a") and demo_pose_outfit("skirt") == "skirt_a"
    pose = load_body_pose("demo:skirt", {}, False)  # the posed body, as POP and CloSET take it
    assert pose.has_body and pose.body_vertices.shape[1] == 3
    for bad in ("dancer", "", "skirt_a/../x"):
        with pytest.raises(ValueError, match="no such demo pose; choose one of: dress, maxi, shirt, skirt"):
            load_joints(f"demo:{bad}")


def test_export_for_sampling_keeps_the_ema_weights_and_cannot_resume(run, frame, tmp_path):
    from pocoloco.engine.checkpoint import export_for_sampling, load_checkpoint

    out = export_for_sampling(run, tmp_path / "shipped")
    files = sorted(p.name for p in out.iterdir())
    assert files == ["meta.json", "model.safetensors"]
    full = load_denoiser(run)
    small = load_denoiser(out)
    for (k, a), (k2, b) in zip(full.model.state_dict().items(), small.model.state_dict().items(), strict=True):
        assert k == k2 and torch.equal(a, b), k
    meta = load_checkpoint(out, training_state=True)
    assert meta.optimizer_state is None and meta.ema_state is None and meta.meta["weights"] == "ema"
    with pytest.raises(ValueError, match="already exists"):
        export_for_sampling(run, out)


def test_float16_export_loads_as_float32_rounded_weights(run, tmp_path):
    """``dtype="float16"``: floating tensors stored as fp16 (half the bytes), loaded back as float32
    equal to the fp16-rounded originals; meta.json records the dtype."""
    from safetensors.torch import load_file

    from pocoloco.engine.checkpoint import export_for_sampling, load_checkpoint

    full = load_checkpoint(run, training_state=False).ema_state
    out32 = export_for_sampling(run, tmp_path / "f32")
    out16 = export_for_sampling(run, tmp_path / "f16", dtype="float16")
    stored = load_file(str(out16 / "model.safetensors"))
    assert {str(v.dtype) for v in stored.values()} == {"torch.float16"}
    size32, size16 = ((o / "model.safetensors").stat().st_size for o in (out32, out16))
    assert 0.45 < size16 / size32 < 0.55, (size16, size32)
    loaded = load_checkpoint(out16, training_state=False)
    assert loaded.meta["weights_dtype"] == "float16" and load_checkpoint(out32).meta["weights_dtype"] == "float32"
    assert loaded.model_state.keys() == full.keys()
    for k, v in full.items():
        assert loaded.model_state[k].dtype == torch.float32 and torch.equal(loaded.model_state[k], v.half().float()), k
    with pytest.raises(ValueError, match="choose one of float32, float16"):
        export_for_sampling(run, tmp_path / "x", dtype="bfloat16")


def test_float16_export_keeps_integer_buffers_and_refuses_overflow(run, tmp_path):
    """Bool buffers are stored as they are, int64 ones that fit as int32 (a body's faces: half the
    bytes) and loaded back as int64, one that does not fit as int64; a float beyond fp16's range is
    a one-line error, not a silent inf."""
    from safetensors.torch import load_file

    from pocoloco.engine.checkpoint import export_for_sampling, load_checkpoint, save_checkpoint

    ck = load_checkpoint(run, training_state=False)
    extra = {"idx": torch.arange(5, dtype=torch.int64), "mask": torch.tensor([True, False]),
             "bf": torch.tensor([0.1, -2.5], dtype=torch.bfloat16), "wide": torch.tensor([2**40, -3])}  # fmt: skip
    state = {**ck.model_state, **extra}
    src = save_checkpoint(tmp_path / "ck", ck.step, model_kind=ck.model_kind, preset=ck.preset, config=ck.config,
                          normalisation=ck.normalisation, model_state=state)  # fmt: skip
    stored = load_file(str(export_for_sampling(src, tmp_path / "o", dtype="float16") / "model.safetensors"))
    assert stored["idx"].dtype == torch.int32 and torch.equal(stored["idx"].long(), extra["idx"])
    assert stored["wide"].dtype == torch.int64 and torch.equal(stored["mask"], extra["mask"])
    back = load_checkpoint(tmp_path / "o", training_state=False).model_state
    assert back["idx"].dtype == torch.int64 and torch.equal(back["idx"], extra["idx"])
    assert stored["bf"].dtype == torch.float16
    loaded = load_checkpoint(src, training_state=False).model_state  # bf16 in a training checkpoint: float32 too
    assert loaded["bf"].dtype == torch.float32 and torch.equal(loaded["bf"], extra["bf"].float())
    big = tmp_path / "big"
    name = next(k for k, v in ck.model_state.items() if v.is_floating_point())
    save_checkpoint(big, ck.step, model_kind=ck.model_kind, preset=ck.preset, config=ck.config,
                    normalisation=ck.normalisation, model_state={**ck.model_state, name: ck.model_state[name] + 1e5})  # fmt: skip
    with pytest.raises(ValueError, match=f"tensor '{name}' does not fit in torch.float16") as e:
        export_for_sampling(big, tmp_path / "o2", dtype="float16")
    assert len(str(e.value).splitlines()) == 1 and not (tmp_path / "o2").exists()


def test_float16_export_samples_like_float32(run, frame, tmp_path):
    """A tiny model's denoiser outputs and 3-step samples from the fp16 export stay within a tight
    tolerance of the float32 export (fp16 keeps ~3 significant digits of each weight)."""
    from pocoloco.engine.checkpoint import export_for_sampling

    m32 = load_denoiser(export_for_sampling(run, tmp_path / "f32"))
    m16 = load_denoiser(export_for_sampling(run, tmp_path / "f16", dtype="float16"))
    assert all(p.dtype == torch.float32 for p in m16.model.state_dict().values() if p.is_floating_point())
    joints = _joints(frame)
    kw = dict(sampler="dpm++", steps=3, seeds=[0, 1])
    a = sample_clouds(*m32, joints, 2, 64, **kw).points  # (2, 64, 3) metres
    b = sample_clouds(*m16, joints, 2, 64, **kw).points
    assert b.dtype == np.float32
    err, spread = np.abs(a - b).max(), np.abs(a - a.mean(axis=1, keepdims=True)).max()
    assert 0 < err < 1e-4 * spread, (err, spread)  # measured: 3e-6 of the spread


def test_non_finite_half_weights_are_a_one_line_corrupt_checkpoint_error(run, tmp_path):
    from safetensors.torch import load_file, save_file

    from pocoloco.engine.checkpoint import CorruptCheckpointError, export_for_sampling, load_checkpoint

    out = export_for_sampling(run, tmp_path / "f16", dtype="float16")
    f = out / "model.safetensors"
    state = load_file(str(f))
    name = next(iter(state))
    state[name] = state[name].clone()
    state[name].view(-1)[0] = float("nan")
    save_file(state, str(f))
    from pocoloco.engine.checkpoint import _write_meta

    _write_meta(out, json.loads((out / "meta.json").read_text()), ["model.safetensors"])  # sealed as written
    with pytest.raises(CorruptCheckpointError) as e:
        load_checkpoint(out, training_state=False)
    msg = str(e.value)
    assert len(msg.splitlines()) == 1 and str(f) in msg and name in msg and "non-finite" in msg, msg
    with pytest.raises(ValueError, match="non-finite"):
        load_denoiser(out)


def test_default_checkpoint_samples_a_demo_pose(tmp_path, capsys):
    """The shipped model (if this copy has it) samples the README's demo pose."""
    from pocoloco.engine.shipped import DEFAULT_MODEL_DIR, resolve_ckpt_arg

    if not (DEFAULT_MODEL_DIR / "meta.json").is_file():
        r = cli_main(["sample", "--joints", "demo:skirt", "--out", str(tmp_path / "o")])
        assert r == 2 and "default model is not installed" in capsys.readouterr().err
        return
    model, norm, cfg = load_denoiser(DEFAULT_MODEL_DIR)
    assert cfg.preset == "latent_small" and cfg.architecture == "latent"
    out = tmp_path / "o"
    assert cli_main(["sample", "--joints", "demo:shirt", "--num", "2", "--points", "256", "--steps", "4", "--out", str(out)]) == 0
    assert (out / "hypotheses.png").is_file() and len(list(out.glob("sample_*.ply"))) == 2
    assert "shirt_a" in (out / "sample.json").read_text()  # demo:shirt is worn by the outfit it was captured on


def test_export_model_cli(run, tmp_path):
    from conftest import run_cli

    r = run_cli("export-model", "--ckpt", str(run), "--out", str(tmp_path / "m"))
    assert r.returncode == 0 and "EMA weights, float16" in r.stdout, r.stderr  # fp16 by default: what ships
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["meta.json", "model.safetensors"]
    assert json.loads((tmp_path / "m" / "meta.json").read_text())["weights_dtype"] == "float16"
    r = run_cli("export-model", "--ckpt", str(run), "--out", str(tmp_path / "m32"), "--dtype", "float32")
    assert r.returncode == 0 and json.loads((tmp_path / "m32" / "meta.json").read_text())["weights_dtype"] == "float32"
    r = run_cli("export-model", "--ckpt", str(run), "--out", str(tmp_path / "m"))
    assert r.returncode == 2 and "already exists" in r.stderr


def test_bf16_sampling_stays_close_to_float32():
    """``bf16=True`` (autocast around the denoiser) on the shipped model: float32 points of the
    right shape, closer to the float32 sample of the same seed than two seeds are to each other."""
    from scipy.spatial import cKDTree

    from pocoloco.engine.shipped import DEFAULT_MODEL_DIR

    from pocoloco.methods import SamplerOptions, load_method

    method = load_method(DEFAULT_MODEL_DIR)
    outfit = method.outfit_id("skirt_a")
    pose = method.load_pose("demo:skirt", outfit)
    fp32 = method.predict(pose, 512, [0, 1], outfit, SamplerOptions("dpm++", 6, clip=5.0)).points
    bf16 = method.predict(pose, 512, [0, 1], outfit, SamplerOptions("dpm++", 6, clip=5.0, bf16=True)).points
    assert bf16.shape == fp32.shape and bf16.dtype == np.float32 and np.isfinite(bf16).all()

    def chamfer(a, b):
        return cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()

    assert chamfer(bf16[0], fp32[0]) < 0.5 * chamfer(fp32[0], fp32[1])


@pytest.mark.parametrize("make, message", [
    (lambda j: j * 1e6, "from the root (a body spans ~1 m)"),
    (lambda j: np.zeros_like(j), "all joints lie within"),
    (lambda j: np.where(np.arange(24)[:, None] == 4, j + (j[4] - j[1]) * 4, j), "impossible bone length"),
    (lambda j: j[:, [0, 2, 1]], "the head is not above the pelvis"),  # y and z swapped: a body lying down
    (lambda j: j * [1, 1, -1], "runs along -z"),  # upside down
])  # fmt: skip
def test_implausible_skeletons_are_refused_unless_asked(tmp_path, capsys, make, message):
    """Joints far outside any body the model saw give one line naming the problem and the override,
    instead of a cloud hundreds of km wide; ``--any-pose`` samples them anyway."""
    bad = make(load_joints("demo:tight").astype(np.float64))
    np.save(tmp_path / "bad.npy", bad)
    argv = ["sample", "--joints", str(tmp_path / "bad.npy"), "--outfit", "tight_a", "--num", "1", "--steps", "2",
            "--points", "16", "--no-render", "--out", str(tmp_path / "out")]  # fmt: skip
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "--any-pose" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
    assert cli_main([*argv, "--any-pose"]) == 0


def test_even_pocoloco_is_the_farthest_point_subset_of_its_own_denser_samples(run, frame):
    """``predict_clouds(..., even=True)`` for PocoLoco (no spots to spread: its points themselves):
    each seed's cloud of ``even_candidates(N)`` samples (4 N up to 4,096 points, 2 N beyond) cut to
    N by farthest-point sampling, against the plain-loop reference; any prefix is the reference's
    prefix (farthest-point order)."""
    from pocoloco.data.poses import Pose
    from pocoloco.methods import SamplerOptions, load_method, predict_clouds
    from pocoloco.ops.sampling import farthest_point_sampling_reference

    method = load_method(run)
    assert method.even_candidates(4096) == 4 * 4096 and method.even_candidates(4097) == 2 * 4097
    pose = Pose(_joints(frame))
    options = SamplerOptions(sampler="ddim", steps=2, even=True)
    even = predict_clouds(method, pose, 20, (3, 4), None, options)
    dense = method.predict(pose, 80, (3, 4), None, SamplerOptions(sampler="ddim", steps=2)).points
    idx = farthest_point_sampling_reference(torch.from_numpy(dense), 20).numpy()
    assert even.points.shape == (2, 20, 3)
    np.testing.assert_array_equal(even.points, np.take_along_axis(dense, idx[:, :, None], axis=1))
