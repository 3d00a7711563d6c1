"""Sampling a trained PocoLoco checkpoint: K point-cloud hypotheses of a clothed body in one pose.

Pipeline (the inverse of the training data path, :mod:`pocoloco.data.dataset`)::

    joints (J, 3) metres --normalise--> (J, 3) normalised  = (joints - root - mean) / std
    noise (K, N, C) per-sample seeds --sampler(denoiser, schedule, cond=joints)--> x0 (K, N, C)
    x0[..., :3] --denormalise--> points (K, N, 3) metres   = x0 * std + mean + root

``root = joints[normalisation.root_joint]`` of the *input* joints, so the samples come out in the
frame the joints were given in. C = 6 models also predict normals (channels 3:6), returned as unit
vectors. The denoiser is resolution-agnostic: N need not match the training ``num_points``.

Every sample k owns a ``torch.Generator`` seeded ``seeds[k]`` whose stream provides its initial
noise and any sampler noise (:class:`~pocoloco.diffusion.samplers.PerSampleRNG`), so sample k is
the same whatever the batch size.

Public API: :func:`sample_clouds` -> :class:`SampledClouds`, :func:`load_joints`,
:func:`write_samples`, and the CLI pieces :func:`add_sample_arguments` / :func:`cmd_sample`
(``pocoloco sample``; also ``python -m pocoloco.sample``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import sys
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from pocoloco.data.dataset import Normalisation
from pocoloco.utils.atomic import output_folder

__all__ = [
    "SAMPLERS",
    "SampledClouds",
    "add_sample_arguments",
    "cmd_sample",
    "load_joints",
    "load_model_from_args",
    "main",
    "sample_clouds",
    "write_samples",
]

#: sampler kinds accepted by :func:`sample_clouds`, and their default number of steps. ddpm is
#: the ancestral sampler strided to 100 steps (``steps=1000`` is the paper's DDPM). The default,
#: dpm++sde (SDE-DPM-Solver++ 2M, 25 steps), is within 4 % of DDPM-1000 at 28x less time for the
#: shipped model; the deterministic DDIM / DPM++ are ~24 % worse (BENCHMARKS.md, "Few-step
#: sampling").
SAMPLERS: dict[str, int | None] = {"dpm++": 20, "dpm++sde": 25, "ddim": 50, "ddpm": 100}
NUM_JOINTS = 24
#: default x0 clamp of the CLI (normalised units); the ``small`` data stay within +-3.52
DEFAULT_CLIP = 5.0
_SAMPLE_FILE = re.compile(r"^sample_(\d+)\.ply$")


# ------------------------------------------------------------------------------------ joints
def _check_joints(src: str, joints: Any, num_joints: int) -> np.ndarray:
    """(J, 3) finite float array or a one-line ValueError naming ``src``."""
    arr = np.asarray(joints)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{src}: joints must be numeric, got dtype {arr.dtype}")
    if arr.shape != (num_joints, 3):
        raise ValueError(f"{src}: expected joints of shape ({num_joints}, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{src}: joints contain NaN or inf")
    return arr.astype(np.float32)


def _load_array_file(path: Path) -> np.ndarray:
    """The joints array of a .npy, or of a .npz (key ``joints``, else its only array)."""
    try:
        loaded = np.load(path, allow_pickle=False)
        if not hasattr(loaded, "files"):  # a .npy array
            return np.asarray(loaded)
        with loaded as z:
            if "joints" in z.files:
                return z["joints"]
            if len(z.files) == 1:
                return z[z.files[0]]
            raise ValueError(f"{path}: npz has no 'joints' array (arrays: {', '.join(sorted(z.files))})")
    except ValueError as e:
        if str(e).startswith(str(path)):
            raise
        raise ValueError(f"{path}: cannot read joints ({type(e).__name__}: {' '.join(str(e).split())})") from None
    except Exception as e:  # zipfile.BadZipFile, EOFError, OSError ...
        raise ValueError(f"{path}: cannot read joints ({type(e).__name__}: {' '.join(str(e).split())})") from None


def _dataset_frame_path(spec: str) -> Path:
    """``DATASET:subject/split/sequence/index`` -> the frame file (the dataset is validated)."""
    from pocoloco.data.format import SPLITS, DatasetLayout, read_card

    root, _, key = spec.rpartition(":")
    parts = key.strip("/").split("/")
    if len(parts) != 4:
        raise ValueError(f"{spec}: expected DATASET:subject/split/sequence/index, got frame key {key!r}")
    subject, split, sequence, index = parts
    read_card(root)  # one-line error when root is not a dataset
    if split not in SPLITS:
        raise ValueError(f"{spec}: unknown split {split!r}; expected one of {SPLITS}")
    try:
        idx = int(index)
    except ValueError:
        raise ValueError(f"{spec}: frame index {index!r} is not an integer") from None
    layout = DatasetLayout(root)
    if subject not in layout.subjects():
        raise ValueError(f"{spec}: no subject {subject!r} in {root} (has {', '.join(layout.subjects()) or 'none'})")
    path = layout.frame_path(subject, split, sequence, idx)
    if not path.is_file():
        raise ValueError(f"{spec}: no such frame ({path})")
    return path


def load_joints(spec: str | os.PathLike, frame_id: int | None = None, num_joints: int = NUM_JOINTS) -> np.ndarray:
    """Read one pose's joints (J, 3) float32, in metres, from ``spec``.

    ``spec`` is one of:

    - a ``.npy`` holding a (J, 3) array, or a ``.npz`` with a ``joints`` array (this covers our
      dataset frame files) or a single (J, 3) array;
    - a LOOSE-style joints text file (per line a frame id and 3J floats,
      :func:`pocoloco.data.published.read_joints_txt`): ``frame_id`` picks the line with that
      frame id (None: the first line);
    - a dataset frame ``DATASET:subject/split/sequence/index`` (e.g. ``data/tiny:s0/test/seq_000/3``);
    - ``demo:NAME``, a pose shipped with the package (``demo:skirt``, ``demo:shirt``, ``demo:tight``).

    Raises:
        ValueError (one line, naming the file): unreadable file, not a dataset, no such frame,
        wrong joint count or shape, NaN / inf.
    """
    from pocoloco.data.format import read_frame
    from pocoloco.data.published import read_joints_txt

    spec = os.fspath(spec)
    path = Path(spec)
    if spec.startswith("demo:") and not path.exists():
        from pocoloco.pretrained import demo_pose_path

        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to joints text files")
        return _check_joints(spec, _load_array_file(demo_pose_path(spec[5:])), num_joints)
    if not path.exists() and ":" in spec:
        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to joints text files")
        return _check_joints(spec, read_frame(_dataset_frame_path(spec), ["joints"]).joints, num_joints)
    if not path.is_file():
        raise ValueError(f"{spec}: no such joints file (or DATASET:subject/split/sequence/index frame)")
    if path.suffix in (".npy", ".npz"):
        if frame_id is not None:
            raise ValueError(f"{spec}: --frame-id only applies to joints text files")
        return _check_joints(spec, _load_array_file(path), num_joints)
    ids, joints = read_joints_txt(path, num_joints)  # (T,), (T, J, 3); validates counts and NaNs
    if frame_id is None:
        return joints[0]
    hit = np.flatnonzero(ids == frame_id)
    if len(hit) == 0:
        raise ValueError(f"{spec}: no line with frame id {frame_id} (ids {ids.min()}..{ids.max()})")
    return joints[hit[0]]


# ----------------------------------------------------------------------------------- sampling
class SampledClouds(NamedTuple):
    """What :func:`sample_clouds` returns; unpacks as ``points, normals``.

    points: (K, N, 3) float32 metres, in the frame of the input joints.
    normals: (K, N, 3) float32 unit normals (models with point_channels 6), else None.
    """

    points: np.ndarray
    normals: np.ndarray | None


def _check_sampler(sampler: str, steps: int | None, num_timesteps: int) -> None:
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; choose one of: {', '.join(SAMPLERS)}")
    if steps is not None and not 1 <= steps <= num_timesteps:
        raise ValueError(f"steps must be in [1, {num_timesteps}] (the model's training timesteps), got {steps}")


@torch.no_grad()
def sample_clouds(
    model: torch.nn.Module,
    normalisation: Normalisation,
    config: Any,
    joints: np.ndarray,
    num: int,
    num_points: int,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seeds: Sequence[int] | None = None,
    batch_size: int = 8,
    progress: Any = None,
    clip: float | None = None,
    bf16: bool = False,
) -> SampledClouds:
    """Draw ``num`` clouds of ``num_points`` points from the denoiser, conditioned on one pose.

    Args:
        model: the trained denoiser ``model(x (B, N, C), t (B,), joints (B, J, 3))`` (its device and
            dtype are used for everything).
        normalisation: the dataset normalisation the model was trained with.
        config: the ``TrainConfig`` (``schedule``, ``num_timesteps``, ``prediction_type``,
            ``denoiser.point_channels`` / ``num_joints``), as returned by ``load_denoiser``.
        joints: (J, 3) joints in metres, any frame (the samples come out in the same frame).
        num: K clouds. num_points: N points per cloud (any N >= 1).
        sampler: "dpm++" (DPM-Solver++ 2M), "dpm++sde" (its SDE form), "ddim" (eta 0) or "ddpm"
            (ancestral).
        steps: sampler steps (None: ``SAMPLERS[sampler]``: 20 for dpm++, 25 for dpm++sde, 50 for
            ddim, 100 for ddpm).
        seeds: K seeds, one per cloud (None: 0 .. K-1). Cloud k depends only on seeds[k].
        batch_size: clouds denoised together (memory / speed only; results do not depend on it
            beyond float round-off of batched matrix products).
        progress: optional ``callable(done_clouds, K)`` called after each batch.
        clip: clamp the sampler's x0 estimates to [-clip, clip] in normalised units (None: off).
            The data fill about [-4.5, 4.5] (a 1.2 m reach over the 0.26 m std of ``small``), so
            ``clip=5`` only stops stray points of an undertrained model from flying away.
        bf16: run the denoiser under bf16 autocast (its matmuls and attention in bfloat16; the
            sampler's arithmetic and the returned points stay float32). Several times faster on
            CPUs with AMX / avx512_bf16 and on recent GPUs; slower on CPUs without them.
    Returns:
        :class:`SampledClouds` (points (K, N, 3), normals (K, N, 3) or None).
    """
    from pocoloco.diffusion.samplers import PerSampleRNG, sample
    from pocoloco.diffusion.schedules import NoiseSchedule

    den = config.denoiser
    C, J = int(den.point_channels), int(den.num_joints)
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    if num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {num_points}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    seeds = list(range(num)) if seeds is None else [int(s) for s in seeds]
    if len(seeds) != num:
        raise ValueError(f"seeds must have num={num} entries, got {len(seeds)}")
    _check_sampler(sampler, steps, config.num_timesteps)
    joints = _check_joints("joints", joints, J)
    param = next(model.parameters())
    device, dtype = param.device, param.dtype

    _, joints_n = normalisation.normalise(np.zeros((1, 3), np.float32), joints)  # (J, 3) normalised
    root = normalisation.root(joints)  # (3,) metres
    schedule = NoiseSchedule.from_kind(config.schedule, config.num_timesteps)
    kwargs: dict[str, Any] = {"prediction_type": config.prediction_type, "clip": clip}
    if steps is not None or SAMPLERS[sampler] is not None:
        kwargs["steps"] = steps if steps is not None else SAMPLERS[sampler]

    was_training = model.training
    model.eval()
    out = np.empty((num, num_points, C), np.float32)  # (K, N, C) normalised
    try:
        for b0 in range(0, num, batch_size):
            chunk = seeds[b0 : b0 + batch_size]
            rng = PerSampleRNG(chunk, device=device)
            noise = rng.randn((num_points, C), dtype=dtype, device=device)  # (B, N, C)
            cond = torch.as_tensor(joints_n, dtype=dtype, device=device).expand(len(chunk), J, 3)  # (B, J, 3)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                x = sample(sampler, model, schedule, noise, cond, rng=rng, **kwargs)  # (B, N, C)
            out[b0 : b0 + len(chunk)] = x.float().cpu().numpy()
            if progress is not None:
                progress(b0 + len(chunk), num)
    finally:
        model.train(was_training)

    points = normalisation.denormalise(out[..., :3], root.astype(np.float32)).astype(np.float32)  # (K, N, 3)
    normals = None
    if C == 6:
        n = out[..., 3:6]
        normals = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)).astype(np.float32)
    return SampledClouds(points, normals)


# ------------------------------------------------------------------------------------- output
def write_samples(
    out: str | os.PathLike, clouds: SampledClouds, settings: dict[str, Any], render: bool = True
) -> Path:
    """Write ``sample_000.ply`` .. (points + normals if any), ``hypotheses.png`` (every cloud from
    the front and the side, up to 8 clouds per row) and ``sample.json`` (``settings``).

    A new ``out`` folder is filled under a temporary name and renamed into place, so it appears
    complete or not at all. An existing ``out`` folder gets each file replaced atomically;
    ``sample_*.ply`` files of an earlier, larger run are removed. Returns ``out``.
    """
    from pocoloco.data.published import write_ply
    from pocoloco.utils.atomic import write_json_atomic

    out = output_folder(out)
    fresh = not out.exists()
    target = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}" if fresh else out
    K = clouds.points.shape[0]
    try:
        target.mkdir(parents=True, exist_ok=True)
        for k in range(K):
            nrm = None if clouds.normals is None else clouds.normals[k]
            write_ply(target / f"sample_{k:03d}.ply", clouds.points[k], normals=nrm)
        if render:
            from pocoloco.render import render_grid

            panels = [(clouds.points[k], None, None if clouds.normals is None else clouds.normals[k],
                       f"sample {k}") for k in range(K)]  # fmt: skip
            render_grid(panels, target / "hypotheses.png", views=("front", "side"), ncols=min(K, 8))
        write_json_atomic(target / "sample.json", settings)
        if fresh:
            os.replace(target, out)
    except BaseException:
        if fresh:
            shutil.rmtree(target, ignore_errors=True)
        raise
    for p in out.iterdir():  # stale clouds of an earlier run with more samples
        m = _SAMPLE_FILE.match(p.name)
        if m and int(m.group(1)) >= K:
            p.unlink()
    return out


# -------------------------------------------------------------------------------- entry points
def add_sample_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``pocoloco sample`` options to ``parser`` (its handler is :func:`cmd_sample`)."""
    parser.add_argument("--ckpt", default="default",
                        help="checkpoint folder, checkpoints folder or run folder; 'default' (the default) = the "
                             "model shipped with pocoloco")  # fmt: skip
    parser.add_argument("--joints", default="demo:skirt",
                        help="pose: .npy/.npz (24, 3) joints, a LOOSE-style joints .txt, a dataset frame .npz, "
                             "DATASET:subject/split/sequence/index, or demo:skirt|shirt|tight (a shipped pose; "
                             "default demo:skirt). POP / CloSET need the posed body: a dataset frame, or an .npz "
                             "with anny pose parameters joint_rotvecs (24, 3)")  # fmt: skip
    parser.add_argument("--frame-id", type=int, help="line of a joints .txt to use (by frame id; default: first)")
    parser.add_argument("--num", type=int, default=None,
                        help="K hypotheses to draw (default 3; POP / CloSET are deterministic: 1)")  # fmt: skip
    parser.add_argument("--outfit",
                        help="POP / CloSET: outfit name or id (default: the subject of a DATASET:... frame)")  # fmt: skip
    parser.add_argument("--sampler", default="dpm++sde",
                        help=f"one of {', '.join(SAMPLERS)} (default dpm++sde: SDE-DPM-Solver++, 25 steps)")  # fmt: skip
    parser.add_argument("--steps", type=int, help="sampler steps (default: dpm++sde 25, ddpm 100, dpm++ 20, ddim 50; ddpm 1000 = the paper's)")
    parser.add_argument("--points", type=int, default=2048, help="N points per cloud (default 2048; any N works)")
    parser.add_argument("--seed", type=int, default=0, help="cloud k uses seed SEED + k (default 0)")
    parser.add_argument("--batch-size", type=int, default=8, help="clouds denoised together (default 8)")
    parser.add_argument("--raw-weights", action="store_true", help="use the raw weights instead of the EMA")
    parser.add_argument("--bf16", action="store_true",
                        help="denoiser under bf16 autocast: several times faster on CPUs with AMX / avx512_bf16 and on GPUs")
    parser.add_argument("--clip", type=float, default=DEFAULT_CLIP,
                        help=f"clamp the sampler's x0 estimates to [-CLIP, CLIP] normalised units (default {DEFAULT_CLIP}: "
                             "outside the data, which stay within +-3.5 on small; 0 = off)")  # fmt: skip
    parser.add_argument("--no-render", action="store_true", help="skip hypotheses.png")
    parser.add_argument("--device", default=None, help="cuda, cuda:1, cpu (default: cuda if available)")
    parser.add_argument("--out", required=True, help="output folder (sample_000.ply ..., hypotheses.png, sample.json)")


def load_model_from_args(args: argparse.Namespace):
    """(model, normalisation, config, checkpoint path, step) for ``--ckpt``, ``--device``, ``--raw-weights``."""
    from pocoloco.checkpoint import load_denoiser, resolve_checkpoint
    from pocoloco.pretrained import resolve_ckpt_arg

    if args.device is None:
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    else:
        device = torch.device(args.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"--device {args.device}: CUDA is not available")
    ckpt = resolve_checkpoint(resolve_ckpt_arg(args.ckpt))
    model, normalisation, config = load_denoiser(ckpt, use_ema=not args.raw_weights, device=device)
    step = json.loads((ckpt / "meta.json").read_text(encoding="utf-8"))["step"]
    return model, normalisation, config, ckpt, step


def cmd_sample(args: argparse.Namespace) -> None:
    """``pocoloco sample``: validate everything, sample, then write the output folder.

    All user mistakes raise a one-line ValueError before anything is written. A POP / CloSET
    checkpoint goes to :func:`pocoloco.peers.cmd_sample_peer` (one deterministic cloud).
    """
    from pocoloco.peers import PEER_KINDS, checkpoint_kind, cmd_sample_peer

    if args.ckpt != "default" and checkpoint_kind(args.ckpt) in PEER_KINDS:
        return cmd_sample_peer(args)
    if args.outfit is not None:
        raise ValueError("--outfit applies to POP / CloSET checkpoints only (PocoLoco has no outfit codes)")
    if args.num is None:
        args.num = 3
    if args.clip < 0:
        raise ValueError(f"--clip must be >= 0 (0 = off), got {args.clip}")
    for name in ("num", "points", "steps", "batch_size"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if args.sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {args.sampler!r}; choose one of: {', '.join(SAMPLERS)}")
    out = output_folder(args.out)
    model, normalisation, config, ckpt, step = load_model_from_args(args)
    device = next(model.parameters()).device
    joints = load_joints(args.joints, args.frame_id, config.denoiser.num_joints)
    _check_sampler(args.sampler, args.steps, config.num_timesteps)
    num_points = args.points if args.points is not None else config.num_points
    steps = args.steps if args.steps is not None else SAMPLERS[args.sampler]
    seeds = [args.seed + k for k in range(args.num)]

    t0 = time.perf_counter()
    clouds = sample_clouds(model, normalisation, config, joints, args.num, num_points, sampler=args.sampler,
                           steps=args.steps, seeds=seeds, batch_size=args.batch_size,
                           clip=args.clip or None, bf16=args.bf16)  # fmt: skip
    seconds = time.perf_counter() - t0
    settings = {
        "checkpoint": str(ckpt), "step": step, "preset": config.preset, "weights": "raw" if args.raw_weights else "ema",
        "joints": os.fspath(args.joints), "frame_id": args.frame_id, "joints_m": joints.tolist(),
        "sampler": args.sampler, "steps": steps if steps is not None else config.num_timesteps,
        "num": args.num, "points": num_points, "seeds": seeds, "batch_size": args.batch_size, "clip": args.clip or None,
        "bf16": args.bf16, "normals": clouds.normals is not None, "device": str(device), "threads": torch.get_num_threads(),
        "seconds_total": seconds, "seconds_per_sample": seconds / args.num,
    }  # fmt: skip
    write_samples(out, clouds, settings, render=not args.no_render)
    print(f"wrote {args.num} samples of {num_points} points to {out} ({seconds / args.num:.3f} s per sample, "
          f"{args.sampler} {settings['steps']} steps)")  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pocoloco.sample``; same options as ``pocoloco sample``. Exit code 2 on user errors."""
    parser = argparse.ArgumentParser(prog="python -m pocoloco.sample", description=__doc__.splitlines()[0])
    add_sample_arguments(parser)
    args = parser.parse_args(argv)
    from .cli import run_command

    return run_command(cmd_sample, args, prog="pocoloco sample")


if __name__ == "__main__":
    sys.exit(main())
