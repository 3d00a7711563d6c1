"""Tests of the virtual multi-view capture (pocoloco.synth.capture)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pocoloco.synth.capture import (
    LABEL_BODY,
    LABEL_GARMENT,
    CaptureMesh,
    CaptureSettings,
    ScanFrame,
    _Surface,
    _visibility_reference,
    camera_centres,
    capture_frame,
    loose_share,
    open_tube,
    possibly_visible_faces,
    visibility,
)

pytest.importorskip("open3d")


def _sphere(radius: float, part: int, subdivisions: int = 4, label: int = LABEL_BODY) -> CaptureMesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return CaptureMesh(np.asarray(m.vertices), np.asarray(m.faces), label, np.full(len(m.faces), part))


def _cylinder_and_tube() -> tuple[CaptureMesh, CaptureMesh]:
    """A closed body-like cylinder (r 0.15, z in [-0.8, 0.8]) and an open tube
    around its middle (r 0.2, z in [-0.4, 0.4]): a tight skirt with a 5 cm gap."""
    cyl = trimesh.creation.cylinder(radius=0.15, height=1.6, sections=48)
    cyl = cyl.subdivide().subdivide()
    body = CaptureMesh(np.asarray(cyl.vertices), np.asarray(cyl.faces), LABEL_BODY, np.full(len(cyl.faces), 3))
    tv, tf = open_tube(0.4, -0.4, (0.2, 0.2), (0.2, 0.2), n_around=64, n_down=12)
    return body, CaptureMesh(tv, tf, LABEL_GARMENT, None)


def test_inner_sphere_is_not_captured():
    for outer_label in (LABEL_BODY, LABEL_GARMENT):  # closed one-sided, and closed two-sided "cloth"
        scan = capture_frame([_sphere(0.5, part=1), _sphere(1.0, part=2, label=outer_label)],
                             CaptureSettings(num_points=5000))
        assert isinstance(scan, ScanFrame) and scan.points.shape == (5000, 3)
        r = np.linalg.norm(scan.points, axis=1)
        assert r.min() > 0.98, "points of the hidden inner sphere were captured"
        if outer_label == LABEL_BODY:
            assert set(np.unique(scan.parts)) == {2}
        # normals of a closed mesh point outwards, even for two-sided faces (the inside is never seen)
        cos = np.einsum("ij,ij->i", scan.normals, scan.points / r[:, None])
        assert cos.min() > 0.99


def test_output_types_and_unit_normals():
    scan = capture_frame([_sphere(0.5, part=5)], CaptureSettings(num_points=2000))
    assert scan.points.dtype == np.float32 and scan.normals.dtype == np.float32
    assert scan.labels.dtype == np.uint8 and scan.parts.dtype == np.int8
    np.testing.assert_allclose(np.linalg.norm(scan.normals, axis=1), 1.0, atol=1e-5)
    assert (scan.labels == LABEL_BODY).all() and (scan.parts == 5).all()
    # points lie on the (triangulated) sphere
    r = np.linalg.norm(scan.points, axis=1)
    assert r.max() <= 0.5 + 1e-5 and r.min() > 0.49


def test_skirt_hides_the_covered_body_and_shows_both_cloth_sides():
    body, tube = _cylinder_and_tube()
    scan = capture_frame([body, tube], CaptureSettings(num_points=20000))
    p, n, lab = scan.points, scan.normals, scan.labels
    radial = p[:, :2] / np.maximum(np.linalg.norm(p[:, :2], axis=1, keepdims=True), 1e-9)
    is_body, is_tube = lab == LABEL_BODY, lab == LABEL_GARMENT
    assert (scan.parts[is_tube] == -1).all() and (scan.parts[is_body] == 3).all()
    # the body wall deep under the tube is seen by no camera
    body_wall = is_body & (np.abs(p[:, 2]) < 0.79)
    assert body_wall.sum() > 1000
    assert not (body_wall & (np.abs(p[:, 2]) < 0.15)).any()
    # ... while it is captured above and below the tube
    assert (body_wall & (p[:, 2] > 0.5)).sum() > 500 and (body_wall & (p[:, 2] < -0.5)).sum() > 500
    # the tube: outer side everywhere, inner side near the openings (seen from below/above)
    out = is_tube & (np.einsum("ij,ij->i", n[:, :2], radial) > 0.9)
    inner = is_tube & (np.einsum("ij,ij->i", n[:, :2], radial) < -0.9)
    assert out.sum() > 3000 and inner.sum() > 200
    assert (p[inner, 2] < -0.3).any() and (p[inner, 2] > 0.3).any()
    # (the inner side is seen across the opening, so mostly near the ends)
    assert (inner & (np.abs(p[:, 2]) > 0.3)).sum() > 3 * (inner & (np.abs(p[:, 2]) < 0.1)).sum()
    # tube points lie on the tube, body points on the cylinder
    np.testing.assert_allclose(np.linalg.norm(p[is_tube, :2], axis=1), 0.2, atol=2e-3)
    # normals of the closed cylinder point outwards
    wall = body_wall & (np.abs(n[:, 2]) < 0.5)
    assert (np.einsum("ij,ij->i", n[wall, :2], radial[wall]) > 0.99).all()
    share = loose_share(lab)
    assert 0.0 < share < 100.0 and share == pytest.approx(100.0 * is_tube.mean())


def test_density_is_uniform_over_the_visible_surface():
    # equal-area spherical caps facing different cameras get the same number of points
    scan = capture_frame([_sphere(1.0, part=0)], CaptureSettings(num_points=40000, seed=3))
    p = scan.points / np.linalg.norm(scan.points, axis=1, keepdims=True)
    caps = [(p[:, 2] > 0.5).sum(), (p[:, 2] < -0.5).sum(), (p[:, 0] > 0.5).sum(), (p[:, 1] < -0.5).sum()]
    expected = 40000 * 0.25  # a cap of height 0.5 on a unit sphere has a quarter of the area
    for c in caps:
        assert abs(c - expected) < 5 * np.sqrt(expected), caps


def test_density_does_not_follow_the_tessellation():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    plus_x = np.flatnonzero(box.face_normals[:, 0] > 0.9)
    for _ in range(4):  # +X face gets 2 * 4**4 triangles, -X keeps 2
        box = box.subdivide(face_index=np.flatnonzero(box.face_normals[:, 0] > 0.9))
    assert (box.face_normals[:, 0] > 0.9).sum() == 2 * 4**4 and len(plus_x) == 2
    mesh = CaptureMesh(np.asarray(box.vertices), np.asarray(box.faces), LABEL_BODY, None)
    scan = capture_frame([mesh], CaptureSettings(num_points=12000))
    on_plus = (scan.points[:, 0] > 0.499).sum()
    on_minus = (scan.points[:, 0] < -0.499).sum()
    assert abs(on_plus - 2000) < 200 and abs(on_minus - 2000) < 200, (on_plus, on_minus)
    assert (scan.parts == -1).all()


def test_deterministic_for_a_fixed_seed():
    body, tube = _cylinder_and_tube()
    s = CaptureSettings(num_points=3000, seed=7, noise_std=1e-3)
    a, b = capture_frame([body, tube], s), capture_frame([body, tube], s)
    for f in ("points", "normals", "labels", "parts"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    c = capture_frame([body, tube], CaptureSettings(num_points=3000, seed=8, noise_std=1e-3))
    assert not np.array_equal(a.points, c.points)


def test_noise_is_along_the_normal_with_the_given_std():
    scan = capture_frame([_sphere(1.0, part=0, subdivisions=5)], CaptureSettings(num_points=20000, noise_std=0.01))
    offset = np.linalg.norm(scan.points, axis=1) - 1.0  # icosphere is within 0.1 mm of the sphere
    assert abs(offset.mean()) < 1e-3 and offset.std() == pytest.approx(0.01, rel=0.05)


def test_rig_moves_with_the_subject():
    body, tube = _cylinder_and_tube()
    s = CaptureSettings(num_points=3000, seed=1)
    a = capture_frame([body, tube], s)
    shift = np.array([3.0, -2.0, 0.5])
    moved = [CaptureMesh(m.vertices + shift, m.faces, m.label, m.face_part) for m in (body, tube)]
    b = capture_frame(moved, s)
    np.testing.assert_allclose(b.points - shift, a.points, atol=1e-5)
    np.testing.assert_array_equal(a.labels, b.labels)


@pytest.mark.parametrize(
    "meshes, match",
    [
        ([], "empty"),
        ([CaptureMesh(np.zeros((4, 2)), np.array([[0, 1, 2]]), LABEL_BODY, None)], "vertices must have shape"),
        ([CaptureMesh(np.full((3, 3), np.nan), np.array([[0, 1, 2]]), LABEL_BODY, None)], "NaN"),
        ([CaptureMesh(np.eye(3), np.array([[0, 1, 3]]), LABEL_BODY, None)], "out of range"),
        ([CaptureMesh(np.eye(3), np.zeros((0, 3), int), LABEL_BODY, None)], "faces must have shape"),
        ([CaptureMesh(np.eye(3), np.array([[0, 1, 2]]), 7, None)], "label"),
        ([CaptureMesh(np.eye(3), np.array([[0, 1, 2]]), LABEL_BODY, np.zeros(2))], "face_part"),
    ],
)
def test_invalid_input_raises(meshes, match):
    with pytest.raises(ValueError, match=match):
        capture_frame(meshes)


def test_invalid_settings_and_labels_raise():
    with pytest.raises(ValueError, match="num_points"):
        capture_frame([_sphere(1.0, 0, 1)], CaptureSettings(num_points=0))
    with pytest.raises(ValueError, match="noise_std"):
        capture_frame([_sphere(1.0, 0, 1)], CaptureSettings(noise_std=-1.0))
    with pytest.raises(ValueError, match="labels"):
        loose_share(np.zeros(0))
    with pytest.raises(ValueError, match="num_cameras"):
        camera_centres(np.zeros(3), 1.0, 0, -50, 90)


def _first_hit_reference(origin: np.ndarray, direction: np.ndarray, tris: np.ndarray) -> float:
    """Slow, obvious Moller-Trumbore: distance to the first triangle hit (inf if none)."""
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    h = np.cross(direction, e2)
    a = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(a) > 1e-12
    f = 1.0 / np.where(ok, a, 1.0)
    s = origin - tris[:, 0]
    u = f * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = f * (q @ direction)
    t = f * np.einsum("ij,ij->i", e2, q)
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return float(t[hit].min()) if hit.any() else np.inf


def test_visibility_matches_a_brute_force_reference():
    import open3d as o3d

    sphere = _sphere(0.3, part=0, subdivisions=2)
    tv, tf = open_tube(0.2, -0.3, (0.35, 0.35), (0.45, 0.45), n_around=16, n_down=4)
    meshes = [sphere, CaptureMesh(tv, tf, LABEL_GARMENT, None)]
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
    surface = _Surface(meshes)
    face, pts = surface.sample(400, np.random.default_rng(0))
    nrm, side = surface.normal[face], surface.side[face]
    cams = camera_centres(np.zeros(3), 1.5, 6, -50.0, 90.0)
    seen, oriented = visibility(scene, pts, nrm, side, cams, min_cos=0.1, hit_tolerance=1e-4)

    tris = np.concatenate([np.asarray(m.vertices, np.float64)[m.faces] for m in meshes])
    ref = np.zeros(len(pts), bool)
    for i, p in enumerate(pts):
        for c in cams:
            d = p - c
            dist = np.linalg.norm(d)
            cos = float(np.dot(-d / dist, nrm[i]))
            if (abs(cos) if side[i] == 0 else cos) <= 0.1:
                continue
            if _first_hit_reference(c, d / dist, tris) >= dist - 1e-4:
                ref[i] = True
                break
    assert 0.2 < ref.mean() < 0.9  # the scene has both hidden and visible points
    assert (seen == ref).mean() > 0.99  # allow a ray grazing a triangle edge
    # every seen point's oriented normal faces at least one camera
    to_cam = cams[None, :, :] - pts[:, None, :]
    assert (np.einsum("nj,ncj->nc", oriented[seen], to_cam[seen]) > 0).any(axis=1).all()


@pytest.fixture(scope="module")
def anny_body():
    from pocoloco.body import AnnyBody

    return AnnyBody()


def test_naked_anny_body_capture_is_on_and_covers_the_surface(anny_body):
    import open3d as o3d

    b = anny_body
    face_part = b.vertex_joint[b.faces[:, 0]]
    scan = capture_frame([CaptureMesh(b.template, b.faces, LABEL_BODY, face_part)],
                         CaptureSettings(num_points=40000))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(b.template), o3d.core.Tensor(b.faces.astype(np.uint32)))
    dist = scene.compute_distance(o3d.core.Tensor(scan.points)).numpy()
    assert dist.max() < 2e-3
    assert set(np.unique(scan.parts)) <= set(range(24)) and len(np.unique(scan.parts)) >= 20
    # coverage: most of a uniform sample of the whole surface has a captured point within 1.5 cm
    from scipy.spatial import cKDTree

    ref, _ = trimesh.sample.sample_surface(trimesh.Trimesh(b.template, b.faces, process=False), 20000, seed=0)
    d_ref, _ = cKDTree(scan.points).query(np.asarray(ref))
    assert (d_ref < 0.015).mean() > 0.9
    # normals point outwards: a point pushed 1 cm along its normal is outside the body
    occ = scene.compute_occupancy(o3d.core.Tensor(scan.points + 0.01 * scan.normals)).numpy()
    assert occ.mean() < 0.01


def _o3d_scene(meshes):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, np.uint32)))  # fmt: skip
    return scene


def test_fast_visibility_matches_the_reference():
    """The (N, 3) x (3, C) float32 version gives the same answer as the original."""
    body, tube = _cylinder_and_tube()
    meshes = [body, tube]
    scene = _o3d_scene(meshes)
    surface = _Surface(meshes)
    face, pts = surface.sample(6000, np.random.default_rng(0))
    cams = camera_centres(np.zeros(3), 2.5, 16, -30.0, 90.0)
    args = (scene, pts, surface.normal[face], surface.side[face], cams, 0.25, 1e-4)
    seen, oriented = visibility(*args)
    seen_ref, oriented_ref = _visibility_reference(*args)
    assert 0.2 < seen.mean() < 0.9
    assert (seen == seen_ref).mean() > 0.999  # float32 cosines may flip a grazing camera
    both = seen & seen_ref
    np.testing.assert_allclose(oriented[both], oriented_ref[both], atol=1e-6)


def test_capture_stops_early_with_the_same_points(monkeypatch):
    """Testing candidates chunk by chunk and stopping once enough are seen keeps the
    first N visible in draw order: the same frame as testing whole batches."""
    import pocoloco.synth.capture as cap

    meshes = list(_cylinder_and_tube())
    settings = CaptureSettings(num_points=3000, num_cameras=12, seed=5)
    monkeypatch.setattr(cap, "_CAPTURE_CHUNK", 500)
    chunked = capture_frame(meshes, settings)
    monkeypatch.setattr(cap, "_CAPTURE_CHUNK", 10**9)
    whole = capture_frame(meshes, settings)
    for k in ("points", "normals", "labels", "parts"):
        np.testing.assert_array_equal(getattr(chunked, k), getattr(whole, k))


def test_culled_faces_keep_the_visible_surface():
    """Faces dropped by the vertex probes hold (almost) no visible point, and a capture
    with culling has the same garment share as one without."""
    body, tube = _cylinder_and_tube()
    meshes = [body, tube]
    scene = _o3d_scene(meshes)
    surface = _Surface(meshes)
    cams = camera_centres(np.zeros(3), 2.5, 16, -30.0, 90.0)
    keep = possibly_visible_faces(surface, scene, cams, 0.25)
    assert 0.3 < keep.mean() < 0.95  # the covered cylinder middle is dropped
    face, pts = surface.sample(40000, np.random.default_rng(1))
    seen, _ = visibility(scene, pts, surface.normal[face], surface.side[face], cams, 0.25, 1e-4)
    lost = seen & ~keep[face]
    assert lost.sum() <= 0.002 * seen.sum()
    probes = sum(len(v) for v, _, _ in surface.sheets)
    n = probes + 1000  # enough points for the probe pass to run
    on = capture_frame(meshes, CaptureSettings(num_points=n, num_cameras=16, cull_hidden_faces=True))
    off = capture_frame(meshes, CaptureSettings(num_points=n, num_cameras=16))
    assert len(on.points) == len(off.points) == n
    assert abs(loose_share(on.labels) - loose_share(off.labels)) < 1.5
    # the covered middle of the cylinder (seen only through the gap) keeps its share
    mid = lambda f: ((np.abs(f.points[:, 2]) < 0.3) & (f.labels == LABEL_BODY)).mean()
    assert abs(mid(on) - mid(off)) < 0.005
