"""Issue 42: the few-step sampler, the teacher pairs, the distillation run and sampling a student."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, sample
from pocoloco.diffusion.samplers import make_timesteps, sample_ddim
from pocoloco.diffusion.few_step import (allowed_calls, check_student_calls, polish, polished_grid,
                                         sample_few_step, sampling_grid, student_grid)
from pocoloco.methods.pocoloco.method import DEFAULT_POLISH_T


@pytest.fixture(scope="module")
def four():
    return NoiseSchedule.from_kind("four", 1000)


class LinearDenoiser(torch.nn.Module):
    """eps = tanh(W x + t / 1000): a fixed nonlinear denoiser for the step-by-step reference."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.w = torch.nn.Parameter(torch.randn(3, 3, generator=g) * 0.3)

    def forward(self, x, t, cond=None):
        return torch.tanh(x @ self.w + t.view(-1, 1, 1).float() / 1000)


def _reference(den, schedule, noise, ts, renoise, gen):
    """The few-step sampler written out as a plain loop over the grid, in float64."""
    x = noise.double()
    for i, t in enumerate(ts):
        ab = schedule.alpha_bar(t)
        eps = den(x.float(), torch.full((x.shape[0],), t), None).double()
        x0 = (x - (1 - ab) ** 0.5 * eps) / ab**0.5
        if i + 1 < len(ts):
            s = schedule.alpha_bar(ts[i + 1])
            z = torch.randn(x.shape, generator=gen).double() if renoise else 0.0
            x = s**0.5 * x0 + (1 - s) ** 0.5 * ((1 - renoise**2) ** 0.5 * eps + renoise * z)
        else:
            x = x0
    return x.float()


def test_student_grid_and_sub_grids():
    assert student_grid(1000, 4) == [999, 749, 499, 249]
    assert student_grid(1000, 2) == [999, 499] and student_grid(1000, 1) == [999]
    check_student_calls(2, 4)
    check_student_calls(3, 4)
    for bad in (5, 0):
        with pytest.raises(ValueError, match="samples with 1 to 4") as e:
            check_student_calls(bad, 4)
        assert "\n" not in str(e.value)
    # what it visits with fewer calls: the grid's first times and its last
    assert [sampling_grid(1000, c, 4) for c in (1, 2, 3, 4)] == [[999], [999, 249], [999, 749, 249], [999, 749, 499, 249]]


@pytest.mark.parametrize("renoise", [0.0, 1.0, 0.5])
def test_few_step_sampler_matches_the_plain_loop(four, renoise):
    den = LinearDenoiser()
    noise = torch.randn(2, 64, 3, generator=torch.Generator().manual_seed(1))
    gen = torch.Generator().manual_seed(7)
    out = sample_few_step(den, four, noise, steps=4, renoise=renoise, rng=torch.Generator().manual_seed(7))
    ref = _reference(den, four, noise, student_grid(1000, 4), renoise, gen)
    assert torch.allclose(out, ref, atol=1e-5), (out - ref).abs().max()
    # the dispatcher's "few-step" is this sampler; deterministic without re-noising
    again = sample("few-step", den, four, noise, steps=4, renoise=renoise, rng=torch.Generator().manual_seed(7))
    assert torch.equal(out, again)


def test_few_step_with_one_call_is_the_one_step_x0(four):
    den = LinearDenoiser()
    noise = torch.randn(1, 32, 3, generator=torch.Generator().manual_seed(2))
    out = sample_few_step(den, four, noise, steps=1)
    ab = four.alpha_bar(999)
    eps = den(noise, torch.tensor([999]))
    assert torch.allclose(out, (noise - (1 - ab) ** 0.5 * eps) / ab**0.5, atol=1e-5)
    with pytest.raises(ValueError, match="renoise"):
        sample_few_step(den, four, noise, renoise=1.5)


def test_sampler_for_routes_students_and_refuses_mixups():
    from pocoloco.methods.pocoloco import train_preset
    from pocoloco.methods.pocoloco.sampling import sampler_for

    teacher = train_preset("latent_tiny")
    student = teacher.replace(student_calls=4)
    assert sampler_for(teacher, "dpm++sde", None) == ("dpm++sde", 25)
    assert sampler_for(student, "dpm++sde", None) == ("few-step", 4)
    assert sampler_for(student, "few-step", 2) == ("few-step", 2)
    for config, sampler, steps, match in [(student, "ddim", None, "few-step sampler only"),
                                          (student, "dpm++sde", 5, "samples with 1 to 4"),
                                          (teacher, "few-step", None, "is for a distilled model")]:  # fmt: skip
        with pytest.raises(ValueError, match=match) as e:
            sampler_for(config, sampler, steps)
        assert "\n" not in str(e.value)


@pytest.fixture(scope="module")
def latent_teacher(tiny_dataset, tmp_path_factory):
    from pocoloco.methods import train
    from pocoloco.methods.pocoloco import train_preset

    out = tmp_path_factory.mktemp("teacher") / "run"
    cfg = train_preset("latent_tiny", steps=2, num_points=64, ckpt_every=0, sample_every=0, log_every=1,
                       outfit_codes=True, body_shape=True)  # fmt: skip
    train(cfg, tiny_dataset, out, progress=False)
    return out


def test_distill_end_to_end_resumes_and_samples(latent_teacher, tiny_dataset, tmp_path, torch_single_thread):
    """Pairs are the teacher's deterministic answers at the grid; the student starts at the teacher,
    its loss falls on its pairs, the run resumes, and the export samples with 1 / 2 / 4 calls."""
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.distill import distill, read_teacher_pairs
    from pocoloco.methods.pocoloco.sampling import sample_clouds

    out = tmp_path / "d"
    # lr 3e-4: at 1e-3 the raw weights of 30 steps of batch 4 land anywhere from 0.5x to 1.3x the start's loss,
    # depending on the CPU the tiny teacher was trained on; at 3e-4 about 0.5x
    kw = dict(calls=4, pairs=6, pair_points=32, teacher_steps=8, batch_size=4, lr=3e-4, log_every=1, lr_schedule="constant",
              warmup_steps=0, progress=False)
    r = distill(latent_teacher, tiny_dataset, out, steps=30, **kw)
    pairs = read_teacher_pairs(out / "pairs")
    assert pairs.states.shape == (6, 4, 32, 3) and pairs.targets.shape == (6, 32, 3)
    assert pairs.grid == [999, 749, 499, 249]
    # state 0 is the initial noise of the pair's seed; the target the teacher's ODE answer from it
    teacher = load_method(latent_teacher)
    rng = PerSampleRNG([int(s) for s in np.load(out / "pairs" / "shard_00000.npz")["seeds"][:1]])
    noise = rng.randn((32, 3))
    assert torch.allclose(torch.from_numpy(pairs.states[0, 0]), noise)
    z = np.load(out / "pairs" / "shard_00000.npz")
    from pocoloco.methods.pocoloco.distill import DistillTask, distill_config

    task = DistillTask(distill_config(teacher.config, 4), tiny_dataset)
    cond = task.condition(torch.from_numpy(z["joints"][:1]), torch.from_numpy(z["subject"][:1]))
    ans = sample("dpm++", teacher.model, NoiseSchedule.from_kind("four", 1000), noise, cond, steps=8)
    assert torch.allclose(ans, torch.from_numpy(pairs.targets[:1]), atol=1e-4)

    # the loss falls on its pairs: the same 8 fixed draws scored by the teacher (= the student's
    # start) and by the trained student (the logged per-batch losses are too noisy to compare)
    task.pairs = pairs
    draws = task.step_batches(teacher.model, 0, 1)
    student_raw = load_method(out, use_ema=False)
    with torch.no_grad():
        fixed = {name: np.mean([task.loss(net.eval(), draws[s], s, 0)[1]["loss"] for s in range(8)])
                 for name, net in [("teacher", teacher.model), ("student", student_raw.model)]}  # fmt: skip
    assert fixed["student"] < 0.9 * fixed["teacher"], fixed
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 30
    meta = json.loads((out / "model" / "meta.json").read_text())
    assert meta["config"]["student_calls"] == 4 and meta["distilled_from"]["teacher_sampler"] == "dpm++"

    # resume: more steps, the same pairs (made once)
    stamp = (out / "pairs" / "shard_00000.npz").stat().st_mtime_ns
    r2 = distill(latent_teacher, tiny_dataset, out, steps=34, resume=True, **kw)
    assert r2.step == 34 and r.step == 30
    assert (out / "pairs" / "shard_00000.npz").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="other settings"):
        distill(latent_teacher, tiny_dataset, out, steps=40, resume=True, **{**kw, "pairs": 7})

    student = load_method(out / "model")
    joints = np.asarray(student.load_pose("demo:skirt").joints)
    for calls in (1, 2, 4):
        a = sample_clouds(student.model, student.normalisation, student.config, joints, 2, 48, steps=calls,
                          **student.condition(0))  # fmt: skip
        b = sample_clouds(student.model, student.normalisation, student.config, joints, 2, 48, steps=calls,
                          **student.condition(0))  # fmt: skip
        assert a.points.shape == (2, 48, 3) and np.isfinite(a.points).all()
        np.testing.assert_array_equal(a.points, b.points)  # deterministic per seed
        assert not np.allclose(a.points[0], a.points[1])  # two seeds, two clouds


