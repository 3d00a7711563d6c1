"""``pocoloco render | view | export-model | uvmap``: pictures, the viewer, shipping a model, UV maps."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from pocoloco.apps.meshing import estimate_normals, mesh_from_points
from pocoloco.body.surface import write_uv_map
from pocoloco.data.poses import load_joints
from pocoloco.data.published import CLOUD_CHECK_HELP, check_cloud, read_ply
from pocoloco.engine.checkpoint import WEIGHTS_DTYPES, export_for_sampling, load_checkpoint, resolve_checkpoint
from pocoloco.methods import method_class
from pocoloco.methods.pocoloco.method import DEFAULT_POLISH_T, polish_link
from pocoloco.viz.render import (
    VIEWS,
    render_gif,
    render_grid,
    render_meshes,
    turntable_gif,
)
from pocoloco.viz.viewer import find_clouds, serve_file, write_viewer

__all__ = ["register"]


# -------------------------------------------------------------------------------------- render
#: at most this many clouds of a folder go into one PNG
MAX_PANELS = 16


def add_render_arguments(parser) -> None:
    """The ``pocoloco render`` options."""
    parser.add_argument("input", help="a .ply (point cloud or mesh) or a folder of .ply files (one panel row each); " + CLOUD_CHECK_HELP)
    parser.add_argument("--out", required=True, help="PNG to write")
    parser.add_argument("--views", nargs="+", default=["front", "side", "back"],
                        help=f"views per input, from {', '.join(VIEWS)} (default front side back)")  # fmt: skip
    parser.add_argument("--color", default="label", choices=("label", "normal", "height"),
                        help="colour by label (skin / garment), normal (estimated when the PLY has none) or "
                             "height (default label)")  # fmt: skip
    parser.add_argument("--mesh", action="store_true",
                        help="draw surfaces: the PLY's faces, or a Poisson mesh of a cloud (pocoloco mesh)")
    parser.add_argument("--depth", type=int, default=8, help="--mesh of a cloud: Poisson octree depth (default 8)")
    parser.add_argument("--turntable", help="also write a turntable GIF of the (first) input")
    parser.add_argument("--animate", help="folder input: also write its clouds as an animation GIF, in file order")
    parser.add_argument("--frames", type=int, default=24, help="turntable frames (default 24)")
    parser.add_argument("--fps", type=float, default=10.0, help="GIF frames per second (default 10)")
    parser.add_argument("--max-points", type=int, default=20000,
                        help="subsample larger clouds to this many points (default 20000)")  # fmt: skip
    parser.add_argument("--joints",
                        help="the clouds' pose, as for `pocoloco sample --joints` (demo:skirt, a joints file, a dataset "
                             "frame): the shading's estimated normals face away from its bones and the loose garment "
                             "of clouds without labels is tinted (default: none; normals oriented by a guess, no tint)")  # fmt: skip


def _read_for_render(path, max_points: int, need_normals: bool, as_mesh: bool, seed: int = 0, depth: int = 8) -> dict:
    """A PLY as {points, labels, normals, faces} ready to draw (one-line ValueErrors)."""
    ply = read_ply(path)
    n = len(ply.points)
    if n == 0:
        raise ValueError(f"{path}: has no points")
    if ply.faces is None or len(ply.faces) == 0:  # a mesh's vertices may be few (a tetrahedron renders)
        check_cloud(os.fspath(path), ply.points)
    item = {"points": ply.points, "labels": ply.labels, "normals": ply.normals, "faces": ply.faces}
    if as_mesh:
        if item["faces"] is None or len(item["faces"]) == 0:
            try:
                m = mesh_from_points(ply.points, ply.normals, depth=depth)
            except ValueError as e:
                raise ValueError(f"{path}: {e}") from None
            item.update(points=m.vertices, faces=m.faces, labels=None, normals=None)
        return item
    item["faces"] = None
    if n > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))
        item.update({k: None if item[k] is None else item[k][keep] for k in ("points", "labels", "normals")})
    if need_normals and item["normals"] is None:
        if len(item["points"]) < 10:
            raise ValueError(f"{path}: {len(item['points'])} points are too few to estimate normals "
                             f"(--color normal needs normals)")  # fmt: skip
        item["normals"] = estimate_normals(item["points"])
    return item


def cmd_render(args) -> None:
    """``pocoloco render``: PNG (and GIFs) of a cloud / mesh PLY or a folder of them."""
    src = Path(args.input)
    for flag, value, ext in (("--out", args.out, ".png"), ("--turntable", args.turntable, ".gif"),
                             ("--animate", args.animate, ".gif")):  # fmt: skip
        if value is not None and not value.lower().endswith(ext):
            raise ValueError(f"{flag} {value}: must end with {ext}")
        if value is not None and Path(value).is_dir():
            raise ValueError(f"{flag} {value}: is a folder")
    bad = [v for v in args.views if v not in VIEWS]
    if bad:
        raise ValueError(f"unknown view(s) {', '.join(bad)}; choose from {', '.join(VIEWS)}")
    if args.frames < 1 or not args.fps > 0 or args.max_points < 1:
        raise ValueError("--frames and --max-points must be >= 1 and --fps > 0")
    joints = None if args.joints is None else load_joints(args.joints)
    if src.is_dir():
        files = find_clouds(src)
    elif src.exists():
        files = [src]
    else:
        raise ValueError(f"{src}: no such file or folder")
    if args.animate and not src.is_dir():
        raise ValueError("--animate needs a folder of clouds (frame_0000.ply ...)")
    panels = files[:MAX_PANELS]
    items = [_read_for_render(f, args.max_points, args.color == "normal", args.mesh, depth=args.depth) for f in panels]
    anim = None
    if args.animate:
        clouds = items if len(files) <= MAX_PANELS and not args.mesh else [
            _read_for_render(f, args.max_points, False, False) for f in files]  # fmt: skip
        n = min(len(c["points"]) for c in clouds)
        anim = np.stack([c["points"][np.sort(np.random.default_rng(0).choice(len(c["points"]), n, replace=False))]
                         for c in clouds])  # fmt: skip
    # everything read and checked: now write
    if args.mesh:
        render_meshes([(c["points"], c["faces"], f.name) for c, f in zip(items, panels, strict=True)], args.out,
                      views=args.views, mode=args.color, panel_size=3.0)  # fmt: skip
    else:
        render_grid([(c["points"], c["labels"], c["normals"], f.name) for c, f in zip(items, panels, strict=True)],
                    args.out, views=args.views, ncols=1 if len(items) > 1 else None, mode=args.color,
                    joints=joints)  # fmt: skip
    written = [args.out]
    if args.turntable:
        c = items[0]
        turntable_gif(args.turntable, c["points"], c["labels"], c["normals"], c["faces"], num_frames=args.frames,
                      mode=args.color, fps=args.fps, joints=joints)  # fmt: skip
        written.append(args.turntable)
    if anim is not None:
        render_gif(anim, args.animate, fps=args.fps)
        written.append(args.animate)
    more = f" (first {MAX_PANELS} of {len(files)} files)" if len(files) > MAX_PANELS else ""
    print(f"rendered {len(panels)} {'mesh' if args.mesh else 'cloud'}{'es' if args.mesh and len(panels) > 1 else ''}"
          f"{'' if args.mesh or len(panels) == 1 else 's'}{more}: wrote {', '.join(written)}")  # fmt: skip


# ---------------------------------------------------------------------------------------- view
def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco view`` options."""
    parser.add_argument("result_dir", help="folder of .ply clouds (sample_000.ply ... or frame_0000.ply ...); " + CLOUD_CHECK_HELP)
    parser.add_argument("--out", help="HTML file to write (default: RESULT_DIR/viewer.html)")
    parser.add_argument("--max-points", type=int, default=20000,
                        help="subsample each cloud to at most this many points (default 20000)")  # fmt: skip
    parser.add_argument("--fps", type=float, default=10.0, help="animation playback rate (default 10)")
    parser.add_argument("--serve", action="store_true",
                        help="serve the page on a local port, print the URL and open a browser")  # fmt: skip
    parser.add_argument("--no-browser", action="store_true", help="with --serve: do not open a browser")


