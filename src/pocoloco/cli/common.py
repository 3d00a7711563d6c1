"""What the commands share: user-error handling (one line, exit 2), devices and threads, loading a
model from ``--ckpt``, progress bars and the options of the apps."""

from __future__ import annotations

import argparse
import errno
import os
import re
import sys
import warnings
from contextlib import contextmanager

import torch

from pocoloco.diffusion.samplers import SAMPLER_STEPS
from pocoloco.engine.shipped import resolve_ckpt_arg
from pocoloco.methods import Method, load_method
from pocoloco.utils.atomic import output_folder
from pocoloco.utils.progress import Progress
from pocoloco.utils.hardware import bf16_is_fast

__all__ = ["EXIT_USER_ERROR", "MAX_SEED", "USER_ERRORS", "add_any_pose_argument", "check_seeds", "add_bf16_argument", "add_even_argument", "resolve_bf16", "add_app_arguments", "add_device_argument", "add_threads_argument",
           "apply_threads", "check_app_args", "choose_device", "pick_outfit", "steps_defaults", "console", "load_method_from_args", "progress_bar",
           "run_command"]  # fmt: skip

EXIT_USER_ERROR = 2
#: Exceptions that mean the user gave something wrong (a path, a file, a value).
USER_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError)


def console(stderr: bool = False):
    """A rich console (colours only on a terminal)."""
    from rich.console import Console

    return Console(stderr=stderr)


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"pocoloco: warning: {str(message).splitlines()[0]}", file=sys.stderr if file is None else file)


def run_command(func, args: argparse.Namespace, prog: str = "pocoloco") -> int:
    """Run one command; a user error becomes one line ``PROG: error: ...`` and exit code 2
    (``POCOLOCO_DEBUG=1`` shows the traceback instead); library warnings print as one line.
    ``--ckpt`` / ``--init-from`` options naming a shipped model (``default``, ``default:pop`` ...) are
    resolved first."""
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
            for name, value in vars(args).items():  # --ckpt[-pop|...] default / default:pop / default:closet
                if (name in ("ckpt", "init_from", "attached", "free", "maps") or name.startswith("ckpt_")) and isinstance(value, str):
                    setattr(args, name, str(resolve_ckpt_arg(value)))
            apply_threads(getattr(args, "threads", None))
            check_seeds(args)
            func(args)
    except (*USER_ERRORS, OSError) as e:  # every OSError: the OS refused a path the user gave us
        if os.environ.get("POCOLOCO_DEBUG"):
            raise
        print(f"{prog}: error: {error_line(e)}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


#: the hidden temporary file of an atomic write (``utils.atomic``): ``.NAME.<12 hex>.tmp``
_TMP_NAME = re.compile(r"^\.(?P<name>.+)\.[0-9a-f]{12}\.tmp$")
_OS_ERRORS = {
    errno.EEXIST: "already exists",
    errno.ENOENT: "no such file or folder",
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.ENOSPC: "no space left on the device",
    errno.EROFS: "the filesystem is read-only",
    errno.ENOTDIR: "a part of this path is a file, not a folder",
    errno.EISDIR: "is a folder, not a file",
    errno.ENAMETOOLONG: "a file or folder name in this path is longer than the filesystem allows (255 bytes)",
}


def user_path(path: str | os.PathLike) -> str:
    """The path the user named: for the hidden temporary file of an atomic write, its destination."""
    head, tail = os.path.split(os.fspath(path))
    m = _TMP_NAME.match(tail)
    return os.path.join(head, m["name"]) if m else os.fspath(path)


def error_line(e: BaseException) -> str:
    """One line for a user error; an ``OSError`` with a path names the user's path and the reason
    in words (``out/x: already exists``), never a hidden temporary file."""
    if isinstance(e, OSError) and e.errno is not None and e.filename is not None:
        path = user_path(e.filename)
        reason = _OS_ERRORS.get(e.errno, e.strerror or type(e).__name__)
        if e.errno == errno.EEXIST and os.path.isfile(path):
            reason = "already exists and is a file (name a folder that does not exist yet)"
        shown = f"{path[:60]}...{path[-40:]}" if len(path) > 120 else path
        return f"{shown}: {reason}"
    msg = str(e).splitlines()[0] if str(e) else type(e).__name__
    return msg


# ------------------------------------------------------------------------- devices, threads
def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default: torch's, all cores; 1 makes runs bit-reproducible)")  # fmt: skip


#: the largest seed a command takes: numpy and torch take seeds below 2**63; output k uses SEED + k
MAX_SEED = 2**62


def check_seeds(args: argparse.Namespace) -> None:
    """``--seed`` / ``--seeds``: one line unless 0 <= seed <= MAX_SEED (before any work)."""
    for name in ("seed", "seeds"):
        value = getattr(args, name, None)
        for seed in value if isinstance(value, (list, tuple)) else [value]:
            if seed is not None and not 0 <= seed <= MAX_SEED:
                raise ValueError(f"--{name} must be in [0, 2**62], got {seed}")


def apply_threads(threads: int | None) -> None:
    """``--threads N``: torch's CPU threads (a one-line error below 1)."""
    if threads is None:
        return
    if isinstance(threads, bool) or threads < 1:
        raise ValueError(f"--threads must be >= 1, got {threads}")
    torch.set_num_threads(int(threads))


def add_any_pose_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--any-pose", action="store_true",
                        help="accept joints that do not look like a human skeleton in metres (default: a "
                             "one-line error; for experiments)")  # fmt: skip


