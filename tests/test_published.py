"""Tests for the published-format readers/writers (pocoloco.data.published)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pocoloco.data import format as fmt
from pocoloco.data.published import (
    LooseStyleSequence,
    import_loose_style,
    read_joints_txt,
    read_ply,
    read_pop_npz,
    write_joints_txt,
    write_ply,
    write_pop_npz,
)


def _cloud(rng, n=40):
    pts = (rng.normal(size=(n, 3)) * 0.3).astype(np.float32)  # a body-sized cloud, metres
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return pts, nrm


# --------------------------------------------------------------------------- PLY
@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("label_dtype", [np.uint8, np.int32])
def test_ply_round_trip_exact(tmp_path, binary, label_dtype):
    rng = np.random.default_rng(0)
    pts, nrm = _cloud(rng)
    pts[0] = [1e-30, -3.4e38, 123456.789]  # extremes must survive ascii too
    labels = rng.integers(0, 200, len(pts)).astype(label_dtype)
    faces = rng.integers(0, len(pts), (9, 3))
    write_ply(tmp_path / "a.ply", pts, nrm, labels, faces, binary=binary)
    ply = read_ply(tmp_path / "a.ply", require_normals=True)
    np.testing.assert_array_equal(ply.points, pts)
    np.testing.assert_array_equal(ply.normals, nrm)
    np.testing.assert_array_equal(ply.labels, labels)
    assert ply.labels.dtype == label_dtype
    np.testing.assert_array_equal(ply.faces, faces)


def test_ply_points_only_and_trimesh_agrees(tmp_path):
    rng = np.random.default_rng(1)
    pts, _ = _cloud(rng, 25)
    write_ply(tmp_path / "p.ply", pts)
    ply = read_ply(tmp_path / "p.ply")
    assert ply.normals is None and ply.labels is None and ply.faces is None
    np.testing.assert_array_equal(ply.points, pts)
    # an independent reader sees the same vertices
    np.testing.assert_allclose(np.asarray(trimesh.load(tmp_path / "p.ply").vertices), pts)
    with pytest.raises(ValueError, match=r"p.ply: has no normals \(nx, ny, nz\)"):
        read_ply(tmp_path / "p.ply", require_normals=True)


def test_ply_written_by_trimesh_with_quads_and_extra_properties(tmp_path):
    # foreign PLYs: trimesh's writer, and a hand-made CRLF ascii file with quads, colours and edges
    box = trimesh.creation.box()
    box.export(tmp_path / "box.ply")
    ply = read_ply(tmp_path / "box.ply")
    np.testing.assert_allclose(ply.points, box.vertices)
    np.testing.assert_array_equal(ply.faces, box.faces)
    text = (
        "ply\r\nformat ascii 1.0\r\ncomment quad\r\nelement vertex 4\r\nproperty double x\r\nproperty double y\r\n"
        "property double z\r\nproperty uchar red\r\nelement face 1\r\nproperty list uchar uint vertex_index\r\n"
        "element edge 1\r\nproperty int vertex1\r\nproperty int vertex2\r\nend_header\r\n"
        "0 0 0 255\r\n1 0 0 0\r\n1 1 0 0\r\n0 1 0 9\r\n4 0 1 2 3\r\n0 1\r\n"
    )
    (tmp_path / "quad.ply").write_bytes(text.encode())
    ply = read_ply(tmp_path / "quad.ply")
    np.testing.assert_array_equal(ply.faces, [[0, 1, 2], [0, 2, 3]])


def test_ply_binary_big_endian_and_mixed_polygons(tmp_path):
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\nelement face 2\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode()
    rng = np.random.default_rng(2)
    v = rng.normal(size=(5, 6)).astype(">f4")
    faces = bytes([3]) + np.array([0, 1, 2], ">i4").tobytes() + bytes([4]) + np.array([1, 2, 3, 4], ">i4").tobytes()
    (tmp_path / "be.ply").write_bytes(header + v.tobytes() + faces)
    ply = read_ply(tmp_path / "be.ply", require_normals=True)
    np.testing.assert_array_equal(ply.points, v[:, :3].astype(np.float32))
    np.testing.assert_array_equal(ply.normals, v[:, 3:].astype(np.float32))
    np.testing.assert_array_equal(ply.faces, [[0, 1, 2], [1, 2, 3], [1, 3, 4]])


@pytest.mark.parametrize("binary", [True, False])
def test_ply_truncated(tmp_path, binary):
    rng = np.random.default_rng(3)
    pts, nrm = _cloud(rng, 30)
    write_ply(tmp_path / "t.ply", pts, nrm, faces=rng.integers(0, 30, (5, 3)), binary=binary)
    data = (tmp_path / "t.ply").read_bytes()
    for cut in (len(data) - 7, len(data) // 2, 40):
        (tmp_path / "t.ply").write_bytes(data[:cut])
        with pytest.raises(ValueError) as info:
            read_ply(tmp_path / "t.ply")
        msg = str(info.value)
        assert msg.startswith(str(tmp_path / "t.ply") + ":") and "\n" not in msg
        assert "truncated" in msg or "malformed" in msg or "expected" in msg


@pytest.mark.parametrize(
    "content, message",
    [
        (b"PK\x03\x04 binary junk", "not a PLY file"),
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unsupported PLY format"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
         "no 'z' property"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n1 nan 2\n", "non-finite vertex coordinates"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n1 abc 2\n", "non-numeric"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
         b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 1 2\n", "out of range"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty flot x\nend_header\n", "malformed property"),
    ],
)  # fmt: skip
def test_ply_malformed(tmp_path, content, message):
    (tmp_path / "m.ply").write_bytes(content)
    with pytest.raises(ValueError, match=message) as info:
        read_ply(tmp_path / "m.ply")
    assert str(tmp_path / "m.ply") in str(info.value)


# --------------------------------------------------------------------------- joints text
def test_joints_txt_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    ids = np.array([5, 6, 9, 100])
    joints = rng.normal(size=(4, 24, 3)).astype(np.float32)
    write_joints_txt(tmp_path / "j.txt", ids, joints)
    got_ids, got = read_joints_txt(tmp_path / "j.txt")
    np.testing.assert_array_equal(got_ids, ids)
    np.testing.assert_array_equal(got, joints)


@pytest.mark.parametrize(
    "line, message",
    [
        ("1 " + " ".join(["0.5"] * 70), r"line 2: expected 1 \+ 3\*24 = 73 values, got 71"),
        ("1 " + " ".join(["0.5"] * 71) + " x", "line 2: non-numeric value"),
        ("1 " + " ".join(["0.5"] * 71) + " nan", "line 2: NaN or inf"),
        ("1.5 " + " ".join(["0.5"] * 72), "line 2: frame id '1.5' is not a non-negative integer"),
        ("0 " + " ".join(["0.5"] * 72), "line 2: frame id 0 repeated"),
    ],
)
def test_joints_txt_errors(tmp_path, line, message):
    good = "0 " + " ".join(["0.1"] * 72)
    (tmp_path / "j.txt").write_text(good + "\n" + line + "\n")
    with pytest.raises(ValueError, match=message) as info:
        read_joints_txt(tmp_path / "j.txt")
    assert str(tmp_path / "j.txt") in str(info.value)


def test_joints_txt_other_joint_count_and_comments(tmp_path):
    (tmp_path / "j.txt").write_text("# id then 2 joints\n\n7, 1, 2, 3, 4, 5, 6\n")
    ids, j = read_joints_txt(tmp_path / "j.txt", num_joints=2)
    assert ids.tolist() == [7] and j.shape == (1, 2, 3) and j[0, 1, 2] == 6
    with pytest.raises(ValueError, match="got 7"):
        read_joints_txt(tmp_path / "j.txt")  # 24 joints expected by default


# --------------------------------------------------------------------------- LOOSE-style sequences
def _make_loose_sequence(folder, rng, ids=(10, 11, 13), n=60):
    folder.mkdir(parents=True, exist_ok=True)
    clouds = {}
    for i in ids:
        pts, nrm = _cloud(rng, n)
        pts += np.float32(i)  # frames differ
        write_ply(folder / f"frame_{i:06d}.ply", pts, nrm)
        clouds[i] = (pts, nrm)
    joints = rng.normal(size=(len(ids), 24, 3)).astype(np.float32)
    write_joints_txt(folder.parent / f"{folder.name}_joints.txt", np.array(ids), joints)
    return clouds, joints, folder.parent / f"{folder.name}_joints.txt"


def test_loose_sequence_matches_frames(tmp_path):
    rng = np.random.default_rng(5)
    clouds, joints, jtxt = _make_loose_sequence(tmp_path / "seqA", rng)
    seq = LooseStyleSequence(tmp_path / "seqA", jtxt)
    assert len(seq) == 3 and seq.frame_ids.tolist() == [10, 11, 13]
    fr = seq[2]
    assert fr.frame_id == 13
    np.testing.assert_array_equal(fr.points, clouds[13][0])
    np.testing.assert_array_equal(fr.normals, clouds[13][1])
    np.testing.assert_array_equal(fr.joints, joints[2])


def test_loose_sequence_missing_and_extra_frames(tmp_path):
    rng = np.random.default_rng(6)
    _, joints, jtxt = _make_loose_sequence(tmp_path / "s", rng)
    (tmp_path / "s" / "frame_000011.ply").unlink()
    with pytest.raises(ValueError, match=r"no .ply for 1 frame ids .* \(11\)"):
        LooseStyleSequence(tmp_path / "s", jtxt)
    write_joints_txt(jtxt, np.array([10]), joints[:1])  # now frame 13 has no joints line
    with pytest.raises(ValueError, match=r"1 PLY files have no line .* \(13\)"):
        LooseStyleSequence(tmp_path / "s", jtxt)
    assert len(LooseStyleSequence(tmp_path / "s", jtxt, strict=False)) == 1


def test_loose_sequence_samples_mesh_without_normals(tmp_path):
    rng = np.random.default_rng(7)
    (tmp_path / "m").mkdir()
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    write_ply(tmp_path / "m" / "3.ply", sphere.vertices, faces=sphere.faces)
    write_joints_txt(tmp_path / "j.txt", np.array([3]), rng.normal(size=(1, 24, 3)))
    fr = LooseStyleSequence(tmp_path / "m", tmp_path / "j.txt", mesh_samples=500)[0]
    assert fr.points.shape == (500, 3) and fr.normals.shape == (500, 3)
    # outward unit normals of a sphere point along the position
    np.testing.assert_allclose(np.linalg.norm(fr.normals, axis=1), 1.0, atol=1e-5)
    assert (np.sum(fr.normals * fr.points, axis=1) > 0.45).all()
    write_ply(tmp_path / "m" / "3.ply", sphere.vertices)  # no faces, no normals
    with pytest.raises(ValueError, match="3.ply: has no normals"):
        LooseStyleSequence(tmp_path / "m", tmp_path / "j.txt")[0]


def test_import_loose_style_writes_our_format(tmp_path):
    rng = np.random.default_rng(8)
    clouds, joints, jtxt = _make_loose_sequence(tmp_path / "raw" / "walk", rng)
    out = tmp_path / "ds"
    seq_dir = import_loose_style(tmp_path / "raw" / "walk", jtxt, out, subject="loose1", split="train", fps=25)
    card = fmt.read_card(out)
    assert card["subjects"]["loose1"]["source"] == "imported"
    assert card["counts"]["loose1"]["train"] == {"sequences": 1, "frames": 3, "rejected_frames": 0}
    assert card["normalisation"]["computed_on"] == "train"
    lay = fmt.DatasetLayout(out)
    frames = lay.iter_frames("train")
    assert [s for s, _, _ in frames] == ["loose1"] * 3 and frames[0][1] == "walk"
    f2 = fmt.read_frame(frames[2][2])
    assert f2.frame_index == 2 and f2.labels is None and f2.body_vertices is None
    np.testing.assert_array_equal(f2.points, clouds[13][0])
    np.testing.assert_array_equal(f2.joints, joints[2])
    meta = fmt.read_sequence_meta(lay.sequence_meta_path("loose1", "train", "walk"))
    assert meta["source"]["source_frame_ids"] == [10, 11, 13] and meta["fps"] == 25
    assert seq_dir == lay.sequence_dir("loose1", "train", "walk")


def _snapshot(root):
    """Every file's bytes and every folder under ``root`` (None for folders): equal means unchanged."""
    return {q.relative_to(root).as_posix(): (q.read_bytes() if q.is_file() else None) for q in sorted(root.rglob("*"))}


