"""The NumPy-file sniffing behind the readers' one-line errors (pocoloco.utils.npfile)."""

import numpy as np

from pocoloco.utils.npfile import numpy_file_kind, numpy_file_problem


def test_kinds_are_read_from_the_first_bytes_whatever_the_name(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros(3))
    np.savez(tmp_path / "b.npz", x=np.zeros(3))
    np.savez(tmp_path / "empty_archive.npz")
    (tmp_path / "a.npy").rename(tmp_path / "a_named.npz")
    (tmp_path / "text.npy").write_text("hello")
    (tmp_path / "empty.npy").write_bytes(b"")
    assert numpy_file_kind(tmp_path / "a_named.npz") == "npy"
    assert numpy_file_kind(tmp_path / "b.npz") == "npz"
    assert numpy_file_kind(tmp_path / "empty_archive.npz") == "npz"
    assert numpy_file_kind(tmp_path / "text.npy") is None
    assert numpy_file_kind(tmp_path / "empty.npy") is None
    assert numpy_file_kind(tmp_path / "missing.npy") is None


def test_problems_in_words(tmp_path):
    np.save(tmp_path / "a.npy", np.zeros(3))
    np.savez(tmp_path / "b.npz", x=np.zeros(3))
    (tmp_path / "text.npy").write_text("hello")
    (tmp_path / "empty.npy").write_bytes(b"")
    assert numpy_file_problem(tmp_path / "a.npy") is None
    assert numpy_file_problem(tmp_path / "a.npy", "npy") is None
    assert numpy_file_problem(tmp_path / "b.npz", "npz") is None
    assert numpy_file_problem(tmp_path / "a.npy", "npz") == "a NumPy .npy array, not a .npz archive"
    assert numpy_file_problem(tmp_path / "b.npz", "npy") == "a NumPy .npz archive, not a .npy array"
    assert numpy_file_problem(tmp_path / "text.npy").startswith("not a NumPy file")
    assert numpy_file_problem(tmp_path / "empty.npy") == "empty file"
    assert numpy_file_problem(tmp_path / "missing.npy") == "cannot be read"
