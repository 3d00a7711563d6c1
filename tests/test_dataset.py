"""Tests for PointCloudDataset and the PocoLoco normalisation (pocoloco.data.dataset)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from pocoloco.data import format as fmt
from pocoloco.data.dataset import Normalisation, PointCloudDataset, rotate_z

SUBJECTS = ("anna", "bob")


def make_dataset(root, rng, n=300, frames=(("train", 4), ("test", 2)), with_norm=True, labels=True):
    """A tiny synthetic dataset: random clouds around a moving root, 2 subjects, 2 sequences each."""
    card = fmt.make_card(subjects={s: {"garment_kind": "skirt", "phenotype": {}} for s in SUBJECTS})
    fmt.write_card(root, card)
    lay = fmt.DatasetLayout(root)
    for s in SUBJECTS:
        for split, count in frames:
            for seq in ("q0", "q1"):
                for i in range(count):
                    joints = (rng.normal(scale=0.3, size=(24, 3)) + rng.normal(size=3)).astype(np.float32)
                    pts = joints[0] + np.array([0.1, -0.2, 0.3]) + rng.normal(scale=[0.3, 0.2, 0.8], size=(n, 3))
                    nrm = rng.normal(size=(n, 3))
                    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
                    lab = rng.integers(0, 3, n).astype(np.uint8) if labels else None
                    frame = fmt.Frame(points=pts.astype(np.float32), normals=nrm.astype(np.float32), joints=joints,
                                      frame_index=i, labels=lab)  # fmt: skip
                    fmt.write_frame(lay.frame_path(s, split, seq, i), frame)
    if with_norm:
        fmt.refresh_card(root)
    return lay


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    make_dataset(root, np.random.default_rng(0))
    return root


def test_items_shapes_and_types(dataset_root):
    ds = PointCloudDataset(dataset_root, "train", num_points=100, with_normals=True)
    assert len(ds) == 2 * 2 * 4 and ds.subject_names == list(SUBJECTS)
    item = ds[5]
    assert item["points"].shape == (100, 3) and item["points"].dtype == torch.float32
    assert item["joints"].shape == (24, 3) and item["normals"].shape == (100, 3)
    assert item["labels"].shape == (100,) and item["labels"].dtype == torch.int64
    assert item["root"].shape == (3,)
    assert item["subject"] == 0 and item["frame_key"] == "anna/train/q1/000001"
    assert "normals" not in PointCloudDataset(dataset_root, "train", num_points=100)[0]
    batch = next(iter(DataLoader(ds, batch_size=3)))
    assert batch["points"].shape == (3, 100, 3) and len(batch["frame_key"]) == 3


def test_normalised_train_has_zero_mean_unit_std(dataset_root):
    ds = PointCloudDataset(dataset_root, "train", num_points=None)
    pts = torch.cat([ds[i]["points"] for i in range(len(ds))]).double()
    assert pts.mean(0).abs().max() < 1e-5
    assert abs(pts.std(unbiased=False).item() - 1.0) < 1e-5
    # on the test split the same (train) statistics are used, so only approximately
    test = PointCloudDataset(dataset_root, "test", num_points=None)
    tp = torch.cat([test[i]["points"] for i in range(len(test))]).double()
    assert tp.mean(0).abs().max() < 0.2 and abs(tp.std().item() - 1.0) < 0.2


def test_denormalise_inverts_exactly(dataset_root):
    ds = PointCloudDataset(dataset_root, "train", num_points=None, with_normals=True)
    item = ds[3]
    frame = fmt.read_frame(ds.frames[3][2])
    back = ds.normalisation.denormalise(item["points"].double(), item["root"].double())
    np.testing.assert_allclose(back.numpy(), frame.points, atol=1e-5)
    jb = ds.normalisation.denormalise(item["joints"].double(), item["root"].double())
    np.testing.assert_allclose(jb.numpy(), frame.joints, atol=1e-5)
    np.testing.assert_array_equal(item["normals"].numpy(), frame.normals)  # unchanged by translation + scale
    # numpy float64 round trip is exact to rounding
    norm = Normalisation(mean=(0.1, -2.0, 3.0), std=0.37, root_joint=0)
    rng = np.random.default_rng(1)
    p, j = rng.normal(size=(2, 50, 3)), rng.normal(size=(2, 24, 3))
    pn, jn = norm.normalise(p, j)
    np.testing.assert_allclose(norm.denormalise(pn, j[:, 0]), p, rtol=0, atol=1e-13)
    np.testing.assert_allclose(norm.denormalise(jn, j[:, 0]), j, rtol=0, atol=1e-13)
    np.testing.assert_allclose(jn[:, 0], np.broadcast_to((-np.array(norm.mean)) / norm.std, (2, 3)), atol=1e-13)


def _rz(angle: float) -> np.ndarray:
    """Slow reference: the 3x3 rotation matrix about +Z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_rotate_z_matches_the_rotation_matrix_in_numpy_and_torch():
    rng = np.random.default_rng(0)
    x, a = rng.normal(size=(4, 7, 3)), rng.uniform(-np.pi, np.pi, size=4)
    ref = np.stack([x[k] @ _rz(a[k]).T for k in range(4)])
    np.testing.assert_allclose(rotate_z(x, a), ref, rtol=0, atol=1e-12)
    got = rotate_z(torch.from_numpy(x), torch.from_numpy(a))
    assert isinstance(got, torch.Tensor) and got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), ref, rtol=0, atol=1e-12)
    assert rotate_z(x.astype(np.float32), a).dtype == np.float32
    np.testing.assert_array_equal(rotate_z(x, np.zeros(4)), x)  # angle 0 is exact (region editing relies on it)


