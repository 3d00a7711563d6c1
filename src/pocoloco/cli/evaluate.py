"""``pocoloco eval`` (one checkpoint and the baselines) and ``pocoloco bench quality`` (every method
on the same frames)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pocoloco.cli.common import (
    add_bf16_argument,
    add_even_argument,
    add_finish_argument,
    add_threads_argument,
    console,
    progress_bar,
    resolve_bf16,
    steps_defaults,
)
from pocoloco.data import format as fmt
from pocoloco.diffusion.samplers import SAMPLER_STEPS
from pocoloco.engine.checkpoint import latest_checkpoint, read_meta
from pocoloco.evaluation.baselines import NEAREST_ALIGNS
from pocoloco.evaluation.evaluate import (
    GARMENT_COLUMNS,
    HISTORY_MODES,
    EvalSettings,
    evaluate,
    markdown_table,
    method_titles,
    write_outputs,
)
from pocoloco.evaluation.quality import (
    PER_SUBJECT_ROWS,
    QUALITY_ROWS,
    UNTRAINED_ROWS,
    bench_quality,
    check_quality_inputs,
    garment_table_markdown,
    table_markdown,
)
from pocoloco.evaluation.judge import JUDGE_HISTORY_MODES, bench_distribution
from pocoloco.methods import train, train_preset
from pocoloco.methods.registry import config_from_checkpoint
from pocoloco.utils.atomic import output_folder

__all__ = ["register"]


def add_history_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--history", choices=HISTORY_MODES, default="dataset",
                        help="the motion before each frame a --motion-window model is given: the frame's own "
                             "(dataset), none (rest: the body at rest), or another frame's of the same subject "
                             "(shuffled: is it the motion or the extra capacity?); pose-only models ignore it "
                             "(default dataset)")  # fmt: skip


def add_nearest_align_argument(parser: argparse.ArgumentParser) -> None:
    """``--nearest-align root|yaw`` (shared by ``eval`` and ``bench quality``)."""
    parser.add_argument("--nearest-align", choices=NEAREST_ALIGNS, default="root",
                        help="nearest-frame baseline: compare poses after moving the roots together (root, default) "
                             "or also turning about the vertical axis (yaw)")  # fmt: skip


def cmd_eval(args: argparse.Namespace) -> None:
    """Everything is validated (one-line errors) before the first sample."""
    if args.ckpt is None and not args.baselines_only:
        raise ValueError("--ckpt is required (or --baselines-only)")
    if args.ckpt is not None and args.baselines_only:
        raise ValueError("--ckpt and --baselines-only exclude each other")
    if args.no_baselines and args.baselines_only:
        raise ValueError("--no-baselines and --baselines-only exclude each other")
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    settings = EvalSettings(split=args.split, num_frames=args.frames, num_points=args.points, seeds=tuple(args.seeds),
                            sampler=args.sampler, steps=args.steps,
                            baselines=() if args.no_baselines else EvalSettings.baselines,
                            subjects=tuple(args.subjects) if args.subjects else None, batch_size=args.batch_size,
                            use_ema=not args.raw_weights, clip=args.clip or None, bf16=resolve_bf16(args.bf16, args.device),
                            nearest_align=args.nearest_align, outfit=args.outfit, even=args.even,
                            history=args.history, finish_t=args.finish_t)  # fmt: skip
    if settings.sampler not in SAMPLER_STEPS:
        raise ValueError(f"unknown sampler {settings.sampler!r}; choose one of: {', '.join(SAMPLER_STEPS)}")
    fmt.read_card(args.data)
    out = output_folder(args.out)
    with progress_bar("eval") as update:
        result, examples = evaluate(args.ckpt, args.data, settings, device=args.device, progress=update)
    write_outputs(out, result, examples)
    titles = method_titles(result.settings)
    print(markdown_table(result.means, titles))
    if any(k in m for k, _, _ in GARMENT_COLUMNS for m in result.means.values()):  # the scan has labels
        print()
        print(markdown_table(result.means, titles, GARMENT_COLUMNS))
    print(f"wrote {out / 'eval.json'}, {out / 'eval.md'}, {out / 'chamfer_per_frame.png'}, {out / 'examples.png'}")


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ckpt", help="checkpoint / run folder of any model; 'default' = the PocoLoco model shipped "
                                       "with pocoloco (default:pop, default:closet its peers, default:hybrid); omit with --baselines-only")  # fmt: skip
    parser.add_argument("--data", required=True, help="pocoloco dataset folder")
    parser.add_argument("--split", default="test", help="split to evaluate (default test)")
    parser.add_argument("--frames", type=int, default=24, help="frames evenly spaced over the split (0 = all; default 24)")
    parser.add_argument("--points", type=int, default=10_000, help="points per cloud (default 10000, as the paper)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="one sample per seed (default 0 1 2)")
    parser.add_argument("--sampler", default="dpm++sde", help=f"one of {', '.join(SAMPLER_STEPS)} (default dpm++sde, {SAMPLER_STEPS['dpm++sde']} steps)")
    parser.add_argument("--steps", type=int, help=f"sampler steps (default: {steps_defaults()})")
    parser.add_argument("--subjects", nargs="+", help="only these subjects (default: all)")
    parser.add_argument("--outfit", help="models with outfits: draw every frame in this trained outfit (e.g. a fitted one, "
                                         "or the nearest trained one for a subject the model never saw; default: each "
                                         "frame's subject)")  # fmt: skip
    add_even_argument(parser)
    add_finish_argument(parser)
    parser.add_argument("--no-baselines", action="store_true", help="skip the nearest-frame / posed-body / GT rows")
    parser.add_argument("--baselines-only", action="store_true", help="no model: only the baselines")
    add_nearest_align_argument(parser)
    add_history_argument(parser)
    parser.add_argument("--batch-size", type=int, default=4, help="clouds sampled together (default 4)")
    parser.add_argument("--raw-weights", action="store_true", help="use the raw weights instead of the EMA")
    parser.add_argument("--clip", type=float, default=5.0,
                        help="clamp the sampler's x0 estimates, normalised units (default 5; 0 = off; see pocoloco sample)")  # fmt: skip
    add_bf16_argument(parser)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1 (default cpu)")
    add_threads_argument(parser)
    parser.add_argument("--out", required=True, help="output folder (eval.json, eval.md, plots)")


def _train_missing(key: str, data, work: Path, steps: int, preset: str) -> Path:
    """Train (or resume / reuse) the quality row ``key`` for ``steps`` steps in ``work/key``; its newest
    checkpoint (``bench quality --train-steps``)."""
    run = work / key
    existing = latest_checkpoint(run / "checkpoints")
    if existing is not None and read_meta(existing)["step"] >= steps:
        return existing
    _, kind, decomposition = QUALITY_ROWS[key]
    if existing is not None:
        cfg = config_from_checkpoint(existing, kind, steps=steps)
    else:
        extra = {"decomposition": False} if decomposition is False else {}
        cfg = train_preset(kind, preset, steps=steps, sample_every=0, ckpt_every=max(steps // 4, 1), **extra)
    train(cfg, data, run, resume=existing is not None, progress=True)
    return latest_checkpoint(run / "checkpoints")


def cmd_bench_quality(args: argparse.Namespace) -> None:
    settings = EvalSettings(split=args.split, num_frames=args.frames, num_points=args.points, seeds=tuple(args.seeds),
                            sampler=args.sampler, steps=args.steps, clip=5.0, nearest_align=args.nearest_align,
                            subjects=tuple(args.subjects) if args.subjects else None, even=args.even,
                            history=args.history, finish_t=args.finish_t)  # fmt: skip
    con = console(stderr=True)
    ckpts = {key: getattr(args, f"ckpt_{key}") for key in QUALITY_ROWS}
    if args.train_steps is not None and (args.train_steps < 1 or args.work is None):
        raise ValueError("--train-steps needs a positive K and --work DIR")
    check_quality_inputs(args.data, ckpts, settings)  # every given input, before any training
    output_folder(args.out)
    trained = []
    if args.train_steps is not None:
        for key in QUALITY_ROWS:
            if ckpts.get(key) is None and key not in UNTRAINED_ROWS:
                con.print(f"[bold]training {QUALITY_ROWS[key][0]} for {args.train_steps} steps in {Path(args.work) / key}")
                ckpts[key] = _train_missing(key, args.data, Path(args.work), args.train_steps, args.preset)
                trained.append(key)
    report = bench_quality(args.data, ckpts, args.out, settings, device=args.device,
                           trained={"rows": trained, "train_steps": args.train_steps, "train_preset": args.preset},
                           progress=lambda m: con.print(f"[bold]{m}"))  # fmt: skip
    print(table_markdown(report["means"]))
    garment = garment_table_markdown(report["means"])
    if garment:
        print()
        print(garment)
    for c in report["claims"]:
        print(f"- {c['claim']}: {'holds' if c['holds'] else 'does not hold'}")
    if report["targets"]:
        print(f"PocoLoco's targets met: {sum(t['holds'] for t in report['targets'])} of {len(report['targets'])} "
              "(quality.md lists them)")  # fmt: skip
    out = Path(args.out)
    print(f"wrote {out / 'quality.json'}, {out / 'quality.md'}, {out / 'quality.png'}")


def add_bench_quality_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="pocoloco dataset")
    parser.add_argument("--split", default="test", help="split to evaluate (default test; heldout: motions drawn anew)")
    parser.add_argument("--subjects", nargs="+", help="only these subjects (default: all)")
    for key, (title, _, _) in QUALITY_ROWS.items():
        if key in PER_SUBJECT_ROWS:
            parser.add_argument(f"--ckpt-{key.replace('_', '-')}", dest=f"ckpt_{key}", nargs="+", metavar="CKPT",
                                help=f"{title}: checkpoints / run folders trained with --subjects, one per subject")  # fmt: skip
            continue
        parser.add_argument(f"--ckpt-{key.replace('_', '-')}", dest=f"ckpt_{key}",
                            help=f"{title} checkpoint / run folder, or 'default[:pop|:closet]' (shipped)")  # fmt: skip
    parser.add_argument("--train-steps", type=int, help="train missing models for K steps into --work")
    parser.add_argument("--work", help="folder for the runs trained by --train-steps (reused / resumed)")
    parser.add_argument("--preset", default="small", help="training preset of the missing models (default small)")
    parser.add_argument("--frames", type=int, default=24, help="frames evenly spaced over the split (0 = all; default 24)")
    parser.add_argument("--points", type=int, default=10_000, help="points per cloud (default 10000)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="PocoLoco samples per frame (default 0 1 2)")
    parser.add_argument("--sampler", default="dpm++sde", help=f"PocoLoco sampler (default dpm++sde, {SAMPLER_STEPS['dpm++sde']} steps)")
    parser.add_argument("--steps", type=int, help="PocoLoco sampler steps (default: the sampler's)")
    add_even_argument(parser)
    add_finish_argument(parser)
    add_nearest_align_argument(parser)
    add_history_argument(parser)
    add_threads_argument(parser)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1 (default cpu)")
    parser.add_argument("--out", required=True, help="output folder (quality.json, quality.md, quality.png)")


def cmd_bench_distribution(args: argparse.Namespace) -> None:
    from rich.markup import escape

    ckpts = {name: getattr(args, f"ckpt_{name}") for name in ("pocoloco", "pop", "closet", "hybrid")
             if getattr(args, f"ckpt_{name}")}  # fmt: skip
    if not ckpts:
        raise ValueError("no model to judge: give --ckpt-pocoloco / --ckpt-pop / --ckpt-closet / --ckpt-hybrid "
                         "(a folder or default, default:pop, ...)")  # fmt: skip
    outfits = {}
    for item in args.outfit or ():
        subject, sep, outfit = item.partition("=")
        if not sep or not subject or not outfit:
            raise ValueError(f"--outfit takes SUBJECT=OUTFIT (e.g. skirt=skirt_a), got {item!r}")
        outfits[subject] = outfit
    con = console()
    with progress_bar("poses", transient=True) as update:
        report = bench_distribution(args.refs, ckpts, args.out, samples=args.samples, points=args.points,
                                    probes=args.probes, seed=args.seed, device=args.device, sampler=args.sampler,
                                    steps=args.steps, outfits=outfits, history=args.history,
                                    finish_t=args.finish_t, progress=update)  # fmt: skip
    con.print(escape((Path(args.out) / "distribution.md").read_text()))
    con.print(f"wrote {escape(str(Path(args.out) / 'distribution.json'))} ({report['settings']['poses']} poses)")


def add_bench_distribution_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--refs", required=True, help="a reference set made by `pocoloco data histories`")
    for name, title in (("pocoloco", "PocoLoco"), ("pop", "POP"), ("closet", "CloSET"), ("hybrid", "the hybrid")):
        parser.add_argument(f"--ckpt-{name}", help=f"{title}: a checkpoint / run folder, or default names "
                            f"(default, default:pop, default:closet, default:hybrid)")  # fmt: skip
    parser.add_argument("--samples", type=int, default=16, help="clouds per pose of a generative model (default 16; "
                        "a deterministic model draws one)")  # fmt: skip
    parser.add_argument("--points", type=int, default=2048, help="points per cloud, true states cut to it too (default 2048)")
    parser.add_argument("--probes", type=int, default=512, help="probe points of the embedding (default 512)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the samples, probes and subsets (default 0)")
    parser.add_argument("--sampler", default="dpm++sde", help="PocoLoco's sampler (default dpm++sde)")
    parser.add_argument("--steps", type=int, help="its network calls (default: the sampler's)")
    add_finish_argument(parser)
    parser.add_argument("--history", choices=JUDGE_HISTORY_MODES, default="dataset",
                        help="a --motion-window model: the frame's own motion where the true states share it "
                             "(dataset), or never (rest: the same network without its window; default dataset)")  # fmt: skip
    parser.add_argument("--outfit", nargs="+", metavar="SUBJECT=OUTFIT", help="models with outfits: draw SUBJECT's "
                        "poses in OUTFIT (default: the subject's own name; e.g. skirt=skirt_a for `small` with the "
                        "medium models)")  # fmt: skip
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1 (default cpu)")
    parser.add_argument("--out", required=True, help="output folder (distribution.json, distribution.md)")


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("eval", help="score a checkpoint and the baselines on a dataset split (JSON + markdown + plots)")
    add_eval_arguments(s)
    s.set_defaults(func=cmd_eval)
    bench = sub.add_parser("bench", help="benchmarks over trained models").add_subparsers(
        dest="bench_command", required=True, metavar="{quality,distribution}")  # fmt: skip
    s = bench.add_parser("quality", help="PocoLoco, POP, CloSET (+/- decomposition) and baselines on the same test "
                                         "frames: quality.json / .md / .png")  # fmt: skip
    add_bench_quality_arguments(s)
    s.set_defaults(func=cmd_bench_quality)
    s = bench.add_parser("distribution", help="the distribution judge: every model against many true states per "
                                              "pose (`data histories`), a proper score: distribution.json / .md")  # fmt: skip
    add_bench_distribution_arguments(s)
    s.set_defaults(func=cmd_bench_distribution)
