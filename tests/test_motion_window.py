"""The motion window: the last seconds of a skeleton sequence seen from its current frame."""

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pocoloco.data.motion_window import motion_window


def _walk(t: int = 60, fps: float = 25.0, speed=(0.8, 0.3), turn_rate: float = 0.7, seed: int = 0):
    """A skeleton that walks at ``speed`` (m/s on the ground) while turning at ``turn_rate`` rad/s,
    its limbs jittering: (T, 24, 3)."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(scale=0.3, size=(24, 3))
    rest[0] = 0.0
    rest[1], rest[2] = (0.1, 0.0, -0.05), (-0.1, 0.0, -0.05)  # hips along x at rest
    out = np.zeros((t, 24, 3))
    for i in range(t):
        yaw = turn_rate * i / fps
        jitter = rng.normal(scale=0.01, size=rest.shape)
        jitter[:3] = 0.0  # the pelvis and hips move rigidly; the limbs jitter
        out[i] = Rotation.from_euler("z", yaw).apply(rest + jitter)
        out[i] += (speed[0] * i / fps, speed[1] * i / fps, 0.9)
    return out


def _slow_window(joints, t, fps, seconds, hz):
    """The window by loops: for each sample, interpolate the frames, express in the current frame."""
    n = int(round(seconds * hz)) + 1

    def at(time):
        f = min(max(time * fps, 0.0), len(joints) - 1)
        lo = int(math.floor(f))
        hi = min(lo + 1, len(joints) - 1)
        return (1 - (f - lo)) * joints[lo] + (f - lo) * joints[hi]

    def heading(j):
        axis = j[1] - j[2]
        return math.atan2(axis[1], axis[0])

    now = joints[t]
    inv = Rotation.from_euler("z", -heading(now))
    out_j, out_v, out_w = [], [], []
    for k in range(n):
        time = t / fps - k / hz
        a, b = at(time), at(time - 1 / hz)
        out_j.append(inv.apply(a - now[0]))
        out_v.append(inv.apply((a[0] - b[0]) * hz))
        d = heading(a) - heading(b)
        out_w.append(((d + math.pi) % (2 * math.pi) - math.pi) * hz)
    return np.array(out_j), np.array(out_v), np.array(out_w)


@pytest.mark.parametrize("t", [0, 7, 30, 59])
def test_the_window_matches_a_loop_reference(t):
    joints = _walk()
    w = motion_window(joints, t, 25.0, seconds=2.0, hz=8.0)
    ref_j, ref_v, ref_w = _slow_window(joints, t, 25.0, 2.0, 8.0)
    assert w.joints.shape == (17, 24, 3) and w.root_velocity.shape == (17, 3) and w.yaw_rate.shape == (17,)
    np.testing.assert_allclose(w.joints, ref_j, atol=1e-5)
    np.testing.assert_allclose(w.root_velocity, ref_v, atol=1e-4)
    np.testing.assert_allclose(w.yaw_rate, ref_w, atol=1e-4)


def test_turning_or_moving_the_whole_motion_changes_nothing():
    joints = _walk()
    moved = Rotation.from_euler("z", 2.3).apply(joints.reshape(-1, 3)).reshape(joints.shape) + (4.0, -1.0, 0.0)
    a, b = motion_window(joints, 45, 25.0), motion_window(moved, 45, 25.0)
    for x, y in zip((a.joints, a.root_velocity, a.yaw_rate), (b.joints, b.root_velocity, b.yaw_rate)):
        np.testing.assert_allclose(x, y, atol=1e-4)


def test_the_root_velocity_and_turn_rate_are_the_motions():
    w = motion_window(_walk(speed=(1.0, 0.0), turn_rate=0.5), 50, 25.0)
    # samples fully inside the motion: speed 1 m/s, turning at 0.5 rad/s
    assert np.linalg.norm(w.root_velocity[:10, :2], axis=1) == pytest.approx(np.ones(10), abs=1e-3)
    assert w.yaw_rate[:10] == pytest.approx(np.full(10, 0.5), abs=1e-3)
    assert np.abs(w.joints[0, 0]).max() < 1e-6  # now: the pelvis at the origin


def test_before_the_first_frame_the_window_holds_it():
    joints = _walk()
    w = motion_window(joints, 0, 25.0)
    assert np.abs(w.root_velocity).max() < 1e-6 and np.abs(w.yaw_rate).max() < 1e-6
    np.testing.assert_allclose(w.joints, np.repeat(w.joints[:1], 17, 0), atol=1e-6)


@pytest.mark.parametrize("bad, msg", [
    (dict(joints=np.zeros((10, 24))), "shape"),
    (dict(joints=np.full((10, 24, 3), np.nan)), "NaN"),
    (dict(fps=0.0), "fps"),
    (dict(seconds=-1.0), "seconds"),
    (dict(t=10), "outside"),
])  # fmt: skip
def test_bad_input_gives_one_line(bad, msg):
    args = dict(joints=_walk(10), t=3, fps=25.0, seconds=2.0)
    args.update(bad)
    with pytest.raises(ValueError, match=msg) as e:
        motion_window(**args)
    assert "\n" not in str(e.value)


def test_a_dataset_frames_window_ends_on_its_stored_skeleton(tiny_dataset):
    """The window of a stored frame, redrawn from the sequence's seed: its current sample is the
    frame's own skeleton (in its heading frame), and the first frame's reaches into the blend from rest."""
    from pocoloco.data.format import DatasetLayout, read_frame
    from pocoloco.synth.motion_windows import sequence_windows

    layout = DatasetLayout(tiny_dataset)
    seq = sorted(p.name for p in (tiny_dataset / "subjects" / "skirt" / "test").iterdir() if p.is_dir())[0]
    windows = sequence_windows(tiny_dataset, "skirt", "test", seq)
    frame = read_frame(layout.frame_path("skirt", "test", seq, 3))
    joints = frame.joints.astype(np.float64)
    axis = joints[1] - joints[2]
    expected = Rotation.from_euler("z", -math.atan2(axis[1], axis[0])).apply(joints - joints[0])
    np.testing.assert_allclose(windows[3].joints[0], expected, atol=2e-4)
    assert len({w.joints.shape for w in windows}) == 1
    # two seconds back from the first stored frame lie in the blend from rest and before it
    assert np.abs(windows[0].joints[-1] - windows[0].joints[0]).max() > 1e-3


# ------------------------------------------------------------------ windows in the data and models
def _slow_features(window, turn, scale):
    """motion_features by loops over joints and samples."""
    S, J = window.joints.shape[:2]
    c, s = math.cos(turn), math.sin(turn)

    def rot(v):
        return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])

    rows = []
    for j in range(J):
        row = []
        for k in range(1, S):
            row += list(rot(window.joints[k, j] - window.joints[0, j]) / scale)
        for k in range(S):
            row += list(rot(window.root_velocity[k]) / scale)
        row += list(window.yaw_rate)
        rows.append(row)
    return np.array(rows)


def test_features_match_a_loop_reference_and_rest_is_zero():
    from pocoloco.data.motion_window import motion_feature_dim, motion_features

    w = motion_window(_walk(), 40, 25.0)
    fast = motion_features(w, 0.7, 0.3)
    assert fast.shape == (24, motion_feature_dim(17)) == (24, 116)
    np.testing.assert_allclose(fast, _slow_features(w, 0.7, 0.3), atol=1e-4)
    still = np.repeat(_walk(1), 30, axis=0)  # a body standing still
    assert np.abs(motion_features(motion_window(still, 29, 25.0), 0.3, 0.3)).max() < 1e-6


def test_synth_stores_each_sequences_whole_motion(tiny_dataset):
    """``data synth`` writes motion_history.npz: the same rows the seed redraws, stored frame i at
    row ``first + i``, the motion before it too; ``data motion-history`` finds them all there."""
    from pocoloco.data.format import DatasetLayout, read_frame
    from pocoloco.data.motion_window import read_motion_history
    from pocoloco.synth.motion_windows import sequence_history, write_motion_histories

    layout = DatasetLayout(tiny_dataset)
    seq = layout.sequences("skirt", "test")[0]
    stored = read_motion_history(layout.motion_history_path("skirt", "test", seq))
    redrawn = sequence_history(tiny_dataset, "skirt", "test", seq)
    np.testing.assert_allclose(stored.joints, redrawn.joints, atol=1e-6)
    assert stored.first == redrawn.first > 0
    frame = read_frame(layout.frame_path("skirt", "test", seq, 2), ["joints"])
    np.testing.assert_allclose(stored.joints[stored.first + 2], frame.joints, atol=1e-5)
    written, kept = write_motion_histories(tiny_dataset)
    assert written == 0 and kept == sum(len(layout.sequences(s, sp)) for s in layout.subjects()
                                        for sp in ("train", "test", "heldout"))  # fmt: skip


def test_dataset_windows_from_the_history_or_padded_from_the_frames(tiny_dataset, tmp_path):
    import shutil

    import torch

    from pocoloco.data.dataset import PointCloudDataset, sequence_history

    ds = PointCloudDataset(tiny_dataset, "train", num_points=None, motion_window=2.0)
    item = ds[3]
    assert item["motion"].shape == (24, ds.motion_feature_dim) == (24, 116)
    assert torch.isfinite(item["motion"]).all() and item["motion"].abs().max() > 0
    a = ds.motion_features(3, rng=np.random.default_rng([0, 4, 7]))
    b = ds.motion_features(3, rng=np.random.default_rng([0, 4, 7]))
    assert torch.equal(a, b) and not torch.equal(a, item["motion"])  # augmented, reproducibly
    # without motion_history.npz: the stored frames' skeletons, padded before the first one
    copy = tmp_path / "data"
    shutil.copytree(tiny_dataset, copy)
    for f in copy.rglob("motion_history.npz"):
        f.unlink()
    padded = PointCloudDataset(copy, "train", num_points=None, motion_window=2.0)
    subject, sequence, _ = padded.frames[3]
    history = padded.history(subject, sequence)
    assert history.padded and history.first == 0
    full = sequence_history(tiny_dataset / "subjects" / subject / "train" / sequence)
    np.testing.assert_allclose(history.joints, full.joints[full.first:], atol=1e-5)
    assert padded[3]["motion"].shape == item["motion"].shape


def test_a_motion_encoder_starts_as_the_model_without_it():
    """Zero-initialised: a --motion-window model loaded with a pose-only model's weights gives the
    same outputs, with or without motion; it answers motion once trained; bad motion: one line."""
    import torch

    from pocoloco.models.conditioning import PoseCondition
    from pocoloco.models.latent import LatentDenoiser, latent_preset

    torch.manual_seed(0)
    base = LatentDenoiser(latent_preset("tiny"))
    mover = LatentDenoiser(latent_preset("tiny", motion_window=2.0))
    missing, unexpected = mover.load_state_dict(base.state_dict(), strict=False)
    assert not unexpected and all(k.startswith("motion_in.") for k in missing)
    x, t, joints = torch.randn(2, 50, 3), torch.tensor([10, 500]), torch.randn(2, 24, 3)
    motion = torch.randn(2, 24, 116)
    with torch.no_grad():
        ref = base(x, t, joints)
        assert torch.equal(mover(x, t, PoseCondition(joints, motion=motion)), ref)
        assert torch.equal(mover(x, t, joints), ref)  # no motion: a body at rest
        torch.nn.init.normal_(mover.motion_in.out.weight, std=0.5)
        torch.nn.init.normal_(base.out.weight, std=0.5)
        mover.out.weight.copy_(base.out.weight)
        moved = mover(x, t, PoseCondition(joints, motion=motion))
        assert not torch.allclose(moved, mover(x, t, PoseCondition(joints, motion=torch.zeros_like(motion))))
    with pytest.raises(ValueError, match="motion must be") as e:
        mover(x, t, PoseCondition(joints, motion=motion[:, :, :10]))
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="no motion window"):
        base(x, t, PoseCondition(joints, motion=motion))


@pytest.mark.parametrize("make, fps, msg", [
    (lambda w: w[:, :20], 25.0, "shape"),
    (lambda w: np.where(np.arange(len(w))[:, None, None] == 3, np.nan, w), 25.0, "NaN"),
    (lambda w: w, 0.0, "--fps"),
    (lambda w: w, 5000.0, "--fps"),
    (lambda w: w + np.arange(len(w))[:, None, None] * np.array([1.0, 0.0, 0.0]), 25.0, "m/s"),  # 25 m/s
])  # fmt: skip
def test_bad_motion_files_give_one_line(tiny_dataset, tmp_path, make, fps, msg):
    from pocoloco.data.dataset import sequence_history
    from pocoloco.data.poses import load_motion

    seq = next((tiny_dataset / "subjects" / "skirt" / "test").iterdir())
    walk = sequence_history(seq).joints
    np.save(tmp_path / "m.npy", make(walk))
    with pytest.raises(ValueError, match=msg) as e:
        load_motion(tmp_path / "m.npy", fps)
    assert "\n" not in str(e.value)


def test_a_motion_file_gives_its_last_frame_and_window(tiny_dataset, tmp_path):
    from pocoloco.data.dataset import sequence_history
    from pocoloco.data.poses import load_motion

    seq = next((tiny_dataset / "subjects" / "skirt" / "test").iterdir())
    history = sequence_history(seq)
    np.save(tmp_path / "walk.npy", history.joints)
    pose, note = load_motion(tmp_path / "walk.npy", history.fps, 2.0)
    np.testing.assert_allclose(pose.joints, history.joints[-1])
    expected = motion_window(history.joints, len(history.joints) - 1, history.fps)
    np.testing.assert_allclose(pose.motion.joints, expected.joints)
    assert (note is None) == ((len(history.joints) - 1) / history.fps >= 2.0)
    same = __import__("pocoloco").Pose.from_motion(history.joints, history.fps)  # the library's call
    np.testing.assert_array_equal(same.motion.joints, pose.motion.joints)
    np.save(tmp_path / "short.npy", history.joints[-5:])
    _, note = load_motion(tmp_path / "short.npy", history.fps, 2.0)
    assert note is not None and "first frame" in note


def test_train_sample_and_eval_with_a_motion_window(tiny_dataset, tmp_path, capsys):
    """A --motion-window fine-tune from a pose-only run starts at it; DATASET: frames, --motion files
    and eval's --history modes reach the model; a pose-only model says it ignores --motion."""
    from pocoloco.cli import main as cli_main

    base, run = tmp_path / "base", tmp_path / "run"
    common = ["--data", str(tiny_dataset), "--no-progress", "--device", "cpu", "--sample-every", "0", "--threads", "1"]
    assert cli_main(["train", "--out", str(base), "--preset", "latent_tiny", "--steps", "2", *common]) in (0, None)
    assert cli_main(["train", "--out", str(run), "--init-from", str(base), "--motion-window", "2.0", "--steps", "2",
                     "--lr-schedule", "constant", *common]) in (0, None)  # fmt: skip
    from pocoloco.methods import load_method

    m = load_method(run)
    assert m.motion_window == 2.0 and m.config.denoiser.motion_window == 2.0
    seq = sorted((tiny_dataset / "subjects" / "skirt" / "test").iterdir())[0]
    pose = m.load_pose(f"{tiny_dataset}:skirt/test/{seq.name}/3")
    assert pose.motion is not None and pose.motion.joints.shape == (17, 24, 3)
    from pocoloco.data.dataset import sequence_history

    np.save(tmp_path / "walk.npy", sequence_history(seq).joints)
    capsys.readouterr()
    out = tmp_path / "s"
    assert cli_main(["sample", "--ckpt", str(run), "--motion", str(tmp_path / "walk.npy"), "--fps", "25", "--num", "1",
                     "--steps", "2", "--points", "64", "--no-render", "--out", str(out)]) in (0, None)  # fmt: skip
    assert json.loads((out / "sample.json").read_text())["motion"] == "given"
    np.save(tmp_path / "pose.npy", sequence_history(seq).joints[-1])  # bare joints: no motion
    assert cli_main(["sample", "--ckpt", str(run), "--joints", str(tmp_path / "pose.npy"), "--num", "1", "--steps", "2",
                     "--points", "64", "--no-render", "--out", str(tmp_path / "r")]) in (0, None)  # fmt: skip
    assert "taken at rest" in capsys.readouterr().out
    assert m.load_pose("demo:skirt").motion.joints.shape == (17, 24, 3)  # the demo poses carry their motion
    assert cli_main(["sample", "--ckpt", str(base), "--motion", str(tmp_path / "walk.npy"), "--num", "1", "--steps",
                     "2", "--points", "64", "--no-render", "--out", str(tmp_path / "p")]) in (0, None)  # fmt: skip
    assert "sees the pose alone" in capsys.readouterr().out
    scores = {}
    for history in ("dataset", "rest", "shuffled"):
        dst = tmp_path / f"eval_{history}"
        assert cli_main(["eval", "--ckpt", str(run), "--data", str(tiny_dataset), "--frames", "2", "--points", "64",
                         "--seeds", "0", "--steps", "2", "--no-baselines", "--history", history,
                         "--out", str(dst)]) in (0, None)  # fmt: skip
        ev = json.loads((dst / "eval.json").read_text())
        assert ev["settings"]["history"] == history
        scores[history] = [f["key"] for f in ev["frames"]]
    assert scores["dataset"] == scores["rest"] == scores["shuffled"]  # the same frames


