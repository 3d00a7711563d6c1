"""``pocoloco train``: any method, one loop (:mod:`pocoloco.engine.trainer`); also what ``torchrun``
launches (``torchrun --nproc_per_node=2 -m pocoloco train ...``: DDP, gloo on CPU, NCCL on GPUs).
Every run ends with a sampling-only copy of its last checkpoint in ``RUN/model`` (``--ckpt RUN/model``)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shutil
from pathlib import Path

import torch
import torch.distributed as dist

from pocoloco.cli.common import add_threads_argument, choose_device, console, progress_bar, resolve_bf16
from pocoloco.data.dataset import OpenedDataset
from pocoloco.data.pack import is_pack, read_pack_meta, training_card
from pocoloco.diffusion.schedules import PREDICTION_TYPES
from pocoloco.engine.trainer import (
    LR_SCALING_RULES,
    check_run_folder,
    dist_info,
    init_distributed,
    load_initial_weights,
    scaled_lr,
)
from pocoloco.engine.trainer import train as run_training
from pocoloco.engine.checkpoint import latest_checkpoint
from pocoloco.methods import METHODS, method_class
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.methods.hybrid import FreeRegionMaps, assemble_hybrid, learn_free_maps
from pocoloco.methods.hybrid.training import train_free_generator, write_free_pack
from pocoloco.methods.pocoloco.config import SCHEDULE_KINDS
from pocoloco.methods.pocoloco.distill import prepare_distillation
from pocoloco.utils.atomic import exclusive_lock, output_folder
from pocoloco.methods.registry import config_from_checkpoint

__all__ = ["register"]

#: command-line option -> train config field (a method whose config lacks the field refuses the option)
FIELD_OPTIONS = {
    "steps": "steps", "batch_size": "batch_size", "lr": "lr", "num_points": "num_points", "seed": "seed",
    "ckpt_every": "ckpt_every", "sample_every": "sample_every", "log_every": "log_every", "bf16": "bf16",
    "ema_decay": "ema_decay", "grad_clip": "grad_clip", "schedule": "schedule", "prediction_type": "prediction_type",
    "min_snr": "min_snr_gamma", "workers": "num_workers", "normal_start": "normal_start",
    "query_points": "query_points", "subjects": "subjects", "outfit_codes": "outfit_codes",
    "body_shape": "body_shape", "body_points": "body_points", "canonical_heading": "canonical_heading",
    "joint_velocity": "joint_velocity", "motion_window": "motion_window", "history_dropout": "history_dropout",
    "motion_lr_scale": "motion_lr_scale", "freeze_trunk": "freeze_trunk",
    "lr_schedule": "lr_schedule", "decay_steps": "decay_steps",
}  # fmt: skip


def _preset_defaults(field: str) -> str:
    """``pocoloco small 20000, pop small 10000, ...``: the ``small`` presets' value of a field."""
    out = []
    for kind, cls in METHODS.items():
        preset = cls.presets().get("small")
        if preset is not None and hasattr(preset, field):
            out.append(f"{kind} {getattr(preset, field)}")
    return "; default (small preset): " + ", ".join(out) if out else ""


def _fields(kind: str) -> set[str]:
    return {f.name for f in dataclasses.fields(method_class(kind).train_config)}


def _applies_to(field: str) -> str:
    return " / ".join(k for k in METHODS if field in _fields(k))


