"""Deterministic seeds derived from integers (numpy ``SeedSequence`` hashing) and a fixed torch
thread count for bit-identical results across processes."""

from __future__ import annotations

import contextlib

import numpy as np
import torch

__all__ = ["seed_of", "torch_threads"]


def seed_of(*words: int) -> int:
    """A 63-bit seed from integers, e.g. ``seed_of(run_seed, 2, step, rank)``: every random draw of
    a training step is a pure function of such a tuple, which is what makes resume bit-exact."""
    return int(np.random.SeedSequence([int(w) for w in words]).generate_state(2, np.uint32).astype(np.uint64)
               .dot(np.array([1, 2**32], np.uint64)) >> np.uint64(1))  # fmt: skip


@contextlib.contextmanager
def torch_threads(n: int = 1):
    """Run a block with ``torch.set_num_threads(n)``, restoring the caller's count after. Float
    reductions (matmuls) split work by thread count, so results are bit-identical across processes
    only under one fixed count: the synthetic data pipeline poses bodies under ``torch_threads(1)``
    so a frame is the same bytes whichever process, shard or caller's thread setting made it."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
