"""Tests for pocoloco.diffusion: schedules, samplers (against diffusers as an oracle), loss."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from pocoloco.diffusion import (
    ALPHA_BAR_MIN,
    NoiseSchedule,
    PerSampleRNG,
    diffusion_loss,
    make_betas,
    make_noise,
    make_timesteps,
    min_snr_weight,
    sample,
    sample_ddim,
    sample_ddpm,
    sample_dpmpp,
    sample_unipc,
)
from pocoloco.diffusion.samplers import SAMPLER_STEPS, SAMPLERS, dpmpp_coefficients
from pocoloco.diffusion.unipc import unipc_rhos

diffusers = pytest.importorskip("diffusers")
# diffusers 0.42 + numpy 2: harmless copy-keyword DeprecationWarning inside DPMSolverMultistep
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")

T = 1000
PRED_TYPES = ("epsilon", "sample", "v_prediction")


def fake_denoiser(x: torch.Tensor, t: torch.Tensor, cond=None) -> torch.Tensor:
    """A fixed, bounded, smooth function of (x, t), per sample (diffusers-test style)."""
    tt = t.to(x.dtype).view(-1, *([1] * (x.ndim - 1))) / T
    return 0.5 * torch.tanh(x * (1 + tt)) + 0.3 * tt * torch.sin(3 * x + tt)


@pytest.fixture(scope="module")
def four() -> NoiseSchedule:
    return NoiseSchedule.from_kind("four", T)


# -- schedules ---------------------------------------------------------------------------------


def test_betas_formulas_and_terminal_alpha_bar():
    lin, four_, cos = make_betas("linear"), make_betas("four"), make_betas("cosine")
    for b in (lin, four_, cos):
        assert b.dtype == torch.float64 and b.shape == (T,)
    assert torch.allclose(four_, torch.linspace(1e-4**0.25, 0.02**0.25, T, dtype=torch.float64) ** 4)
    assert four_[0].item() == pytest.approx(1e-4) and four_[-1].item() == pytest.approx(0.02)
    assert torch.allclose(lin, torch.from_numpy(np.linspace(1e-4, 0.02, T)))
    # terminal alpha_bar of the 'four' schedule (1000 steps, 1e-4 .. 0.02)
    assert torch.prod(1 - four_).item() == pytest.approx(0.00418, rel=0.01)
    assert torch.prod(1 - lin).item() == pytest.approx(4.04e-5, rel=0.01)
    # the paper's literal (t / 10000)^4 would leave alpha_bar_T ~ 0.98 (the typo)
    literal = (torch.arange(1, T + 1, dtype=torch.float64) / 10000) ** 4
    assert torch.prod(1 - literal).item() > 0.97
    # cosine: Nichol & Dhariwal, equal to diffusers' squaredcos_cap_v2 (float32 there)
    from diffusers.schedulers.scheduling_ddpm import betas_for_alpha_bar

    assert torch.allclose(cos, betas_for_alpha_bar(T).double(), rtol=1e-5, atol=1e-7)
    assert cos.max().item() == pytest.approx(0.999)
    with pytest.raises(ValueError, match="unknown beta schedule"):
        make_betas("quadratic")


def test_schedule_tables_against_diffusers(four):
    ref = diffusers.DDPMScheduler(num_train_timesteps=T, trained_betas=four.betas.numpy(), variance_type="fixed_small")
    assert torch.allclose(four.alphas_cumprod, ref.alphas_cumprod.double(), rtol=1e-5)
    ref.set_timesteps(T)
    for t in (1, 10, 500, 999):
        # diffusers forms 1 - abar in float32: ~3e-4 relative error at t = 1
        assert four.posterior_variance[t].item() == pytest.approx(ref._get_variance(t).item(), rel=1e-3)
    assert four.posterior_variance[0].item() == 0.0
    assert torch.isfinite(four.posterior_log_variance_clipped).all()
    assert four.posterior_log_variance_clipped[0] == four.posterior_log_variance_clipped[1]
    # posterior mean coefficients reproduce E[x_{t-1} | x_t, x0] of a one-step forward chain
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(3, 5, 3, generator=g, dtype=torch.float64)
    eps = torch.randn(3, 5, 3, generator=g, dtype=torch.float64)
    t = torch.tensor([0, 7, 999])
    ours = four.add_noise(x0, eps, t)
    theirs = ref.add_noise(x0.float(), eps.float(), t)
    assert torch.allclose(ours.float(), theirs, atol=1e-5)


@pytest.mark.parametrize("prediction_type", PRED_TYPES)
def test_prediction_conversions_roundtrip(four, prediction_type):
    g = torch.Generator().manual_seed(1)
    x0 = torch.randn(4, 6, 3, generator=g, dtype=torch.float64)
    eps = torch.randn(4, 6, 3, generator=g, dtype=torch.float64)
    t = torch.tensor([0, 100, 600, 999])
    x_t = four.add_noise(x0, eps, t)
    target = four.training_target(x0, eps, t, prediction_type)
    eps_hat, x0_hat = four.pred_to_eps_x0(target, x_t, t, prediction_type)
    assert torch.allclose(eps_hat, eps, atol=1e-9) and torch.allclose(x0_hat, x0, atol=1e-9)
    snr = four.snr(t)
    assert torch.allclose(snr, four.alphas_cumprod[t] / (1 - four.alphas_cumprod[t]))
    with pytest.raises(ValueError, match="t must have shape"):
        four.add_noise(x0, eps, t[:2])


# -- timesteps ---------------------------------------------------------------------------------


def test_timestep_spacings_match_diffusers():
    for steps in (1, 10, 20, 50, 1000):
        ddim = diffusers.DDIMScheduler(num_train_timesteps=T, timestep_spacing="trailing")
        ddim.set_timesteps(steps)
        assert make_timesteps(T, steps, "trailing") == ddim.timesteps.tolist()
    for steps in (10, 20):
        dpm = diffusers.DPMSolverMultistepScheduler(num_train_timesteps=T, timestep_spacing="linspace")
        dpm.set_timesteps(steps)
        assert make_timesteps(T, steps, "linspace") == dpm.timesteps.tolist()
    assert make_timesteps(T, T) == list(range(T - 1, -1, -1))
    with pytest.raises(ValueError, match="spacing"):
        make_timesteps(T, 10, "leading")
    with pytest.raises(ValueError, match="steps"):
        make_timesteps(T, 0)


@pytest.mark.parametrize("kind", ["four", "linear"])
def test_karras_and_lambda_spacings_match_diffusers(kind):
    """"karras" = diffusers' use_karras_sigmas, "lambda" = use_lu_lambdas (their rounded timesteps)."""
    sched = NoiseSchedule.from_betas(make_betas(kind, T).float().double())
    for spacing, flag in (("karras", "use_karras_sigmas"), ("lambda", "use_lu_lambdas")):
        for steps in (2, 3, 5, 8, 10, 15, 20, 25):
            ref = diffusers.DPMSolverMultistepScheduler(num_train_timesteps=T, trained_betas=sched.betas.numpy(),
                                                        **{flag: True})  # fmt: skip
            ref.set_timesteps(steps)
            ours = make_timesteps(T, steps, spacing, sched.alphas_cumprod)
            assert ours == ref.timesteps.tolist(), (spacing, steps)
            assert ours[0] == T - 1 and ours[-1] == 0
    # many steps: rounding collides near t = 0; the list stays strictly decreasing with `steps` entries
    for spacing in ("karras", "lambda"):
        ts = make_timesteps(T, 300, spacing, sched.alphas_cumprod)
        assert len(ts) == 300 and all(a > b for a, b in itertools.pairwise(ts)) and ts[0] == T - 1 and ts[-1] == 0
    with pytest.raises(ValueError, match="alphas_cumprod"):
        make_timesteps(T, 10, "karras")


