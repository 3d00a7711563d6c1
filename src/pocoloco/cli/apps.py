"""``pocoloco complete | edit | animate | fit | mesh``: the applications of trained models."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.apps.animation import (
    ANCHORS,
    METHODS,
    animate,
    evaluate_animation,
    load_motion,
)
from pocoloco.apps.common import read_cloud, save_npy, student_chain_start, subset, write_folder
from pocoloco.apps.completion import (
    DEFAULT_CANDIDATES,
    DEFAULT_MAX_COS,
    DEFAULT_RADIUS_M,
    DEFAULT_SAMPLE_T,
    INITS,
    complete,
)
from pocoloco.apps.editing import DEFAULT_THRESHOLD_M, MODES, edit
from pocoloco.apps.fitting import fit_outfit
from pocoloco.apps.meshing import mesh_ply, refine_body_ply
from pocoloco.cli.common import (
    add_app_arguments,
    add_threads_argument,
    check_app_args,
    load_method_from_args,
    pick_outfit,
    progress_bar,
)
from pocoloco.data.motion_window import motion_window
from pocoloco.data.poses import load_joints, subject_of_spec
from pocoloco.data.published import CLOUD_CHECK_HELP, write_ply
from pocoloco.diffusion.samplers import check_sampler
from pocoloco.methods import check_memory, checkpoint_kind
from pocoloco.utils.atomic import jsonable, no_file_reason, write_json_atomic
from pocoloco.viz.render import render_gif, render_grid

__all__ = ["register"]

#: ``--method`` names that stand for a method with an anchor
METHOD_ALIASES = {"chain-world": ("chain", "world"), "chain-root": ("chain", "root")}


# ------------------------------------------------------------------------------------ completion
#: upper bounds of the options that multiply the work (RePaint passes, candidate samples per output)
MAX_RESAMPLE = 100
MAX_CANDIDATES = 64


def add_complete_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco complete`` options."""
    parser.add_argument("--partial", required=True, help="partial scan: .ply (or a dataset frame .npz / (M, 3) .npy); " + CLOUD_CHECK_HELP)
    parser.add_argument("--joints", required=True, help="the scan's pose, as for `pocoloco sample --joints`")
    parser.add_argument("--frame-id", type=int, help="line of a joints .txt to use (by frame id; default: first)")
    parser.add_argument("--points", type=int, default=4096, help="N points per completed cloud (default 4096)")
    parser.add_argument("--num", type=int, default=1, help="K completions to draw (default 1)")
    parser.add_argument("--coverage", type=float, help="share of the N points taken from the scan (default: estimated)")
    parser.add_argument("--coverage-radius", type=float, default=DEFAULT_RADIUS_M,
                        help=f"sample points closer than this (m) to the scan are on the scanned surface, not in a "
                             f"hole (default {DEFAULT_RADIUS_M})")  # fmt: skip
    parser.add_argument("--max-normal-cos", type=float, default=DEFAULT_MAX_COS,
                        help=f"a sample point beyond the radius is a hole point only if its offset from the nearest "
                             f"scan point makes an absolute cosine below this with that point's normal (off-surface points lie "
                             f"along it); 1 = distance only (default {DEFAULT_MAX_COS}; the scan's normals, or "
                             f"estimated from its points)")  # fmt: skip
    parser.add_argument("--candidates", type=int, default=DEFAULT_CANDIDATES,
                        help=f"init sample: draw K full samples and keep the one closest to the visible scan "
                             f"(K x steps network calls; default {DEFAULT_CANDIDATES})")  # fmt: skip
    parser.add_argument("--init", default="sample", choices=INITS,
                        help="generated points start from the chosen sample's hole points, renoised to --t "
                             "(sample, default) or from pure noise (noise: plain RePaint)")  # fmt: skip
    parser.add_argument("--t", type=int, help=f"init sample: start step of the harmonising chain in [0, T], 0 = "
                                              f"none (default {DEFAULT_SAMPLE_T})")  # fmt: skip
    parser.add_argument("--resample", type=int, default=1,
                        help="RePaint resampling: run each --jump steps of the chain this many times (ancestral "
                             "DDPM steps; network calls x this; default 1 = off)")  # fmt: skip
    parser.add_argument("--jump", type=int, default=10, help="RePaint jump length in chain steps (default 10)")
    add_app_arguments(parser, "output folder (completed_000.ply ..., known.npy, completion.png, completion.json)")


