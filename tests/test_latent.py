"""Latent read / compute / write denoiser: slow reference, invariances, config, diffusion plumbing."""

import json
import math

import pytest
import torch
from torch import nn

from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, diffusion_loss, sample
from pocoloco.models import (
    LATENT_PRESETS,
    LatentDenoiser,
    LatentDenoiserConfig,
    latent_preset,
    positional_encoding,
    timestep_embedding,
)
from pocoloco.models.conditioning import PoseCondition
from pocoloco.models.pocoloco import joint_offset_features

# tiny models run fastest on one thread, and bit-exact comparisons need a fixed thread count
pytestmark = pytest.mark.usefixtures("torch_single_thread")


def tiny_model(seed: int = 0, **overrides) -> LatentDenoiser:
    """Tiny latent denoiser whose zero-initialised head is randomised so outputs are non-trivial."""
    torch.manual_seed(seed)
    model = LatentDenoiser(latent_preset("tiny", **overrides))
    nn.init.normal_(model.out.weight, std=0.2)
    nn.init.normal_(model.out.bias, std=0.2)
    return model.eval()


def inputs(B=2, N=100, C=3, J=24, seed=1, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, N, C, generator=g, dtype=dtype)
    t = torch.randint(0, 1000, (B,), generator=g)
    joints = torch.randn(B, J, 3, generator=g, dtype=dtype) * 0.5
    return x, t, joints


# --------------------------------------------------------------------- slow reference
def ref_linear(x, lin):
    return x @ lin.weight.T + lin.bias


def ref_layer_norm(x, ln):
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)  # biased variance, as nn.LayerNorm
    return (x - mean) / torch.sqrt(var + ln.eps) * ln.weight + ln.bias


def ref_gelu(x):
    return 0.5 * x * (1.0 + torch.erf(x / math.sqrt(2.0)))


def ref_mlp(x, mlp):
    return ref_linear(ref_gelu(ref_linear(x, mlp.fc1)), mlp.fc2)


def ref_attention(x, context, attn):
    """softmax(Q K^T / sqrt(c)) V per head, the softmax written out; x (B, Q, .), context (B, K, .)."""
    H, c = attn.heads, attn.head_dim
    q = ref_linear(x, attn.to_q)  # (B, Q, H c)
    kv = ref_linear(context, attn.to_kv)
    k, v = kv[..., : H * c], kv[..., H * c :]
    heads = []
    for h in range(H):
        sl = slice(h * c, (h + 1) * c)
        s = q[..., sl] @ k[..., sl].transpose(1, 2) / math.sqrt(c)  # (B, Q, K)
        e = torch.exp(s - s.max(dim=-1, keepdim=True).values)
        a = e / e.sum(dim=-1, keepdim=True)  # each query's weights sum to one over the keys
        heads.append(a @ v[..., sl])  # (B, Q, c)
    return ref_linear(torch.cat(heads, dim=-1), attn.proj)


