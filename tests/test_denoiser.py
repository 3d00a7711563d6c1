"""PocoLoco denoiser: encodings, SDPA vs dense reference, invariances, validation, training smoke."""

import math

import pytest
import torch
from torch import nn

from pocoloco.models import (
    DENOISER_PRESETS,
    PocoLocoDenoiser,
    PocoLocoDenoiserConfig,
    attention,
    denoiser_preset,
    dense_attention,
    nerf_encoding,
    positional_encoding,
    positional_encoding_dim,
    timestep_embedding,
    transformer_encoding,
)

# tiny models run fastest on one thread, and bit-exact comparisons need a fixed thread count
pytestmark = pytest.mark.usefixtures("torch_single_thread")


def tiny_model(seed: int = 0, **overrides) -> PocoLocoDenoiser:
    """Tiny denoiser whose zero-initialised output layer is randomised so outputs are non-trivial."""
    torch.manual_seed(seed)
    model = PocoLocoDenoiser(denoiser_preset("tiny", **overrides))
    nn.init.normal_(model.out.weight, std=0.2)
    nn.init.normal_(model.out.bias, std=0.2)
    return model.eval()


def inputs(B=2, N=100, C=3, J=24, seed=1):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, N, C, generator=g)
    t = torch.randint(0, 1000, (B,), generator=g)
    joints = torch.randn(B, J, 3, generator=g) * 0.5
    return x, t, joints


# --------------------------------------------------------------------- encodings
def test_nerf_encoding_values():
    x = torch.tensor([[0.5, 0.0, 0.25]])
    enc = nerf_encoding(x, num_freqs=2)  # sin(x pi), sin(2 x pi) per axis, then cos
    expected_sin = [math.sin(0.5 * math.pi), math.sin(math.pi), 0.0, 0.0, math.sin(0.25 * math.pi), math.sin(0.5 * math.pi)]
    expected_cos = [math.cos(0.5 * math.pi), math.cos(math.pi), 1.0, 1.0, math.cos(0.25 * math.pi), math.cos(0.5 * math.pi)]
    torch.testing.assert_close(enc[0], torch.tensor(expected_sin + expected_cos), atol=1e-6, rtol=0)
    assert nerf_encoding(x, 7, include_input=True).shape == (1, 45)
    torch.testing.assert_close(nerf_encoding(x, 7, include_input=True)[..., -3:], x)


def test_transformer_encoding_values():
    x = torch.tensor([[0.3, -1.2, 2.0]])
    L = 7
    enc = transformer_encoding(x, L)
    assert enc.shape == (1, 42) == (1, positional_encoding_dim(3, L))
    freqs = [10000.0 ** (-2 * i / (2 * L)) for i in range(L)]
    for a in range(3):
        for i, w in enumerate(freqs):
            assert enc[0, a * 2 * L + 2 * i].item() == pytest.approx(math.sin(w * x[0, a].item()), abs=1e-6)
            assert enc[0, a * 2 * L + 2 * i + 1].item() == pytest.approx(math.cos(w * x[0, a].item()), abs=1e-6)
    with pytest.raises(ValueError, match="positional encoding"):
        positional_encoding(x, "fourier", 7)


def test_timestep_embedding():
    emb = timestep_embedding(torch.tensor([0, 10, 999]), 16)
    assert emb.shape == (3, 16)
    torch.testing.assert_close(emb[0], torch.cat([torch.ones(8), torch.zeros(8)]))
    assert emb[1, 8].item() == pytest.approx(math.sin(10.0))  # first frequency is 1


# --------------------------------------------------------------------- attention
@pytest.mark.parametrize("M", [24, 37])
def test_sdpa_matches_dense_reference(M):
    g = torch.Generator().manual_seed(0)
    q = torch.randn(2, 3, 37, 16, generator=g)
    k, v = torch.randn(2, 2, 3, M, 16, generator=g)
    torch.testing.assert_close(attention(q, k, v, "sdpa"), dense_attention(q, k, v), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="attention impl"):
        attention(q, k, v, "flash3")


