"""Training loop and checkpoints: schedules, data order, exact resume, DDP replicas, bad input."""

import dataclasses
import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pocoloco.cli import main as cli_main
from pocoloco.cli.train import add_train_arguments
from pocoloco.data.dataset import PointCloudDataset
from pocoloco.data.step_batches import StepBatches
from pocoloco.engine import checkpoint as ckpt_io
from pocoloco.engine.trainer import ema_decay_at, lr_at
from pocoloco.methods import train
from pocoloco.methods.pocoloco import TRAIN_PRESETS, load_denoiser, train_preset
from pocoloco.methods.pocoloco import PocoLocoTrainConfig as TrainConfig

# tiny models run fastest on one thread, and bit-exact comparisons need a fixed thread count
pytestmark = pytest.mark.usefixtures("torch_single_thread")


def tiny(**overrides) -> TrainConfig:
    """The tiny preset made even faster: no samples, no intermediate checkpoints."""
    base = dict(steps=4, batch_size=2, num_points=256, ckpt_every=0, sample_every=0, log_every=1)
    return train_preset("tiny", **{**base, **overrides})


def _states_equal(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k].float() - b[k].float()).abs().max()) for k in a)


# ------------------------------------------------------------------------------- pure pieces
def test_lr_warmup_and_cosine():
    c = train_preset("tiny", steps=10, warmup_steps=4, lr=1.0, lr_schedule="cosine")
    lrs = [lr_at(c.loop(), s) for s in range(10)]
    assert lrs[:4] == [0.25, 0.5, 0.75, 1.0]
    assert lrs[4] == pytest.approx(1.0) and lrs[-1] == pytest.approx(0.5 * (1 + math.cos(math.pi * 5 / 6)))
    assert all(a >= b for a, b in zip(lrs[3:], lrs[4:]))
    const = c.replace(lr_schedule="constant")
    assert [lr_at(const.loop(), s) for s in range(4, 10)] == [1.0] * 6


def test_lr_wsd_is_constant_then_linear_to_zero():
    c = train_preset("tiny", steps=10, warmup_steps=2, lr=1.0, lr_schedule="wsd", decay_steps=4)
    lrs = [lr_at(c.loop(), s) for s in range(10)]
    assert lrs == [0.5, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.75, 0.5, 0.25]  # decay over steps 6..9, 0 at step 10
    with pytest.raises(ValueError, match="decay_steps"):
        train_preset("tiny", steps=10, lr_schedule="wsd", decay_steps=0)
    with pytest.raises(ValueError, match="decay_steps"):
        train_preset("tiny", steps=10, lr_schedule="wsd", decay_steps=11)


def test_lr_wsd_on_the_clock_takes_the_lower_of_steps_and_time():
    c = train_preset("tiny", steps=100, warmup_steps=0, lr=1.0, lr_schedule="wsd", decay_steps=20).loop()
    assert lr_at(c, 10, 0.0) == lr_at(c, 10) == 1.0  # stable on both clocks
    assert lr_at(c, 10, 0.8) == pytest.approx(1.0) and lr_at(c, 10, 0.7) == 1.0  # the last fifth of the budget starts the decay
    assert lr_at(c, 10, 0.9) == pytest.approx(0.5)  # slower machine than planned: the clock decides
    assert lr_at(c, 10, 1.0) == 0.0 and lr_at(c, 10, 1.5) == 0.0
    assert lr_at(c, 90, 0.1) == pytest.approx(0.5)  # faster machine: the step count decides
    const = dataclasses.replace(c, lr_schedule="constant")
    assert lr_at(const, 10, 0.99) == 1.0  # only wsd runs on the clock
    warm = dataclasses.replace(c, warmup_steps=10)
    assert lr_at(warm, 4, 0.0) == 0.5 and lr_at(warm, 4, 0.95) == pytest.approx(0.25)  # a budget spent in warm-up


def test_ema_decay_warmup():
    assert ema_decay_at(0.999, 0) == pytest.approx(0.1)
    assert ema_decay_at(0.999, 10) == pytest.approx(11 / 20)
    assert ema_decay_at(0.999, 10**6) == 0.999


def test_presets_and_config_roundtrip():
    paper = TRAIN_PRESETS["paper"]
    assert (paper.denoiser.width, paper.denoiser.depth, paper.lr, paper.batch_size, paper.num_points) == (
        512, 8, 2e-4, 16, 10_000)  # fmt: skip
    for name, cfg in TRAIN_PRESETS.items():
        assert cfg.preset == name
        assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    c = train_preset("tiny", prediction_type="v_prediction")  # the diffusion's, not the network's
    assert c.prediction_type == "v_prediction" and "prediction_type" not in c.denoiser.to_dict()
    # a checkpoint stored when the network config still carried it reads the same
    old = c.to_dict()
    old["denoiser"]["prediction_type"] = "v_prediction"
    assert TrainConfig.from_dict(old) == c


@pytest.mark.parametrize(
    "changes, match",
    [({"num_points": 0}, "num_points"), ({"schedule": "quadratic"}, "schedule"), ({"lr": -1.0}, "lr"),
     ({"prediction_type": "x0"}, "prediction_type"), ({"min_snr_gamma": 0.0}, "min_snr")],
)  # fmt: skip
def test_config_validation(changes, match):
    with pytest.raises(ValueError, match=match):
        train_preset("tiny", **changes)
    with pytest.raises(ValueError, match="unknown training preset 'huge'"):
        train_preset("huge")