def test_polished_grid_and_the_calls_it_allows():
    """With its teacher making the last call, a 4-call student samples with 3 .. 5 calls: its
    grid's first calls - 2 times and its last, then the teacher; 1 and 2 calls stay its own."""
    assert polished_grid(1000, 4, 4) == [999, 749, 249]
    assert polished_grid(1000, 3, 4) == [999, 249]
    assert polished_grid(1000, 5, 4) == [999, 749, 499, 249]
    assert polished_grid(1000, 2, 4) is None and polished_grid(1000, 6, 4) is None
    assert allowed_calls(4) == [1, 2, 3, 4] and allowed_calls(4, polish=True) == [1, 2, 3, 4, 5]
    check_student_calls(5, 4, polish=True)
    with pytest.raises(ValueError, match="samples with 1 to 5 .*its teacher makes the last") as e:
        check_student_calls(6, 4, polish=True)
    assert "\n" not in str(e.value)


def test_polish_is_one_teacher_call_on_the_renoised_answer(four):
    """``polish`` against the written-out SDEdit step: x_t = sqrt(abar) x0 + sqrt(1 - abar) z at
    1-based step t, then the denoiser's x0 estimate there."""
    den = LinearDenoiser()
    x0 = torch.randn(2, 64, 3, generator=torch.Generator().manual_seed(3))
    out = polish(den, four, x0, None, 20, torch.Generator().manual_seed(5))
    ab = four.alpha_bar(19)
    z = torch.randn(x0.shape, generator=torch.Generator().manual_seed(5))
    xt = ab**0.5 * x0.double() + (1 - ab) ** 0.5 * z.double()
    eps = den(xt.float(), torch.full((2,), 19)).double()
    ref = ((xt - (1 - ab) ** 0.5 * eps) / ab**0.5).float()
    assert torch.allclose(out, ref, atol=1e-5), (out - ref).abs().max()
    assert (out - x0).abs().mean() > 1e-3  # it moved the points
    for bad in (0, 1001):
        with pytest.raises(ValueError, match="polish t must be in"):
            polish(den, four, x0, None, bad, None)


@pytest.fixture(scope="module")
def tiny_student(latent_teacher, tiny_dataset, tmp_path_factory):
    from pocoloco.methods.pocoloco.distill import distill

    out = tmp_path_factory.mktemp("student") / "d"
    distill(latent_teacher, tiny_dataset, out, steps=2, calls=4, pairs=2, pair_points=16, teacher_steps=4,
            batch_size=2, progress=False)  # fmt: skip
    return out / "model"


def test_a_teacher_finishes_a_polished_student(latent_teacher, tiny_student, tiny_run, tmp_path, torch_single_thread):
    """``export-model --polish-with TEACHER``: the student's 4 calls become 3 of its own (999, 749,
    249) and its teacher's one at --polish-t, equal to the loop written out; 1 and 2 calls are the
    student's alone; a changed, wrong or missing teacher is a one-line error."""
    import shutil

    from pocoloco.cli import main
    from pocoloco.diffusion.samplers import sample_ddim
    from pocoloco.methods import SamplerOptions, load_method
    from pocoloco.methods.pocoloco.sampling import condition_for

    teacher_copy = tmp_path / "teacher"
    assert main(["export-model", "--ckpt", str(latent_teacher), "--out", str(teacher_copy)]) == 0
    out = tmp_path / "p"
    assert main(["export-model", "--ckpt", str(tiny_student), "--polish-with", str(teacher_copy), "--polish-t", "30",
                 "--out", str(out)]) == 0  # fmt: skip
    meta = json.loads((out / "meta.json").read_text())
    assert meta["polish"]["t"] == 30 and meta["polish"]["ckpt"] == str(teacher_copy.resolve())
    m, plain, teacher = load_method(out), load_method(tiny_student), load_method(teacher_copy)
    assert m.polish is not None and m.polish[1] == 30 and plain.polish is None
    pose = m.load_pose("demo:skirt")
    joints = np.asarray(pose.joints)
    got = m.predict(pose, 48, seeds=[3], outfit=0).points[0]  # 4 calls, the default
    assert m.sample_settings(SamplerOptions(), 48)["student_timesteps"] == [999, 749, 249]

    schedule = NoiseSchedule.from_kind(m.config.schedule, m.config.num_timesteps)
    kw = m.condition(0)
    joints_n = m.normalisation.normalise(np.zeros((1, 3), np.float32), joints)[1]
    cond = condition_for(torch.as_tensor(joints_n)[None], kw["outfit"], kw["shape"])
    rng = PerSampleRNG([3])
    x = sample_ddim(plain.model, schedule, rng.randn((48, 3)), cond, timesteps=[999, 749, 249], renoise=1.0, rng=rng,
                    prediction_type=m.config.prediction_type, clip=None)  # fmt: skip
    x = polish(teacher.model, schedule, x, cond, 30, rng, prediction_type=m.config.prediction_type)
    root = m.normalisation.root(joints).astype(np.float32)
    ref = m.normalisation.denormalise(x.numpy(), root, m.normalisation.angle(joints))[0]
    np.testing.assert_allclose(got, ref, atol=1e-5)
    for calls in (1, 2):  # below 3 calls the teacher does not finish
        opts = SamplerOptions(steps=calls)
        np.testing.assert_array_equal(m.predict(pose, 48, seeds=[3], outfit=0, options=opts).points,
                                      plain.predict(pose, 48, seeds=[3], outfit=0, options=opts).points)  # fmt: skip
    assert m.predict(pose, 48, seeds=[3], outfit=0, options=SamplerOptions(steps=3)).points.shape == (1, 48, 3)

    for args, match in [(["--ckpt", str(tiny_student), "--polish-t", "20"], None),  # no teacher named
                        (["--ckpt", str(latent_teacher), "--polish-with", str(teacher_copy)], None),  # not a student
                        (["--ckpt", str(tiny_student), "--polish-with", str(tiny_run)], None)]:  # another network
        assert main(["export-model", *args, "--out", str(tmp_path / "bad")]) == 2 and not (tmp_path / "bad").exists()
    shutil.rmtree(teacher_copy)
    with pytest.raises(ValueError, match="cannot be loaded") as e:
        load_method(out)
    assert "\n" not in str(e.value)
    assert main(["export-model", "--ckpt", str(latent_teacher), "--raw-weights", "--out", str(teacher_copy)]) == 0
    with pytest.raises(ValueError, match="has changed since the export") as e:
        load_method(out)
    assert "\n" not in str(e.value)
    # the error's advice, from the exported student itself: export it again with --polish-with
    assert main(["export-model", "--ckpt", str(out), "--polish-with", str(teacher_copy), "--out",
                 str(tmp_path / "relinked")]) == 0  # fmt: skip
    relinked = load_method(tmp_path / "relinked")
    assert relinked.polish is not None and relinked.polish[1] == DEFAULT_POLISH_T == 5  # --polish-t's default
    assert main(["export-model", "--ckpt", str(out), "--out", str(tmp_path / "stale")]) == 2  # not without it