def _bad_ply_in_the_middle(folder):
    (folder / "frame_000011.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\n")


def test_import_records_frames_and_reimport_replaces_the_sequence(tmp_path):
    rng = np.random.default_rng(20)
    _, _, jtxt = _make_loose_sequence(tmp_path / "raw" / "walk", rng)
    out = tmp_path / "ds"
    import_loose_style(tmp_path / "raw" / "walk", jtxt, out, subject="a", split="train")
    card = fmt.read_card(out)
    recs = card["frame_files"]["a/train/walk"]
    assert sorted(recs) == ["000000.npz", "000001.npz", "000002.npz"]
    frame0 = fmt.DatasetLayout(out).frame_path("a", "train", "walk", 0)
    assert recs["000000.npz"] == [frame0.stat().st_size, fmt.file_crc32(frame0)]
    assert fmt.verify_dataset(out).ok and [q.name for q in out.iterdir()] == ["card.json", "subjects"]
    # the same sequence again, shorter and with other points of the same size: replaced, no stale frame
    _, _, jtxt2 = _make_loose_sequence(tmp_path / "raw2" / "walk", rng, ids=(4, 5))
    import_loose_style(tmp_path / "raw2" / "walk", jtxt2, out, subject="a", split="train")
    assert fmt.DatasetLayout(out).frame_indices("a", "train", "walk") == [0, 1]
    card = fmt.read_card(out)
    assert card["counts"]["a"]["train"]["frames"] == 2 and card["frame_files"]["a/train/walk"]["000000.npz"] != recs["000000.npz"]
    assert fmt.verify_dataset(out).ok and not list(out.glob(".import-*"))