# -- step-for-step against diffusers -----------------------------------------------------------


def _collect():
    xs = []
    return xs, lambda info: xs.append(info.x.clone())


def _diffusers_loop(scheduler, noise, steps, step_kwargs=None):
    """Run a diffusers scheduler with fake_denoiser; steps None: its timesteps are already set."""
    if steps is not None:
        scheduler.set_timesteps(steps)
    x, xs = noise.clone(), []
    for t in scheduler.timesteps:
        out = fake_denoiser(x, torch.full((x.shape[0],), int(t)))
        x = scheduler.step(out, t, x, **(step_kwargs or {})).prev_sample
        xs.append(x)
    return xs


def _assert_trajectories_close(ours, theirs, rtol):
    """Every step agrees to rtol relative to max(1, max |x|) of that step."""
    assert len(ours) == len(theirs)
    err = max((a - b).abs().max().item() / max(1.0, b.abs().max().item()) for a, b in zip(ours, theirs, strict=True))
    assert err < rtol, f"max relative trajectory difference {err:.2e} >= {rtol:.0e}"


def _float64_oracle(ref, schedule: NoiseSchedule):
    """Give a diffusers DDPM/DDIM scheduler float64 tables (they are float32 by default).

    In float32, 1 - abar near t = 0 carries ~3e-4 relative error, which puts the oracle itself
    ~1e-4 off a float64 computation over 1000 steps (measured); with float64 tables and float64
    samples the two implementations agree to ~1e-10.
    """
    ref.betas = schedule.betas.clone()
    ref.alphas = schedule.alphas.clone()
    ref.alphas_cumprod = schedule.alphas_cumprod.clone()
    ref.one = torch.tensor(1.0, dtype=torch.float64)
    if hasattr(ref, "final_alpha_cumprod"):
        ref.final_alpha_cumprod = torch.tensor(1.0, dtype=torch.float64)
    return ref


@pytest.mark.parametrize("prediction_type", PRED_TYPES)
@pytest.mark.parametrize("steps", [50, 1000])
def test_ddpm_matches_diffusers(four, prediction_type, steps):
    seeds = [11, 12]
    noise = make_noise((64, 3), [101, 102], dtype=torch.float64)
    ref = diffusers.DDPMScheduler(
        num_train_timesteps=T, trained_betas=four.betas.numpy(), variance_type="fixed_small",
        clip_sample=False, timestep_spacing="trailing", prediction_type=prediction_type,
    )  # fmt: skip
    gens = [torch.Generator().manual_seed(s) for s in seeds]
    theirs = _diffusers_loop(_float64_oracle(ref, four), noise, steps, {"generator": gens})
    ours, cb = _collect()
    out = sample_ddpm(fake_denoiser, four, noise, prediction_type=prediction_type, steps=steps,
                      rng=PerSampleRNG(seeds), progress=cb)  # fmt: skip
    assert out.dtype == torch.float64 and out.shape == noise.shape
    # diffusers adds 1e-10 * noise on the last step (variance clamped at 1e-20), we add none
    _assert_trajectories_close(ours, theirs, rtol=1e-8)


def test_ddpm_float32_matches_diffusers(four):
    """The everyday float32 path against diffusers' own float32 computation, 50 strided steps."""
    noise = make_noise((64, 3), [5, 6])
    ref = diffusers.DDPMScheduler(num_train_timesteps=T, trained_betas=four.betas.numpy(), clip_sample=False,
                                  timestep_spacing="trailing")  # fmt: skip
    theirs = _diffusers_loop(ref, noise, 50, {"generator": [torch.Generator().manual_seed(s) for s in (1, 2)]})
    ours, cb = _collect()
    out = sample_ddpm(fake_denoiser, four, noise, steps=50, rng=PerSampleRNG([1, 2]), progress=cb)
    assert out.dtype == torch.float32
    _assert_trajectories_close(ours, theirs, rtol=1e-5)


