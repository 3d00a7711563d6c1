"""Tests of the POP baseline (pocoloco.models.pop) on a synthetic UV-mapped cylinder.

Tiny preset, tiny maps, fixed seeds, one torch thread; no anny body is built.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import pocoloco.models.pop_decoder as pop_module
from pocoloco.body.skeleton import NUM_JOINTS
from pocoloco.body.surface import BodySurface
from pocoloco.data.format import (
    DatasetLayout,
    Frame,
    SubjectAsset,
    write_frame,
    write_subject,
)
from pocoloco.methods.pop import (
    POPDataset,
    collate_pop,
    fit_unseen_outfit,
    make_optimizer,
    pop_losses,
    pop_losses_reference,
    pop_sample_from_frame,
    train_step,
)
from pocoloco.models.pop import POP, POPBatch, POPConfig, POPLossWeights, POPQuery, pop_preset

pytestmark = pytest.mark.usefixtures("torch_single_thread")


def cylinder(n_theta: int = 16, n_z: int = 10, radius: float = 0.15, height: float = 1.0):
    """Open cylinder around Z with a seam column duplicated; UVs tile [0.05, 0.95]^2."""
    th = np.linspace(0, 2 * np.pi, n_theta + 1)
    z = np.linspace(-height / 2, height / 2, n_z)
    T, Z = np.meshgrid(th, z)  # (n_z, n_theta + 1)
    verts = np.stack([radius * np.cos(T), radius * np.sin(T), Z], -1).reshape(-1, 3).astype(np.float32)
    U, W = np.meshgrid(np.linspace(0.05, 0.95, n_theta + 1), np.linspace(0.05, 0.95, n_z))
    uv = np.stack([U, W], -1).reshape(-1, 2).astype(np.float32)
    w = n_theta + 1
    faces = []
    for i in range(n_z - 1):
        for j in range(n_theta):
            a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
            faces += [(a, b, d), (a, d, c)]
    faces = np.asarray(faces, np.int64)
    return verts, faces, uv, faces.copy()


def rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return (q * np.sign(np.linalg.det(q))).astype(np.float32)


def synthetic_frame(verts, rng, offset: float = 0.03, n_scan: int = 600) -> Frame:
    """A rigidly posed cylinder body with a 'garment' scan `offset` outside it (world coords)."""
    R, t = rotation(rng), rng.normal(size=3).astype(np.float32)
    body = verts @ R.T + t
    ang = rng.uniform(0, 2 * np.pi, n_scan)
    zz = rng.uniform(-0.45, 0.45, n_scan)
    nrm = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
    pts = (0.15 + offset) * nrm + np.stack([0 * zz, 0 * zz, zz], -1)
    joints = rng.normal(scale=0.3, size=(NUM_JOINTS, 3)).astype(np.float32)
    joints[0] = 0.0
    return Frame(points=(pts @ R.T + t).astype(np.float32), normals=(nrm @ R.T).astype(np.float32),
                 joints=(joints @ R.T + t).astype(np.float32), frame_index=0, body_vertices=body.astype(np.float32),
                 vtransf=np.broadcast_to(R, (len(verts), 3, 3)).copy())  # fmt: skip


@pytest.fixture(scope="module")
def mesh():
    return cylinder()


@pytest.fixture(scope="module")
def surface(mesh):
    _, faces, uv, uv_faces = mesh
    return BodySurface(faces, uv, uv_faces)


def make_model(surface, mesh, outfits=2, seed=0, **kw) -> POP:
    torch.manual_seed(seed)
    return POP(pop_preset("tiny", **kw), surface, outfits, len(mesh[0]))


def make_batch(mesh, seed=0, n=2, n_scan=600, num_points=500) -> POPBatch:
    rng = np.random.default_rng(seed)
    frames = [synthetic_frame(mesh[0], rng, n_scan=n_scan) for _ in range(n)]
    return collate_pop([pop_sample_from_frame(f, i % 2, num_points, rng) for i, f in enumerate(frames)])


def test_shapes_and_unit_normals(surface, mesh):
    model = make_model(surface, mesh)
    batch = make_batch(mesh)
    out = model(batch)
    P = surface.raster(model.config.query_resolution).num_valid
    assert model.num_query_points == P > 100
    for t in (out.points, out.normals, out.displacement, out.base):
        assert t.shape == (2, P, 3)
    assert out.geom.shape == (2, 8, 32, 32)
    torch.testing.assert_close(out.normals.norm(dim=-1), torch.ones(2, P))
    assert model.input_posmap(batch.pose_vertices).shape == (2, 3, 32, 32)


def test_paper_preset_parameter_count(surface, mesh):
    model = POP(POPConfig(), surface, 1, len(mesh[0]))
    n = model.num_network_parameters()
    assert 11.0e6 < n < 11.6e6  # the paper's POP: about 11.3M
    assert model.geom.shape == (1, 64, 128, 128)


@pytest.mark.parametrize("training", [False, True])
def test_fast_decoder_matches_conv1d_reference(surface, mesh, training):
    fast = make_model(surface, mesh, seed=3)
    ref = make_model(surface, mesh, seed=3, decoder_impl="conv1d_all_pixels")
    ref.load_state_dict(fast.state_dict())
    fast.double().train(training)  # float64: the two paths differ only by summation order
    ref.double().train(training)
    b = make_batch(mesh, seed=1)
    batch = POPBatch(*(t.double() for t in (b.pose_vertices, b.body_vertices, b.vtransf)), b.outfit)
    outs, grads = [], []
    w = torch.randn(2, fast.num_query_points, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for m in (fast, ref):
        m.zero_grad()
        out = m(batch)
        ((out.points * w).sum() + (out.normals * w).sum()).backward()
        outs.append(out)
        grads.append({n: p.grad.clone() for n, p in m.named_parameters()})
    torch.testing.assert_close(outs[0].points, outs[1].points, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(outs[0].normals, outs[1].normals, rtol=1e-10, atol=1e-10)
    for n in grads[0]:
        torch.testing.assert_close(grads[0][n], grads[1][n], rtol=1e-8, atol=1e-10, msg=n)
    for (n, x), y in zip(fast.state_dict().items(), ref.state_dict().values()):  # BN running stats too
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-12, msg=n)


def _interpolate_reference(values: np.ndarray, flat: np.ndarray, R: int, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slow reference of ``POP.interpolate_pixels``: per query UV, the four pixel centres around
    it (row i holds v = 1 - (i + .5) / R, column j u = (j + .5) / R), bilinear weights, only the
    valid ones summed, divided by their total weight."""
    valid = {int(f): k for k, f in enumerate(flat)}
    out, total = np.zeros((len(uv), values.shape[1])), np.zeros(len(uv))
    for q, (u, v) in enumerate(uv):
        x, y = u * R - 0.5, (1 - v) * R - 0.5  # continuous column / row of the pixel centres
        j0, i0 = int(np.floor(x)), int(np.floor(y))
        for i, wi in ((i0, 1 - (y - i0)), (i0 + 1, y - i0)):
            for j, wj in ((j0, 1 - (x - j0)), (j0 + 1, x - j0)):
                k = valid.get(i * R + j) if 0 <= i < R and 0 <= j < R else None
                if k is not None:
                    out[q] += wi * wj * values[k]
                    total[q] += wi * wj
    return out / np.maximum(total, 1e-12)[:, None], total


