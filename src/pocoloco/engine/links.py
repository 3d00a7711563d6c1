"""Links between checkpoints: a model that uses another checkpoint's weights by name instead of a
copy of them (a linked hybrid its POP and generator, ``pocoloco hybrid --link``; a distilled model
the teacher that makes its last call, ``pocoloco export-model --polish-with``). A link is
``{"ckpt": NAME, "meta_sha256": DIGEST}``: the source's shipped name (``default``, ``default:pop``
...: found wherever pocoloco is installed) or its folder's absolute path, and the digest of its
``meta.json`` (which holds its weight files' digests), so that a changed source is refused."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pocoloco.engine.checkpoint import Checkpoint, load_checkpoint, one_line
from pocoloco.engine.shipped import resolve_ckpt_arg, shipped_name

__all__ = ["link_name", "link_to", "load_linked"]


def link_name(path: str | os.PathLike) -> str:
    """How a link names a source checkpoint folder: ``default:pop`` / ``default`` for a shipped
    model, else the folder's absolute path."""
    return shipped_name(path) or os.fspath(Path(path).resolve())


def link_to(path: str | os.PathLike, meta: Mapping[str, Any], hint: str) -> dict[str, str]:
    """The link to the checkpoint folder ``path`` whose ``meta.json`` is ``meta``; an older checkpoint
    without checksums is a one-line error ending in ``hint`` (what to do instead)."""
    digest = meta.get("meta_sha256")
    if not digest:
        raise ValueError(f"{path}: an older checkpoint without checksums cannot be linked ({hint})")
    return {"ckpt": link_name(path), "meta_sha256": str(digest)}


def load_linked(owner: str | os.PathLike, ref: Mapping[str, Any], expect_model: str, what: str, since: str,
                redo: str) -> Checkpoint:  # fmt: skip
    """The checkpoint the link ``ref`` of the checkpoint ``owner`` names (``ref["ckpt"]`` non-empty),
    without training state; one-line errors when it cannot be loaded or its digest is not the one
    recorded. ``what`` names the source in them ("the free model", "its teacher"), ``since`` the
    moment the link was made ("the export"), ``redo`` how to make it again."""
    name = ref["ckpt"]
    try:
        source = load_checkpoint(resolve_ckpt_arg(name), expect_model=expect_model, training_state=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{owner}: links {what} {name}, which cannot be loaded ({one_line(e)})") from None
    if source.meta.get("meta_sha256") != ref.get("meta_sha256"):
        raise ValueError(f"{owner}: links {what} {name}, which has changed since {since} (meta.json digest "
                         f"{str(source.meta.get('meta_sha256'))[:12]}, recorded {str(ref.get('meta_sha256'))[:12]}): "
                         f"{redo}")  # fmt: skip
    return source
