"""CloSET (models/closet.py) and its PointNet++ blocks (models/pointnet2.py).

Tiny preset on a synthetic ellipsoid mesh (icosphere, 642 vertices), fixed seeds."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from pocoloco.data.format import Frame
from pocoloco.methods.closet import (
    closet_loss,
    closet_predict,
    closet_train_step,
    make_closet_batch,
    make_closet_optimizer,
    nearest_sq,
)
from pocoloco.models.closet import (
    CloSET,
    CloSETConfig,
    CloSETLossWeights,
    closet_preset,
)
from pocoloco.models.pointnet2 import (
    FeaturePropagation,
    PointNet2Encoder,
    SetAbstraction,
    TemplateHierarchy,
    gather_points,
    three_interpolate,
    three_interpolate_reference,
    three_nn_weights,
)
from pocoloco.ops import ball_query, chamfer_distance_reference, farthest_point_sampling

torch.set_num_threads(1)


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], np.float32)


@pytest.fixture(scope="module")
def mesh():
    """Ellipsoid 'body' (~1.6 m tall): template (V, 3), faces (F, 3)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    v = (np.asarray(m.vertices) * np.array([0.25, 0.15, 0.8])).astype(np.float32)
    return v, np.asarray(m.faces, np.int64)


def _posed(template: np.ndarray, deg: float, pelvis=(0.0, 0.0, 0.0)):
    """Rigidly rotated template with a bend in the upper half; vtransf = the rotation."""
    R = _rot("z", deg) @ _rot("x", deg / 3)
    v = template @ R.T
    v = v + np.where(template[:, 2:3] > 0, 0.05 * np.sin(np.deg2rad(deg)), 0.0) * np.array([1, 0, 0], np.float32)
    tf = np.broadcast_to(R, (len(template), 3, 3)).copy()
    return (v + np.asarray(pelvis, np.float32)).astype(np.float32), tf.astype(np.float32)


def _frame(template, faces, deg, pelvis=(0.1, -0.2, 0.9), offset=0.03, n=600, seed=0) -> Frame:
    """A frame whose GT cloud is the posed mesh pushed out by ``offset`` along its normals."""
    import trimesh

    v, tf = _posed(template, deg, pelvis)
    m = trimesh.Trimesh(v, faces, process=False)
    pts, fid = trimesh.sample.sample_surface(m, n, seed=seed)
    nrm = np.asarray(m.face_normals[fid], np.float32)
    joints = np.zeros((24, 3), np.float32)
    joints[0] = pelvis
    return Frame(points=(pts + offset * nrm).astype(np.float32), normals=nrm, joints=joints, frame_index=0,
                 body_vertices=v, vtransf=tf)  # fmt: skip


@pytest.fixture(scope="module")
def tiny_model(mesh):
    torch.manual_seed(0)
    return CloSET(mesh[0], mesh[1], num_outfits=2, config=closet_preset("tiny"))


def _inputs(model, template, faces, B=2, P=300, seed=0):
    q = model.sample_query_points(P, seed)
    frames = [_frame(template, faces, deg) for deg in (10.0, 40.0)[:B]]
    return make_closet_batch(frames, [0, 1][:B], q, num_gt_points=400)


# --------------------------------------------------------------------------- PointNet++ blocks


def test_gather_points_matches_indexing():
    g = torch.Generator().manual_seed(0)
    vals = torch.randn(3, 20, 4, generator=g)
    idx = torch.randint(0, 20, (3, 5, 6), generator=g)
    ref = torch.stack([vals[b][idx[b]] for b in range(3)])
    assert torch.equal(gather_points(vals, idx), ref)


def test_set_abstraction_and_fp_shapes():
    g = torch.Generator().manual_seed(1)
    xyz = torch.rand(2, 120, 3, generator=g)
    feats = torch.randn(2, 120, 5, generator=g)
    sa = SetAbstraction(npoint=32, radius=0.3, nsample=8, in_channels=5, widths=(16, 24))
    new_xyz, new_f, index = sa(xyz, feats)
    assert new_xyz.shape == (2, 32, 3) and new_f.shape == (2, 32, 24)
    assert index.group_idx.shape == (2, 32, 8) and index.interp_idx.shape == (2, 120, 3)
    # centroids are the FPS points, groups the ball query (PointNet++ convention)
    cidx = farthest_point_sampling(xyz, 32, backend="torch")
    assert torch.equal(index.centroid_idx, cidx)
    assert torch.equal(index.group_idx, ball_query(new_xyz, xyz, 0.3, 8))
    fp = FeaturePropagation(24 + 5, (16, 12))
    out = fp(xyz, new_xyz, feats, new_f)
    assert out.shape == (2, 120, 12)
    # max pooling: the pooled feature bounds each group member's MLP output
    rel = (gather_points(xyz, index.group_idx) - new_xyz[:, :, None]) / 0.3
    per = sa.mlp(torch.cat([rel, gather_points(feats, index.group_idx)], -1))
    assert torch.allclose(per.amax(2), new_f)


