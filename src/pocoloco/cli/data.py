"""``pocoloco data synth | info | verify | preview | export | import | pack``: the synthetic capture
pipeline and the dataset tools."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import shutil
import tempfile
from pathlib import Path

from pocoloco.cli.common import console, progress_bar
from pocoloco.utils.atomic import exclusive_lock, output_folder
from pocoloco.synth.config import CLOTH_VERSIONS, CURRENT_CLOTH, SYNTH_PRESETS, cloth_version, config_of_card, synth_preset
from pocoloco.synth.fabric import DAMPING_MODELS
from pocoloco.synth.histories import HistoriesSpec, make_histories
from pocoloco.synth.motion_windows import write_motion_histories
from pocoloco.synth.distributed import BACKENDS, LaunchSettings, launch_synth
from pocoloco.data.format import (
    FRAME_STORAGES,
    SPLITS,
    DatasetLayout,
    FrameReport,
    check_frames,
    read_card,
    scan_frames,
    verify_dataset,
)
from pocoloco.data.motion_window import read_motion_history
from pocoloco.data.pack import pack_summary, write_pack
from pocoloco.data.published import CLOUD_CHECK_HELP, export_frame, import_loose_style
from pocoloco.viz.preview import preview_dataset

__all__ = ["register"]


def _parse_shard(text: str) -> tuple[int, int]:
    """``--shard K/N`` -> (K, N); a one-line error unless 1 <= K <= N."""
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
    if not m or not 1 <= int(m[1]) <= int(m[2]):
        raise ValueError(f"--shard must be K/N with 1 <= K <= N (e.g. 3/8), got {text!r}")
    return int(m[1]), int(m[2])


def _check_synth_modes(args: argparse.Namespace) -> None:
    """One mode at a time: a shard, the finalisation, a launch or a whole run; one-line errors."""
    modes = [f for f, on in (("--shard", args.shard is not None), ("--finalize-only", args.finalize_only),
                             ("--launch", args.launch)) if on]  # fmt: skip
    if len(modes) > 1:
        raise ValueError(f"{' and '.join(modes)} cannot be combined")
    launch_only = {"--shards": args.shards, "--cpus-per-shard": args.cpus_per_shard, "--log-dir": args.log_dir,
                   "--slurm-partition": args.slurm_partition, "--slurm-time": args.slurm_time}  # fmt: skip
    given = [k for k, v in launch_only.items() if v is not None]
    if given and not args.launch:
        raise ValueError(f"{given[0]} needs --launch slurm|local")
    if args.launch and args.shards is None:
        raise ValueError("--launch needs --shards N")
    if args.launch != "slurm" and (args.slurm_partition is not None or args.slurm_time is not None):
        raise ValueError("--slurm-partition and --slurm-time need --launch slurm")
    if args.launch and args.workers is not None:
        raise ValueError("--workers does not apply to --launch: each shard uses --cpus-per-shard workers")
    for flag in ("--shards", "--cpus-per-shard", "--slurm-time"):
        if launch_only[flag] is not None and launch_only[flag] < 1:
            raise ValueError(f"{flag} must be >= 1, got {launch_only[flag]}")


def cmd_data_synth(args: argparse.Namespace) -> None:
    # lazy: the synth extra (newton, warp, open3d) is only needed to generate data
    from pocoloco.synth.pipeline import (
        finalize_dataset,
        missing_jobs,
        synthesize,
        synthesize_shard,
    )

    _check_synth_modes(args)
    shard = _parse_shard(args.shard) if args.shard is not None else None  # --shard '' is an error, not "no shard"
    config = dataclasses.replace(synth_preset(args.preset), **CLOTH_VERSIONS[getattr(args, "cloth", CURRENT_CLOTH)])
    overrides = {
        k: v
        for k, v in dict(
            seed=args.seed,
            train_sequences=args.train_sequences,
            test_sequences=args.test_sequences,
            heldout_sequences=args.heldout_sequences,
            frames_per_sequence=args.frames,
            num_points=args.points,
        ).items()
        if v is not None
    }
    for k, v in overrides.items():
        if k in ("seed", "heldout_sequences"):
            if v < 0:
                raise ValueError(f"--{k.replace('_', '-')} must be >= 0, got {v}")
        elif v <= 0:
            raise ValueError(f"--{k.replace('_', '-')} must be positive, got {v}")
    if args.frame_storage is not None:
        overrides["frame_storage"] = args.frame_storage
    if args.cloth_damping is not None:
        overrides["cloth_damping"] = args.cloth_damping
    config = dataclasses.replace(config, **overrides)
    out = Path(args.out or f"data/{args.preset}")
    workers = args.workers or 1
    con = console()
    if args.finalize_only:
        with exclusive_lock(out, "pocoloco data synth --finalize-only"):  # no shard may still be writing
            card = finalize_dataset(config, out)
        print_card(card, out)
        return
    launch = None
    if args.launch:
        given = {k: v for k, v in (("cpus_per_shard", args.cpus_per_shard), ("time_minutes", args.slurm_time))
                 if v is not None}  # fmt: skip
        launch = LaunchSettings(backend=args.launch, shards=args.shards, partition=args.slurm_partition,
                                log_dir=args.log_dir, **given)  # fmt: skip
        launch.check()
    what = f"workers={workers}"
    if shard:
        what = f"shard {shard[0]}/{shard[1]}, workers={workers}"
    elif launch:
        what = f"{args.shards} shards on {args.launch}, {launch.cpus_per_shard} cpus each"
    con.print(f"[bold]pocoloco data synth[/] preset={args.preset} -> {out} ({what})")

    def run(progress):
        if launch:
            return launch_synth(config, out, launch, progress=progress)
        if shard:
            return synthesize_shard(config, out, *shard, workers=workers, progress=progress)
        return synthesize(config, out, workers=workers, progress=progress)

    with contextlib.ExitStack() as locks:  # one writer per dataset; shards share it, one writer per shard
        if shard:
            locks.enter_context(exclusive_lock(out, f"pocoloco data synth --shard {shard[0]}/{shard[1]}", shared=True))
            locks.enter_context(exclusive_lock(out, f"pocoloco data synth --shard {shard[0]}/{shard[1]}",
                                               name=f".lock-shard-{shard[0]}-of-{shard[1]}"))  # fmt: skip
        elif not launch:  # a launcher's shards lock for themselves
            locks.enter_context(exclusive_lock(out, "pocoloco data synth"))
        with progress_bar("shards done" if launch else "frames", transient=False) as update:
            result = run(update)
    if shard:
        left = len(missing_jobs(config, out))
        frames = sum(r["num_stored"] for r in result)
        con.print(f"shard {shard[0]}/{shard[1]}: {len(result)} sequences done ({frames} frames stored); "
                  f"{left} sequences of the dataset still missing")  # fmt: skip
        if not left:
            con.print(f"all shards are done: `pocoloco data synth --preset {args.preset} --out {out} --finalize-only` "
                      "writes the dataset card (with the same options)")  # fmt: skip
        return
    print_card(result, out)


def cmd_data_heldout(args: argparse.Namespace) -> None:
    # lazy: the synth extra (newton, warp, open3d) is only needed to generate data
    from pocoloco.synth.pipeline import add_heldout

    con = console()
    con.print(f"[bold]pocoloco data heldout[/] {args.path}: {args.sequences} sequence(s) per subject")
    is_dataset = (Path(args.path) / "card.json").is_file()  # else add_heldout's one line, and no lock file left
    lock = exclusive_lock(args.path, "pocoloco data heldout") if is_dataset else contextlib.nullcontext()
    with lock, progress_bar("frames", transient=False) as update:
        card = add_heldout(args.path, args.sequences, args.workers, update)
    print_card(card, Path(args.path))


def cmd_data_histories(args: argparse.Namespace) -> None:
    spec = HistoriesSpec(split=args.split, poses=args.poses, histories=args.histories,
                         shared_seconds=tuple(args.shared_seconds), seed=args.seed,
                         subjects=tuple(args.subjects or ()))  # fmt: skip
    spec.check()
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    shard = _parse_shard(args.shard) if args.shard is not None else (1, 1)
    out = Path(args.out)
    con = console()
    con.print(f"[bold]pocoloco data histories[/] {args.path} -> {out}: {spec.poses} {spec.split} poses x "
              f"{spec.histories} histories x windows {list(spec.shared_seconds)} s")  # fmt: skip
    lock = exclusive_lock(out, f"pocoloco data histories (shard {shard[0]}/{shard[1]})") if out.is_dir() \
        else contextlib.nullcontext()  # fmt: skip
    with lock, progress_bar("references", transient=False) as update:
        card = make_histories(args.path, out, spec, workers=args.workers, shard=shard, progress=update)
    print_card(card, out)


def cmd_data_motion_history(args: argparse.Namespace) -> None:
    with progress_bar("motion histories") as update:
        written, kept = write_motion_histories(args.path, progress=update)
    print(f"{args.path}: {written} motion histories written, {kept} already there")


def cmd_data_info(args: argparse.Namespace) -> None:
    print_card(read_card(Path(args.path)), Path(args.path))


def _files_status(card: dict, path: Path, report: FrameReport) -> tuple[str, str]:
    """(title words, a line under the tables) saying what can be vouched for about the frame files."""
    from rich.markup import escape

    status = card.get("status", "complete")
    if not report.ok:
        kinds = ", ".join(f"{n} {k}" for k, n in report.kinds().items())
        line = f"[red]{escape(report.summary())}\nrun `pocoloco data verify {escape(str(path))}` for the full list[/]"
        return f"DAMAGED: {kinds}", line
    if report.card_records:
        line = (f"files: {report.frames} frame files present with the sizes card.json records; "
                f"`pocoloco data verify {path}` checks their contents")  # fmt: skip
        return f"{status}, {report.frames} frames recorded", escape(line)
    line = (f"files: {report.frames} frame files present; card.json records no sizes or checksums (an older "
            f"dataset): `pocoloco data verify {path} --record` checks every frame and records them")  # fmt: skip
    return f"{status}, {report.frames} frames, not recorded", escape(line)


def print_card(card: dict, path: Path) -> None:
    """The dataset card as rich tables, and what a cheap check of the frame files (listings, sizes) found."""
    from rich.markup import escape
    from rich.table import Table

    con = console()
    title, files_line = _files_status(card, path, scan_frames(path, card=card))
    con.print(escape(f"dataset {path} ({title})"))
    table = Table(title="frames per split")
    counts = card.get("counts", {})
    heldout = any(c.get("heldout", {}).get("frames") for c in counts.values())
    splits = ("train", "test", "heldout") if heldout else ("train", "test")
    for col in ("subject", "garment", *splits, "rejected", "loose %", "pen. max/mean mm"):
        table.add_column(col, justify="right" if col != "subject" else "left")
    for name, s in card.get("subjects", {}).items():
        c = counts.get(name, {})
        pen = s.get("penetration")
        share = card.get("loose_share", {}).get(name)
        table.add_row(
            name,
            s.get("garment_kind", "?"),
            *(str(c.get(split, {}).get("frames", "-")) for split in splits),
            str(sum(v.get("rejected_frames", 0) for v in c.values())) if c else "-",
            f"{100 * share:.1f}" if share is not None else "-",
            f"{pen['max_mm']:.1f} / {pen['mean_mm']:.2f}" if pen else "-",
        )
    con.print(table)
    for key, split in (("pose_coverage", "test"), ("pose_coverage_heldout", "heldout")):
        coverage = card.get(key)
        if not coverage:
            continue
        cov = Table(title=f"{split} poses: RMS distance of the root-aligned joints to the nearest training pose (cm)")
        for col in ("subject", f"{split} frames", "median", "p90", "max"):
            cov.add_column(col, justify="right" if col != "subject" else "left")
        for name, c in coverage.items():
            cov.add_row(name, str(c["test_frames"]), f"{c['median_cm']:.1f}", f"{c['p90_cm']:.1f}", f"{c['max_cm']:.1f}")
        con.print(cov)
    cfg = card.get("generation_config", {})
    keys = ("train_sequences", "test_sequences", "heldout_sequences", "frames_per_sequence", "fps", "num_points", "capture_cameras", "seed")
    keys += ("frame_storage",) if "frame_storage" in cfg else ()
    keys += ("cloth_damping",) if "cloth_damping" in cfg else ()
    line = ", ".join(f"{k}={cfg.get(k)}" for k in keys)
    if cfg:
        with contextlib.suppress(ValueError):
            line += f", cloth={cloth_version(config_of_card(cfg))}"
    con.print("config: " + line)
    norm = card.get("normalisation")
    if norm:
        con.print(f"normalisation (root-centred, on {norm['computed_on']}): mean={[round(m, 4) for m in norm['mean']]} "
                  f"std={norm['std']:.4f}")  # fmt: skip
    gen = card.get("generation")
    if gen:
        per = gen["cpu_seconds_per_frame"]
        how = f"{gen['shards']} shards x {gen['workers']}" if gen.get("shards") else str(gen["workers"])
        con.print("generation: " + ", ".join(f"{k} {v:.3f} s/frame" for k, v in per.items())
                  + f"; wall {gen['wall_seconds_last_run']:.0f} s with {how} worker(s)")  # fmt: skip
    hist = card.get("histories")
    if isinstance(hist, dict):
        con.print(escape(f"reference set: {len(hist.get('poses', []))} {hist.get('split')} poses of {hist.get('source')} x "
                         f"{hist.get('histories')} histories (+ the frame's own scan) x shared windows "
                         f"{hist.get('shared_seconds')} s; prefix motions {hist.get('prefix_seconds')} s, seed "
                         f"{hist.get('seed')}"))  # fmt: skip
    con.print(escape(_motion_line(path)))
    con.print(files_line)
    if card.get("status", "complete") != "complete":
        again = "data histories" if isinstance(hist, dict) else "data synth"
        con.print(f"[yellow]incomplete: rerun the same `pocoloco {again}` command to resume[/]")


def _motion_line(path: Path) -> str:
    """What motion windows (issue 41) the dataset's sequences can give their frames."""
    layout = DatasetLayout(path)
    seqs = [(s, sp, q) for s in layout.subjects() for sp in SPLITS for q in layout.sequences(s, sp)]
    have = [layout.motion_history_path(*k) for k in seqs if layout.motion_history_path(*k).is_file()]
    if not seqs:
        return "motion windows: no sequences"
    if not have:
        return (f"motion windows: none of the {len(seqs)} sequences stores its motion before the first frame; windows "
                f"reaching before it hold that frame (`pocoloco data motion-history {path}` adds them to a "
                "synthetic dataset)")  # fmt: skip
    before = min(h.first / h.fps for h in map(read_motion_history, have[:50]))
    return (f"motion windows: {len(have)} of {len(seqs)} sequences store their whole motion (motion_history.npz; "
            f"{before:.2f} s or more before the first stored frame, the rest pose before that): any window W, "
            "e.g. `train --motion-window 2.0`")  # fmt: skip