def test_heading_normalisation_is_invariant_to_turning_the_body_and_inverts():
    """Turning a frame about the vertical axis through its root leaves its heading-normalised cloud
    unchanged (the angle grows by the turn), and denormalise with the angle gives the frame back."""
    rng = np.random.default_rng(3)
    norm = Normalisation(mean=(0.01, -0.05, -0.14), std=0.26, heading=True)
    joints = rng.normal(scale=0.3, size=(24, 3)) + np.array([1.0, 2.0, 0.9])
    points = joints[0] + rng.normal(scale=0.3, size=(100, 3))
    pn, jn = norm.normalise(points, joints)
    for turn in (0.3, 2.5, -3.0):
        R = _rz(turn)
        root = joints[0]
        p2, j2 = (points - root) @ R.T + root + [0.5, -1, 0], (joints - root) @ R.T + root + [0.5, -1, 0]
        pn2, jn2 = norm.normalise(p2, j2)
        np.testing.assert_allclose(pn2, pn, atol=1e-10)
        np.testing.assert_allclose(jn2, jn, atol=1e-10)
        d = (norm.angle(j2) - norm.angle(joints) - turn + np.pi) % (2 * np.pi) - np.pi
        assert abs(d) < 1e-10
        np.testing.assert_allclose(norm.denormalise(pn2, j2[0], norm.angle(j2)), p2, atol=1e-10)
    # the canonical frame: hips and shoulders run along +X
    across = jn[1] - jn[2] + jn[16] - jn[17]
    assert abs(across[1]) < 1e-10 and across[0] > 0
    # torch batches give the same as numpy
    tj = torch.from_numpy(np.stack([joints, joints + 1]))
    tp = torch.from_numpy(np.stack([points, points + 1]))
    np.testing.assert_allclose(norm.normalise(tp, tj)[0][0].numpy(), pn, atol=1e-10)
    with pytest.raises(ValueError, match="needs the frame's angle"):
        norm.denormalise(pn, joints[0])
    with pytest.raises(ValueError, match="24-joint"):
        norm.angle(joints[:10])
    assert Normalisation(mean=(0, 0, 0), std=1.0).angle(joints) == 0.0


def test_dataset_with_heading_turns_points_and_normals_alike(dataset_root):
    plain = PointCloudDataset(dataset_root, "train", num_points=None, with_normals=True, random_subsample=False)
    turned = PointCloudDataset(dataset_root, "train", num_points=None, with_normals=True, random_subsample=False,
                               heading=True)  # fmt: skip
    assert turned.normalisation.heading and not plain.normalisation.heading
    a, b = plain[2], turned[2]
    assert float(a["angle"]) == 0.0 and float(b["angle"]) != 0.0
    back = turned.normalisation.denormalise(b["points"].double(), b["root"].double(), b["angle"].double())
    np.testing.assert_allclose(back.numpy(), fmt.read_frame(turned.frames[2][2]).points, atol=1e-5)
    # normals turn like the points: the same rotation maps plain -> turned for both
    R = _rz(-float(b["angle"]))
    np.testing.assert_allclose(b["normals"].numpy(), a["normals"].numpy() @ R.T, atol=1e-5)
    mean, std = np.array(turned.normalisation.mean), turned.normalisation.std
    np.testing.assert_allclose(b["points"].numpy(), ((a["points"].numpy() * std + mean) @ R.T - mean) / std, atol=1e-4)


