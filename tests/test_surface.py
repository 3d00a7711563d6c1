"""Body-surface machinery: UV rasterisation vs a slow reference, position maps,
barycentric sampling, local frames (pocoloco.body.surface)."""

import numpy as np
import pytest
import torch

from pocoloco.body import NUM_JOINTS, AnnyBody
from pocoloco.body.surface import (
    BodySurface,
    SurfacePoints,
    barycentric_interpolate,
    blend_transforms,
    largest_component_faces,
    mean_shape_body,
    pixel_uv,
    pose_mean_shape,
    position_map,
    rasterize_uv,
    rasterize_uv_reference,
    sample_surface_points,
    uv_island_labels,
    uv_to_grid,
)
from pocoloco.ops import sample_surface


@pytest.fixture(scope="module")
def body():
    return AnnyBody({"gender": 0.3, "height": 0.6})


@pytest.fixture(scope="module")
def posed(body):
    """Two frames: zero pose and a random pose, both with the root turned."""
    rng = np.random.default_rng(3)
    rot = rng.normal(scale=0.25, size=(2, NUM_JOINTS, 3)).astype(np.float32)
    rot[0] = 0
    return body.pose(rot)


def _rotz(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)


def _assert_same_raster(a, b):
    assert a.resolution == b.resolution
    np.testing.assert_array_equal(a.face_idx, b.face_idx)
    np.testing.assert_array_equal(a.coverage, b.coverage)
    np.testing.assert_allclose(a.barycentric, b.barycentric, atol=1e-6)


# ---------------------------------------------------------------------------
# rasterisation
# ---------------------------------------------------------------------------


def test_rasterizer_matches_reference_on_random_triangles():
    """Overlapping, clockwise, degenerate and partly off-texture triangles."""
    rng = np.random.default_rng(0)
    uv = rng.uniform(-0.2, 1.2, size=(30, 2))
    uv_faces = rng.integers(0, 30, size=(12, 3))
    uv_faces[3] = [5, 5, 7]  # degenerate
    uv_faces[4] = uv_faces[2, ::-1]  # same triangle, other winding: covers the same pixels
    for R in (1, 7, 13):
        fast, ref = rasterize_uv(uv, uv_faces, R, chunk=5), rasterize_uv_reference(uv, uv_faces, R)
        _assert_same_raster(fast, ref)
    assert fast.num_overlapping > 0 and not (fast.face_idx == 3).any() and not (fast.face_idx == 4).any()
    m = fast.mask
    assert np.allclose(fast.barycentric[m].sum(-1), 1, atol=1e-6) and (fast.barycentric >= 0).all()
    assert (fast.barycentric[~m] == 0).all() and (fast.face_idx[~m] == -1).all()


def test_unit_square_tiling_ties_go_to_the_lowest_face():
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    # diagonal (0,0)-(1,1): pixel centres with i + j = R - 1 lie exactly on it
    r = rasterize_uv(uv, np.array([[0, 1, 2], [0, 2, 3]]), 8)
    assert r.num_valid == 64 and r.num_overlapping == 8
    i, j = np.nonzero(r.coverage == 2)
    assert (i + j == 7).all() and (r.face_idx[i, j] == 0).all()
    # upper-left half of the image is v > u: face 1
    assert r.face_idx[0, 0] == 1 and r.face_idx[7, 7] == 0
    # a fan around (0.3, 0.6): no pixel centre on an edge at R = 8 -> a clean partition
    fan = np.concatenate([uv, [[0.3, 0.6]]])
    r2 = rasterize_uv(fan, np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]), 8)
    assert r2.num_valid == 64 and r2.num_overlapping == 0 and len(np.unique(r2.face_idx)) == 4
    _assert_same_raster(r2, rasterize_uv_reference(fan, np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]), 8))


def test_pixel_centre_convention():
    assert np.allclose(pixel_uv(np.array([[0, 0], [3, 1]]), 4), [[0.125, 0.875], [0.375, 0.125]])
    # a tiny triangle around UV (0.625, 0.125) covers exactly pixel (i, j) = (3, 2) at R = 4
    uv = np.array([[0.6, 0.1], [0.65, 0.1], [0.62, 0.15]])
    r = rasterize_uv(uv, np.array([[0, 1, 2]]), 4)
    assert r.num_valid == 1 and r.face_idx[3, 2] == 0


