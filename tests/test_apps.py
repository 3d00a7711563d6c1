"""Applications (completion, pose editing, animation) on a tiny 2-step model: invariants, slow
references, CLI outputs and one-line errors."""

import json

from pathlib import Path

import numpy as np
import pytest
import torch

from pocoloco.apps.animation import animate, flicker_cm, load_motion, warp_by_body
from pocoloco.diffusion.chains import chain_timesteps, repaint_resampling
from pocoloco.apps.common import denoise_from, subset, to_normalised
from pocoloco.apps.completion import (
    candidate_seeds,
    choose_candidate,
    complete,
    draw_candidates,
    estimate_coverage,
    estimate_normals,
    hole_points,
    region_mask,
    score_hole,
)
from pocoloco.apps.editing import _bones, edit, moving_region, nearest_bone
from pocoloco.cli import main
from pocoloco.data.format import DatasetLayout, read_frame
from pocoloco.data.published import read_ply, write_ply
from pocoloco.diffusion.sampler_base import PerSampleRNG
from pocoloco.diffusion.samplers import make_timesteps, sample_ddpm
from pocoloco.diffusion.schedules import NoiseSchedule
from pocoloco.methods import train
from pocoloco.methods import load_method
from pocoloco.methods.pocoloco import load_denoiser, sample_clouds, train_preset

pytestmark = pytest.mark.usefixtures("torch_single_thread")


@pytest.fixture(scope="module")
def run(tiny_dataset, tmp_path_factory):
    """A tiny model trained for 2 steps (its run folder)."""
    out = tmp_path_factory.mktemp("apps") / "run"
    cfg = train_preset("tiny", steps=2, batch_size=2, num_points=64, ckpt_every=0, sample_every=0, log_every=1)
    train(cfg, tiny_dataset, out, progress=False)
    return out


@pytest.fixture(scope="module")
def loaded(run):
    return load_denoiser(run)


@pytest.fixture(scope="module")
def prior(run):
    """The apps' hook of the trained tiny model (``method.point_prior``)."""
    return load_method(run).point_prior(None)


@pytest.fixture(scope="module")
def seq(tiny_dataset):
    """(spec, frames) of the first test sequence of the tiny dataset, frames read fully."""
    layout = DatasetLayout(tiny_dataset)
    subject, sequence, _ = layout.iter_frames("test")[0]
    paths = [layout.frame_path(subject, "test", sequence, i) for i in layout.frame_indices(subject, "test", sequence)]
    return f"{tiny_dataset}:{subject}/test/{sequence}", [read_frame(p) for p in paths]


# ------------------------------------------------------------------------------------ common
def test_chain_timesteps_match_the_samplers_at_T_and_start_at_t():
    assert chain_timesteps(1000, 1000, "dpm++") == make_timesteps(1000, 20)
    assert chain_timesteps(1000, 1000, "ddim", 7) == make_timesteps(1000, 7)
    assert chain_timesteps(100, 1000, "ddpm") == list(range(99, -1, -1))
    ts = chain_timesteps(100, 1000, "dpm++")
    assert ts[0] == 99 and len(ts) == 20 and all(a > b >= 0 for a, b in zip(ts, ts[1:]))
    assert chain_timesteps(3, 1000, "dpm++") == [2, 1, 0]
    with pytest.raises(ValueError, match=r"t must be in \[1, 1000\]"):
        chain_timesteps(0, 1000, "dpm++")


# -------------------------------------------------------------------------------- completion
def test_completion_keeps_known_points_exactly(loaded, prior, seq):
    model, norm, cfg = loaded
    fr = seq[1][0]
    inside = region_mask(fr.points, fr.joints, "left_hand")
    partial = fr.points[~inside]
    comp = complete(prior, partial, fr.joints, 64, num=2, steps=3, seeds=[3, 4], coverage=0.5)
    assert comp.points.shape == (2, 64, 3) and comp.known.shape == (2, 64) and comp.num_known == 32
    assert comp.known[:, :32].all() and not comp.known[:, 32:].any()
    for k, s in enumerate([3, 4]):  # bit-exact copies of the scan subset drawn from the output's seed
        np.testing.assert_array_equal(comp.points[k, :32], partial[subset(len(partial), 32, [s, 1])])
    assert np.isfinite(comp.points).all() and np.abs(comp.points[0, 32:] - comp.points[1, 32:]).max() > 1e-3
    # the sampler itself keeps them (up to float round-off), before the exact copy
    xk = np.zeros((1, 64, 3), np.float32)
    xk[0, :32] = to_normalised(norm, partial[:32], None, fr.joints, 3)
    mask = np.zeros((1, 64), bool)
    mask[0, :32] = True
    for sampler in ("dpm++", "ddpm"):
        x = denoise_from(prior, fr.joints, None, 1000, sampler, 4, [0], known=(mask, xk))
        np.testing.assert_allclose(x[0, :32], xk[0, :32], atol=1e-5)