def reference_forward(model: LatentDenoiser, x, t, joints, body=None):
    """The network of ``latent.py``'s module docstring written out with explicit operations
    (``body``: (B, K, 3) posed-body vertices, tokens after the joints')."""
    cfg = model.config
    enc = lambda a: positional_encoding(a, cfg.posenc, cfg.num_freqs, cfg.posenc_include_input)
    B = x.shape[0]
    feats = torch.cat([enc(x[..., :3]), x[..., 3:]], dim=-1)
    p = ref_linear(feats, model.point_in)
    if cfg.joint_offsets:
        off = model.offset_in
        p = p + ref_linear(ref_gelu(ref_linear(joint_offset_features(x[..., :3], joints), off[0])), off[2])
        if body is not None:  # offsets to the body vertices, written out per point and vertex
            d = torch.stack([x[:, :, :3] - body[:, k : k + 1] for k in range(body.shape[1])], dim=2)  # (B, N, K, 3)
            feats_b = torch.cat([d.flatten(2), torch.sqrt((d**2).sum(-1))], dim=-1)
            off = model.body_offset_in
            p = p + ref_linear(ref_gelu(ref_linear(feats_b, off[0])), off[2])
    p = ref_layer_norm(p, model.ln_points)
    te = model.time_embed.mlp
    tau = ref_linear(ref_gelu(ref_linear(timestep_embedding(t, cfg.width).to(x.dtype), te[0])), te[2])
    jt = ref_linear(enc(joints), model.joint_in) + model.joint_embed
    tokens = [model.latents.expand(B, -1, -1), tau[:, None], jt]
    if body is not None:
        tokens.append(ref_linear(enc(body), model.body_in) + model.body_embed)
    z = torch.cat(tokens, dim=1)
    z = ref_layer_norm(z, model.ln_latents)
    for blk in model.blocks:
        z = z + ref_attention(ref_layer_norm(z, blk.ln_read_z), ref_layer_norm(p, blk.ln_read_p), blk.read)
        for layer in blk.compute:
            h = ref_layer_norm(z, layer["ln_attn"])
            z = z + ref_attention(h, h, layer["attn"])
            z = z + ref_mlp(ref_layer_norm(z, layer["ln_mlp"]), layer["mlp"])
        p = p + ref_attention(ref_layer_norm(p, blk.ln_write_p), ref_layer_norm(z, blk.ln_write_z), blk.write)
        p = p + ref_mlp(ref_layer_norm(p, blk.ln_point_mlp), blk.point_mlp)
    return ref_linear(ref_layer_norm(p, model.ln_out), model.out)


@pytest.mark.parametrize(
    "overrides",
    [
        {"compute_layers": 2},
        {"joint_offsets": False, "point_channels": 6, "posenc": "nerf", "posenc_include_input": True,
         "point_width": None, "rw_heads": 4},
        {"body_points": 5},
    ],
    ids=["offsets-2compute", "normals-nerf-equal-widths", "posed-body-tokens"],
)  # fmt: skip
def test_forward_matches_slow_reference_float64(overrides):
    model = tiny_model(**overrides).double()
    with torch.no_grad():  # every parameter random, so a swapped LayerNorm or bias shows
        g = torch.Generator().manual_seed(5)
        for prm in model.parameters():
            prm.add_(0.1 * torch.randn(prm.shape, generator=g, dtype=prm.dtype))
    x, t, joints = inputs(N=37, C=model.config.point_channels, dtype=torch.float64)
    K = model.config.body_points
    body = torch.randn(x.shape[0], K, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64) if K else None
    got = model(x, t, PoseCondition(joints, body=body) if K else joints)
    with torch.no_grad():
        want = reference_forward(model, x, t, joints, body)
    assert got.dtype == torch.float64 and want.abs().mean() > 0.1
    torch.testing.assert_close(got, want, atol=1e-10, rtol=1e-10)