def test_interpolated_decoding_matches_reference_and_the_training_pixels(surface, mesh):
    """Off the training map, POP interpolates what it decoded at the training pixels (normalised
    bilinear over the valid ones, checked against a per-point loop); at the training pixels
    themselves that is the decoder's output exactly; rim points without a valid neighbour are
    decoded directly."""
    model = make_model(surface, mesh, seed=4).double().eval()
    b = make_batch(mesh, seed=2)
    batch = POPBatch(*(t.double() for t in (b.pose_vertices, b.body_vertices, b.vtransf)), b.outfit)
    R = model.config.query_resolution
    vals = torch.randn(2, model.num_query_points, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    fine = model.query_points(3 * R + 1)
    # three points whose UVs lie outside the layout (no valid pixel around them): the rim case
    outside = torch.tensor([[0.01, 0.01], [0.99, 0.99], [0.02, 0.5]], dtype=fine.uv.dtype)
    fine = POPQuery(torch.cat([fine.face_idx, fine.face_idx[:3]]), torch.cat([fine.barycentric, fine.barycentric[:3]]),
                    torch.cat([fine.uv, outside]))  # fmt: skip
    got, weight = model.interpolate_pixels(vals, fine.uv.double())
    for k in range(2):
        want, total = _interpolate_reference(vals[k].numpy(), model.q_flat.numpy(), R, fine.uv.double().numpy())
        np.testing.assert_allclose(weight.numpy(), total, atol=1e-12)
        ok = total > 1e-9
        np.testing.assert_allclose(got[k].numpy()[ok], want[ok], rtol=1e-9, atol=1e-12)
    at_pixels, w = model.interpolate_pixels(vals, model.q_uv.double())
    torch.testing.assert_close(at_pixels, vals, rtol=0, atol=1e-12)
    torch.testing.assert_close(w, torch.ones_like(w), rtol=0, atol=1e-12)

    with torch.no_grad():
        plain = model(batch)
        same = model(batch, query=model.query_points(), interpolate=True)
        torch.testing.assert_close(same.points, plain.points, rtol=0, atol=1e-12)
        out = model(batch, query=fine, interpolate=True)
        feats = model.feature_maps(model.input_posmap(batch.pose_vertices), model.geom[batch.outfit])
        r_px, n_px = model.decode(feats, None)
        r_q, _ = model.interpolate_pixels(torch.cat([r_px, n_px], -1), fine.uv.double())
        rim = weight < 1e-3
        assert rim[-3:].all() and not rim[:-3].any()
        direct = model(batch, query=fine)  # decoded at the fine UVs
        torch.testing.assert_close(out.points[:, rim], direct.points[:, rim])
        scale = model.config.displacement_scale
        torch.testing.assert_close(out.displacement[:, ~rim], scale * r_q[:, ~rim, :3])
    assert out.points.shape == (2, len(fine.uv), 3) and bool(torch.isfinite(out.points).all())
    torch.testing.assert_close(out.normals.norm(dim=-1), torch.ones(2, len(fine.uv), dtype=torch.float64))


def _plain_layer(layer, *parts):
    """The slow reference: the modules as written (concatenation, BatchNorm1d, Softplus(beta))."""
    y = layer.linear(torch.cat(parts, -1))
    return y if layer.bn is None else F.softplus(layer.bn(y), beta=layer.beta)


@pytest.mark.parametrize("training", [True, False])
def test_fused_mlp_layer_matches_plain_modules(monkeypatch, training):
    """_MLPLayer's fast paths (fused BatchNorm + softplus node in training, folded BatchNorm in
    evaluation, row chunks smaller than the batch) against the plain modules: outputs, all
    gradients and the BatchNorm running statistics, in float64."""
    monkeypatch.setattr(pop_module, "_ROW_CHUNK", 7)
    g = torch.Generator().manual_seed(0)
    fast = pop_module._MLPLayer(9, 6, beta=20.0).double()
    with torch.no_grad():
        fast.bn.weight.uniform_(0.5, 1.5, generator=g)
        fast.bn.bias.normal_(0, 0.5, generator=g)
        fast.bn.running_mean.normal_(0, 0.3, generator=g)
        fast.bn.running_var.uniform_(0.5, 2.0, generator=g)
    ref = copy.deepcopy(fast)
    fast.train(training), ref.train(training)
    parts = [torch.randn(50, c, generator=g, dtype=torch.float64) * 3 for c in (5, 4)]
    w = torch.randn(50, 6, generator=g, dtype=torch.float64)
    results = []
    for layer, fn in ((fast, lambda *p: fast(*p)), (ref, lambda *p: _plain_layer(ref, *p))):
        xs = [p.clone().requires_grad_() for p in parts]
        out = fn(*xs)
        (out * w).sum().backward()
        results.append((out, [x.grad for x in xs], {n: p.grad for n, p in layer.named_parameters()}))
    (o1, gx1, gp1), (o2, gx2, gp2) = results
    torch.testing.assert_close(o1, o2, rtol=1e-8, atol=1e-12)
    for a, b in zip(gx1, gx2):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-10)
    for n in gp2:
        if n == "linear.bias" and training:  # zero up to rounding before a BatchNorm
            torch.testing.assert_close(gp1[n], torch.zeros_like(gp1[n]), rtol=0, atol=1e-10)
            continue
        torch.testing.assert_close(gp1[n], gp2[n], rtol=1e-7, atol=1e-10, msg=n)
    for (n, a), b in zip(fast.state_dict().items(), ref.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14, msg=n)