@pytest.mark.parametrize("case", ["bad ply", "joint count", "missing frame id"])
def test_failed_import_into_a_new_folder_leaves_nothing(tmp_path, case):
    rng = np.random.default_rng(21)
    raw = tmp_path / "raw" / "walk"
    _, joints, jtxt = _make_loose_sequence(raw, rng)
    if case == "bad ply":
        _bad_ply_in_the_middle(raw)
    elif case == "joint count":
        write_joints_txt(jtxt, np.array([10, 11, 13]), joints[:, :23])
    else:
        write_joints_txt(jtxt, np.array([10, 11, 12, 13]), np.concatenate([joints, joints[:1]]))
    before = _snapshot(tmp_path)
    with pytest.raises(ValueError):
        import_loose_style(raw, jtxt, tmp_path / "new" / "deeper" / "ds", subject="a", split="train")
    with pytest.raises(ValueError):
        import_loose_style(raw, jtxt, tmp_path / "ds", subject="a", split="train")
    assert _snapshot(tmp_path) == before  # no dataset, no card, no parent folder, no temporary


@pytest.mark.parametrize("case", ["bad ply", "joint count", "missing frame id", "card"])
def test_failed_import_into_a_dataset_changes_nothing(tmp_path, case):
    rng = np.random.default_rng(22)
    _, _, jtxt = _make_loose_sequence(tmp_path / "raw" / "walk", rng)
    out = tmp_path / "ds"
    import_loose_style(tmp_path / "raw" / "walk", jtxt, out, subject="a", split="train")
    raw = tmp_path / "raw2" / "walk"  # the same sequence name: it would replace the one in the dataset
    _, joints, jtxt2 = _make_loose_sequence(raw, rng)
    if case == "bad ply":
        _bad_ply_in_the_middle(raw)
    elif case == "joint count":
        write_joints_txt(jtxt2, np.array([10, 11, 13]), joints[:, :23])
    elif case == "missing frame id":
        write_joints_txt(jtxt2, np.array([10, 11, 12, 13]), np.concatenate([joints, joints[:1]]))
    else:  # every frame is written and moved in, then recounting the card fails on another sequence's frame
        import_loose_style(tmp_path / "raw" / "walk", jtxt, out, subject="a", split="train", sequence="run")
        frame = fmt.DatasetLayout(out).frame_path("a", "train", "run", 1)
        frame.write_bytes(frame.read_bytes()[:-100])
    before = _snapshot(out)
    for subject in ("a", "new_subject"):
        with pytest.raises(ValueError):
            import_loose_style(raw, jtxt2, out, subject=subject, split="train")
        assert _snapshot(out) == before, subject  # not a byte changed: card, frames, folders