def test_model_sdpa_matches_dense_forward_and_backward():
    model = tiny_model()
    x, t, joints = inputs()
    outs, grads = {}, {}
    for impl in ("sdpa", "dense"):
        model.set_attention_impl(impl).zero_grad()
        y = model(x, t, joints)
        (y**2).mean().backward()
        outs[impl] = y.detach()
        grads[impl] = torch.cat([p.grad.flatten() for p in model.parameters()])
    assert outs["sdpa"].abs().mean() > 0.1
    torch.testing.assert_close(outs["sdpa"], outs["dense"], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(grads["sdpa"], grads["dense"], atol=1e-5, rtol=1e-4)


# --------------------------------------------------------------------- model properties
def test_zero_initialised_output():
    torch.manual_seed(0)
    model = PocoLocoDenoiser(DENOISER_PRESETS["tiny"])
    assert torch.count_nonzero(model(*inputs())) == 0


@pytest.mark.parametrize("N", [100, 257])
def test_any_resolution_and_permutation_equivariance(N):
    model = tiny_model()
    x, t, joints = inputs(N=N)
    y = model(x, t, joints)
    assert y.shape == (2, N, 3) and y.dtype == torch.float32
    perm = torch.randperm(N, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(model(x[:, perm], t, joints), y[:, perm], atol=1e-5, rtol=1e-5)


def test_conditioning_and_batch_independence():
    model = tiny_model()
    x, t, joints = inputs(B=3)
    y = model(x, t, joints)
    # each sample depends only on its own inputs
    torch.testing.assert_close(model(x[1:2], t[1:2], joints[1:2]), y[1:2], atol=1e-5, rtol=1e-5)
    # the output depends on the timestep and on the joints
    assert (model(x, t + 100, joints) - y).abs().max() > 1e-3
    assert (model(x, t, joints + 0.3) - y).abs().max() > 1e-3
    # a scalar t is broadcast over the batch
    torch.testing.assert_close(model(x, torch.tensor(5), joints), model(x, torch.full((3,), 5), joints))


def test_joint_offset_features_match_a_loop():
    from pocoloco.models.pocoloco import joint_offset_features

    x, _, joints = inputs(B=2, N=7, J=5)
    f = joint_offset_features(x, joints)
    assert f.shape == (2, 7, 20)
    for b in range(2):
        for i in range(7):
            for j in range(5):
                d = x[b, i] - joints[b, j]
                torch.testing.assert_close(f[b, i, 3 * j : 3 * j + 3], d)
                torch.testing.assert_close(f[b, i, 15 + j], d.norm())


def test_joint_offsets_model_equivariant_and_pose_dependent():
    model = tiny_model(joint_offsets=True)
    x, t, joints = inputs(N=64)
    y = model(x, t, joints)
    perm = torch.randperm(64, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(model(x[:, perm], t, joints), y[:, perm], atol=1e-5, rtol=1e-5)
    # the offset branch is live: zeroing it changes the output
    with torch.no_grad():
        model.offset_in[-1].weight.zero_()
        model.offset_in[-1].bias.zero_()
    assert (model(x, t, joints) - y).abs().max() > 1e-4
    assert model.num_parameters() > PocoLocoDenoiser(denoiser_preset("tiny")).num_parameters()


@pytest.mark.parametrize("posenc", ["nerf", "transformer"])
def test_posenc_variants_and_normals(posenc):
    model = tiny_model(posenc=posenc, point_channels=6, posenc_include_input=True)
    x, t, joints = inputs(C=6)
    y = model(x, t, joints)
    assert y.shape == (2, 100, 6) and torch.isfinite(y).all()


def test_bf16_autocast():
    model = tiny_model()
    x, t, joints = inputs()
    ref = model(x, t, joints)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = model(x, t, joints)
    assert y.dtype == torch.float32 and torch.isfinite(y).all()
    assert (y - ref).abs().max() < 0.05 * ref.abs().max()


def test_validation_errors_name_the_argument():
    model = tiny_model()
    x, t, joints = inputs()
    with pytest.raises(ValueError, match="joints must have 24 joints"):
        model(x, t, joints[:, :22])
    with pytest.raises(ValueError, match="joints must have shape"):
        model(x, t, joints[..., :2])
    with pytest.raises(ValueError, match="x must have shape"):
        model(x[..., :2], t, joints)
    with pytest.raises(ValueError, match="t must have shape"):
        model(x, t[:1], joints)
    bad = x.clone()
    bad[0, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="x contains NaN"):
        model(bad, t, joints)
    with pytest.raises(ValueError, match="unknown denoiser preset"):
        denoiser_preset("huge")
    with pytest.raises(ValueError, match="posenc"):
        PocoLocoDenoiserConfig(posenc="fourier")


def test_preset_parameter_counts():
    counts = {name: PocoLocoDenoiser(cfg).num_parameters() for name, cfg in DENOISER_PRESETS.items()}
    assert counts == {"paper": 34_218_499, "small": 1_135_491, "tiny": 39_907}


def test_tiny_overfits_one_batch():
    """A few AdamW steps on the epsilon loss of one fixed batch reduce it (training smoke test)."""
    torch.manual_seed(0)
    model = PocoLocoDenoiser(DENOISER_PRESETS["tiny"]).train()
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


def test_condition_tokens_shape_the_output_and_are_checked():
    """Outfit / body-shape tokens (models.conditioning): the output depends on them, a model without
    them refuses them, a model with them needs them; a grown outfit table keeps the old codes."""
    from pocoloco.models import denoiser_preset
    from pocoloco.models.conditioning import PoseCondition
    from pocoloco.models.pocoloco import PocoLocoDenoiser

    torch.manual_seed(0)
    net = PocoLocoDenoiser(denoiser_preset("tiny").replace(num_outfits=3, shape_dim=6)).eval()
    torch.nn.init.normal_(net.out.weight, std=0.1)  # the zero-initialised head would hide everything
    x, t, j = torch.randn(2, 9, 3), torch.tensor([5, 500]), torch.randn(2, 24, 3)
    shape = torch.rand(2, 6)
    a = net(x, t, PoseCondition(j, torch.tensor([0, 1]), shape))
    b = net(x, t, PoseCondition(j, torch.tensor([2, 1]), shape))
    assert not torch.allclose(a[0], b[0]) and torch.allclose(a[1], b[1])  # per sample
    c = net(x, t, PoseCondition(j, torch.tensor([0, 1]), shape + 0.3))
    assert not torch.allclose(a, c)
    with pytest.raises(ValueError, match="needs an outfit id"):
        net(x, t, j)
    with pytest.raises(ValueError, match=r"outfit ids must be in \[0, 3\)"):
        net(x, t, PoseCondition(j, torch.tensor([0, 3]), shape))
    plain = PocoLocoDenoiser(denoiser_preset("tiny"))
    with pytest.raises(ValueError, match="no outfit"):
        plain(x, t, PoseCondition(j, torch.tensor([0, 1]), None))
    new = net.who.add_outfit()
    assert new == 3 and torch.allclose(net(x, t, PoseCondition(j, torch.tensor([0, 1]), shape)), a)