def test_coverage_estimate_against_brute_force(loaded, prior, seq):
    model, norm, cfg = loaded
    fr = seq[1][0]
    partial = fr.points[~region_mask(fr.points, fr.joints, "hem")][::7]
    c = estimate_coverage(prior, partial, fr.joints, 48, radius=0.3, seed=2, probe_steps=2)
    probe = sample_clouds(model, norm, cfg, fr.joints, 1, 48, steps=2, seeds=[2]).points[0]
    d = np.sqrt(((probe[:, None].astype(np.float64) - partial[None]) ** 2).sum(-1)).min(1)
    assert c == pytest.approx(float((d < 0.3).mean()))
    comp = complete(prior, partial, fr.joints, 48, steps=2, seeds=[2], radius=0.3, probe_steps=2)
    assert comp.coverage_estimated and comp.num_known == round(comp.coverage * 48)


def test_hole_points_finds_the_missing_cap_and_ignores_strays():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20000, 3))  # dense: no gap in the scan wider than the radius
    sphere = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    scan = sphere[sphere[:, 2] < 0.3]  # the cap z > 0.3 is missing
    sample = np.concatenate([0.5 * (e := rng.normal(size=(400, 3))) / np.linalg.norm(e, axis=1, keepdims=True),
                             [[3.0, 0.0, 0.0]]])  # fmt: skip  # + one stray far from everything
    idx, cov = hole_points(sample, scan, radius=0.05)
    cap = sample[:400, 2] > 0.35
    assert 400 not in idx  # the stray is not a hole point
    assert set(np.flatnonzero(cap)) <= set(idx.tolist()) and (sample[idx, 2] > 0.25).all()
    assert cov == pytest.approx(1 - len(idx) / 400)
    far = hole_points(sample, scan, radius=0.05, num=10)[0]  # the 10 farthest (kept) points: top of the cap
    assert len(far) == 10 and 400 not in far and (sample[far, 2] > 0.45).all()


def test_completion_sample_init_starts_from_the_samples_hole_points(loaded, prior, seq):
    model, norm, cfg = loaded
    fr = seq[1][0]
    partial = fr.points[~region_mask(fr.points, fr.joints, "hem")]
    kw = {"num": 1, "sampler": "ddpm", "steps": 3, "seeds": [5], "radius": 0.3, "max_cos": None}  # distance-only hole test
    comp = complete(prior, partial, fr.joints, 64, init="sample", t=1, coverage=0.75, candidates=1, **kw)
    assert comp.init == "sample" and comp.t == 1 and comp.num_known == 48
    full = sample_clouds(model, norm, cfg, fr.joints, 1, 64, sampler="ddpm", steps=3, seeds=[5]).points[0]
    start = full[hole_points(full, partial, 0.3, num=16)[0]]
    gen = comp.points[0, 48:]
    # t = 1: one nearly noise-free denoiser call, so the generated points stay at their start
    assert np.linalg.norm(gen - start, axis=1).max() < 0.05
    noise = complete(prior, partial, fr.joints, 64, init="noise", coverage=0.75, **kw)
    assert noise.t == 1000 and np.linalg.norm(noise.points[0, 48:] - start, axis=1).mean() > 0.05
    with pytest.raises(ValueError, match="unknown completion init"):
        complete(prior, partial, fr.joints, 64, init="magic")


class _GaussianDenoiser:
    """The exact x0 predictor for data x0 ~ N(0, I): E[x0 | x_t] = sqrt(abar_t) x_t; counts its calls."""

    prediction_type = "sample"

    def __init__(self, schedule):
        self.ab = torch.as_tensor(schedule.alphas_cumprod, dtype=torch.float64)
        self.calls = 0

    def __call__(self, x, t, cond):
        self.calls += 1
        return (self.ab[t].to(x.dtype).view(-1, 1, 1) ** 0.5) * x