def test_import_refuses_a_folder_that_is_not_a_dataset(tmp_path):
    rng = np.random.default_rng(23)
    _, _, jtxt = _make_loose_sequence(tmp_path / "raw" / "walk", rng)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="other: exists and is not a pocoloco dataset"):
        import_loose_style(tmp_path / "raw" / "walk", jtxt, tmp_path / "other", subject="a", split="train")
    (tmp_path / "empty").mkdir()  # an empty folder is fine
    import_loose_style(tmp_path / "raw" / "walk", jtxt, tmp_path / "empty", subject="a", split="test")
    assert fmt.read_card(tmp_path / "empty")["counts"]["a"]["test"]["frames"] == 3


# --------------------------------------------------------------------------- POP npz
def _pop_arrays(rng, v=30, n=50, four=False):
    return {
        "scan_pc": rng.normal(size=(n, 3)).astype(np.float32),
        "scan_n": rng.normal(size=(n, 3)).astype(np.float32),
        "body_verts": rng.normal(size=(v, 3)).astype(np.float32),
        "vtransf": rng.normal(size=(v, 4, 4) if four else (v, 3, 3)).astype(np.float32),
    }


@pytest.mark.parametrize("four", [False, True])
def test_pop_round_trip(tmp_path, four):
    rng = np.random.default_rng(9)
    a = _pop_arrays(rng, four=four)
    pm = rng.normal(size=(16, 16, 3)).astype(np.float32)
    write_pop_npz(tmp_path / "p.npz", **a, scan_name="subject_00001", posmap256=pm, posmap_canonical128=pm[:8, :8])
    got = read_pop_npz(tmp_path / "p.npz", require=("scan_pc", "scan_n", "posmap256", "scan_name"))
    assert got["scan_name"] == "subject_00001"
    for k, v in a.items():
        np.testing.assert_array_equal(got[k], v)
    np.testing.assert_array_equal(got["posmap_canonical128"], pm[:8, :8])