def test_ddpm_clip_matches_diffusers(four):
    noise = make_noise((64, 3), [5, 6], dtype=torch.float64) * 2
    ref = diffusers.DDPMScheduler(
        num_train_timesteps=T, trained_betas=four.betas.numpy(), clip_sample=True, clip_sample_range=0.5,
        timestep_spacing="trailing",
    )  # fmt: skip
    gens = [torch.Generator().manual_seed(s) for s in (1, 2)]
    theirs = _diffusers_loop(_float64_oracle(ref, four), noise, 25, {"generator": gens})
    ours, cb = _collect()
    sample_ddpm(fake_denoiser, four, noise, steps=25, clip=0.5, rng=PerSampleRNG([1, 2]), progress=cb)
    _assert_trajectories_close(ours, theirs, rtol=1e-8)


@pytest.mark.parametrize("prediction_type", PRED_TYPES)
@pytest.mark.parametrize("eta", [0.0, 1.0])
def test_ddim_matches_diffusers(four, prediction_type, eta):
    seeds = [21, 22, 23]
    noise = make_noise((64, 3), [201, 202, 203], dtype=torch.float64)
    ref = diffusers.DDIMScheduler(
        num_train_timesteps=T, trained_betas=four.betas.numpy(), clip_sample=False, set_alpha_to_one=True,
        timestep_spacing="trailing", prediction_type=prediction_type,
    )  # fmt: skip
    gens = [torch.Generator().manual_seed(s) for s in seeds]
    theirs = _diffusers_loop(_float64_oracle(ref, four), noise, 50, {"eta": eta, "generator": gens})
    ours, cb = _collect()
    sample_ddim(fake_denoiser, four, noise, prediction_type=prediction_type, steps=50, eta=eta,
                rng=PerSampleRNG(seeds), progress=cb)  # fmt: skip
    _assert_trajectories_close(ours, theirs, rtol=1e-10)


def test_ddim_clip_matches_diffusers(four):
    noise = make_noise((64, 3), [7, 8], dtype=torch.float64) * 2
    ref = diffusers.DDIMScheduler(
        num_train_timesteps=T, trained_betas=four.betas.numpy(), clip_sample=True, clip_sample_range=0.5,
        timestep_spacing="trailing",
    )  # fmt: skip
    theirs = _diffusers_loop(_float64_oracle(ref, four), noise, 50, {"use_clipped_model_output": True})
    ours, cb = _collect()
    sample_ddim(fake_denoiser, four, noise, steps=50, clip=0.5, progress=cb)
    _assert_trajectories_close(ours, theirs, rtol=1e-10)


@pytest.mark.parametrize(
    ("kind", "prediction_type", "steps", "spacing", "order"),
    [
        ("four", "epsilon", 20, "trailing", 2),
        ("four", "epsilon", 20, "linspace", 2),
        ("four", "sample", 20, "trailing", 2),
        ("four", "v_prediction", 20, "trailing", 2),
        ("four", "epsilon", 10, "trailing", 2),  # < 15 steps: diffusers' lower_order_final branch
        ("four", "epsilon", 20, "trailing", 1),
        ("linear", "epsilon", 20, "trailing", 2),
        ("cosine", "epsilon", 20, "trailing", 2),  # alpha_bar_T = 2.4e-9
    ],
)
def test_dpmpp_matches_diffusers(kind, prediction_type, steps, spacing, order):
    # both sides on the same float32-rounded betas (diffusers rounds trained_betas to float32)
    sched = NoiseSchedule.from_betas(make_betas(kind, T).float().double())
    noise = make_noise((64, 3), [301, 302])
    ref = diffusers.DPMSolverMultistepScheduler(
        num_train_timesteps=T, trained_betas=sched.betas.numpy(), algorithm_type="dpmsolver++",
        solver_order=order, prediction_type=prediction_type, timestep_spacing=spacing,
    )  # fmt: skip
    theirs = _diffusers_loop(ref, noise, steps)
    ours, cb = _collect()
    sample_dpmpp(fake_denoiser, sched, noise, prediction_type=prediction_type, steps=steps, order=order,
                 spacing=spacing, progress=cb)  # fmt: skip
    # diffusers' DPM-Solver computes in float32 whatever the input dtype: compare in float32
    _assert_trajectories_close(ours, theirs, rtol=1e-5)


@pytest.mark.parametrize(("steps", "order"), [(25, 2), (10, 2), (20, 1)])
def test_dpmpp_sde_matches_diffusers(four, steps, order):
    """SDE-DPM-Solver++(2M) step by step against diffusers' "sde-dpmsolver++" (midpoint), with
    the same per-sample generators (diffusers draws one (N, C) float32 noise per sample and step,
    as PerSampleRNG does)."""
    sched = NoiseSchedule.from_betas(make_betas("four", T).float().double())
    seeds = [21, 22]
    noise = make_noise((64, 3), [303, 304])
    ref = diffusers.DPMSolverMultistepScheduler(
        num_train_timesteps=T, trained_betas=sched.betas.numpy(), algorithm_type="sde-dpmsolver++",
        solver_order=order, timestep_spacing="trailing",
    )  # fmt: skip
    theirs = _diffusers_loop(ref, noise, steps, {"generator": [torch.Generator().manual_seed(s) for s in seeds]})
    ours, cb = _collect()
    sample("dpm++sde", fake_denoiser, sched, noise, steps=steps, order=order, rng=PerSampleRNG(seeds), progress=cb)
    _assert_trajectories_close(ours, theirs, rtol=1e-5)
    ode = sample("dpm++", fake_denoiser, sched, noise, steps=steps, order=order)
    assert not torch.allclose(ode, ours[-1], atol=1e-3)  # the noise really enters