def test_distill_from_a_training_pack(latent_teacher, tiny_dataset, tmp_path):
    """``distill --data PACK``: the teacher pairs and the student from a training pack (what a GPU
    lease carries), their poses the pack's frames; the student samples."""
    from pocoloco.cli import main
    from pocoloco.data.pack import PackedDataset, write_pack
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.distill import read_teacher_pairs

    pack = tmp_path / "t.pack"
    write_pack(tiny_dataset, pack, splits=("train",), every=1, points=256)
    out = tmp_path / "d"
    assert main(["distill", "--ckpt", str(latent_teacher), "--data", str(pack), "--out", str(out), "--pairs", "3",
                 "--pair-points", "32", "--teacher-steps", "4", "--steps", "2", "--batch-size", "2", "--threads", "1",
                 "--device", "cpu"]) == 0  # fmt: skip
    pairs = read_teacher_pairs(out / "pairs")
    ds = PackedDataset(pack, "train")
    frames = np.concatenate([np.load(f)["frames"] for f in sorted((out / "pairs").glob("shard_*.npz"))])
    np.testing.assert_allclose(pairs.joints, np.stack([ds[int(i)]["joints"] for i in frames]), atol=1e-6)
    m = load_method(out / "model")
    assert m.config.student_calls == 4 and m.predict(m.load_pose("demo:skirt"), 32, outfit=0).points.shape == (1, 32, 3)


def test_distill_on_the_teachers_data_made_again(latent_teacher, tiny_dataset, tmp_path):
    """The teacher's data regenerated (its statistics moved in their last digits) is the teacher's
    data: the student and its pairs take the teacher's normalisation exactly; data whose mean is a
    millimetre off is another dataset, a one-line error."""
    from pocoloco.engine.checkpoint import load_checkpoint
    from pocoloco.methods.pocoloco.distill import prepare_distillation

    def made_again(name: str, shift_m: float):
        out = tmp_path / name
        out.mkdir()
        for p in tiny_dataset.iterdir():
            if p.name != "card.json":
                (out / p.name).symlink_to(p)
        card = json.loads((tiny_dataset / "card.json").read_text())
        card["normalisation"]["mean"][0] += shift_m
        (out / "card.json").write_text(json.dumps(card))
        return out

    teacher = load_checkpoint(latent_teacher, expect_model="pocoloco", training_state=False).normalisation
    task = prepare_distillation(latent_teacher, made_again("close", 2e-5), tmp_path / "d", pairs=2, pair_points=16,
                                teacher_steps=4)  # fmt: skip
    assert task.normalisation == teacher and task.dataset.normalisation == teacher
    assert task.dataset.normalisation.matches(teacher) and not teacher.matches(
        dataclasses.replace(teacher, mean=(teacher.mean[0] + 1e-3, *teacher.mean[1:])))
    with pytest.raises(ValueError, match="normalisation differs from the teacher's") as e:
        prepare_distillation(latent_teacher, made_again("far", 1e-3), tmp_path / "e", pairs=2, pair_points=16,
                             teacher_steps=4)  # fmt: skip
    assert "\n" not in str(e.value) and "--teacher-frame" in str(e.value)
    # --teacher-frame: the teacher's subjects made with fewer motions, their poses in the teacher's frame
    task = prepare_distillation(latent_teacher, made_again("fewer", 1e-3), tmp_path / "f", pairs=2, pair_points=16,
                                teacher_steps=4, teacher_frame=True)  # fmt: skip
    assert task.normalisation == teacher and task.dataset.normalisation == teacher
    far = load_checkpoint(latent_teacher, expect_model="pocoloco", training_state=False)
    assert [o["name"] for o in task.outfits] == [o["name"] for o in far.meta["outfits"]]


def test_distill_init_from_a_student_of_the_same_teacher(latent_teacher, tiny_student, tiny_dataset, tmp_path):
    """``distill --init-from STUDENT``: a student of the same teacher and grid goes on from its own
    weights (training it longer); the teacher itself, a student of other calls or of another teacher
    is a one-line error before any training."""
    from pocoloco.engine.checkpoint import load_checkpoint
    from pocoloco.methods.pocoloco.distill import distill, prepare_distillation, student_start

    kw = {"pairs": 2, "pair_points": 16, "teacher_steps": 4, "batch_size": 2, "progress": False}
    out = tmp_path / "longer"
    distill(latent_teacher, tiny_dataset, out, steps=1, calls=4, init_from=tiny_student, **kw)
    student = load_checkpoint(tiny_student, expect_model="pocoloco", training_state=False)
    assert load_checkpoint(out / "checkpoints", expect_model="pocoloco").meta["init_from"] == str(student.path)
    for init, calls, match in [(latent_teacher, 4, "not a distilled student"), (tiny_student, 2, "a student of 4 calls")]:
        with pytest.raises(ValueError, match=match) as e:
            distill(latent_teacher, tiny_dataset, tmp_path / f"bad{calls}", steps=1, calls=calls, init_from=init, **kw)
        assert "\n" not in str(e.value) and not (tmp_path / f"bad{calls}" / "checkpoints").exists()
        assert not (tmp_path / f"bad{calls}" / "pairs").exists()  # refused before the teacher pairs
    task = prepare_distillation(latent_teacher, tiny_dataset, tmp_path / "other", pairs=2, pair_points=16,
                                teacher_steps=4)  # fmt: skip
    task.teacher_sha256 = "0" * 64
    with pytest.raises(ValueError, match="a student of another teacher"):
        student_start(task, tiny_student)