def test_shuffled_history_comes_from_another_sequence_of_the_same_subject():
    from pocoloco.evaluation.evaluate import shuffled_frame

    frames = [("a", "s0", "a0"), ("a", "s0", "a1"), ("a", "s1", "a2"), ("a", "s1", "a3"), ("b", "s0", "b0")]
    picks = {shuffled_frame(frames, "a", "s0", f"a/test/s0/{i}") for i in range(20)}
    assert picks <= {"a2", "a3"} and len(picks) == 2
    assert shuffled_frame(frames, "a", "s0", "k") == shuffled_frame(frames, "a", "s0", "k")
    assert shuffled_frame(frames, "b", "s0", "k") == "b0"  # one sequence only: its own frames


def test_pop_with_a_motion_window_starts_as_pop_and_trains(tiny_dataset, tmp_path):
    """The ablation: POP whose pose features get the window's code. Loaded with a pose-only POP's
    weights it computes the same features; a fine-tune from it trains, samples and evaluates."""
    import dataclasses

    import torch

    from pocoloco.cli import main as cli_main
    from pocoloco.methods import load_method
    from pocoloco.models.pop import POP

    base, run = tmp_path / "pop", tmp_path / "pop_motion"
    common = ["--model", "pop", "--data", str(tiny_dataset), "--no-progress", "--sample-every", "0", "--threads", "1"]
    assert cli_main(["train", "--preset", "tiny", "--steps", "2", "--out", str(base), *common]) in (0, None)
    pop = load_method(base).model
    mover = POP(dataclasses.replace(pop.config, motion_window=2.0), pop.surface, pop.num_outfits, pop.num_vertices)
    missing, unexpected = mover.load_state_dict(pop.state_dict(), strict=False)
    mover.eval()  # batch norm: the loaded running statistics, as the loaded POP
    assert not unexpected and missing and all(k.startswith("motion_in.") for k in missing)
    posmap, geom = torch.randn(2, 3, pop.config.input_resolution, pop.config.input_resolution), pop.geom[:1].expand(2, -1, -1, -1)
    with torch.no_grad():
        assert torch.equal(mover.feature_maps(posmap, geom, torch.randn(2, 24, 116)), pop.feature_maps(posmap, geom))
    with pytest.raises(ValueError, match="no motion window"):
        pop.feature_maps(posmap, geom, torch.randn(2, 24, 116))
    assert cli_main(["train", "--init-from", str(base), "--motion-window", "2.0", "--steps", "2", "--out", str(run),
                     *common]) in (0, None)  # fmt: skip
    m = load_method(run)
    assert m.motion_window == 2.0
    seq = sorted((tiny_dataset / "subjects" / "skirt" / "test").iterdir())[0]
    pose = m.load_pose(f"{tiny_dataset}:skirt/test/{seq.name}/3")
    assert pose.motion is not None
    assert m.sample(pose, 64, 0).points.shape == (1, 64, 3)
    code = cli_main(["train", "--model", "closet", "--preset", "tiny", "--motion-window", "2", "--steps", "1", "--data",
                     str(tiny_dataset), "--out", str(tmp_path / "c"), "--no-progress"])  # fmt: skip
    assert code not in (0, None) and not (tmp_path / "c" / "checkpoints").exists()  # CloSET has no motion window


