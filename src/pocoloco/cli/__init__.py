"""The ``pocoloco`` command: entry points only (parse, check user input, call the library, report).

Nothing in the library imports this package. User mistakes (bad paths, malformed files, wrong
shapes, unknown presets) surface as one line ``pocoloco: error: ...`` and exit code 2
(:func:`pocoloco.cli.common.run_command`); set ``POCOLOCO_DEBUG=1`` to see the traceback.
``python -m pocoloco ARGS`` is the same command (what ``torchrun`` launches for DDP).
"""

from __future__ import annotations

import argparse
import sys

from pocoloco import __version__
from pocoloco.cli import apps, data, evaluate, sample, tools, train
from pocoloco.cli.common import EXIT_USER_ERROR, USER_ERRORS, run_command

__all__ = ["EXIT_USER_ERROR", "USER_ERRORS", "OneLineParser", "build_parser", "main", "run_command"]


class OneLineParser(argparse.ArgumentParser):
    """argparse, with its own errors (an unknown option, a value of the wrong type, a missing required
    option) as the one line every other user error gets, instead of the usage block; every
    sub-command's parser is one too (argparse builds them with the parent's class)."""

    def error(self, message: str):  # type: ignore[override]
        sys.stderr.write(f"pocoloco: error: {message} (`{self.prog} --help` lists the options)\n")
        raise SystemExit(EXIT_USER_ERROR)


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="pocoloco", description="Point-cloud models of humans in loose clothing.")
    p.add_argument("--version", action="version", version=f"pocoloco {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for module in (data, train, sample, apps, evaluate, tools):
        module.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    least = 0 if getattr(args, "func", None) is train.cmd_train else 1  # train: 0 loads in the main process
    if getattr(args, "workers", None) is not None and args.workers < least:
        parser.error(f"--workers must be >= {least}")
    return run_command(args.func, args)


if __name__ == "__main__":
    sys.exit(main())