def test_distill_resume_after_a_kill_while_making_pairs(latent_teacher, tiny_dataset, tmp_path, capsys):
    """A run killed before its first student checkpoint (pairs made, or half made) goes on with
    ``--resume``: the pairs are kept, the student starts from the teacher; ``--resume`` into an
    empty folder is still a one-line error."""
    from pocoloco.cli import main
    from pocoloco.methods.pocoloco.distill import prepare_distillation

    out = tmp_path / "d"
    prepare_distillation(latent_teacher, tiny_dataset, out, pairs=3, pair_points=32, teacher_steps=4)
    stamp = (out / "pairs" / "shard_00000.npz").stat().st_mtime_ns
    args = ["distill", "--ckpt", str(latent_teacher), "--data", str(tiny_dataset), "--pairs", "3", "--pair-points",
            "32", "--teacher-steps", "4", "--steps", "2", "--batch-size", "2", "--threads", "1", "--device", "cpu",
            "--resume"]  # fmt: skip
    assert main([*args, "--out", str(out)]) == 0
    assert "no student checkpoint yet" in " ".join(capsys.readouterr().err.split())
    assert (out / "pairs" / "shard_00000.npz").stat().st_mtime_ns == stamp
    assert (out / "model" / "meta.json").is_file()
    assert main([*args, "--out", str(tmp_path / "empty")]) != 0
    err = " ".join(capsys.readouterr().err.split())
    assert "--resume but no checkpoint" in err and "Traceback" not in err


def test_distill_refuses_bad_teachers_and_settings(latent_teacher, tiny_run, tiny_dataset, tmp_path):
    from pocoloco.methods.pocoloco.distill import PairSettings, distill

    for kwargs, match in [({"teacher_sampler": "dpm++sde"}, "must sample deterministically"),
                          ({"teacher_steps": 10}, "multiple of --calls"),
                          ({"calls": 0}, "--calls must be")]:  # fmt: skip
        with pytest.raises(ValueError, match=match) as e:
            distill(latent_teacher, tiny_dataset, tmp_path / "x", pairs=2, pair_points=16, steps=1, progress=False,
                    **kwargs)  # fmt: skip
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="only the latent denoiser"):
        distill(tiny_run, tiny_dataset, tmp_path / "y", pairs=2, pair_points=16, steps=1, progress=False)
    assert PairSettings(2, 16, 4, "dpm++", 20, 0, 16, "t", "s").check(1000)[:2] == [999, 949]


def test_int8_rows_round_off_within_half_a_step():
    from pocoloco.engine.checkpoint import dequantise_int8, quantise_int8

    v = torch.randn(7, 3, 40, generator=torch.Generator().manual_seed(3))
    v[0, 0] = 0.0  # an all-zero row
    q, s = quantise_int8(v)
    assert q.dtype == torch.int8 and s.shape == (7, 3)
    back = dequantise_int8(q, s)
    for idx in np.ndindex(7, 3):  # the slow reference: row by row
        row = v[idx]
        step = float(row.abs().max()) / 127 or 1.0
        assert float((back[idx] - row).abs().max()) <= 0.5 * step * 1.002 + 1e-7
    assert torch.equal(back[0, 0], torch.zeros(40))


def test_int8_export_loads_close_to_float32_and_says_when_damaged(tiny_run, tmp_path):
    from safetensors.torch import load_file, save_file

    from pocoloco.engine.checkpoint import export_for_sampling, load_checkpoint

    f32 = export_for_sampling(tiny_run, tmp_path / "f32", dtype="float32")
    i8 = export_for_sampling(tiny_run, tmp_path / "i8", dtype="int8")
    assert (i8 / "model.safetensors").stat().st_size < 0.4 * (f32 / "model.safetensors").stat().st_size
    a, b = load_checkpoint(f32).model_state, load_checkpoint(i8).model_state
    assert set(a) == set(b)
    for k in a:
        assert b[k].dtype == a[k].dtype, k
        if a[k].is_floating_point():
            assert float((a[k] - b[k]).abs().max()) <= 0.01 * float(a[k].abs().max()) + 1e-3, k
    raw = load_file(str(i8 / "model.safetensors"))
    key = next(k for k in raw if k.endswith(".int8_scale"))
    raw[key] = raw[key][:-1]
    bad = tmp_path / "bad"
    bad.mkdir()
    save_file(raw, str(bad / "model.safetensors"))
    import shutil

    shutil.copy(i8 / "meta.json", bad / "meta.json")
    with pytest.raises(ValueError) as e:
        load_checkpoint(bad)
    assert "\n" not in str(e.value)


def test_pair_batches_mix_teacher_states_and_renoised_answers(four):
    """A re-noised draw is the teacher's answer noised to its grid time (never at the noisiest time);
    the others are the teacher's stored states; the same step gives the same batch."""
    from pocoloco.methods.pocoloco.distill import PairBatches, PairSettings, TeacherPairs

    rng = np.random.default_rng(0)
    P, K, N = 5, 4, 16
    pairs = TeacherPairs(rng.standard_normal((P, K, N, 3)).astype(np.float32),
                         rng.standard_normal((P, N, 3)).astype(np.float32), np.zeros((P, 24, 3), np.float32),
                         np.zeros(P, np.int64), None, student_grid(1000, 4),
                         PairSettings(P, N, 4, "dpm++", 20, 0, 16, "t", "s"))  # fmt: skip
    ab = four.alphas_cumprod.double().numpy()
    batches = PairBatches(pairs, 64, 0, 10, renoised=0.5, alpha_bar=ab)
    b = batches[3]
    assert torch.equal(b["x"], batches[3]["x"])
    traj, t = b["trajectory"].numpy(), b["t"].numpy()
    assert (t[~traj] != 999).all() and 0 < (~traj).sum() < 64 and (t == 999).sum() > 10
    for i in range(64):
        target = b["target"][i].numpy()
        if traj[i]:
            k = pairs.grid.index(int(t[i]))
            assert any(np.array_equal(b["x"][i].numpy(), pairs.states[p, k]) for p in range(P))
        else:  # x = sqrt(abar) target + sqrt(1 - abar) z with z ~ N(0, 1)
            z = (b["x"][i].numpy() - np.sqrt(ab[t[i]]) * target) / np.sqrt(1 - ab[t[i]])
            assert abs(z.std() - 1) < 0.35 and not any(np.allclose(b["x"][i].numpy(), pairs.states[p, k])
                                                       for p in range(P) for k in range(K))  # fmt: skip
    with pytest.raises(ValueError, match="alpha_bar"):
        PairBatches(pairs, 4, 0, 10, renoised=0.5)


def test_a_diffusion_model_finishes_with_its_own_call(latent_teacher, tiny_student, tmp_path, torch_single_thread):
    """``finish_t`` / ``--finish-t``: after its chain the model's own x0 at step T of the cloud
    re-noised there, equal to the chain then ``polish`` with the model as its own teacher, written
    out; recorded in sample.json and the judge's settings; a student, a step outside [1, T] or a
    non-integer is a one-line error before any work; a deterministic model warns and ignores it."""
    from pocoloco.cli import main
    from pocoloco.diffusion import sample as diffusion_sample
    from pocoloco.methods import SamplerOptions, load_method
    from pocoloco.methods.pocoloco.sampling import condition_for

    m = load_method(latent_teacher)
    pose = m.load_pose("demo:skirt")
    joints = np.asarray(pose.joints)
    opts = SamplerOptions(sampler="dpm++sde", steps=4, finish_t=5)
    got = m.predict(pose, 40, seeds=[2], outfit=0, options=opts).points[0]
    plain = m.predict(pose, 40, seeds=[2], outfit=0, options=SamplerOptions(sampler="dpm++sde", steps=4)).points[0]
    assert not np.allclose(got, plain)

    schedule = NoiseSchedule.from_kind(m.config.schedule, m.config.num_timesteps)
    kw = m.condition(0)
    joints_n = m.normalisation.normalise(np.zeros((1, 3), np.float32), joints)[1]
    cond = condition_for(torch.as_tensor(joints_n)[None], kw["outfit"], kw["shape"])
    rng = PerSampleRNG([2])
    x = diffusion_sample("dpm++sde", m.model, schedule, rng.randn((40, 3)), cond, rng=rng, steps=4,
                         prediction_type=m.config.prediction_type, clip=None)  # fmt: skip
    x = polish(m.model, schedule, x, cond, 5, rng, prediction_type=m.config.prediction_type)
    root = m.normalisation.root(joints).astype(np.float32)
    ref = m.normalisation.denormalise(x.numpy(), root, m.normalisation.angle(joints))[0]
    np.testing.assert_allclose(got, ref, atol=1e-5)
    assert m.sample_settings(opts, 40)["finish_t"] == 5 and "finish_t" not in m.sample_settings(SamplerOptions(), 40)

    out = tmp_path / "s"
    assert main(["sample", "--ckpt", str(latent_teacher), "--points", "40", "--num", "1", "--steps", "4",
                 "--finish-t", "5", "--no-render", "--out", str(out)]) == 0  # fmt: skip
    assert json.loads((out / "sample.json").read_text())["finish_t"] == 5
    student = load_method(tiny_student)
    for method, t, match in [(m, 0, r"\[1, 1000\], got 0"), (m, 1001, "got 1001"), (m, 2.5, "got 2.5"),
                             (student, 5, "is for a diffusion model")]:  # fmt: skip
        with pytest.raises(ValueError, match=match) as e:
            method.check_options(SamplerOptions(finish_t=t))
        assert "\n" not in str(e.value)
    assert main(["sample", "--ckpt", str(tiny_student), "--points", "40", "--finish-t", "5", "--no-render",
                 "--out", str(tmp_path / "refused")]) == 2  # fmt: skip
    assert not (tmp_path / "refused" / "sample.json").exists()


