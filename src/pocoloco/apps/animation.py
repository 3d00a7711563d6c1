"""Animation: a sequence of clouds for a motion (T poses), and a flicker metric.

Methods (frame k has pose joints[k]; ``seed`` the base seed):

* ``independent``: frame k is sampled from scratch with seed ``seed + k`` (no coherence);
* ``shared-noise``: every frame is sampled from the same initial noise (seed ``seed``), so the
  deterministic sampler maps nearby poses to nearby clouds;
* ``chain``: frame 0 is sampled from scratch; frame k starts from frame k-1's result, renoised
  to step ``t`` (SDEdit, Meng et al. 2022; default t = 200 of 1000) and denoised under pose k
  (seed ``seed + k``). Point i of frame k descends from point i of frame k-1, so the sequence
  is coherent. ``anchor="root"`` (default) carries frame k-1 root-relative (it moves with the
  root: normalised with frame k-1's root, denormalised with frame k's); ``anchor="world"``
  keeps its world position (normalised with frame k's root) and lets the denoiser follow.

Flicker metric (:func:`flicker_cm`): for consecutive frames, frame k's points are moved by the
body motion, each with the displacement of its nearest posed-body vertex from frame k to k+1
(:func:`warp_by_body`), and compared with frame k+1 (PocoLoco Chamfer, cm). 0 for a cloud that
moves exactly like the body; the ground truth's own value (different scan subsets per frame) is
the floor to compare with.

Public API: :func:`load_motion`, :func:`animate`, :func:`warp_by_body`, :func:`flicker_cm`,
:func:`render_gif`, :func:`evaluate_animation`; CLI pieces :func:`add_animate_arguments` /
:func:`cmd_animate` (``pocoloco animate``).
"""

from __future__ import annotations

import argparse
import io
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pocoloco.apps._common import (add_common_arguments, check_common_args, denoise_from, jsonable,
                                   load_model_from_args, subset, to_metres, to_normalised, write_folder)  # fmt: skip
from pocoloco.data.dataset import Normalisation

__all__ = ["METHODS", "Animation", "MotionInput", "add_animate_arguments", "animate", "cmd_animate",
           "evaluate_animation", "flicker_cm", "load_motion", "render_gif", "warp_by_body"]  # fmt: skip

METHODS = ("independent", "shared-noise", "chain")
ANCHORS = ("root", "world")


@dataclass
class MotionInput:
    """joints: (T, J, 3) float32 metres. frames: the dataset frame file of each pose, or None
    (a joints array was given). name: the spec it was read from."""

    joints: np.ndarray
    frames: list[Path] | None
    name: str


@dataclass
class Animation:
    """points: (T, N, 3) float32 metres. normals: (T, N, 3) or None. seeds: (T,) seed of each frame."""

    points: np.ndarray
    normals: np.ndarray | None
    seeds: list[int]


# --------------------------------------------------------------------------------------- motion
def load_motion(spec: str | os.PathLike, num_joints: int = 24) -> MotionInput:
    """Read a motion: a (T, J, 3) joints ``.npy`` (or ``.npz`` with a ``joints`` array), or a
    dataset sequence ``DATASET:subject/split/sequence`` (the joints of every stored frame).

    Raises one-line ValueErrors: no such file / sequence, wrong shape, a skeleton with another
    joint count than the model's, NaN / inf.
    """
    from pocoloco.data import format as fmt

    spec = os.fspath(spec)
    path = Path(spec)
    if path.is_file():
        try:
            loaded = np.load(path, allow_pickle=False)
            if hasattr(loaded, "files"):
                with loaded as z:
                    if "joints" not in z.files:
                        raise ValueError(f"{spec}: npz has no 'joints' array")
                    arr = z["joints"]
            else:
                arr = np.asarray(loaded)
        except ValueError as e:
            if str(e).startswith(spec):
                raise
            raise ValueError(f"{spec}: cannot read joints ({type(e).__name__})") from None
        except Exception as e:
            raise ValueError(f"{spec}: cannot read joints ({type(e).__name__})") from None
        frames = None
    elif ":" in spec:
        root, _, key = spec.rpartition(":")
        parts = key.strip("/").split("/")
        if len(parts) != 3:
            raise ValueError(f"{spec}: expected DATASET:subject/split/sequence, got {key!r}")
        subject, split, sequence = parts
        fmt.read_card(root)
        if split not in fmt.SPLITS:
            raise ValueError(f"{spec}: unknown split {split!r}; expected one of {fmt.SPLITS}")
        layout = fmt.DatasetLayout(root)
        idx = layout.frame_indices(subject, split, sequence)
        if not idx:
            raise ValueError(f"{spec}: no such sequence (or it has no frames)")
        frames = [layout.frame_path(subject, split, sequence, i) for i in idx]
        arr = np.stack([fmt.read_frame(p, ["joints"]).joints for p in frames])
    else:
        raise ValueError(f"{spec}: no such motion file (or DATASET:subject/split/sequence)")
    if arr.dtype.kind not in "fiu" or arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1:
        raise ValueError(f"{spec}: expected joints of shape (T, {num_joints}, 3), got {arr.shape}")
    if arr.shape[1] != num_joints:
        raise ValueError(f"{spec}: the skeleton has {arr.shape[1]} joints, the model expects {num_joints}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{spec}: joints contain NaN or inf")
    return MotionInput(arr.astype(np.float32), frames, spec)