@pytest.mark.parametrize("order", [2, 3])
def test_dpmpp_eta_interpolates_ode_and_sde(four, order):
    """eta = 1 is the SDE, eta = 0 the ODE (no noise drawn); eta = 0.5 lies in between, and the
    exact denoiser's toy data come out right for any eta."""
    noise = make_noise((64, 3), [311, 312])
    kw = {"steps": 12, "order": order}
    sde = sample_dpmpp(fake_denoiser, four, noise, stochastic=True, rng=PerSampleRNG([1, 2]), **kw)
    assert torch.equal(sample_dpmpp(fake_denoiser, four, noise, stochastic=True, eta=1.0, rng=PerSampleRNG([1, 2]), **kw), sde)
    rng = PerSampleRNG([1, 2])
    ode = sample_dpmpp(fake_denoiser, four, noise, stochastic=True, eta=0.0, rng=rng, **kw)
    assert torch.allclose(ode, sample_dpmpp(fake_denoiser, four, noise, **kw), atol=1e-6)
    assert torch.equal(rng.randn((1,)), PerSampleRNG([1, 2]).randn((1,)))  # eta 0 drew no noise
    half = sample_dpmpp(fake_denoiser, four, noise, stochastic=True, eta=0.5, rng=PerSampleRNG([1, 2]), **kw)
    assert (half - ode).abs().mean() < (sde - ode).abs().mean()
    den = MixtureDenoiser(four)
    rng = PerSampleRNG([0, 1, 2, 3])
    out = sample_dpmpp(den, four, rng.randn((1024, 3)), stochastic=True, eta=0.5, steps=25, rng=rng)
    _, _, within, frac = _mixture_stats(out)
    assert torch.allclose(within, torch.full((3,), SD, dtype=torch.float64), rtol=0.08), within
    assert abs(frac.item() - 0.5) < 0.04
    with pytest.raises(ValueError, match="eta"):
        sample_dpmpp(fake_denoiser, four, noise, stochastic=True, eta=-1.0)


def _set_custom_timesteps(ref, ts: list[int]) -> None:
    """UniPCMultistepScheduler.set_timesteps takes no custom timesteps: set them and their sigmas
    (final sigma 0) the way it does for its own spacings."""
    ref.set_timesteps(len(ts))
    ab = ref.alphas_cumprod.double().numpy()
    sig = np.sqrt((1 - ab) / ab)[ts]
    ref.timesteps = torch.tensor(ts, dtype=torch.int64)
    ref.sigmas = torch.from_numpy(np.concatenate([sig, [0.0]]).astype(np.float32))


@pytest.mark.parametrize(
    ("steps", "spacing", "prediction_type"),
    [
        (20, "trailing", "epsilon"),
        (10, "trailing", "epsilon"),  # < 15 steps: second-to-last step second order
        (5, "trailing", "epsilon"),
        (20, "lambda", "epsilon"),
        (10, "karras", "v_prediction"),
        (20, "linspace", "sample"),
    ],
)
def test_dpmpp3m_matches_diffusers(steps, spacing, prediction_type):
    """DPM-Solver++(3M) with diffusers' D2 coefficient ("half") step by step against
    DPMSolverMultistepScheduler(solver_order=3), on the same integer timesteps."""
    sched = NoiseSchedule.from_betas(make_betas("four", T).float().double())
    ts = make_timesteps(T, steps, spacing, sched.alphas_cumprod)
    noise = make_noise((64, 3), [305, 306])
    ref = diffusers.DPMSolverMultistepScheduler(num_train_timesteps=T, trained_betas=sched.betas.numpy(),
                                                algorithm_type="dpmsolver++", solver_order=3,
                                                prediction_type=prediction_type)  # fmt: skip
    ref.set_timesteps(timesteps=ts)
    theirs = _diffusers_loop(ref, noise, None)
    ours, cb = _collect()
    sample("dpm++3m", fake_denoiser, sched, noise, prediction_type=prediction_type, timesteps=ts, d2="half",
           progress=cb)  # fmt: skip
    _assert_trajectories_close(ours, theirs, rtol=1e-5)
    exact = sample("dpm++3m", fake_denoiser, sched, noise, prediction_type=prediction_type, timesteps=ts)
    if steps > 5:  # the third-order term makes a difference (5 steps: one third-order step only)
        assert not torch.allclose(exact, ours[-1], atol=1e-5)


@pytest.mark.parametrize(
    ("steps", "order", "variant", "spacing", "prediction_type"),
    [
        (20, 2, "bh2", "trailing", "epsilon"),
        (10, 2, "bh2", "trailing", "epsilon"),
        (10, 3, "bh2", "trailing", "epsilon"),
        (5, 3, "bh1", "trailing", "epsilon"),
        (10, 1, "bh2", "trailing", "epsilon"),
        (8, 3, "bh2", "karras", "v_prediction"),
        (10, 2, "bh1", "lambda", "epsilon"),
        (10, 2, "bh2", "trailing", "sample"),
        (20, 3, "bh2", "linspace", "epsilon"),
    ],
)
def test_unipc_matches_diffusers(steps, order, variant, spacing, prediction_type):
    """UniPC (predictor + corrector, data prediction) step by step against diffusers'
    UniPCMultistepScheduler on the same integer timesteps; one denoiser call per step."""
    sched = NoiseSchedule.from_betas(make_betas("four", T).float().double())
    ts = make_timesteps(T, steps, spacing, sched.alphas_cumprod)
    noise = make_noise((64, 3), [307, 308])
    ref = diffusers.UniPCMultistepScheduler(num_train_timesteps=T, trained_betas=sched.betas.numpy(),
                                            solver_order=order, solver_type=variant, predict_x0=True,
                                            prediction_type=prediction_type)  # fmt: skip
    _set_custom_timesteps(ref, ts)
    x, theirs = noise.clone(), []
    for t in ref.timesteps:
        x = ref.step(fake_denoiser(x, torch.full((x.shape[0],), int(t))), t, x).prev_sample
        theirs.append(x)
    ours, cb = _collect()
    calls = []

    def counting(x, t, c):
        calls.append(int(t[0]))
        return fake_denoiser(x, t, c)

    sample("unipc", counting, sched, noise, prediction_type=prediction_type, timesteps=ts, order=order,
           variant=variant, progress=cb)  # fmt: skip
    assert calls == ts
    _assert_trajectories_close(ours, theirs, rtol=1e-5)