def test_every_demo_pose_ships_the_window_that_ends_on_it():
    from pocoloco.data.poses import demo_motion, demo_pose_names, load_joints

    for name in demo_pose_names():
        w = demo_motion(f"demo:{name}", 2.0)
        joints = load_joints(f"demo:{name}", None, 24).astype(np.float64)
        axis = joints[1] - joints[2]
        now = Rotation.from_euler("z", -math.atan2(axis[1], axis[0])).apply(joints - joints[0])
        np.testing.assert_allclose(w.joints[0], now, atol=2e-3)  # float16
        assert np.abs(w.joints[-1] - w.joints[0]).max() > 0.01  # the body moved into it
        assert demo_motion(f"demo:{name}", 1.5) is None  # another window length: none


def test_animation_gives_each_frame_its_own_window():
    """A motion-aware prior: the frames' windows reach the denoiser (other windows, other clouds;
    no windows = every frame at rest = all-None windows), and it is left at rest afterwards."""
    import torch

    from pocoloco.apps.animation import animate
    from pocoloco.data.dataset import Normalisation
    from pocoloco.diffusion.schedules import NoiseSchedule
    from pocoloco.methods.base import PointPrior
    from pocoloco.models.conditioning import OutfitBound
    from pocoloco.models.latent import LatentDenoiser, latent_preset

    torch.manual_seed(0)
    net = LatentDenoiser(latent_preset("tiny", motion_window=2.0)).eval()
    torch.nn.init.normal_(net.motion_in.out.weight, std=0.5)
    torch.nn.init.normal_(net.out.weight, std=0.1)
    prior = PointPrior(OutfitBound(net, None), Normalisation((0.0, 0.0, 0.0), 0.3), NoiseSchedule.from_kind("four", 1000),
                       "epsilon", 3, 24)  # fmt: skip
    walk = _walk(40)
    frames = walk[[30, 35]]
    windows = [motion_window(walk, 30, 25.0), motion_window(walk, 35, 25.0)]
    kw = dict(method="independent", steps=3, seed=0)
    moving = animate(prior, frames, 32, windows=windows, **kw).points
    assert prior.denoiser.motion is None
    still = animate(prior, frames, 32, **kw).points
    np.testing.assert_array_equal(still, animate(prior, frames, 32, windows=[None, None], **kw).points)
    assert np.abs(moving - still).max() > 1e-4
    with pytest.raises(ValueError, match="one entry per frame"):
        animate(prior, frames, 32, windows=windows[:1], **kw)


