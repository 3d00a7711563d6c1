"""Where the cloth follows the body and where it hangs free, learned per outfit from the training
data: the free-region map of the hybrid method (the "clothing-cut map" of FreeCloth, Ye et al.
CVPR 2025, which draws it by hand; here it is estimated from labelled captures).

For every vertex v of the body surface and every sampled training frame of an outfit, the posed
vertex votes *free* when its nearest captured point is loose garment (``LABEL_GARMENT``) or lies
farther than ``margin`` from it (the cloth has left the body there). The vertex's free share is the
fraction of frames that voted free; vertices with a share above ``threshold`` form the free
region. A scan point belongs to the region of its nearest posed body vertex, so the same rule
splits training scans and generated clouds. The outfit's free point share is the mean fraction of
its scan points in the free region: how many of N output points the generator draws.

Shapes: V body vertices, O outfits, N points.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pocoloco.data.format import LABEL_GARMENT, DatasetLayout, read_frame, read_subject
from pocoloco.engine.checkpoint import load_checkpoint
from pocoloco.utils.atomic import atomic_open
from pocoloco.utils.npfile import numpy_file_problem
from pocoloco.viz.render import render_grid

__all__ = ["MIN_FREE_SHARE", "FreeRegionMaps", "inside_depth", "learn_free_maps", "point_regions",
           "recount_point_shares", "render_free_maps", "scan_vertex_votes", "stored_vertex_share"]

#: an outfit with a smaller free point share has no free region (wholly attached)
MIN_FREE_SHARE = 0.02


@dataclass(frozen=True)
class FreeRegionMaps:
    """Per-outfit free-region maps.

    outfits: outfit (subject) names, ids in this order. vertex_share: (O, V) float32 share of
    frames in which each body vertex was free. point_share: (O,) float32 mean share of an outfit's
    scan points in its free region. margin (m) / threshold: the rule that made them.
    frames: (O,) int32 frames each outfit's map was estimated from. far: the point rule the point
    shares were counted with (:func:`point_regions`; None: the nearest vertex alone).
    """

    outfits: tuple[str, ...]
    vertex_share: np.ndarray
    point_share: np.ndarray
    margin: float
    threshold: float
    frames: np.ndarray
    far: float | None = None

    def __post_init__(self):
        O = len(self.outfits)
        if self.vertex_share.ndim != 2 or self.vertex_share.shape[0] != O:
            raise ValueError(f"vertex_share must have shape ({O}, V), got {self.vertex_share.shape}")
        if self.point_share.shape != (O,) or self.frames.shape != (O,):
            raise ValueError(f"point_share and frames must have shape ({O},)")
        if not (np.isfinite(self.vertex_share).all() and np.isfinite(self.point_share).all()):
            raise ValueError("free-region maps hold NaN or infinite values")

    def free(self, outfit: int) -> np.ndarray:
        """(V,) bool: the outfit's free vertices."""
        return self.vertex_share[int(outfit)] > self.threshold

    def without_small_regions(self, min_share: float = MIN_FREE_SHARE) -> FreeRegionMaps:
        """These maps with every outfit whose free point share is below ``min_share`` made wholly
        attached (a few stray vertices, e.g. an uncaptured sole, are no free region)."""
        small = self.point_share < min_share
        share = self.vertex_share.copy()
        share[small] = 0.0
        return FreeRegionMaps(self.outfits, share, np.where(small, 0.0, self.point_share).astype(np.float32),
                              self.margin, self.threshold, self.frames, self.far)  # fmt: skip

    def free_share_of(self, outfit: int) -> float:
        return float(self.point_share[int(outfit)])

    def save(self, path: str | os.PathLike) -> Path:
        """Write as ``.npz`` (atomic)."""
        with atomic_open(path, "wb") as f:
            np.savez(f, outfits=np.array(self.outfits), vertex_share=self.vertex_share.astype(np.float32),
                     point_share=self.point_share.astype(np.float32), margin=np.float32(self.margin),
                     threshold=np.float32(self.threshold), frames=self.frames.astype(np.int32),
                     far=np.float64(np.nan if self.far is None else self.far))  # fmt: skip
        return Path(path)

    @classmethod
    def _from_checkpoint(cls, path: str | os.PathLike) -> FreeRegionMaps:
        """The maps a hybrid checkpoint holds (its ``vertex_share`` or ``free_bits``, ``point_share``,
        and the rule in its config), without loading its networks."""
        ck = load_checkpoint(path, expect_model="hybrid", training_state=False)
        try:
            state, config = ck.model_state, ck.config
            outfits = tuple(str(o["name"]) for o in ck.meta["outfits"])
            share = stored_vertex_share(state, int(ck.meta["num_vertices"]))
            frames = np.asarray(ck.meta.get("map_frames", [0] * len(outfits)), np.int32)
            far = config.get("far")
            return cls(outfits, share, state["point_share"].float().numpy(), float(config["margin"]),
                       float(config["threshold"]), frames, None if far is None else float(far))  # fmt: skip
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{ck.path}: no free-region maps in this hybrid checkpoint ({e})") from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> FreeRegionMaps:
        """Read a ``.npz`` written by :meth:`save`, or the maps of a hybrid checkpoint / run folder
        (a linked one keeps them thresholded: shares 0 / 1); one-line errors for missing or damaged
        files."""
        if Path(path).is_dir():
            return cls._from_checkpoint(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                far = float(z["far"]) if "far" in z.files else float("nan")
                return cls(tuple(str(s) for s in z["outfits"]), z["vertex_share"].astype(np.float32),
                           z["point_share"].astype(np.float32), float(z["margin"]), float(z["threshold"]),
                           z["frames"].astype(np.int32), None if np.isnan(far) else far)  # fmt: skip
        except FileNotFoundError:
            raise ValueError(f"{path}: no such free-region map file") from None
        except (KeyError, ValueError, OSError, EOFError) as e:
            why = numpy_file_problem(path, "npz") or f"{type(e).__name__}: {e}"
            raise ValueError(f"{path}: not a free-region map file ({why})") from None


def stored_vertex_share(state: dict[str, Any], num_vertices: int) -> np.ndarray:
    """(O, V) float32 the vertex maps a hybrid checkpoint's ``state`` holds: ``vertex_share``, or in
    a linked one ``free_bits`` (O, ceil(V / 8)) uint8, the thresholded maps packed (shares 0 / 1)."""
    if "free_bits" in state:
        bits = np.asarray(state["free_bits"].cpu().numpy(), np.uint8)
        return np.unpackbits(bits, axis=1, count=int(num_vertices)).astype(np.float32)
    return state["vertex_share"].float().cpu().numpy()


def point_regions(points: np.ndarray, body_vertices: np.ndarray, free: np.ndarray,
                  far: float | None = None) -> np.ndarray:  # fmt: skip
    """(N,) bool: whether each point (N, 3) lies in the free region, i.e. its nearest posed body
    vertex (V, 3) is free (``free`` (V,) bool) or, with ``far`` (metres), it lies farther than that
    from every body vertex (a hem swinging past a hand or a foot, whose vertices are attached)."""
    dist, nearest = cKDTree(np.asarray(body_vertices, np.float64)).query(np.asarray(points, np.float64))
    region = np.asarray(free, bool)[nearest]
    return region if far is None else region | (dist > far)


def inside_depth(points: np.ndarray, body_vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,) how deep each point (N, 3) lies inside the posed body (metres; > 0 inside, <= 0 on or
    outside): minus its offset along the normal (V, 3) of its nearest body vertex (V, 3)."""
    points = np.asarray(points, np.float64)
    _, nearest = cKDTree(np.asarray(body_vertices, np.float64)).query(points)
    return -np.einsum("nc,nc->n", points - body_vertices[nearest], normals[nearest])


def scan_vertex_votes(points: np.ndarray, labels: np.ndarray | None, body_vertices: np.ndarray,
                      margin: float) -> np.ndarray:  # fmt: skip
    """(V,) float32 0 / 1: one frame's vote of each posed body vertex (V, 3) on a scan (N, 3) with
    point ``labels`` (N,) (None: distance only): free when its nearest scan point is loose garment
    or lies farther than ``margin`` (metres)."""
    dist, idx = cKDTree(np.asarray(points, np.float64)).query(np.asarray(body_vertices, np.float64))
    vote = dist > margin
    if labels is not None:
        vote |= np.asarray(labels)[idx] == LABEL_GARMENT
    return vote.astype(np.float32)


def learn_free_maps(
    data: str | os.PathLike,
    subjects: Sequence[str] | None = None,
    *,
    margin: float = 0.03,
    threshold: float = 0.5,
    every: int = 60,
    labels: bool = True,
    far: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> FreeRegionMaps:
    """Estimate the free-region maps of ``subjects`` (default: all) from every ``every``-th frame of
    their train split (module docstring); the point share from every third of those frames.
    ``labels=False``: a vertex votes free on distance alone (garment that hugs the body, such as
    trousers, stays attached). ``far``: the point shares count points farther than this from the
    body as free too (:func:`point_regions`). Outfits with a free point share below
    ``MIN_FREE_SHARE`` come out wholly attached (:meth:`FreeRegionMaps.without_small_regions`).

    One-line ValueErrors: a subject without train frames, frames without labels or posed body."""
    if not margin > 0:
        raise ValueError(f"margin must be > 0 metres, got {margin}")
    if not 0 < threshold < 1:
        raise ValueError(f"threshold must be in (0, 1), got {threshold}")
    if not (isinstance(every, int) and every >= 1):
        raise ValueError(f"every must be an integer >= 1, got {every!r}")
    layout = DatasetLayout(data)
    names = sorted(subjects) if subjects is not None else layout.subjects()
    plan = {s: _train_frames(layout, data, s, every) for s in names}
    total, done = sum(len(p) for p in plan.values()), 0
    shares, point_shares, counts, samples = [], [], [], []
    for s, paths in plan.items():
        votes: np.ndarray | None = None
        bodies = []
        for path in paths:
            fr = read_frame(path, ("points", "labels", "body_vertices"), allow_missing=True)
            if fr.labels is None or fr.body_vertices is None:
                raise ValueError(f"{path}: the free-region map needs point labels and the posed body (synthetic data)")
            vote = scan_vertex_votes(fr.points, fr.labels if labels else None, fr.body_vertices, margin)
            votes = vote.astype(np.int32) if votes is None else votes + vote.astype(np.int32)
            bodies.append((fr.points, fr.body_vertices))
            done += 1
            if progress is not None:
                progress(done, total)
        share = votes.astype(np.float32) / len(paths)
        free = share > threshold
        point_shares.append(np.mean([point_regions(p, b, free).mean() for p, b in bodies[::3]]))
        samples.append(bodies[::3])
        shares.append(share)
        counts.append(len(paths))
    if len({len(x) for x in shares}) != 1:
        raise ValueError(f"{data}: subjects have bodies with different vertex counts")
    maps = FreeRegionMaps(tuple(plan), np.stack(shares), np.asarray(point_shares, np.float32), float(margin),
                          float(threshold), np.asarray(counts, np.int32)).without_small_regions()  # fmt: skip
    if far is None:
        return maps
    return dataclasses.replace(maps, point_share=_point_shares(maps, samples, far), far=float(far))


def _train_frames(layout: DatasetLayout, data: str | os.PathLike, subject: str, every: int) -> list[Path]:
    """Every ``every``-th train frame of ``subject`` (a one-line error when it has none)."""
    paths = [layout.frame_path(subject, "train", q, i) for q in layout.sequences(subject, "train")
             for i in layout.frame_indices(subject, "train", q)]  # fmt: skip
    if not paths:
        raise ValueError(f"{data}: subject {subject!r} has no train frames")
    return paths[::every]


def _point_shares(maps: FreeRegionMaps, samples: Sequence[Sequence[tuple[np.ndarray, np.ndarray]]],
                  far: float | None) -> np.ndarray:  # fmt: skip
    """(O,) float32: each outfit's mean share of scan points in its free region by the rule ``far``
    over its ``samples`` [(points, posed body vertices)]; an outfit without a free region stays
    wholly attached (0), whatever lies far."""
    return np.asarray([np.mean([point_regions(p, b, maps.free(o), far).mean() for p, b in samples[o]])
                       if maps.free(o).any() else 0.0 for o in range(len(maps.outfits))], np.float32)  # fmt: skip


def recount_point_shares(maps: FreeRegionMaps, data: str | os.PathLike, far: float | None, *, every: int = 180,
                         progress: Callable[[int, int], None] | None = None) -> FreeRegionMaps:  # fmt: skip
    """``maps`` with each outfit's free point share counted again on every ``every``-th train frame
    of ``data`` by the point rule ``far`` (:func:`point_regions`): the share a hybrid drawing
    points farther than ``far`` from the body in the free region needs. The vertex maps are kept."""
    layout = DatasetLayout(data)
    plan = {s: _train_frames(layout, data, s, every) for s in maps.outfits}
    total, done, samples = sum(len(p) for p in plan.values()), 0, []
    for o, paths in enumerate(plan.values()):
        bodies = []
        for path in paths if maps.free(o).any() else ():  # no free region: nothing to read
            fr = read_frame(path, ("points", "body_vertices"), allow_missing=True)
            if fr.body_vertices is None:
                raise ValueError(f"{path}: the free point share needs the posed body (synthetic data)")
            bodies.append((fr.points, fr.body_vertices))
            done += 1
            if progress is not None:
                progress(done, total)
        done += len(paths) - len(bodies)
        samples.append(bodies)
    return dataclasses.replace(maps, point_share=_point_shares(maps, samples, far),
                               far=None if far is None else float(far))


def render_free_maps(maps: FreeRegionMaps, data: str | os.PathLike, path: str | os.PathLike,
                     outfits: Sequence[str] | None = None) -> str:  # fmt: skip
    """A PNG of each outfit's map on its rest-pose body, front and back: vertices coloured from blue
    (attached: the cloth follows the body) to red (free in every frame), titled with the outfit's
    free point share. Returns ``path``."""
    layout = DatasetLayout(data)
    chosen = list(outfits) if outfits is not None else list(maps.outfits)
    unknown = [o for o in chosen if o not in maps.outfits]
    if unknown:
        raise ValueError(f"no free-region map for {unknown}; the maps have {list(maps.outfits)}")
    blue, red = np.array([0.25, 0.45, 0.85]), np.array([0.85, 0.2, 0.15])
    clouds, colors = [], []
    for name in chosen:
        o = maps.outfits.index(name)
        clouds.append((np.asarray(read_subject(layout.subject_path(name)).template, np.float32), None, None,
                       f"{name} {100 * maps.point_share[o]:.0f}% free"))  # fmt: skip
        share = maps.vertex_share[o][:, None]
        colors.append((1 - share) * blue + share * red)
    return render_grid(clouds, path, views=("front", "back"), ncols=min(len(chosen), 4), colors=colors,
                       panel_size=2.0, dpi=70)  # fmt: skip