def cmd_complete(args: argparse.Namespace) -> None:
    """``pocoloco complete``: validate, complete, write the output folder (nothing on error)."""

    check_app_args(args)
    for name in ("points", "num"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.coverage is not None and not 0.0 <= args.coverage <= 1.0:
        raise ValueError(f"--coverage must be in [0, 1], got {args.coverage}")
    if not 0 < args.coverage_radius < float("inf"):
        raise ValueError(f"--coverage-radius must be a finite number > 0, got {args.coverage_radius}")
    if not 0.0 < args.max_normal_cos <= 1.0:
        raise ValueError(f"--max-normal-cos must be in (0, 1], got {args.max_normal_cos}")
    for name, most in (("candidates", MAX_CANDIDATES), ("resample", MAX_RESAMPLE), ("jump", None)):
        value = getattr(args, name)
        if value < 1 or (most is not None and value > most):
            raise ValueError(f"--{name} must be in [1, {most}], got {value}" if most else f"--{name} must be >= 1, got {value}")
    partial, normals = read_cloud(args.partial)
    method = load_method_from_args(args)
    prior = method.point_prior(pick_outfit(method, args.outfit, args.joints))
    check_memory(method, args.points, args.num * args.candidates)  # K candidates each
    ckpt, step, T = method.path, method.step, prior.schedule.num_timesteps
    joints = load_joints(args.joints, args.frame_id, prior.num_joints, any_pose=args.any_pose)
    check_sampler(args.sampler, args.steps, T)
    if args.t is None and getattr(prior, "student_calls", 0):  # a distilled model: one call of its grid
        args.t = student_chain_start(prior)
    if args.t is not None and not 0 <= args.t <= T:
        raise ValueError(f"--t must be in [0, {T}] (0: no harmonising chain), got {args.t}")
    seeds = [args.seed + k for k in range(args.num)]
    t0 = time.perf_counter()
    comp = complete(prior, partial, joints, args.points, partial_normals=normals,
                    num=args.num, sampler=args.sampler, steps=args.steps, seeds=seeds, coverage=args.coverage,
                    radius=args.coverage_radius, max_cos=args.max_normal_cos, candidates=args.candidates,
                    init=args.init, t=args.t, resample=args.resample, jump=args.jump,
                    name=os.fspath(args.partial))  # fmt: skip
    seconds = time.perf_counter() - t0
    settings = {
        "checkpoint": str(ckpt), "step": step, "partial": os.fspath(args.partial), "partial_points": len(partial),
        "joints": os.fspath(args.joints), "points": args.points, "num": args.num, "sampler": args.sampler,
        "steps": args.steps, "seeds": seeds, "coverage": comp.coverage, "coverage_estimated": comp.coverage_estimated,
        "coverage_radius_m": args.coverage_radius, "max_normal_cos": args.max_normal_cos,
        "normals_estimated": comp.normals_estimated, "num_known": comp.num_known,
        "num_generated": args.points - comp.num_known, "num_known_per_output": comp.known.sum(1).tolist(),
        "init": comp.init, "t": comp.t,
        "resample": args.resample, "jump": args.jump, "candidates": args.candidates,
        "chosen_candidate": comp.chosen.tolist(), "visible_distance_cm": comp.visible_cm.tolist(),
        "method": ("best-of-K sample-initialised inpainting (the hole points of the full sample closest to the "
                   "visible scan, renoised to t and inpainted with the scan kept)" if comp.init == "sample"
                   else "RePaint inpainting from noise"),
        "known_flags": "known.npy: (K, N) bool, True = copied from the scan (the first num_known_per_output[k])",
        "seconds_total": seconds,
    }  # fmt: skip

    def fill(folder: Path) -> set[str]:
        names = set()
        for k in range(args.num):
            nrm = None if comp.normals is None else comp.normals[k]
            write_ply(folder / f"completed_{k:03d}.ply", comp.points[k], normals=nrm)
            names.add(f"completed_{k:03d}.ply")
        save_npy(folder / "known.npy", comp.known)
        names.add("known.npy")
        if not args.no_render:

            show = partial[subset(len(partial), 4 * args.points, [0])]
            panels = [(show, None, None, "partial scan")]
            panels += [(comp.points[k], np.where(comp.known[k], 0, 2), None, f"completed {k} (orange: generated)")
                       for k in range(min(args.num, 4))]  # fmt: skip
            render_grid(panels, folder / "completion.png", views=("front", "side"), ncols=len(panels), joints=joints)
            names.add("completion.png")
        write_json_atomic(folder / "completion.json", jsonable(settings))
        names.add("completion.json")
        return names

    write_folder(args.out, fill, stale=lambda n: n.startswith("completed_") and n.endswith(".ply"))
    print(f"wrote {args.num} completions of {args.points} points ({comp.num_known} from the scan, coverage "
          f"{comp.coverage:.2f}) to {args.out} ({seconds:.1f} s)")  # fmt: skip


# ------------------------------------------------------------------------------------ editing
def add_edit_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco edit`` options."""
    parser.add_argument("--source", required=True, help="source cloud: .ply (or a dataset frame .npz / (M, 3) .npy); " + CLOUD_CHECK_HELP)
    parser.add_argument("--joints", required=True, help="TARGET pose, as for `pocoloco sample --joints`")
    parser.add_argument("--source-joints", help="the source's pose (same forms; needed by --mode region)")
    parser.add_argument("--mode", default="renoise", help="renoise (SDEdit) or region (inpaint the moving parts)")
    parser.add_argument("--t", type=int, help="start step in [1, T]: renoise default 100; region default T "
                                              "(moving points from pure noise)")  # fmt: skip
    parser.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD_M,
                        help=f"region: a joint moved if its root-relative position changed more (m; default "
                             f"{DEFAULT_THRESHOLD_M})")  # fmt: skip
    parser.add_argument("--points", type=int, help="N points per edited cloud (default min(source points, 4096))")
    parser.add_argument("--num", type=int, default=1, help="K edits to draw (default 1)")
    add_app_arguments(parser, "output folder (edited_000.ply ..., regenerated.npy, edit.png, edit.json)")


def cmd_edit(args: argparse.Namespace) -> None:
    """``pocoloco edit``: validate, edit, write the output folder (nothing on error)."""

    check_app_args(args)
    if args.mode not in MODES:
        raise ValueError(f"unknown --mode {args.mode!r}; choose one of: {', '.join(MODES)}")
    if args.mode == "region" and args.source_joints is None:
        raise ValueError("--mode region needs --source-joints (the source cloud's pose)")
    for name in ("points", "num"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise ValueError(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not 0 < args.threshold < float("inf"):
        raise ValueError(f"--threshold must be a finite number > 0 (metres), got {args.threshold}")
    source, normals = read_cloud(args.source)
    method = load_method_from_args(args)
    prior = method.point_prior(pick_outfit(method, args.outfit, args.joints))
    check_memory(method, args.points or min(len(source), 4096), args.num)
    ckpt, step, T, J = method.path, method.step, prior.schedule.num_timesteps, prior.num_joints
    target = load_joints(args.joints, None, J, any_pose=args.any_pose)
    src_joints = None if args.source_joints is None else load_joints(args.source_joints, None, J, any_pose=args.any_pose)
    check_sampler(args.sampler, args.steps, T)
    if args.t is None and getattr(prior, "student_calls", 0) and args.mode in (None, "renoise"):  # its grid
        args.t = student_chain_start(prior)
    if args.t is not None and not 1 <= args.t <= T:
        raise ValueError(f"--t must be in [1, {T}] (the model's training timesteps), got {args.t}")
    seeds = [args.seed + k for k in range(args.num)]
    t0 = time.perf_counter()
    res = edit(prior, source, target, source_joints=src_joints, source_normals=normals,
               mode=args.mode, t=args.t, num_points=args.points, num=args.num, sampler=args.sampler, steps=args.steps,
               seeds=seeds, threshold=args.threshold, name=os.fspath(args.source))  # fmt: skip
    seconds = time.perf_counter() - t0
    N = res.points.shape[1]
    settings = {
        "checkpoint": str(ckpt), "step": step, "source": os.fspath(args.source), "joints": os.fspath(args.joints),
        "source_joints": args.source_joints, "mode": args.mode, "t": res.t, "points": N, "num": args.num,
        "sampler": args.sampler, "steps": args.steps, "seeds": seeds, "threshold_m": args.threshold,
        "moved_joints": None if res.moved_joints is None else np.flatnonzero(res.moved_joints).tolist(),
        "regenerated_share": float(res.regenerated.mean()), "seconds_total": seconds,
        "regenerated_flags": "regenerated.npy: (K, N) bool, True = generated, False = kept from the source",
    }  # fmt: skip

    def fill(folder: Path) -> set[str]:
        names = {"regenerated.npy", "edit.json"}
        for k in range(args.num):
            nrm = None if res.normals is None else res.normals[k]
            write_ply(folder / f"edited_{k:03d}.ply", res.points[k], normals=nrm)
            names.add(f"edited_{k:03d}.ply")
        save_npy(folder / "regenerated.npy", res.regenerated)
        if not args.no_render:

            show = source[subset(len(source), 4 * N, [0])]
            panels = [(show, None, None, "source")]
            for k in range(min(args.num, 4)):
                lab = np.where(res.regenerated[k], 2, 0) if args.mode == "region" else None
                panels.append((res.points[k], lab, None, f"edit {k}" + (" (orange: new)" if lab is not None else "")))
            render_grid(panels, folder / "edit.png", views=("front", "side"), ncols=len(panels),
                        joints=[src_joints] + [target] * (len(panels) - 1))  # fmt: skip
            names.add("edit.png")
        write_json_atomic(folder / "edit.json", jsonable(settings))
        return names

    write_folder(args.out, fill, stale=lambda n: n.startswith("edited_") and n.endswith(".ply"))
    print(f"wrote {args.num} {args.mode} edits of {N} points (t={res.t}, {100 * res.regenerated.mean():.0f}% "
          f"regenerated) to {args.out} ({seconds:.1f} s)")  # fmt: skip


# ------------------------------------------------------------------------------------ animation
def _parse_frames(text: str | None, total: int) -> list[int]:
    """``START:STOP[:STEP]`` (Python slice syntax, any part optional) -> frame indices."""
    if text is None:
        return list(range(total))
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        vals = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise ValueError(f"--frames {text!r}: expected START:STOP[:STEP], e.g. 0:40:2") from None
    if len(vals) == 3 and vals[2] is not None and vals[2] < 1:
        raise ValueError(f"--frames {text!r}: STEP must be >= 1")
    idx = list(range(total))[slice(*vals)]
    if not idx:
        raise ValueError(f"--frames {text!r} selects no frame of the {total}")
    return idx


def add_animate_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco animate`` options."""
    parser.add_argument("--motion", required=True,
                        help="(T, 24, 3) joints .npy / .npz, or a dataset sequence "
                             "DATASET:subject/split/sequence")  # fmt: skip
    parser.add_argument("--method", default="chain",
                        help="independent, shared-noise, chain (default) or chain-world (= chain --anchor world, "
                             "the recommended one: least flicker at equal accuracy, BENCHMARKS.md)")  # fmt: skip
    parser.add_argument("--t", type=int, default=None, help="chain: renoising step of each new frame (default 200; a "
                        "distilled model: 250, one network call per frame)")  # fmt: skip
    parser.add_argument("--anchor", default=None, help="chain: carry the previous frame root-relative (root, "
                                                       "default) or in world coordinates (world)")  # fmt: skip
    parser.add_argument("--points", type=int, default=2048, help="N points per frame (default 2048)")
    parser.add_argument("--frames", help="frames to animate, START:STOP[:STEP] (default: all)")
    parser.add_argument("--fps", type=float, default=10.0, help="GIF frame rate (default 10)")
    parser.add_argument("--no-polish", action="store_true",
                        help="a distilled model whose teacher makes the last call (default:fast): each frame with "
                             "the student's call alone (one network call per chained frame instead of two)")  # fmt: skip
    parser.add_argument("--motion-fps", type=float, default=25.0,
                        help="frames per second of a --motion joints file, for models trained with --motion-window "
                             "(each frame gets the motion before it; dataset sequences know theirs; default 25)")  # fmt: skip
    add_app_arguments(parser, "output folder (frame_0000.ply ..., animation.gif, animation.json)")


def cmd_animate(args: argparse.Namespace) -> None:
    """``pocoloco animate``: validate, animate, write the output folder (nothing on error)."""

    check_app_args(args)
    if args.method in METHOD_ALIASES:  # chain-world = chain --anchor world
        method_name, anchor = METHOD_ALIASES[args.method]
        if args.anchor not in (None, anchor):
            raise ValueError(f"--method {args.method} means --anchor {anchor}; got --anchor {args.anchor}")
        args.method, args.anchor = method_name, anchor
    if args.anchor is None:
        args.anchor = "root"
    if args.method not in METHODS:
        raise ValueError(f"unknown --method {args.method!r}; choose one of: {', '.join([*METHODS, *METHOD_ALIASES])}")
    if args.anchor not in ANCHORS:
        raise ValueError(f"unknown --anchor {args.anchor!r}; choose one of: {', '.join(ANCHORS)}")
    if args.points < 1:
        raise ValueError(f"--points must be >= 1, got {args.points}")
    if not 0 < args.fps <= 1000:
        raise ValueError(f"--fps must be in (0, 1000], got {args.fps}")
    if not 0 < args.motion_fps <= 1000:
        raise ValueError(f"--motion-fps must be in (0, 1000], got {args.motion_fps}")
    method = load_method_from_args(args)
    outfit = pick_outfit(method, args.outfit, args.motion)
    hook = method.animation_prior(outfit, args.points)
    prior = hook.prior
    ckpt, step, T = method.path, method.step, prior.schedule.num_timesteps
    motion = load_motion(args.motion, prior.num_joints, any_pose=args.any_pose)
    chosen = _parse_frames(args.frames, len(motion.joints))
    finish = None
    if hook.finish is not None:  # the frames need their posed bodies (the hybrid)
        if motion.frames is None:
            raise ValueError(f"--motion {args.motion}: {method.title} animates dataset sequences only "
                             "(DATASET:subject/split/sequence): it needs each frame's posed body")  # fmt: skip
        subject = subject_of_spec(motion.name)
        poses = {k: method.pose_from_frame(motion.frames[i], subject) for k, i in enumerate(chosen)}
        finish = lambda k, points, seed: hook.finish(poses[k], points, seed)  # noqa: E731
    student = getattr(prior, "student_calls", 0)  # a distilled model: its few-step sampler, grid steps
    if args.t is None:
        args.t = student_chain_start(prior) if student else 200
    if not student:
        check_sampler(args.sampler, args.steps, T)
    if not 1 <= args.t <= T:
        raise ValueError(f"--t must be in [1, {T}] (the model's training timesteps), got {args.t}")
    joints = motion.joints[chosen]
    windows = None
    if method.motion_window:  # each frame its own window: the dataset's motion, or the given joints' at --fps
        windows = ([method.motion_of_frame(motion.frames[i]) for i in chosen] if motion.frames is not None else
                   [motion_window(motion.joints, i, args.motion_fps, method.motion_window) for i in chosen])  # fmt: skip
    check_memory(method, args.points, len(chosen))  # every frame is kept
    t0 = time.perf_counter()
    with progress_bar("animate", total=len(chosen)) as update:
        anim = animate(prior, joints, hook.prior_points, method=args.method, t=args.t,
                       sampler=args.sampler, steps=args.steps, seed=args.seed, anchor=args.anchor,
                       finish=finish, progress=update, windows=windows, polish=not args.no_polish)  # fmt: skip
    seconds = time.perf_counter() - t0
    polished = student and prior.polish is not None and not args.no_polish
    info: dict[str, Any] = {
        "checkpoint": str(ckpt), "step": step, "motion": motion.name, "frames": chosen, "method": args.method,
        "t": args.t if args.method == "chain" else None, "anchor": args.anchor if args.method == "chain" else None,
        "points": args.points, "sampler": "few-step" if student else args.sampler, "steps": args.steps, "seeds": anim.seeds,
        "seconds_total": seconds, "seconds_per_frame": seconds / len(chosen),
        "motion_window_s": method.motion_window, "polish_t": prior.polish[1] if polished else None,
    }  # fmt: skip
    if motion.frames is not None:
        info["metrics"] = evaluate_animation(anim.points, [motion.frames[i] for i in chosen], args.points)

    def fill(folder: Path) -> set[str]:
        names = {"animation.json"}
        for k in range(len(chosen)):
            write_ply(folder / f"frame_{k:04d}.ply", anim.points[k],
                      normals=None if anim.normals is None else anim.normals[k])  # fmt: skip
            names.add(f"frame_{k:04d}.ply")
        if not args.no_render:
            render_gif(anim.points, folder / "animation.gif", fps=args.fps, joints=joints)
            names.add("animation.gif")
        write_json_atomic(folder / "animation.json", jsonable(info))
        return names

    write_folder(args.out, fill, stale=lambda n: n.startswith("frame_") and n.endswith(".ply"))
    msg = f"wrote {len(chosen)} frames ({args.method}) of {args.points} points to {args.out} ({seconds:.1f} s)"
    if "metrics" in info:
        m = info["metrics"]
        msg += (f"; flicker {m['flicker_mean_cm']:.2f} cm (GT {m['gt_flicker_mean_cm']:.2f}), Chamfer to GT "
                f"{m['chamfer_to_gt_mean_cm']:.2f} cm")  # fmt: skip
    print(msg)


# ----------------------------------------------------------------------------------------- fit
def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco fit`` options."""
    parser.add_argument("--model", choices=("pop", "pocoloco", "hybrid"),
                        help="the kind --ckpt must be (checked; default: whatever it is): POP fits its geometric "
                             "features to one scan (paper Sec. 3.3), PocoLoco trained with --outfit-codes an outfit "
                             "code to one or a few scans")  # fmt: skip
    parser.add_argument("--ckpt", required=True, help="trained POP or PocoLoco checkpoint / run folder")
    parser.add_argument("--scan", required=True, nargs="+",
                        help="PLY(s) of the unseen outfit (world frame of the matching --frame; POP needs normals); "
                             + CLOUD_CHECK_HELP)  # fmt: skip
    parser.add_argument("--frame", required=True, nargs="+",
                        help="DATASET:subject/split/sequence/index per --scan: the body and pose it was taken in")  # fmt: skip
    parser.add_argument("--name", help="name of the new outfit (default: the first scan file's stem)")
    parser.add_argument("--steps", type=int, default=400, help="Adam steps (default 400, as the POP paper)")
    parser.add_argument("--lr", type=float, help="learning rate (default: POP's feature lr; PocoLoco 1e-2)")
    parser.add_argument("--points", type=int, help="scan points per cloud used by the loss (default: the model's)")
    parser.add_argument("--start", choices=("nearest", "mean"), default="nearest",
                        help="start code: the trained outfit nearest to the first scan (default) or the mean of the "
                             "trained outfits (POP paper)")  # fmt: skip
    parser.add_argument("--anchor", type=float, default=0.0,
                        help="PocoLoco: weight of an L2 pull of the code to its start (default 0)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="seed of the scan points used and scored (default 0)")
    add_threads_argument(parser)
    parser.add_argument("--out", required=True, help="new folder: the checkpoint with the added outfit + fit.json")


def cmd_fit(args: argparse.Namespace) -> None:
    if len(args.scan) != len(args.frame):
        raise ValueError(f"give one --frame per --scan: {len(args.scan)} scans, {len(args.frame)} frames")
    if args.model is not None:
        kind = checkpoint_kind(args.ckpt)
        if kind != args.model:
            raise ValueError(f"--ckpt {args.ckpt}: checkpoint is of model {kind!r}, expected {args.model!r} (--model)")
    with progress_bar("fit", total=args.steps, loss=True) as update:
        rep = fit_outfit(args.ckpt, list(zip(args.scan, args.frame)), args.out, name=args.name, steps=args.steps,
                         lr=args.lr, num_points=args.points, seed=args.seed, start=args.start, anchor=args.anchor,
                         progress=lambda d, n, loss: update(d, loss=f"{loss:.3f}"))  # fmt: skip
    b, nb, a = rep.before_start, rep.before_nearest, rep.after
    print(f"outfit {rep.outfit!r} (id {rep.outfit_id}) fitted in {rep.seconds:.1f} s: Chamfer {b['chamfer_cm']:.2f} cm "
          f"(start: {rep.start}) / {nb['chamfer_cm']:.2f} cm (nearest trained outfit {rep.nearest_outfit!r}) -> "
          f"{a['chamfer_cm']:.2f} cm; CD {b['pop_chamfer_e-4m2']:.2f} -> {a['pop_chamfer_e-4m2']:.2f} 1e-4 m^2")  # fmt: skip
    print(f"wrote {rep.checkpoint} and {Path(args.out) / 'fit.json'}; pose it with "
          f"`pocoloco sample --ckpt {args.out} --outfit {rep.outfit} --joints DATASET:subject/split/sequence/index`")


# ---------------------------------------------------------------------------------------- mesh
def add_mesh_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco mesh`` options."""
    parser.add_argument("input", help="point cloud .ply (normals used when present, estimated otherwise); " + CLOUD_CHECK_HELP)
    parser.add_argument("--out", help="mesh .ply to write (default: INPUT_mesh.ply next to the input)")
    parser.add_argument("--depth", type=int, default=8, help="Poisson octree depth (default 8; +1 ~ 4x the faces)")
    parser.add_argument("--density-quantile", type=float, default=0.0,
                        help="trim at most this fraction of lowest-density vertices, those also > 4 sample "
                             "spacings from any point (Poisson's filling of holes in the cloud); 0 = keep all, "
                             "watertight (the default); e.g. 0.02 trims a skirt hem's bridging surface")  # fmt: skip
    parser.add_argument("--knn", type=int, default=30, help="neighbours for normal estimation (default 30)")
    parser.add_argument("--render", help="also write a PNG of the mesh (front and side views)")
    parser.add_argument("--refine-body", action="store_true",
                        help="fit the anny body to the cloud and replace its head and hands by the body's "
                             "before meshing (PocoLoco appendix A.2); needs --joints")  # fmt: skip
    parser.add_argument("--joints", help="the cloud's pose, as for `pocoloco sample --joints`: estimated normals face away "
                        "from its bones (no Poisson balloons on hands and feet); needed by --refine-body")  # fmt: skip
    parser.add_argument("--frame-id", type=int, help="line of a joints .txt to use (by frame id; default: first)")
    parser.add_argument("--body-out", help="--refine-body: fitted body mesh .ply (default: OUT_body.ply)")
    parser.add_argument("--fit-steps", type=int, default=150, help="--refine-body: Adam steps per stage (default 150)")


def cmd_mesh(args: argparse.Namespace) -> None:
    """``pocoloco mesh``: reconstruct, write, print sizes and watertightness."""
    src = Path(args.input)
    out = Path(args.out) if args.out else src.with_name(src.stem + "_mesh.ply")
    if out.resolve() == src.resolve():
        raise ValueError(f"--out {out}: would overwrite the input")
    if out.is_dir():
        raise ValueError(f"--out {out}: is a folder")
    if args.knn < 3:
        raise ValueError(f"--knn must be >= 3 (neighbours for a normal), got {args.knn}")
    if args.fit_steps < 1:
        raise ValueError(f"--fit-steps must be >= 1, got {args.fit_steps}")
    if args.refine_body:
        _cmd_refine(args, src, out)
        return
    joints = None if args.joints is None else load_joints(args.joints, args.frame_id)
    r = mesh_ply(src, out, depth=args.depth, density_quantile=args.density_quantile, render=args.render,
                 knn=args.knn, joints=joints)  # fmt: skip
    closed = "watertight" if r.watertight else (
        "NOT watertight (trimmed where the cloud has holes; --density-quantile 0 keeps it closed)")
    print(f"wrote {out}: {r.num_vertices} vertices, {r.num_faces} faces, {closed}, {r.seconds:.1f} s"
          + (f"; render {args.render}" if args.render else ""))  # fmt: skip


def _cmd_refine(args: argparse.Namespace, src: Path, out: Path) -> None:
    """``pocoloco mesh --refine-body``: validate, fit + replace + mesh with a progress bar, report."""
    if args.joints is None:
        raise ValueError("--refine-body needs --joints (the pose the cloud was generated for)")
    if args.fit_steps < 1:
        raise ValueError(f"--fit-steps must be >= 1, got {args.fit_steps}")
    body_out = Path(args.body_out) if args.body_out else out.with_name(out.stem + "_body.ply")
    if body_out.resolve() in (src.resolve(), out.resolve()):
        raise ValueError(f"--body-out {body_out}: would overwrite the input or the mesh")
    if not src.is_file():
        raise ValueError(f"{src}: {no_file_reason(src)}")
    joints = load_joints(args.joints, args.frame_id)
    with progress_bar("fitting the body", total=2 * args.fit_steps) as update:
        r = refine_body_ply(src, out, joints, body_out, depth=args.depth, density_quantile=args.density_quantile,
                            render=args.render, fit_steps=args.fit_steps, knn=args.knn,
                            progress=lambda done, total: update(done))  # fmt: skip
    m, f = r.mesh, r.fit
    closed = "watertight" if m.watertight else "NOT watertight"
    print(f"fitted anny: joints {f.joint_error_cm:.2f} cm off, head/hands Chamfer {f.part_error_cm_initial:.2f} -> "
          f"{f.part_error_cm:.2f} cm; replaced {r.removed} head/hand points by {r.added} body points")  # fmt: skip
    print(f"wrote {out}: {m.num_vertices} vertices, {m.num_faces} faces, {closed}, {m.seconds:.1f} s; body {body_out}"
          + (f"; render {args.render}" if args.render else ""))  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("complete", help="complete a partial scan with the model (inpainting; PLY + PNG + JSON)")
    add_complete_arguments(s)
    s.set_defaults(func=cmd_complete)
    s = sub.add_parser("edit", help="move a cloud to a new pose (renoise or regenerate the moving region)")
    add_edit_arguments(s)
    s.set_defaults(func=cmd_edit)
    s = sub.add_parser("animate", help="clouds for a motion (independent / shared-noise / chain; PLYs + GIF + JSON)")
    add_animate_arguments(s)
    s.set_defaults(func=cmd_animate)
    s = sub.add_parser("fit", help="fit a new outfit to one scan (POP: only its geometric features) -> new checkpoint")
    add_fit_arguments(s)
    s.set_defaults(func=cmd_fit)
    s = sub.add_parser("mesh", help="watertight mesh from a point cloud PLY (screened Poisson reconstruction)")
    add_mesh_arguments(s)
    s.set_defaults(func=cmd_mesh)