def test_a_pack_carries_the_motion_histories(tiny_dataset, tmp_path):
    """``data pack --motion``: the packed frames' windows are the dataset folder's (within the
    joints' quantisation); a pack without them says how to make one; a --motion-window run trains
    on it."""
    from pocoloco.cli import main as cli_main
    from pocoloco.data.dataset import PointCloudDataset
    from pocoloco.data.pack import PackedDataset, write_pack

    write_pack(tiny_dataset, tmp_path / "m.pack", points=64, motion=True)
    write_pack(tiny_dataset, tmp_path / "p.pack", points=64)
    packed = PackedDataset(tmp_path / "m.pack", "train", motion_window=2.0)
    folder = PointCloudDataset(tiny_dataset, "train", num_points=None, motion_window=2.0)
    where = {folder.frame_key(i): i for i in range(len(folder))}
    for i in (0, len(packed) - 1):
        np.testing.assert_allclose(packed[i]["motion"], folder[where[packed.frame_key(i)]]["motion"], atol=0.02)
    with pytest.raises(ValueError, match="data pack --motion") as e:
        PackedDataset(tmp_path / "p.pack", "train", motion_window=2.0)
    assert "\n" not in str(e.value)
    assert cli_main(["train", "--data", str(tmp_path / "m.pack"), "--preset", "latent_tiny", "--motion-window", "2.0",
                     "--steps", "2", "--num-points", "64", "--out", str(tmp_path / "run"), "--no-progress", "--sample-every", "0"]) in (0, None)  # fmt: skip


