"""Distilling a PocoLoco model into a few-step student (issue 42, ``pocoloco distill``).

1. **Teacher pairs** (:func:`make_teacher_pairs`): for P training frames (their pose, outfit and
   body shape, and motion window if the teacher takes one) and P initial noises x_T (N, C), the
   teacher's *deterministic* sampler (DPM-Solver++(2M) ODE, 20 steps by default: its answer is a
   function of x_T, which a regression can learn; the SDE's is not) is run once; the states it
   passes at the student's grid timesteps (4 calls: 999, 749, 499, 249) and its answer x0* are kept
   (float32, sharded ``pairs/shard_XXXXX.npz``, written atomically: an interrupted run resumes).
2. **The student** (:class:`DistillTask`, the shared training loop) starts from the teacher's
   weights (its x0 estimate ``(x - sigma eps) / alpha`` is the skip parametrisation
   ``c_skip x + c_out F``, with c_skip = 1/alpha, c_out = -sigma/alpha, so it starts at the
   teacher's one-step answer) and learns, at each grid state x_t of a pair, x0(x_t, t) = x0*:
   the consistency condition of Song et al. 2023 at the grid times only (consistency distillation
   with the teacher's whole path instead of one ODE step). Loss per cloud: mean pseudo-Huber
   distance of corresponding points, ``sqrt(|d|^2 + c^2) - c`` (Song & Dhariwal 2023), plus
   ``distill_chamfer`` x the Chamfer distance to x0* (PSF, Wu et al. CVPR 2023, distils its one-step
   point generator with a Chamfer loss). The noisiest time, where the student must do the most, is
   drawn for 40 % of a batch's clouds (the others evenly). Re-noised draws (``distill_renoised``)
   put the student where its own sampler puts it, the teacher's answer noised afresh to a later
   grid time; their target is that answer (``distill_renoised_targets="answer"``, scored by Chamfer
   alone: the student learns a denoiser there, whose answer is pulled toward the pose's mean) or
   the teacher's deterministic answer from that re-noised state (``"ode"``,
   :func:`make_renoised_pairs`: the consistency condition on the states the sampler visits, so
   the chain keeps its draws apart; points correspond, so the per-point term applies). Optionally (``distill_set``, pairs made
   with D > 1 draws per frame) a set-level term: a batch of whole frames; each frame's D noises
   taken down the student's own sampling chain, and its D answers scored against the teacher's D
   by the judge's proper score on the probe-distance embedding (:mod:`pocoloco.ops.probe_energy`;
   the loss adds the energy score, whose gradient is the energy distance's and which is never
   negative). Each call keeps most of a frame's spread on the teacher's path, but every fresh
   re-noising pulls the next answer toward the mean: the chain loses it call after call, which
   Chamfer rewards and the proper score does not (docs/lab/fast.md). Optionally (``distill_chain``)
   a chain term: each pair's initial noise taken down the student's own few-call sampler
   (``distill_chain_calls``, e.g. 2: 999 then 249, fresh re-noising between them, a gradient through
   the last call, or with ``distill_chain_grad`` "all" through every call) and its answer scored against the teacher's answer for that noise by Chamfer
   alone, ``distill_chain`` x it (the fresh noise breaks the points' correspondence): the last call
   learns to mend the earlier calls' answers, which are further from the teacher's path the fewer
   they are (one call: +50 % Chamfer), rather than only the teacher's own states.
3. Sampling: :func:`pocoloco.diffusion.few_step.sample_few_step` with 1 to 4 calls (and, with
   ``export-model --polish-with``, the teacher's finishing call, :func:`~pocoloco.diffusion.few_step.polish`).

Everything random is a pure function of the seed: the pair frames and noises (``seed_of(seed, 11,
shard)``, per-pair ``PerSampleRNG`` seeds), each step's pairs and times (``seed_of(seed, 12, step,
rank)``).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pocoloco.diffusion import NoiseSchedule, PerSampleRNG, sample
from pocoloco.diffusion.few_step import polished_grid, sampling_grid, student_grid
from pocoloco.diffusion.sampler_base import randn_like
from pocoloco.diffusion.samplers import StepInfo, make_timesteps, sample_ddim
from pocoloco.engine.checkpoint import (Checkpoint, check_model_kind, load_checkpoint, meta_digest, read_meta,
                                       resolve_checkpoint)
from pocoloco.engine.trainer import train
from pocoloco.methods.pocoloco.config import PocoLocoTrainConfig
from pocoloco.methods.pocoloco.method import PocoLocoMethod
from pocoloco.methods.pocoloco.training import PocoLocoTask
from pocoloco.ops.chamfer import chamfer_distance
from pocoloco.ops.probe_energy import box_probes, probe_embedding, set_energy_distance
from pocoloco.utils.atomic import save_npz_atomic, write_json_atomic
from pocoloco.utils.seeding import seed_of

__all__ = ["DISTILL_SAMPLERS", "DistillTask", "PairSettings", "TeacherPairs", "distill", "distill_config",
           "make_renoised_pairs", "make_teacher_pairs", "prepare_distillation", "read_teacher_pairs",
           "student_start"]  # fmt: skip

#: deterministic samplers a teacher's pairs may come from (an SDE's answer is not a function of x_T)
DISTILL_SAMPLERS = ("dpm++", "ddim", "unipc", "dpm++3m")
#: share of each batch's clouds at the noisiest grid time (the others share the rest evenly)
NOISIEST_SHARE = 0.4
#: probes of the set-level loss's embedding, per frame and step
SET_PROBES = 256
PAIRS_FILE = "pairs.json"


@dataclass(frozen=True)
class PairSettings:
    """How the teacher pairs were made: ``pairs`` clouds of ``num_points`` points, ``calls`` student
    grid timesteps, the teacher's deterministic ``sampler`` with ``steps`` steps, ``seed``,
    ``shard`` pairs per file, the teacher (its checkpoint folder and meta SHA-256), and ``draws``
    pairs per frame (consecutive pairs, each from its own noise: the sets a set-level loss compares)."""

    pairs: int
    num_points: int
    calls: int
    sampler: str
    steps: int
    seed: int
    shard: int
    teacher: str
    teacher_sha256: str
    num_timesteps: int = 1000
    draws: int = 1

    def check(self, num_timesteps: int) -> list[int]:
        """One-line errors for settings no student can learn from; returns the teacher's timesteps."""
        if self.pairs < 1 or self.num_points < 1 or self.shard < 1:
            raise ValueError(f"--pairs, --pair-points and the shard size must be >= 1, got {self.pairs}, "
                             f"{self.num_points}, {self.shard}")  # fmt: skip
        if self.sampler not in DISTILL_SAMPLERS:
            raise ValueError(f"--teacher-sampler {self.sampler}: a teacher must sample deterministically; choose one "
                             f"of {', '.join(DISTILL_SAMPLERS)}")  # fmt: skip
        if not 1 <= self.calls <= 8:
            raise ValueError(f"--calls must be in [1, 8], got {self.calls}")
        if self.draws < 1 or self.shard % self.draws or self.pairs % self.draws:
            raise ValueError(f"--draws-per-frame {self.draws}: must divide --pairs {self.pairs} and the shard size "
                             f"{self.shard}")  # fmt: skip
        ts = make_timesteps(num_timesteps, self.steps, "trailing")
        grid = student_grid(num_timesteps, self.calls)
        if not set(grid) <= set(ts):
            raise ValueError(f"--teacher-steps {self.steps}: the teacher's timesteps must include the student's "
                             f"{grid}; use a multiple of --calls {self.calls}")  # fmt: skip
        return ts