# -------------------------------------------------------------------------------------- animate
def animate(
    model,
    normalisation: Normalisation,
    config: Any,
    joints: np.ndarray,
    num_points: int,
    *,
    method: str = "chain",
    t: int = 200,
    sampler: str = "dpm++sde",
    steps: int | None = None,
    seed: int = 0,
    seeds: Sequence[int] | None = None,
    anchor: str = "root",
    progress: Callable[[int, int], None] | None = None,
) -> Animation:
    """Clouds (T, N, 3) for the poses ``joints`` (T, J, 3) (module docstring for the methods).

    seeds: per-frame seeds overriding the method's (``seed + k``, or ``seed`` for every frame
    with shared-noise). t: chain's renoising step in [1, T_train] (steps: that chain's steps,
    at most t; from-scratch frames use the sampler's default or ``steps``).
    """
    from pocoloco.sample import _check_joints, _check_sampler

    if method not in METHODS:
        raise ValueError(f"unknown animation method {method!r}; choose one of: {', '.join(METHODS)}")
    if anchor not in ANCHORS:
        raise ValueError(f"unknown anchor {anchor!r}; choose one of: {', '.join(ANCHORS)}")
    C, J, T = int(config.denoiser.point_channels), int(config.denoiser.num_joints), int(config.num_timesteps)
    joints = np.asarray(joints)
    if joints.ndim != 3 or joints.shape[0] < 1:
        raise ValueError(f"joints must have shape (T, {J}, 3), got {joints.shape}")
    joints = np.stack([_check_joints(f"joints[{k}]", j, J) for k, j in enumerate(joints)])
    _check_sampler(sampler, steps, T)
    if not 1 <= t <= T:
        raise ValueError(f"t must be in [1, {T}] (the model's training timesteps), got {t}")
    if num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {num_points}")
    F = len(joints)
    if seeds is None:
        seeds = [seed] * F if method == "shared-noise" else [seed + k for k in range(F)]
    seeds = [int(s) for s in seeds]
    if len(seeds) != F:
        raise ValueError(f"seeds must have one entry per frame ({F}), got {len(seeds)}")
    points = np.empty((F, num_points, 3), np.float32)
    normals = np.empty((F, num_points, 3), np.float32) if C == 6 else None
    for k in range(F):
        if method != "chain" or k == 0:
            x = denoise_from(model, normalisation, config, joints[k], None, T, sampler, steps, [seeds[k]],
                             num_points=num_points)  # fmt: skip
        else:
            ref = joints[k - 1] if anchor == "root" else joints[k]
            prev_n = None if normals is None else normals[k - 1]
            x0 = to_normalised(normalisation, points[k - 1], prev_n, ref, C)[None]  # (1, N, C)
            x = denoise_from(model, normalisation, config, joints[k], x0, t, sampler,
                             None if steps is None else min(steps, t), [seeds[k]])  # fmt: skip
        p, n = to_metres(normalisation, x, joints[k])
        points[k] = p[0]
        if normals is not None:
            normals[k] = n[0]
        if progress is not None:
            progress(k + 1, F)
    return Animation(points, normals, seeds)