def add_bf16_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                        help="run the denoiser under bf16 autocast (sampler arithmetic stays float32); default: on "
                             "where it runs natively (CPUs with avx512_bf16 / AMX, recent GPUs), off elsewhere")  # fmt: skip


def add_finish_argument(parser: argparse.ArgumentParser) -> None:
    """``--finish-t`` (``sample``, ``eval``, ``bench quality``, ``bench distribution``): a diffusion
    model's own finishing call (:class:`pocoloco.methods.SamplerOptions`)."""
    parser.add_argument("--finish-t", type=int, default=None, metavar="T",
                        help="after the sampler's chain, re-noise each cloud to step T (of 1,000) and take the "
                             "network's own estimate there: one call more, which undoes the slight shrinking of "
                             "the chain's last estimate (5 is the measured best; default: off)")  # fmt: skip


def add_even_argument(parser: argparse.ArgumentParser) -> None:
    """``--even`` (``sample``, ``eval``, ``bench quality``): :func:`pocoloco.methods.predict_clouds`."""
    parser.add_argument("--even", action="store_true",
                        help="spread each cloud's points evenly over its surface: draw more points (POP: every pixel "
                             "of its UV map; CloSET 4x; PocoLoco 4x, 2x beyond 4,096 points) and keep N by "
                             "farthest-point sampling (any method; slow beyond ~10K points; default: each method's "
                             "own random points)")  # fmt: skip


def resolve_bf16(flag: bool | None, device) -> bool:
    """``--bf16`` / ``--no-bf16`` as given, else whether bf16 runs natively on ``device``."""
    return bf16_is_fast(device) if flag is None else bool(flag)


def add_device_argument(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    parser.add_argument("--device", default=default,
                        help="cpu, cuda, cuda:1 (default: " + (default or "cuda if available, else cpu") + ")")  # fmt: skip


def choose_device(arg: str | None) -> torch.device:
    """``--device``: the given device (a one-line error if CUDA is asked for and missing), else
    CUDA when available, else the CPU. Only entry points choose the device."""
    if arg is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(arg)
    except RuntimeError:
        raise ValueError(f"--device {arg}: not a device (cpu, cuda, cuda:1 ...)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {arg}: CUDA is not available")
    return device


def pick_outfit(method: Method, outfit: str | None, spec: str | None) -> int | None:
    """``--outfit``'s id (:meth:`pocoloco.methods.Method.choose_outfit`)."""
    return method.choose_outfit(outfit, spec)


def load_method_from_args(args: argparse.Namespace, expect: str | tuple[str, ...] | None = None) -> Method:
    """The model of ``--ckpt`` on ``--device`` (``--raw-weights``: the raw weights instead of the EMA)."""
    device = choose_device(getattr(args, "device", None))
    return load_method(args.ckpt, device=device, use_ema=not getattr(args, "raw_weights", False), expect=expect)


@contextmanager
def progress_bar(label: str, total: int | None = None, loss: bool = False, transient: bool = True):
    """A rich progress bar on a terminal (stderr); in a log a plain line every minute instead
    (``utils.progress.Progress``). Yields ``update(done, total=None, **fields)``."""
    with Progress(label, total, loss=loss, transient=transient) as bar:
        yield bar.update


# ------------------------------------------------------------------------------------- the apps
def steps_defaults() -> str:
    """``dpm++sde 25, ddpm 100, ...``: every sampler's default step count, for help texts."""
    return ", ".join(f"{k} {v}" for k, v in SAMPLER_STEPS.items())


def add_app_arguments(parser: argparse.ArgumentParser, out_help: str) -> None:
    """--ckpt, --sampler, --steps, --seed, --raw-weights, --device, --threads, --no-render, --out."""
    parser.add_argument("--ckpt", default="default",
                        help="checkpoint / run folder of a PocoLoco model; 'default' = the model shipped with pocoloco")  # fmt: skip
    parser.add_argument("--sampler", default="dpm++sde",
                        help=f"one of {', '.join(SAMPLER_STEPS)} (default dpm++sde)")  # fmt: skip
    parser.add_argument("--steps", type=int, help=f"sampler steps (default: {steps_defaults()}; at most t)")
    parser.add_argument("--seed", type=int, default=0, help="output k uses seed SEED + k (default 0)")
    parser.add_argument("--outfit", help="models that know who wears what: outfit name or id (default: the subject "
                                         "of a DATASET:... pose or motion, or the outfit a demo:NAME pose was captured on)")  # fmt: skip
    parser.add_argument("--raw-weights", action="store_true", help="use the raw weights instead of the EMA")
    add_any_pose_argument(parser)
    add_device_argument(parser)
    add_threads_argument(parser)
    parser.add_argument("--no-render", action="store_true", help="skip the PNG / GIF")
    parser.add_argument("--out", required=True, help=out_help)


def check_app_args(args: argparse.Namespace) -> None:
    """One-line errors for the options of :func:`add_app_arguments` (before any work)."""
    if args.sampler not in SAMPLER_STEPS:
        raise ValueError(f"unknown sampler {args.sampler!r}; choose one of: {', '.join(SAMPLER_STEPS)}")
    if args.steps is not None and args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    output_folder(args.out)