def cmd_view(args: argparse.Namespace) -> None:
    """``pocoloco view``: write the viewer page (and optionally serve it)."""
    path, clouds = write_viewer(args.result_dir, args.out, max_points=args.max_points, fps=args.fps)
    shown = sum(len(c.points) for c in clouds)
    print(f"wrote {path} ({len(clouds)} clouds, {shown} points, {path.stat().st_size / 1e6:.2f} MB)")
    if args.serve:
        serve_file(path, open_browser=not args.no_browser)


# -------------------------------------------------------------------------------- export-model
def cmd_export_model(args: argparse.Namespace) -> None:
    """A small sampling-only copy of a checkpoint (how the shipped models were made)."""
    ckpt = resolve_checkpoint(args.ckpt)
    ck = load_checkpoint(ckpt, expect_model=None, training_state=False)
    unlinked = ck
    if args.polish_with:  # re-linking: the old link may name a teacher that has changed since
        unlinked = dataclasses.replace(ck, meta={k: v for k, v in ck.meta.items() if k != "polish"})
    model = method_class(ck.model_kind).from_checkpoint(unlinked).model
    buffers = [name for name, b in model.named_buffers() if b.is_floating_point()]
    if args.polish_t is not None and not args.polish_with:
        raise ValueError("--polish-t goes with --polish-with (the teacher that makes the last call)")
    extra = {}
    if args.polish_with:
        t = DEFAULT_POLISH_T if args.polish_t is None else args.polish_t
        extra["polish"] = polish_link(unlinked, args.polish_with, t)
    out = export_for_sampling(ck, args.out, use_ema=not args.raw_weights, dtype=args.dtype,
                              keep_float32=buffers, extra_meta=extra)  # geometry buffers (templates, UV queries) stay float32
    size = sum(f.stat().st_size for f in out.iterdir())
    weights = json.loads((out / "meta.json").read_text(encoding="utf-8"))["weights"]  # raw if the model keeps no EMA
    print(f"wrote {out} ({size / 1e6:.1f} MB, {'EMA' if weights == 'ema' else 'raw'} weights, {args.dtype})")