# ---------------------------------------------------------------------------------- data order
def test_step_batches_order(tiny_dataset):
    ds = PointCloudDataset(tiny_dataset, "train", num_points=None, random_subsample=False)
    L = len(ds)
    B, world = 2, 2
    steps_per_epoch = math.ceil(L / (B * world)) + 1
    ranks = [StepBatches(ds, B, 64, seed=3, steps=100, rank=r, world_size=world) for r in range(world)]
    seen = np.concatenate([np.concatenate([rk.frame_indices(s)[1] for rk in ranks]) for s in range(steps_per_epoch)])
    # every frame exactly once per epoch, across ranks
    assert sorted(seen[:L].tolist()) == list(range(L))
    # a batch is a pure function of (seed, step, rank)
    again = StepBatches(ds, B, 64, seed=3, steps=100, rank=1, world_size=world)
    b1, b2 = ranks[1][5], again[5]
    assert torch.equal(b1["points"], b2["points"]) and torch.equal(b1["index"], b2["index"])
    assert b1["points"].shape == (B, 64, 3) and b1["joints"].shape == (B, 24, 3) and b1["root"].shape == (B, 3)
    # the chosen points are frame points (normalised), no duplicates
    frame = ds[int(b1["index"][0])]["points"]
    assert (b1["points"][0][:, None, :] == frame[None]).all(dim=-1).any(dim=1).all()
    assert len(torch.unique(b1["points"][0], dim=0)) == 64
    other_seed = StepBatches(ds, B, 64, seed=4, steps=100, rank=1, world_size=world)[5]
    assert not torch.equal(other_seed["points"], b1["points"])


# ------------------------------------------------------------------------------ the whole loop
def test_train_writes_run_and_loads(tiny_dataset, tmp_path):
    cfg = tiny(steps=3, ckpt_every=2, sample_every=3, sample_steps=2)
    res = train(cfg, tiny_dataset, tmp_path / "run", progress=False)
    run = tmp_path / "run"
    assert res.step == 3 and math.isfinite(res.final_loss)
    for f in ("config.json", "metrics.jsonl", "loss.png", "samples/step_000003.png"):
        assert (run / f).is_file(), f
    recs = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in recs] == [1, 2, 3] and all(math.isfinite(r["loss"]) for r in recs)
    assert {d.name for d in (run / "checkpoints").iterdir()} == {"latest", "step_000002", "step_000003"}
    assert (run / "checkpoints" / "latest").read_text().strip() == "step_000003"
    files = {p.name for p in (run / "checkpoints" / "step_000003").iterdir()}
    assert files == {"meta.json", "model.safetensors", "ema.safetensors", "training_state.pt"}

    ck = ckpt_io.load_checkpoint(run)  # a run folder resolves to its newest checkpoint
    assert ck.step == 3 and ck.preset == "tiny" and ck.model_kind == "pocoloco"
    assert ck.normalisation == PointCloudDataset(tiny_dataset, "train", num_points=None).normalisation
    assert _states_equal(ck.model_state, res.model.state_dict()) == 0.0
    assert _states_equal(ck.ema_state, res.ema.state_dict()) == 0.0
    assert _states_equal(ck.ema_state, ck.model_state) > 0.0  # the EMA lags the raw weights

    model, norm, config = load_denoiser(run / "checkpoints" / "step_000003")
    assert config == cfg and norm == ck.normalisation and not model.training
    assert _states_equal(model.state_dict(), res.ema.state_dict()) == 0.0
    raw, _, _ = load_denoiser(run, use_ema=False)
    assert _states_equal(raw.state_dict(), res.model.state_dict()) == 0.0


def test_resume_is_exact(tiny_dataset, tmp_path):
    cfg = tiny(steps=4, warmup_steps=3, ema_decay=0.9)
    straight = train(cfg, tiny_dataset, tmp_path / "a", progress=False)

    train(cfg.replace(steps=2), tiny_dataset, tmp_path / "b", progress=False)
    torch.manual_seed(12345)  # disturb global RNGs: the resumed run must not depend on them
    np.random.seed(7)
    resumed = train(cfg, tiny_dataset, tmp_path / "b", resume=True, progress=False)

    assert resumed.step == 4
    assert _states_equal(straight.model.state_dict(), resumed.model.state_dict()) == 0.0
    assert _states_equal(straight.ema.state_dict(), resumed.ema.state_dict()) == 0.0
    a = ckpt_io.load_checkpoint(tmp_path / "a")
    b = ckpt_io.load_checkpoint(tmp_path / "b")
    exp_avg = lambda ck: [s["exp_avg_sq"] for s in ck.optimizer_state["state"].values()]  # noqa: E731
    assert all(torch.equal(x, y) for x, y in zip(exp_avg(a), exp_avg(b), strict=True))
    # the log of the resumed run is continuous, without duplicate steps
    steps = [json.loads(line)["step"] for line in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4]
    # sanity: the comparison can fail (another seed gives other weights)
    other = train(cfg.replace(seed=1), tiny_dataset, tmp_path / "c", progress=False)
    assert _states_equal(straight.model.state_dict(), other.model.state_dict()) > 1e-4


def test_resume_after_a_kill_cleans_temporaries_and_skips_a_damaged_checkpoint(tiny_dataset, tmp_path, capsys):
    """What ``kill -9`` leaves: a half-written ``.tmp-step_*`` folder (removed on start) and, after a
    disk fault, a truncated newest checkpoint: ``--resume`` and ``sample`` fall back to the newest
    intact one with a one-line warning naming the skipped one, and the resumed run is still exact."""
    from pocoloco.cli import main as cli_main

    cfg = tiny(steps=4, ckpt_every=1, keep_checkpoints=5)
    straight = train(cfg, tiny_dataset, tmp_path / "a", progress=False)
    run = tmp_path / "b"
    train(cfg.replace(steps=3), tiny_dataset, run, progress=False)
    root = run / "checkpoints"
    stale = root / ".tmp-step_000004-deadbeef"
    stale.mkdir()
    (stale / "model.safetensors").write_bytes(b"half a file")
    weights = root / "step_000003" / "ema.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])  # the newest checkpoint, truncated

    with pytest.warns(ckpt_io.CheckpointFallbackWarning, match=r"step_000003 .*; using .*step_000002"):
        ck = ckpt_io.load_checkpoint(run, expect_model="pocoloco")
    assert ck.step == 2
    with pytest.raises(ValueError, match="truncated or damaged"):  # asked for by name: no fallback
        ckpt_io.load_checkpoint(root / "step_000003")
    code = cli_main(["sample", "--ckpt", str(run), "--joints", "demo:skirt", "--num", "1", "--steps", "2",
                     "--points", "32", "--no-render", "--out", str(tmp_path / "s")])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 0 and err.startswith("pocoloco: warning: skipped damaged checkpoint step_000003")
    assert len(err.splitlines()) == 1 and json.loads((tmp_path / "s" / "sample.json").read_text())["step"] == 2

    with pytest.warns(ckpt_io.CheckpointFallbackWarning):
        resumed = train(cfg, tiny_dataset, run, resume=True, progress=False)
    assert not stale.exists()
    assert resumed.step == 4 and _states_equal(straight.model.state_dict(), resumed.model.state_dict()) == 0.0
    assert _states_equal(straight.ema.state_dict(), resumed.ema.state_dict()) == 0.0


