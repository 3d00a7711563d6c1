"""The registry of models shipped with the package (``--ckpt default``, ``default:pop``,
``default:closet``): where each lives under ``assets/`` and how to name it in reports.

Each folder holds a sampling-only checkpoint (``meta.json`` + ``model.safetensors``, the weights
stored as fp16 (CloSET's as per-row int8) and loaded as float32, their SHA-256 in the meta). ``assets/pocoloco_medium/`` is
PocoLoco's ``latent_small`` preset (the linear-in-N latent denoiser, outfit codes + body shape)
trained on the ``medium`` synthetic dataset (14 outfits, 7 garment kinds) on one GPU for 5.5 min
(EMA weights); ``assets/pop_medium`` POP (``small`` preset) trained on ``medium``, 10,000 steps on
one CPU thread; ``assets/closet_medium`` CloSET (``small`` preset) trained on ``medium``, 10,000
steps on one CPU thread; the peers' raw weights (they keep no EMA). All three were then fine-tuned
on a quarter of ``medium`` made with the data-v3 cloth, then on one made with the data-v4 cloth
(``scripts/finetune_medium.sh``: 40 / 15 / 25 CPU minutes each time). ``assets/hybrid_medium`` the hybrid of
the two (``default:pop`` + ``default``): its free-region maps and a link to each, no weights of its own
(``pocoloco hybrid --link``). ``assets/pocoloco_fast_medium`` (``default:fast``, issue 42) a
student distilled from ``default`` (``pocoloco distill``; docs/lab/fast.md) that samples
in 1 to 4 network calls, its default 4 of which the last is ``default``'s (``export-model --polish-with``), stored as per-row int8; ``assets/hybrid_fast_medium``
(``default:hybrid-fast``) the hybrid with that student as its free-region generator (``default:pop``
+ ``default:fast``, ``default:hybrid``'s maps, linked like it). A new ``default`` means a new
``default:fast`` (its teacher must be the very network it makes the last call with). How each was trained and its evaluation are in README.md ("The default
model", "POP and CloSET"). Written by :func:`pocoloco.engine.checkpoint.export_for_sampling`
(``pocoloco export-model``).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ASSETS_DIR", "SHIPPED_MODELS", "default_checkpoint", "describe_checkpoint", "resolve_ckpt_arg",
           "shipped_name"]

ASSETS_DIR = Path(__file__).resolve().parent.parent / "assets"
DEFAULT_MODEL_DIR = ASSETS_DIR / "pocoloco_medium"
#: ``--ckpt default:NAME`` -> folder under assets/ (``default`` alone is PocoLoco's)
SHIPPED_MODELS = {"pocoloco": "pocoloco_medium", "pop": "pop_medium", "closet": "closet_medium",
                  "hybrid": "hybrid_medium", "fast": "pocoloco_fast_medium", "hybrid-fast": "hybrid_fast_medium"}


def default_checkpoint(kind: str = "pocoloco") -> Path:
    """Folder of the shipped checkpoint ``kind`` (a key of :data:`SHIPPED_MODELS`); a one-line
    error if unknown or if this installation lacks it."""
    if kind not in SHIPPED_MODELS:
        raise ValueError(f"default:{kind}: no shipped model of that name; choose one of: "
                         + ", ".join(f"default:{k}" for k in SHIPPED_MODELS))  # fmt: skip
    path = ASSETS_DIR / SHIPPED_MODELS[kind]
    if not (path / "meta.json").is_file():
        raise ValueError(f"{path}: the default model is not installed with this copy of pocoloco ({kind})")
    return path


def shipped_name(path: str | os.PathLike) -> str | None:
    """``default`` / ``default:pop`` ... when ``path`` is a shipped model's folder, else None."""
    p = Path(path).resolve()
    for kind, folder in SHIPPED_MODELS.items():
        if p == (ASSETS_DIR / folder).resolve():
            return "default" if kind == "pocoloco" else f"default:{kind}"
    return None


def describe_checkpoint(path: str | os.PathLike) -> str:
    """How to name a checkpoint folder in reports: ``default:pop`` etc. for a shipped model, else
    the path relative to the working directory when it lies below it, else the path as given."""
    name = shipped_name(path)
    if name is not None:
        return name
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def resolve_ckpt_arg(ckpt: str | None) -> str | Path | None:
    """``"default"`` -> the shipped PocoLoco checkpoint, ``"default:pop"`` / ``"default:closet"`` /
    (/ ``"default:pocoloco"``) -> that shipped model; anything else unchanged."""
    if ckpt == "default":
        return default_checkpoint()
    if isinstance(ckpt, str) and ckpt.startswith("default:"):
        return default_checkpoint(ckpt.split(":", 1)[1])
    return ckpt