def _config_from_args(args: argparse.Namespace):
    """The run's config: the preset (or, with ``--resume`` or ``--init-from`` and no ``--preset``, the
    checkpoint's) with the options given; an option the method has no use for is a one-line error."""
    cls = method_class(args.model)
    have = _fields(args.model)
    overrides = {}
    for option, field in FIELD_OPTIONS.items():
        value = getattr(args, option, None)
        if value is None:  # not given (flags default to None; --no-bf16 gives False)
            continue
        if field not in have:
            raise ValueError(f"--{option.replace('_', '-')} applies to --model {_applies_to(field)} only")
        overrides[field] = value
    extra = {}
    if args.no_decomposition:
        takers = [k for k, c in METHODS.items() if "decomposition" in getattr(c, "train_options", ())]
        if args.model not in takers:
            raise ValueError(f"--no-decomposition applies to --model {' / '.join(takers)} only")
        extra["decomposition"] = False
    if args.preset is None and args.resume:
        root = Path(args.out) / "checkpoints"
        if check_run_folder(args.out, resume=True) is None:  # raises the one-line error
            raise ValueError(f"{args.out}: --resume but no checkpoint in {root}")
        if extra:
            raise ValueError("--no-decomposition cannot change on --resume (it comes from the checkpoint)")
        return config_from_checkpoint(root, args.model, **overrides)
    if args.preset is None and args.init_from is not None and not args.resume:
        if extra:
            raise ValueError("--no-decomposition cannot change with --init-from (the network comes from the checkpoint)")
        # the machine's settings do not travel with the weights: a fine-tune of a GPU-trained model on
        # a CPU without native bf16 would otherwise run its forward pass emulated (~10x slower here)
        # and start a GPU run's loader processes
        # nor does a frozen trunk: a fine-tune of a --freeze-trunk model trains every weight unless told
        machine_bf16 = cls.trains_in_bf16 and resolve_bf16(None, choose_device(args.device))
        for field, value in (("bf16", machine_bf16), ("num_workers", 0), ("freeze_trunk", False)):
            if field in have and field not in overrides:
                overrides[field] = value
        return config_from_checkpoint(args.init_from, args.model, **overrides)
    if "batch_size" in overrides and "lr" not in overrides and args.lr_scaling != "none":
        base = cls.preset(args.preset or "small", **extra)
        overrides["lr"] = scaled_lr(base.lr, overrides["batch_size"], base.batch_size, args.lr_scaling)
    return cls.preset(args.preset or "small", **extra, **overrides)


def cmd_train(args: argparse.Namespace) -> None:
    """Validate everything (options, data, run folder), then print the banner and train."""
    # one line if --data is neither a dataset folder nor a training pack; a folder is opened once
    # (its card read here, its frames checked below) and handed down
    packed = is_pack(args.data)
    if packed:
        training_card(args.data)
        data = args.data
    else:
        data = OpenedDataset.open(args.data, subjects=[])
    config = _config_from_args(args)
    if getattr(config, "freeze_trunk", False) and args.init_from is None and not args.resume:
        raise ValueError("--freeze-trunk keeps every weight but the motion encoder's as initialised: give --init-from "
                         "CKPT (a trained model), or a frozen random network learns nothing")  # fmt: skip
    if packed and config.model != "pocoloco" and not read_pack_meta(args.data).get("bodies"):
        raise ValueError(f"--data {args.data}: --model {config.model} trains on posed bodies and normals, which this "
                         "pack does not hold: make it with `pocoloco data pack --bodies`, or train on the dataset folder")  # fmt: skip
    if not packed:
        data = data.ensure_checked(config.subjects)
    task = method_class(config.model).training_task(config, data)
    if args.time_budget is not None and not args.time_budget > 0:
        raise ValueError(f"--time-budget must be > 0 minutes, got {args.time_budget}")
    if args.init_from is not None and not args.resume:  # the weights fit this run's network (one line, before work)
        load_initial_weights(task.build_model(), args.init_from, task)
    if int(os.environ.get("RANK", "0")) != 0:  # torchrun: rank 0 holds the run folder's lock
        _train(args, config, task)
        return
    out = output_folder(args.out)
    with exclusive_lock(out, "pocoloco train") as lock:  # a second train into the same folder is refused
        check_run_folder(out, args.resume)  # under the lock: another run may have just written one
        fresh = all(p == lock for p in out.iterdir())
        try:
            _train(args, config, task)
        except Exception:  # a run that fails before its first checkpoint leaves only the lock, which
            if fresh and latest_checkpoint(out / "checkpoints") is None:  # takes a folder it made with it
                for p in out.iterdir():
                    if p == lock:
                        continue
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p)
                    else:
                        p.unlink()
            raise