# ---------------------------------------------------------------------------------------- uvmap
def _parse_phenotype(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        try:
            out[key] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            raise ValueError(f"--phenotype expects KEY=VALUE with a number, got {item!r}")
    return out


def cmd_uvmap(args: argparse.Namespace) -> None:
    r = write_uv_map(args.out, args.resolution, _parse_phenotype(args.phenotype), all_faces=args.all_faces, png=args.png)
    print(f"uv map {r.resolution}x{r.resolution}: {r.num_valid} valid pixels ({r.num_valid / r.resolution**2:.1%}), "
          f"{r.num_overlapping} covered by >1 face -> {args.out}" + (f", {args.png}" if args.png else ""))  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("render", help="PNG renders of clouds / meshes from several views (+ turntable / animation GIF)")
    add_render_arguments(s)
    s.set_defaults(func=cmd_render)
    s = sub.add_parser("view", help="self-contained HTML viewer (WebGL) for a folder of PLY clouds")
    add_view_arguments(s)
    s.set_defaults(func=cmd_view)
    s = sub.add_parser("export-model", help="write a sampling-only copy of a checkpoint (meta.json + weights)")
    s.add_argument("--ckpt", required=True, help="checkpoint folder, checkpoints folder or run folder")
    s.add_argument("--out", required=True, help="new folder to write (must not exist)")
    s.add_argument("--raw-weights", action="store_true", help="export the raw weights instead of the EMA")
    s.add_argument("--dtype", choices=list(WEIGHTS_DTYPES), default="float16",
                   help="storage dtype of the floating weights (default float16: half the bytes, what ships; "
                        "loaded back as float32)")  # fmt: skip
    s.add_argument("--polish-with", metavar="CKPT",
                   help="a distilled model only: its teacher (e.g. default), linked by name and digest, makes the "
                        "last of 3 or more calls, denoising the student's answer re-noised to --polish-t")  # fmt: skip
    s.add_argument("--polish-t", type=int, default=None,
                   help=f"the step (1-based, of 1,000) the teacher re-noises to (default {DEFAULT_POLISH_T})")
    s.set_defaults(func=cmd_export_model)
    s = sub.add_parser("uvmap", help="rasterise the anny UV layout: pixel -> (face, barycentric) + template position map")
    s.add_argument("--resolution", type=int, default=256, help="map size R (default 256)")
    s.add_argument("--phenotype", nargs="*", default=[], metavar="KEY=VALUE",
                   help="anny phenotype, e.g. gender=0.3 height=0.6 (default: all 0.5)")  # fmt: skip
    s.add_argument("--all-faces", action="store_true",
                   help="also rasterise anny's eyeballs and mouth interior (default: body only)")  # fmt: skip
    s.add_argument("--out", required=True, help="output .npz (face_idx, barycentric, mask, uv, posmap)")
    s.add_argument("--png", help="also save the template's position map as a PNG")
    s.set_defaults(func=cmd_uvmap)