def test_repaint_resampling_one_pass_is_the_ddpm_chain_and_keeps_known_points():
    schedule = NoiseSchedule.from_kind("linear", 1000)
    ts = make_timesteps(1000, 12)
    noise = PerSampleRNG([1, 2]).randn((50, 3))
    mask = torch.zeros(2, 50, dtype=torch.bool)
    mask[:, :20] = True
    known = (mask, torch.randn(2, 50, 3, generator=torch.Generator().manual_seed(0)))
    den = _GaussianDenoiser(schedule)
    plain = sample_ddpm(den, schedule, noise, timesteps=ts, rng=PerSampleRNG([1, 2]), known=known)
    for jump in (1, 5, 12):  # resample 1: the plain chain bit for bit, whatever the jump
        out = repaint_resampling(den, schedule, noise, None, ts, PerSampleRNG([1, 2]), None, known, 1, jump)
        assert torch.equal(out, plain)
    den.calls = 0
    out = repaint_resampling(den, schedule, noise, None, ts, PerSampleRNG([1, 2]), None, known, 3, 5)
    assert den.calls == 3 * len(ts) and torch.equal(out[:, :20], known[1][:, :20])  # known points exact
    assert not torch.equal(out[:, 20:], plain[:, 20:])


def test_repaint_resampling_jumps_keep_the_marginals():
    # data N(0, I) with its exact denoiser: the jumps back are q(x_a | x_b), so the output stays N(0, I)
    schedule = NoiseSchedule.from_kind("linear", 1000)
    ts = make_timesteps(1000, 50)
    noise = PerSampleRNG([3]).randn((20000, 3))
    den = _GaussianDenoiser(schedule)
    plain = sample_ddpm(den, schedule, noise, timesteps=ts, rng=PerSampleRNG([3]))
    jumped = repaint_resampling(den, schedule, noise, None, ts, PerSampleRNG([3]), None, None, 4, 10)
    assert abs(jumped.std().item() - plain.std().item()) < 0.02 and abs(jumped.mean().item()) < 0.02


def test_resampling_options_are_validated(loaded, prior, seq):
    model, norm, cfg = loaded
    fr = seq[1][0]
    with pytest.raises(ValueError, match="resample and jump must be >= 1"):
        denoise_from(prior, fr.joints, None, 10, "ddpm", 2, [0], num_points=8, resample=0)
    partial = fr.points[~region_mask(fr.points, fr.joints, "hem")]
    for bad, message in (({"jump": 0}, "resample and jump"), ({"candidates": 0}, "candidates must be >= 1"),
                         ({"t": -1}, r"t must be in \[0, 1000\]"), ({"max_cos": 0.0}, r"max_cos must be in")):
        with pytest.raises(ValueError, match=message):
            complete(prior, partial, fr.joints, 16, steps=2, **bad)


def test_best_of_k_picks_the_candidate_closest_to_the_visible_scan(loaded, prior, seq):
    rng = np.random.default_rng(1)
    scan = rng.normal(size=(300, 3))
    samples = np.stack([scan[:200] + off for off in ([0.3, 0, 0], [0.01, 0, 0], [0.1, 0, 0])]).astype(np.float32)
    i, d = choose_candidate(samples, scan)
    brute = [np.sqrt(((scan[:, None] - s[None]) ** 2).sum(-1)).min(1).mean() for s in samples]
    assert i == 1 and np.allclose(d, brute)
    assert candidate_seeds(7, 1) == [7] and candidate_seeds(7, 3)[:2] == candidate_seeds(7, 2)
    assert len(set(candidate_seeds(7, 4) + candidate_seeds(8, 4))) == 8
    model, norm, cfg = loaded
    fr = seq[1][0]
    partial = fr.points[~region_mask(fr.points, fr.joints, "hem")]
    cands = draw_candidates(prior, fr.joints, 32, [4, 5], 3, steps=2)
    assert cands.points.shape == (2, 3, 32, 3) and cands.seeds[1, 0] == 5
    plain = sample_clouds(model, norm, cfg, fr.joints, 1, 32, steps=2, seeds=[5]).points[0]
    np.testing.assert_allclose(cands.points[1, 0], plain, atol=1e-5)  # candidate 0: the seed's plain sample
    kw = {"num": 2, "steps": 2, "seeds": [4, 5], "candidates": 3}
    comp = complete(prior, partial, fr.joints, 32, **kw)
    assert comp.chosen.tolist() == [choose_candidate(cands.points[b], partial)[0] for b in range(2)]
    again = complete(prior, partial, fr.joints, 32, samples=cands, **kw)  # drawn once, reused
    np.testing.assert_array_equal(again.points, comp.points)
    with pytest.raises(ValueError, match="samples must be draw_candidates"):
        complete(prior, partial, fr.joints, 32, samples=cands, **(kw | {"seeds": [4, 6]}))