@dataclass
class TeacherPairs:
    """The pairs in memory: ``states`` (P, K, N, C) the teacher's states at the K grid timesteps
    ``grid`` (state 0 = the initial noise), ``targets`` (P, N, C) its answers, ``joints`` (P, J, 3)
    normalised, ``subject`` (P,) dataset subject ids, ``motion`` (P, J, F) window features or None;
    ``renoised_states`` / ``renoised_targets`` (P, K - 1, N, C) or None: each answer noised afresh to
    the later grid times and the teacher's answer from there (:func:`make_renoised_pairs`)."""

    states: np.ndarray
    targets: np.ndarray
    joints: np.ndarray
    subject: np.ndarray
    motion: np.ndarray | None
    grid: list[int]
    settings: PairSettings
    renoised_states: np.ndarray | None = None
    renoised_targets: np.ndarray | None = None


def check_set_batches(draws: int, batch_size: int) -> None:
    """One-line error unless batches of whole frames can be made: the set-level term needs >= 2
    teacher pairs per frame and a batch size that is a multiple of them."""
    if draws < 2 or batch_size % draws:
        raise ValueError(f"--set-weight needs >= 2 teacher pairs per frame (--draws-per-frame, got {draws}) and a "
                         f"batch size that is a multiple of it (got {batch_size})")  # fmt: skip


def chain_grid(num_timesteps: int, calls: int) -> list[int]:
    """The grid the set-level term runs the student's chain on: the one it samples with by default
    (a teacher's finishing call after it: :func:`~pocoloco.diffusion.few_step.polished_grid`, e.g.
    [999, 749, 249] for 4 calls), else its whole grid."""
    return polished_grid(num_timesteps, calls, calls) or student_grid(num_timesteps, calls)


def teacher_sha(ck: Checkpoint) -> str:
    """The teacher's identity: its meta's ``meta_sha256`` (checkpoints written with checksums) or
    the same digest computed (:func:`~pocoloco.engine.checkpoint.meta_digest`)."""
    return str(ck.meta.get("meta_sha256") or meta_digest(ck.meta))