def test_sdpa_matches_dense_forward_and_backward():
    model = tiny_model()
    x, t, joints = inputs()
    outs, grads = {}, {}
    for impl in ("sdpa", "dense"):
        model.set_attention_impl(impl).zero_grad()
        y = model(x, t, joints)
        (y**2).mean().backward()
        outs[impl] = y.detach()
        grads[impl] = torch.cat([p.grad.flatten() for p in model.parameters()])
    torch.testing.assert_close(outs["sdpa"], outs["dense"], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(grads["sdpa"], grads["dense"], atol=1e-5, rtol=1e-4)
    with pytest.raises(ValueError, match="attention impl"):
        model.set_attention_impl("flash3")


# --------------------------------------------------------------------- model properties
@pytest.mark.parametrize("N", [1, 2, 37, 257])
def test_output_shape_for_any_N(N):
    model = tiny_model()
    x, t, joints = inputs(N=N)
    y = model(x, t, joints)
    assert y.shape == (2, N, 3) and y.dtype == torch.float32 and torch.isfinite(y).all()


def test_permutation_equivariance():
    model = tiny_model()
    x, t, joints = inputs(N=101)
    y = model(x, t, joints)
    perm = torch.randperm(101, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(model(x[:, perm], t, joints), y[:, perm], atol=1e-5, rtol=1e-5)


def test_read_is_a_mean_so_duplicating_the_cloud_changes_nothing():
    """The read's softmax over points makes each latent a weighted *mean* of the cloud: feeding
    every point twice leaves the latents, hence every point's output, unchanged (no drift with N)."""
    model = tiny_model()
    x, t, joints = inputs(N=50)
    y = model(x, t, joints)
    y2 = model(torch.cat([x, x], dim=1), t, joints)
    torch.testing.assert_close(y2, torch.cat([y, y], dim=1), atol=1e-5, rtol=1e-5)


def test_zero_output_at_init():
    torch.manual_seed(0)
    model = LatentDenoiser(LATENT_PRESETS["tiny"])
    assert torch.count_nonzero(model(*inputs())) == 0


def test_gradients_reach_every_parameter():
    model = tiny_model(compute_layers=2, joint_offsets=True).train()
    x, t, joints = inputs()
    (model(x, t, joints) ** 2).mean().backward()
    dead = [n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert dead == []


def test_batch_independence_and_conditioning():
    model = tiny_model()
    x, t, joints = inputs(B=3)
    y = model(x, t, joints)
    # sample b depends only on its own inputs
    torch.testing.assert_close(model(x[1:2], t[1:2], joints[1:2]), y[1:2], atol=1e-5, rtol=1e-5)
    x2, joints2 = x.clone(), joints.clone()
    x2[0] += 1.0
    joints2[2] -= 0.5
    y2 = model(x2, t.clone().index_fill_(0, torch.tensor([2]), 7), joints2)
    torch.testing.assert_close(y2[1], y[1], atol=1e-5, rtol=1e-5)
    # the output depends on the timestep and on the joints
    assert (model(x, t + 100, joints) - y).abs().max() > 1e-3
    assert (model(x, t, joints + 0.3) - y).abs().max() > 1e-3
    # a scalar t is broadcast over the batch
    torch.testing.assert_close(model(x, torch.tensor(5), joints), model(x, torch.full((3,), 5), joints))


def test_bf16_autocast():
    model = tiny_model()
    x, t, joints = inputs()
    ref = model(x, t, joints)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = model(x, t, joints)
    assert y.dtype == torch.float32 and torch.isfinite(y).all()
    assert (y - ref).abs().max() < 0.05 * ref.abs().max()


# --------------------------------------------------------------------- config
def test_config_round_trip_and_presets():
    for name, cfg in LATENT_PRESETS.items():
        d = json.loads(json.dumps(cfg.to_dict()))
        assert LatentDenoiserConfig.from_dict(d) == cfg, name
    cfg = latent_preset("tiny", num_latents=5)
    assert cfg.num_latents == 5 and cfg.replace(num_latents=8) == LATENT_PRESETS["tiny"]
    assert cfg.num_tokens == 5 + 1 + 24 and LATENT_PRESETS["paper"].point_dim == 128
    assert LatentDenoiserConfig(point_width=None).point_dim == 512
    # the diffusion code reads these fields like PocoLocoDenoiserConfig's; the parametrisation is not
    # the network's (an older checkpoint's stored one is dropped on read, nothing else is)
    model = LatentDenoiser(latent_preset("tiny"))
    assert model.config.point_channels == 3 and not hasattr(model, "prediction_type")
    old = {**LATENT_PRESETS["tiny"].to_dict(), "prediction_type": "epsilon"}
    assert LatentDenoiserConfig.from_dict(old) == LATENT_PRESETS["tiny"]
    with pytest.raises(ValueError, match="unknown LatentDenoiserConfig field"):
        LatentDenoiserConfig.from_dict({**old, "prediction": "epsilon"})


def test_preset_parameter_counts():
    counts = {name: LatentDenoiser(cfg).num_parameters() for name, cfg in LATENT_PRESETS.items()}
    assert counts == {"paper": 29_655_043, "base": 9_100_227, "small": 3_806_723, "tiny": 43_747}


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("width", 0, "width must be >= 1"),
        ("depth", 0, "depth must be >= 1"),
        ("compute_layers", 0, "compute_layers must be >= 1"),
        ("num_latents", 0, "num_latents must be >= 1"),
        ("point_width", 0, "point_width must be >= 1"),
        ("rw_heads", 3, "point_width 16 is not divisible by rw_heads 3"),
        ("heads", 3, "width 32 is not divisible by heads 3"),
        ("head_dim", 0, "head_dim must be >= 1"),
        ("mlp_ratio", 0.0, "mlp_ratio must be > 0"),
        ("point_mlp_ratio", -1.0, "point_mlp_ratio must be > 0"),
        ("posenc", "fourier", "posenc must be one of"),
        ("attention", "flash3", "attention must be one of"),
        ("point_channels", 4, "point_channels must be 3"),
        ("dropout", 1.0, "dropout must be in"),
    ],
)
def test_config_validation_errors_name_the_field(field, value, match):
    with pytest.raises(ValueError, match=match) as err:
        latent_preset("tiny", **{field: value})
    assert "\n" not in str(err.value)


def test_unknown_fields_and_presets():
    with pytest.raises(ValueError, match="unknown LatentDenoiserConfig field.*: latent_count$"):
        LatentDenoiserConfig.from_dict({**LATENT_PRESETS["tiny"].to_dict(), "latent_count": 3})
    with pytest.raises(ValueError, match="unknown LatentDenoiserConfig field.*: latent_count$"):
        LATENT_PRESETS["tiny"].replace(latent_count=3)
    with pytest.raises(ValueError, match="unknown latent denoiser preset 'huge'; choose one of: paper, small, base, tiny"):
        latent_preset("huge")


def test_forward_validation_errors_name_the_argument():
    model = tiny_model()
    x, t, joints = inputs()
    with pytest.raises(ValueError, match="joints must have 24 joints"):
        model(x, t, joints[:, :22])
    with pytest.raises(ValueError, match="joints must have shape"):
        model(x, t, joints[..., :2])
    with pytest.raises(ValueError, match="x must have shape"):
        model(x[..., :2], t, joints)
    with pytest.raises(ValueError, match="x must have shape"):
        model(x[:, :0], t, joints)
    with pytest.raises(ValueError, match="t must have shape"):
        model(x, t[:1], joints)
    bad = x.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="x contains NaN"):
        model(bad, t, joints)


