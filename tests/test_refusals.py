"""Issue 44: a refused command leaves the user's folders exactly as they were (its lock file
included), and no degenerate cloud reaches a model: one check for every command that reads one."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pocoloco.cli import main
from pocoloco.data.published import check_cloud, write_joints_txt, write_ply
from pocoloco.utils.atomic import exclusive_lock


def _snapshot(root: Path) -> dict:
    return {q.relative_to(root).as_posix(): (q.read_bytes() if q.is_file() else None) for q in sorted(root.rglob("*"))}


def _refused(capsys, argv) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("pocoloco: error: ") and "Traceback" not in err, err
    return err


# ------------------------------------------------------------------------------------------ locks
def test_a_lock_goes_with_its_holder_and_one_that_was_there_stays(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    with exclusive_lock(folder, "test") as lock:
        assert lock.exists()
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]
    with pytest.raises(RuntimeError):
        with exclusive_lock(folder, "test"):
            raise RuntimeError("refused")
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]
    (folder / ".lock").write_text("")  # a lock file the user (or an older pocoloco) left: not ours to remove
    with exclusive_lock(folder, "test"):
        pass
    assert sorted(p.name for p in folder.iterdir()) == [".lock", "notes.txt"]
    new = tmp_path / "new"
    with exclusive_lock(new, "test"):
        pass
    assert not new.exists()  # a folder it made for nothing goes too


def test_shared_holders_leave_the_lock_to_the_last_one(tmp_path):
    with exclusive_lock(tmp_path, "a", shared=True) as lock:
        with exclusive_lock(tmp_path, "b", shared=True):
            pass
        assert lock.exists()  # a still holds it
        with pytest.raises(ValueError, match="in use by"):
            with exclusive_lock(tmp_path, "writer"):
                pass
    assert not (tmp_path / ".lock").exists()
    with exclusive_lock(tmp_path, "writer"):  # and a writer gets it afterwards
        pass


def test_refused_commands_leave_their_folders_byte_identical(tiny_dataset, tiny_run, tmp_path, capsys):
    folder = tmp_path / "user"
    folder.mkdir()
    (folder / "notes.txt").write_text("the user's own file")
    empty = tmp_path / "empty"
    empty.mkdir()
    with_ckpt = tmp_path / "hybrid_out"
    shutil.copytree(tiny_run, with_ckpt)
    cases = [
        (["data", "synth", "--preset", "tiny", "--out", str(folder)], folder),
        (["data", "synth", "--preset", "tiny", "--out", str(folder), "--finalize-only"], folder),
        (["data", "synth", "--preset", "tiny", "--out", str(folder), "--shard", "1/2"], folder),
        (["train", "--data", str(tiny_dataset), "--resume", "--out", str(empty), "--steps", "1", "--no-progress"], empty),
        (["train", "--data", str(tiny_dataset), "--out", str(with_ckpt), "--steps", "1", "--no-progress"], with_ckpt),
        (["hybrid", "--attached", str(tiny_run), "--free", str(tiny_run), "--data", str(tiny_dataset), "--out",
          str(with_ckpt)], with_ckpt),
    ]  # fmt: skip
    for argv, where in cases:
        before = _snapshot(where)
        _refused(capsys, argv)
        assert _snapshot(where) == before, argv


# ----------------------------------------------------------------------------------- clouds
def _degenerate_clouds() -> dict[str, tuple[np.ndarray, str]]:
    rng = np.random.default_rng(0)
    line = np.zeros((500, 3), np.float32)
    line[:, 2] = np.linspace(0.0, 1.6, 500)
    return {
        "one_point": (np.tile([[0.1, 0.2, 1.0]], (2000, 1)).astype(np.float32), "1 distinct point(s) of 2000"),
        "few_points": (np.repeat(rng.normal(size=(10, 3)), 50, 0).astype(np.float32), "10 distinct point(s)"),
        "blob": ((rng.normal(size=(2000, 3)) * 1e-3 + [0, 0, 1]).astype(np.float32), "need a bounding box"),
        "line": (line, "of a line"),
        "millimetres": ((rng.normal(size=(2000, 3)) * 300).astype(np.float32), "not in metres"),
    }


def test_check_cloud_names_each_problem_and_passes_a_body():
    for name, (pts, message) in _degenerate_clouds().items():
        with pytest.raises(ValueError, match=re.escape(message)):
            check_cloud(f"{name}.ply", pts)
    with pytest.raises(ValueError, match="3 of 100 points have NaN"):
        bad = np.random.default_rng(0).normal(size=(100, 3))
        bad[:3, 1] = np.nan
        check_cloud("nan.npy", bad)
    with pytest.raises(ValueError, match="empty.ply: the cloud is empty"):
        check_cloud("empty.ply", np.zeros((0, 3)))
    with pytest.raises(ValueError, match="shape"):
        check_cloud("flat.npy", np.zeros(30))
    body = np.random.default_rng(1).normal(size=(4000, 3)) * [0.2, 0.15, 0.5]
    assert check_cloud("body.ply", body).dtype == np.float32
    plane = np.random.default_rng(1).uniform(size=(500, 3)) * [0.5, 0.5, 0.0]  # a flat patch is a valid scan
    check_cloud("plane.ply", plane)


def test_every_command_that_reads_a_cloud_refuses_a_degenerate_one(tiny_dataset, tiny_run, tmp_path, capsys):
    from pocoloco.data.format import DatasetLayout, read_frame

    subject, seq, path = next(f for f in DatasetLayout(tiny_dataset).iter_frames("test") if f[0] == "skirt")
    spec = f"{tiny_dataset}:{subject}/test/{seq}/{int(read_frame(path, ['frame_index']).frame_index)}"
    for name, (pts, _) in _degenerate_clouds().items():
        folder = tmp_path / name
        folder.mkdir()
        ply = folder / "frame_0001.ply"
        normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1)).astype(np.float32)
        write_ply(ply, pts, normals=normals)
        np.save(tmp_path / f"{name}.npy", pts)
        joints_txt = tmp_path / f"{name}.txt"
        write_joints_txt(joints_txt, np.array([1]), np.zeros((1, 24, 3), np.float32))
        out = tmp_path / f"out_{name}"
        commands = [
            ["edit", "--source", str(ply), "--joints", "demo:skirt", "--ckpt", str(tiny_run), "--out", str(out)],
            ["complete", "--partial", str(tmp_path / f"{name}.npy"), "--joints", "demo:skirt", "--ckpt", str(tiny_run),
             "--out", str(out)],
            ["fit", "--ckpt", "default:pop", "--scan", str(ply), "--frame", spec, "--steps", "1", "--out", str(out)],
            ["mesh", str(ply), "--out", str(out) + ".ply"],
            ["render", str(ply), "--out", str(out) + ".png"],
            ["view", str(folder), "--out", str(out) + ".html"],
            ["data", "import", str(folder), "--joints", str(joints_txt), "--subject", "scan", "--out", str(out)],
        ]  # fmt: skip
        before = _snapshot(tmp_path)
        for argv in commands:
            err = _refused(capsys, argv)
            assert "frame_0001.ply" in err or f"{name}.npy" in err, err
            assert "degenerate" in err or "not in metres" in err, err
        assert _snapshot(tmp_path) == before, name