def test_pop_errors(tmp_path):
    rng = np.random.default_rng(10)
    a = _pop_arrays(rng)
    np.savez(tmp_path / "nomap.npz", **a, scan_name="x")
    with pytest.raises(ValueError, match="nomap.npz: missing key 'posmap256'"):
        read_pop_npz(tmp_path / "nomap.npz", require=("posmap256",))
    b = dict(a)
    del b["scan_n"]
    np.savez(tmp_path / "non.npz", **b)
    with pytest.raises(ValueError, match="non.npz: missing key 'scan_n'"):
        read_pop_npz(tmp_path / "non.npz")
    np.savez(tmp_path / "shape.npz", **{**a, "vtransf": a["vtransf"][:, :2]})
    with pytest.raises(ValueError, match=r"'vtransf' must have shape \(V, 3, 3\) or \(V, 4, 4\)"):
        read_pop_npz(tmp_path / "shape.npz")
    np.savez(tmp_path / "nn.npz", **{**a, "scan_n": a["scan_n"][:-1]})
    with pytest.raises(ValueError, match="'scan_pc' .* and 'scan_n' .* disagree"):
        read_pop_npz(tmp_path / "nn.npz")
    bad = a["scan_pc"].copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="'scan_pc' contains NaN"):
        write_pop_npz(tmp_path / "w.npz", **{**a, "scan_pc": bad}, scan_name="x")
    write_pop_npz(tmp_path / "ok.npz", **a, scan_name="x")
    data = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "ok.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="ok.npz: corrupt or truncated npz"):
        read_pop_npz(tmp_path / "ok.npz")


def test_cli_imports_a_loose_style_folder_and_reports_bad_joints(tmp_path):
    from conftest import run_cli

    rng = np.random.default_rng(9)
    _, _, jtxt = _make_loose_sequence(tmp_path / "raw" / "walk", rng)
    out = tmp_path / "ds"
    r = run_cli("data", "import", str(tmp_path / "raw" / "walk"), "--joints", str(jtxt), "--out", str(out),
                "--subject", "s1")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert fmt.read_card(out)["counts"]["s1"]["train"]["frames"] == 3
    bad = tmp_path / "bad.txt"
    bad.write_text("10 " + " ".join(["0.1"] * 69) + "\n")  # 23 joints instead of 24
    r = run_cli("data", "import", str(tmp_path / "raw" / "walk"), "--joints", str(bad), "--out", str(out),
                "--subject", "s2")  # fmt: skip
    assert r.returncode == 2 and "bad.txt" in r.stderr and len(r.stderr.strip().splitlines()) == 1