def test_shipped_fast_model_samples_with_its_own_sampler(tmp_path):
    """``--ckpt default:fast``: a student of the shipped default (its teacher named by SHA-256), int8
    weights, 4 calls by default (3 of its own, the default's last: ``polish``); a clothed body near
    the demo pose's joints; a diffusion sampler or 6 calls is a one-line error."""
    from pocoloco.cli import main
    from pocoloco.engine.shipped import default_checkpoint, describe_checkpoint

    path = default_checkpoint("fast")
    meta = json.loads((path / "meta.json").read_text())
    teacher = json.loads((default_checkpoint() / "meta.json").read_text())
    assert meta["weights_dtype"] == "int8" and meta["config"]["student_calls"] == 4
    assert meta["distilled_from"]["teacher_sha256"] == teacher["meta_sha256"]
    assert meta["polish"] == {"ckpt": "default", "meta_sha256": teacher["meta_sha256"], "t": 5}
    assert describe_checkpoint(path) == "default:fast"
    out = tmp_path / "s"
    assert main(["sample", "--ckpt", "default:fast", "--points", "400", "--num", "2", "--no-render", "--threads", "1",
                 "--out", str(out)]) == 0  # fmt: skip
    info = json.loads((out / "sample.json").read_text())
    assert info["sampler"] == "few-step" and info["steps"] == 4
    assert info["student_timesteps"] == [999, 749, 249] and info["polish"] == {"with": "default", "t": 5}
    from pocoloco.data.published import read_ply
    from pocoloco.methods import load_method

    pts = read_ply(out / "sample_000.ply").points
    joints = np.asarray(load_method(path).load_pose("demo:skirt").joints)
    assert np.isfinite(pts).all() and np.linalg.norm(pts.mean(0) - joints.mean(0)) < 0.3
    for extra in (["--sampler", "ddim"], ["--steps", "6"]):
        assert main(["sample", "--ckpt", "default:fast", "--points", "64", "--out", str(tmp_path / "x"), *extra]) == 2


def test_shipped_fast_hybrid_links_pop_and_the_student_with_the_hybrids_maps(tmp_path):
    """``--ckpt default:hybrid-fast``: ``default:hybrid`` with ``default:fast`` as its free-region
    generator (linked by name, the same maps); it samples, and the student's call counts apply."""
    from pocoloco.cli import main
    from pocoloco.engine.shipped import default_checkpoint, describe_checkpoint
    from pocoloco.methods import load_method

    path = default_checkpoint("hybrid-fast")
    assert describe_checkpoint(path) == "default:hybrid-fast"
    m, ref = load_method(path), load_method(default_checkpoint("hybrid"))
    assert m.config.sources == {"attached": "default:pop", "free": "default:fast"}
    assert m.free.config.student_calls == 4 and ref.free.config.student_calls == 0
    o = m.outfit_id("skirt_a")
    assert (m.maps.free(o) == ref.maps.free(o)).all()
    out = tmp_path / "s"
    assert main(["sample", "--ckpt", "default:hybrid-fast", "--points", "300", "--num", "2", "--no-render",
                 "--threads", "1", "--out", str(out)]) == 0  # fmt: skip
    assert main(["sample", "--ckpt", "default:hybrid-fast", "--points", "64", "--steps", "5",
                 "--out", str(tmp_path / "x")]) == 2  # fmt: skip


def test_a_student_refuses_to_fit_an_outfit():
    from pocoloco.apps.fitting import fit_outfit
    from pocoloco.engine.shipped import default_checkpoint
    from pocoloco.methods import load_method

    assert not load_method(default_checkpoint("fast")).fits_outfits and load_method(default_checkpoint()).fits_outfits
    with pytest.raises(ValueError, match="a distilled model cannot") as e:
        fit_outfit(default_checkpoint("fast"), [], "/tmp/never")
    assert "\n" not in str(e.value)


def test_edit_and_complete_with_the_fast_model_start_on_its_grid(tmp_path):
    """``edit`` / ``complete`` with ``default:fast`` and no ``--t``: the chain starts at t = 250 (one
    call); a t off the grid is a one-line error naming the grid."""
    from pocoloco.cli import main
    from pocoloco.data.published import read_ply

    assert main(["sample", "--ckpt", "default:fast", "--points", "300", "--num", "1", "--no-render",
                 "--out", str(tmp_path / "src")]) == 0  # fmt: skip
    src = tmp_path / "src" / "sample_000.ply"
    assert main(["edit", "--ckpt", "default:fast", "--source", str(src), "--joints", "demo:skirt", "--no-render",
                 "--out", str(tmp_path / "ed")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "ed" / "edit.json").read_text())["t"] == 250
    part = read_ply(src).points
    np.save(tmp_path / "part.npy", part[part[:, 2] > np.median(part[:, 2])])
    assert main(["complete", "--ckpt", "default:fast", "--partial", str(tmp_path / "part.npy"), "--joints",
                 "demo:skirt", "--points", "400", "--no-render", "--out", str(tmp_path / "cp")]) == 0  # fmt: skip
    assert main(["edit", "--ckpt", "default:fast", "--source", str(src), "--joints", "demo:skirt", "--t", "100",
                 "--no-render", "--out", str(tmp_path / "bad")]) == 2  # fmt: skip


