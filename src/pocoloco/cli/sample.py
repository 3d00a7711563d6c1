"""``pocoloco sample``: clouds for one pose from any checkpoint (PLYs, a PNG, ``sample.json``)."""

from __future__ import annotations

import argparse
import os
import time
import warnings

import torch

from pocoloco.cli.common import (
    add_any_pose_argument,
    add_bf16_argument,
    add_even_argument,
    add_finish_argument,
    add_device_argument,
    add_threads_argument,
    load_method_from_args,
    pick_outfit,
    resolve_bf16,
    steps_defaults,
)
from pocoloco.data.dataset import DEFAULT_FPS
from pocoloco.data.motion_window import DEFAULT_SECONDS
from pocoloco.data.poses import load_motion, pose_spec_kind
from pocoloco.diffusion.samplers import SAMPLER_STEPS
from pocoloco.methods import SamplerOptions, fit_to_memory, predict_clouds
from pocoloco.methods.outputs import write_samples
from pocoloco.methods.pocoloco.sampling import DEFAULT_CLIP
from pocoloco.utils.atomic import output_folder

__all__ = ["register"]


def cmd_sample(args: argparse.Namespace) -> None:
    """Validate everything (one-line errors before anything is written), sample, write the folder."""
    for name in ("num", "points", "steps", "batch_size"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if args.clip < 0:
        raise ValueError(f"--clip must be >= 0 (0 = off), got {args.clip}")
    if args.motion is not None and args.joints is not None:
        raise ValueError("--motion and --joints exclude each other (the motion's last frame is the pose)")
    if args.fps is not None and args.motion is None:
        raise ValueError("--fps applies to --motion only")
    out = output_folder(args.out)
    method = load_method_from_args(args)
    spec = os.fspath(args.motion if args.motion is not None else args.joints or "demo:skirt")
    if method.deterministic:
        if args.num is not None and args.num != 1:
            raise ValueError(f"--num {args.num}: {method.title} is deterministic (one cloud per pose and outfit); "
                             "use --num 1")  # fmt: skip
        num = 1
        if args.steps is not None or args.sampler != "dpm++sde" or args.finish_t is not None:
            warnings.warn(f"{method.title} is deterministic: --sampler / --steps / --finish-t do not apply and are "
                          "ignored")  # fmt: skip
    else:
        num = 3 if args.num is None else args.num
    options = SamplerOptions(sampler=args.sampler, steps=args.steps, clip=args.clip or None,
                             bf16=resolve_bf16(args.bf16, method.device),
                             batch_size=args.batch_size, even=args.even,
                             finish_t=None if method.deterministic else args.finish_t)  # fmt: skip
    if not method.deterministic and args.sampler not in SAMPLER_STEPS:
        raise ValueError(f"unknown sampler {args.sampler!r}; choose one of: {', '.join(SAMPLER_STEPS)}")
    notes = []
    if args.motion is not None:
        if method.needs_body:
            raise ValueError(f"--motion gives joints only; {method.title} needs the posed body (a DATASET: frame or "
                             "demo:OUTFIT with --joints)")  # fmt: skip
        fps = DEFAULT_FPS if args.fps is None else args.fps
        pose, note = load_motion(spec, fps, method.motion_window or DEFAULT_SECONDS, any_pose=args.any_pose)
        notes += [note] if note else []
        notes += [] if args.fps is not None else [f"--motion read at {fps:g} frames per second (give --fps)"]
        outfit = pick_outfit(method, args.outfit, spec)
    elif method.needs_body:  # the body is posed with the outfit's phenotype
        pose_spec_kind(spec)  # bare joints: the one-line error first
        outfit = pick_outfit(method, args.outfit, spec)
        pose = method.load_pose(spec, outfit, args.frame_id, any_pose=args.any_pose)
    else:  # a bad joints file is named before a missing --outfit
        pose = method.load_pose(spec, None, args.frame_id, any_pose=args.any_pose)
        outfit = pick_outfit(method, args.outfit, spec)
    if method.motion_window and pose.motion is None:
        notes.append(f"{spec}: no motion before this pose: the body is taken at rest (give --motion FILE or a "
                     "DATASET: frame)")  # fmt: skip
    elif not method.motion_window and args.motion is not None:
        notes.append(f"{method.title} ({method.path}) sees the pose alone: the motion before it is not used")
    method.check_options(options)
    options = fit_to_memory(method, args.points, num, options)
    seeds = [args.seed + k for k in range(num)]

    t0 = time.perf_counter()
    clouds = predict_clouds(method, pose, args.points, seeds, outfit, options)
    seconds = time.perf_counter() - t0
    settings = {
        "checkpoint": str(method.path), "model_kind": method.kind, "model": method.title, "step": method.step,
        "preset": method.config.preset, "joints": spec, "motion_window_s": method.motion_window,
        "motion": "none (at rest)" if pose.motion is None else "given", "frame_id": args.frame_id, "joints_m": pose.joints.tolist(),
        "num": num, "points": args.points, "seed": args.seed, "seeds": seeds, "deterministic": method.deterministic, "even": args.even,
        **method.sample_settings(options, args.points),
    }  # fmt: skip
    if outfit is not None:
        settings.update(outfit=method.outfit_names()[outfit], outfit_id=outfit, body_source=pose.source)
    settings.update(normals=clouds.normals is not None, device=str(method.device), threads=torch.get_num_threads(),
                    seconds_total=seconds, seconds_per_sample=seconds / num)  # fmt: skip
    write_samples(out, clouds, settings, render=not args.no_render, pose=pose)
    what = f"{num} samples" if not method.deterministic else f"1 {method.title} cloud"
    how = (f"{settings.get('sampler', args.sampler)} {settings['steps']} steps" if "steps" in settings
           else f"outfit {method.outfit_names()[outfit]}" if outfit is not None else method.title)  # fmt: skip
    if settings.get("finish_t") is not None:
        how += f" + its own call at step {settings['finish_t']}"
    for note in notes:
        print(f"note: {note}")
    print(f"wrote {what} of {args.points} points to {out} ({seconds / num:.3f} s per sample, {how})")


def add_sample_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco sample`` options."""
    parser.add_argument("--ckpt", default="default",
                        help="checkpoint folder, checkpoints folder or run folder of any model; 'default' (the "
                             "default) = the PocoLoco model shipped with pocoloco (latent denoiser, trained on medium), "
                             "default:pop / default:closet its shipped peers, default:hybrid the hybrid of POP and it, "
                             "default:fast / default:hybrid-fast the same in 4 network calls (a distilled student)")  # fmt: skip
    parser.add_argument("--joints", default=None,
                        help="pose: .npy/.npz (24, 3) joints, a LOOSE-style joints .txt, a dataset frame .npz, "
                             "DATASET:subject/split/sequence/index, or demo:OUTFIT (a shipped pose, one per outfit: "
                             "demo:skirt_a ... demo:trousers_b; demo:skirt = demo:skirt_a; default demo:skirt). POP / "
                             "CloSET need the posed body: a dataset frame, demo:OUTFIT, or an .npz with anny pose "
                             "parameters joint_rotvecs (24, 3)")  # fmt: skip
    parser.add_argument("--motion", metavar="FILE",
                        help="a joints sequence .npy / .npz (T, 24, 3), metres, z up: its last frame is the pose and "
                             "a --motion-window model also sees the motion before it (instead of --joints)")  # fmt: skip
    parser.add_argument("--fps", type=float, help="frames per second of --motion (default 25)")
    parser.add_argument("--frame-id", type=int, help="line of a joints .txt to use (by frame id; default: first)")
    parser.add_argument("--num", type=int, default=None,
                        help="K hypotheses to draw (default 3; POP / CloSET are deterministic: 1)")  # fmt: skip
    parser.add_argument("--outfit",
                        help="models with outfits (POP, CloSET, PocoLoco --outfit-codes): outfit name or id (default: the "
                             "subject of a DATASET:... frame, or the outfit a demo:NAME pose was captured on)")  # fmt: skip
    parser.add_argument("--sampler", default="dpm++sde",
                        help=f"one of {', '.join(SAMPLER_STEPS)} (default dpm++sde: SDE-DPM-Solver++, {SAMPLER_STEPS['dpm++sde']} steps)")  # fmt: skip
    parser.add_argument("--steps", type=int,
                        help=f"sampler steps (default: {steps_defaults()}; ddpm 1000 = the paper's)")  # fmt: skip
    parser.add_argument("--points", type=int, default=2048, help="N points per cloud (default 2048; any N works)")
    add_even_argument(parser)
    add_finish_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="cloud k uses seed SEED + k (default 0)")
    parser.add_argument("--batch-size", type=int, default=8, help="clouds denoised together (default 8)")
    parser.add_argument("--raw-weights", action="store_true", help="use the raw weights instead of the EMA")
    add_any_pose_argument(parser)
    add_bf16_argument(parser)
    parser.add_argument("--clip", type=float, default=DEFAULT_CLIP,
                        help=f"clamp the sampler's x0 estimates to [-CLIP, CLIP] normalised units (default {DEFAULT_CLIP}: "
                             "outside the data, which stay within +-3.5 on small; 0 = off)")  # fmt: skip
    parser.add_argument("--no-render", action="store_true", help="skip hypotheses.png")
    add_device_argument(parser)
    add_threads_argument(parser)
    parser.add_argument("--out", required=True, help="output folder (sample_000.ply ..., hypotheses.png, sample.json)")


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("sample", help="sample clouds for a pose from a trained checkpoint (PLY + PNG)")
    add_sample_arguments(s)
    s.set_defaults(func=cmd_sample)