def cmd_data_verify(args: argparse.Namespace) -> None:
    """Read every frame file; a table of the bad ones, then a one-line error (exit 2) if any."""
    from rich.markup import escape
    from rich.table import Table

    root = Path(args.path)
    if args.max_rows < 0:
        raise ValueError(f"--max-rows must be >= 0, got {args.max_rows}")
    read_card(root)
    with progress_bar("verify") as update:
        report = verify_dataset(root, record=args.record, progress=update)
    con = console()
    if not report.ok:
        table = Table(title=escape(f"dataset {root}: bad frame files"))
        for col in ("problem", "file", "detail"):
            table.add_column(col)
        for p in report.problems[: args.max_rows or None]:
            table.add_row(p.kind, escape(str(p.path.relative_to(root) if p.path.is_relative_to(root) else p.path)),
                          escape(p.detail))  # fmt: skip
        con.print(table)
        if args.max_rows and len(report.problems) > args.max_rows:
            con.print(f"... and {len(report.problems) - args.max_rows} more")
        raise ValueError(f"{root}: {report.summary()}")
    unrecorded = report.frames - report.recorded
    how = ([f"{report.recorded} by CRC-32"] if report.recorded else []) + (
        [f"{unrecorded} read and validated, no record in card.json"] if unrecorded else [])  # fmt: skip
    con.print(escape(f"{root}: {report.frames} frame files OK ({'; '.join(how) or 'none'})"))
    if args.record and not report.card_records:
        con.print(f"recorded the size and CRC-32 of {report.frames} frame files in {root / 'card.json'}")
    elif unrecorded and not report.card_records:
        con.print(f"card.json records no sizes or checksums: `pocoloco data verify {root} --record` adds them")