def test_the_apps_chains_end_with_the_finishing_call(latent_teacher, tiny_student, tmp_path, torch_single_thread):
    """A polished student's app chains (editing, completion, each animation frame: ``denoise_from``)
    end with its teacher's call, equal to the student's chain then ``polish`` written out; with
    ``polish=False`` they are the plain student's; known points stay known."""
    from pocoloco.apps.animation import animate
    from pocoloco.apps.common import denoise_from
    from pocoloco.cli import main
    from pocoloco.methods import load_method

    out = tmp_path / "p"
    assert main(["export-model", "--ckpt", str(tiny_student), "--polish-with", str(latent_teacher), "--polish-t", "30",
                 "--out", str(out)]) == 0  # fmt: skip
    m, plain = load_method(out), load_method(tiny_student)
    prior, plain_prior = m.point_prior(0), plain.point_prior(0)
    assert prior.polish is not None and prior.polish[1] == 30 and plain_prior.polish is None
    joints = np.asarray(m.load_pose("demo:skirt").joints)
    x0 = np.random.default_rng(0).normal(size=(1, 40, 3)).astype(np.float32)
    got = denoise_from(prior, joints, x0, 250, seeds=[4])
    student_only = denoise_from(plain_prior, joints, x0, 250, seeds=[4])
    np.testing.assert_array_equal(denoise_from(prior, joints, x0, 250, seeds=[4], polish=False), student_only)
    # written out: the student's call from t = 250, then the teacher at t = 30, one generator
    rng = PerSampleRNG([4])
    noise = rng.randn((40, 3))
    from pocoloco.diffusion.chains import renoise
    from pocoloco.diffusion.samplers import sample

    _, joints_n = prior.normalisation.normalise(np.zeros((1, 3), np.float32), joints)
    cond = torch.as_tensor(joints_n)[None]
    x = sample("few-step", prior.denoiser, prior.schedule, renoise(prior.schedule, x0, noise, 250), cond,
               timesteps=[249], rng=rng, prediction_type=prior.prediction_type, renoise=prior.student_renoise)  # fmt: skip
    ref = polish(prior.polish[0], prior.schedule, x, cond, 30, rng, prediction_type=prior.prediction_type)
    np.testing.assert_allclose(got, ref.float().numpy(), atol=1e-5)
    assert np.abs(got - student_only).max() > 1e-4
    mask = np.zeros((1, 40), bool)
    mask[0, :10] = True
    kept = denoise_from(prior, joints, None, 250, seeds=[4], known=(mask, x0))
    np.testing.assert_allclose(kept[0, :10], x0[0, :10], atol=1e-6)
    # animate: two frames, the finishing call on each unless told
    poses = np.stack([joints, joints + 0.01]).astype(np.float32)
    a = animate(prior, poses, 32, t=250, seed=1)
    b = animate(prior, poses, 32, t=250, seed=1, polish=False)
    c = animate(plain_prior, poses, 32, t=250, seed=1)
    np.testing.assert_array_equal(b.points, c.points)
    assert np.abs(a.points - c.points).max() > 1e-4


def test_set_energy_distance_matches_the_judges_statistic():
    """The torch probe embedding and energy distance of the set-level loss are the judge's
    (``embed_cloud`` with a KD-tree, ``energy_distance`` in float64 numpy), and their gradient
    moves a collapsed set of draws apart."""
    from pocoloco.evaluation.distribution import embed_cloud, energy_distance
    from pocoloco.ops.probe_energy import box_probes, probe_embedding, set_energy_distance

    rng = np.random.default_rng(0)
    G, M, K, N, P = 2, 3, 4, 50, 40
    s = torch.from_numpy(rng.standard_normal((G, M, N, 3)))
    t = torch.from_numpy(rng.standard_normal((G, K, N, 3)) * 1.5)
    probes = box_probes(t, P, torch.Generator().manual_seed(0))
    assert probes.shape == (G, P, 3)
    lo, hi = t.flatten(1, 2).amin(1), t.flatten(1, 2).amax(1)
    assert ((probes >= (lo - 0.05 * (hi - lo)).unsqueeze(1)) & (probes <= (hi + 0.05 * (hi - lo)).unsqueeze(1))).all()
    es, et = probe_embedding(s, probes.unsqueeze(1)), probe_embedding(t, probes.unsqueeze(1))
    got = set_energy_distance(es, et)
    for g in range(G):
        ref_s = np.stack([embed_cloud(c, None, probes[g].numpy()) for c in s[g].numpy()])
        ref_t = np.stack([embed_cloud(c, None, probes[g].numpy()) for c in t[g].numpy()])
        np.testing.assert_allclose(es[g].numpy(), ref_s, rtol=1e-6, atol=1e-9)
        ref = energy_distance(ref_s, ref_t)
        for key in ("to_refs", "spread_samples", "spread_refs", "energy_distance", "energy_score"):
            assert got[key][g].item() == pytest.approx(ref[key], rel=1e-6), key
    # M copies of one cloud (no spread) against a spread-out truth: the gradient spreads them
    one = s[:, :1].repeat(1, M, 1, 1) + 1e-3 * torch.from_numpy(rng.standard_normal((G, M, N, 3)))
    one.requires_grad_(True)
    ed = set_energy_distance(probe_embedding(one, probes.unsqueeze(1)), et)
    ed["energy_distance"].sum().backward()
    moved = (one - 0.5 * one.grad).detach()
    after = set_energy_distance(probe_embedding(moved, probes.unsqueeze(1)), et)
    assert (after["spread_samples"] > ed["spread_samples"].detach()).all()
    assert (after["energy_distance"] < ed["energy_distance"].detach()).all()
    with pytest.raises(ValueError, match="share G and P"):
        set_energy_distance(es, et[:, :, :5])


def test_grouped_pair_batches_hold_whole_frames_at_one_time(four):
    """With D draws per frame, a grouped batch is B / D whole frames: their D pairs consecutive,
    at one grid time; ungrouped batches are unchanged by D; bad group sizes are one-line errors."""
    from pocoloco.methods.pocoloco.distill import PairBatches, PairSettings, TeacherPairs

    rng = np.random.default_rng(0)
    P, K, N, D = 12, 4, 8, 3
    joints = np.repeat(rng.standard_normal((P // D, 24, 3)), D, axis=0).astype(np.float32)
    pairs = TeacherPairs(rng.standard_normal((P, K, N, 3)).astype(np.float32),
                         rng.standard_normal((P, N, 3)).astype(np.float32), joints, np.zeros(P, np.int64), None,
                         student_grid(1000, 4), PairSettings(P, N, 4, "dpm++", 20, 0, 12, "t", "s", draws=D))  # fmt: skip
    b = PairBatches(pairs, 6, 0, 10, grouped=True)[2]
    x, t = b["x"].numpy().reshape(2, D, N, 3), b["t"].numpy().reshape(2, D)
    assert (t == t[:, :1]).all()
    for g in range(2):
        assert (b["joints"].numpy().reshape(2, D, 24, 3)[g] == b["joints"][g * D].numpy()).all()
        assert len({x[g, i].tobytes() for i in range(D)}) == D  # D different pairs of the frame
    plain = PairBatches(pairs, 6, 0, 10)[2]
    assert plain["x"].shape == (6, N, 3)
    for draws, batch in [(1, 6), (3, 4)]:
        p = TeacherPairs(*[getattr(pairs, f) for f in ("states", "targets", "joints", "subject", "motion", "grid")],
                         PairSettings(P, N, 4, "dpm++", 20, 0, 12, "t", "s", draws=draws))  # fmt: skip
        with pytest.raises(ValueError, match="pairs per frame") as e:
            PairBatches(p, batch, 0, 10, grouped=True)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="--draws-per-frame 5"):
        PairSettings(12, N, 4, "dpm++", 20, 0, 16, "t", "s", draws=5).check(1000)


def test_distill_with_the_set_level_loss(latent_teacher, tiny_dataset, tmp_path, torch_single_thread):
    """``--draws-per-frame 2 --set-weight``: the pairs come in twos of one frame (two noises), the run
    logs the set statistics and records the draws; without enough draws it is refused before any
    pair is made; an old pairs folder (no ``draws``) still reads as one draw per frame."""
    from pocoloco.methods.pocoloco.distill import PAIRS_FILE, distill, read_teacher_pairs

    out = tmp_path / "d"
    kw = dict(calls=4, pairs=4, pair_points=32, teacher_steps=8, batch_size=4, progress=False, log_every=1)
    distill(latent_teacher, tiny_dataset, out, steps=3, draws=2, distill_set=1.0, **kw)
    pairs = read_teacher_pairs(out / "pairs")
    assert pairs.settings.draws == 2
    np.testing.assert_array_equal(pairs.joints[0], pairs.joints[1])
    np.testing.assert_array_equal(pairs.joints[2], pairs.joints[3])
    assert not np.allclose(pairs.states[0, 0], pairs.states[1, 0]) and not np.allclose(pairs.targets[0], pairs.targets[1])
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["set_energy_distance"]) and r["set_spread_refs"] > 0 and r["loss"] > 0 for r in logged)
    assert all(r["set_spread_samples"] > 0 for r in logged)  # the chain's answers differ per noise
    meta = json.loads((out / "model" / "meta.json").read_text())
    assert meta["distilled_from"]["draws_per_frame"] == 2 and meta["config"]["distill_set"] == 1.0
    with pytest.raises(ValueError, match="--set-weight needs") as e:
        distill(latent_teacher, tiny_dataset, tmp_path / "bad", steps=1, distill_set=1.0, **kw)
    assert "\n" not in str(e.value) and not (tmp_path / "bad" / "pairs").exists()
    # a folder made before `draws` existed
    old = tmp_path / "old"
    distill(latent_teacher, tiny_dataset, old, steps=1, **{**kw, "pairs": 2, "batch_size": 2})
    meta_path = old / "pairs" / PAIRS_FILE
    settings = json.loads(meta_path.read_text())
    del settings["draws"]
    meta_path.write_text(json.dumps(settings))
    assert read_teacher_pairs(old / "pairs").settings.draws == 1
    distill(latent_teacher, tiny_dataset, old, steps=2, resume=True, **{**kw, "pairs": 2, "batch_size": 2})