def test_unipc_rhos_solve_the_order_conditions():
    """The predictor / corrector weights against a direct evaluation of Zhao et al.'s g_i(h) by
    numerical integration: g_i = int_0^1 e^{-h(1-s)} ... via phi_{i+1}(-h) = int_0^1 e^{-h(1-s)} s^i / i! ds."""
    h = 0.8
    for variant, B in (("bh1", -h), ("bh2", math.expm1(-h))):
        for rks in ([-0.7, 1.0], [-0.6, -1.5], [-0.6, -1.3, 1.0]):
            s = np.linspace(0.0, 1.0, 20001)
            g = []
            for i in range(1, len(rks) + 1):
                phi = np.trapezoid(np.exp(-h * (1 - s)) * s**i / math.factorial(i), s)  # phi_{i+1}(-h)
                g.append(-h * math.factorial(i) * phi)
            R = np.array([[r**i for r in rks] for i in range(len(rks))])
            assert np.allclose(unipc_rhos(h, rks, variant), np.linalg.solve(R, np.array(g) / B), rtol=1e-6)
    assert unipc_rhos(h, [1.0], "bh2").tolist() == [0.5]


def test_dpmpp_third_order_term_integrates_a_quadratic_exactly():
    """One 3M step with x0 quadratic in lambda: "exact" reproduces the exponential integral,
    diffusers' "half" does not (its c2 is half the exact one)."""
    h, h0, h1 = 0.7, 0.5, 0.9
    f = lambda u: 1 + 0.3 * u + 0.8 * u * u
    u = np.linspace(0.0, h, 200001)
    m0, m1, m2 = f(0.0), f(-h0), f(-h0 - h1)
    r0, r1 = h0 / h, h1 / h
    d1_0, d1_1 = (m0 - m1) / r0, (m1 - m2) / r1
    d2 = (d1_0 - d1_1) / (r0 + r1)
    for eta in (0.0, 1.0, 0.5):
        rate = 1.0 + eta
        integral = rate * np.trapezoid(np.exp(-rate * (h - u)) * f(u), u)
        _, c0, c1, c2 = dpmpp_coefficients(h, eta, "exact")
        assert c0 * m0 + c1 * (d1_0 + r0 * d2) + c2 * d2 == pytest.approx(integral, rel=1e-9)
        _, c0, c1, c2h = dpmpp_coefficients(h, eta, "half")
        assert c2h == pytest.approx(c2 / 2)
        assert abs(c0 * m0 + c1 * (d1_0 + r0 * d2) + c2h * d2 - integral) > 1e-2


def _slow_dpmpp3m(den, sched, noise, ts, seeds, stochastic):
    """A slow, obviously-correct DPM-Solver++(3M): each step integrates the Lagrange interpolant
    of the last p x0 estimates (in lambda) against the exponential kernel numerically (p = 1, 3),
    or takes the 2M midpoint step (p = 2); p = min(3, i + 1), at most 2 on the second-to-last
    step when there are fewer than 15, the last step returns x0."""
    gens = [torch.Generator().manual_seed(s) for s in seeds]
    ab = [sched.alpha_bar(t) for t in ts]
    lam = [0.5 * math.log(a / (1 - a)) for a in ab]
    x, hist, xs, n = noise.double(), [], [], len(ts)
    for i, t in enumerate(ts):
        eps = fake_denoiser(x.float(), torch.full((x.shape[0],), t)).double()
        x0 = (x - math.sqrt(1 - ab[i]) * eps) / math.sqrt(ab[i])
        hist = [*hist[-2:], (lam[i], x0)]
        if i == n - 1:
            xs.append(x0)
            break
        a_s, s_s, s_t = math.sqrt(ab[i + 1]), math.sqrt(1 - ab[i + 1]), math.sqrt(1 - ab[i])
        h = lam[i + 1] - lam[i]
        p = min(3, i + 1, 2 if (i == n - 2 and n < 15) else 3)
        rate = 2.0 if stochastic else 1.0
        if p == 2:
            (l1, m1), (l0, m0) = hist[-2:]
            integral = -math.expm1(-rate * h) * (m0 + 0.5 * h / (l0 - l1) * (m0 - m1))
        else:
            nodes = hist[-p:]
            u = np.linspace(0.0, h, 4001)
            weights = []
            for k, (lk, _) in enumerate(nodes):  # Lagrange basis k at u (u = lambda - lambda_t)
                basis = np.ones_like(u)
                for j, (lj, _) in enumerate(nodes):
                    if j != k:
                        basis *= (u - (lj - lam[i])) / (lk - lj)
                weights.append(rate * np.trapezoid(np.exp(-rate * (h - u)) * basis, u))
            integral = sum(w * m for w, (_, m) in zip(weights, nodes))
        decay = math.exp(-h) if stochastic else 1.0
        x = decay * s_s / s_t * x + a_s * integral
        if stochastic:
            z = torch.stack([torch.randn(x.shape[1:], generator=g) for g in gens]).double()
            x = x + s_s * math.sqrt(-math.expm1(-2 * h)) * z
        xs.append(x)
    return xs


