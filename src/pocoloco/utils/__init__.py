"""Small shared utilities (atomic file writes)."""

from .atomic import atomic_write, save_npz_atomic, write_json_atomic

__all__ = ["atomic_write", "save_npz_atomic", "write_json_atomic"]