def _ellipsoid(n, rng, axes=(0.3, 0.2, 0.5)):
    d = rng.normal(size=(n, 3))
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    p = u * np.asarray(axes)
    g = p / np.asarray(axes) ** 2  # gradient of the implicit function: the outward normal
    return p, g / np.linalg.norm(g, axis=1, keepdims=True)


def test_hole_test_finds_the_removed_cap_not_points_off_the_surface():
    rng = np.random.default_rng(2)
    surf, nrm = _ellipsoid(30000, rng)
    keep = surf[:, 2] < 0.3  # the cap z > 0.3 is removed from the scan
    scan, scan_n = surf[keep], nrm[keep]
    pts, pn = _ellipsoid(1000, rng)
    low = pts[:, 2] < 0.0
    sample = np.where(low[:, None], pts + 0.08 * pn, pts)  # the lower half 8 cm too wide: off-surface, not a hole
    cap = pts[:, 2] > 0.38
    dist_only = hole_points(sample, scan, radius=0.03)[0]
    assert set(np.flatnonzero(low)) <= set(dist_only.tolist())  # distance alone takes the wide half as a hole
    for normals in (scan_n, None):  # the scan's normals, or estimated from its points
        idx, cov = hole_points(sample, scan, radius=0.03, normals=normals, max_cos=0.8)
        assert set(np.flatnonzero(cap)) <= set(idx.tolist())  # where the cap was
        assert not low[idx].any() and (pts[idx, 2] > 0.25).all()  # not where the sample is merely off
        assert cov == pytest.approx(1 - len(idx) / len(sample))
    est = estimate_normals(scan, at=np.arange(0, len(scan), 97))
    assert np.abs((est * scan_n[::97]).sum(1)).min() > 0.95  # unoriented PCA normals match the true ones