def test_fused_batchnorm_softplus_gradcheck():
    g = torch.Generator().manual_seed(1)
    y = torch.randn(12, 3, generator=g, dtype=torch.float64, requires_grad=True)
    weight = (torch.rand(3, generator=g, dtype=torch.float64) + 0.5).requires_grad_()
    bias = torch.randn(3, generator=g, dtype=torch.float64, requires_grad=True)
    fn = lambda y, a, b: pop_module._BatchNormSoftplus.apply(y, a, b, 3.0, 1e-5)[0]  # noqa: E731
    assert torch.autograd.gradcheck(fn, (y, weight, bias))


def test_inference_decoder_matches_plain_modules(monkeypatch):
    """ShapeDecoder's no-grad evaluation path (folded BatchNorm, chunked rows, reused buffers)
    against the plain modules layer by layer."""
    monkeypatch.setattr(pop_module, "_ROW_CHUNK", 16)
    torch.manual_seed(0)
    dec = pop_module.ShapeDecoder(7, 12, 8, 4, 6, 20.0).double()
    for m in dec.modules():
        if isinstance(m, torch.nn.BatchNorm1d):
            m.running_mean.normal_(0, 0.3)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
    dec.eval()
    x = torch.randn(45, 7, dtype=torch.float64)
    h = x
    for i, layer in enumerate(dec.trunk, start=1):
        h = _plain_layer(layer, h, x) if i == dec.skip else _plain_layer(layer, h)
    want = []
    for head in (dec.disp_head, dec.normal_head):
        r = h
        for layer in head:
            r = _plain_layer(layer, r)
        want.append(r)
    with torch.no_grad():
        got = dec(x)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-11)


