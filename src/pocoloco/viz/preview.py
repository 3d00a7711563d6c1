"""A dataset preview (``pocoloco data preview``): a PNG grid of rendered frames, coloured by label."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pocoloco.data.format import DatasetLayout, read_card, read_frame
from pocoloco.viz.render import render_grid


def preview_dataset(
    root: Path, out: str | None = None, num: int = 4, split: str = "train", seed: int = 0,
    subjects: list[str] | None = None, views: tuple[str, ...] = ("front", "side"),
) -> Path:
    """Render ``num`` frames per subject (``subjects``: these, in this order; default all) of
    ``split`` (evenly spaced over the split's frames) from ``views``; returns the PNG path.
    One row per subject."""
    if num < 1:
        raise ValueError(f"--num must be >= 1, got {num}")
    card = read_card(root)
    unknown = [s for s in subjects or [] if s not in card["subjects"]]
    if unknown:
        raise ValueError(f"{root}: no subject {unknown[0]!r}; the dataset has: {', '.join(card['subjects'])}")
    layout = DatasetLayout(root)
    clouds = []
    for subject in subjects or list(card["subjects"]):
        frames = layout.iter_frames(split, subjects=[subject])
        if not frames:
            continue
        picks = np.unique(np.linspace(0, len(frames) - 1, num).round().astype(int))
        garment = card["subjects"][subject].get("garment_kind", "")
        for k in picks:
            _, sequence, path = frames[k]
            f = read_frame(path, keys=["points", "normals", "labels"])
            rng = np.random.default_rng(seed)
            keep = rng.choice(len(f.points), size=min(len(f.points), 12_000), replace=False)
            title = f"{subject}: {garment} {sequence.rsplit('_', 1)[-1]}/{int(Path(path).stem)}"
            clouds.append((f.points[keep], f.labels[keep], f.normals[keep], title))
    if not clouds:
        raise ValueError(f"{root}: no frames in split {split!r} to preview")
    target = Path(out) if out else root / f"preview_{split}.png"
    return Path(render_grid(clouds, target, views=views, ncols=min(num, len(clouds))))
