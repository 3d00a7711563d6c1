"""Point ops: fast implementations against their slow references, gradients, known answers."""

import numpy as np
import pytest
import torch

from pocoloco.ops import (
    ball_query,
    ball_query_reference,
    chamfer_distance,
    chamfer_distance_reference,
    farthest_point_sampling,
    farthest_point_sampling_reference,
    knn,
    knn_numpy,
    knn_reference,
    sample_surface,
)
from pocoloco.ops.sampling import fpsample_available


def _rand(*shape, seed=0, dtype=torch.float64):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


# ----------------------------------------------------------------------------- knn


@pytest.mark.parametrize("k", [1, 3, 8])
@pytest.mark.parametrize("chunk", [None, 7])
def test_knn_matches_reference(k, chunk):
    q, r = _rand(2, 40, 3, seed=1), _rand(2, 60, 3, seed=2)
    fast, ref = knn(q, r, k, chunk=chunk), knn_reference(q, r, k)
    assert fast.dists.shape == fast.idx.shape == (2, 40, k)
    assert torch.equal(fast.idx, ref.idx)
    torch.testing.assert_close(fast.dists, ref.dists, rtol=0, atol=1e-12)
    assert (fast.dists[..., 1:] >= fast.dists[..., :-1]).all()


@pytest.mark.parametrize("k", [1, 2])
def test_knn_float32_far_from_origin(k):
    # coordinates of ~1e3 m with ~mm spacing: cancellation must not corrupt the distances
    q, r = _rand(1, 50, 3, seed=3, dtype=torch.float32), _rand(1, 80, 3, seed=4, dtype=torch.float32)
    q, r = q * 0.05 + 1000.0, r * 0.05 + 1000.0
    fast, ref = knn(q, r, k), knn_reference(q, r, k)
    torch.testing.assert_close(fast.dists, ref.dists, rtol=1e-3, atol=1e-9)


def test_knn_gradient_matches_reference():
    q, r = _rand(1, 20, 3, seed=5).requires_grad_(), _rand(1, 30, 3, seed=6).requires_grad_()
    knn(q, r, 2).dists.sum().backward()
    gq, gr = q.grad.clone(), r.grad.clone()
    q.grad, r.grad = None, None
    knn_reference(q, r, 2).dists.sum().backward()
    torch.testing.assert_close(gq, q.grad)
    torch.testing.assert_close(gr, r.grad)
    assert gr.abs().sum() > 0


def test_knn_numpy_matches_torch():
    q, r = _rand(1, 50, 3, seed=7), _rand(1, 70, 3, seed=8)
    a, b = knn_numpy(q[0].numpy(), r[0].numpy(), 4), knn(q, r, 4)
    assert a.dists.shape == (50, 4)
    np.testing.assert_array_equal(a.idx, b.idx[0].numpy())
    np.testing.assert_allclose(a.dists, b.dists[0].numpy(), atol=1e-12)


def test_knn_validation():
    with pytest.raises(ValueError, match="k must be"):
        knn(_rand(1, 4, 3), _rand(1, 3, 3), 4)
    with pytest.raises(ValueError, match="batch size"):
        knn(_rand(2, 4, 3), _rand(1, 3, 3), 1)
    with pytest.raises(ValueError, match="query must"):
        knn(_rand(4, 3), _rand(1, 3, 3), 1)


# ----------------------------------------------------------------------------- chamfer


def test_chamfer_matches_reference_and_known_answer():
    x, y = _rand(2, 30, 3, seed=9), _rand(2, 45, 3, seed=10)
    fast, ref = chamfer_distance(x, y, chunk=8), chamfer_distance_reference(x, y)
    for name in ("xy_sq", "yx_sq", "xy", "yx", "chamfer_sq", "chamfer"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name))
    assert torch.equal(fast.idx_xy, ref.idx_xy) and torch.equal(fast.idx_yx, ref.idx_yx)
    # identical clouds: 0; a translated single point: the squared / unsquared offset
    assert chamfer_distance(x, x).chamfer.abs().max() == 0
    p = torch.zeros(1, 1, 3, dtype=torch.float64)
    c = chamfer_distance(p, p + torch.tensor([0.0, 0.3, 0.4], dtype=torch.float64))
    torch.testing.assert_close(c.chamfer, torch.tensor([1.0], dtype=torch.float64))
    torch.testing.assert_close(c.chamfer_sq, torch.tensor([0.5], dtype=torch.float64))


def test_chamfer_gradient_finite_at_zero_distance():
    x = _rand(1, 10, 3, seed=11).requires_grad_()
    y = torch.cat([x.detach()[:, :5], _rand(1, 5, 3, seed=12)], dim=1)  # 5 exact matches
    chamfer_distance(x, y).chamfer.sum().backward()
    assert torch.isfinite(x.grad).all()
    torch.autograd.gradcheck(lambda a: chamfer_distance(a, y).chamfer_sq, (_rand(1, 6, 3, seed=13).requires_grad_(),))