def test_resume_with_other_config_or_without_flag_raises(tiny_dataset, tmp_path):
    cfg = tiny(steps=2)
    train(cfg, tiny_dataset, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match=r"cannot resume with a different config \(lr: checkpoint 0.001"):
        train(cfg.replace(lr=1e-4, steps=4), tiny_dataset, tmp_path / "run", resume=True, progress=False)
    with pytest.raises(ValueError, match="expected 'small'"):
        train(train_preset("small", steps=4), tiny_dataset, tmp_path / "run", resume=True, progress=False)
    with pytest.raises(ValueError, match="already holds checkpoints"):
        train(cfg, tiny_dataset, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="no checkpoint"):
        train(cfg, tiny_dataset, tmp_path / "empty", resume=True, progress=False)
    # more steps is an allowed change
    assert train(cfg.replace(steps=3), tiny_dataset, tmp_path / "run", resume=True, progress=False).step == 3
    # so is a new learning-rate curve that keeps the rates of the steps taken: a constant run cooled down
    with pytest.raises(ValueError, match=r"cannot resume with steps, lr_schedule, decay_steps changed: the learning rate of step 2"):
        train(cfg.replace(steps=6, lr_schedule="wsd", decay_steps=5), tiny_dataset, tmp_path / "run", resume=True,
              progress=False)  # fmt: skip
    cooled = train(cfg.replace(steps=6, lr_schedule="wsd", decay_steps=3), tiny_dataset, tmp_path / "run", resume=True,
                   progress=False)  # fmt: skip
    assert cooled.step == 6
    lrs = [json.loads(line)["lr"] for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines() if '"lr"' in line]
    assert lrs[-3:] == pytest.approx([cfg.lr, cfg.lr * 2 / 3, cfg.lr / 3])
    # a cosine run cannot be stretched: its past rates would change
    cos = tiny(steps=3, lr_schedule="cosine", warmup_steps=0)
    train(cos, tiny_dataset, tmp_path / "cos", progress=False)
    with pytest.raises(ValueError, match="cannot resume with steps changed"):
        train(cos.replace(steps=6), tiny_dataset, tmp_path / "cos", resume=True, progress=False)


@pytest.mark.parametrize(
    "changes",
    [dict(bf16=True), dict(prediction_type="v_prediction", min_snr_gamma=5.0, schedule="cosine"),
     dict(prediction_type="sample", schedule="linear", grad_clip=None, lr_schedule="cosine")],
)  # fmt: skip
def test_training_options_run(tiny_dataset, tmp_path, changes):
    res = train(tiny(steps=2, **changes), tiny_dataset, tmp_path / "run", progress=False)
    assert res.step == 2 and math.isfinite(res.final_loss)
    _, _, config = load_denoiser(tmp_path / "run")
    for k, v in changes.items():
        assert getattr(config, k) == v


