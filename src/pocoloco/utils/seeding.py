"""Deterministic seeds derived from integers (numpy ``SeedSequence`` hashing)."""

from __future__ import annotations

import numpy as np

__all__ = ["seed_of"]


def seed_of(*words: int) -> int:
    """A 63-bit seed from integers, e.g. ``seed_of(run_seed, 2, step, rank)``: every random draw of
    a training step is a pure function of such a tuple, which is what makes resume bit-exact."""
    return int(np.random.SeedSequence([int(w) for w in words]).generate_state(2, np.uint32).astype(np.uint64)
               .dot(np.array([1, 2**32], np.uint64)) >> np.uint64(1))  # fmt: skip
