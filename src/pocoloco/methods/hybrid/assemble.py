"""Assemble a hybrid checkpoint from a trained POP (attached region), a trained PocoLoco denoiser
(free region) and free-region maps learnt from the dataset (``pocoloco hybrid``).

A hybrid holds copies of both networks' weights, or (``link=True``, ``pocoloco hybrid --link``)
only its maps and a reference to each checkpoint it was made of: the shipped models by name
(``default:pop``, ``default``), others by their checkpoint folder, each with the checksum of its
``meta.json`` (which holds its weights' checksums), so a linked hybrid loads only the very weights
it was assembled from. The shipped ``default:hybrid`` is one: its maps are a few kilobytes, where a
copy of the two networks would be 17 MB."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from pocoloco.engine.checkpoint import load_checkpoint, save_checkpoint
from pocoloco.engine.links import link_name, link_to
from pocoloco.methods.hybrid.method import HybridConfig
from pocoloco.methods.hybrid.regions import FreeRegionMaps, learn_free_maps, recount_point_shares, render_free_maps
from pocoloco.methods.pocoloco.method import PocoLocoMethod
from pocoloco.methods.pop.method import POPMethod

__all__ = ["assemble_hybrid", "link_name"]


def assemble_hybrid(
    attached: str | os.PathLike,
    free: str | os.PathLike,
    data: str | os.PathLike,
    out: str | os.PathLike,
    *,
    margin: float = 0.03,
    threshold: float = 0.5,
    every: int = 60,
    maps: str | os.PathLike | None = None,
    generator_share: float = 1.0,
    inside_tolerance: float | None = None,
    area_weighted: bool = True,
    far: float | None = None,
    trust: float | None = None,
    link: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Write the hybrid of the POP checkpoint ``attached`` and the PocoLoco checkpoint ``free`` into
    the run folder ``out`` (``out/checkpoints``, ``out/maps.npz``, ``out/maps.png``). The maps are
    learnt from ``data``'s train split for POP's outfits (``margin``, ``threshold``, ``every``:
    :func:`~pocoloco.methods.hybrid.regions.learn_free_maps`), or read from ``maps``.
    ``generator_share``: of the free region's points, the share the denoiser draws (POP the rest);
    ``inside_tolerance``: generated points deeper inside the posed body are drawn again (metres);
    ``area_weighted``: POP's points drawn by the body area their pixels stand for; ``far``: points
    farther than this from the body are free whatever their nearest vertex (the point shares are
    counted by the same rule, again from ``data`` when ``maps`` were counted otherwise); ``trust``:
    generated points farther than this from POP's own points in the free region are drawn again;
    ``link``: store references to the two checkpoints instead of copies of their weights, and the
    maps thresholded (one bit per outfit and body vertex; module docstring). Returns the checkpoint
    folder. One-line errors: wrong checkpoint kinds, outfits the maps or the free-region model do
    not know, a free-region model that needs the posed body."""
    if not 0.0 <= generator_share <= 1.0:
        raise ValueError(f"--generator-share must be in [0, 1], got {generator_share}")
    if inside_tolerance is not None and not 0.0 <= inside_tolerance < math.inf:
        raise ValueError(f"--inside-tolerance must be a distance >= 0 (metres), got {inside_tolerance}")
    if far is not None and not 0.0 < far < math.inf:
        raise ValueError(f"--far must be a distance > 0 (metres), got {far}")
    if trust is not None and not 0.0 < trust < math.inf:
        raise ValueError(f"--trust must be a distance > 0 (metres), got {trust}")
    pop = POPMethod.from_checkpoint(load_checkpoint(attached, expect_model="pop", training_state=False))
    gen = PocoLocoMethod.from_checkpoint(load_checkpoint(free, expect_model="pocoloco", training_state=False))
    if gen.needs_body:
        raise ValueError(f"{free}: a free-region model trained with --body-points cannot be assembled yet")
    if pop.motion_window and gen.motion_window and pop.motion_window != gen.motion_window:
        raise ValueError(f"{attached} sees {pop.motion_window:g} s of motion and {free} {gen.motion_window:g} s: a hybrid "
                         "of two motion-aware models needs one window")  # fmt: skip
    names = pop.outfit_names()
    if maps is None:
        region = learn_free_maps(data, names, margin=margin, threshold=threshold, every=every, far=far,
                                 progress=progress)  # fmt: skip
    else:
        region = FreeRegionMaps.load(maps)
        missing = [n for n in names if n not in region.outfits]
        if missing:
            raise ValueError(f"{maps}: no free-region map for outfits {missing}")
        rows = [region.outfits.index(n) for n in names]
        region = FreeRegionMaps(tuple(names), region.vertex_share[rows], region.point_share[rows], region.margin,
                                region.threshold, region.frames[rows], region.far).without_small_regions()  # fmt: skip
        if region.far != far:
            region = recount_point_shares(region, data, far, progress=progress)
    if region.vertex_share.shape[1] != int(pop.model.num_vertices):
        raise ValueError(f"the maps are over {region.vertex_share.shape[1]} body vertices, POP's body has "
                         f"{int(pop.model.num_vertices)}")  # fmt: skip
    known = gen.outfit_names()
    lacking = [n for i, n in enumerate(names) if region.point_share[i] > 0 and known and n not in known]
    if lacking:
        raise ValueError(f"{free}: the free-region model never learnt outfits {lacking}, which hang free")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    region.save(out / "maps.npz")
    render_free_maps(region, data, out / "maps.png")
    point_share = torch.from_numpy(region.point_share.astype(np.float32))
    if link:
        linked = {part: link_to(m.path, m.meta, "leave out --link") for part, m in (("attached", pop), ("free", gen))}
        free_mask = np.stack([region.free(i) for i in range(len(names))])
        state = {"free_bits": torch.from_numpy(np.packbits(free_mask, axis=1)), "point_share": point_share}
        sources = {part: ref["ckpt"] for part, ref in linked.items()}
    else:
        linked = None
        state = {**{f"attached.{k}": v for k, v in pop.model.state_dict().items()},
                 **{f"free.{k}": v for k, v in gen.model.state_dict().items()},
                 "vertex_share": torch.from_numpy(region.vertex_share.astype(np.float32)), "point_share": point_share}
        sources = {"attached": str(pop.path), "free": str(gen.path)}
    config = HybridConfig(attached=pop.config.to_dict(), free=gen.config.to_dict(), margin=region.margin,
                          threshold=region.threshold, sources=sources,
                          generator_share=float(generator_share),
                          inside_tolerance=None if inside_tolerance is None else float(inside_tolerance),
                          area_weighted=bool(area_weighted), far=None if far is None else float(far),
                          trust=None if trust is None else float(trust))  # fmt: skip
    return save_checkpoint(out / "checkpoints", 0, model_kind="hybrid", preset=config.preset, config=config.to_dict(),
                           normalisation=gen.normalisation, model_state=state,
                           extra={"outfits": pop.outfits, "num_vertices": int(pop.model.num_vertices),
                                  "free_outfits": gen.outfits, "map_frames": region.frames.tolist(),
                                  "data": os.fspath(data), **({"linked": linked} if linked else {})})  # fmt: skip