def test_loss_decreases_on_tiny_data(tiny_dataset, tmp_path):
    """60 steps on the tiny dataset lower the epsilon loss from ~1 (the zero-initialised output)."""
    res = train(tiny(steps=60, batch_size=4, num_points=128, log_every=1, warmup_steps=5), tiny_dataset,
                tmp_path / "run", progress=False)  # fmt: skip
    losses = [json.loads(line)["loss"] for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert res.step == 60
    assert np.mean(losses[:5]) > 0.9 and np.mean(losses[-10:]) < 0.8 * np.mean(losses[:5])


# ---------------------------------------------------------------------------- checkpoint errors
def test_checkpoint_errors_name_file(tiny_dataset, tmp_path):
    train(tiny(steps=1), tiny_dataset, tmp_path / "run", progress=False)
    ck = tmp_path / "run" / "checkpoints" / "step_000001"
    with pytest.raises(ValueError, match="model 'pocoloco', expected 'pop'"):
        ckpt_io.load_checkpoint(ck, expect_model="pop")
    with pytest.raises(ValueError, match="preset 'tiny', expected 'paper'"):
        ckpt_io.load_checkpoint(ck, expect_preset="paper")
    with pytest.raises(ValueError, match="no such checkpoint"):
        ckpt_io.load_checkpoint(tmp_path / "nowhere")

    data = (ck / "ema.safetensors").read_bytes()
    (ck / "ema.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"ema\.safetensors: \d+ bytes, meta.json records \d+ \(truncated") as e:
        load_denoiser(ck)
    assert "\n" not in str(e.value)
    (ck / "ema.safetensors").write_bytes(data)
    assert load_denoiser(ck).config.preset == "tiny"
    (ck / "training_state.pt").write_bytes(b"garbage")
    with pytest.raises(ValueError, match=r"training_state\.pt: 7 bytes, meta.json records"):
        ckpt_io.load_checkpoint(ck, expect_model=None)
    (ck / "meta.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"meta\.json: corrupt checkpoint metadata"):
        ckpt_io.load_checkpoint(ck)


def test_rng_state_roundtrip():
    import random

    state = ckpt_io.capture_rng_state()
    a = (random.random(), np.random.rand(), torch.rand(2))
    torch.manual_seed(0)
    np.random.seed(0)
    random.seed(0)
    ckpt_io.restore_rng_state(state)
    b = (random.random(), np.random.rand(), torch.rand(2))
    assert a[0] == b[0] and a[1] == b[1] and torch.equal(a[2], b[2])


# ------------------------------------------------------------------------------- command line
def _parse(*argv):
    import argparse

    p = argparse.ArgumentParser()
    add_train_arguments(p)
    return p.parse_args(list(argv))


@pytest.mark.parametrize(
    "argv, message",
    [(["--num-points", "0"], "num_points must be >= 1"), (["--preset", "huge"], "unknown training preset 'huge'")],
)  # fmt: skip
def test_cli_bad_input_one_line(tiny_dataset, tmp_path, capsys, argv, message):
    code = cli_main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "run"), "--no-progress", *argv])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and len(err.splitlines()) == 1


def test_cli_not_a_dataset(tmp_path, capsys):
    code = cli_main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--preset", "tiny", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "not a pocoloco dataset" in err and len(err.splitlines()) == 1


def test_cli_trains_and_resumes_with_checkpoint_config(tiny_dataset, tmp_path):
    out = str(tmp_path / "run")
    base = ["--data", str(tiny_dataset), "--out", out, "--no-progress", "--device", "cpu", "--threads", "1"]
    assert cli_main(["train", *base, "--preset", "tiny", "--steps", "2", "--sample-every", "0", "--min-snr", "5"]) == 0
    args = _parse(*base, "--resume", "--steps", "3")
    assert args.preset is None
    assert cli_main(["train", *base, "--resume", "--steps", "3"]) == 0  # preset and options come from the checkpoint
    ck = ckpt_io.load_checkpoint(out)
    assert ck.step == 3 and ck.config["min_snr_gamma"] == 5.0 and ck.config["sample_every"] == 0


def test_cli_init_from_fine_tunes_from_a_checkpoints_weights(tiny_dataset, tmp_path, capsys, monkeypatch):
    """--init-from: a fresh run (step 0, new optimiser) that starts from another run's EMA weights with
    that run's config; the source is recorded; another network or model kind is one line, nothing kept."""
    src, out = str(tmp_path / "src"), str(tmp_path / "ft")
    base = ["--data", str(tiny_dataset), "--no-progress", "--device", "cpu", "--threads", "1"]
    assert cli_main(["train", *base, "--out", src, "--preset", "tiny", "--steps", "3", "--sample-every", "0",
                     "--min-snr", "5"]) == 0  # fmt: skip
    source = ckpt_io.load_checkpoint(src)
    from pocoloco.engine import trainer as trainer_mod

    real, seen = trainer_mod.load_initial_weights, {}

    def capture(model, path, task):
        r = real(model, path, task)
        seen["state"] = {k: v.clone() for k, v in model.state_dict().items()}
        return r

    monkeypatch.setattr(trainer_mod, "load_initial_weights", capture)
    assert cli_main(["train", *base, "--out", out, "--init-from", src, "--steps", "2", "--no-bf16"]) == 0
    for k, v in source.ema_state.items():  # started from the source's EMA weights
        torch.testing.assert_close(seen["state"][k], v.to(seen["state"][k].dtype), msg=k)
    ck = ckpt_io.load_checkpoint(out)
    assert ck.step == 2 and ck.config["min_snr_gamma"] == 5.0  # the source's config, a fresh step count
    assert ck.meta["init_from"] == str(source.path) and json.loads((Path(out) / "config.json").read_text())["init_from"]
    capsys.readouterr()
    bad = str(tmp_path / "bad")
    code = cli_main(["train", *base, "--out", bad, "--init-from", src, "--preset", "tiny", "--steps", "1"]
                    + ["--outfit-codes"])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "--init-from" in err and "differs" in err, err
    assert not Path(bad).exists() or not any(p.name != ".lock" for p in Path(bad).rglob("*") if p.is_file())


def test_init_from_leaves_the_source_machines_settings_behind(tiny_dataset, tmp_path, monkeypatch):
    """--init-from takes the source's recipe but not its machine's settings: bf16 autocast follows
    this device (emulated bf16 made a CPU fine-tune of the GPU-trained default ~10x slower) and the
    loader runs in the main process, unless the options say otherwise."""
    import pocoloco.cli.common as cli_common

    monkeypatch.setattr(cli_common, "bf16_is_fast", lambda device: False)  # a CPU without native bf16
    src = str(tmp_path / "src")
    base = ["--data", str(tiny_dataset), "--no-progress", "--device", "cpu", "--threads", "1", "--sample-every", "0"]
    assert cli_main(["train", *base, "--out", src, "--preset", "tiny", "--steps", "1", "--bf16", "--workers", "1"]) == 0
    assert ckpt_io.load_checkpoint(src).config["bf16"] is True
    for extra, bf16, workers in (([], False, 0), (["--bf16", "--workers", "1"], True, 1)):
        out = str(tmp_path / f"ft{len(extra)}")
        assert cli_main(["train", *base, "--out", out, "--init-from", src, "--steps", "1", *extra]) == 0
        config = ckpt_io.load_checkpoint(out).config
        assert (config["bf16"], config["num_workers"]) == (bf16, workers), (extra, config["bf16"], config["num_workers"])


def test_init_from_on_a_bf16_machine_keeps_pop_in_float32(tiny_dataset, tmp_path, monkeypatch):
    """On a machine with native bf16 a fine-tune takes bf16 autocast by default, except a model that
    trains in float32 only: POP fine-tuned with --init-from trains (it was a 'bf16 is not available
    for POP' error on such a machine, CPU or GPU), and --bf16 asked for it explicitly is still one."""
    import pocoloco.cli.common as cli_common

    monkeypatch.setattr(cli_common, "bf16_is_fast", lambda device: True)  # avx512_bf16 / AMX / a bf16 GPU
    base = ["--model", "pop", "--data", str(tiny_dataset), "--no-progress", "--device", "cpu", "--threads", "1",
            "--sample-every", "0"]  # fmt: skip
    src, out = str(tmp_path / "src"), str(tmp_path / "ft")
    assert cli_main(["train", *base, "--out", src, "--preset", "tiny", "--steps", "1"]) == 0
    assert cli_main(["train", *base, "--out", out, "--init-from", src, "--steps", "1"]) == 0
    assert ckpt_io.load_checkpoint(out, expect_model="pop").config["bf16"] is False
    assert cli_main(["train", *base, "--out", str(tmp_path / "ft2"), "--init-from", src, "--steps", "1", "--bf16"]) == 2


def test_init_from_matches_outfit_codes_by_name(tiny_dataset, tmp_path):
    """Fine-tuning on a subset of outfits starts each outfit from the source's code of the same name."""
    src, out = tmp_path / "src", tmp_path / "ft"
    train(tiny(steps=2, outfit_codes=True), tiny_dataset, src, progress=False)
    res = train(tiny(steps=1, lr=1e-12, outfit_codes=True, subjects=["tight"]), tiny_dataset, out, progress=False,
                init_from=src)  # fmt: skip
    source = ckpt_io.load_checkpoint(src)
    names = [o["name"] for o in source.meta["outfits"]]
    (key,) = [k for k in source.ema_state if k.endswith("outfit_embed.weight")]
    start = source.ema_state[key][names.index("tight")]
    torch.testing.assert_close(res.model.state_dict()[key][0], start.to(torch.float32), atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------- DDP (gloo)
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, world: int, port: int, data: str, out: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        res = train(tiny(steps=3, ckpt_every=2), data, out, progress=False)
        torch.save({"model": res.model.state_dict(), "ema": res.ema.state_dict()}, f"{out}.rank{rank}.pt")
    finally:
        dist.destroy_process_group()


def test_ddp_two_cpu_processes_keep_replicas_identical(tiny_dataset, tmp_path):
    out = tmp_path / "run"
    torch.multiprocessing.spawn(_ddp_worker, args=(2, _free_port(), str(tiny_dataset), str(out)), nprocs=2)
    r0, r1 = (torch.load(f"{out}.rank{r}.pt", weights_only=True) for r in range(2))
    assert _states_equal(r0["model"], r1["model"]) == 0.0
    assert _states_equal(r0["ema"], r1["ema"]) == 0.0
    ck = ckpt_io.load_checkpoint(out)  # written once, by rank 0
    assert ck.step == 3 and ck.meta["world_size"] == 2
    assert _states_equal(ck.model_state, r0["model"]) == 0.0
    # the replicas trained: not the initial weights, and not what one process alone would give
    single = train(tiny(steps=3), tiny_dataset, tmp_path / "single", progress=False)
    assert _states_equal(single.model.state_dict(), r0["model"]) > 1e-6


def test_torchrun_entry_point(tiny_dataset, tmp_path):
    """``torchrun --nproc_per_node=2 -m pocoloco train`` runs end to end on CPU (gloo)."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--master_port", str(_free_port()),
           "-m", "pocoloco", "train", "--data", str(tiny_dataset), "--out", str(out), "--preset", "tiny",
           "--steps", "2", "--sample-every", "0", "--no-progress", "--device", "cpu"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    ck = ckpt_io.load_checkpoint(out)
    assert ck.step == 2 and ck.meta["world_size"] == 2


def test_latent_architecture_trains_resumes_and_samples_through_the_same_pieces(tiny_dataset, tmp_path):
    """``architecture="latent"`` (the linear-in-N network): the same loop trains it, resume is exact,
    the checkpoint records the architecture, and any N samples."""
    from pocoloco.methods import load_method
    from pocoloco.models.latent import LatentDenoiser

    cfg = train_preset("latent_tiny", steps=3, ckpt_every=0, sample_every=0, log_every=1)
    straight = train(cfg, tiny_dataset, tmp_path / "a", progress=False)
    train(cfg.replace(steps=2), tiny_dataset, tmp_path / "b", progress=False)
    resumed = train(cfg, tiny_dataset, tmp_path / "b", resume=True, progress=False)
    assert _states_equal(straight.model.state_dict(), resumed.model.state_dict()) == 0.0
    ck = ckpt_io.load_checkpoint(tmp_path / "a")
    assert ck.config["architecture"] == "latent" and TrainConfig.from_dict(ck.config) == cfg
    method = load_method(tmp_path / "a")
    assert isinstance(method.model, LatentDenoiser)
    pose = method.load_pose("demo:skirt")
    for n in (1, 37, 700):
        assert method.predict(pose, n, seeds=[0]).points.shape == (1, n, 3)
    with pytest.raises(ValueError, match="architecture"):
        cfg.replace(architecture="transformer")


@pytest.mark.parametrize("preset", ["tiny", "latent_tiny"])
def test_who_wears_what_conditioning_end_to_end(tiny_dataset, tmp_path, capsys, preset):
    """--outfit-codes --body-shape: one code per subject and its phenotype enter the denoiser; the
    checkpoint lists the outfits; sample needs an outfit (default: a DATASET: frame's subject),
    different outfits give different clouds from the same noise, and a joints-only model refuses one."""
    from pocoloco.cli import main as cli_main
    from pocoloco.data import format as fmt
    from pocoloco.methods import load_method

    out = tmp_path / "run"
    argv = ["train", "--data", str(tiny_dataset), "--out", str(out), "--preset", preset, "--steps", "2",
            "--sample-every", "2", "--outfit-codes", "--body-shape", "--no-progress", "--threads", "1"]  # fmt: skip
    assert cli_main(argv) == 0, capsys.readouterr().err
    method = load_method(out)
    subjects = fmt.DatasetLayout(tiny_dataset).subjects()
    assert method.outfit_names() == subjects and method.model.config.num_outfits == len(subjects)
    assert method.model.config.shape_dim == 6 and (out / "samples" / "step_000002.png").is_file()
    # a shipped demo pose wears the outfit of its name if the model has one (tiny has a skirt), else
    # the outfit must be named
    assert "skirt" in subjects and "shirt" not in subjects
    assert cli_main(["sample", "--ckpt", str(out), "--joints", "demo:skirt", "--num", "1", "--steps", "2", "--points",
                     "32", "--no-render", "--out", str(tmp_path / "d")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "d" / "sample.json").read_text())["outfit"] == "skirt"
    code = cli_main(["sample", "--ckpt", str(out), "--joints", "demo:shirt", "--out", str(tmp_path / "x")])
    assert code == 2 and "--outfit is required" in capsys.readouterr().err
    spec = f"{tiny_dataset}:{fmt.DatasetLayout(tiny_dataset).iter_frames('test')[0][0]}/test/" + \
        f"{fmt.DatasetLayout(tiny_dataset).iter_frames('test')[0][1]}/0"  # fmt: skip
    clouds = {}
    for outfit in subjects:
        pose = method.load_pose(spec)
        clouds[outfit] = method.predict(pose, 64, seeds=[0], outfit=method.outfit_id(outfit)).points
    assert not np.allclose(clouds[subjects[0]], clouds[subjects[1]])
    assert cli_main(["sample", "--ckpt", str(out), "--joints", spec, "--num", "1", "--steps", "2", "--points", "32",
                     "--no-render", "--out", str(tmp_path / "s")]) == 0  # fmt: skip
    assert json.loads((tmp_path / "s" / "sample.json").read_text())["outfit"] == spec.split(":")[-1].split("/")[0]
    # the apps take --outfit too (default: the motion's / pose's subject)
    motion = spec.rsplit("/", 1)[0]
    assert cli_main(["animate", "--ckpt", str(out), "--motion", motion, "--frames", "0:2", "--points", "16", "--steps",
                     "2", "--t", "50", "--no-render", "--out", str(tmp_path / "a")]) == 0  # fmt: skip
    assert cli_main(["animate", "--ckpt", str(out), "--motion", motion, "--frames", "0:2", "--points", "16", "--steps",
                     "2", "--t", "50", "--no-render", "--outfit", subjects[-1], "--out", str(tmp_path / "b")]) == 0  # fmt: skip
    code = cli_main(["animate", "--ckpt", str(out), "--motion", motion, "--outfit", "nobody", "--out", str(tmp_path / "c")])
    assert code == 2 and "was never trained" in capsys.readouterr().err
    # a joints-only model: no outfits, and --outfit is a one-line error
    plain = train(tiny(steps=1), tiny_dataset, tmp_path / "plain", progress=False)
    assert plain.step == 1
    code = cli_main(["sample", "--ckpt", str(tmp_path / "plain"), "--joints", "demo:skirt", "--outfit", "skirt",
                     "--out", str(tmp_path / "y")])  # fmt: skip
    assert code == 2 and "has none" in capsys.readouterr().err


def test_pocoloco_fits_an_unseen_outfit_code(tiny_dataset, tmp_path, capsys):
    """`pocoloco fit` on a PocoLoco trained with --outfit-codes on one subject: only a new outfit code
    is optimised (the network is unchanged), from scans of the other subject (two scans, two poses);
    the fitted checkpoint samples the new outfit; a joints-only PocoLoco cannot fit."""
    from pocoloco.cli import main as cli_main
    from pocoloco.data import format as fmt
    from pocoloco.data.published import write_ply
    from pocoloco.methods import load_method

    run = tmp_path / "run"
    assert cli_main(["train", "--data", str(tiny_dataset), "--out", str(run), "--preset", "latent_tiny", "--steps",
                     "2", "--sample-every", "0", "--outfit-codes", "--body-shape", "--subjects", "tight",
                     "--no-progress", "--threads", "1"]) == 0  # fmt: skip
    layout = fmt.DatasetLayout(tiny_dataset)
    frames = [f for f in layout.iter_frames("test") if f[0] == "skirt"][:2]
    argv = ["fit", "--ckpt", str(run), "--steps", "12", "--name", "skirt_new", "--points", "128", "--out",
            str(tmp_path / "fitted"), "--scan"]  # fmt: skip
    specs = []
    for k, (subject, seq, path) in enumerate(frames):
        fr = fmt.read_frame(path, ["points", "frame_index"])
        write_ply(tmp_path / f"scan{k}.ply", fr.points[::4])
        argv.append(str(tmp_path / f"scan{k}.ply"))
        specs.append(f"{tiny_dataset}:{subject}/test/{seq}/{int(fr.frame_index)}")
    assert cli_main([*argv, "--frame", *specs]) == 0, capsys.readouterr().err
    rep = json.loads((tmp_path / "fitted" / "fit.json").read_text())
    assert rep["model_kind"] == "pocoloco" and len(rep["scans"]) == 2 and rep["outfit_id"] == 1
    assert np.isfinite(rep["after"]["chamfer_cm"]) and np.isfinite(rep["before_start"]["chamfer_cm"])
    old, new = load_method(run), load_method(tmp_path / "fitted")
    assert new.outfit_names() == ["tight", "skirt_new"] and new.model.config.num_outfits == 2
    # the body shape is the scans' body (skirt's phenotype from the dataset card), not a trained subject's
    assert new.outfits[1]["phenotype"] == fmt.read_card(tiny_dataset)["subjects"]["skirt"]["phenotype"]
    assert new.outfits[1]["phenotype"] != new.outfits[0]["phenotype"]
    for k, v in old.model.state_dict().items():  # only the outfit table grew
        w = new.model.state_dict()[k]
        assert torch.equal(w[: v.shape[0]] if "outfit_embed" in k else w, v), k
    start = old.model.who.outfit_embed.weight[0]  # the nearest (only) trained outfit: where the fit starts
    assert rep["start"] == "nearest" and not torch.equal(new.model.who.outfit_embed.weight[1], start)
    # --anchor pulls the code to its start: a strong pull keeps it closer than the plain diffusion loss
    assert cli_main([*argv[:argv.index("--out")], "--anchor", "1e4", "--out", str(tmp_path / "anchored"), "--scan",
                     *argv[argv.index("--scan") + 1:], "--frame", *specs]) == 0, capsys.readouterr().err  # fmt: skip
    anchored = load_method(tmp_path / "anchored").model.who.outfit_embed.weight[1]
    free = new.model.who.outfit_embed.weight[1]
    assert (anchored - start).abs().max() < 0.5 * (free - start).abs().max()
    assert cli_main(["sample", "--ckpt", str(tmp_path / "fitted"), "--outfit", "skirt_new", "--joints", specs[0],
                     "--num", "1", "--steps", "2", "--points", "32", "--no-render", "--out", str(tmp_path / "s")]) == 0  # fmt: skip
    # eval scores the unseen subject in a named outfit (before: the trained one; after: the fitted one)
    base = ["eval", "--data", str(tiny_dataset), "--subjects", "skirt", "--frames", "1", "--points", "64", "--seeds",
            "0", "--steps", "2", "--no-baselines", "--threads", "1"]  # fmt: skip
    assert cli_main([*base, "--ckpt", str(run), "--out", str(tmp_path / "e0")]) == 2
    assert "never trained" in capsys.readouterr().err
    assert cli_main([*base, "--ckpt", str(run), "--outfit", "tight", "--out", str(tmp_path / "e1")]) == 0
    assert cli_main([*base, "--ckpt", str(tmp_path / "fitted"), "--outfit", "skirt_new", "--out", str(tmp_path / "e2")]) == 0
    before, after = (json.loads((tmp_path / e / "eval.json").read_text()) for e in ("e1", "e2"))
    assert before["settings"]["outfit"] == "tight" and after["settings"]["outfit"] == "skirt_new"
    assert before["means"]["model"]["chamfer_cm"] != after["means"]["model"]["chamfer_cm"]
    assert cli_main([*base, "--ckpt", str(run), "--outfit", "nobody", "--out", str(tmp_path / "e3")]) == 2
    assert "never trained" in capsys.readouterr().err
    plain = tmp_path / "plain"
    train(tiny(steps=1), tiny_dataset, plain, progress=False)
    assert cli_main(["fit", "--ckpt", str(plain), "--scan", str(tmp_path / "scan0.ply"), "--frame", specs[0],
                     "--out", str(tmp_path / "f2")]) == 2  # fmt: skip
    assert "cannot fit a new outfit" in capsys.readouterr().err


def test_canonical_heading_trains_records_and_samples_turn_with_the_body(tiny_dataset, tmp_path, capsys):
    """--canonical-heading: the checkpoint records it, and a body turned about the vertical axis gives
    the same cloud turned (same seed): the model never sees the facing direction. Region editing
    keeps the source's static points turned with the root."""
    from pocoloco.apps.editing import edit
    from pocoloco.data.dataset import rotate_z
    from pocoloco.methods.pocoloco.sampling import sample_clouds

    out = tmp_path / "run"
    assert cli_main(["train", "--data", str(tiny_dataset), "--out", str(out), "--preset", "latent_tiny", "--steps", "2",
                     "--sample-every", "2", "--canonical-heading", "--no-progress", "--threads", "1"]) == 0  # fmt: skip
    model, norm, config = load_denoiser(out)
    assert norm.heading and json.loads((out / "config.json").read_text())["canonical_heading"] is True
    assert (out / "samples" / "step_000002.png").is_file()
    ds = PointCloudDataset(tiny_dataset, "test", num_points=None)
    joints = ds[0]["joints"].numpy() * ds.normalisation.std + np.array(ds.normalisation.mean) + ds[0]["root"].numpy()
    root = joints[0]
    turn = 1.1
    turned = rotate_z(joints - root, turn) + root + np.array([0.3, 0.0, 0.0], np.float32)
    a = sample_clouds(model, norm, config, joints, num=1, num_points=64, steps=3, seeds=[5]).points[0]
    b = sample_clouds(model, norm, config, turned.astype(np.float32), num=1, num_points=64, steps=3, seeds=[5]).points[0]
    np.testing.assert_allclose(b, rotate_z(a - root, turn) + root + [0.3, 0.0, 0.0], atol=2e-4)
    # region editing: static points are the source turned with the root (exactly what the model's frame does)
    # (a small turn: no joint moves by more than the 5 cm threshold, so points are kept)
    small = (rotate_z(joints - root, 0.02) + root + np.array([0.3, 0.0, 0.0])).astype(np.float32)
    from pocoloco.data import format as fmt

    src = fmt.read_frame(ds.frames[0][2]).points[:200]
    from pocoloco.methods import load_method

    res = edit(load_method(out).point_prior(None), src, small, source_joints=joints, mode="region", steps=2)
    kept = ~res.regenerated[0]
    assert kept.any()
    np.testing.assert_allclose(res.points[0][kept], (rotate_z(src - root, 0.02) + root + [0.3, 0, 0])[kept], atol=1e-5)


def test_joint_velocity_from_neighbouring_frames_trains_and_samples(tiny_dataset, tmp_path, capsys):
    """--joint-velocity: velocities are the backward difference to the previous stored frame (the next
    one at a sequence's start) in m/s, normalised like the points; the model samples from a DATASET:
    frame with them (different from the body at rest once the velocity MLP is non-zero) and refuses
    velocities of the wrong shape; a model without them refuses velocities."""
    from pocoloco.data import format as fmt
    from pocoloco.data.dataset import frame_velocity
    from pocoloco.methods import load_method
    from pocoloco.methods.pocoloco.sampling import sample_clouds

    subject, seq, path = fmt.DatasetLayout(tiny_dataset).iter_frames("test")[1]
    frames = sorted(p for s, q, p in fmt.DatasetLayout(tiny_dataset).iter_frames("test") if (s, q) == (subject, seq))
    j = [fmt.read_frame(p, ["joints"]).joints.astype(np.float64) for p in frames[:3]]
    fps = json.loads((Path(frames[0]).parent.parent / "sequence.json").read_text())["fps"]
    np.testing.assert_allclose(frame_velocity(frames[1], j[1]), (j[1] - j[0]) * fps, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(frame_velocity(frames[0], j[0]), (j[1] - j[0]) * fps, rtol=1e-5, atol=1e-5)
    ds = PointCloudDataset(tiny_dataset, "test", num_points=None, velocity=True)
    k = ds.frames.index((subject, seq, frames[1]))
    np.testing.assert_allclose(ds[k]["velocity"].numpy(), (j[1] - j[0]) * fps / ds.normalisation.std, rtol=1e-4, atol=1e-4)

    out = tmp_path / "run"
    assert cli_main(["train", "--data", str(tiny_dataset), "--out", str(out), "--preset", "latent_tiny", "--steps", "2",
                     "--sample-every", "2", "--joint-velocity", "--outfit-codes", "--no-progress", "--threads", "1"]) == 0  # fmt: skip
    method = load_method(out)
    assert method.model.config.joint_velocity and method.model.velocity_in is not None
    spec = f"{tiny_dataset}:{subject}/test/{seq}/{int(fmt.read_frame(frames[1], ['frame_index']).frame_index)}"
    pose = method.load_pose(spec)
    assert pose.velocity is not None and np.abs(pose.velocity).max() > 0
    with torch.no_grad():  # make the (zero-initialised) velocity MLP matter
        method.model.velocity_in[2].weight.normal_(0, 0.5)
    moving = method.predict(pose, 32, seeds=[0]).points
    pose.velocity = None
    at_rest = method.predict(pose, 32, seeds=[0]).points
    assert not np.allclose(moving, at_rest)
    with pytest.raises(ValueError, match="velocity must be"):
        sample_clouds(method.model, method.normalisation, method.config, pose.joints, 1, 16, steps=2,
                      velocity=np.zeros((3, 3)), **method.condition(0))  # fmt: skip
    assert cli_main(["sample", "--ckpt", str(out), "--joints", spec, "--num", "1", "--steps", "2", "--points", "32",
                     "--no-render", "--out", str(tmp_path / "s")]) == 0  # fmt: skip
    from pocoloco.models.conditioning import PoseCondition
    from pocoloco.models.latent import LatentDenoiser

    plain = LatentDenoiser(train_preset("latent_tiny").denoiser)
    jt = torch.zeros(1, 24, 3)
    with pytest.raises(ValueError, match="no joint velocities"):
        plain(torch.zeros(1, 8, 3), torch.zeros(1), PoseCondition(jt, velocity=torch.zeros(1, 24, 3)))


def test_the_config_base_round_trips_every_preset_and_names_unknown_fields():
    """One Config base (utils.config) for every typed config: to_dict is plain JSON, from_dict restores
    tuples and nested configs exactly, replace and from_dict refuse unknown fields in one line."""
    import json

    from pocoloco.methods.pocoloco.config import TRAIN_PRESETS
    from pocoloco.methods.skinned import SKINNED_PRESETS
    from pocoloco.models.closet import CLOSET_PRESETS
    from pocoloco.models.latent import LATENT_PRESETS
    from pocoloco.models.pop import POP_PRESETS
    from pocoloco.synth.config import SYNTH_PRESETS

    for presets in (TRAIN_PRESETS, SKINNED_PRESETS, CLOSET_PRESETS, LATENT_PRESETS, POP_PRESETS, SYNTH_PRESETS):
        for config in presets.values():
            d = config.to_dict()
            assert json.loads(json.dumps(d)) == d  # plain JSON types
            assert type(config).from_dict(d) == config
            with pytest.raises(ValueError, match=f"unknown {type(config).__name__} field\\(s\\): bogus$"):
                config.replace(bogus=1)
            with pytest.raises(ValueError, match=f"unknown {type(config).__name__} field\\(s\\): bogus$"):
                type(config).from_dict({**d, "bogus": 1})


@pytest.mark.parametrize("model", ["pocoloco", "pop"])
def test_train_opens_the_dataset_once(tiny_dataset, tmp_path, monkeypatch, model):
    """`pocoloco train` reads the card and checks the frame files once per command: the opened
    dataset (data.dataset.OpenedDataset) is handed down to the task and its datasets."""
    from pocoloco.cli import main
    from pocoloco.data import card as card_module
    from pocoloco.data import verify

    calls = {"read_card": 0, "check_frames": 0}

    def counting(module, name):
        original = getattr(module, name)

        def wrapper(*args, **kwargs):
            calls[name] += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(module, name, wrapper)

    counting(card_module, "read_card")
    counting(verify, "check_frames")
    from pocoloco.data import format as fmt

    monkeypatch.setattr(fmt, "read_card", card_module.read_card)
    monkeypatch.setattr(fmt, "check_frames", verify.check_frames)
    argv = ["train", "--model", model, "--data", str(tiny_dataset), "--out", str(tmp_path / "run"), "--preset", "tiny",
            "--steps", "1", "--sample-every", "0", "--ckpt-every", "0", "--no-progress", "--threads", "1"]  # fmt: skip
    assert main(argv) == 0
    assert calls == {"read_card": 1, "check_frames": 1}, calls
