"""Tests of ``pocoloco mesh`` (pocoloco.apps.meshing): screened Poisson reconstruction of clouds.

Shapes with a known surface: a sphere (radius 0.5) and a "dress" (an ellipsoid torso above an
open cone skirt), sampled uniformly; mesh vertices are compared with the analytic surface or
with a dense reference sample of it.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

pytest.importorskip("open3d")

from pocoloco.apps.meshing import (  # noqa: E402
    MIN_POINTS,
    _cancel_face_pairs,
    _drop_small_components,
    estimate_normals,
    is_watertight,
    mesh_from_points,
    skeleton_outward,
)
from pocoloco.cli import main  # noqa: E402
from pocoloco.data.published import read_ply, write_ply  # noqa: E402

R = 0.5


def _sphere(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return R * d / np.linalg.norm(d, axis=1, keepdims=True)


def _dress(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ellipsoid torso (semi-axes 0.3, 0.2, 0.5 around z=0.8) above an open cone skirt
    (z in [0, 0.5], radius 0.15 at the top to 0.40 at the hem), sampled about uniformly by area.
    Returns points (n, 3) and outward normals (n, 3)."""
    rng = np.random.default_rng(seed)
    axes = np.array([0.3, 0.2, 0.5])
    d = rng.normal(size=(n // 2, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    torso = d * axes + [0, 0, 0.8]
    torso_n = d / axes
    m = n - n // 2
    h = np.sqrt(rng.uniform(0, 1, m))  # area grows towards the hem: density ~ radius
    z = 0.5 * (1 - h)
    r = 0.15 + 0.5 * (0.5 - z)
    a = rng.uniform(0, 2 * np.pi, m)
    skirt = np.stack([r * np.cos(a), r * np.sin(a), z], 1)
    skirt_n = np.stack([np.cos(a), np.sin(a), np.full(m, 0.5)], 1)  # cone slope dr/dz = -0.5
    pts = np.concatenate([torso, skirt])
    nrm = np.concatenate([torso_n, skirt_n])
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def _dist_to(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(reference).query(points)[0]


# ----------------------------------------------------------------------------- normals
def test_estimated_normals_point_outwards_on_a_sphere():
    pts = _sphere(3000)
    n = estimate_normals(pts)
    cos = np.sum(n * pts / R, axis=1)
    assert (cos > 0.95).mean() > 0.99, np.quantile(cos, [0, 0.01, 0.5])


def test_estimated_normals_are_consistent_on_the_dress():
    pts, true_n = _dress(4000)
    n = estimate_normals(pts)
    cos = np.sum(n * true_n, axis=1)
    assert (cos > 0.8).mean() > 0.97, np.quantile(cos, [0, 0.01, 0.05, 0.5])


def _limbs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on 3 cm tubes around every bone of the demo:tight pose (hands, feet and fingers
    included: the thin parts where propagated orientation flips). Returns joints (24, 3), points
    (n, 3) and outward directions (n, 3), unit."""
    from pocoloco.body.skeleton import JOINT_PARENTS
    from pocoloco.data.poses import load_joints

    J = load_joints("demo:tight").astype(np.float64)
    bones = [(p, c) for c, p in enumerate(JOINT_PARENTS) if p >= 0]
    rng = np.random.default_rng(seed)
    b = rng.integers(0, len(bones), n)
    a, c = J[[bones[i][0] for i in b]], J[[bones[i][1] for i in b]]
    axis = (c - a) / np.linalg.norm(c - a, axis=1, keepdims=True)
    r = rng.normal(size=(n, 3))
    r -= np.sum(r * axis, axis=1, keepdims=True) * axis
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    t = rng.uniform(0.2, 0.8, (n, 1))  # away from the joints, where tubes of two bones overlap
    return J, a + t * (c - a) + 0.03 * r, r


def test_skeleton_outward_matches_a_per_point_reference():
    """The vectorised nearest-bone direction against a plain loop over points and bones."""
    from pocoloco.body.skeleton import JOINT_PARENTS

    J, pts, _ = _limbs(300, seed=1)
    pts = pts + np.random.default_rng(2).normal(scale=0.05, size=pts.shape)
    fast = skeleton_outward(pts, J)
    for i, p in enumerate(pts):
        best, vec = np.inf, None
        for child, parent in enumerate(JOINT_PARENTS):
            if parent < 0:
                continue
            a, b = J[parent], J[child]
            t = min(max(float((p - a) @ (b - a)) / float((b - a) @ (b - a)), 0.0), 1.0)
            d = p - (a + t * (b - a))
            if d @ d < best:
                best, vec = d @ d, d
        np.testing.assert_allclose(fast[i], vec, atol=1e-12)
    with pytest.raises(ValueError, match="joints must have shape"):
        skeleton_outward(pts, J[:10])


def test_normals_oriented_by_the_skeleton_point_away_from_the_bones():
    """With the pose, every tube normal faces outwards (the propagated orientation is not asked
    to get thin tubes right); the CLI takes the pose with --joints."""
    J, pts, outward = _limbs(6000)
    by_skeleton = (np.sum(estimate_normals(pts, knn=15, joints=J) * outward, axis=1) > 0).mean()
    propagated = (np.sum(estimate_normals(pts, knn=15) * outward, axis=1) > 0).mean()
    # ~1 % of tube points lie nearer another bone where short bones meet (0.987 here); propagation 0.78
    assert by_skeleton > 0.97 and by_skeleton > propagated + 0.1, (by_skeleton, propagated)


# ----------------------------------------------------------------------------- reconstruction
@pytest.mark.parametrize("with_normals", [True, False])
def test_sphere_mesh_is_watertight_and_on_the_surface(with_normals):
    pts = _sphere(4000)
    normals = pts / R if with_normals else None
    verts, faces = mesh_from_points(pts, normals, depth=7)
    assert verts.dtype == np.float32 and faces.dtype == np.int64 and faces.shape[1] == 3
    assert is_watertight(verts, faces)
    err = np.abs(np.linalg.norm(verts, axis=1) - R)
    assert err.max() < 0.02 * R and err.mean() < 0.005 * R, (err.max(), err.mean())
    # a closed surface with uniform sampling has no low-density vertex to trim
    _, faces0 = mesh_from_points(pts, normals, depth=7, density_quantile=0.0)
    assert len(faces0) == len(faces)
    # outward winding: positive enclosed volume close to the ball's
    vol = trimesh.Trimesh(verts, faces, process=False).volume
    assert vol == pytest.approx(4 / 3 * np.pi * R**3, rel=0.03)


def test_poisson_runs_on_one_thread_and_repeats_exactly(monkeypatch):
    """Open3D's multi-threaded Poisson solver has a data race that segfaults the process now
    and then; the reconstruction asks for one thread, and two runs give identical meshes."""
    import open3d as o3d

    calls = []
    real = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson

    def spy(*args, **kwargs):
        calls.append(kwargs.get("n_threads", -1))
        return real(*args, **kwargs)

    monkeypatch.setattr(o3d.geometry.TriangleMesh, "create_from_point_cloud_poisson", spy)
    pts = _sphere(2000)
    a = mesh_from_points(pts, pts / R, depth=6)
    b = mesh_from_points(pts, pts / R, depth=6)
    assert calls and set(calls) == {1}, calls
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_dress_mesh_watertight_untrimmed_and_trimmed_hugs_the_data():
    pts, _ = _dress(6000)
    reference, _ = _dress(200_000, seed=1)  # dense sample of the true surface
    verts0, faces0 = mesh_from_points(pts, None, depth=7, density_quantile=0.0)
    assert is_watertight(verts0, faces0)  # Poisson closes the open hem
    d0 = _dist_to(verts0, reference)
    assert (d0 > 0.05).any()  # ... with a cap far from any sample
    verts, faces = mesh_from_points(pts, None, depth=7, density_quantile=0.05)
    d = _dist_to(verts, reference)
    height = 1.3  # the cap is gone; what is left hugs the surface (sample spacing here ~1 cm)
    assert np.median(d) < 0.002 * height and np.quantile(d, 0.99) < 0.035 * height and d.max() < 0.05 * height, (
        np.quantile(d, [0.5, 0.99, 1]), np.quantile(d0, [0.5, 0.99, 1]))
    assert np.quantile(d0, 0.99) > 3 * np.quantile(d, 0.99)
    assert len(faces) < len(faces0) and not is_watertight(verts, faces)


# ----------------------------------------------------------------------------- mesh clean-up
def test_cancel_face_pairs_matches_a_reference():
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    fin = np.array([[1, 2, 4], [2, 1, 4]])  # same triangle, opposite windings: both go
    twin = np.array([[0, 1, 3], [1, 3, 0]])  # same winding twice: one stays
    out = _cancel_face_pairs(np.concatenate([tet, fin, twin]))
    key = {tuple(np.roll(f, -int(np.argmin(f)))) for f in out}
    assert len(out) == 4 and key == {tuple(np.roll(f, -int(np.argmin(f)))) for f in tet}
    assert _cancel_face_pairs(tet) is tet


def test_drop_small_components_keeps_the_big_ones():
    big = trimesh.creation.icosphere(2)  # 320 faces
    small = trimesh.creation.icosphere(0)  # 20 faces
    faces = np.concatenate([big.faces, small.faces + len(big.vertices)])
    n = len(big.vertices) + len(small.vertices)
    assert len(_drop_small_components(faces, n, 0.1)) == 320
    assert len(_drop_small_components(faces, n, 0.05)) == 340
    assert len(_drop_small_components(faces, n, 0.0)) == 340


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "points, message",
    [
        (np.zeros((0, 3)), "point cloud is empty"),
        (_sphere(MIN_POINTS - 1), "too sparse to mesh: 99 points"),
        (np.where(np.arange(300)[:, None] == 7, np.nan, _sphere(300)), "1 row(s) with NaN"),
        (np.zeros((200, 2)), "points must have shape (N, 3)"),
        (np.c_[np.linspace(0, 1, 200), np.zeros((200, 2))], "degenerate"),
    ],
)
def test_bad_points_raise_one_line(points, message):
    with pytest.raises(ValueError) as e:
        mesh_from_points(points)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_bad_normals_and_options_raise_one_line():
    pts = _sphere(300)
    for kwargs, message in [
        (dict(normals=np.ones((10, 3))), "normals must have shape (300, 3)"),
        (dict(normals=np.zeros((300, 3))), "zero-length"),
        (dict(depth=0), "depth must be in 1..12"),
        (dict(density_quantile=1.0), "density quantile must be in [0, 1)"),
    ]:
        with pytest.raises(ValueError, match=None) as e:
            mesh_from_points(pts, **kwargs)
        assert message in str(e.value) and "\n" not in str(e.value)


# ----------------------------------------------------------------------------- CLI
def test_cli_meshes_a_cloud_without_normals(tmp_path, capsys):
    src = tmp_path / "ball.ply"
    write_ply(src, _sphere(2000))
    out, png = tmp_path / "ball_mesh.ply", tmp_path / "ball.png"
    assert main(["mesh", str(src), "--depth", "6", "--render", str(png)]) == 0, capsys.readouterr().err
    msg = capsys.readouterr().out
    assert "watertight" in msg and "NOT" not in msg and str(out) in msg
    mesh = read_ply(out)
    assert mesh.faces is not None and mesh.normals is not None
    assert is_watertight(mesh.points, mesh.faces)
    # vertex normals point outwards
    assert (np.sum(mesh.normals * mesh.points, axis=1) > 0).mean() > 0.99
    assert png.stat().st_size > 5000


def test_cli_orients_by_the_pose_given_with_joints(tmp_path, capsys):
    """``pocoloco mesh CLOUD --joints POSE`` (no --refine-body) meshes with skeleton-oriented normals."""
    J, pts, _ = _limbs(4000)
    write_ply(tmp_path / "limbs.ply", pts)
    np.save(tmp_path / "j.npy", J.astype(np.float32))
    out = tmp_path / "m.ply"
    argv = ["mesh", str(tmp_path / "limbs.ply"), "--joints", str(tmp_path / "j.npy"), "--depth", "7", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    assert "watertight" in capsys.readouterr().out and read_ply(out).faces is not None
    assert main([*argv[:3], str(tmp_path / "nope.npy"), *argv[4:]]) == 2
    assert "nope.npy" in capsys.readouterr().err


@pytest.mark.parametrize(
    "content, message",
    [
        (b"not a ply file", "not a PLY file"),
        (None, "no such file"),
        ("sparse", "too sparse to mesh"),
        ("nan", "non-finite vertex coordinates"),
    ],
)
def test_cli_bad_input_one_line_and_nothing_written(tmp_path, capsys, content, message):
    src = tmp_path / "in.ply"
    if content == "sparse":
        write_ply(src, _sphere(50))
    elif content == "nan":
        pts = _sphere(500)
        pts[3, 1] = np.nan
        write_ply(src, pts)
    elif content is not None:
        src.write_bytes(content)
    out = tmp_path / "out.ply"
    assert main(["mesh", str(src), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pocoloco: error:") and message in err and "\n" not in err, err
    assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == (["in.ply"] if content is not None else [])


def test_cli_refuses_to_overwrite_the_input(tmp_path, capsys):
    src = tmp_path / "in.ply"
    write_ply(src, _sphere(500))
    assert main(["mesh", str(src), "--out", str(src)]) == 2
    assert "overwrite the input" in capsys.readouterr().err


# ----------------------------------------------------------------------- body refinement
def test_replace_parts_takes_part_points_from_the_body():
    from pocoloco.apps.meshing import replace_parts, sample_faces

    # the "body": an icosphere; its "head" = the vertices above z = 0.3 (a cap)
    ico = trimesh.creation.icosphere(subdivisions=3, radius=R)
    verts, faces = np.asarray(ico.vertices), np.asarray(ico.faces)
    part = verts[:, 2] > 0.3
    # the "cloud": the sphere 1 cm outside the body, plus a far stray point above the cap
    cloud = _sphere(3000, seed=1) * 1.02
    cloud = np.concatenate([cloud, [[0.0, 0.0, 0.9]]])
    pts, nrm, from_body, body_nrm = replace_parts(cloud, None, verts, faces, part, margin=0.06, seed=0)
    assert nrm is None and from_body.dtype == bool and len(pts) == len(from_body)
    near = _dist_to(cloud, verts)
    nearest_part = part[trimesh.proximity.ProximityQuery(ico).vertex(cloud)[1]]
    removed = nearest_part & (near < 0.06)
    kept = pts[~from_body]
    np.testing.assert_array_equal(kept, cloud[~removed].astype(np.float32))  # the others are untouched, in order
    assert np.allclose(kept[-1], [0.0, 0.0, 0.9])  # beyond the margin: kept
    body_pts = pts[from_body]
    assert len(body_pts) >= removed.sum() and len(body_pts) == len(body_nrm)
    # body points lie on the body's cap faces (z > 0.3 - one edge), with outward unit normals
    on_surface = np.abs(np.linalg.norm(body_pts, axis=1) - R)
    assert on_surface.max() < 0.01 and body_pts[:, 2].min() > 0.3 - 0.1
    np.testing.assert_allclose(np.linalg.norm(body_nrm, axis=1), 1.0, atol=1e-5)
    assert (np.sum(body_nrm * body_pts, axis=1) > 0).all()
    # area-uniform sampling: the cap's points spread like the area (mean height of a uniform cap)
    p, _ = sample_faces(verts, faces[part[faces].all(1)], 20000, seed=3)
    assert abs(p[:, 2].mean() - (R + p[:, 2].min()) / 2) < 0.01


@pytest.fixture(scope="module")
def posed_anny():
    """A posed anny body with known, non-average shape and a cloud sampled on it."""
    from pocoloco.apps.meshing import sample_faces
    from pocoloco.body.anny_body import AnnyBody

    rng = np.random.default_rng(0)
    body = AnnyBody({"weight": 0.8, "height": 0.3, "proportions": 0.7})
    rot = 0.25 * rng.normal(size=(24, 3)).astype(np.float32)
    rot[0] = [0.0, 0.0, 0.3]
    posed = body.pose(rot, root_translation=np.array([0.1, -0.2, 1.0], np.float32))
    pts, _ = sample_faces(posed.vertices[0], body.faces, 4000, seed=1)
    return pts, posed.joints[0], posed.vertices[0], body.faces


def test_body_fit_meets_the_joints_and_the_surface_fit_reduces_the_error(posed_anny):
    import torch

    from pocoloco.body.anny_body import fit_body_to_cloud

    torch.set_num_threads(1)
    pts, joints, true_verts, faces = posed_anny
    fit = fit_body_to_cloud(pts, joints, joint_steps=60, surface_steps=40, lr=0.03)
    assert fit.vertices.shape == true_verts.shape and fit.faces.shape == faces.shape
    assert fit.joint_error_cm < 2.0, fit.joint_error_cm
    # the surface stage (head and hands vs. the cloud) improves on the pose-from-joints fit
    assert fit.part_error_cm < 0.9 * fit.part_error_cm_initial, (fit.part_error_cm_initial, fit.part_error_cm)
    # and the fitted head/hands are closer to the true body's than the average-shape start
    d = _dist_to(fit.vertices[fit.part_vertices], true_verts).mean()
    assert d < 0.02, d
    assert fit.losses[-1] < fit.losses[60]


def test_cli_refine_body_writes_a_watertight_mesh_and_the_body(tmp_path, capsys, posed_anny):
    pts, joints, _, _ = posed_anny
    src = tmp_path / "cloud.ply"
    write_ply(src, pts[::2])
    np.save(tmp_path / "j.npy", joints)
    out = tmp_path / "m.ply"
    argv = ["mesh", str(src), "--refine-body", "--joints", str(tmp_path / "j.npy"), "--fit-steps", "5", "--depth",
            "7", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    msg = capsys.readouterr().out
    assert "fitted anny" in msg and "head/hands Chamfer" in msg and "watertight" in msg and "NOT" not in msg, msg
    body = read_ply(tmp_path / "m_body.ply")
    assert body.faces is not None and len(body.points) > 10000  # the whole anny mesh
    mesh = read_ply(out)
    assert mesh.faces is not None and len(mesh.faces) > 1000 and is_watertight(mesh.points, mesh.faces)


@pytest.mark.parametrize(
    "joints, message",
    [(None, "--refine-body needs --joints"), ("j17.npy", "expected joints of shape (24, 3), got (17, 3)"),
     ("far.npy", "m from the pose's root joint")],
)  # fmt: skip
def test_cli_refine_body_bad_joints_one_line_nothing_written(tmp_path, capsys, joints, message):
    src = tmp_path / "in.ply"
    write_ply(src, _sphere(500) + [0, 0, 1.0])
    np.save(tmp_path / "j17.npy", np.zeros((17, 3)))
    from pocoloco.data.poses import load_joints

    np.save(tmp_path / "far.npy", load_joints("demo:tight") + 10.0)  # a body, 10 m from the cloud
    argv = ["mesh", str(src), "--refine-body", "--out", str(tmp_path / "o.ply")]
    if joints:
        argv += ["--joints", str(tmp_path / joints)]
    before = sorted(os.listdir(tmp_path))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("pocoloco: error:") and message in err and "\n" not in err, err
    assert sorted(os.listdir(tmp_path)) == before


def test_split_nonmanifold_edges_makes_two_tetrahedra_sharing_an_edge_watertight():
    from pocoloco.apps.meshing import _split_nonmanifold_edges

    # two closed tetrahedra touching along the edge (0, 1): that edge is used by four faces
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0.2], [0.5, 0.3, 1], [0.5, -1, 0.2], [0.5, -0.3, -1]], np.float32)
    tet = lambda a, b, c, d: [[a, c, b], [a, b, d], [a, d, c], [b, c, d]]  # noqa: E731
    faces = np.array(tet(0, 1, 2, 3) + tet(0, 1, 4, 5))
    if trimesh.Trimesh(v, faces[:4], process=False).volume < 0:
        faces[:4] = faces[:4, ::-1]
    if trimesh.Trimesh(v, faces[4:], process=False).volume < 0:
        faces[4:] = faces[4:, ::-1]
    assert not is_watertight(v, faces)
    v2, f2 = _split_nonmanifold_edges(v, faces)
    assert is_watertight(v2, f2) and len(v2) == len(v) + 2 and f2.shape == faces.shape
    np.testing.assert_array_equal(v2[f2], v[faces])  # same triangles, geometrically
    # a manifold mesh is returned unchanged
    v3, f3 = _split_nonmanifold_edges(v, faces[:4])
    assert v3 is v and np.array_equal(f3, faces[:4])
