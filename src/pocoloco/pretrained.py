"""The PocoLoco model shipped with the package (``--ckpt default``).

``assets/pocoloco_small/`` holds a sampling-only checkpoint (``meta.json`` + the EMA weights as
``model.safetensors``) of the ``small`` preset trained on the ``small`` synthetic dataset; how it
was trained and its evaluation are in README.md ("The default model"). Written by
:func:`pocoloco.checkpoint.export_for_sampling`.
"""

from __future__ import annotations

from pathlib import Path

DEFAULT_MODEL_DIR = Path(__file__).resolve().parent / "assets" / "pocoloco_small"
#: (24, 3) joints in metres of one test frame per subject of the ``small`` dataset (frame 40 of
#: its test sequence), usable as ``--joints demo:NAME``
DEMO_POSES_DIR = Path(__file__).resolve().parent / "assets" / "poses"


def demo_pose_names() -> list[str]:
    """Names of the shipped demo poses (``skirt``, ``shirt``, ``tight``)."""
    return sorted(p.stem for p in DEMO_POSES_DIR.glob("*.npy"))


def demo_pose_path(name: str) -> Path:
    """The .npy of a shipped demo pose; a one-line error naming the known ones otherwise."""
    path = DEMO_POSES_DIR / f"{name}.npy"
    if not path.is_file():
        raise ValueError(f"demo:{name}: no such demo pose; choose one of: {', '.join(demo_pose_names())}")
    return path


def default_checkpoint() -> Path:
    """Folder of the shipped checkpoint; a one-line error if this installation lacks it."""
    if not (DEFAULT_MODEL_DIR / "meta.json").is_file():
        raise ValueError(f"{DEFAULT_MODEL_DIR}: the default model is not installed with this copy of pocoloco")
    return DEFAULT_MODEL_DIR


def resolve_ckpt_arg(ckpt: str | None) -> str | Path | None:
    """``"default"`` -> the shipped checkpoint; anything else unchanged."""
    return default_checkpoint() if ckpt == "default" else ckpt