# -------------------------------------------------------------------------------------- flicker
def warp_by_body(points: np.ndarray, body_from: np.ndarray, body_to: np.ndarray) -> np.ndarray:
    """Move each point (N, 3) by the displacement of its nearest vertex of ``body_from`` (V, 3)
    to the same vertex of ``body_to`` (V, 3): ``p + body_to[i] - body_from[i]``, i = nearest."""
    from pocoloco.metrics import nearest

    body_from, body_to = np.asarray(body_from, np.float64), np.asarray(body_to, np.float64)
    if body_from.shape != body_to.shape:
        raise ValueError(f"body vertices must have the same shape, got {body_from.shape} and {body_to.shape}")
    _, idx = nearest(points, body_from)
    return np.asarray(points, np.float64) + (body_to - body_from)[idx]


def flicker_cm(clouds: Sequence[np.ndarray], bodies: Sequence[np.ndarray]) -> np.ndarray:
    """(T-1,) PocoLoco Chamfer (cm) between frame k warped by the body motion (:func:`warp_by_body`)
    and frame k+1, for T clouds (N_k, 3) and their posed bodies (V, 3)."""
    from pocoloco.metrics import chamfer_cm

    if len(clouds) != len(bodies):
        raise ValueError(f"{len(clouds)} clouds but {len(bodies)} bodies")
    return np.array([chamfer_cm(warp_by_body(clouds[k], bodies[k], bodies[k + 1]), clouds[k + 1])
                     for k in range(len(clouds) - 1)])  # fmt: skip


def evaluate_animation(anim_points: np.ndarray, frames: Sequence[os.PathLike], num_points: int,
                       seed: int = 0) -> dict[str, Any]:  # fmt: skip
    """Flicker and accuracy of generated clouds (T, N, 3) for a dataset sequence's frame files.

    Returns ``flicker_cm`` (T-1,) and its mean, ``gt_flicker_cm`` (the same on N-point subsets of
    the GT scans, the floor), ``chamfer_to_gt_cm`` (T,) (each frame vs. its GT subset) and mean.
    """
    from pocoloco.data.format import read_frame
    from pocoloco.metrics import chamfer_cm

    gts, bodies = [], []
    for k, p in enumerate(frames):
        fr = read_frame(p, ["points", "body_vertices"], allow_missing=True)
        if fr.body_vertices is None:
            raise ValueError(f"{p}: no body_vertices (imported data?): the flicker metric needs the posed body")
        gts.append(fr.points[subset(fr.num_points, num_points, [seed, k])])
        bodies.append(fr.body_vertices)
    fl = flicker_cm(list(anim_points), bodies)
    gfl = flicker_cm(gts, bodies)
    acc = np.array([chamfer_cm(a, g) for a, g in zip(anim_points, gts, strict=True)])
    nan = float("nan")
    return {"flicker_cm": fl.tolist(), "flicker_mean_cm": float(fl.mean()) if len(fl) else nan,
            "gt_flicker_cm": gfl.tolist(), "gt_flicker_mean_cm": float(gfl.mean()) if len(gfl) else nan,
            "chamfer_to_gt_cm": acc.tolist(), "chamfer_to_gt_mean_cm": float(acc.mean())}  # fmt: skip


# ------------------------------------------------------------------------------------------ GIF
def render_gif(clouds: np.ndarray, path: str | os.PathLike, fps: float = 10.0, view: str = "front",
               size: float = 3.0, dpi: int = 80, colors: np.ndarray | None = None) -> str:  # fmt: skip
    """Render clouds (T, N, 3) as an animated GIF (one shared window, so motion is visible);
    written atomically. colors: (T, N, 3) RGB or None (skin colour, depth-shaded)."""
    from PIL import Image

    from pocoloco.render import _figure, _project, render_points
    from pocoloco.utils.atomic import atomic_open

    clouds = np.asarray(clouds, np.float64)
    if clouds.ndim != 3 or clouds.shape[-1] != 3 or len(clouds) == 0:
        raise ValueError(f"clouds must have shape (T, N, 3), got {clouds.shape}")
    u, v, _ = _project(clouds.reshape(-1, 3), view)
    half = 0.52 * max(float(np.ptp(u)), float(np.ptp(v)), 1e-6)
    cu, cv = (u.min() + u.max()) / 2, (v.min() + v.max()) / 2
    images = []
    for k, pts in enumerate(clouds):
        fig = _figure(size, size, dpi)
        fig.patch.set_facecolor("white")
        ax = fig.add_axes((0, 0, 1, 1))
        render_points(ax, pts, colors=None if colors is None else colors[k], view=view,
                      extent=(cu - half, cu + half, cv - half, cv + half))  # fmt: skip
        ax.text(0.02, 0.97, f"{k}", transform=ax.transAxes, fontsize=8, va="top")
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]  # (H, W, 3) uint8
        images.append(Image.fromarray(rgb).convert("P", palette=Image.ADAPTIVE))
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())
    return os.fspath(path)