def test_score_hole_against_brute_force():
    rng = np.random.default_rng(3)
    scan = rng.normal(size=(400, 3)).astype(np.float32)
    inside = scan[:, 0] > 0.8
    gen = scan[inside][::2] + rng.normal(scale=0.05, size=(int(inside.sum() + 1) // 2, 3)).astype(np.float32)
    gen = np.concatenate([gen, [[5.0, 0.0, 0.0]]]).astype(np.float32)  # one point far off

    def dist(a, b):
        return np.sqrt(((a[:, None].astype(np.float64) - b[None]) ** 2).sum(-1)).min(1)

    s = score_hole(gen, scan, inside)
    assert s["s2m_cm"] == pytest.approx(100 * dist(scan[inside], gen).mean(), rel=1e-5)
    assert s["m2s_cm"] == pytest.approx(100 * dist(gen, scan).mean(), rel=1e-5)
    assert s["far_share"] == pytest.approx((dist(gen, scan) > 0.05).mean()) and s["num"] == len(gen)
    empty = score_hole(np.zeros((0, 3)), scan, inside)  # nothing generated: the hole stays open
    assert empty["s2m_cm"] == pytest.approx(100 * dist(scan[inside], scan[~inside]).mean(), rel=1e-5)
    assert np.isnan(empty["m2s_cm"]) and empty["num"] == 0
    with pytest.raises(ValueError, match="the region holds no scan point"):
        score_hole(gen, scan, np.zeros(len(scan), bool))


# ----------------------------------------------------------------------------------- editing
def test_edit_renoise_small_t_keeps_the_source_full_chain_forgets_it(loaded, prior, seq):
    model, norm, cfg = loaded
    src_fr, tgt_fr = seq[1][0], seq[1][-1]
    source = src_fr.points[:64]  # N = M: the subsample is the identity (sorted indices)
    kw = dict(source_joints=src_fr.joints, num_points=64, seeds=[1])
    # t = 1: one denoiser call at abar_0 = 1 - 1e-4; the result is the source moved with the root
    near = edit(prior, source, tgt_fr.joints, mode="renoise", t=1, **kw).points[0]
    shift = norm.root(tgt_fr.joints) - norm.root(src_fr.joints)
    dev = np.linalg.norm(near - (source + shift), axis=1)
    assert dev.mean() < 0.01 and dev.max() < 0.05, (dev.mean(), dev.max())
    # t = T: pure noise, exactly sampling from scratch, whatever the source
    kw["sampler"] = "dpm++"  # deterministic: equal to sampling from scratch to float round-off
    full = edit(prior, source, tgt_fr.joints, mode="renoise", t=1000, steps=3, **kw).points[0]
    other = edit(prior, source[::-1].copy() + 0.1, tgt_fr.joints, mode="renoise", t=1000, steps=3,
                 **kw).points[0]  # fmt: skip
    scratch = sample_clouds(model, norm, cfg, tgt_fr.joints, 1, 64, sampler="dpm++", steps=3, seeds=[1]).points[0]
    np.testing.assert_allclose(full, scratch, atol=1e-5)
    np.testing.assert_allclose(other, scratch, atol=1e-5)
    assert np.linalg.norm(full - (source + shift), axis=1).mean() > 10 * dev.mean()


def _nearest_bone_slow(points, joints):
    out = []
    for p in points.astype(np.float64):
        best, arg = np.inf, -1
        for b, (i, j) in enumerate(_bones(len(joints))):
            a, c = joints[i].astype(np.float64), joints[j].astype(np.float64)
            s = min(max(np.dot(p - a, c - a) / max(np.dot(c - a, c - a), 1e-12), 0.0), 1.0)
            d = np.linalg.norm(p - (a + s * (c - a)))
            if d < best:
                best, arg = d, b
        out.append(arg)
    return np.array(out)


def test_region_edit_keeps_static_points_and_regenerates_moving_ones(loaded, prior, seq):
    model, norm, cfg = loaded
    src_fr = seq[1][0]
    hand = region_mask(src_fr.points, src_fr.joints, ((22,), 0.06))
    source = np.concatenate([src_fr.points[hand][:32], src_fr.points[~hand][:32]])  # (64, 3)
    np.testing.assert_array_equal(nearest_bone(source, src_fr.joints), _nearest_bone_slow(source, src_fr.joints))
    target = src_fr.joints.copy() + np.array([0.3, 0.0, 0.0], np.float32)  # whole body moved...
    target[[20, 22]] += np.array([0.0, 0.0, 0.2], np.float32)  # ...and the left wrist and hand lifted
    moving, moved = moving_region(source, src_fr.joints, target, threshold=0.05)
    assert np.flatnonzero(moved).tolist() == [20, 22]
    bone_moves = np.array([moved[a] or moved[b] for a, b in _bones(24)])
    np.testing.assert_array_equal(moving, bone_moves[_nearest_bone_slow(source, src_fr.joints)])
    res = edit(prior, source, target, mode="region", source_joints=src_fr.joints, num_points=64,
               steps=3, seeds=[0], threshold=0.05)  # fmt: skip
    np.testing.assert_array_equal(res.regenerated[0], moving)
    np.testing.assert_allclose(res.points[0][~moving], source[~moving] + np.float32([0.3, 0, 0]), atol=1e-6)
    assert moving[:32].mean() > 0.5 and not moving[32:].all()  # the hand moves, most of the body does not
    assert np.abs(res.points[0][moving] - source[moving]).max() > 1e-2
    with pytest.raises(ValueError, match="region mode needs the source pose"):
        edit(prior, source, target, mode="region")


# --------------------------------------------------------------------------------- animation
def test_chain_depends_on_the_previous_frame_independent_does_not(loaded, prior, seq):
    model, norm, cfg = loaded
    joints = np.stack([f.joints for f in seq[1][:3]])
    kw = dict(t=200, steps=3)
    a = animate(prior, joints, 48, method="chain", seeds=[0, 1, 2], **kw).points
    b = animate(prior, joints, 48, method="chain", seeds=[9, 1, 2], **kw).points
    assert np.abs(a[0] - b[0]).max() > 1e-2 and np.abs(a[1] - b[1]).max() > 1e-3
    i = animate(prior, joints, 48, method="independent", seeds=[0, 1, 2], sampler="dpm++", **kw).points
    j = animate(prior, joints, 48, method="independent", seeds=[9, 1, 2], sampler="dpm++", **kw).points
    np.testing.assert_array_equal(i[1:], j[1:])
    for k in range(3):  # independent frames are plain samples
        ref = sample_clouds(model, norm, cfg, joints[k], 1, 48, sampler="dpm++", steps=3, seeds=[k]).points[0]
        np.testing.assert_allclose(i[k], ref, atol=1e-5)
    same = animate(prior, joints[[0, 0]], 48, method="shared-noise", seed=4, **kw).points
    np.testing.assert_array_equal(same[0], same[1])


def _flicker_slow(clouds, bodies):
    out = []
    for k in range(len(clouds) - 1):
        warped = []
        for p in clouds[k]:
            i = int(np.argmin(((bodies[k] - p) ** 2).sum(1)))
            warped.append(p + bodies[k + 1][i] - bodies[k][i])
        warped, nxt = np.array(warped), clouds[k + 1]
        d = np.sqrt(((warped[:, None] - nxt[None]) ** 2).sum(-1))
        out.append(100 * (d.min(0).mean() + d.min(1).mean()))
    return np.array(out)


def test_flicker_zero_for_a_rigid_copy_and_matches_slow_reference(seq):
    rng = np.random.default_rng(0)
    body = seq[1][0].body_vertices.astype(np.float64)[::40]  # (V, 3)
    cloud = body[rng.choice(len(body), 60)] + rng.normal(0, 0.01, (60, 3))
    steps = np.array([[0, 0, 0], [0.05, -0.02, 0.01], [0.11, 0.0, 0.03]])
    bodies = [body + s for s in steps]
    clouds = [cloud + s for s in steps]
    np.testing.assert_allclose(flicker_cm(clouds, bodies), 0.0, atol=1e-9)
    np.testing.assert_allclose(warp_by_body(cloud, bodies[0], bodies[2]), clouds[2], atol=1e-12)
    bodies = [body, body + rng.normal(0, 0.02, body.shape), body + rng.normal(0, 0.04, body.shape)]
    clouds = [cloud, cloud + rng.normal(0, 0.02, cloud.shape), rng.normal(0, 0.3, (45, 3))]
    np.testing.assert_allclose(flicker_cm(clouds, bodies), _flicker_slow(clouds, bodies), rtol=1e-10)


def test_load_motion_forms_and_errors(seq, tmp_path):
    spec, frames = seq
    m = load_motion(spec)
    assert m.joints.shape == (len(frames), 24, 3) and len(m.frames) == len(frames)
    np.testing.assert_array_equal(m.joints[1], frames[1].joints)
    np.save(tmp_path / "m.npy", m.joints)
    np.testing.assert_array_equal(load_motion(tmp_path / "m.npy").joints, m.joints)
    np.save(tmp_path / "m22.npy", m.joints[:, :22])
    for bad, msg in [(tmp_path / "m22.npy", "the skeleton has 22 joints, the model expects 24"),
                     (spec + "x", "no such sequence"), (tmp_path / "none.npy", "no such motion file")]:  # fmt: skip
        with pytest.raises(ValueError, match=msg) as e:
            load_motion(bad)
        assert len(str(e.value).splitlines()) == 1


# --------------------------------------------------------------------------------------- CLI
def test_cli_complete_edit_animate_write_their_outputs(run, seq, tmp_path, capsys):
    spec, frames = seq
    fr = frames[0]
    write_ply(tmp_path / "partial.ply", fr.points[~region_mask(fr.points, fr.joints, "left_hand")][::10])
    write_ply(tmp_path / "src.ply", fr.points[::10])
    np.save(tmp_path / "j0.npy", fr.joints)
    np.save(tmp_path / "j1.npy", frames[-1].joints)
    common = ["--ckpt", str(run), "--steps", "2", "--device", "cpu"]
    out = tmp_path / "c"
    argv = ["complete", *common, "--partial", str(tmp_path / "partial.ply"), "--joints", str(tmp_path / "j0.npy"),
            "--points", "32", "--num", "2", "--coverage", "0.75", "--candidates", "2", "--resample", "2", "--jump", "1",
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["completed_000.ply", "completed_001.ply", "completion.json",
                                                     "completion.png", "known.npy"]  # fmt: skip
    known = np.load(out / "known.npy")
    assert known.shape == (2, 32) and known.sum() == 48
    info = json.loads((out / "completion.json").read_text())
    assert info["num_known"] == 24 and info["resample"] == 2 and len(info["visible_distance_cm"][1]) == 2
    assert read_ply(out / "completed_001.ply").points.shape == (32, 3)
    out = tmp_path / "e"
    assert main(["edit", *common, "--source", str(tmp_path / "src.ply"), "--joints", str(tmp_path / "j1.npy"),
                 "--source-joints", str(tmp_path / "j0.npy"), "--mode", "region", "--points", "32",
                 "--out", str(out)]) == 0, capsys.readouterr().err  # fmt: skip
    assert sorted(p.name for p in out.iterdir()) == ["edit.json", "edit.png", "edited_000.ply", "regenerated.npy"]
    assert json.loads((out / "edit.json").read_text())["t"] == 1000
    out = tmp_path / "a"
    assert main(["animate", *common, "--motion", spec, "--frames", "0:3", "--points", "32", "--t", "50",
                 "--out", str(out)]) == 0, capsys.readouterr().err  # fmt: skip
    names = sorted(p.name for p in out.iterdir())
    assert names == ["animation.gif", "animation.json", "frame_0000.ply", "frame_0001.ply", "frame_0002.ply"]
    meta = json.loads((out / "animation.json").read_text())
    assert len(meta["metrics"]["flicker_cm"]) == 2 and len(meta["metrics"]["chamfer_to_gt_cm"]) == 3
    from PIL import Image

    assert Image.open(out / "animation.gif").n_frames == 3
    # rerun with fewer frames into the same folder: stale frames go
    assert main(["animate", *common, "--motion", spec, "--frames", "0:2", "--points", "32", "--no-render",
                 "--out", str(out)]) == 0  # fmt: skip
    assert sorted(p.name for p in out.glob("frame_*.ply")) == ["frame_0000.ply", "frame_0001.ply"]
    # README's recommended method by its name: chain-world = chain --anchor world (the same clouds)
    args = [*common, "--motion", spec, "--frames", "0:2", "--points", "32", "--t", "50", "--no-render"]
    assert main(["animate", *args, "--method", "chain-world", "--out", str(tmp_path / "w1")]) == 0
    assert main(["animate", *args, "--method", "chain", "--anchor", "world", "--out", str(tmp_path / "w2")]) == 0
    m1 = json.loads((tmp_path / "w1" / "animation.json").read_text())
    assert (m1["method"], m1["anchor"]) == ("chain", "world")
    np.testing.assert_array_equal(read_ply(tmp_path / "w1" / "frame_0001.ply").points,
                                  read_ply(tmp_path / "w2" / "frame_0001.ply").points)  # fmt: skip


def test_cli_bad_inputs_one_line_and_nothing_written(run, seq, tmp_path, capsys):
    spec, frames = seq
    fr = frames[0]
    write_ply(tmp_path / "empty.ply", np.zeros((0, 3), np.float32))
    write_ply(tmp_path / "mm.ply", fr.points[::50] * 1000)
    write_ply(tmp_path / "far.ply", fr.points[::50] + np.float32([3, 0, 0]))
    write_ply(tmp_path / "ok.ply", fr.points[::50])
    nan = fr.points[::50].copy()
    nan[3, 1] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    np.save(tmp_path / "j.npy", fr.joints)
    np.save(tmp_path / "m22.npy", np.stack([fr.joints[:22]] * 2))
    common = ["--ckpt", str(run), "--steps", "2", "--device", "cpu", "--out", str(tmp_path / "out")]
    j = str(tmp_path / "j.npy")
    cases = [
        (["complete", "--partial", str(tmp_path / "empty.ply"), "--joints", j], "the cloud is empty"),
        (["complete", "--partial", str(tmp_path / "nan.npy"), "--joints", j], "NaN or inf"),
        (["complete", "--partial", str(tmp_path / "mm.ply"), "--joints", j], "millimetres"),
        (["complete", "--partial", str(tmp_path / "far.ply"), "--joints", j], "m from the pose's root joint"),
        (["complete", "--partial", str(tmp_path / "ok.ply"), "--joints", j, "--coverage", "2"], "--coverage must be"),
        (["complete", "--partial", str(tmp_path / "ok.ply"), "--joints", j, "--candidates", "0"], "--candidates must"),
        (["complete", "--partial", str(tmp_path / "ok.ply"), "--joints", j, "--jump", "0"], "--jump must be >= 1"),
        (["complete", "--partial", str(tmp_path / "ok.ply"), "--joints", j, "--t", "1001"], "--t must be in [0, 1000]"),
        (["edit", "--source", str(tmp_path / "ok.ply"), "--joints", j, "--mode", "region"], "needs --source-joints"),
        (["edit", "--source", str(tmp_path / "ok.ply"), "--joints", j, "--t", "0"], "--t must be in [1, 1000]"),
        (["edit", "--source", str(tmp_path / "ok.ply"), "--joints", j, "--points", "5000"], "fewer than the 5000"),
        (["edit", "--source", str(tmp_path / "ok.ply"), "--joints", j, "--mode", "warp"], "unknown --mode 'warp'"),
        (["animate", "--motion", str(tmp_path / "m22.npy")], "the skeleton has 22 joints, the model expects 24"),
        (["animate", "--motion", spec, "--method", "morph"], "unknown --method 'morph'"),
        (["animate", "--motion", spec, "--frames", "3:1"], "selects no frame"),
        (["animate", "--motion", spec, "--method", "chain-world", "--anchor", "root"], "means --anchor world"),
        (["animate", "--motion", spec, "--threads", "0"], "--threads must be >= 1"),
    ]
    for argv, message in cases:
        code = main([*argv, *common])
        err = capsys.readouterr().err.strip()
        assert code == 2 and message in err and len(err.splitlines()) == 1, (argv, err)
        assert not (tmp_path / "out").exists()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


# ------------------------------------------------------------------ the apps through the Method hook
class _SphereDenoiser(torch.nn.Module):
    """The exact denoiser of a toy prior: every clean point lies on the unit sphere of the normalised
    frame (x0_hat = x / |x|), returned as the epsilon its schedule implies."""

    def __init__(self, alpha_bar: torch.Tensor):
        super().__init__()
        self.register_buffer("alpha_bar", alpha_bar.to(torch.float32))
        self.unused = torch.nn.Parameter(torch.zeros(1))  # the apps read the device and dtype from a parameter

    def forward(self, x, t, joints):
        ab = self.alpha_bar[t].view(-1, 1, 1)
        x0 = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return (x - ab.sqrt() * x0) / (1 - ab).sqrt()


def _fourth_method():
    """A dummy fourth method: only :meth:`Method.point_prior` is implemented for the apps."""
    from pocoloco.data.dataset import Normalisation
    from pocoloco.diffusion.schedules import NoiseSchedule
    from pocoloco.methods.base import Method, PointPrior

    schedule = NoiseSchedule.from_kind("four", 1000)
    norm = Normalisation(mean=(0.0, 0.0, 0.0), std=0.25)

    class SphereMethod(Method):
        kind = "sphere"

        @classmethod
        def from_checkpoint(cls, ck, device="cpu", use_ema=True):
            raise NotImplementedError

        @classmethod
        def presets(cls):
            return {}

        @classmethod
        def training_task(cls, config, data):
            raise NotImplementedError

        def load_pose(self, spec, outfit=None, frame_id=None, any_pose=False):
            raise NotImplementedError

        def predict(self, pose, num_points, seeds=(0,), outfit=None, options=None):
            raise NotImplementedError

        def point_prior(self, outfit):
            alpha_bar = torch.tensor([schedule.alpha_bar(t) for t in range(1000)])
            return PointPrior(_SphereDenoiser(alpha_bar), self.normalisation, schedule, "epsilon", 3, 24)

    return SphereMethod(torch.nn.Linear(1, 1), None, norm, Path("."), 0, {}), norm


def test_a_fourth_method_gets_completion_and_animation_through_the_hook(seq):
    """Completion and animation run on any method that gives a PointPrior: a dummy method whose
    denoiser puts every point on the unit sphere of the normalised frame gets both, and its outputs
    land on that sphere (known points of the completion kept exactly)."""
    method, norm = _fourth_method()
    prior = method.point_prior(None)
    frames = seq[1][:3]
    joints = np.stack([f.joints for f in frames])

    def radius(points, j):  # distance from the sphere's centre in normalised units
        return np.linalg.norm(to_normalised(norm, points, None, j, 3), axis=-1)

    anim = animate(prior, joints, 64, method="chain", t=200, steps=5, seeds=[0, 1, 2])
    assert anim.points.shape == (3, 64, 3)
    for k in range(3):
        np.testing.assert_allclose(radius(anim.points[k], joints[k]), 1.0, atol=0.02)
    fr = frames[0]
    root = fr.joints[0]
    shell = np.random.default_rng(0).normal(size=(400, 3))
    shell = root + 0.25 * shell / np.linalg.norm(shell, axis=1, keepdims=True)  # the prior's own surface, in metres
    partial = shell[shell[:, 2] > root[2]].astype(np.float32)  # its upper half: the lower half is the hole
    comp = complete(prior, partial, fr.joints, 64, steps=5, seeds=[3], coverage=0.5, candidates=1)
    np.testing.assert_array_equal(comp.points[0, : comp.num_known], partial[subset(len(partial), comp.num_known, [3, 1])])
    np.testing.assert_allclose(radius(comp.points[0], fr.joints), 1.0, atol=0.02)
    with pytest.raises(ValueError, match="POP cannot complete, edit or animate"):
        from pocoloco.methods.pop.method import POPMethod

        POPMethod.point_prior(POPMethod.__new__(POPMethod), None)