def test_three_interpolate_matches_reference():
    g = torch.Generator().manual_seed(2)
    known = torch.rand(2, 9, 3, generator=g)
    unknown = torch.cat([torch.rand(2, 15, 3, generator=g), known[:, :3]], dim=1)  # incl. exact hits
    feats = torch.randn(2, 9, 4, generator=g)
    idx, w = three_nn_weights(unknown, known)
    got = three_interpolate(feats, idx, w)
    ref = three_interpolate_reference(unknown, known, feats)
    assert torch.allclose(got, ref, atol=1e-5)
    assert torch.allclose(got[:, 15:], feats[:, :3], atol=1e-5)  # a coinciding point copies its feature
    # fewer than 3 known points
    got2 = three_interpolate(feats[:, :2], *three_nn_weights(unknown, known[:, :2]))
    assert torch.allclose(got2, three_interpolate_reference(unknown, known[:, :2], feats[:, :2]), atol=1e-5)


def test_cached_hierarchy_identical_to_recomputing(mesh, tiny_model):
    template = torch.from_numpy(mesh[0])
    cfg = closet_preset("tiny").pose
    torch.manual_seed(3)
    enc = PointNet2Encoder(cfg, in_channels=3)
    h = enc.build_hierarchy(template)
    assert h.sizes() == [len(template), 96, 48, 24, 12, 6, 3]
    v = torch.from_numpy(np.stack([_posed(mesh[0], d)[0] for d in (5.0, 50.0)]))
    xyz = template[None].expand(2, -1, -1)
    for train in (True, False):  # BatchNorm batch statistics and running statistics
        enc.train(train)
        with torch.no_grad():
            a = enc(xyz, v, h)
            b = enc(xyz, v, None)
        assert a.shape == (2, len(template), cfg.out_channels)
        assert torch.equal(a, b)
    # whole model: cached=False recomputes FPS / ball query / 3-NN every call
    batch = _inputs(tiny_model, *mesh)
    tiny_model.eval()
    with torch.no_grad():
        o1 = tiny_model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        o2 = tiny_model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric, cached=False)
    assert torch.equal(o1.points, o2.points) and torch.equal(o1.normals, o2.normals)
    # the garment hierarchy shares the pose hierarchy's identical first levels
    assert tiny_model.garment_hierarchy.l0_group_idx is tiny_model.pose_hierarchy.l0_group_idx


def test_hierarchy_reuse_only_matching_levels(mesh):
    xyz = torch.from_numpy(mesh[0])
    a = TemplateHierarchy(xyz, (64, 16), (0.2, 0.5), (8, 8))
    b = TemplateHierarchy(xyz, (64, 16), (0.2, 0.4), (8, 8), reuse=a)
    c = TemplateHierarchy(xyz, (64, 16), (0.2, 0.4), (8, 8))
    assert b.l0_group_idx is a.l0_group_idx
    assert torch.equal(b.l1_group_idx, c.l1_group_idx)


# --------------------------------------------------------------------------- CloSET


def test_zero_decoders_put_points_on_posed_surface(mesh):
    torch.manual_seed(4)
    for decomposition in (True, False):
        model = CloSET(mesh[0], mesh[1], 2, closet_preset("tiny", decomposition=decomposition))
        model.zero_displacement_heads_()
        batch = _inputs(model, *mesh)
        out = model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        # independent numpy blend of the posed face corners
        v = batch.vertices.numpy().astype(np.float64)
        corners = v[:, mesh[1][batch.face_idx.numpy()]]  # (B, P, 3, 3)
        expect = (corners * batch.barycentric.numpy()[None, :, :, None]).sum(2)
        assert torch.count_nonzero(out.r) == 0
        assert torch.equal(out.points, out.body_points)
        np.testing.assert_allclose(out.points.detach().numpy(), expect, atol=1e-6)
        assert torch.allclose(out.normals.norm(dim=-1), torch.ones(()), atol=1e-5)