def test_normalisation_from_card_and_identity(dataset_root):
    card = fmt.read_card(dataset_root)
    norm = Normalisation.from_card(card)
    assert norm.mean == tuple(card["normalisation"]["mean"]) and norm.std == card["normalisation"]["std"]
    ds = PointCloudDataset(dataset_root, "train", num_points=None, normalise=False)
    frame = fmt.read_frame(ds.frames[0][2])
    np.testing.assert_allclose(ds[0]["points"].numpy(), frame.points - frame.joints[0], atol=1e-6)
    with pytest.raises(ValueError, match="no 'normalisation'"):
        Normalisation.from_card({**card, "normalisation": None})
    with pytest.raises(ValueError, match="std must be finite and > 0"):
        Normalisation(mean=(0, 0, 0), std=0.0)


def test_subsampling_random_vs_deterministic(dataset_root):
    det = PointCloudDataset(dataset_root, "train", num_points=50, random_subsample=False, seed=3)
    a, b = det[2]["points"], det[2]["points"]
    assert torch.equal(a, b)
    other_seed = PointCloudDataset(dataset_root, "train", num_points=50, random_subsample=False, seed=4)
    assert not torch.equal(a, other_seed[2]["points"])
    full = PointCloudDataset(dataset_root, "train", num_points=None)[2]["points"]
    # every subsampled point is one of the frame's points, without repeats
    same = (a[:, None, :] == full[None, :, :]).all(-1)  # (50, 300) exact matches
    assert torch.all(same.sum(1) == 1) and len(set(same.int().argmax(1).tolist())) == 50
    rnd = PointCloudDataset(dataset_root, "train", num_points=50, random_subsample=True)
    torch.manual_seed(0)
    r1 = rnd[2]["points"]
    r2 = rnd[2]["points"]
    torch.manual_seed(0)
    r3 = rnd[2]["points"]
    assert not torch.equal(r1, r2) and torch.equal(r1, r3)
    too_many = PointCloudDataset(dataset_root, "train", num_points=301)
    with pytest.raises(ValueError, match="000000.npz: frame has 300 points, fewer than num_points=301"):
        too_many[0]


def test_subject_filter(dataset_root):
    ds = PointCloudDataset(dataset_root, "test", num_points=10, subjects=["bob"])
    assert len(ds) == 4 and all(ds[i]["subject"] == 1 for i in range(len(ds)))
    assert ds[0]["frame_key"].startswith("bob/test/")


def test_validation_errors(dataset_root, tmp_path):
    with pytest.raises(ValueError, match="not a pocoloco dataset"):
        PointCloudDataset(tmp_path)
    with pytest.raises(ValueError, match="unknown split 'val'"):
        PointCloudDataset(dataset_root, "val")
    with pytest.raises(ValueError, match=r"unknown subjects \['carol'\]"):
        PointCloudDataset(dataset_root, subjects=["carol"])
    empty = tmp_path / "empty"
    make_dataset(empty, np.random.default_rng(2), frames=(("train", 1),))
    with pytest.raises(ValueError, match="no frames in split 'test'"):
        PointCloudDataset(empty, "test")
    nonorm = tmp_path / "nonorm"
    make_dataset(nonorm, np.random.default_rng(3), frames=(("train", 1),), with_norm=False)
    with pytest.raises(ValueError, match="no 'normalisation'"):
        PointCloudDataset(nonorm)
    assert len(PointCloudDataset(nonorm, normalise=False, num_points=10)) == 4
    with pytest.raises(IndexError):
        PointCloudDataset(dataset_root, num_points=10)[10_000]


def test_unlabelled_frames_get_unknown_label(tmp_path):
    make_dataset(tmp_path, np.random.default_rng(4), frames=(("train", 1),), labels=False)
    item = PointCloudDataset(tmp_path, num_points=20)[0]
    assert torch.all(item["labels"] == fmt.LABEL_UNKNOWN)
    assert json.loads((tmp_path / "card.json").read_text())["normalisation"]["std"] > 0


def test_a_missing_or_truncated_frame_is_refused_in_one_line(tmp_path):
    lay = make_dataset(tmp_path, np.random.default_rng(7), n=50)
    gone = lay.frame_path("bob", "test", "q1", 1)  # another split than the one asked for counts too
    gone.unlink()
    with pytest.raises(ValueError, match=rf"{gone}: missing \(card.json records it\); run `pocoloco data verify"):
        PointCloudDataset(tmp_path, "train")
    assert len(PointCloudDataset(tmp_path, "train", num_points=10, subjects=["anna"])) == 8  # bob is not used
    short = lay.frame_path("anna", "train", "q0", 0)
    short.write_bytes(short.read_bytes()[:100])
    with pytest.raises(ValueError, match=rf"{short}: 100 bytes, card.json records \d+ \(truncated\)"):
        PointCloudDataset(tmp_path, "train", subjects=["anna"])
