"""Bad input through the CLI: one line naming the user's own path or value, exit 2, nothing
written (issue 24). In-process, on the tiny dataset and the shipped model."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from pocoloco.cli import main
from pocoloco.cli.common import error_line, user_path

LONG = "n" * 300  # longer than any filesystem's name limit (255 bytes)


def _one_line(capsys, code: int) -> str:
    captured = capsys.readouterr()
    assert code == 2, captured.err
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("pocoloco: error: "), err
    assert "Traceback" not in captured.err and not captured.out.strip(), captured.out
    return err


def test_hidden_temporary_files_are_reported_by_the_users_name():
    assert user_path("/a/b/.model.ply.0123456789ab.tmp") == "/a/b/model.ply"
    assert user_path("/a/b/.hidden.ply") == "/a/b/.hidden.ply"
    e = PermissionError(errno.EACCES, "Permission denied", "/a/b/.x.npz.0123456789ab.tmp")
    assert error_line(e) == "/a/b/x.npz: permission denied"
    e = OSError(errno.ENAMETOOLONG, "File name too long", "/a/" + LONG)
    line = error_line(e)
    assert "longer than the filesystem allows" in line and len(line) < 240


@pytest.mark.parametrize("argv, message", [
    (["sample", "--joints", "demo:skirt", "--num", "1", "--points", "16", "--no-render", "--out", LONG],
     "longer than the filesystem allows"),
    (["train", "--data", "DATA", "--steps", "1", "--out", f"{LONG}/run"], "longer than the filesystem allows"),
    (["train", "--data", "DATA", "--steps", "1", "--out", "FILE"], "FILE: exists and is not a folder"),
    (["data", "export", "DATA", "--out", "FILE"], "FILE: exists and is not a folder"),
    (["mesh", "CLOUD", "--out", f"{LONG}.ply"], "longer than the filesystem allows"),
    (["animate", "--motion", "GARBAGE", "--outfit", "skirt_a", "--out", "OUT"], "GARBAGE: not a NumPy .npy / .npz file"),
    (["complete", "--partial", "FOLDER", "--joints", "demo:skirt", "--out", "OUT"], "FOLDER: is a folder, not a file"),
    (["bench", "quality", "--data", "DATA", "--split", "heldout", "--ckpt-pocoloco", "default", "--out", "OUT"],
     "no frames in split 'heldout'"),
])  # fmt: skip
def test_paths_the_os_refuses_are_one_line(tiny_dataset, tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FILE").write_text("not a folder")
    (tmp_path / "GARBAGE").write_bytes(os.urandom(300))
    (tmp_path / "FOLDER").mkdir()
    pts = np.random.default_rng(0).normal(size=(500, 3)) * 0.1
    np.save(tmp_path / "cloud.npy", pts)
    from pocoloco.data.published import write_ply

    write_ply(tmp_path / "CLOUD", pts.astype(np.float32))
    before = sorted(os.listdir(tmp_path))
    argv = [str(tiny_dataset) if a == "DATA" else a for a in argv]
    err = _one_line(capsys, main(argv))
    assert message in err
    assert sorted(os.listdir(tmp_path)) == before  # nothing written


def test_sampling_more_points_than_memory_holds_is_refused_or_split(tmp_path, capsys, monkeypatch):
    """A request whose one cloud cannot fit in free memory: one line naming the most points that fit,
    nothing written; one that fits one cloud at a time: denoised one at a time, with a warning."""
    from pocoloco.cli import common

    per_point = 4 * (64 * (4 + 2) + 64)  # the shipped latent_small's estimate
    monkeypatch.setattr(common, "available_memory_bytes", lambda device: int(1000 * per_point / common.MEMORY_SHARE))
    argv = ["sample", "--joints", "demo:skirt", "--steps", "2", "--no-render"]
    err = _one_line(capsys, main([*argv, "--points", "5000", "--out", str(tmp_path / "a")]))
    assert "--points 5,000: one cloud needs" in err and "at most ~1,000 points fit" in err
    assert not (tmp_path / "a").exists()
    assert main([*argv, "--points", "600", "--num", "3", "--out", str(tmp_path / "b")]) == 0
    captured = capsys.readouterr()
    assert "denoising 1 of the 3 clouds at a time" in captured.err and len(list((tmp_path / "b").glob("*.ply"))) == 3


def test_a_train_that_fails_before_its_first_checkpoint_leaves_no_folder(tiny_dataset, tmp_path, capsys, monkeypatch):
    """A frame that turns out corrupt mid-run (or any user error inside the loop) before the first
    checkpoint: one line, and the run folder it had begun (config.json, metrics.jsonl) is gone; a
    folder that held something before is left as it was."""
    from pocoloco.cli import train as train_cli

    def failing_run(task, data, out, **kw):
        (Path(out) / "config.json").write_text("{}")
        (Path(out) / "metrics.jsonl").write_text("")
        raise ValueError(f"{data}/subjects/skirt/train/x.npz: CRC-32 mismatch (corrupt)")

    monkeypatch.setattr(train_cli, "run_training", failing_run)
    argv = ["train", "--data", str(tiny_dataset), "--preset", "tiny", "--steps", "1", "--out"]
    assert main([*argv, str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err  # the banner (the run had begun), then the one-line error
    assert "CRC-32 mismatch" in err.strip().splitlines()[-1] and "Traceback" not in err
    assert not (tmp_path / "run").exists()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    assert main([*argv, str(tmp_path / "mine")]) == 2  # refused as not a run folder, or the run fails
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"