# --------------------------------------------------------------------- diffusion plumbing
def test_plugs_into_diffusion_loss_and_samplers():
    """``diffusion_loss`` and the samplers take the network unchanged (cond = joints)."""
    torch.manual_seed(0)
    model = LatentDenoiser(LATENT_PRESETS["tiny"])
    schedule = NoiseSchedule.from_kind("four", 1000)
    x0, _, joints = inputs(N=64)
    loss, logs = diffusion_loss(model, x0, joints, schedule, "epsilon",
                                generator=torch.Generator().manual_seed(0))  # fmt: skip
    loss.backward()
    assert math.isfinite(logs["loss"]) and model.out.weight.grad.abs().sum() > 0
    # sample 3 of a batch is the same whatever the batch (per-sample seeds, batch-independent net)
    nn.init.normal_(model.out.weight, std=0.2)
    model.eval()

    def run(kind, seeds, cond):
        rng = PerSampleRNG(seeds)
        return sample(kind, model, schedule, rng.randn((64, 3)), cond, rng=rng, steps=4)

    for kind in ("dpm++sde", "ddim"):
        a = run(kind, [3, 4], joints)
        b = run(kind, [4], joints[1:])
        assert a.shape == (2, 64, 3) and torch.isfinite(a).all()
        torch.testing.assert_close(a[1], b[0], atol=1e-5, rtol=1e-5)


def test_tiny_learns_one_batch():
    """A few AdamW steps on the epsilon loss of one fixed batch reduce it (training smoke test)."""
    torch.manual_seed(0)
    model = LatentDenoiser(LATENT_PRESETS["tiny"]).train()
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    x0, t, joints = inputs(N=64)
    noise = torch.randn_like(x0)
    xt = 0.6 * x0 + 0.8 * noise
    losses = []
    for _ in range(40):
        loss = ((model(xt, t, joints) - noise) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]