@pytest.mark.parametrize(("kind", "steps", "spacing"), [("dpm++3m", 20, "trailing"), ("dpm++3m", 10, "lambda"),
                                                        ("dpm++3msde", 20, "trailing"), ("dpm++3msde", 8, "karras")])  # fmt: skip
def test_dpmpp3m_exact_matches_slow_reference(kind, steps, spacing):
    """3M (ODE and SDE, exact third-order term) against the quadrature reference, same noise
    streams. diffusers' sde-dpmsolver++ order 3 is no oracle here (see sample_dpmpp)."""
    sched = NoiseSchedule.from_kind("four", T)
    ts = make_timesteps(T, steps, spacing, sched.alphas_cumprod)
    seeds = [41, 42]
    noise = make_noise((64, 3), [309, 310])
    ref = _slow_dpmpp3m(fake_denoiser, sched, noise, ts, seeds, kind == "dpm++3msde")
    ours, cb = _collect()
    sample(kind, fake_denoiser, sched, noise, timesteps=ts, rng=PerSampleRNG(seeds), progress=cb)
    # trapezoid quadrature with 4001 nodes: ~1e-8 relative
    _assert_trajectories_close(ours, [r.float() for r in ref], rtol=1e-6)


def test_zero_terminal_snr_stays_finite():
    betas = make_betas("four").clone()
    betas[-1] = 1.0  # alpha_bar_T = 0 exactly
    sched = NoiseSchedule.from_betas(betas)
    assert sched.alphas_cumprod[-1].item() == 0.0
    noise = make_noise((32, 3), [0])
    for kind in ("ddpm", "ddim", "dpm++"):
        out = sample(kind, fake_denoiser, sched, noise, steps=10, rng=PerSampleRNG([1]))
        assert torch.isfinite(out).all(), kind
    assert ALPHA_BAR_MIN == 2.0**-24


# -- exact denoiser on a known distribution (EDM2-style toy) -------------------------------------

MU = torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64)
SD = 0.2


class MixtureDenoiser:
    """Exact eps-prediction for points iid from 0.5 N(MU, SD^2 I) + 0.5 N(-MU, SD^2 I) in R^3."""

    prediction_type = "epsilon"

    def __init__(self, schedule: NoiseSchedule):
        self.schedule = schedule
        self.calls = 0

    def __call__(self, x, t, cond=None):
        self.calls += 1
        x = x.double()
        ab = self.schedule.alphas_cumprod[t].view(-1, 1, 1)
        var = ab * SD**2 + 1 - ab
        means = torch.stack([MU, -MU]) * ab.sqrt().unsqueeze(-1)  # (B, 1, 2, 3)
        d2 = ((x.unsqueeze(2) - means) ** 2).sum(-1)  # (B, N, 2)
        r = torch.sigmoid((d2[..., 1:] - d2[..., :1]) / (2 * var))  # (B, N, 1) posterior of +MU
        mean = (2 * r - 1) * means[:, :, 0]  # (B, N, 3)
        return ((1 - ab).sqrt() * (x - mean) / var).float()


def _mixture_stats(x: torch.Tensor):
    pts = x.reshape(-1, 3).double()
    side = torch.sign(pts @ MU)
    within = pts - side[:, None] * MU
    return pts.mean(0), pts.std(0), within.std(0), (side > 0).double().mean()


@pytest.mark.parametrize(
    ("kind", "kwargs"),
    [("ddim", {"steps": 50}), ("dpm++", {"steps": 20}), ("dpm++sde", {"steps": 25}), ("ddpm", {}),
     ("dpm++3m", {"steps": 20}), ("dpm++3msde", {"steps": 25}), ("unipc", {"steps": 20, "order": 3}),
     ("unipc", {"steps": 20, "spacing": "karras"}), ("dpm++sde", {"steps": 25, "spacing": "lambda"})],
)  # fmt: skip
def test_exact_denoiser_reproduces_data(four, kind, kwargs):
    den = MixtureDenoiser(four)
    rng = PerSampleRNG([0, 1, 2, 3])
    noise = rng.randn((1024, 3))
    out = sample(kind, den, four, noise, rng=rng, **kwargs)
    assert den.calls == kwargs.get("steps", T)
    mean, std, within, frac = _mixture_stats(out)
    assert torch.allclose(mean, torch.zeros(3, dtype=torch.float64), atol=0.06), mean
    assert torch.allclose(std, (MU**2 + SD**2).sqrt(), rtol=0.05, atol=0.01), std
    # measured: DDIM-50 0.191-0.193, DPM++-20 0.187-0.191, DDPM-1000 0.199-0.203
    # (DDIM-10 0.157-0.182 and DDPM-50 0.178-0.182 would fail)
    assert torch.allclose(within, torch.full((3,), SD, dtype=torch.float64), rtol=0.08), within
    assert abs(frac.item() - 0.5) < 0.04


# -- seeds, inpainting, progress, dispatch -----------------------------------------------------


def test_make_noise_per_sample_invariance():
    a = make_noise((10, 3), [3, 4, 5])
    b = make_noise((10, 3), [4])
    assert torch.equal(a[1], b[0]) and not torch.equal(a[0], a[1])