def test_the_set_terms_chain_is_the_students_sampler(latent_teacher, tiny_dataset, tmp_path, torch_single_thread):
    """The set-level term scores what the student samples: its chain (no gradient but the last
    call's) equals ``sample_few_step`` on the grid it ships with, given the same noise stream."""
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.distill import DistillTask, chain_grid, distill_config

    assert chain_grid(1000, 4) == [999, 749, 249] and chain_grid(1000, 2) == [999, 499]
    teacher = load_method(latent_teacher)
    task = DistillTask(distill_config(teacher.config, 4, distill_set=1.0), tiny_dataset)
    noise = torch.randn(4, 32, 3, generator=torch.Generator().manual_seed(1))
    cond = task.condition(torch.zeros(4, 24, 3), torch.zeros(4, dtype=torch.long))
    net = teacher.model.eval()
    got = task.student_chain(net, noise, cond, torch.Generator().manual_seed(5))
    assert got.requires_grad
    with torch.no_grad():
        want = sample_few_step(net, task.schedule, noise, cond, timesteps=[999, 749, 249], renoise=1.0,
                               rng=torch.Generator().manual_seed(5), prediction_type=task.config.prediction_type)  # fmt: skip
    torch.testing.assert_close(got.detach(), want, atol=1e-4, rtol=1e-4)
    # the chain term's 2-call chain is the 2-call sampler (999, then 249)
    got = task.student_chain(net, noise, cond, torch.Generator().manual_seed(6), grid=sampling_grid(1000, 2, 4))
    with torch.no_grad():
        want = sample_few_step(net, task.schedule, noise, cond, timesteps=[999, 249], renoise=1.0,
                               rng=torch.Generator().manual_seed(6), prediction_type=task.config.prediction_type)  # fmt: skip
    torch.testing.assert_close(got.detach(), want, atol=1e-4, rtol=1e-4)
    # --chain-grad all: the same answers, the gradient through every call (the first call's too)
    for grid, seed in (([999, 249], 6), ([999, 749, 249], 5)):
        net.zero_grad()
        got = task.student_chain(net, noise, cond, torch.Generator().manual_seed(seed), grid=grid, grad="all")
        with torch.no_grad():
            want = sample_few_step(net, task.schedule, noise, cond, timesteps=grid, renoise=1.0,
                                   rng=torch.Generator().manual_seed(seed), prediction_type=task.config.prediction_type)  # fmt: skip
        torch.testing.assert_close(got.detach(), want, atol=1e-4, rtol=1e-4)
    # the first call gets a gradient through the re-noised state only with "all"
    grads = {}
    for grad in ("last", "all"):
        x = noise.clone().requires_grad_(True)
        task.student_chain(net, x, cond, torch.Generator().manual_seed(6), grid=[999, 249], grad=grad).square().sum().backward()
        grads[grad] = x.grad
    assert grads["last"] is None and grads["all"].abs().sum() > 0
    with pytest.raises(ValueError, match="grad must be last or all"):
        task.student_chain(net, noise, cond, torch.Generator().manual_seed(6), grad="first")
    with pytest.raises(ValueError, match="end_at must be in"):  # the shared sampler stops only below its last step
        sample_ddim(net, task.schedule, noise, cond, timesteps=[999, 749], end_at=749)