# ------------------------------------------------------------------------------------------ CLI
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
    """The ``pocoloco animate`` options (handler :func:`cmd_animate`)."""
    parser.add_argument("--motion", required=True,
                        help="(T, 24, 3) joints .npy / .npz, or a dataset sequence "
                             "DATASET:subject/split/sequence")  # fmt: skip
    parser.add_argument("--method", default="chain", help="independent, shared-noise or chain (default chain)")
    parser.add_argument("--t", type=int, default=200, help="chain: renoising step of each new frame (default 200)")
    parser.add_argument("--anchor", default="root", help="chain: carry the previous frame root-relative (root, "
                                                         "default) or in world coordinates (world)")  # fmt: skip
    parser.add_argument("--points", type=int, default=2048, help="N points per frame (default 2048)")
    parser.add_argument("--frames", help="frames to animate, START:STOP[:STEP] (default: all)")
    parser.add_argument("--fps", type=float, default=10.0, help="GIF frame rate (default 10)")
    add_common_arguments(parser, "output folder (frame_0000.ply ..., animation.gif, animation.json)")


def cmd_animate(args: argparse.Namespace) -> None:
    """``pocoloco animate``: validate, animate, write the output folder (nothing on error)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from pocoloco.data.published import write_ply
    from pocoloco.sample import _check_sampler
    from pocoloco.utils.atomic import write_json_atomic

    check_common_args(args)
    if args.method not in METHODS:
        raise ValueError(f"unknown --method {args.method!r}; choose one of: {', '.join(METHODS)}")
    if args.anchor not in ANCHORS:
        raise ValueError(f"unknown --anchor {args.anchor!r}; choose one of: {', '.join(ANCHORS)}")
    if args.points < 1:
        raise ValueError(f"--points must be >= 1, got {args.points}")
    if not args.fps > 0:
        raise ValueError(f"--fps must be > 0, got {args.fps}")
    model, normalisation, config, ckpt, step = load_model_from_args(args)
    motion = load_motion(args.motion, config.denoiser.num_joints)
    chosen = _parse_frames(args.frames, len(motion.joints))
    _check_sampler(args.sampler, args.steps, config.num_timesteps)
    if not 1 <= args.t <= config.num_timesteps:
        raise ValueError(f"--t must be in [1, {config.num_timesteps}] (the model's training timesteps), got {args.t}")
    joints = motion.joints[chosen]
    t0 = time.perf_counter()
    with Progress(TextColumn("animate"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  transient=True) as bar:  # fmt: skip
        task = bar.add_task("frames", total=len(chosen))
        anim = animate(model, normalisation, config, joints, args.points, method=args.method, t=args.t,
                       sampler=args.sampler, steps=args.steps, seed=args.seed, anchor=args.anchor,
                       progress=lambda d, n: bar.update(task, completed=d, total=n))  # fmt: skip
    seconds = time.perf_counter() - t0
    info: dict[str, Any] = {
        "checkpoint": str(ckpt), "step": step, "motion": motion.name, "frames": chosen, "method": args.method,
        "t": args.t if args.method == "chain" else None, "anchor": args.anchor if args.method == "chain" else None,
        "points": args.points, "sampler": args.sampler, "steps": args.steps, "seeds": anim.seeds,
        "seconds_total": seconds, "seconds_per_frame": seconds / len(chosen),
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
            render_gif(anim.points, folder / "animation.gif", fps=args.fps)
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