def test_zero_displacement_puts_points_on_the_body(surface, mesh):
    model = make_model(surface, mesh)
    last = model.decoder.disp_head[-1].linear
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    batch = make_batch(mesh, seed=2)
    out = model(batch)
    assert torch.equal(out.points, out.base)
    # base points are the barycentric blend of the posed faces (numpy check, all pixels)
    pts = surface.raster(model.config.query_resolution).points()
    v = batch.body_vertices.numpy()
    f = mesh[1][pts.face_idx]  # (P, 3)
    expect = (v[:, f] * pts.barycentric[None, :, :, None]).sum(2)
    np.testing.assert_allclose(out.points.detach().numpy(), expect, atol=1e-6)
    assert (pts.barycentric >= 0).all()


def test_losses_match_slow_reference(surface, mesh):
    model = make_model(surface, mesh)
    batch = make_batch(mesh, seed=4, n_scan=80, num_points=60)
    out = model(batch)
    out.points.retain_grad()
    c = POPLossWeights(s2m=2e4, displacement=1e3)  # not the defaults: the weights are applied
    for wn, backend in ((0.0, "kdtree"), (0.1, "brute"), (0.1, "kdtree")):
        fast = pop_losses(out, batch.scan_points, batch.scan_normals, c, normal_weight=wn, nn_backend=backend)
        slow = pop_losses_reference(out, batch.scan_points, batch.scan_normals, c, normal_weight=wn)
        for k in ("total", "s2m", "m2s", "normal", "displacement", "feature"):
            torch.testing.assert_close(getattr(fast, k), getattr(slow, k), rtol=1e-5, atol=1e-8, msg=k)
    gf = torch.autograd.grad(fast.total, out.points, retain_graph=True)[0]
    gs = torch.autograd.grad(slow.total, out.points)[0]
    torch.testing.assert_close(gf, gs, rtol=1e-4, atol=1e-6)
    assert fast.s2m > 0 and fast.m2s > 0 and fast.normal > 0


def test_training_steps_reduce_the_loss(surface, mesh):
    model = make_model(surface, mesh, outfits=1, seed=5)
    rng = np.random.default_rng(5)
    batch = collate_pop([pop_sample_from_frame(synthetic_frame(mesh[0], rng), 0, 500, rng)])
    opt = make_optimizer(model, lr=3e-3, lr_features=3e-3)
    losses = [train_step(model, opt, batch, step)["total"] for step in range(25)]
    assert np.isfinite(losses).all()
    assert min(losses[-5:]) < 0.5 * losses[0], losses