def test_the_motion_encoder_can_learn_faster_than_the_rest(tiny_dataset):
    """--motion-lr-scale: the encoder's parameters in their own AdamW groups at lr x scale (weight
    decay as the rest's), every other parameter at lr; POP's in their own Adam group too."""
    from pocoloco.methods.pocoloco import train_preset
    from pocoloco.methods.pocoloco.training import PocoLocoTask

    task = PocoLocoTask(train_preset("latent_tiny", motion_window=2.0, motion_lr_scale=10.0), tiny_dataset)
    model = task.build_model()
    opt = task.make_optimizer(model)
    lr_of = {id(p): g["lr"] for g in opt.param_groups for p in g["params"]}
    for name, p in model.named_parameters():
        assert lr_of[id(p)] == pytest.approx(task.config.lr * (10.0 if name.startswith("motion_in.") else 1.0)), name
    assert sum(len(g["params"]) for g in opt.param_groups) == len(list(model.parameters()))
    with pytest.raises(ValueError, match="motion_lr_scale"):
        train_preset("latent_tiny", motion_lr_scale=0.0)


def test_a_frozen_trunk_trains_the_motion_encoder_alone(tiny_dataset, tmp_path, capsys):
    """--freeze-trunk: only the motion encoder is in the optimiser and changes; every other weight
    of the fine-tune is the checkpoint's, bit for bit; without --motion-window or --init-from it is a
    one-line error, and a fine-tune *from* such a run trains everything again."""
    import torch
    from safetensors.torch import load_file

    from pocoloco.cli import main as cli_main
    from pocoloco.methods.pocoloco import train_preset
    from pocoloco.methods.pocoloco.training import PocoLocoTask

    task = PocoLocoTask(train_preset("latent_tiny", motion_window=2.0, freeze_trunk=True), tiny_dataset)
    model = task.build_model()
    opt = task.make_optimizer(model)
    trained = {id(p) for g in opt.param_groups for p in g["params"]}
    for name, p in model.named_parameters():
        assert (id(p) in trained) == p.requires_grad == name.startswith("motion_in."), name
    with pytest.raises(ValueError, match="needs --motion-window"):
        train_preset("latent_tiny", freeze_trunk=True)

    base, run, again = tmp_path / "base", tmp_path / "run", tmp_path / "again"
    common = ["--data", str(tiny_dataset), "--no-progress", "--device", "cpu", "--sample-every", "0", "--threads", "1"]
    assert cli_main(["train", "--out", str(base), "--preset", "latent_tiny", "--steps", "2", *common]) in (0, None)
    capsys.readouterr()
    assert cli_main(["train", "--out", str(tmp_path / "x"), "--preset", "latent_tiny", "--motion-window", "2.0",
                     "--freeze-trunk", "--steps", "2", *common]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert "--init-from" in err and "\n" not in err
    assert cli_main(["train", "--out", str(run), "--init-from", str(base), "--motion-window", "2.0", "--freeze-trunk",
                     "--steps", "3", "--lr", "1e-2", "--lr-schedule", "constant", *common]) in (0, None)  # fmt: skip
    before, after = load_file(base / "model" / "model.safetensors"), load_file(run / "model" / "model.safetensors")
    assert set(after) - set(before) and all(k.startswith("motion_in.") for k in set(after) - set(before))
    for k, v in before.items():
        assert torch.equal(v, after[k]), k
    assert any(not torch.equal(v, torch.zeros_like(v)) for k, v in after.items() if k.endswith("out.weight")
               and k.startswith("motion_in."))  # the zero-initialised projection has learnt
    assert cli_main(["train", "--out", str(again), "--init-from", str(run), "--steps", "2", "--lr", "1e-2",
                     "--lr-schedule", "constant", *common]) in (0, None)  # fmt: skip
    last = load_file(again / "model" / "model.safetensors")
    assert any(not torch.equal(v, last[k]) for k, v in before.items())