def test_distill_with_the_teachers_answers_from_renoised_states(latent_teacher, tiny_dataset, tmp_path,
                                                               torch_single_thread):  # fmt: skip
    """``--renoised-targets ode``: beside each pair shard, its answer noised afresh to each later grid
    time and the teacher's deterministic sampler run from there over its own remaining timesteps
    (checked against that sampler called directly); they are made once (a rerun keeps them), read
    back with the pairs, and the batches' re-noised draws are those stored states with those
    answers, scored point by point; asked for without re-noised draws, or read incomplete, a
    one-line error."""
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.distill import (DistillTask, PairBatches, distill, distill_config,
                                                   read_teacher_pairs)  # fmt: skip
    from pocoloco.utils.seeding import seed_of

    out = tmp_path / "d"
    kw = dict(calls=4, pairs=4, pair_points=32, teacher_steps=8, batch_size=4, progress=False, log_every=1,
              distill_renoised=0.5, distill_renoised_targets="ode")  # fmt: skip
    distill(latent_teacher, tiny_dataset, out, steps=2, **kw)
    pairs = read_teacher_pairs(out / "pairs", renoised=True)
    assert pairs.renoised_states.shape == pairs.renoised_targets.shape == (4, 3, 32, 3)
    # the slow reference: the stored state is the answer noised with the pair's own noise stream, the
    # stored answer the teacher's DPM-Solver++ ODE from it over its timesteps from that grid time on
    teacher = load_method(latent_teacher)
    task = DistillTask(distill_config(teacher.config, 4), tiny_dataset)
    schedule, i = task.schedule, 2
    rng = PerSampleRNG([seed_of(0, 14, i)])  # distill seed 0
    ts = make_timesteps(1000, 8, "trailing")
    cond = task.condition(torch.from_numpy(pairs.joints[i:i + 1]), torch.from_numpy(pairs.subject[i:i + 1]))
    for k, t in enumerate(pairs.grid[1:]):
        ab = schedule.alphas_cumprod.double()[t]
        x = (ab.sqrt() * torch.from_numpy(pairs.targets[i:i + 1]).double()
             + (1 - ab).sqrt() * rng.randn((32, 3)).double()).float()  # fmt: skip
        torch.testing.assert_close(torch.from_numpy(pairs.renoised_states[i:i + 1, k]), x)
        want = sample("dpm++", teacher.model.eval(), schedule, x, cond, timesteps=ts[ts.index(t):],
                      prediction_type=task.config.prediction_type)  # fmt: skip
        torch.testing.assert_close(torch.from_numpy(pairs.renoised_targets[i:i + 1, k]), want, atol=1e-4, rtol=1e-4)
    assert not np.allclose(pairs.renoised_targets[:, 0], pairs.targets)  # from 749 the teacher draws anew
    # batches: a re-noised draw is a stored state with its stored answer, every draw scored per point
    b = PairBatches(pairs, 64, 0, 5, renoised=0.5, alpha_bar=schedule.alphas_cumprod.double().numpy())[1]
    assert b["trajectory"].all()
    hits = 0
    for j in range(64):
        k = pairs.grid.index(int(b["t"][j]))
        on_path = [p for p in range(4) if np.array_equal(b["x"][j].numpy(), pairs.states[p, k])]
        stored = [p for p in range(4) if k and np.array_equal(b["x"][j].numpy(), pairs.renoised_states[p, k - 1])]
        assert len(on_path) + len(stored) == 1
        want = pairs.targets[on_path[0]] if on_path else pairs.renoised_targets[stored[0], k - 1]
        np.testing.assert_array_equal(b["target"][j].numpy(), want)
        hits += bool(stored)
    assert 0 < hits < 64
    meta = json.loads((out / "model" / "meta.json").read_text())
    assert meta["distilled_from"]["renoised_targets"] == "ode"
    assert np.array_equal(read_teacher_pairs(out / "pairs", renoised=None).renoised_targets, pairs.renoised_targets)
    # made once: a resumed run keeps them
    stamp = (out / "pairs" / "renoised_00000.npz").stat().st_mtime_ns
    distill(latent_teacher, tiny_dataset, out, steps=3, resume=True, **kw)
    assert (out / "pairs" / "renoised_00000.npz").stat().st_mtime_ns == stamp
    (out / "pairs" / "renoised_00000.npz").unlink()
    with pytest.raises(ValueError, match="re-noised teacher pairs incomplete") as e:
        read_teacher_pairs(out / "pairs", renoised=True)
    assert "\n" not in str(e.value)
    assert read_teacher_pairs(out / "pairs", renoised=None).renoised_states is None  # where they are all there
    with pytest.raises(ValueError, match="--renoised-share > 0") as e:
        distill(latent_teacher, tiny_dataset, tmp_path / "bad", steps=1, **{**kw, "distill_renoised": 0.0})
    assert "\n" not in str(e.value) and not (tmp_path / "bad" / "pairs").exists()


def test_distill_with_the_chain_term(latent_teacher, tiny_dataset, tmp_path, torch_single_thread):
    """``--chain-weight``: each pair's noise down the student's 2-call sampler, scored against the
    teacher's answer by Chamfer; the run logs its terms, records the weight, and its gradient moves the
    student (a run with it ends elsewhere than one without); a chain longer than the grid is refused
    in one line before any pair is made."""
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.distill import distill

    kw = dict(calls=4, pairs=4, pair_points=32, teacher_steps=8, batch_size=4, progress=False, log_every=1)
    distill(latent_teacher, tiny_dataset, tmp_path / "c", steps=2, distill_chain=1.0, **kw)
    logged = [json.loads(line) for line in (tmp_path / "c" / "metrics.jsonl").read_text().splitlines()]
    assert logged and all(r["chain_chamfer"] > 0 and r["loss"] > r["huber"] + r["chamfer"] for r in logged)
    assert not any("chain_huber" in r for r in logged)  # fresh noise between the calls: Chamfer alone
    meta = json.loads((tmp_path / "c" / "model" / "meta.json").read_text())
    assert meta["config"]["distill_chain"] == 1.0 and meta["config"]["distill_chain_calls"] == 2
    distill(latent_teacher, tiny_dataset, tmp_path / "p", steps=2, **kw)
    a = load_method(tmp_path / "c" / "model").model.state_dict()
    b = load_method(tmp_path / "p" / "model").model.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="--chain-calls") as e:
        distill(latent_teacher, tiny_dataset, tmp_path / "bad", steps=1, distill_chain=1.0, distill_chain_calls=5, **kw)
    assert "\n" not in str(e.value) and not (tmp_path / "bad" / "pairs").exists()
    # --chain-grad all: the first call learns from the chain too, so the run ends elsewhere again
    distill(latent_teacher, tiny_dataset, tmp_path / "g", steps=2, distill_chain=1.0, distill_chain_grad="all", **kw)
    g = load_method(tmp_path / "g" / "model").model.state_dict()
    assert json.loads((tmp_path / "g" / "model" / "meta.json").read_text())["config"]["distill_chain_grad"] == "all"
    assert any(not torch.equal(a[k], g[k]) for k in a)
    with pytest.raises(ValueError, match="--chain-grad") as e:
        distill(latent_teacher, tiny_dataset, tmp_path / "bad2", steps=1, distill_chain=1.0, distill_chain_grad="first", **kw)
    assert "\n" not in str(e.value) and not (tmp_path / "bad2" / "pairs").exists()


def test_the_set_term_on_the_2_call_chain(latent_teacher, tiny_dataset, tmp_path, torch_single_thread, monkeypatch):
    """``--set-calls 2``: the set-level term scores the student's 2-call draws (999, then 249); beside
    the chain term on the same 2 calls the two share one chain per step (the set term's own chain
    runs only where the grids differ); the run logs both terms and records the calls; a count
    beyond the student's grid is refused in one line before any pair is made."""
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.distill import DistillTask, distill, distill_config

    teacher = load_method(latent_teacher)
    assert DistillTask(distill_config(teacher.config, 4, distill_set=1.0, distill_set_calls=2), tiny_dataset).set_grid() \
        == [999, 249]  # fmt: skip
    assert DistillTask(distill_config(teacher.config, 4, distill_set=1.0), tiny_dataset).set_grid() == [999, 749, 249]
    chains = []
    real = DistillTask.student_chain
    monkeypatch.setattr(DistillTask, "student_chain", lambda self, *a, **k: chains.append(k.get("grid")) or real(self, *a, **k))
    kw = dict(calls=4, pairs=4, pair_points=32, teacher_steps=8, batch_size=4, draws=2, progress=False, log_every=1)
    distill(latent_teacher, tiny_dataset, tmp_path / "s", steps=2, distill_set=1.0, distill_set_calls=2,
            distill_chain=1.0, **kw)  # fmt: skip
    assert chains == [[999, 249]] * 2  # one shared chain per step
    logged = [json.loads(line) for line in (tmp_path / "s" / "metrics.jsonl").read_text().splitlines()]
    assert logged and all(r["chain_chamfer"] > 0 and np.isfinite(r["set_energy_distance"]) for r in logged)
    assert json.loads((tmp_path / "s" / "model" / "meta.json").read_text())["config"]["distill_set_calls"] == 2
    chains.clear()
    distill(latent_teacher, tiny_dataset, tmp_path / "d", steps=2, distill_set=1.0, distill_chain=1.0, **kw)
    assert chains == [[999, 249], [999, 749, 249]] * 2  # the default set grid differs: its own chain
    with pytest.raises(ValueError, match="--set-calls") as e:
        distill(latent_teacher, tiny_dataset, tmp_path / "bad", steps=1, distill_set=1.0, distill_set_calls=5, **kw)
    assert "\n" not in str(e.value) and not (tmp_path / "bad" / "pairs").exists()