def test_fit_unseen_outfit_changes_only_the_new_features(surface, mesh):
    model = make_model(surface, mesh, outfits=2, seed=6)
    model.train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    rng = np.random.default_rng(6)
    s = pop_sample_from_frame(synthetic_frame(mesh[0], rng, offset=0.05), 0, 500, rng)
    fit = fit_unseen_outfit(model, s.scan_points, s.scan_normals, s.pose_vertices, s.body_vertices, s.vtransf,
                            steps=8, lr=1e-2)  # fmt: skip
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert model.training and all(p.requires_grad for p in model.parameters())
    init = before["geom"].mean(0, keepdim=True)
    assert fit.features.shape == init.shape and not torch.allclose(fit.features, init)
    assert fit.losses[-1] < fit.losses[0]
    new_id = model.add_outfit(fit.features)
    assert new_id == 2 and model.num_outfits == 3
    model.eval()
    b = collate_pop([s])
    b.outfit = torch.tensor([new_id])
    torch.testing.assert_close(model(b).points, model(b, geom=fit.features).points)


def test_dataset_reads_and_centres_frames(surface, mesh, tmp_path):
    verts, faces, uv, uv_faces = mesh
    layout = DatasetLayout(tmp_path)
    rng = np.random.default_rng(7)
    frames = []
    for s in ("b_subject", "a_subject"):
        write_subject(layout.subject_path(s), SubjectAsset(template=verts, faces=faces, uv=uv, uv_faces=uv_faces,
                                                            vertex_joint=np.zeros(len(verts), np.int8)))  # fmt: skip
        for i in range(2):
            f = synthetic_frame(verts, rng)
            f.frame_index = i
            write_frame(layout.frame_path(s, "train", "seq0", i), f)
            frames.append((s, f))
    ds = POPDataset(tmp_path, "train", num_points=300, pose_input="subject")
    assert len(ds) == 4 and ds.outfits == {"a_subject": 0, "b_subject": 1}
    item = ds[0]
    assert item.outfit == 0 and item.scan_points.shape == (300, 3)
    first = frames[2][1]  # first frame of a_subject (outfit 0)
    np.testing.assert_allclose(item.body_vertices, first.body_vertices - first.joints[0], atol=1e-6)
    np.testing.assert_allclose(item.pose_vertices, item.body_vertices)
    d = ((item.scan_points + first.joints[0])[:, None] - first.points[None]).__pow__(2).sum(-1).min(1)
    assert d.max() < 1e-10  # a subset of the frame's points, centred
    batch = collate_pop([ds[i] for i in range(4)])
    out = make_model(surface, mesh)(batch)
    assert out.points.shape[0] == 4


def test_bad_input_raises_one_line_errors(surface, mesh):
    model = make_model(surface, mesh)
    batch = make_batch(mesh)
    rng = np.random.default_rng(0)
    frame = synthetic_frame(mesh[0], rng)

    def check(fn, match):
        with pytest.raises(ValueError, match=match) as e:
            fn()
        assert "\n" not in str(e.value)

    bad = POPBatch(batch.pose_vertices[:, :-1], batch.body_vertices, batch.vtransf, batch.outfit)
    check(lambda: model(bad), "pose_vertices must have shape")
    bad = POPBatch(batch.pose_vertices, batch.body_vertices, batch.vtransf[:, :-1], batch.outfit)
    check(lambda: model(bad), "vtransf must have shape")
    bad = POPBatch(batch.pose_vertices, batch.body_vertices, batch.vtransf, torch.tensor([0, 2]))
    check(lambda: model(bad), r"outfit ids must be in \[0, 2\)")
    frame_j = Frame(**{**frame.__dict__, "joints": frame.joints[:10]})
    check(lambda: pop_sample_from_frame(frame_j, 0, 100, rng), "joints must have shape")
    check(lambda: pop_sample_from_frame(frame, 0, 100, rng, num_vertices=5), "body has .* vertices")
    check(lambda: pop_sample_from_frame(frame, 0, 10_000, rng), "scan has 600 points, fewer than")
    nonorm = POPBatch(batch.pose_vertices, batch.body_vertices, batch.vtransf, batch.outfit, batch.scan_points)
    check(lambda: train_step(model, make_optimizer(model), nonorm, 0), "needs scan_normals")
    check(lambda: pop_preset("huge"), "unknown POP preset")
    check(lambda: POPConfig(input_resolution=100), "divisible")
    check(lambda: POP(pop_preset("tiny"), surface, 0), "num_outfits")
    check(lambda: fit_unseen_outfit(model, np.zeros((5, 2)), None, *(t[0] for t in
                                    (batch.pose_vertices, batch.body_vertices, batch.vtransf)), steps=1), "scan_points")  # fmt: skip