def test_decomposition_and_single_decoder_ablation(mesh, tiny_model):
    batch = _inputs(tiny_model, *mesh)
    tiny_model.eval()
    with torch.no_grad():
        out = tiny_model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        assert torch.equal(out.r, out.r_g + out.r_p)
        # x = T r + p^u with T the blended vtransf (here the frame's single rotation)
        T = batch.vtransf[:, 0]
        assert torch.allclose(out.points, torch.einsum("bij,bpj->bpi", T, out.r) + out.body_points, atol=1e-6)
        # r_g = D_g(phi_g, p): pose-independent; r_p changes with the pose
        other = torch.from_numpy(np.stack([_posed(mesh[0], 70.0)[0]] * 2)) - batch.pelvis[:, None]
        out2 = tiny_model(other, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        assert torch.equal(out2.r_g, out.r_g)
        assert not torch.allclose(out2.r_p, out.r_p)
        # different outfits -> different garment templates
        out3 = tiny_model(batch.vertices, batch.vtransf, torch.tensor([1, 0]), batch.face_idx, batch.barycentric)
        assert torch.equal(out3.r_g[0], out.r_g[1])
    torch.manual_seed(5)
    single = CloSET(mesh[0], mesh[1], 2, closet_preset("tiny", decomposition=False))
    names = {n.split(".")[0] for n, _ in single.named_parameters()}
    assert "decoder" in names and "garment_decoder" not in names and "pose_decoder" not in names
    assert {"garment_decoder", "pose_decoder"} <= {n.split(".")[0] for n, _ in tiny_model.named_parameters()}
    o = single(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
    assert o.r_g is None and o.r_p is None and o.r.shape == (2, 300, 3)
    losses = closet_loss(o, batch.points, batch.normals)
    assert float(losses["reg_pd"]) == 0.0


def test_loss_terms_match_definitions(mesh, tiny_model):
    batch = _inputs(tiny_model, *mesh)
    tiny_model.eval()
    with torch.no_grad():
        out = tiny_model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        w = CloSETLossWeights()
        got = closet_loss(out, batch.points, batch.normals, w)
    x, y = out.points.double(), batch.points.double()
    d = ((x[:, :, None] - y[:, None]) ** 2).sum(-1)  # (B, P, N)
    cd = (d.min(2).values.mean(1) + d.min(1).values.mean(1)).mean()
    nn_n = torch.stack([batch.normals[b][d[b].argmin(1)] for b in range(2)]).double()
    nml = (out.normals.double() - nn_n).abs().sum(-1).mean()
    assert abs(float(got["chamfer"]) - float(cd)) < 1e-6 * max(1.0, float(cd))
    assert abs(float(got["normal"]) - float(nml)) < 1e-4
    codes = tiny_model.garment_codes[batch.outfit].detach()
    total = w.chamfer * cd + w.normal * nml + w.rgl * (
        (out.r.double() ** 2).sum(-1).mean() + w.pd * (out.r_p.double() ** 2).sum(-1).mean()
        + w.gc * (codes.double() ** 2).sum(-1).mean()
    )  # fmt: skip
    assert abs(float(got["total"]) - float(total)) < 1e-4 * float(total)


def test_nearest_sq_backends_match_reference():
    g = torch.Generator().manual_seed(7)
    x = torch.rand(2, 60, 3, generator=g, requires_grad=True)
    y = torch.rand(2, 45, 3, generator=g)
    ref = chamfer_distance_reference(x.detach(), y)
    grads = []
    for backend in ("kdtree", "torch"):
        d, i = nearest_sq(x, y, backend)
        assert torch.equal(i, ref.idx_xy)
        assert torch.allclose(d, ref.dist_xy, atol=1e-6)
        (gx,) = torch.autograd.grad(d.sum(), x)
        grads.append(gx)
    assert torch.allclose(grads[0], grads[1])
    assert torch.allclose(grads[0], 2 * (x.detach() - torch.gather(y, 1, ref.idx_xy[..., None].expand(-1, -1, 3))))


def test_training_steps_reduce_loss_on_one_frame(mesh):
    torch.manual_seed(6)
    model = CloSET(mesh[0], mesh[1], 1, closet_preset("tiny"))
    q = model.sample_query_points(400, 0)
    batch = make_closet_batch([_frame(*mesh, 25.0, offset=0.05)], 0, q, num_gt_points=500)
    opt = make_closet_optimizer(model, lr=3e-3, code_lr=3e-3)
    hist = [closet_train_step(model, opt, batch) for _ in range(40)]
    first, last = hist[0]["chamfer"], min(h["chamfer"] for h in hist[-5:])
    assert last < 0.5 * first, (first, last)
    assert min(h["total"] for h in hist[-5:]) < hist[0]["total"]
    assert all(np.isfinite(h["total"]) for h in hist)


def test_batch_builder_is_pelvis_centred(mesh, tiny_model):
    q = tiny_model.sample_query_points(50, 1)
    fr = _frame(*mesh, 20.0, pelvis=(0.5, 0.25, 1.0))
    b = make_closet_batch([fr, fr], 1, q, num_gt_points=100, seed=3)
    assert b.vertices.shape == (2, len(mesh[0]), 3) and b.points.shape == (2, 100, 3)
    np.testing.assert_allclose(b.vertices[0].numpy(), fr.body_vertices - fr.joints[0], atol=1e-6)
    np.testing.assert_allclose(b.pelvis[0].numpy(), [0.5, 0.25, 1.0])
    assert b.outfit.tolist() == [1, 1]
    assert torch.equal(b.face_idx, torch.from_numpy(q.face_idx))
    # the query points lie on the body component only and are reusable for every frame
    assert tiny_model.face_mask[b.face_idx].all()


def test_state_round_trip(mesh, tiny_model):
    as_json = json.loads(json.dumps(tiny_model.config.to_dict()))  # tuples -> lists, as in a checkpoint
    cfg = CloSETConfig.from_dict(as_json)
    assert cfg == tiny_model.config
    clone = CloSET.from_state(as_json, tiny_model.state_dict())
    batch = _inputs(tiny_model, *mesh)
    tiny_model.eval()
    clone.eval()
    with torch.no_grad():
        a = tiny_model(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
        b = clone(batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric)
    assert torch.equal(a.points, b.points)
    assert not any("hierarchy" in k for k in tiny_model.state_dict())
    pts, nrm = closet_predict(clone, batch)  # world coordinates: pelvis added back
    np.testing.assert_allclose(pts, (b.points + batch.pelvis[:, None]).numpy(), atol=1e-6)
    assert pts.dtype == np.float32 and nrm.shape == pts.shape


def _one_line_error(fn, match):
    with pytest.raises(ValueError, match=match) as e:
        fn()
    assert "\n" not in str(e.value)


def test_bad_inputs_raise_one_line_value_errors(mesh, tiny_model):
    batch = _inputs(tiny_model, *mesh)
    v, tf, o, fi, bc = batch.vertices, batch.vtransf, batch.outfit, batch.face_idx, batch.barycentric
    m = tiny_model
    _one_line_error(lambda: m(v[:, :-1], tf, o, fi, bc), "vertices have 641 vertices, the CloSET template has 642")
    _one_line_error(lambda: m(v, tf, torch.tensor([0, 2]), fi, bc), r"outfit id out of range \[0, 2\)")
    _one_line_error(lambda: m(v, tf, -1, fi, bc), "outfit id out of range")
    _one_line_error(lambda: m(v, tf, torch.tensor([0.0, 1.0]), fi, bc), "outfit must be an integer")
    # POP-style inputs: a UV position map and 4x4 vtransf
    _one_line_error(lambda: m(torch.zeros(2, 3, 32, 32), tf, o, fi, bc), "POP UV position map")
    tf4 = torch.zeros(2, len(mesh[0]), 4, 4)
    _one_line_error(lambda: m(v, tf4, o, fi, bc), r"POP's 4x4 vtransf")
    _one_line_error(lambda: m(v, tf, o, torch.full_like(fi, 10**6), bc), "face_idx outside")
    _one_line_error(lambda: closet_preset("huge"), "unknown CloSET preset 'huge'")
    _one_line_error(lambda: closet_preset("tiny", widht=3), "unknown CloSETConfig field")
    _one_line_error(lambda: CloSET(mesh[0], mesh[1], 0, closet_preset("tiny")), "num_outfits")
    _one_line_error(lambda: CloSET(mesh[0][:, :2], mesh[1], 1, closet_preset("tiny")), "template must have shape")
    q = m.sample_query_points(10)
    fr = _frame(*mesh, 0.0)
    imported = dataclasses.replace(fr, body_vertices=None, vtransf=None)
    _one_line_error(lambda: make_closet_batch([imported], 0, q), "has no 'body_vertices'")
    _one_line_error(lambda: make_closet_batch([fr], 0, q, num_gt_points=10**6), "fewer than num_gt_points")
    _one_line_error(lambda: make_closet_batch([fr, fr], [0], q), "one id or one per frame")
    _one_line_error(lambda: m.sample_query_points(0), "positive integer")