def distill_config(teacher: PocoLocoTrainConfig, calls: int, **overrides: Any) -> PocoLocoTrainConfig:
    """The student's train config: the teacher's network and conditioning, ``student_calls=calls``,
    and the distillation run's loop settings (a fine-tune: small lr, short warm-up, EMA 0.995, wsd
    cool-down over the last fifth; checkpoints every 100 steps; no previews)."""
    if teacher.student_calls:
        raise ValueError("the teacher is already a distilled student; distil the diffusion model it came from")
    if teacher.architecture != "latent":
        raise ValueError("pocoloco distill: only the latent denoiser (latent_* presets) is supported")
    steps = int(overrides.pop("steps", 2000))
    base: dict[str, Any] = {"student_calls": calls, "steps": steps, "batch_size": 16, "lr": 5e-5, "warmup_steps": 20,
                            "lr_schedule": "wsd", "decay_steps": max(1, steps // 5), "ema_decay": 0.995,
                            "ckpt_every": 100, "sample_every": 0, "log_every": 10, "keep_checkpoints": 2,
                            "freeze_trunk": False}  # fmt: skip
    return teacher.replace(**{**base, **overrides})


def _shard_path(out: Path, k: int, kind: str = "shard") -> Path:
    return out / f"{kind}_{k:05d}.npz"


@torch.no_grad()
def make_teacher_pairs(task: DistillTask, teacher: nn.Module, settings: PairSettings, out: str | Path,
                       progress: Callable[[int, int], None] | None = None) -> TeacherPairs:  # fmt: skip
    """Make (or finish) the teacher pairs of ``settings`` in ``out`` (see the module docstring) for
    the training frames of ``task``'s dataset; returns them. A folder made with other settings is a
    one-line error; shards already written are kept."""
    c = task.config
    if settings.num_timesteps != c.num_timesteps:
        raise ValueError(f"pair settings say {settings.num_timesteps} timesteps, the teacher has {c.num_timesteps}")
    ts = settings.check(c.num_timesteps)
    grid = student_grid(c.num_timesteps, settings.calls)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta_path = out / PAIRS_FILE
    want = dict(settings.__dict__)
    if meta_path.is_file():
        have = {"draws": 1, **json.loads(meta_path.read_text())}  # folders made before draws existed: one each
        if have != want:
            diff = [k for k in want if have.get(k) != want[k]]
            raise ValueError(f"{out}: teacher pairs made with other settings ({', '.join(diff)}); choose another --out")
    else:
        write_json_atomic(meta_path, want)
    schedule = NoiseSchedule.from_kind(c.schedule, c.num_timesteps)
    capture = {ts.index(g) - 1: k for k, g in enumerate(grid) if k > 0}  # sampler step -> grid slot of its result
    device = next(teacher.parameters()).device
    C = int(c.denoiser.point_channels)
    ds = task.dataset
    shards = _num_shards(settings)
    done = 0
    teacher.eval()
    for k in range(shards):
        n = min(settings.shard, settings.pairs - k * settings.shard)
        path = _shard_path(out, k)
        if path.is_file():
            done += n
            if progress is not None:
                progress(done, settings.pairs)
            continue
        rng = np.random.default_rng(seed_of(settings.seed, 11, k))
        m = n // settings.draws  # frames in this shard, each drawn `draws` times from its own noises
        frames = np.repeat(rng.choice(len(ds), m, replace=len(ds) < m), settings.draws)
        items = [ds[int(i)] for i in frames]
        joints = torch.stack([torch.as_tensor(it["joints"]) for it in items]).float()  # (n, J, 3) normalised
        subject = torch.tensor([int(it["subject"]) for it in items])
        motion = (torch.stack([torch.as_tensor(it["motion"]) for it in items]).float()
                  if c.motion_window else None)  # fmt: skip
        seeds = [settings.seed * 1_000_003 + k * settings.shard + j for j in range(n)]
        prng = PerSampleRNG(seeds, device=device)
        noise = prng.randn((settings.num_points, C), device=device)  # (n, N, C)
        states = torch.empty(n, len(grid), settings.num_points, C)
        states[:, 0] = noise.float().cpu()

        def keep(info: StepInfo) -> None:
            if info.index in capture:
                states[:, capture[info.index]] = info.x.float().cpu()

        cond = task.condition(joints.to(device), subject.to(device), motion=None if motion is None else motion.to(device))
        x0 = sample(settings.sampler, teacher, schedule, noise, cond, prediction_type=c.prediction_type,
                    steps=settings.steps, rng=prng, progress=keep)  # fmt: skip
        arrays = {"states": states.numpy(), "targets": x0.float().cpu().numpy(), "joints": joints.numpy(),
                  "subject": subject.numpy(), "frames": np.asarray(frames, np.int64), "seeds": np.asarray(seeds)}  # fmt: skip
        if motion is not None:
            arrays["motion"] = motion.numpy()
        save_npz_atomic(path, **arrays)
        done += n
        if progress is not None:
            progress(done, settings.pairs)
    return read_teacher_pairs(out)


@torch.no_grad()
def make_renoised_pairs(task: DistillTask, teacher: nn.Module, pairs: TeacherPairs, folder: str | Path,
                        progress: Callable[[int, int], None] | None = None) -> TeacherPairs:  # fmt: skip
    """Make (or finish) the re-noised pairs of ``pairs``, the complete teacher pairs in ``folder``
    (made by :func:`make_teacher_pairs` for this teacher): for each pair and each later grid time t_k, its
    answer x0* noised afresh, ``x = sqrt(abar_k) x0* + sqrt(1 - abar_k) z`` (what the re-noising
    sampler hands its next call, DDPM eq. 4), and the teacher's deterministic sampler run from x
    over its own timesteps from t_k down (``renoised_XXXXX.npz`` beside each pair shard, written
    atomically; z from per-pair seeds ``seed_of(seed, 14, pair)``). Costs the teacher
    (K - 1) / 2 of the pairs' calls on the 4-call grid. Returns ``pairs`` with them read in."""
    s, c, folder = pairs.settings, task.config, Path(folder)
    ts = s.check(c.num_timesteps)
    schedule = NoiseSchedule.from_kind(c.schedule, c.num_timesteps)
    ab = schedule.alphas_cumprod.double()
    device = next(teacher.parameters()).device
    teacher.eval()
    for k in range(_num_shards(s)):
        lo, hi = k * s.shard, min((k + 1) * s.shard, s.pairs)
        path = _shard_path(folder, k, "renoised")
        if not path.is_file():
            target = torch.from_numpy(pairs.targets[lo:hi]).to(device).double()
            joints, subject = torch.from_numpy(pairs.joints[lo:hi]), torch.from_numpy(pairs.subject[lo:hi])
            motion = None if pairs.motion is None else torch.from_numpy(pairs.motion[lo:hi]).to(device)
            cond = task.condition(joints.to(device), subject.to(device), motion=motion)
            prng = PerSampleRNG([seed_of(s.seed, 14, i) for i in range(lo, hi)], device=device)
            states, answers = [], []
            for t in pairs.grid[1:]:
                x = (ab[t].sqrt() * target + (1 - ab[t]).sqrt() * prng.randn(target.shape[1:], device=device).double())
                x = x.float()
                states.append(x.cpu())
                answers.append(sample(s.sampler, teacher, schedule, x, cond, prediction_type=c.prediction_type,
                                      timesteps=ts[ts.index(t):], rng=prng).float().cpu())  # fmt: skip
            save_npz_atomic(path, states=torch.stack(states, 1).numpy(), targets=torch.stack(answers, 1).numpy())
        if progress is not None:
            progress(hi, s.pairs)
    return _with_renoised(pairs, folder)


def read_teacher_pairs(folder: str | Path, renoised: bool | None = False) -> TeacherPairs:
    """The pairs of a folder :func:`make_teacher_pairs` completed (``renoised``: with the re-noised
    pairs of :func:`make_renoised_pairs`; None: with them where they are all there); one-line errors
    for a missing, incomplete or damaged one."""
    folder = Path(folder)
    try:
        settings = PairSettings(**json.loads((folder / PAIRS_FILE).read_text()))
    except FileNotFoundError:
        raise ValueError(f"{folder}: no teacher pairs ({PAIRS_FILE} missing)") from None
    except (TypeError, json.JSONDecodeError) as e:
        raise ValueError(f"{folder / PAIRS_FILE}: damaged ({e})") from None
    cat = _gather_shards(folder, settings, "shard")
    grid = student_grid(settings.num_timesteps, settings.calls)
    pairs = TeacherPairs(cat["states"], cat["targets"], cat["joints"], cat["subject"], cat.get("motion"), grid,
                         settings)  # fmt: skip
    if renoised is None:
        renoised = all(_shard_path(folder, k, "renoised").is_file() for k in range(_num_shards(settings)))
    return _with_renoised(pairs, folder) if renoised else pairs


def _num_shards(settings: PairSettings) -> int:
    return -(-settings.pairs // settings.shard)


def _gather_shards(folder: Path, settings: PairSettings, kind: str) -> dict[str, np.ndarray]:
    """The arrays of every ``kind`` shard of a pairs folder, concatenated; one-line errors for a
    missing or damaged shard."""
    parts: dict[str, list[np.ndarray]] = {}
    for k in range(_num_shards(settings)):
        path = _shard_path(folder, k, kind)
        if not path.is_file():
            what = "teacher pairs" if kind == "shard" else "re-noised teacher pairs"
            raise ValueError(f"{folder}: {what} incomplete ({path.name} missing; rerun to finish them)")
        try:
            with np.load(path) as z:
                for key in z.files:
                    parts.setdefault(key, []).append(z[key])
        except (OSError, ValueError, EOFError) as e:
            raise ValueError(f"{path}: damaged shard ({e}); delete it and rerun") from None
    return {k: np.concatenate(v) for k, v in parts.items()}


def _with_renoised(pairs: TeacherPairs, folder: Path) -> TeacherPairs:
    """``pairs`` with the re-noised pairs of ``folder`` (:func:`make_renoised_pairs`) read in."""
    re = _gather_shards(folder, pairs.settings, "renoised")
    want = (len(pairs.targets), len(pairs.grid) - 1, *pairs.targets.shape[1:])
    if re["states"].shape != want or re["targets"].shape != want:
        raise ValueError(f"{folder}: re-noised pairs of shape {re['states'].shape}, expected {want}; delete the "
                         "renoised_*.npz files and rerun")  # fmt: skip
    pairs.renoised_states, pairs.renoised_targets = re["states"], re["targets"]
    return pairs


class PairBatches(torch.utils.data.Dataset):
    """Step s -> a batch of B (pair, grid time) draws: ``x`` (B, N, C) the teacher's state, ``t`` (B,),
    ``target`` (B, N, C), ``joints`` (B, J, 3), ``subject`` (B,) [, ``motion`` (B, J, F)].

    Re-noised draws (``renoised``: that share of the later-grid draws) are the stored re-noised
    states with the teacher's answers from them where the pairs hold them (:func:`make_renoised_pairs`),
    else the answer noised afresh here with the answer as target (``trajectory`` False: no per-point
    correspondence).

    grouped: whole frames instead of single pairs: B / D frames (D = the pairs' ``draws``), all D
    pairs of a frame consecutive in the batch and at the same grid time (the sets a set-level loss
    compares). grouped or ``chain``: the batch also holds each pair's initial noise ``noise`` and the
    teacher's answer for it ``answers`` (B, N, C), for a term on the student's own chain."""

    def __init__(self, pairs: TeacherPairs, batch_size: int, seed: int, steps: int, rank: int = 0,
                 renoised: float = 0.0, alpha_bar: np.ndarray | None = None, grouped: bool = False,
                 chain: bool = False):  # fmt: skip
        self.pairs, self.batch_size, self.seed, self.steps, self.rank = pairs, batch_size, seed, steps, rank
        self.renoised, self.alpha_bar, self.grouped, self.chain = renoised, alpha_bar, grouped, chain
        if renoised and alpha_bar is None:
            raise ValueError("re-noised draws need the schedule's alpha_bar")
        if grouped:
            check_set_batches(pairs.settings.draws, batch_size)
        K = len(pairs.grid)
        self.time_p = np.full(K, (1.0 - NOISIEST_SHARE) / max(K - 1, 1))
        self.time_p[0] = NOISIEST_SHARE if K > 1 else 1.0

    def __len__(self) -> int:
        return self.steps

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        p = self.pairs
        rng = np.random.default_rng(seed_of(self.seed, 12, int(step), self.rank))
        if self.grouped:  # whole frames, each frame's draws at one grid time
            D = p.settings.draws
            groups, g = len(p.targets) // D, self.batch_size // D
            first = D * rng.choice(groups, g, replace=groups < g)
            idx = (first[:, None] + np.arange(D)).reshape(-1)
            k = np.repeat(rng.choice(len(p.grid), g, p=self.time_p), D)
        else:
            idx = rng.choice(len(p.targets), self.batch_size, replace=len(p.targets) < self.batch_size)
            k = rng.choice(len(p.grid), self.batch_size, p=self.time_p)
        x = p.states[idx, k]  # (B, N, C) the teacher's states
        target = p.targets[idx]
        # re-noised draws (a later grid time): the teacher's answer noised afresh, as the sampler does
        renoised = (k > 0) & (rng.random(self.batch_size) < self.renoised)
        corresponds = ~renoised
        if renoised.any() and p.renoised_states is not None:  # stored, with the teacher's answer from there
            x, target = x.copy(), target.copy()
            x[renoised] = p.renoised_states[idx[renoised], k[renoised] - 1]
            target[renoised] = p.renoised_targets[idx[renoised], k[renoised] - 1]
            corresponds = np.ones_like(renoised)
        elif renoised.any():  # drawn now; the target stays the answer, scored by Chamfer alone
            ab = self.alpha_bar[np.asarray(p.grid)[k[renoised]]].reshape(-1, 1, 1)
            z = rng.standard_normal(x[renoised].shape).astype(np.float32)
            x = x.copy()
            x[renoised] = (np.sqrt(ab) * p.targets[idx[renoised]] + np.sqrt(1 - ab) * z).astype(np.float32)
        batch = {"x": torch.from_numpy(x), "t": torch.as_tensor(np.asarray(p.grid)[k]),
                 "target": torch.from_numpy(target), "joints": torch.from_numpy(p.joints[idx]),
                 "subject": torch.from_numpy(p.subject[idx]), "trajectory": torch.from_numpy(corresponds)}  # fmt: skip
        if p.motion is not None:
            batch["motion"] = torch.from_numpy(p.motion[idx])
        if self.grouped or self.chain:  # the draws' initial noises, for the student's own chain, and their answers
            batch["noise"] = torch.from_numpy(p.states[idx, 0])
            batch["answers"] = torch.from_numpy(p.targets[idx])
        return batch


class DistillTask(PocoLocoTask):
    """Train a few-step student of a PocoLoco teacher on teacher pairs (module docstring). The
    dataset, outfits and conditioning are PocoLoco's (:class:`PocoLocoTask`); ``pairs`` must be set
    (:func:`make_teacher_pairs`) before the loop asks for batches."""

    def __init__(self, config: PocoLocoTrainConfig, data: str | Path, teacher: str | None = None,
                 teacher_sha256: str | None = None):  # fmt: skip
        if not config.student_calls:
            raise ValueError("a distillation run needs student_calls >= 1")
        super().__init__(config, data)
        self.pairs: TeacherPairs | None = None
        self.teacher, self.teacher_sha256 = teacher, teacher_sha256
        self.start = teacher  # the checkpoint a fresh student starts from (prepare_distillation: --init-from)

    def step_bytes(self) -> int | None:
        per = super().step_bytes()
        chained = self.config.distill_chain > 0 or self.config.distill_set > 0  # a second forward, on the chain
        return None if per is None else (4 if chained else 2) * per  # the student's forward and the Chamfer terms

    def step_batches(self, model: nn.Module, rank: int, world: int) -> PairBatches:
        if self.pairs is None:
            raise RuntimeError("DistillTask: make or read the teacher pairs first")
        return PairBatches(self.pairs, self.config.batch_size, self.config.seed, self.config.steps, rank,
                           self.config.distill_renoised, self.schedule.alphas_cumprod.double().numpy(),
                           grouped=self.config.distill_set > 0, chain=self.config.distill_chain > 0)  # fmt: skip

    def loss(self, net: nn.Module, batch: dict[str, torch.Tensor], step: int, rank: int):
        c = self.config
        x, t, target = batch["x"], batch["t"], batch["target"]
        cond = self.condition(batch["joints"], batch["subject"], motion=batch.get("motion"))
        out = net(x, t, cond)
        _, x0 = self.schedule.pred_to_eps_x0(out.float(), x.float(), t, c.prediction_type)  # (B, N, C)
        per_point = batch.get("trajectory", torch.ones(len(x), dtype=torch.bool, device=x.device))
        # points correspond only along the teacher's path; a re-noised draw is scored by Chamfer alone
        d2 = (x0 - target).square().sum(-1)  # (B, N)
        huber = (((d2 + c.distill_huber**2).sqrt() - c.distill_huber).mean(-1) * per_point).sum() / len(x)
        loss = huber
        logs = {"huber": huber.detach()}
        if c.distill_chamfer > 0:
            cham = chamfer_distance(x0[..., :3], target[..., :3]).chamfer.mean()
            loss = loss + c.distill_chamfer * cham
            logs["chamfer"] = cham.detach()
        chained, chain_grid_ = None, None
        if c.distill_chain > 0:  # each pair's noise down the student's few-call chain, to the teacher's answer
            gen = torch.Generator(device=x.device).manual_seed(seed_of(c.seed, 14, int(step), rank))
            chain_grid_ = sampling_grid(c.num_timesteps, c.distill_chain_calls, c.student_calls)
            chained = self.student_chain(net, batch["noise"], cond, gen, grid=chain_grid_, grad=c.distill_chain_grad)
            # fresh noise between the calls: its points no longer correspond to the answer's, so Chamfer alone
            chain_cham = chamfer_distance(chained[..., :3], batch["answers"][..., :3].float()).chamfer.mean()
            loss = loss + c.distill_chain * chain_cham
            logs["chain_chamfer"] = chain_cham.detach()
        if c.distill_set > 0:  # each frame's draws down the student's chain, scored against the teacher's set
            shared = chained if chain_grid_ is not None and chain_grid_ == self.set_grid() else None
            ed = self.set_loss(net, batch, cond, step, rank, answers=shared)
            loss = loss + c.distill_set * ed["energy_score"]  # = energy distance / 2 + a constant; never < 0
            logs.update({f"set_{k}": v.detach() for k, v in ed.items()})
        logs["loss"] = loss.detach()
        as_tensors = x.device.type != "cpu"
        return loss, {k: v if as_tensors else float(v) for k, v in logs.items()}

    def student_chain(self, net: nn.Module, noise: torch.Tensor, cond: Any, gen: torch.Generator,
                      grid: list[int] | None = None, grad: str = "last") -> torch.Tensor:  # fmt: skip
        """(B, N, C) the student's answers from ``noise`` (B, N, C) down ``grid`` (default
        :func:`chain_grid`), as :func:`~pocoloco.diffusion.few_step.sample_few_step` gives them
        (``student_renoise`` fresh noise from ``gen`` at each re-noising), with a gradient through
        the last call (``grad`` "last") or through every call ("all": backpropagation through the
        unrolled chain, x_s = sqrt(abar_s) x0 + sqrt(1 - abar_s) (sqrt(1 - r^2) eps_hat + r z))."""
        c = self.config
        grid = chain_grid(c.num_timesteps, c.student_calls) if grid is None else grid
        if grad not in ("last", "all"):
            raise ValueError(f"grad must be last or all, got {grad!r}")
        x = noise.float()
        if grad == "all":
            for i, t in enumerate(grid):
                tt = torch.full((len(x),), t, device=x.device)
                eps, x0 = self.schedule.pred_to_eps_x0(net(x, tt, cond).float(), x, tt, c.prediction_type)
                if i + 1 == len(grid):
                    return x0
                ab = float(self.schedule.alpha_bar(grid[i + 1]))
                sigma = c.student_renoise * (1.0 - ab) ** 0.5
                x = ab**0.5 * x0 + max(1.0 - ab - sigma**2, 0.0) ** 0.5 * eps
                if sigma > 0:  # the same draw as the sampler's (float32 noise from ``gen``)
                    x = x + sigma * randn_like(x, gen)
        if len(grid) > 1:  # every call but the last, without a gradient, ending at the last call's state
            with torch.no_grad():
                x = sample_ddim(net, self.schedule, x, cond, prediction_type=c.prediction_type, timesteps=grid[:-1],
                                renoise=c.student_renoise, rng=gen, end_at=grid[-1])  # fmt: skip
        tt = torch.full((len(x),), grid[-1], device=x.device)
        return self.schedule.pred_to_eps_x0(net(x, tt, cond).float(), x, tt, c.prediction_type)[1]

    def set_grid(self) -> list[int]:
        """The timesteps of the chain the set-level term runs: the student's default sampler
        (:func:`chain_grid`) or, with ``distill_set_calls``, its sampling grid of that many calls."""
        c = self.config
        if c.distill_set_calls:
            return sampling_grid(c.num_timesteps, c.distill_set_calls, c.student_calls)
        return chain_grid(c.num_timesteps, c.student_calls)

    def set_loss(self, net: nn.Module, batch: dict[str, torch.Tensor], cond: Any, step: int,
                 rank: int, answers: torch.Tensor | None = None) -> dict[str, torch.Tensor]:  # fmt: skip
        """The set-level term, on the student's own chain: each frame's D initial noises (a batch of
        whole frames, :class:`PairBatches` ``grouped``) taken down :meth:`set_grid` (each call
        re-noised with ``student_renoise`` fresh noise, as
        :func:`~pocoloco.diffusion.few_step.sample_few_step` does; no gradient but the last call's),
        and the last call's answers scored as a set against the teacher's D answers the way the
        judge scores a sampler: the energy distance / score of the probe-distance embeddings
        (:mod:`pocoloco.ops.probe_energy`; SET_PROBES probes drawn afresh each step in each
        frame's bounding box). ``answers`` (B, N, C): the chain's answers already made for these
        noises on the same grid (the chain term's), used instead of running it again. Returns the
        statistics averaged over the frames, normalised units."""
        if self.pairs is None:
            raise RuntimeError("DistillTask: make or read the teacher pairs first")
        c, D = self.config, self.pairs.settings.draws
        noise = batch["noise"]
        gen = torch.Generator(device=noise.device).manual_seed(seed_of(c.seed, 13, int(step), rank))
        x0 = self.student_chain(net, noise, cond, gen, grid=self.set_grid()) if answers is None else answers
        target = batch["answers"][..., :3].float()
        s, t = x0[..., :3].reshape(-1, D, x0.shape[1], 3), target.reshape(-1, D, target.shape[1], 3)  # (G, D, N, 3)
        probes = box_probes(t, SET_PROBES, gen).unsqueeze(1)  # (G, 1, P, 3): one fixed map per frame
        ed = set_energy_distance(probe_embedding(s, probes), probe_embedding(t, probes))
        return {k: v.mean() for k, v in ed.items()}

    def check_resume(self, ck: Checkpoint) -> None:
        super().check_resume(ck)
        stored = ck.meta.get("distilled_from", {}).get("teacher_sha256")
        if self.teacher_sha256 is not None and stored not in (None, self.teacher_sha256):
            raise ValueError(f"{ck.path}: this run distils another teacher ({stored[:12]}...); choose another --out")

    def checkpoint_extra(self, model: nn.Module) -> dict[str, Any]:
        extra = super().checkpoint_extra(model)
        s = self.pairs.settings if self.pairs is not None else None
        extra["distilled_from"] = {"teacher": self.teacher, "teacher_sha256": self.teacher_sha256,
                                   **({"pairs": s.pairs, "pair_points": s.num_points, "teacher_sampler": s.sampler,
                                       "teacher_steps": s.steps, "draws_per_frame": s.draws,
                                       "renoised_targets": self.config.distill_renoised_targets}
                                      if s is not None else {})}  # fmt: skip
        return extra

    def preview(self, model: nn.Module, step: int, out: Path, device: torch.device) -> Path | None:
        return None


def prepare_distillation(teacher: str | Path, data: str | Path, out: str | Path, *, calls: int = 4,
                         pairs: int = 1024, pair_points: int = 512, teacher_sampler: str = "dpm++",
                         teacher_steps: int = 20, draws: int = 1, seed: int = 0,
                         device: str | torch.device = "cpu", init_from: str | Path | None = None,
                         teacher_frame: bool = False, pair_progress: Callable[[int, int], None] | None = None, **overrides: Any) -> DistillTask:  # fmt: skip
    """The first half of ``pocoloco distill``: the student's task (:func:`distill_config` with
    ``overrides``: steps, batch_size, lr, ...) with its teacher pairs made or finished in
    ``out/pairs`` (``pair_progress(done, total)`` after each shard); one-line errors for a bad
    teacher, data, settings or ``init_from`` (:func:`student_start`) before any work.
    ``task.teacher`` is the teacher's checkpoint folder, ``task.start`` the one a fresh student
    starts from. ``teacher_frame``: data of the teacher's subjects whose normalisation differs (made
    with fewer train motions, say) is taken in the teacher's frame instead of refused: the pairs need
    only its training poses, and the student sees the teacher's frame either way."""
    if not 1 <= calls <= 8:
        raise ValueError(f"--calls must be in [1, 8], got {calls}")
    if overrides.get("distill_set"):  # before any pair is made
        check_set_batches(draws, int(overrides.get("batch_size") or 16))
    ck = load_checkpoint(teacher, expect_model="pocoloco", training_state=False)
    method = PocoLocoMethod.from_checkpoint(ck, device=str(device))
    config = distill_config(method.config, calls, seed=seed, num_points=pair_points, **overrides)
    sha = teacher_sha(ck)
    task = DistillTask(config, data, teacher=str(ck.path), teacher_sha256=sha)
    if task.normalisation != ck.normalisation:
        if not (teacher_frame or ck.normalisation.matches(task.normalisation)):
            raise ValueError(f"--data {data}: its normalisation differs from the teacher's; distil on the data the "
                             "teacher was trained on (or, for data of its subjects made with fewer motions, "
                             "--teacher-frame)")  # fmt: skip
        # the teacher's data made again (its statistics moved in their last digits): the teacher's frame, exactly
        task.dataset.normalisation = task.normalisation = ck.normalisation
        if teacher_frame:  # its poses in the teacher's frame: the teacher's subjects (and body points), one-line error
            task.check_resume(ck)
    task.start = student_start(task, init_from)
    settings = PairSettings(pairs=pairs, num_points=pair_points, calls=calls, sampler=teacher_sampler,
                            steps=teacher_steps, seed=seed, shard=16, teacher=str(ck.path), teacher_sha256=sha,
                            num_timesteps=config.num_timesteps, draws=draws)  # fmt: skip
    settings.check(config.num_timesteps)
    task.pairs = make_teacher_pairs(task, method.model, settings, Path(out) / "pairs", progress=pair_progress)
    if config.distill_renoised_targets == "ode":  # (the config refuses it without re-noised draws)
        # one bar for both passes: the pairs are the first half of it, their re-noised answers the second
        more = None if pair_progress is None else (lambda done, total: pair_progress(total + done, 2 * total))
        task.pairs = make_renoised_pairs(task, method.model, task.pairs, Path(out) / "pairs", progress=more)
    return task


def student_start(task: DistillTask, init_from: str | Path | None = None) -> str:
    """The weights a fresh student starts from: its teacher's, or ``init_from``, a student of the
    same teacher on the same grid (e.g. the shipped ``default:fast``, to train it longer; int8
    weights are read back as float). One-line errors for any other checkpoint, from its meta.json
    alone (the training loop loads the weights)."""
    if init_from is None:
        return str(task.teacher)
    path = resolve_checkpoint(init_from)
    meta = read_meta(path)
    check_model_kind(path, meta["model_kind"], "pocoloco", "--init-from")
    calls = int(meta["config"].get("student_calls") or 0)
    if calls != task.config.student_calls:
        what = "not a distilled student" if not calls else f"a student of {calls} calls"
        raise ValueError(f"--init-from {init_from}: {what}; start from a {task.config.student_calls}-call student of "
                         "this teacher, or from the teacher (no --init-from)")  # fmt: skip
    sha = meta.get("distilled_from", {}).get("teacher_sha256")
    if sha != task.teacher_sha256:
        raise ValueError(f"--init-from {init_from}: a student of another teacher ({str(sha)[:12]}...); start from a "
                         "student of this teacher")  # fmt: skip
    return str(path)


def distill(teacher: str | Path, data: str | Path, out: str | Path, *, resume: bool = False,
            device: str | torch.device = "cpu", progress: bool = True, time_budget_s: float | None = None,
            **kwargs: Any):  # fmt: skip
    """``pocoloco distill``: :func:`prepare_distillation` (``kwargs``: its options, ``init_from``
    included, and train config fields), then the student trained from ``task.start`` (the teacher's
    weights, or ``init_from``'s) by the shared loop into the run folder ``out`` (``resume``: from its
    newest checkpoint), its sampling-only export in ``out/model``. Returns the loop's
    :class:`~pocoloco.engine.trainer.TrainResult`."""
    task = prepare_distillation(teacher, data, out, device=device, **kwargs)
    return train(task, out, device=device, resume=resume, progress=progress, time_budget_s=time_budget_s,
                 export_to=Path(out) / "model", init_from=None if resume else task.start)
