"""Tests for the on-disk dataset format (pocoloco.data.format) and atomic writes."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from pocoloco.body.skeleton import JOINT_NAMES
from pocoloco.data import format as fmt
from pocoloco.data import published
from pocoloco.data.published import read_ply, read_pop_npz
from pocoloco.utils import atomic_write, save_npz_atomic, write_json_atomic
from pocoloco.utils.atomic import jsonable, output_folder


def random_frame(rng: np.random.Generator, n: int = 50, v: int = 20, vg: int | None = 7, index: int = 3) -> fmt.Frame:
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return fmt.Frame(
        points=rng.normal(size=(n, 3)).astype(np.float32),
        normals=normals,
        joints=rng.normal(size=(24, 3)).astype(np.float32),
        frame_index=index,
        labels=rng.integers(0, 3, n).astype(np.uint8),
        parts=rng.integers(-1, 24, n).astype(np.int8),
        body_vertices=rng.normal(size=(v, 3)).astype(np.float32),
        vtransf=rng.normal(size=(v, 3, 3)).astype(np.float32),
        garment_vertices=None if vg is None else rng.normal(size=(vg, 3)).astype(np.float32),
    )


def assert_frames_equal(a: fmt.Frame, b: fmt.Frame) -> None:
    assert a.frame_index == b.frame_index
    for k in ("points", "normals", "joints", "labels", "parts", "body_vertices", "vtransf", "garment_vertices"):
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None) == (y is None), k
        if x is not None:
            assert x.dtype == y.dtype, k
            np.testing.assert_array_equal(x, y, err_msg=k)


# --------------------------------------------------------------------------- atomic writes
def test_atomic_write_replaces_and_leaves_no_temp_on_error(tmp_path):
    p = tmp_path / "sub" / "a.bin"
    atomic_write(p, lambda f: f.write(b"one"))
    assert p.read_bytes() == b"one"

    def failing(f):
        f.write(b"partial")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        atomic_write(p, failing)
    assert p.read_bytes() == b"one"  # untouched
    assert os.listdir(p.parent) == ["a.bin"]  # temp file cleaned up


def test_save_npz_and_json_atomic(tmp_path):
    save_npz_atomic(tmp_path / "x.npz", a=np.arange(3), b=np.eye(2))
    with np.load(tmp_path / "x.npz") as z:
        np.testing.assert_array_equal(z["a"], np.arange(3))
        np.testing.assert_array_equal(z["b"], np.eye(2))
    write_json_atomic(tmp_path / "c.json", {"k": [1, 2.5, "s"]})
    assert json.loads((tmp_path / "c.json").read_text()) == {"k": [1, 2.5, "s"]}
    with pytest.raises(ValueError):
        write_json_atomic(tmp_path / "d.json", {"k": float("nan")})  # strict JSON only
    assert not (tmp_path / "d.json").exists()


def test_jsonable_rounds_floats_to_significant_digits_only_when_asked():
    x = {"a": [np.float32(1.23456789), 2.0 / 3.0, float("nan"), 7, True], 3: np.array([123456.789, -1e-9 / 3])}
    assert jsonable(x) == {"a": [float(np.float32(1.23456789)), 2.0 / 3.0, None, 7, True], "3": [123456.789, -1e-9 / 3]}
    short = jsonable(x, digits=6)
    assert short == {"a": [1.23457, 0.666667, None, 7, True], "3": [123457.0, -3.33333e-10]}
    for full, kept in zip(jsonable(x)["a"][:2] + jsonable(x)["3"], short["a"][:2] + short["3"]):
        assert abs(kept - full) <= 5e-6 * abs(full)  # each value to 1e-6 of itself
    assert isinstance(short["a"][3], int) and short["a"][4] is True  # ints and bools are not floats here


def test_output_folder_accepts_folders_and_new_paths_not_files(tmp_path):
    assert output_folder(tmp_path) == tmp_path
    assert output_folder(str(tmp_path / "new" / "deeper")) == tmp_path / "new" / "deeper"
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(ValueError, match="file.txt: exists and is not a folder"):
        output_folder(tmp_path / "file.txt")
    assert not (tmp_path / "new").exists()  # checks only, creates nothing


# --------------------------------------------------------------------------- frames
@pytest.mark.parametrize("vg", [7, None])
def test_frame_round_trip_exact(tmp_path, vg):
    frame = random_frame(np.random.default_rng(0), vg=vg)
    p = tmp_path / "f.npz"
    fmt.write_frame(p, frame)
    back = fmt.read_frame(p)
    assert isinstance(back, fmt.Frame)
    assert_frames_equal(frame, back)


def test_frame_optional_fields_absent(tmp_path):
    rng = np.random.default_rng(1)
    f = random_frame(rng)
    minimal = fmt.Frame(points=f.points, normals=f.normals, joints=f.joints, frame_index=0)
    fmt.write_frame(tmp_path / "m.npz", minimal)
    with np.load(tmp_path / "m.npz") as z:
        assert sorted(z.files) == sorted(fmt.REQUIRED_FRAME_KEYS)
    back = fmt.read_frame(tmp_path / "m.npz")
    assert back.labels is None and back.body_vertices is None and back.vtransf is None
    with pytest.raises(ValueError, match="missing key 'labels'"):
        fmt.read_frame(tmp_path / "m.npz", ["points", "labels"])
    sub = fmt.read_frame(tmp_path / "m.npz", ["points", "labels"], allow_missing=True)
    assert sub.labels is None and sub.normals is None
    np.testing.assert_array_equal(sub.points, f.points)


def test_read_frame_subset_of_keys(tmp_path):
    frame = random_frame(np.random.default_rng(2))
    fmt.write_frame(tmp_path / "f.npz", frame)
    d = fmt.read_frame(tmp_path / "f.npz", ["points", "joints"])
    assert d.normals is None and d.frame_index is None and d.vtransf is None
    np.testing.assert_array_equal(d.joints, frame.joints)
    np.testing.assert_array_equal(d.points, frame.points)
    assert fmt.read_frame(tmp_path / "f.npz", "labels").labels.dtype == np.uint8
    with pytest.raises(ValueError, match="unknown frame keys"):
        fmt.read_frame(tmp_path / "f.npz", ["colour"])


def _write_raw(path, **arrays):
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a: a.pop("normals"), "missing key 'normals'"),
        (lambda a: a.__setitem__("points", a["points"][:, :2]), r"'points' must have shape \(N, 3\)"),
        (lambda a: a.__setitem__("joints", a["joints"][:22]), r"'joints' must have shape \(24, 3\)"),
        (lambda a: a["points"].__setitem__((4, 1), np.nan), "'points' contains NaN or inf"),
        (lambda a: a["body_vertices"].__setitem__((0, 0), np.inf), "'body_vertices' contains NaN or inf"),
        (lambda a: a.__setitem__("labels", a["labels"][:-1]), "per-point arrays disagree on N"),
        (lambda a: a.__setitem__("vtransf", a["vtransf"][:-1]), "'vtransf' has"),
        (lambda a: a.__setitem__("labels", a["labels"].astype(np.float32)), "'labels' must be integer"),
        (lambda a: a.__setitem__("frame_index", np.arange(2)), "'frame_index' must be a scalar"),
    ],
)
def test_read_frame_rejects_bad_content(tmp_path, change, message):
    arrays = random_frame(np.random.default_rng(3)).to_arrays()
    change(arrays)
    p = _write_raw(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=message) as info:
        fmt.read_frame(p)
    assert str(p) in str(info.value) and "\n" not in str(info.value)


def test_write_frame_validates(tmp_path):
    frame = random_frame(np.random.default_rng(4))
    frame.joints = frame.joints[:10]
    with pytest.raises(ValueError, match="'joints' must have shape"):
        fmt.write_frame(tmp_path / "f.npz", frame)
    with pytest.raises(ValueError, match=r"f.npz: frame lacks required fields \['normals'\]"):
        fmt.write_frame(tmp_path / "f.npz", fmt.Frame(points=frame.points, joints=frame.joints[:0], frame_index=0))
    assert not (tmp_path / "f.npz").exists()


@pytest.mark.parametrize("keep", [0.3, 0.9, 0.999])
def test_read_frame_truncated(tmp_path, keep):
    p = tmp_path / "f.npz"
    fmt.write_frame(p, random_frame(np.random.default_rng(5)))
    data = p.read_bytes()
    p.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError, match="corrupt or truncated npz") as info:
        fmt.read_frame(p)
    assert str(p) in str(info.value) and "\n" not in str(info.value)


def test_read_frame_corrupt_bytes_and_not_npz(tmp_path):
    p = tmp_path / "f.npz"
    fmt.write_frame(p, random_frame(np.random.default_rng(6)), compress=True)
    data = bytearray(p.read_bytes())
    data[200:260] = b"\x00" * 60  # inside the first compressed member
    p.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="corrupt or truncated npz"):
        fmt.read_frame(p)
    q = tmp_path / "text.npz"
    q.write_text("hello")
    with pytest.raises(ValueError, match="text.npz: not a NumPy file"):
        fmt.read_frame(q)
    np.save(tmp_path / "array.npy", np.zeros(3))
    with pytest.raises(ValueError, match=r"array.npy: a NumPy .npy array, not a .npz archive"):
        fmt.read_frame(tmp_path / "array.npy")
    with pytest.raises(FileNotFoundError):
        fmt.read_frame(tmp_path / "nope.npz")


# --------------------------------------------------------------------------- card and layout
def test_card_round_trip_and_errors(tmp_path):
    card = fmt.make_card(subjects={"s0": {"garment_kind": "skirt", "phenotype": {"height": 0.5}}},
                         generation_config={"fps": 30})  # fmt: skip
    fmt.write_card(tmp_path, card)
    back = fmt.read_card(tmp_path)
    assert back == json.loads(json.dumps(card))
    assert back["skeleton"]["joint_names"] == list(JOINT_NAMES)
    assert back["format"] == fmt.FORMAT_NAME and back["version"] == fmt.FORMAT_VERSION

    with pytest.raises(ValueError, match="not a pocoloco dataset"):
        fmt.read_card(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"empty: not a pocoloco dataset \(no card.json\)"):
        fmt.read_card(tmp_path / "empty")
    (tmp_path / "card.json").write_text("{not json")
    with pytest.raises(ValueError, match="card.json: malformed JSON"):
        fmt.read_card(tmp_path)
    (tmp_path / "card.json").write_text(json.dumps({**card, "format": "other"}))
    with pytest.raises(ValueError, match="not a pocoloco dataset card"):
        fmt.read_card(tmp_path)
    (tmp_path / "card.json").write_text(json.dumps({**card, "version": 2}))
    with pytest.raises(ValueError, match="unsupported dataset format version 2"):
        fmt.read_card(tmp_path)
    with pytest.raises(ValueError, match="'normalisation' must be"):
        fmt.write_card(tmp_path, {**card, "normalisation": {"mean": [0, 0], "std": 1.0}})


def test_layout_paths_and_iteration(tmp_path):
    lay = fmt.DatasetLayout(tmp_path)
    assert str(lay.frame_path("s", "train", "q", 123)).endswith(os.path.join("s", "train", "q", "frames", "000123.npz"))
    with pytest.raises(ValueError, match="unknown split 'val'"):
        lay.sequence_dir("s", "val", "q")
    rng = np.random.default_rng(7)
    for s, seq, idx in [("b", "q1", [2, 0, 1]), ("a", "q0", [0, 1]), ("a", "q1", [5])]:
        for i in idx:
            fmt.write_frame(lay.frame_path(s, "train", seq, i), random_frame(rng, index=i))
    (tmp_path / "subjects" / "a" / "train" / "q0" / "frames" / ".000009.npz.tmp").write_bytes(b"")
    got = [(s, q, os.path.basename(p)) for s, q, p in lay.iter_frames("train")]
    assert got == [("a", "q0", "000000.npz"), ("a", "q0", "000001.npz"), ("a", "q1", "000005.npz"),
                   ("b", "q1", "000000.npz"), ("b", "q1", "000001.npz"), ("b", "q1", "000002.npz")]  # fmt: skip
    assert lay.iter_frames("test") == []
    assert [s for s, _, _ in lay.iter_frames("train", ["b"])] == ["b"] * 3


def test_subject_motion_sequence_files_round_trip(tmp_path):
    rng = np.random.default_rng(8)
    lay = fmt.DatasetLayout(tmp_path)
    subj = fmt.SubjectAsset(
        template=rng.normal(size=(10, 3)).astype(np.float32), faces=rng.integers(0, 10, (6, 3)).astype(np.int32),
        uv=rng.random((12, 2)).astype(np.float32), uv_faces=rng.integers(0, 12, (6, 3)).astype(np.int32),
        vertex_joint=rng.integers(0, 24, 10).astype(np.int8), phenotype={"gender": 0.3, "height": 0.7},
    )  # fmt: skip
    fmt.write_subject(lay.subject_path("s"), subj)
    back = fmt.read_subject(lay.subject_path("s"))
    assert back.phenotype == subj.phenotype and back.garment_faces is None
    np.testing.assert_array_equal(back.template, subj.template)
    np.testing.assert_array_equal(back.uv_faces, subj.uv_faces)

    m = fmt.StoredMotion(rng.normal(size=(5, 24, 3)).astype(np.float32), rng.normal(size=(5, 3)).astype(np.float32))
    fmt.write_motion(lay.motion_path("s", "train", "q"), m)
    mb = fmt.read_motion(lay.motion_path("s", "train", "q"))
    np.testing.assert_array_equal(mb.joint_rotvecs, m.joint_rotvecs)
    with pytest.raises(ValueError, match="joint_rotvecs must have shape"):
        fmt.write_motion(tmp_path / "bad.npz", fmt.StoredMotion(np.zeros((5, 23, 3)), np.zeros((5, 3))))

    meta = {"num_frames": 5, "fps": 30, "motion": [{"name": "walk", "seed": 1, "kind": "walk", "start": 0, "stop": 5}],
            "rejected_frames": [{"frame": 2, "reason": "cloth exploded"}]}  # fmt: skip
    fmt.write_sequence_meta(lay.sequence_meta_path("s", "train", "q"), meta)
    assert fmt.read_sequence_meta(lay.sequence_meta_path("s", "train", "q")) == meta
    with pytest.raises(ValueError, match="integer 'num_frames'"):
        fmt.write_sequence_meta(tmp_path / "x.json", {"fps": 30})


# --------------------------------------------------------------------------- normalisation statistics
def _reference_normalisation(paths):
    """Slow, obvious reference: everything in memory, numpy mean/std."""
    centred = []
    for p in paths:
        f = fmt.read_frame(p)
        centred.append(f.points.astype(np.float64) - f.joints[0].astype(np.float64))
    c = np.concatenate(centred)
    mean = c.mean(axis=0)
    return mean, (c - mean).std()


def test_compute_normalisation_matches_reference(tmp_path):
    rng = np.random.default_rng(9)
    paths = []
    for i, n in enumerate([30, 200, 7, 64]):  # unequal N: points weigh equally, not frames
        f = random_frame(rng, n=n, index=i)
        f.points = (f.points * (0.2 + i) + np.array([1.0, -2.0, 0.5]) * i + 10.0).astype(np.float32)
        p = tmp_path / f"{i}.npz"
        fmt.write_frame(p, f)
        paths.append(p)
    stats = fmt.compute_normalisation(iter(paths))  # a generator is enough: streaming
    mean, std = _reference_normalisation(paths)
    np.testing.assert_allclose(stats["mean"], mean, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(stats["std"], std, rtol=1e-12)
    assert stats["num_points"] == 301 and stats["num_frames"] == 4
    with pytest.raises(ValueError, match="no frames"):
        fmt.compute_normalisation([])


def test_refresh_card_counts_and_normalisation(tmp_path):
    rng = np.random.default_rng(10)
    lay = fmt.DatasetLayout(tmp_path)
    fmt.write_card(tmp_path, fmt.make_card(subjects={"a": {}, "b": {}}))
    for s, split, n in [("a", "train", 3), ("b", "train", 2), ("a", "test", 1)]:
        for i in range(n):
            fmt.write_frame(lay.frame_path(s, split, "q", i), random_frame(rng, index=i))
        fmt.write_sequence_meta(lay.sequence_meta_path(s, split, "q"),
                                {"num_frames": n + 1, "rejected_frames": [{"frame": n, "reason": "x"}]})  # fmt: skip
    card = fmt.refresh_card(tmp_path)
    assert card["counts"]["a"] == {"train": {"sequences": 1, "frames": 3, "rejected_frames": 1},
                                   "test": {"sequences": 1, "frames": 1, "rejected_frames": 1}}  # fmt: skip
    assert card["counts"]["b"]["test"]["frames"] == 0
    mean, std = _reference_normalisation([p for _, _, p in lay.iter_frames("train")])
    np.testing.assert_allclose(card["normalisation"]["mean"], mean, rtol=1e-10)
    assert card["normalisation"]["computed_on"] == "train" and card["normalisation"]["root_joint"] == 0
    assert fmt.read_card(tmp_path) == card


# --------------------------------------------------------------------------- integrity
def _recorded_dataset(root, rng):
    """Subject "a": train sequence "q" with frames 0, 1, 3 (2 rejected), test sequence "r" with frame 0."""
    lay = fmt.DatasetLayout(root)
    fmt.write_card(root, fmt.make_card(subjects={"a": {}}))
    for split, seq, frames, num, rejected in [("train", "q", (0, 1, 3), 4, [2]), ("test", "r", (0,), 1, [])]:
        for i in frames:
            fmt.write_frame(lay.frame_path("a", split, seq, i), random_frame(rng, index=i))
        fmt.write_sequence_meta(lay.sequence_meta_path("a", split, seq),
                                {"num_frames": num, "rejected_frames": [{"frame": f, "reason": "x"} for f in rejected]})  # fmt: skip
    return fmt.refresh_card(root), lay


def test_refresh_card_records_frame_files(tmp_path):
    card, lay = _recorded_dataset(tmp_path, np.random.default_rng(30))
    assert sorted(card["frame_files"]) == ["a/test/r", "a/train/q"]
    assert sorted(card["frame_files"]["a/train/q"]) == ["000000.npz", "000001.npz", "000003.npz"]
    f = lay.frame_path("a", "train", "q", 3)
    assert card["frame_files"]["a/train/q"]["000003.npz"] == [f.stat().st_size, fmt.file_crc32(f)]
    report = fmt.verify_dataset(tmp_path)
    assert report.ok and report.frames == report.recorded == 4 and report.records == card["frame_files"]
    assert fmt.check_frames(tmp_path, splits=("test",)).frames == 1


def test_scan_finds_a_rejected_frame_on_disk_and_a_malformed_sequence_json(tmp_path):
    rng = np.random.default_rng(31)
    _, lay = _recorded_dataset(tmp_path, rng)
    fmt.write_frame(lay.frame_path("a", "train", "q", 2), random_frame(rng, index=2))  # the rejected one
    lay.sequence_meta_path("a", "test", "r").write_text("{not json")
    report = fmt.scan_frames(tmp_path)
    assert [(p.kind, p.path.name) for p in report.problems] == [("unreadable", "sequence.json"), ("extra", "000002.npz")]
    assert report.kinds() == {"extra": 1, "unreadable": 1}
    assert report.summary().startswith("2 bad frame files (1 extra, 1 unreadable); first: ")
    with pytest.raises(ValueError, match=r"r/sequence.json: malformed JSON .*; run `pocoloco data verify"):
        fmt.check_frames(tmp_path)


def test_scan_refuses_malformed_records_in_one_line(tmp_path):
    card, _ = _recorded_dataset(tmp_path, np.random.default_rng(32))
    card["frame_files"]["a/train/q"]["000001.npz"] = "big"
    (tmp_path / "card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match=r"card.json: malformed frame_files record a/train/q/000001.npz: 'big'"):
        fmt.check_frames(tmp_path)
    card["frame_files"] = ["a list"]
    (tmp_path / "card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match="'frame_files' must be"):
        fmt.read_card(tmp_path)


def test_refresh_card_refuses_to_record_a_truncated_frame(tmp_path):
    _, lay = _recorded_dataset(tmp_path, np.random.default_rng(33))
    f = lay.frame_path("a", "test", "r", 0)
    f.write_bytes(f.read_bytes()[:-5])
    before = (tmp_path / "card.json").read_bytes()
    with pytest.raises(ValueError, match=rf"{f}: corrupt or truncated npz"):
        fmt.refresh_card(tmp_path)
    assert (tmp_path / "card.json").read_bytes() == before


# --------------------------------------------------------------------------- export
def test_export_frame_ply_and_pop(tmp_path):
    lay = fmt.DatasetLayout(tmp_path)
    frame = random_frame(np.random.default_rng(11))
    fp = lay.frame_path("subj", "train", "seq", 3)
    fmt.write_frame(fp, frame)
    published.export_frame(fp, tmp_path / "out.ply", "ply")
    ply = read_ply(tmp_path / "out.ply", require_normals=True)
    np.testing.assert_array_equal(ply.points, frame.points)
    np.testing.assert_array_equal(ply.normals, frame.normals)
    np.testing.assert_array_equal(ply.labels, frame.labels)
    published.export_frame(fp, tmp_path / "out.npz", "npz")
    pop = read_pop_npz(tmp_path / "out.npz")
    np.testing.assert_array_equal(pop["scan_pc"], frame.points)
    np.testing.assert_array_equal(pop["vtransf"], frame.vtransf)
    assert pop["scan_name"] == "subj_train_seq_000003"
    bare = fmt.Frame(points=frame.points, normals=frame.normals, joints=frame.joints, frame_index=0)
    fmt.write_frame(tmp_path / "bare.npz", bare)
    with pytest.raises(ValueError, match="bare.npz: frame has no body_vertices"):
        published.export_frame(tmp_path / "bare.npz", tmp_path / "o2.npz", "npz")
    with pytest.raises(ValueError, match="fmt must be"):
        published.export_frame(fp, tmp_path / "o.obj", "obj")


def test_atomic_files_get_normal_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        write_json_atomic(tmp_path / "p.json", {})
    finally:
        os.umask(old)
    assert (tmp_path / "p.json").stat().st_mode & 0o777 == 0o644


def test_card_reports_test_pose_coverage_and_info_prints_it(tiny_dataset, capsys):
    """card["pose_coverage"]: per subject, each test frame's RMS root-aligned joint distance to the
    nearest training frame (checked against a plain double loop), shown by ``data info``."""
    from pocoloco.cli import main

    card = fmt.read_card(tiny_dataset)
    layout = fmt.DatasetLayout(tiny_dataset)
    cov = fmt.pose_coverage(tiny_dataset, layout.subjects())
    assert set(cov) == set(layout.subjects()) and card["pose_coverage"].keys() == cov.keys()
    for s, c in cov.items():
        joints = {sp: [fmt.read_frame(p, ["joints"]).joints.astype(np.float64) for _, _, p in layout.iter_frames(sp, [s])]
                  for sp in fmt.SPLITS}  # fmt: skip
        ref = []
        for q in joints["test"]:
            best = min(np.sqrt((((q - q[0]) - (k - k[0])) ** 2).sum(-1).mean()) for k in joints["train"])
            ref.append(100 * best)
        assert c["test_frames"] == len(ref)
        np.testing.assert_allclose([c["median_cm"], c["p90_cm"], c["max_cm"]],
                                   [np.median(ref), np.quantile(ref, 0.9), max(ref)], rtol=1e-9)  # fmt: skip
    assert main(["data", "info", str(tiny_dataset)]) == 0
    out = capsys.readouterr().out
    assert "nearest training pose" in out and "p90" in out