def _check_split_frames(root: Path, split: str, subjects: list[str] | None) -> None:
    """Unknown subjects, or a missing / truncated / unreadable frame of the split: one line, before
    anything is written."""
    card = read_card(root)
    unknown = [s for s in subjects or [] if s not in card["subjects"]]
    if unknown:
        raise ValueError(f"{root}: no subject {', '.join(map(repr, unknown))}; it has {', '.join(sorted(card['subjects']))}")
    check_frames(root, splits=[split], subjects=subjects, card=card)


def cmd_data_preview(args: argparse.Namespace) -> None:
    subjects = [s.strip() for s in args.subject.split(",")] if args.subject else None
    _check_split_frames(Path(args.path), args.split, subjects)
    views = ("front",) if args.front_only else ("front", "side")
    path = preview_dataset(Path(args.path), out=args.out, num=args.num, split=args.split, seed=args.seed,
                           subjects=subjects, views=views)  # fmt: skip
    print(f"wrote {path}")


def cmd_data_export(args: argparse.Namespace) -> None:
    """All or nothing: the frames are checked first, written into a hidden folder beside ``--out``
    and moved into place at the end (``--out`` must not exist yet, or be empty)."""
    root = Path(args.path)
    if args.limit < 0:
        raise ValueError(f"--limit must be >= 0, got {args.limit}")
    _check_split_frames(root, args.split, [args.subject] if args.subject else None)
    frames = DatasetLayout(root).iter_frames(args.split, [args.subject] if args.subject else None)
    if not frames:
        raise ValueError(f"{root}: no frames for split {args.split!r}" + (f" and subject {args.subject!r}" if args.subject else ""))
    out = output_folder(args.out)
    if out.is_dir() and any(out.iterdir()):
        raise ValueError(f"{out}: already exists and is not empty; choose a new --out")
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        for subject, sequence, frame_path in frames[: args.limit or None]:
            export_frame(frame_path, stage / f"{subject}_{sequence}_{Path(frame_path).stem}.{args.format}", args.format)
        if out.is_dir():
            out.rmdir()
        os.replace(stage, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    print(f"wrote {min(len(frames), args.limit or len(frames))} {args.format} files to {out}")


def cmd_data_import(args: argparse.Namespace) -> None:
    """All or nothing: a failed import leaves ``--out`` as it was."""
    seq = import_loose_style(args.ply_dir, args.joints, args.out, subject=args.subject, split=args.split,
                             sequence=args.sequence)  # fmt: skip
    frames = len(DatasetLayout(args.out).frame_indices(args.subject, args.split, seq.name))
    print(f"imported {frames} frames into {seq}")


def cmd_data_pack(args: argparse.Namespace) -> None:
    """``pocoloco data pack``: all or nothing (the pack is written atomically at the end)."""
    out = Path(args.out)
    if out.is_dir():
        raise ValueError(f"--out {out}: is a folder; name the pack file to write")
    if out.exists() and not args.overwrite:
        raise ValueError(f"--out {out}: already exists; pass --overwrite to replace it")
    subjects = [s.strip() for s in args.subjects.split(",")] if args.subjects else None
    with progress_bar("frames", transient=False) as update:
        meta = write_pack(args.path, out, splits=args.splits, every=args.every, eval_every=args.eval_every,
                          points=args.points, resolution_mm=args.resolution_mm, subjects=subjects,
                          velocity=args.velocity, bodies=args.bodies, motion=args.motion, seed=args.seed,
                          progress=update)  # fmt: skip
    print(f"wrote {out}: {pack_summary(meta)}")


def register(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="synthetic data: generate, inspect, verify, preview, export, import").add_subparsers(
        dest="data_command", required=True, metavar="{synth,heldout,histories,info,verify,preview,export,import,pack}")  # fmt: skip

    s = data.add_parser("synth", help="generate (or resume) a synthetic capture dataset")
    s.add_argument("--preset", default="small", help=f"one of {', '.join(SYNTH_PRESETS)} (default: small)")
    s.add_argument("--out", help="output folder (default: data/PRESET); rerun the same command to resume")
    s.add_argument("--workers", type=int, help="parallel worker processes, one sequence each (default 1)")
    s.add_argument("--seed", type=int, help="seed of everything random: bodies' motions, garments, capture "
                                            "(default: the preset's, 0)")  # fmt: skip
    s.add_argument("--train-sequences", type=int, help="motion sequences per subject in the train split "
                                                       "(default: the preset's)")  # fmt: skip
    s.add_argument("--test-sequences", type=int, help="motion sequences per subject in the test split "
                                                      "(default: the preset's)")  # fmt: skip
    s.add_argument("--heldout-sequences", type=int, help="motion sequences per subject in the heldout split: "
                   "test-style motions from other seeds, for a last check (default: the preset's)")  # fmt: skip
    s.add_argument("--frames", type=int, help="stored frames per sequence (default: the preset's)")
    s.add_argument("--points", type=int, help="points stored per frame (default: the preset's)")
    s.add_argument("--frame-storage", choices=FRAME_STORAGES,
                   help="float32: exact, uncompressed frame files; compact: deflated, float16 normals and skinning "
                        "transforms, positions within 0.1 mm, ~37%% of the bytes (default: the preset's, float32)")  # fmt: skip
    s.add_argument("--cloth", choices=tuple(CLOTH_VERSIONS), default=CURRENT_CLOTH,
                   help="the cloth of a data version: v4 (achiral mesh, air drag with the drag of small "
                        "oscillations, fabric damping, cloth-skin friction, accelerated sweeps: hanging cloth comes "
                        "to rest; the shipped models are trained on it), v3 (steady drag only, plain sweeps), v2 "
                        "(isotropic mesh, undamped), v1 (the first grid meshes, world frame), to reproduce older "
                        "datasets (default: %(default)s)")  # fmt: skip
    s.add_argument("--cloth-damping", choices=DAMPING_MODELS,
                   help="override the damping alone: none (data v1 / v2: no air, almost no damping); physical "
                        "(v3: air drag, the fabric's damping and cloth-skin friction, synth.fabric); unsteady "
                        "(v4: physical and the drag of small oscillations) "
                        "(default: that of --cloth)")  # fmt: skip
    g = s.add_argument_group("shards (big datasets; README: Generating big datasets on a cluster)")
    g.add_argument("--shard", metavar="K/N",
                   help="generate only shard K of N (a fixed, cost-balanced share of the sequences) into --out; "
                        "shards may run at once (on a shared filesystem); the card is left incomplete")  # fmt: skip
    g.add_argument("--finalize-only", action="store_true",
                   help="write the card of a dataset whose shards are all done, generating nothing "
                        "(a one-line error saying how many sequences are missing otherwise)")  # fmt: skip
    g.add_argument("--launch", choices=BACKENDS,
                   help="submit --shards jobs through submitit (slurm: a job array; local: subprocesses here), "
                        "wait for them and write the card; rerun to resume (needs pocoloco[cluster])")  # fmt: skip
    g.add_argument("--shards", type=int, help="with --launch: number of shards (jobs)")
    g.add_argument("--cpus-per-shard", type=int, help="with --launch: CPUs per job, as many worker processes (default 1)")
    g.add_argument("--slurm-partition", help="with --launch slurm: the partition (default: the cluster's)")
    g.add_argument("--slurm-time", type=int, metavar="MIN",
                   help=f"with --launch slurm: time limit per job in minutes (default {LaunchSettings.time_minutes})")  # fmt: skip
    g.add_argument("--log-dir", help="with --launch: submitit's job files and logs (default: OUT/.submitit)")
    s.set_defaults(func=cmd_data_synth)

    s = data.add_parser("heldout", help="draw (or extend) a dataset's heldout split: test-style motions from "
                        "new seeds, generated with the dataset's own settings; train and test untouched")  # fmt: skip
    s.add_argument("path", help="a dataset made by `pocoloco data synth`")
    s.add_argument("--sequences", type=int, default=2, help="heldout sequences per subject (default 2)")
    s.add_argument("--workers", type=int, default=1, help="parallel worker processes (default 1)")
    s.set_defaults(func=cmd_data_heldout)

    s = data.add_parser("histories", help="reference sets of true states: for N frames of a split, K cloth states "
                        "at exactly that frame's body, each reached by another motion (the distribution judge's "
                        "truth; resumable)")  # fmt: skip
    s.add_argument("path", help="a dataset made by `pocoloco data synth`")
    s.add_argument("--out", required=True, help="output folder (a dataset: `data info` / `data verify` read it); "
                   "rerun the same command to resume")  # fmt: skip
    s.add_argument("--split", default="test", choices=("test", "heldout"), help="frames of this split (default test)")
    s.add_argument("--poses", type=int, default=24, help="frames, spread over every subject (default 24)")
    s.add_argument("--histories", type=int, default=8, help="cloth states per frame and window (default 8)")
    s.add_argument("--shared-seconds", type=float, nargs="+", default=[0.0, 2.0],
                   help="windows: seconds of the frame's own motion every history shares before it (0: the pose "
                        "alone; default 0 2)")  # fmt: skip
    s.add_argument("--seed", type=int, default=0, help="seed of the frames, prefix motions and capture (default 0)")
    s.add_argument("--subjects", nargs="+", help="only frames of these subjects (default: every subject)")
    s.add_argument("--workers", type=int, default=1, help="parallel worker processes (default 1)")
    s.add_argument("--shard", metavar="K/N", help="make only every N-th history (all its windows) from the K-th "
                   "(shards may run at once into --out; the one that finds all done writes the card)")  # fmt: skip
    s.set_defaults(func=cmd_data_histories)

    s = data.add_parser("motion-history", help="store every sequence's whole body motion (the warm-up and blend "
                        "from rest before the first stored frame too), from which --motion-window models cut each "
                        "frame's window (a dataset made by `pocoloco data synth`; resumable)")  # fmt: skip
    s.add_argument("path", help="a dataset made by `pocoloco data synth`")
    s.set_defaults(func=cmd_data_motion_history)

    s = data.add_parser("info", help="print a dataset's card as tables (and whether its frame files are all there)")
    s.add_argument("path", help="dataset folder (holds card.json)")
    s.set_defaults(func=cmd_data_info)

    s = data.add_parser("verify", help="check every frame file against the card: missing, extra, truncated or "
                                       "corrupt frames (exit 2 if any)")  # fmt: skip
    s.add_argument("path", help="dataset folder (holds card.json)")
    s.add_argument("--record", action="store_true",
                   help="if every frame is fine and card.json records no checksums (an older dataset), record them")  # fmt: skip
    s.add_argument("--max-rows", type=int, default=20, help="bad frames listed in the table (default 20, 0 = all)")
    s.set_defaults(func=cmd_data_verify)

    s = data.add_parser("preview", help="PNG grid of rendered frames coloured by label")
    s.add_argument("path", help="dataset folder")
    s.add_argument("--out", help="PNG path (default: PATH/preview_SPLIT.png)")
    s.add_argument("--num", type=int, default=4, help="frames per subject, evenly spaced (default 4)")
    s.add_argument("--split", default="train", choices=SPLITS, help="split to show (default train)")
    s.add_argument("--seed", type=int, default=0, help="seed of the point subsets drawn (default 0)")
    s.add_argument("--subject", help="only these subjects, comma-separated, in this order (default: all)")
    s.add_argument("--front-only", action="store_true", help="front views only (default: front and side)")
    s.set_defaults(func=cmd_data_preview)

    s = data.add_parser("export", help="write frames as PLY (points, normals, labels) or POP-style NPZ")
    s.add_argument("path", help="dataset folder")
    s.add_argument("--out", required=True, help="output folder (created)")
    s.add_argument("--format", choices=["ply", "npz"], default="ply",
                   help="ply: points, normals, labels; npz: POP's packed training file (default ply)")  # fmt: skip
    s.add_argument("--split", default="test", choices=SPLITS, help="split to export (default test)")
    s.add_argument("--subject", help="only this subject (default: all)")
    s.add_argument("--limit", type=int, default=0, help="at most this many frames (default 0 = all)")
    s.set_defaults(func=cmd_data_export)

    s = data.add_parser("import", help="convert a LOOSE/DynaCap-style sequence (one .ply per frame + a joints text file)")
    s.add_argument("ply_dir", help="folder with one .ply per frame (frame id = last integer in the file name); "
                   + CLOUD_CHECK_HELP)
    s.add_argument("--joints", required=True, help="text file: per line a frame id then 3 x 24 floats")
    s.add_argument("--out", required=True, help="dataset folder (created or extended; left as it was if the import fails)")
    s.add_argument("--subject", required=True, help="subject name in the dataset")
    s.add_argument("--split", default="train", choices=SPLITS, help="split to import into (default train)")
    s.add_argument("--sequence", help="sequence name (default: the ply folder's name)")
    s.set_defaults(func=cmd_data_import)

    s = data.add_parser("pack", help="one compact file with what a model's training reads (for a remote GPU): "
                                     "a subset of frames and points, quantised; `pocoloco train --data FILE` takes it")  # fmt: skip
    s.add_argument("path", help="dataset folder")
    s.add_argument("--out", required=True, help="pack file to write (e.g. medium.pack)")
    s.add_argument("--splits", nargs="+", default=["train"], choices=SPLITS,
                   help="splits to pack (default train; test / heldout give training previews and validation)")  # fmt: skip
    s.add_argument("--every", type=int, default=1, help="keep every K-th frame of each train sequence (default 1: all; "
                                                        "frames matter more than points, BENCHMARKS.md)")  # fmt: skip
    s.add_argument("--eval-every", type=int, default=20,
                   help="keep every K-th frame of each test / heldout sequence (default 20)")  # fmt: skip
    s.add_argument("--points", type=int, default=512,
                   help="points per frame, drawn uniformly without replacement (default 512, the training clouds' "
                        "size; a recipe with more points per cloud needs at least that many)")  # fmt: skip
    s.add_argument("--resolution-mm", type=float, default=1.0, help="position quantisation step in mm (default 1)")
    s.add_argument("--subjects", help="only these subjects, comma-separated (default: all)")
    s.add_argument("--velocity", action="store_true", help="also store joint velocities (for --joint-velocity models)")
    s.add_argument("--motion", action="store_true",
                   help="also store every packed sequence's whole motion (for --motion-window models; ~1-2 %% of a "
                        "pack's bytes)")  # fmt: skip
    s.add_argument("--bodies", action="store_true",
                   help="also store the points' normals and each frame's posed body and posed mean shape, as 24 "
                        "skinning transforms (what POP and CloSET train on; needs anny)")  # fmt: skip
    s.add_argument("--seed", type=int, default=0, help="seed of the point subsets (default 0)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing pack file")
    s.set_defaults(func=cmd_data_pack)