def test_anny_raster_matches_reference(body):
    for R in (5, 16):
        _assert_same_raster(rasterize_uv(body.uv, body.uv_faces, R), rasterize_uv_reference(body.uv, body.uv_faces, R))
    a = rasterize_uv(body.uv, body.uv_faces, 48)
    _assert_same_raster(a, rasterize_uv(body.uv, body.uv_faces, 48, chunk=777))  # chunking is invisible


def test_anny_uv_layout_has_no_overlaps(body):
    uvt = body.uv[body.uv_faces].astype(np.float64)
    e1, e2 = uvt[:, 1] - uvt[:, 0], uvt[:, 2] - uvt[:, 0]
    area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert (area > 0).all()  # no flipped or degenerate UV triangles
    r = rasterize_uv(body.uv, body.uv_faces, 256)
    assert r.num_overlapping == 0 and r.coverage.max() == 1
    assert abs(r.num_valid / 256**2 - area.sum()) < 0.01  # covered fraction ~ total UV area


def test_uv_islands(body):
    lab = uv_island_labels(body.uv_faces)
    assert lab.max() + 1 == 14 and lab[0] == 0
    sizes = np.bincount(lab)
    assert sorted(sizes.tolist()) == [70, 70, 70, 70, 448, 586, 586, 796, 2144, 2144, 3196, 3196, 6232, 7812]
    # islands never mix 3D components (the body component's islands are the big ones)
    keep = largest_component_faces(body.faces)
    assert all(len(np.unique(keep[lab == k])) == 1 for k in range(14))
    assert np.array_equal(uv_island_labels(np.array([[0, 1, 2], [5, 6, 7], [2, 3, 4]])), [0, 1, 0])


def test_raster_barycentrics_reproduce_pixel_uv(body):
    r = rasterize_uv(body.uv, body.uv_faces, 64)
    pts = r.points()
    uv = np.einsum("pk,pkc->pc", pts.barycentric.astype(np.float64), body.uv[body.uv_faces[pts.face_idx]])
    assert np.abs(uv - r.uv()).max() < 1e-6
    s = BodySurface(body.faces, body.uv, body.uv_faces)
    assert np.abs(s.points_uv(pts) - r.uv()).max() < 1e-6


def test_body_only_surface_drops_eyes_and_mouth(body):
    keep = largest_component_faces(body.faces)
    assert keep.sum() == 26692 and len(keep) == 27420  # anny 0.6: body + 2 eyeballs + mouth interior
    s = BodySurface.from_body(body)
    r = s.raster(64)
    assert s.raster(64) is r  # cached
    full = rasterize_uv(body.uv, body.uv_faces, 64)
    assert keep[r.face_idx[r.mask]].all() and 0 < full.num_valid - r.num_valid < 0.02 * full.num_valid
    assert (full.face_idx[r.mask] == r.face_idx[r.mask]).all()


# ---------------------------------------------------------------------------
# position maps, interpolation, frames
# ---------------------------------------------------------------------------


def test_position_map_is_the_barycentric_blend(body, posed):
    r = rasterize_uv(body.uv, body.uv_faces, 32)
    verts = np.stack([body.template, posed.vertices[1]])  # (2, V, 3)
    pm = position_map(torch.from_numpy(verts), body.faces, r)
    assert pm.maps.shape == (2, 3, 32, 32) and pm.maps.dtype == torch.float32
    assert torch.equal(pm.mask, torch.from_numpy(r.mask))
    assert (pm.maps[:, :, ~pm.mask] == 0).all()
    rng = np.random.default_rng(1)
    ii, jj = np.nonzero(r.mask)
    for k in rng.choice(len(ii), 20, replace=False):
        i, j = ii[k], jj[k]
        f, w = r.face_idx[i, j], r.barycentric[i, j].astype(np.float64)
        for b in range(2):
            expect = w @ verts[b, body.faces[f]]
            assert np.abs(pm.maps[b, :, i, j].numpy() - expect).max() < 1e-6


def test_uv_to_grid_samples_pixel_centres(body):
    r = rasterize_uv(body.uv, body.uv_faces, 16)
    pm = position_map(torch.from_numpy(body.template[None]), body.faces, r).maps  # (1, 3, R, R)
    grid = uv_to_grid(torch.from_numpy(r.uv()))[None, None]  # (1, 1, P, 2)
    got = torch.nn.functional.grid_sample(pm, grid, align_corners=False)[0, :, 0].T  # (P, 3)
    assert torch.allclose(got, pm[0][:, pm.new_tensor(r.mask).bool()].T, atol=1e-6)


