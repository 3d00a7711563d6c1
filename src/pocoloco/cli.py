"""The ``pocoloco`` command. Entry points only: parse, call the library, report.

User mistakes (bad paths, malformed files, wrong shapes, unknown presets)
surface as one line ``pocoloco: error: ...`` and exit code 2; set
``POCOLOCO_DEBUG=1`` to see the traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

EXIT_USER_ERROR = 2


def _console():
    from rich.console import Console

    return Console()


# --------------------------------------------------------------------------------------- data
def cmd_data_synth(args: argparse.Namespace) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from .data.config import synth_preset
    from .data.synth import synthesize

    config = synth_preset(args.preset)
    overrides = {
        k: v
        for k, v in dict(
            seed=args.seed,
            train_sequences=args.train_sequences,
            test_sequences=args.test_sequences,
            frames_per_sequence=args.frames,
            num_points=args.points,
        ).items()
        if v is not None
    }
    for k, v in overrides.items():
        if k != "seed" and v <= 0:
            raise ValueError(f"--{k.replace('_', '-')} must be positive, got {v}")
    config = dataclasses.replace(config, **overrides)
    out = Path(args.out or f"data/{args.preset}")
    console = _console()
    console.print(f"[bold]pocoloco data synth[/] preset={args.preset} -> {out} (workers={args.workers})")
    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
    ) as bar:
        task = bar.add_task("frames", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        card = synthesize(config, out, workers=args.workers, progress=progress)
    _print_card(card, out)


def cmd_data_info(args: argparse.Namespace) -> None:
    from .data.format import read_card

    card = read_card(Path(args.path))
    _print_card(card, Path(args.path))


def _print_card(card: dict, path: Path) -> None:
    from rich.table import Table

    console = _console()
    table = Table(title=f"dataset {path} ({card.get('status', 'complete')}): frames per split")
    for col in ("subject", "garment", "train", "test", "rejected", "loose %", "pen. max/mean mm"):
        table.add_column(col, justify="right" if col != "subject" else "left")
    for name, s in card.get("subjects", {}).items():
        c = card.get("counts", {}).get(name, {})
        pen = s.get("penetration")
        share = card.get("loose_share", {}).get(name)
        table.add_row(
            name,
            s.get("garment_kind", "?"),
            str(c.get("train", {}).get("frames", "-")),
            str(c.get("test", {}).get("frames", "-")),
            str(sum(v.get("rejected_frames", 0) for v in c.values())) if c else "-",
            f"{100 * share:.1f}" if share is not None else "-",
            f"{pen['max_mm']:.1f} / {pen['mean_mm']:.2f}" if pen else "-",
        )
    console.print(table)
    cfg = card.get("generation_config", {})
    keys = ("train_sequences", "test_sequences", "frames_per_sequence", "fps", "num_points", "capture_cameras", "seed")
    console.print("config: " + ", ".join(f"{k}={cfg.get(k)}" for k in keys))
    norm = card.get("normalisation")
    if norm:
        console.print(f"normalisation (root-centred, on {norm['computed_on']}): mean={[round(m, 4) for m in norm['mean']]} std={norm['std']:.4f}")
    gen = card.get("generation")
    if gen:
        per = gen["cpu_seconds_per_frame"]
        console.print(
            "generation: "
            + ", ".join(f"{k} {v:.3f} s/frame" for k, v in per.items())
            + f"; wall {gen['wall_seconds_last_run']:.0f} s with {gen['workers']} worker(s)"
        )
    if card.get("status", "complete") != "complete":
        console.print("[yellow]incomplete: rerun the same `pocoloco data synth` command to resume[/]")


def cmd_data_preview(args: argparse.Namespace) -> None:
    from .data.preview import preview_dataset

    path = preview_dataset(Path(args.path), out=args.out, num=args.num, split=args.split, seed=args.seed)
    print(f"wrote {path}")


def cmd_data_export(args: argparse.Namespace) -> None:
    from .data.format import DatasetLayout, read_card
    from .data.published import export_frame

    root = Path(args.path)
    read_card(root)
    frames = DatasetLayout(root).iter_frames(args.split)
    if args.subject:
        frames = [f for f in frames if f[0] == args.subject]
    if not frames:
        raise ValueError(f"{root}: no frames for split {args.split!r}" + (f" and subject {args.subject!r}" if args.subject else ""))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for subject, sequence, frame_path in frames[: args.limit or None]:
        target = out / f"{subject}_{sequence}_{Path(frame_path).stem}.{args.format}"
        export_frame(frame_path, target, args.format)
    print(f"wrote {min(len(frames), args.limit or len(frames))} {args.format} files to {out}")


def cmd_data_import(args: argparse.Namespace) -> None:
    from .data.published import import_loose_style

    seq = import_loose_style(
        args.ply_dir, args.joints, args.out, subject=args.subject, split=args.split, sequence=args.sequence
    )
    print(f"imported into {seq}")


# --------------------------------------------------------------------------------------- main
def cmd_export_model(args: argparse.Namespace) -> None:
    """``pocoloco export-model``: a small sampling-only copy of a checkpoint (how the default model ships)."""
    from .checkpoint import export_for_sampling, resolve_checkpoint

    out = export_for_sampling(resolve_checkpoint(args.ckpt), args.out, use_ema=not args.raw_weights)
    size = sum(f.stat().st_size for f in out.iterdir())
    weights = json.loads((out / "meta.json").read_text(encoding="utf-8"))["weights"]  # raw if the model keeps no EMA
    print(f"wrote {out} ({size / 1e6:.1f} MB, {'EMA' if weights == 'ema' else 'raw'} weights)")


def build_parser() -> argparse.ArgumentParser:
    from .data.config import SYNTH_PRESETS

    p = argparse.ArgumentParser(prog="pocoloco", description="Point-cloud models of humans in loose clothing.")
    sub = p.add_subparsers(dest="command", required=True)

    data = sub.add_parser("data", help="synthetic data: generate, inspect, preview, export").add_subparsers(
        dest="data_command", required=True
    )
    s = data.add_parser("synth", help="generate (or resume) a synthetic capture dataset")
    s.add_argument("--preset", default="small", help=f"one of {', '.join(SYNTH_PRESETS)} (default: small)")
    s.add_argument("--out", help="output folder (default: data/PRESET); rerun to resume")
    s.add_argument("--workers", type=int, default=1, help="parallel worker processes (one sequence each)")
    s.add_argument("--seed", type=int)
    s.add_argument("--train-sequences", type=int)
    s.add_argument("--test-sequences", type=int)
    s.add_argument("--frames", type=int, help="stored frames per sequence")
    s.add_argument("--points", type=int, help="points stored per frame")
    s.set_defaults(func=cmd_data_synth)

    s = data.add_parser("info", help="print a dataset's card as tables")
    s.add_argument("path")
    s.set_defaults(func=cmd_data_info)

    s = data.add_parser("preview", help="PNG grid of rendered frames coloured by label")
    s.add_argument("path")
    s.add_argument("--out", help="PNG path (default: PATH/preview.png)")
    s.add_argument("--num", type=int, default=4, help="frames per subject")
    s.add_argument("--split", default="train", choices=["train", "test"])
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_data_preview)

    s = data.add_parser("export", help="write frames as PLY (points, normals, labels) or POP-style NPZ")
    s.add_argument("path")
    s.add_argument("--out", required=True)
    s.add_argument("--format", choices=["ply", "npz"], default="ply")
    s.add_argument("--split", default="test", choices=["train", "test"])
    s.add_argument("--subject")
    s.add_argument("--limit", type=int, default=0, help="at most this many frames (0 = all)")
    s.set_defaults(func=cmd_data_export)

    s = data.add_parser(
        "import", help="convert a LOOSE/DynaCap-style sequence (one .ply per frame + a joints text file)"
    )
    s.add_argument("ply_dir", help="folder with one .ply per frame (frame id = last integer in the file name)")
    s.add_argument("--joints", required=True, help="text file: per line a frame id then 3 x 24 floats")
    s.add_argument("--out", required=True, help="dataset folder (created or extended)")
    s.add_argument("--subject", required=True)
    s.add_argument("--split", default="train", choices=["train", "test"])
    s.add_argument("--sequence", help="sequence name (default: the ply folder's name)")
    s.set_defaults(func=cmd_data_import)

    from .train import add_train_arguments, cmd_train

    s = sub.add_parser("train", help="train a model on a dataset (PocoLoco diffusion, or the peers POP / CloSET)")
    add_train_arguments(s)
    s.set_defaults(func=cmd_train)

    from .sample import add_sample_arguments, cmd_sample

    s = sub.add_parser("sample", help="sample clouds for a pose from a trained checkpoint (PLY + PNG)")
    add_sample_arguments(s)
    s.set_defaults(func=cmd_sample)

    from .apps.completion import add_complete_arguments, cmd_complete

    s = sub.add_parser("complete", help="complete a partial scan with the model (inpainting; PLY + PNG + JSON)")
    add_complete_arguments(s)
    s.set_defaults(func=cmd_complete)

    from .apps.editing import add_edit_arguments, cmd_edit

    s = sub.add_parser("edit", help="move a cloud to a new pose (renoise or regenerate the moving region)")
    add_edit_arguments(s)
    s.set_defaults(func=cmd_edit)

    from .apps.animation import add_animate_arguments, cmd_animate

    s = sub.add_parser("animate", help="clouds for a motion (independent / shared-noise / chain; PLYs + GIF + JSON)")
    add_animate_arguments(s)
    s.set_defaults(func=cmd_animate)

    from .evaluate import add_eval_arguments, cmd_eval

    s = sub.add_parser("eval", help="score a checkpoint and the baselines on a dataset split (JSON + markdown + plots)")
    add_eval_arguments(s)
    s.set_defaults(func=cmd_eval)

    from .peers import add_fit_arguments, cmd_fit

    s = sub.add_parser("fit", help="POP: fit a new outfit to one scan (only its geometric features) -> new checkpoint")
    add_fit_arguments(s)
    s.set_defaults(func=cmd_fit)

    bench = sub.add_parser("bench", help="benchmarks over trained models").add_subparsers(dest="bench_command",
                                                                                         required=True)  # fmt: skip
    from .bench_quality import add_bench_quality_arguments, cmd_bench_quality

    s = bench.add_parser("quality", help="PocoLoco, POP, CloSET (+/- decomposition) and baselines on the same test "
                                         "frames: quality.json / .md / .png")  # fmt: skip
    add_bench_quality_arguments(s)
    s.set_defaults(func=cmd_bench_quality)

    s = sub.add_parser("export-model", help="write a sampling-only copy of a checkpoint (meta.json + weights)")
    s.add_argument("--ckpt", required=True, help="checkpoint folder, checkpoints folder or run folder")
    s.add_argument("--out", required=True, help="new folder to write (must not exist)")
    s.add_argument("--raw-weights", action="store_true", help="export the raw weights instead of the EMA")
    s.set_defaults(func=cmd_export_model)

    from .body.surface import add_uvmap_arguments, cmd_uvmap

    s = sub.add_parser("uvmap", help="rasterise the anny UV layout: pixel -> (face, barycentric) + template position map")
    add_uvmap_arguments(s)
    s.set_defaults(func=cmd_uvmap)

    from .meshing import add_mesh_arguments, cmd_mesh

    s = sub.add_parser("mesh", help="watertight mesh from a point cloud PLY (screened Poisson reconstruction)")
    add_mesh_arguments(s)
    s.set_defaults(func=cmd_mesh)

    from .viewer import add_view_arguments, cmd_view

    s = sub.add_parser("view", help="self-contained HTML viewer (WebGL) for a folder of PLY clouds")
    add_view_arguments(s)
    s.set_defaults(func=cmd_view)

    from .render import add_render_arguments, cmd_render

    s = sub.add_parser("render", help="PNG renders of clouds / meshes from several views (+ turntable / animation GIF)")
    add_render_arguments(s)
    s.set_defaults(func=cmd_render)
    return p


#: Exceptions that mean the user gave something wrong (a path, a file, a value).
USER_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError)


def run_command(func, args: argparse.Namespace, prog: str = "pocoloco") -> int:
    """Run one command; a user error becomes one line ``PROG: error: ...`` and
    exit code 2 (``POCOLOCO_DEBUG=1`` shows the traceback instead)."""
    try:
        from .pretrained import resolve_ckpt_arg

        for name, value in vars(args).items():  # --ckpt[-pop|...] default / default:pop / default:closet
            if (name == "ckpt" or name.startswith("ckpt_")) and isinstance(value, str):
                setattr(args, name, str(resolve_ckpt_arg(value)))
        func(args)
    except USER_ERRORS as e:
        if os.environ.get("POCOLOCO_DEBUG"):
            raise
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "workers", 1) is not None and getattr(args, "workers", 1) < 1:
        parser.error("--workers must be >= 1")
    return run_command(args.func, args)


if __name__ == "__main__":
    sys.exit(main())