# ----------------------------------------------------------------------------- fps


@pytest.mark.parametrize("start", [0, 17])
def test_fps_matches_reference(start):
    pts = _rand(2, 60, 3, seed=14)
    fast = farthest_point_sampling(pts, 12, start, backend="torch")
    assert fast.shape == (2, 12) and (fast[:, 0] == start).all()
    assert torch.equal(fast, farthest_point_sampling_reference(pts, 12, start))
    assert all(len(set(row.tolist())) == 12 for row in fast)  # no repeats


def test_fps_picks_extremes_on_a_line():
    pts = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [0.9, 0, 0]]])
    assert farthest_point_sampling(pts, 3, 0, backend="torch").tolist() == [[0, 3, 2]]


@pytest.mark.skipif(not fpsample_available(), reason="fpsample not installed (optional)")
def test_fps_fpsample_backend_matches_torch():
    pts = _rand(2, 500, 3, seed=15, dtype=torch.float32)
    a = farthest_point_sampling(pts, 64, 3, backend="fpsample")
    assert torch.equal(a, farthest_point_sampling(pts, 64, 3, backend="torch"))


def test_fps_validation():
    with pytest.raises(ValueError, match="num must be"):
        farthest_point_sampling(_rand(1, 5, 3), 6)
    with pytest.raises(ValueError, match="start_index"):
        farthest_point_sampling(_rand(1, 5, 3), 2, start_index=5)


# ----------------------------------------------------------------------------- ball query


@pytest.mark.parametrize("radius,k", [(0.15, 4), (0.3, 16), (0.05, 3)])
def test_ball_query_matches_reference(radius, k):
    ref = _rand(2, 70, 3, seed=16)
    query = torch.cat([ref[:, :10], _rand(2, 5, 3, seed=17) + 2.0], dim=1)  # last 5: empty balls
    fast = ball_query(query, ref, radius, k, chunk=4)
    assert fast.shape == (2, 15, k)
    assert torch.equal(fast, ball_query_reference(query, ref, radius, k))
    # members are inside the ball (or the nearest point for empty balls), first slot = first hit
    d = ((torch.gather(ref, 1, fast.reshape(2, -1, 1).expand(-1, -1, 3)).reshape(2, 15, k, 3) - query[:, :, None]) ** 2).sum(-1)
    assert (d[:, :10] < radius**2).all()


def test_ball_query_padding_convention():
    ref = torch.tensor([[[0.0, 0, 0], [5.0, 0, 0], [0.1, 0, 0], [0.05, 0, 0]]])
    q = torch.tensor([[[0.0, 0, 0], [4.0, 0, 0]]])
    idx = ball_query(q, ref, 0.2, 5)
    assert idx.tolist() == [[[0, 2, 3, 0, 0], [1, 1, 1, 1, 1]]]  # first-found padding; empty -> nearest


# ----------------------------------------------------------------------------- surface sampling


def _two_triangles():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.5], [3, 0, 0.5], [0, 3, 0.5]], dtype=np.float64)
    f = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 4.5
    return v, f


def test_sample_surface_uniform_by_area_and_on_faces():
    v, f = _two_triangles()
    s = sample_surface(v, f, 20000, seed=0)
    assert isinstance(s.points, np.ndarray) and s.points.shape == (20000, 3)
    frac = np.mean(s.face_idx == 0)
    assert abs(frac - 0.1) < 0.01  # 4 sigma of a binomial(20000, 0.1)
    assert (s.barycentric >= 0).all()
    np.testing.assert_allclose(s.barycentric.sum(1), 1)
    np.testing.assert_allclose(np.einsum("nk,nkc->nc", s.barycentric, v[f[s.face_idx]]), s.points)
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1.0], (20000, 1)))
    # uniform inside a triangle: the mean is the centroid (std of the mean ~ 0.003)
    big = s.points[s.face_idx == 1]
    np.testing.assert_allclose(big.mean(0), [1.0, 1.0, 0.5], atol=0.02)


def test_sample_surface_seeded_and_torch():
    v, f = _two_triangles()
    a, b = sample_surface(v, f, 100, seed=3), sample_surface(v, f, 100, seed=3)
    np.testing.assert_array_equal(a.points, b.points)
    t = sample_surface(torch.from_numpy(v).float(), torch.from_numpy(f), 100, seed=3)
    assert t.points.dtype == torch.float32
    np.testing.assert_allclose(t.points.numpy(), a.points, atol=1e-6)
    with pytest.raises(ValueError, match="faces index"):
        sample_surface(v, f + 10, 5)