def test_interpolating_vertices_gives_the_sampled_points(body):
    s = sample_surface(body.template, body.faces, 500, seed=4)
    pts = sample_surface_points(body.template, body.faces, 500, seed=4)
    assert np.array_equal(pts.face_idx, s.face_idx) and len(pts) == 500
    got = barycentric_interpolate(torch.from_numpy(body.template[None]), body.faces, pts.face_idx, pts.barycentric)
    assert got.shape == (1, 500, 3) and np.abs(got[0].numpy() - s.points).max() < 1e-6


def test_barycentric_interpolate_matches_loop_and_has_gradients():
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(2, 9, 4, generator=g, dtype=torch.float64, requires_grad=True)
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 8], [7, 8, 0]])
    fid = torch.tensor([[0, 3, 3, 2, 1], [1, 1, 0, 2, 3]])
    w = torch.rand(2, 5, 3, generator=g, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True)
    out = barycentric_interpolate(feats, faces, fid, w)  # per-batch face ids
    ref = torch.zeros(2, 5, 4, dtype=torch.float64)
    for b in range(2):
        for p in range(5):
            for k in range(3):
                ref[b, p] += w[b, p, k] * feats[b, faces[fid[b, p], k]]
    assert torch.allclose(out, ref)
    shared = barycentric_interpolate(feats, faces, fid[0], w[0])  # (P,) ids shared by the batch
    assert torch.allclose(shared[0], out[0])
    shared.sum().backward()
    grad = torch.zeros(9, dtype=torch.float64)
    for p in range(5):
        for k in range(3):
            grad[faces[fid[0, p], k]] += w[0, p, k]
    assert torch.allclose(feats.grad, grad[None, :, None].expand(2, 9, 4))
    x = feats.detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: barycentric_interpolate(x, faces, fid, w), (x,))


def test_frames_of_an_unposed_body_are_identity(body, posed):
    P = 300
    pts = sample_surface_points(body.template, body.faces, P, seed=2)
    eye = torch.eye(3).expand(1, body.num_vertices, 3, 3)  # bind pose: vtransf = I by definition
    for mode in ("blend", "polar"):
        t = blend_transforms(eye, body.faces, pts.face_idx, pts.barycentric, mode=mode)
        assert t.shape == (1, P, 3, 3) and torch.allclose(t, torch.eye(3).expand_as(t), atol=1e-6)
    # anny's zero pose is not quite its bind pose (bones tilt by up to ~0.1 rad), so its
    # frames are near-identity, the polar ones exact rotations
    vt = torch.from_numpy(posed.vtransf[:1])
    for mode in ("blend", "polar"):
        t = blend_transforms(vt, body.faces, pts.face_idx, pts.barycentric, mode=mode)
        assert 0 < (t - torch.eye(3)).abs().max() < 0.12


def test_rigid_root_rotation_rotates_frames(body, posed):
    theta = 0.9
    rot = np.zeros((1, NUM_JOINTS, 3), np.float32)
    rot[0, 0, 2] = theta
    turned = body.pose(rot)
    s = BodySurface.from_body(body)
    pts = s.raster(32).points()
    r = torch.from_numpy(_rotz(theta))
    for mode in ("blend", "polar"):
        t0 = s.frames(torch.from_numpy(posed.vtransf[:1]), pts, mode)
        t1 = s.frames(torch.from_numpy(turned.vtransf), pts, mode)
        assert (t1 - r @ t0).abs().max() < 2e-4
    p0 = s.interpolate(torch.from_numpy(posed.vertices[:1]), pts)
    p1 = s.interpolate(torch.from_numpy(turned.vertices), pts)
    root = torch.from_numpy(posed.joints[0, 0])
    assert ((p1 - root) - (p0 - root) @ r.T).abs().max() < 2e-4


