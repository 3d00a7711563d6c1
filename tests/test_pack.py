"""Training packs (`pocoloco data pack`), training from one, and the GPU-path pieces of the trainer
that run on the CPU too: the time budget, the exported model, the learning-rate rule, sync-free logs."""

import json
import math
import zipfile

import numpy as np
import pytest
import torch

from pocoloco.cli import main as cli_main
from pocoloco.data.dataset import PointCloudDataset, frame_velocity
from pocoloco.data.pack import (
    PackedBodies,
    PackedDataset,
    decode_normals,
    decode_points,
    encode_normals,
    encode_points,
    open_point_clouds,
    pack_summary,
    read_pack_meta,
    read_pack_subjects,
    write_pack,
)
from pocoloco.diffusion import NoiseSchedule, diffusion_loss
from pocoloco.engine import checkpoint as ckpt_io
from pocoloco.engine.trainer import fused_optimizer_options, scaled_lr

pytestmark = pytest.mark.usefixtures("torch_single_thread")


@pytest.fixture(scope="module")
def tiny_pack(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("pack") / "tiny.pack"
    meta = write_pack(tiny_dataset, out, splits=("train", "test"), every=1, eval_every=2, points=512, velocity=True)
    return out, meta


# ------------------------------------------------------------------------------ encoding
def test_points_codec_matches_plain_quantisation():
    """The Morton-sorted delta code gives back exactly the rounded points (as a set per frame)."""
    rng = np.random.default_rng(0)
    rel = rng.normal(0, 0.4, (3, 700, 3)).astype(np.float32)
    res = 1e-3
    back = decode_points(encode_points(rel, res), 3, 700, res)
    for f in range(3):
        want = np.round(rel[f].astype(np.float64) / res).astype(np.int64)  # the slow reference
        got = np.round(back[f].astype(np.float64) / res).astype(np.int64)
        assert np.array_equal(want[np.lexsort(want.T)], got[np.lexsort(got.T)])
    with pytest.raises(ValueError, match="beyond what"):
        encode_points(np.full((1, 2, 3), 40.0, np.float32), 1e-3)


# ------------------------------------------------------------------------------ the pack
def test_pack_holds_the_dataset_frames(tiny_dataset, tiny_pack):
    path, meta = tiny_pack
    assert meta["splits"] == {"train": 8, "test": 4} and meta["bytes"] == path.stat().st_size
    full = PointCloudDataset(tiny_dataset, "train", num_points=None)
    packed = PackedDataset(path, "train", velocity=True)
    assert len(packed) == len(full) and packed.subject_names == full.subject_names
    assert packed.normalisation == full.normalisation
    for i in (0, len(full) - 1):
        a, b = full[i], packed[i]
        assert a["frame_key"] == b["frame_key"] and a["subject"] == b["subject"]
        assert torch.allclose(a["root"], b["root"])
        std = full.normalisation.std
        assert (a["joints"] - b["joints"]).abs().max() * std <= 0.5e-4 + 1e-6  # 0.05 mm
        # every packed point is one of the frame's points, quantised to 1 mm
        d = torch.cdist(b["points"], a["points"]).min(dim=1).values * std
        assert b["points"].shape == (512, 3) and float(d.max()) <= 0.5e-3 * math.sqrt(3) + 1e-6
        path_i = full.frames[i][2]
        from pocoloco.data.format import read_frame

        v = frame_velocity(path_i, read_frame(path_i, ["joints"]).joints)
        assert np.allclose(b["velocity"].numpy() * std, v, atol=2e-3 * np.abs(v).max() + 1e-4)
    assert len(PackedDataset(path, "test")) == 4  # every 2nd of the 8 test frames
    sub = open_point_clouds(path, "train", num_points=None, subjects=["skirt"])
    assert {sub[i]["subject"] for i in range(len(sub))} == {full.subject_names.index("skirt")}


def test_pack_flags_subset_frames_and_points(tiny_dataset, tmp_path):
    meta = write_pack(tiny_dataset, tmp_path / "p.pack", every=2, points=100, subjects=["tight"])
    assert meta["splits"] == {"train": 2} and meta["points_per_frame"] == 100 and list(meta["subjects"]) == ["tight"]
    ds = PackedDataset(tmp_path / "p.pack")
    assert ds.subject_names == ["tight"] and ds[0]["subject"] == 0


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage"])
def test_damaged_pack_is_one_line(tiny_pack, tmp_path, damage):
    src, _ = tiny_pack
    raw = bytearray(src.read_bytes())
    bad = tmp_path / "bad.pack"
    if damage == "truncate":
        raw = raw[: len(raw) // 2]
    elif damage == "flip":  # a byte inside the train points (stored, not compressed, by the zip)
        with zipfile.ZipFile(src) as z:
            info = z.getinfo("train_points.npy")
        raw[info.header_offset + 200] ^= 0xFF
    else:
        raw = bytearray(b"not a pack at all")
    bad.write_bytes(bytes(raw))
    with pytest.raises(ValueError) as e:
        PackedDataset(bad)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)


def test_pack_refusals(tiny_dataset, tiny_pack, tmp_path):
    path, _ = tiny_pack
    with pytest.raises(ValueError, match="no 'heldout' frames"):
        PackedDataset(path, "heldout")
    with pytest.raises(ValueError, match="no normals"):
        PackedDataset(path, with_normals=True)
    with pytest.raises(ValueError, match="fewer than --points"):
        write_pack(tiny_dataset, tmp_path / "x.pack", points=10**6)
    with pytest.raises(ValueError, match="needs the train split"):
        write_pack(tiny_dataset, tmp_path / "x.pack", splits=("test",))
    assert not (tmp_path / "x.pack").exists()
    plain = write_pack(tiny_dataset, tmp_path / "plain.pack", points=64)
    with pytest.raises(ValueError, match="no joint velocities"):
        PackedDataset(tmp_path / "plain.pack", velocity=True)
    assert read_pack_meta(tmp_path / "plain.pack")["velocity"] is False and plain["velocity"] is False


def test_cli_pack_and_train_from_it(tiny_dataset, tmp_path, capsys):
    pack = tmp_path / "t.pack"
    assert cli_main(["data", "pack", str(tiny_dataset), "--out", str(pack), "--every", "1", "--points", "300"]) == 0
    assert "8 train frames x 300 points" in capsys.readouterr().out
    assert cli_main(["data", "pack", str(tiny_dataset), "--out", str(pack)]) == 2
    assert "already exists" in capsys.readouterr().err
    run = tmp_path / "run"
    base = ["train", "--data", str(pack), "--out", str(run), "--preset", "latent_tiny", "--no-progress", "--device", "cpu",
            "--threads", "1", "--sample-every", "0"]  # fmt: skip
    assert cli_main([*base, "--steps", "2", "--outfit-codes", "--body-shape"]) == 0
    ck = ckpt_io.load_checkpoint(run)
    assert ck.step == 2 and ck.normalisation == PointCloudDataset(tiny_dataset, "train").normalisation
    assert [o["name"] for o in ck.meta["outfits"]] == ["skirt", "tight"]
    assert (run / "model" / "meta.json").is_file()  # every run ends with its exported model
    assert json.loads((run / "model" / "meta.json").read_text())["step"] == 2
    assert cli_main(["train", "--model", "pop", "--data", str(pack), "--out", str(tmp_path / "pop"), "--no-progress"]) == 2
    assert "pocoloco data pack --bodies" in capsys.readouterr().err
    assert cli_main([*base[:4], str(tmp_path / "b"), *base[5:], "--body-points", "8"]) == 2
    assert "no posed bodies" in capsys.readouterr().err


# ------------------------------------------------------------------------------ packs with bodies (POP, CloSET)
def test_normals_codec_is_within_two_degrees():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(5000, 3))
    n = np.concatenate([n, np.eye(3), -np.eye(3), [[1, -1, 0], [0, 1, -1], [-1, 0, -1]]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    back = decode_normals(encode_normals(n))
    angle = np.degrees(np.arccos(np.clip((n * back).sum(1), -1, 1)))
    assert encode_normals(n).dtype == np.int8 and angle.max() < 2.0
    assert np.allclose(np.linalg.norm(back, axis=1), 1, atol=1e-6)


@pytest.fixture(scope="module")
def bodies_pack(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("bpack") / "bodies.pack"
    meta = write_pack(tiny_dataset, out, splits=("train", "test"), every=2, eval_every=4, points=600, bodies=True)
    return out, meta


def test_bodies_pack_gives_the_dataset_frames_and_bodies(tiny_dataset, bodies_pack):
    """Each packed frame's body, vtransf, joints, points and normals against the dataset frame's
    (the slow reference: the stored arrays), and the mean shape against anny's (MeanShapeCache)."""
    from scipy.spatial import cKDTree

    from pocoloco.data.format import DatasetLayout, read_frame, read_subject
    from pocoloco.data.poses import MeanShapeCache, motion_path_of

    path, meta = bodies_pack
    assert meta["bodies"]["rigs"] == ["skirt", "tight", "mean"] and "posed bodies" in pack_summary(meta)
    ds = PackedBodies(path, "train")
    layout, cache = DatasetLayout(tiny_dataset), MeanShapeCache()
    assert len(ds) == 4
    for i in range(len(ds)):
        subject, split, seq, idx = ds.frame_key(i).split("/")
        src = layout.frame_path(subject, split, seq, int(idx))
        want = read_frame(src, ["points", "normals", "joints", "frame_index", "body_vertices", "vtransf"])
        got = ds.frame(i)
        assert got.frame_index == want.frame_index
        assert np.abs(got.body_vertices - want.body_vertices).max() < 5e-4
        assert np.abs(got.vtransf - want.vtransf).max() < 1e-3
        assert np.abs(got.joints - want.joints).max() < 1e-4
        d, j = cKDTree(want.points).query(got.points)
        assert d.max() <= 0.5e-3 * math.sqrt(3) + 1e-6
        cos = (got.normals * want.normals[j]).sum(1)
        assert np.mean(cos > np.cos(np.radians(2))) > 0.99  # the rest: another point at the same place
        mean = cache.get(motion_path_of(src), int(want.frame_index))
        assert np.abs(ds.mean_shape(i) - mean).max() < 5e-4
    for name, asset in read_pack_subjects(path).items():
        stored = read_subject(layout.subject_path(name))
        assert np.array_equal(asset.faces, stored.faces) and np.array_equal(asset.uv_faces, stored.uv_faces)
        assert np.allclose(asset.uv, stored.uv) and np.array_equal(asset.vertex_joint, stored.vertex_joint)
        assert np.abs(asset.template - stored.template).max() < 1e-4
    # a pack still serves PocoLoco as before
    assert len(PackedDataset(path, "train")) == 4 and PackedDataset(path, "train")[0]["points"].shape == (600, 3)


@pytest.mark.parametrize("model", ["pop", "closet"])
def test_pop_and_closet_train_from_a_bodies_pack(bodies_pack, tmp_path, capsys, model):
    path, _ = bodies_pack
    run = tmp_path / model
    argv = ["train", "--model", model, "--preset", "tiny", "--data", str(path), "--out", str(run), "--steps", "2",
            "--num-points", "300", "--sample-every", "2", "--no-progress", "--threads", "1"]  # fmt: skip
    assert cli_main(argv) == 0
    from safetensors import safe_open

    with safe_open(str(run / "model" / "model.safetensors"), "pt") as f:  # the run's own export
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    floats = {k: t.dtype for k, t in tensors.items() if t.is_floating_point()}
    geometry = {"pop": "surface_uv", "closet": "template"}[model]
    assert any(geometry in k and d == torch.float32 for k, d in floats.items()), floats  # buffers stay float32
    assert torch.float16 in floats.values()  # the weights are halved
    ck = ckpt_io.load_checkpoint(run, expect_model=model)
    assert ck.step == 2 and [o["name"] for o in ck.meta["outfits"]] == ["skirt", "tight"]
    assert (run / "samples" / "step_000002.png").is_file()
    assert cli_main([*argv[:3], *argv[5:9], "--steps", "3", "--resume", "--no-progress", "--threads", "1"]) == 0
    assert ckpt_io.load_checkpoint(run, expect_model=model).step == 3


def test_a_pack_with_too_few_points_for_the_recipe_is_one_line(bodies_pack, tmp_path, capsys):
    path, _ = bodies_pack
    argv = ["train", "--model", "pop", "--preset", "tiny", "--data", str(path), "--out", str(tmp_path / "r"),
            "--num-points", "601", "--no-progress"]  # fmt: skip
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert "holds 600 scan points per frame" in err and "--num-points 600" in err and len(err.strip().splitlines()) == 1


def test_pop_batches_from_a_pack_use_the_posed_mean_shape(bodies_pack):
    from pocoloco.methods.pop.method import POPTask
    from pocoloco.methods.skinned import SkinnedBatches, skinned_preset

    path, _ = bodies_pack
    task = POPTask(skinned_preset("pop", "small", steps=2, batch_size=2, num_points=100), path)
    assert task.needs_mean_shape
    task.model = task.build_model()
    batches = SkinnedBatches(task)
    item = batches.frames(0)[0]
    assert item.mean_shape is not None and item.mean_shape.shape == item.frame.body_vertices.shape
    batch = batches[0]
    assert batch.pose_vertices.shape == batch.body_vertices.shape and batch.scan_normals.shape == (2, 100, 3)
    assert not torch.allclose(batch.pose_vertices, batch.body_vertices)  # the mean shape, not the subject's body


# ------------------------------------------------------------------------------ the GPU-path pieces
def test_time_budget_stops_with_a_checkpoint_and_an_export(tiny_pack, tmp_path, capsys):
    path, _ = tiny_pack
    run = tmp_path / "run"
    argv = ["train", "--data", str(path), "--out", str(run), "--preset", "latent_tiny", "--steps", "1000", "--no-progress",
            "--device", "cpu", "--threads", "1", "--sample-every", "0", "--ckpt-every", "0", "--lr-schedule", "wsd",
            "--decay-steps", "1000", "--time-budget", "0.0001"]  # fmt: skip
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert "time budget reached" in out
    ck = ckpt_io.load_checkpoint(run)
    assert ck.step == 1  # the first step already passes a 6 ms budget
    assert json.loads((run / "model" / "meta.json").read_text())["step"] == 1
    spent = ck.meta["train_seconds"]
    assert spent > 0.0
    capsys.readouterr()
    # the budget is the whole run's: a resume with the same one has nothing left (one line, nothing written)
    assert cli_main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("pocoloco: error: ") and "larger --time-budget" in err[-1] and "Traceback" not in "".join(err), err
    assert ckpt_io.load_checkpoint(run).step == 1
    # a budget 0.1 ms longer: one more step, the clock going on from the checkpoint's
    assert cli_main([*argv[:-1], f"{(spent + 1e-4) / 60}", "--resume"]) == 0
    assert json.loads((run / "model" / "meta.json").read_text())["step"] == 2
    assert ckpt_io.load_checkpoint(run).meta["train_seconds"] > spent
    first, resumed = (json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines())
    assert first["step"] == 1 and first["lr"] == pytest.approx(5e-4)  # warm-up step 1 of 2; the clock not begun
    assert resumed["step"] == 2 and resumed["lr"] < 0.05e-3  # the clock's decay nearly done (a fresh clock: 1e-3)
    assert cli_main([*argv[:-1], "-1", "--resume"]) == 2


def test_lr_rule_and_fused_options(tiny_dataset, tmp_path):
    assert scaled_lr(5e-4, 256, 16) == pytest.approx(2e-3)
    assert scaled_lr(5e-4, 64, 16, "linear") == pytest.approx(2e-3) and scaled_lr(5e-4, 64, 16, "none") == 5e-4
    with pytest.raises(ValueError, match="lr scaling rule"):
        scaled_lr(1.0, 2, 1, "cubic")
    assert fused_optimizer_options(torch.nn.Linear(2, 2)) == {}
    from pocoloco.cli.train import _config_from_args
    from tests.test_train import _parse

    args = _parse("--data", str(tiny_dataset), "--out", str(tmp_path), "--preset", "latent_small", "--batch-size", "64")
    assert _config_from_args(args).lr == pytest.approx(1e-3)
    args = _parse("--data", "x", "--out", "y", "--preset", "latent_small", "--batch-size", "64", "--lr-scaling", "none")
    assert _config_from_args(args).lr == pytest.approx(5e-4)
    args = _parse("--data", "x", "--out", "y", "--preset", "latent_small", "--batch-size", "64", "--lr", "1e-4")
    assert _config_from_args(args).lr == pytest.approx(1e-4)


def test_sync_free_loss_logs_equal_the_float_logs():
    torch.manual_seed(0)
    lin = torch.nn.Linear(3, 3)
    x0 = torch.randn(6, 20, 3)
    sched = NoiseSchedule.from_kind("four", 1000)
    t = torch.tensor([0, 10, 300, 600, 700, 999])
    noise = torch.randn_like(x0)
    la, a = diffusion_loss(lambda x, t_, c: lin(x), x0, None, sched, t=t, noise=noise)
    lb, b = diffusion_loss(lambda x, t_, c: lin(x), x0, None, sched, t=t, noise=noise, as_tensors=True)
    assert torch.equal(la, lb) and all(torch.is_tensor(v) for v in b.values())
    assert {k for k, v in b.items() if not math.isnan(float(v))} == set(a)
    for k in a:
        assert float(b[k]) == pytest.approx(a[k], rel=1e-6)
    t2 = torch.tensor([0, 1, 2, 3, 4, 5])  # every sample in the first quarter: the others are NaN
    _, c = diffusion_loss(lambda x, t_, c_: lin(x), x0, None, sched, t=t2, noise=noise, as_tensors=True)
    assert math.isnan(float(c["mse_q3"])) and not math.isnan(float(c["mse_q0"]))


def test_a_second_train_into_a_locked_run_folder_is_refused(tiny_pack, tmp_path, capsys):
    """Two trains into one folder: the second gets one line and writes nothing (the first holds the lock)."""
    from pocoloco.utils.atomic import exclusive_lock

    path, _ = tiny_pack
    run = tmp_path / "run"
    argv = ["train", "--data", str(path), "--out", str(run), "--preset", "latent_tiny", "--steps", "2", "--no-progress",
            "--device", "cpu", "--threads", "1", "--sample-every", "0"]  # fmt: skip
    with exclusive_lock(run, "pocoloco train"):  # what a running train holds (flock: per open file)
        assert cli_main(argv) == 2
        assert "in use by pocoloco train (pid" in capsys.readouterr().err
        assert [p.name for p in run.iterdir()] == [".lock"]
    assert not run.exists()  # nothing was written, so nothing is left
    assert cli_main(argv) == 0 and ckpt_io.load_checkpoint(run).step == 2
    (tmp_path / "file").write_text("x")
    assert cli_main([*argv[:4], str(tmp_path / "file"), *argv[5:]]) == 2
    assert "is not a folder" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["model.safetensors", "ema.safetensors", "training_state.pt", "meta.json"])
def test_a_flipped_byte_anywhere_in_a_checkpoint_is_detected(tiny_pack, tmp_path, name):
    """Every file of a checkpoint is checked against the SHA-256 its meta.json records (and meta.json
    against its own): the damaged newest checkpoint is skipped for the older intact one."""
    path, _ = tiny_pack
    run = tmp_path / "run"
    assert cli_main(["train", "--data", str(path), "--out", str(run), "--preset", "latent_tiny", "--steps", "2",
                     "--ckpt-every", "1", "--no-progress", "--device", "cpu", "--threads", "1", "--sample-every", "0"]) == 0  # fmt: skip
    f = run / "checkpoints" / "step_000002" / name
    raw = bytearray(f.read_bytes())
    if name == "meta.json":  # a digit of the normalisation: still valid JSON, a silently different value
        i = raw.index(b'"std": ') + len(b'"std": 0.') + 2
        raw[i] = ord("7") if raw[i] != ord("7") else ord("3")
    else:
        raw[len(raw) // 2] ^= 0x10
    f.write_bytes(bytes(raw))
    with pytest.raises(ckpt_io.CorruptCheckpointError, match="checksum mismatch"):
        ckpt_io.load_checkpoint(f.parent)
    with pytest.warns(ckpt_io.CheckpointFallbackWarning, match="step_000002"):
        assert ckpt_io.load_checkpoint(run).step == 1
    model = run / "model" / "model.safetensors"  # the exported model is sealed the same way
    raw = bytearray(model.read_bytes())
    raw[len(raw) // 2] ^= 0x01
    model.write_bytes(bytes(raw))
    with pytest.raises(ckpt_io.CorruptCheckpointError, match="checksum mismatch"):
        ckpt_io.load_checkpoint(run / "model", training_state=False)


@pytest.mark.parametrize("argv, message", [
    (["sample", "--joints", "demo:skirt", "--seed", "-1", "--out", "OUT"], "--seed must be in [0, 2**62], got -1"),
    (["sample", "--joints", "demo:skirt", "--seed", str(2**64), "--out", "OUT"], "--seed must be in [0, 2**62]"),
    (["data", "synth", "--preset", "tiny", "--shard", "", "--out", "OUT"], "--shard must be K/N"),
])  # fmt: skip
def test_seed_and_shard_values_are_one_line_errors(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert cli_main([str(out) if a == "OUT" else a for a in argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_nan_weights_are_named_when_loaded(tiny_pack, tmp_path, capsys):
    """A diverged run's NaN weights: one line naming the file and the tensor (not a later
    'x contains NaN' from the sampler), and ``sample`` refuses the checkpoint."""
    from safetensors.torch import load_file, save_file

    from pocoloco.engine.checkpoint import _write_meta

    path, _ = tiny_pack
    run = tmp_path / "run"
    assert cli_main(["train", "--data", str(path), "--out", str(run), "--preset", "latent_tiny", "--steps", "1",
                     "--no-progress", "--device", "cpu", "--threads", "1", "--sample-every", "0"]) == 0  # fmt: skip
    capsys.readouterr()
    ck = run / "checkpoints" / "step_000001"
    for name in ("model.safetensors", "ema.safetensors"):
        state = load_file(str(ck / name))
        key = sorted(state)[0]
        state[key].view(-1)[0] = float("nan")
        save_file(state, str(ck / name))
    _write_meta(ck, json.loads((ck / "meta.json").read_text()),
                ["model.safetensors", "ema.safetensors", "training_state.pt"])  # sealed as a diverged run writes them
    with pytest.raises(ckpt_io.CorruptCheckpointError, match=rf"{key!r} holds 1 non-finite value: NaN or infinite"):
        ckpt_io.load_checkpoint(ck)
    assert cli_main(["sample", "--ckpt", str(ck), "--joints", "demo:skirt", "--num", "1", "--steps", "2", "--points", "16",
                     "--no-render", "--out", str(tmp_path / "s")]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert "NaN or infinite" in err and len(err.splitlines()) == 1