@pytest.mark.parametrize(
    ("kind", "kwargs"),
    [("ddpm", {"steps": 100}), ("ddim", {"eta": 1.0}), ("dpm++", {}), ("dpm++sde", {}), ("dpm++3msde", {}),
     ("unipc", {})],
)  # fmt: skip
def test_sampling_per_sample_seed_invariance(four, kind, kwargs):
    den = MixtureDenoiser(four)
    mask = torch.zeros(1, 256, dtype=torch.bool)
    mask[:, :64] = True
    x0k = make_noise((256, 3), [99]) * 0.1

    def run(seeds):
        rng = PerSampleRNG(seeds)
        noise = rng.randn((256, 3))
        known = (mask.expand(len(seeds), -1), x0k.expand(len(seeds), -1, -1))
        return sample(kind, den, four, noise, rng=rng, known=known, **kwargs)

    a, b = run([3, 4, 5]), run([4])
    assert torch.equal(a[1], b[0])
    assert not torch.allclose(a[0], a[1])


@pytest.mark.parametrize(
    ("kind", "kwargs"),
    [("ddpm", {"steps": 50}), ("ddim", {}), ("dpm++", {}), ("dpm++3m", {}), ("unipc", {"steps": 20})],
)
def test_inpainting_keeps_known_points(four, kind, kwargs):
    g = torch.Generator().manual_seed(0)
    B, N = 2, 300
    mask = torch.rand(B, N, generator=g) < 0.4
    x0k = torch.randn(B, N, 3, generator=g)
    seen = []

    ts = make_timesteps(T, kwargs.get("steps", 50 if kind == "ddim" else 20))

    def progress(info):
        ab = four.alpha_bar(ts[info.index + 1] if info.index + 1 < len(ts) else -1)
        z = (info.x[mask].double() - ab**0.5 * x0k[mask].double()) / max(1 - ab, 1e-12) ** 0.5
        seen.append((ab, z.std().item()))

    rng = PerSampleRNG([1, 2])
    noise = rng.randn((N, 3))
    out = sample(kind, MixtureDenoiser(four), four, noise, rng=rng, known=(mask, x0k), progress=progress, **kwargs)
    assert torch.equal(out[mask], x0k[mask])
    assert not torch.equal(out[~mask], x0k[~mask])
    # before the end the known points carry the forward-process noise of the new timestep
    for ab, zstd in seen[:-1]:
        assert zstd == pytest.approx(1.0, abs=0.1), (ab, zstd)


SC, SDV = 2.0, 0.1


class SharedOffsetDenoiser:
    """Exact eps for x0_n = c + SDV z_n, with c ~ N(0, SC^2 I) shared by the N points of a sample.

    Per coordinate x0 ~ N(0, S), S = SC^2 11^T + SDV^2 I, so E[x0 | x_t] = a S (a^2 S + s^2 I)^-1 x_t
    (a^2 = abar, s^2 = 1 - abar), inverted with Sherman-Morrison.
    """

    def __init__(self, schedule: NoiseSchedule):
        self.schedule = schedule

    def __call__(self, x, t, cond=None):
        x, n = x.double(), x.shape[1]
        ab = self.schedule.alphas_cumprod[t].view(-1, 1, 1)
        lam, kap = ab * SDV**2 + (1 - ab), ab * SC**2
        u = (x - kap * x.sum(1, keepdim=True) / (lam + n * kap)) / lam  # (a^2 S + s^2 I)^-1 x
        x0 = ab.sqrt() * (SC**2 * u.sum(1, keepdim=True) + SDV**2 * u)
        return ((x - ab.sqrt() * x0) / (1 - ab).sqrt()).float()


@pytest.mark.parametrize(("kind", "tol"), [("ddpm", 0.2), ("ddim", 0.6), ("dpm++", 0.6)])
def test_inpainting_conditions_the_unknown_points(four, kind, tol):
    """Completion: half the points are known around offset c; the rest must follow c.

    Replacement without resampling harmonises well with the ancestral sampler (measured unknown
    means within 0.1 of c) and worse with the deterministic ones (within 0.4); unconditional
    samples land ~1-4 away.
    """
    B, N = 3, 64
    c = torch.tensor([1.5, -1.0, 0.5])
    x0k = c + SDV * torch.randn(B, N, 3, generator=torch.Generator().manual_seed(0))
    mask = torch.zeros(B, N, dtype=torch.bool)
    mask[:, :32] = True
    rng = PerSampleRNG([1, 2, 3])
    out = sample(kind, SharedOffsetDenoiser(four), four, rng.randn((N, 3)), rng=rng, known=(mask, x0k))
    unknown = out[~mask].view(B, N - 32, 3)
    assert (unknown.mean(1) - c).abs().max() < tol
    assert unknown.std(1).mean().item() == pytest.approx(SDV, rel=0.3)