def test_polar_frames_are_rotations_close_to_the_blend(body, posed):
    pts = sample_surface_points(body.template, body.faces, 400, seed=5)
    vt = torch.from_numpy(posed.vtransf)
    blend = blend_transforms(vt, body.faces, pts.face_idx, pts.barycentric)
    polar = blend_transforms(vt, body.faces, pts.face_idx, pts.barycentric, mode="polar")
    eye = torch.eye(3).expand_as(polar)
    assert torch.allclose(polar @ polar.transpose(-1, -2), eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(polar), torch.ones(polar.shape[:2]), atol=1e-5)
    assert (polar - blend).abs().max() < 0.3  # LBS blends are near-rotations
    rigid = torch.from_numpy(np.stack([_rotz(0.3), _rotz(-1.0)]))[:, None].expand(2, body.num_vertices, 3, 3)
    same = blend_transforms(rigid, body.faces, pts.face_idx, pts.barycentric, mode="polar")
    assert torch.allclose(same, rigid[:, :400], atol=1e-5)  # a rotation is its own polar factor


def test_query_points_reused_across_frames(body, posed):
    s = BodySurface.from_body(body)
    pts = s.sample(body.template, 256, seed=0)
    assert isinstance(pts, SurfacePoints) and s.face_mask[pts.face_idx].all()
    out = s.interpolate(torch.from_numpy(posed.vertices), pts)  # (2, P, 3): one draw, every frame
    for b in range(2):
        expect = np.einsum("pk,pkc->pc", pts.barycentric, posed.vertices[b][body.faces[pts.face_idx]])
        assert np.abs(out[b].numpy() - expect).max() < 1e-5


def test_mean_shape_body_poses_like_the_subject(body):
    mean = mean_shape_body()
    assert mean is mean_shape_body() and set(mean.phenotype.values()) == {0.5}
    rot = np.zeros((1, NUM_JOINTS, 3), np.float32)
    rot[0, 0, 2] = 0.5
    out = pose_mean_shape(rot)
    assert out.vertices.shape == (1, body.num_vertices, 3)
    assert np.abs(out.vertices[0] - mean.pose(rot).vertices[0]).max() == 0
    assert np.abs(out.vertices[0] - body.pose(rot).vertices[0]).max() > 1e-3  # a different shape


def test_bad_input_is_rejected(body):
    with pytest.raises(ValueError, match="resolution"):
        rasterize_uv(body.uv, body.uv_faces, 0)
    with pytest.raises(ValueError, match="uv_faces index"):
        rasterize_uv(body.uv, body.uv_faces + len(body.uv), 8)
    with pytest.raises(ValueError, match="uv must be"):
        rasterize_uv(body.uv[:, :1], body.uv_faces, 8)
    with pytest.raises(ValueError, match="face_mask"):
        rasterize_uv(body.uv, body.uv_faces, 8, face_mask=np.ones(3, bool))
    v = torch.zeros(1, body.num_vertices, 3)
    with pytest.raises(ValueError, match="face_idx outside"):
        barycentric_interpolate(v, body.faces, np.array([len(body.faces)]), np.ones((1, 3)) / 3)
    with pytest.raises(ValueError, match="barycentric must have shape"):
        barycentric_interpolate(v, body.faces, np.array([0, 1]), np.ones((1, 3)) / 3)
    with pytest.raises(ValueError, match="vertices must have shape"):
        position_map(v[0], body.faces, rasterize_uv(body.uv, body.uv_faces, 4))
    with pytest.raises(ValueError, match="mode"):
        blend_transforms(torch.zeros(1, body.num_vertices, 3, 3), body.faces, np.array([0]), np.ones((1, 3)) / 3, "qr")


def test_uvmap_command_writes_tables_and_rejects_bad_input(body, tmp_path, capsys):
    from pocoloco.cli import main

    out, png = tmp_path / "uv32.npz", tmp_path / "uv32.png"
    assert main(["uvmap", "--resolution", "32", "--phenotype", "gender=0.3", "height=0.6", "--out", str(out),
                 "--png", str(png)]) == 0  # fmt: skip
    d = np.load(out)
    s = BodySurface.from_body(body)
    r = s.raster(32)
    assert np.array_equal(d["face_idx"], r.face_idx) and np.array_equal(d["mask"], r.mask)
    pm = s.position_map(torch.from_numpy(body.template[None]), 32).maps[0].permute(1, 2, 0).numpy()
    assert np.allclose(d["posmap"], pm) and png.stat().st_size > 0
    assert "valid pixels" in capsys.readouterr().out
    for bad in (["--resolution", "0"], ["--phenotype", "gender"], ["--phenotype", "size=0.2"]):
        bad_out = tmp_path / "bad.npz"
        assert main(["uvmap", *bad, "--out", str(bad_out)]) == 2
        assert not bad_out.exists()
    assert "error:" in capsys.readouterr().err
