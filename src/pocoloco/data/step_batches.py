"""The batches of a training run, indexed by step (the frame order every method trains in)."""

from __future__ import annotations

import numpy as np
import torch

from pocoloco.data.dataset import PointCloudDataset

__all__ = ["StepBatches"]


class StepBatches(torch.utils.data.Dataset):
    """The batches of a run, indexed by step: ``batches[step]`` is rank ``rank``'s batch of that step.

    Frame order: global position ``g = step * B * world + rank * B + i`` (i < B) reads frame
    ``perm_e[g mod L]`` of epoch ``e = g // L`` with ``perm_e = default_rng([seed, 0, e]).permutation(L)``
    (every frame once per epoch, across all ranks). Points: N of the frame's points without
    replacement from ``default_rng([seed, 1, g])``. So a batch depends only on (seed, step, rank)
    and is the same with any number of DataLoader workers, and after a resume.

    Items: ``points`` (B, N, C) normalised (C = 3, or 6 with unit normals), ``joints`` (B, J, 3)
    normalised, ``root`` (B, 3) metres, ``index`` (B,) frame indices, ``subject`` (B,) the frames'
    subject ids (``dataset.subject_names`` order), ``body`` (B, K, 3) when the dataset gives it, and
    ``motion`` (B, J, F) motion-window features when the dataset has a ``motion_window``, augmented
    from ``default_rng([seed, 4, g])`` (:meth:`PointCloudDataset.motion_features`).
    """

    def __init__(self, dataset: PointCloudDataset, batch_size: int, num_points: int, seed: int, steps: int,
                 rank: int = 0, world_size: int = 1):  # fmt: skip
        if dataset.num_points is not None:
            raise ValueError("StepBatches subsamples points itself: build the dataset with num_points=None")
        self.dataset, self.B, self.N, self.seed = dataset, batch_size, num_points, seed
        self.steps, self.rank, self.world = steps, rank, world_size
        self._perms: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return self.steps

    def frame_indices(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(B,) global positions and (B,) frame indices of this rank's batch at ``step``."""
        L = len(self.dataset)
        g = step * self.B * self.world + self.rank * self.B + np.arange(self.B, dtype=np.int64)
        idx = np.empty(self.B, dtype=np.int64)
        for k, gk in enumerate(g):
            e = int(gk // L)
            if e not in self._perms:
                if len(self._perms) > 4:
                    self._perms.clear()
                self._perms[e] = np.random.default_rng([self.seed, 0, e]).permutation(L)
            idx[k] = self._perms[e][gk % L]
        return g, idx

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        g, idx = self.frame_indices(int(step))
        pts, jts, roots, angles, subjects, bodies, velocities, motions = [], [], [], [], [], [], [], []
        for gk, i in zip(g, idx, strict=True):
            item = self.dataset[int(i)]
            n = item["points"].shape[0]
            if n < self.N:
                path = self.dataset.frames[int(i)][2]
                raise ValueError(f"{path}: frame has {n} points, fewer than num_points={self.N}")
            sel = torch.from_numpy(np.random.default_rng([self.seed, 1, int(gk)]).choice(n, self.N, replace=False))
            p = item["points"][sel]
            if self.dataset.with_normals:
                p = torch.cat([p, item["normals"][sel]], dim=-1)
            pts.append(p)
            jts.append(item["joints"])
            roots.append(item["root"])
            angles.append(item["angle"])
            subjects.append(item["subject"])
            if "body" in item:
                bodies.append(item["body"])
            if "velocity" in item:
                velocities.append(item["velocity"])
            if "motion" in item:  # the window again, augmented: time-warp, jitter, noise
                motions.append(self.dataset.motion_features(int(i), rng=np.random.default_rng([self.seed, 4, int(gk)])))
        batch = {"points": torch.stack(pts), "joints": torch.stack(jts), "root": torch.stack(roots),
                 "angle": torch.stack(angles), "index": torch.from_numpy(idx), "subject": torch.tensor(subjects, dtype=torch.long)}  # fmt: skip
        if bodies:
            batch["body"] = torch.stack(bodies)
        if velocities:
            batch["velocity"] = torch.stack(velocities)
        if motions:
            batch["motion"] = torch.stack(motions)
        return batch