def test_progress_and_dispatch(four):
    infos = []
    noise = make_noise((16, 3), [0, 1])
    out = sample("ddim", fake_denoiser, four, noise, steps=7, progress=infos.append)
    assert [i.index for i in infos] == list(range(7)) and infos[0].num_steps == 7
    assert infos[0].t == 999 and torch.equal(infos[-1].x, out)
    assert infos[-1].x0_pred.shape == noise.shape
    # cond reaches the denoiser; a denoiser's own prediction_type attribute is honoured
    cond = object()

    class X0Denoiser:
        prediction_type = "sample"

        def __call__(self, x, t, c):
            assert c is cond and t.dtype == torch.long and t.shape == (x.shape[0],)
            return 0.5 * torch.tanh(x)

    a = sample("dpm++", X0Denoiser(), four, noise, cond, steps=5)
    b = sample("dpm++", lambda x, t, c: 0.5 * torch.tanh(x), four, noise, steps=5, prediction_type="sample")
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="unknown sampler kind"):
        sample("euler", fake_denoiser, four, noise)
    assert set(SAMPLER_STEPS) <= set(SAMPLERS)  # every name the CLI offers can be dispatched
    assert torch.equal(sample("unipc", fake_denoiser, four, noise, steps=6), sample_unipc(fake_denoiser, four, noise, steps=6))
    with pytest.raises(ValueError, match="order"):
        sample("unipc", fake_denoiser, four, noise, order=4)
    with pytest.raises(ValueError, match="d2"):
        sample("dpm++3m", fake_denoiser, four, noise, d2="double")
    with pytest.raises(ValueError, match="prediction_type"):
        sample("ddpm", fake_denoiser, four, noise, prediction_type="score")
    with pytest.raises(ValueError, match="timesteps"):
        sample_ddpm(fake_denoiser, four, noise, timesteps=[5, 10])
    with pytest.raises(ValueError, match="seeds"):
        sample_ddpm(fake_denoiser, four, noise, rng=PerSampleRNG([1]))
    with pytest.raises(ValueError, match="known mask"):
        sample_dpmpp(fake_denoiser, four, noise, known=(torch.ones(2, 15, dtype=torch.bool), noise))


def test_explicit_timesteps_partial_denoising(four):
    """Pose-editing style: noise a sample to t = 99 and run the ancestral chain from there."""
    den = MixtureDenoiser(four)
    rng = PerSampleRNG([0])
    x0 = (MU * torch.sign(torch.randn(1, 512, 1, generator=torch.Generator().manual_seed(0)))).float()
    x_t = four.add_noise(x0, rng.randn((512, 3)), torch.tensor([99]))
    out = sample_ddpm(den, four, x_t, timesteps=range(99, -1, -1), rng=rng)
    assert (out - x0).norm(dim=-1).mean() < 0.5  # stays near the source, cluster for cluster


# -- loss --------------------------------------------------------------------------------------


@pytest.mark.parametrize("prediction_type", PRED_TYPES)
@pytest.mark.parametrize("weighting", ["none", "min_snr"])
def test_loss_matches_per_sample_loop(four, prediction_type, weighting):
    g = torch.Generator().manual_seed(0)
    B = 6
    x0 = torch.randn(B, 20, 3, generator=g)
    loss, logs = diffusion_loss(fake_denoiser, x0, None, four, prediction_type, weighting, 5.0,
                                generator=torch.Generator().manual_seed(42))  # fmt: skip
    # slow reference: same draws, one sample at a time, plain Python scalars
    g = torch.Generator().manual_seed(42)
    t = torch.randint(0, T, (B,), generator=g)
    noise = torch.randn(x0.shape, generator=g)
    total = 0.0
    for b in range(B):
        ab = float(four.alphas_cumprod[t[b]])
        x_t = math.sqrt(ab) * x0[b] + math.sqrt(1 - ab) * noise[b]
        target = {"epsilon": noise[b], "sample": x0[b],
                  "v_prediction": math.sqrt(ab) * noise[b] - math.sqrt(1 - ab) * x0[b]}[prediction_type]  # fmt: skip
        mse = ((fake_denoiser(x_t[None], t[b : b + 1])[0] - target) ** 2).mean().item()
        snr = ab / (1 - ab)
        w = {"epsilon": min(snr, 5.0) / snr, "sample": min(snr, 5.0), "v_prediction": min(snr, 5.0) / (snr + 1)}
        total += (w[prediction_type] if weighting == "min_snr" else 1.0) * mse
    assert loss.item() == pytest.approx(total / B, rel=1e-5)
    assert logs["loss"] == pytest.approx(loss.item())
    assert set(logs) >= {"loss", "mse"}


def test_min_snr_weights_are_x0_space_weights(four):
    """For every parametrisation, w * mse(pred) equals min(SNR, gamma) * mse(x0) (Hang et al.)."""
    g = torch.Generator().manual_seed(3)
    x0 = torch.randn(5, 8, 3, generator=g, dtype=torch.float64)
    eps = torch.randn(5, 8, 3, generator=g, dtype=torch.float64)
    t = torch.tensor([0, 50, 300, 700, 999])
    x_t = four.add_noise(x0, eps, t)
    x0_hat = x0 + 0.1 * torch.randn(5, 8, 3, generator=g, dtype=torch.float64)
    eps_hat = (x_t - four.sqrt_alphas_cumprod[t].view(-1, 1, 1) * x0_hat) / four.sqrt_one_minus_alphas_cumprod[
        t
    ].view(-1, 1, 1)
    snr = four.snr(t)
    ref = snr.clamp(max=5.0) * ((x0_hat - x0) ** 2).flatten(1).mean(1)
    for p in PRED_TYPES:
        pred = four.training_target(x0_hat, eps_hat, t, p)
        target = four.training_target(x0, eps, t, p)
        got = min_snr_weight(snr, p, 5.0) * ((pred - target) ** 2).flatten(1).mean(1)
        assert torch.allclose(got, ref, rtol=1e-8), p


def test_loss_is_differentiable_and_validates(four):
    lin = torch.nn.Linear(3, 3)
    x0 = torch.randn(4, 10, 3)
    loss, logs = diffusion_loss(lambda x, t, c: lin(x), x0, None, four, weighting="min_snr",
                                generator=torch.Generator().manual_seed(0))  # fmt: skip
    loss.backward()
    assert lin.weight.grad is not None and torch.isfinite(lin.weight.grad).all()
    assert any(k.startswith("mse_q") for k in logs)
    with pytest.raises(ValueError, match="weighting"):
        diffusion_loss(fake_denoiser, x0, None, four, weighting="p2")
    with pytest.raises(ValueError, match="t must be"):
        diffusion_loss(fake_denoiser, x0, None, four, t=torch.tensor([0, 1, 2, T]))