def _train(args: argparse.Namespace, config, task) -> None:
    device, started = init_distributed(args.device)
    rank, world = dist_info()
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    if args.threads is None and device.type == "cpu" and "OMP_NUM_THREADS" not in os.environ:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // max(local_world, 1)))
    try:
        model = task.build_model() if rank == 0 else None
        if rank == 0:
            n_params = sum(p.numel() for p in model.parameters())
            del model
            console(stderr=True).print(
                f"[bold]pocoloco train[/] model={config.model} preset={config.preset} params={n_params:,} "
                f"device={device} world={world} threads={torch.get_num_threads()} steps={config.steps} "
                f"batch={config.batch_size}x{world} N={config.num_points} lr={config.lr:.3g}"
                + (f" budget={args.time_budget:g} min" if args.time_budget else "") + f" -> {args.out}"
            )  # fmt: skip
        result = run_training(task, args.out, device=device, resume=args.resume,
                              progress=not args.no_progress,
                              time_budget_s=None if args.time_budget is None else 60.0 * args.time_budget,
                              compile_model=args.compile, export_to=Path(args.out) / "model",
                              init_from=None if args.resume else args.init_from)  # fmt: skip
        if rank == 0:
            n_params = sum(p.numel() for p in result.model.parameters())
            why = " (time budget reached)" if result.stopped_by_budget else ""
            print(f"trained to step {result.step}{why} ({result.steps_per_s:.3f} steps/s, {n_params:,} parameters), "
                  f"loss {result.final_loss:.4f}; checkpoint {result.last_checkpoint}; model {result.export}")  # fmt: skip
    finally:
        if started:
            dist.destroy_process_group()


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco train`` options."""
    d = _preset_defaults
    parser.add_argument("--model", default="pocoloco", choices=list(METHODS),
                        help="method to train (default pocoloco: the diffusion model; pop / closet: its peers)")  # fmt: skip
    parser.add_argument("--data", required=True,
                        help="pocoloco dataset folder (trains on its train split), or for pocoloco a training pack "
                             "file (`pocoloco data pack`)")  # fmt: skip
    parser.add_argument("--preset", default=None,
                        help="training preset: tiny (tests), small (this CPU), paper (the paper's settings); pocoloco also "
                             "latent_tiny, latent_small, latent_base (one GPU), latent_paper (the linear-in-N latent network) "
                             "(default small; with --resume, the checkpoint's config)")  # fmt: skip
    parser.add_argument("--out", required=True, help="run folder (checkpoints, logs, samples)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the newest intact checkpoint in --out (bit-exact with one thread)")  # fmt: skip
    parser.add_argument("--steps", type=int, help="total optimiser steps" + d("steps"))
    parser.add_argument("--batch-size", type=int, help="clouds (frames) per step per process" + d("batch_size"))
    parser.add_argument("--lr", type=float, help="peak learning rate" + d("lr"))
    parser.add_argument("--lr-schedule", choices=("constant", "cosine", "wsd"),
                        help="after the warm-up: constant, cosine to 0 at --steps, or wsd: constant, then linear to 0 "
                             "over the last --decay-steps. A run may be resumed with another schedule or --steps if "
                             "the steps already taken keep their learning rates (e.g. a constant run cooled down "
                             "with wsd)" + d("lr_schedule"))  # fmt: skip
    parser.add_argument("--decay-steps", type=int, help="wsd: steps of the final linear decay (default 0: none; wsd needs > 0)")
    parser.add_argument("--num-points", type=int, help="points per training cloud (scan points for pop / closet)"
                        + d("num_points"))  # fmt: skip
    parser.add_argument("--seed", type=int, help="seed of everything random" + d("seed"))
    parser.add_argument("--ckpt-every", type=int, help="checkpoint period in steps, 0: only at the end" + d("ckpt_every"))
    parser.add_argument("--sample-every", type=int, help="rendered-preview period in steps, 0: never" + d("sample_every"))
    parser.add_argument("--log-every", type=int, help="metrics period in steps" + d("log_every"))
    parser.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                        help="bf16 autocast of the forward pass (pocoloco, closet; default off; --no-bf16 turns "
                             "off a checkpoint's bf16 with --resume / --init-from)")  # fmt: skip
    parser.add_argument("--init-from", metavar="CKPT",
                        help="fine-tune: start from this checkpoint's weights (e.g. default), with its training config "
                             "unless --preset is given (the network must match); step, optimiser and schedule start "
                             "afresh")  # fmt: skip
    parser.add_argument("--workers", type=int, help="DataLoader worker processes (default 0: load in the main process)")
    parser.add_argument("--ema-decay", type=float, help="EMA decay of the weights" + d("ema_decay"))
    parser.add_argument("--grad-clip", type=float, help="max gradient L2 norm" + d("grad_clip"))
    g = parser.add_argument_group("pocoloco only")
    g.add_argument("--schedule", choices=SCHEDULE_KINDS, help="beta schedule (default four = PocoLoco's quartic)")
    g.add_argument("--prediction-type", choices=PREDICTION_TYPES, help="network target (default epsilon)")
    g.add_argument("--min-snr", type=float, metavar="GAMMA", help="min-SNR-gamma loss weighting, e.g. 5 (default off)")
    g.add_argument("--outfit-codes", action="store_true", default=None,
                   help="condition on a learned code per subject's outfit (default off: joints only, as the paper)")  # fmt: skip
    g.add_argument("--body-shape", action="store_true", default=None,
                   help="condition on each subject's body shape, its anny phenotype (default off)")  # fmt: skip
    g.add_argument("--body-points", type=int, metavar="K",
                   help="latent presets: also condition on K vertices of the posed body, as POP and CloSET are "
                        "(sampling then needs a dataset frame or anny pose parameters, not bare joints; default 0: "
                        "the paper's skeleton only)")  # fmt: skip
    g.add_argument("--canonical-heading", action="store_true", default=None,
                   help="turn every frame about the vertical axis to face one way before normalising, and samples "
                        "back (not in the paper; default off)")  # fmt: skip
    g.add_argument("--joint-velocity", action="store_true", default=None,
                   help="latent presets: also condition on the joints' velocities (the neighbouring frame of the "
                        "sequence; the cloth follows the motion, not only the pose). Sampling takes them from a "
                        "DATASET: frame; other poses and the apps take the body at rest (not in the paper; default off)")  # fmt: skip
    g.add_argument("--motion-window", type=float, metavar="SECONDS",
                   help="latent presets: also condition on the last SECONDS of the body's motion (8 samples per "
                        "second; 2.0 is issue 41's window). Sampling takes it from a DATASET: frame or `sample "
                        "--motion`; other poses are taken at rest (not in the paper; default 0: the pose alone)")  # fmt: skip
    g.add_argument("--history-dropout", type=float, metavar="P",
                   help="with --motion-window: share of training frames shown at rest, so the model also samples "
                        "without motion (default 0.15)")  # fmt: skip
    g.add_argument("--motion-lr-scale", type=float, metavar="X",
                   help="with --motion-window: the motion encoder's learning rate in multiples of --lr (a fine-tune "
                        "from a pose-only model; default 1)")  # fmt: skip
    g.add_argument("--freeze-trunk", action="store_true", default=None,
                   help="with --motion-window and --init-from: train the motion encoder alone, every other weight "
                        "kept as the checkpoint's (what the run gains is the window's; default off)")  # fmt: skip
    parser.add_argument("--subjects", nargs="+",
                        help="train on these subjects only: one model per subject as the PocoLoco paper, or hold one "
                             "out for `pocoloco fit` (default: all)")  # fmt: skip
    g = parser.add_argument_group("pop / closet only")
    g.add_argument("--no-decomposition", action="store_true",
                   help="closet: one decoder instead of garment template + pose wrinkles (the paper's ablation)")  # fmt: skip
    g.add_argument("--normal-start", type=int,
                   help="first step with the normal loss (default: 62.5%% of --steps, as POP)")  # fmt: skip
    g.add_argument("--query-points", type=int, help="closet: surface points per training frame" + d("query_points"))
    parser.add_argument("--lr-scaling", choices=LR_SCALING_RULES, default="sqrt",
                        help="with --batch-size and no --lr: scale the preset's learning rate by sqrt(B / B_preset) "
                             "(Adam's rule), linearly, or not at all (default sqrt)")  # fmt: skip
    parser.add_argument("--time-budget", type=float, metavar="MINUTES",
                        help="stop after this many minutes of training (a leased machine): the last step's checkpoint "
                             "is written and the model exported as usual; the whole run's minutes (--resume goes on with "
                             "those its checkpoint records); with --lr-schedule wsd the decay also runs on "
                             "this clock (the last decay-steps/steps share of the budget), so the run ends cooled down "
                             "on a slower machine too; other schedules run to --steps (default: none)")  # fmt: skip
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile the forward pass (GPU; single process; default off)")  # fmt: skip
    parser.add_argument("--device", default=None, help="cuda, cuda:1, cpu (default: cuda if available, else cpu)")
    add_threads_argument(parser)
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (in a log, where stderr is not a terminal, the bar is a line a minute)")


def cmd_hybrid(args: argparse.Namespace) -> None:
    """``pocoloco hybrid``: learn the free-region maps (and, with ``--fine-tune``, fine-tune the
    free-region generator on a pack of them) and write the hybrid checkpoint."""
    for name in ("margin", "threshold", "generator_share"):
        if not math.isfinite(getattr(args, name)):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite number, got {getattr(args, name)}")
    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    if args.fine_tune is not None and not (math.isfinite(args.fine_tune) and args.fine_tune > 0):
        raise ValueError(f"--fine-tune must be > 0 minutes, got {args.fine_tune}")
    if args.pack_every < 1 or args.pack_points < 1:
        raise ValueError(f"--pack-every and --pack-points must be >= 1, got {args.pack_every} and {args.pack_points}")
    out = output_folder(args.out)
    with exclusive_lock(out, "pocoloco hybrid"):
        if latest_checkpoint(out / "checkpoints") is not None:
            raise ValueError(f"--out {out}: already holds a checkpoint (choose a new folder)")
        free, maps = args.free, args.maps
        if args.fine_tune is not None:
            free, maps = _fine_tuned_generator(args, out)
        with progress_bar("free-region maps", total=None) as update:
            ck = assemble_hybrid(args.attached, free, args.data, out, margin=args.margin, threshold=args.threshold,
                                 every=args.every, maps=maps, generator_share=args.generator_share,
                                 inside_tolerance=args.inside_tolerance, area_weighted=not args.no_area_weighting,
                                 far=args.far, trust=args.trust, link=args.link,
                                 progress=lambda done, total: update(done, total=total))  # fmt: skip
    print(f"wrote {ck} and the free-region maps {out / 'maps.npz'}, {out / 'maps.png'}; sample it with "
          f"`pocoloco sample --ckpt {out} --joints DATASET:subject/split/sequence/index`")  # fmt: skip


def _fine_tuned_generator(args: argparse.Namespace, out: Path) -> tuple[Path, Path]:
    """``pocoloco hybrid --fine-tune``'s stages in ``out`` (each kept, so a rerun after a kill goes
    on where it stopped): maps.npz, free.pack, free_generator/ (methods.hybrid.training). Returns
    (the fine-tuned generator, the maps file)."""
    maps_path, pack_path, run = out / "maps.npz", out / "free.pack", out / "free_generator"
    if args.maps is not None:
        maps = FreeRegionMaps.load(args.maps)
    elif maps_path.is_file():
        maps = FreeRegionMaps.load(maps_path)
    else:
        with progress_bar("free-region maps", total=None) as update:
            maps = learn_free_maps(args.data, margin=args.margin, threshold=args.threshold, every=args.every,
                                   progress=lambda done, total: update(done, total=total))  # fmt: skip
    maps.save(maps_path)
    if not pack_path.is_file():
        with progress_bar("free-region pack", total=None) as update:
            meta = write_free_pack(args.data, maps, pack_path, every=args.pack_every, points=args.pack_points,
                                   progress=lambda done, total: update(done, total=total))  # fmt: skip
        print(f"packed the free region of {', '.join(meta['packed'])}: {pack_path} ({meta['bytes'] / 1e6:.1f} MB)")
    if not (run / "model").is_dir():
        train_free_generator(pack_path, resolve_ckpt_arg(args.free), run, minutes=args.fine_tune,
                             device=choose_device(None), progress=not args.no_progress,
                             num_points=args.pack_points)  # fmt: skip
    return run / "model", maps_path


def add_hybrid_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--attached", required=True, metavar="CKPT", help="POP checkpoint: the attached region")
    parser.add_argument("--free", required=True, metavar="CKPT",
                        help="PocoLoco checkpoint: the free region (e.g. default, or one fine-tuned on a free-region "
                             "pack)")  # fmt: skip
    parser.add_argument("--data", required=True, help="the dataset both were trained on (the maps are learnt from it)")
    parser.add_argument("--out", required=True, help="run folder to write (checkpoints/, maps.npz, maps.png)")
    parser.add_argument("--maps", help="free-region maps to use instead of learning them: a .npz, or a hybrid checkpoint "
                                       "whose maps to reuse (e.g. default:hybrid)")  # fmt: skip
    parser.add_argument("--margin", type=float, default=0.03,
                        help="a body vertex is free in a frame when its nearest captured point is loose garment or "
                             "farther than this (metres; default 0.03)")  # fmt: skip
    parser.add_argument("--threshold", type=float, default=0.5,
                        help="free region: vertices free in more than this share of frames (default 0.5)")
    parser.add_argument("--every", type=int, default=60, help="learn the maps from every K-th train frame (default 60)")
    parser.add_argument("--generator-share", type=float, default=0.5,
                        help="of the free region's points, the share PocoLoco draws; POP draws the rest there "
                             "(default 0.5, the measured best trade-off; 1: the free region wholly generated)")  # fmt: skip
    parser.add_argument("--fine-tune", type=float, default=None, metavar="MINUTES",
                        help="first fine-tune --free on a pack of the free region's points for this many minutes "
                             "(stages maps.npz, free.pack, free_generator/ in --out; rerun the same command to go "
                             "on after a kill)")  # fmt: skip
    parser.add_argument("--pack-every", type=int, default=3, help="--fine-tune: pack every K-th train frame (default 3)")
    parser.add_argument("--pack-points", type=int, default=512,
                        help="--fine-tune: free-region points per packed frame, and per cloud in training (default 512)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (in a log: a line a minute)")
    add_threads_argument(parser)
    parser.add_argument("--no-area-weighting", action="store_true",
                        help="draw POP's points uniformly among its UV pixels (default: by the body area each "
                             "stands for)")  # fmt: skip
    parser.add_argument("--inside-tolerance", type=float, default=None, metavar="M",
                        help="draw again generated points deeper than M metres inside the posed body (default: "
                             "keep them)")  # fmt: skip
    parser.add_argument("--far", type=float, default=None, metavar="M",
                        help="points farther than M metres from the posed body belong to the free region whatever "
                             "their nearest body vertex (a hem swinging past a hand or a foot; default: the "
                             "nearest vertex alone)")  # fmt: skip
    parser.add_argument("--trust", type=float, default=None, metavar="M",
                        help="draw again generated points farther than M metres from POP's own points in the free "
                             "region (default: keep them)")  # fmt: skip
    parser.add_argument("--link", action="store_true",
                        help="store references to --attached and --free (the shipped models by name, others by "
                             "folder, each with its checksum) instead of copies of their weights, and the maps "
                             "thresholded: a checkpoint of kilobytes (how default:hybrid ships)")  # fmt: skip


def cmd_distill(args: argparse.Namespace) -> None:
    """``pocoloco distill``: teacher pairs, then the few-step student (issue 42)."""
    if args.time_budget is not None and not args.time_budget > 0:
        raise ValueError(f"--time-budget must be > 0 minutes, got {args.time_budget}")
    if is_pack(args.data):  # a training pack (pocoloco data pack): what a GPU lease can carry
        training_card(args.data)
        data = args.data
    else:
        data = OpenedDataset.open(args.data, subjects=[]).ensure_checked(None)
    device, _ = init_distributed(args.device)
    if args.threads is None and device.type == "cpu" and "OMP_NUM_THREADS" not in os.environ:
        torch.set_num_threads(max(1, os.cpu_count() or 1))
    overrides = {k: v for k, v in {"steps": args.steps, "batch_size": args.batch_size, "lr": args.lr,
                                   "distill_chamfer": args.chamfer_weight, "distill_renoised": args.renoised_share,
                                   "student_renoise": args.renoise, "distill_set": args.set_weight,
                                   "distill_renoised_targets": args.renoised_targets,
                                   "distill_chain": args.chain_weight, "distill_chain_calls": args.chain_calls,
                                   "distill_chain_grad": args.chain_grad,
                                   "distill_set_calls": args.set_calls}.items()
                 if v is not None}  # fmt: skip
    out = output_folder(args.out)
    with exclusive_lock(out, "pocoloco distill"):
        log = console(stderr=True).print
        resume = args.resume
        if resume and latest_checkpoint(Path(out) / "checkpoints") is None and (Path(out) / "pairs").is_dir():
            # killed while making the teacher pairs: they resume shard by shard, the student starts afresh
            log(f"{args.out}: no student checkpoint yet; the teacher pairs resume and the student starts from the teacher")
            resume = False
        check_run_folder(out, resume)
        log(f"[bold]pocoloco distill[/] teacher={args.ckpt} calls={args.calls} device={device} "
            f"threads={torch.get_num_threads()}" + (f" budget={args.time_budget:g} min" if args.time_budget else "")
            + f" -> {args.out}")  # fmt: skip
        with progress_bar("teacher pairs", args.pairs) as update:  # closed before the training loop's bar
            task = prepare_distillation(resolve_ckpt_arg(args.ckpt), data, out, calls=args.calls, pairs=args.pairs,
                                        pair_points=args.pair_points, teacher_sampler=args.teacher_sampler,
                                        teacher_steps=args.teacher_steps, draws=args.draws_per_frame,
                                        seed=args.seed, device=device, teacher_frame=args.teacher_frame,
                                        init_from=None if args.init_from is None else resolve_ckpt_arg(args.init_from),
                                        pair_progress=lambda d, n: update(d, n), **overrides)  # fmt: skip
        result = run_training(task, out, device=device, resume=resume, progress=True,
                              time_budget_s=None if args.time_budget is None else 60.0 * args.time_budget,
                              export_to=Path(out) / "model", init_from=None if resume else task.start)  # fmt: skip
        why = " (time budget reached)" if result.stopped_by_budget else ""
        print(f"distilled to step {result.step}{why} ({result.steps_per_s:.3f} steps/s), loss {result.final_loss:.4f}; "
              f"model {result.export} (sample with --ckpt {result.export} --steps 1 to {args.calls})")  # fmt: skip


def add_distill_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``pocoloco distill`` options."""
    parser.add_argument("--ckpt", default="default", help="the teacher: a PocoLoco checkpoint (default: default)")
    parser.add_argument("--data", required=True, help="the dataset the teacher was trained on (its train split), or "
                        "a training pack of it (pocoloco data pack)")  # fmt: skip
    parser.add_argument("--out", required=True, help="run folder (teacher pairs in OUT/pairs, the student in OUT/model)")
    parser.add_argument("--calls", type=int, default=4, help="network calls of the student's grid (default 4; it "
                        "samples with 1 to 4)")  # fmt: skip
    parser.add_argument("--pairs", type=int, default=1024, help="teacher pairs (default 1024)")
    parser.add_argument("--pair-points", type=int, default=512, help="points per pair cloud (default 512)")
    parser.add_argument("--teacher-sampler", default="dpm++", help="the teacher's deterministic sampler (default "
                        "dpm++, DPM-Solver++(2M) ODE)")  # fmt: skip
    parser.add_argument("--teacher-steps", type=int, default=20, help="its steps (a multiple of --calls; default 20)")
    parser.add_argument("--draws-per-frame", type=int, default=1, help="teacher pairs per training frame, each "
                        "from its own noise (default 1; > 1 for --set-weight)")  # fmt: skip
    parser.add_argument("--set-weight", type=float, default=None, help="weight of the set-level term: the energy "
                        "distance between a frame's student draws and the teacher's (the judge's embedding; keeps "
                        "the draws' spread; needs --draws-per-frame >= 2; default 0)")  # fmt: skip
    parser.add_argument("--set-calls", type=int, default=None, help="calls of the chain the set-level term runs "
                        "(1 .. --calls; default: the student's default sampler, e.g. 2 to keep the 2-call draws' "
                        "spread; shared with the chain term's chain when both run the same calls)")  # fmt: skip
    parser.add_argument("--chain-weight", type=float, default=None, help="weight of the chain term: each pair's "
                        "noise down the student's own --chain-calls sampler, scored by Chamfer against the teacher's answer "
                        "(the last call learns to mend the earlier ones; default 0)")  # fmt: skip
    parser.add_argument("--chain-calls", type=int, default=None, help="calls of the chain term's sampler (2 .. "
                        "--calls; default 2: 999 then 249)")  # fmt: skip
    parser.add_argument("--chain-grad", choices=("last", "all"), default=None, help="the chain term's gradient: "
                        "through its last call (default) or through every call (the earlier calls learn to hand "
                        "the last a state it can mend)")  # fmt: skip
    parser.add_argument("--teacher-frame", action="store_true", help="data of the teacher's subjects with another "
                        "normalisation (made with fewer train motions): take its poses in the teacher's frame")  # fmt: skip
    parser.add_argument("--steps", type=int, default=None, help="student training steps (default 2000)")
    parser.add_argument("--batch-size", type=int, default=None, help="pairs per step (default 16)")
    parser.add_argument("--lr", type=float, default=None, help="learning rate (default 5e-5)")
    parser.add_argument("--chamfer-weight", type=float, default=None, help="weight of the Chamfer term (default 1)")
    parser.add_argument("--renoised-share", type=float, default=None, help="share of the later-grid draws made as "
                        "the re-noising sampler makes them: the teacher's answer noised afresh, scored by Chamfer "
                        "(default 0)")  # fmt: skip
    parser.add_argument("--renoised-targets", choices=("answer", "ode"), default=None, help="the re-noised draws' "
                        "target: the teacher's answer they were noised from (answer, the default) or the teacher's "
                        "deterministic answer from the re-noised state (ode: made once beside the pairs, costs the "
                        "teacher (calls - 1) / 2 of the pairs' time; keeps the chain's draws apart)")  # fmt: skip
    parser.add_argument("--renoise", type=float, default=None, help="the student's sampler: share of fresh noise "
                        "when re-noising, 0 (deterministic) .. 1 (default 1)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="seed of the pairs' frames and noises and of the "
                        "training batches (default 0)")  # fmt: skip
    parser.add_argument("--init-from", default=None, metavar="STUDENT", help="start the student from this student "
                        "of the same teacher and calls instead of the teacher (e.g. default:fast, to train it longer; "
                        "default: the teacher's weights)")  # fmt: skip
    parser.add_argument("--resume", action="store_true", help="continue the run in --out (pairs and training)")
    parser.add_argument("--time-budget", type=float, default=None, help="stop training after this many minutes "
                        "of the whole run, --resume included (the learning rate cools down on the clock)")  # fmt: skip
    parser.add_argument("--device", default=None, help="cpu / cuda (default: cuda if available)")
    add_threads_argument(parser)


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("train", help="train a model on a dataset (PocoLoco diffusion, or POP / CloSET)")
    add_train_arguments(s)
    s.set_defaults(func=cmd_train)
    s = sub.add_parser("hybrid", help="assemble a hybrid model: POP where the cloth follows the body, PocoLoco where "
                                      "it hangs free (maps learnt from the data)")  # fmt: skip
    add_hybrid_arguments(s)
    s.set_defaults(func=cmd_hybrid)
    s = sub.add_parser("distill", help="distil a PocoLoco model into a few-step student (1-4 network calls)")
    add_distill_arguments(s)
    s.set_defaults(func=cmd_distill)
