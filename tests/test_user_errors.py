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
    (["animate", "--motion", "GARBAGE", "--outfit", "skirt_a", "--out", "OUT"], "GARBAGE: not a NumPy file"),
    (["sample", "--joints", "GARBAGE.npz", "--out", "OUT"], "GARBAGE.npz: cannot read joints: not a NumPy file"),
    (["complete", "--partial", "GARBAGE.npy", "--joints", "demo:skirt", "--out", "OUT"],
     "GARBAGE.npy: cannot read a (N, 3) points array: not a NumPy file"),
    (["complete", "--partial", "EMPTY.npy", "--joints", "demo:skirt", "--out", "OUT"], "EMPTY.npy: cannot read a (N, 3) points array: empty file"),
    (["complete", "--partial", "FOLDER", "--joints", "demo:skirt", "--out", "OUT"], "FOLDER: is a folder, not a file"),
    (["bench", "quality", "--data", "DATA", "--split", "heldout", "--ckpt-pocoloco", "default", "--out", "OUT"],
     "no frames in split 'heldout'"),
])  # fmt: skip
def test_paths_the_os_refuses_are_one_line(tiny_dataset, tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FILE").write_text("not a folder")
    for name in ("GARBAGE", "GARBAGE.npz", "GARBAGE.npy"):
        (tmp_path / name).write_bytes(b"not numpy " + os.urandom(300))
    (tmp_path / "EMPTY.npy").write_bytes(b"")
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
    from pocoloco.methods import base

    per_point = 4 * (64 * (4 + 2) + 64)  # the shipped latent_small's estimate
    monkeypatch.setattr(base, "available_memory_bytes", lambda device: int(1000 * per_point / base.MEMORY_SHARE))
    argv = ["sample", "--joints", "demo:skirt", "--steps", "2", "--no-render"]
    err = _one_line(capsys, main([*argv, "--points", "5000", "--out", str(tmp_path / "a")]))
    assert "--points 5,000: one cloud needs" in err and "at most ~1,000 points fit" in err
    assert not (tmp_path / "a").exists()
    assert main([*argv, "--points", "600", "--num", "3", "--out", str(tmp_path / "b")]) == 0
    captured = capsys.readouterr()
    assert "denoising 1 of the 3 clouds at a time" in captured.err and len(list((tmp_path / "b").glob("*.ply"))) == 3


def test_eval_checks_memory_before_the_first_sample(tiny_dataset, tiny_run, tmp_path, capsys, monkeypatch):
    from pocoloco.methods import base

    monkeypatch.setattr(base, "available_memory_bytes", lambda device: 10_000)
    argv = ["eval", "--ckpt", str(tiny_run), "--data", str(tiny_dataset), "--frames", "1", "--points", "5000",
            "--seeds", "0", "--no-baselines", "--out", str(tmp_path / "e")]  # fmt: skip
    err = _one_line(capsys, main(argv))
    assert "--points 5,000: one cloud needs" in err and not (tmp_path / "e").exists()


def test_a_train_that_fails_before_its_first_checkpoint_leaves_no_folder(tiny_dataset, tmp_path, capsys, monkeypatch):
    """A frame that turns out corrupt mid-run (or any user error inside the loop) before the first
    checkpoint: one line, and the run folder it had begun (config.json, metrics.jsonl) is gone; a
    folder that held something before is left as it was."""
    from pocoloco.cli import train as train_cli

    def failing_run(task, out, **kw):
        (Path(out) / "config.json").write_text("{}")
        (Path(out) / "metrics.jsonl").write_text("")
        raise ValueError(f"{task.data}/subjects/skirt/train/x.npz: CRC-32 mismatch (corrupt)")

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


# ------------------------------------------------------------------ the corpus of malformed inputs
def _write_corpus(d: Path) -> None:
    """Malformed joints, clouds and checkpoints, each named for what is wrong with it."""
    from pocoloco.data.poses import load_joints

    good = load_joints("demo:skirt")
    np.save(d / "j_23.npy", good[:23])
    np.save(d / "j_24x2.npy", good[:, :2])
    bad = good.copy()
    bad[3, 1] = np.nan
    np.save(d / "j_nan.npy", bad)
    np.save(d / "j_str.npy", np.array([["a"] * 3] * 24))
    (d / "j_empty.npy").write_bytes(b"")
    (d / "j_trunc.npy").write_bytes((d / "j_23.npy").read_bytes()[:100])
    np.savez(d / "j_twokeys.npz", a=good, b=good)
    (d / "j_count.txt").write_text("0 1 2 3\n")
    (d / "j_nan.txt").write_text("0 " + " ".join(["nan"] * 72) + "\n")
    np.save(d / "j_mm.npy", good * 1000.0)
    header = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (d / "c_empty.ply").write_text(header.format(n=0))
    (d / "c_short.ply").write_text(header.format(n=10) + "0 0 0\n1 1 1\n")
    (d / "c_nan.ply").write_text(header.format(n=3) + "0 0 0\nnan 0 0\n0 1 0\n")
    (d / "c_text.ply").write_text("this is not a ply file\n")
    (d / "c_words.ply").write_text(header.format(n=2) + "a b c\nd e f\n")
    (d / "ck_empty").mkdir()
    (d / "ck_garbage").mkdir()
    (d / "ck_garbage" / "meta.json").write_text("{not json")
    (d / "ck_wrongformat").mkdir()
    (d / "ck_wrongformat" / "meta.json").write_text('{"format": "something-else", "version": 1}')


SAMPLE = ["sample", "--num", "1", "--steps", "2", "--points", "16", "--no-render", "--out", "OUT"]
CORPUS = [
    *[([*SAMPLE, "--joints", f"{{d}}/{name}"], what) for name, what in [
        ("j_23.npy", "expected joints of shape (24, 3)"), ("j_24x2.npy", "expected joints of shape (24, 3)"),
        ("j_nan.npy", "NaN"), ("j_str.npy", "numeric"), ("j_empty.npy", "j_empty.npy"), ("j_trunc.npy", "j_trunc.npy"),
        ("j_twokeys.npz", "no 'joints' array"), ("j_count.txt", "values"), ("j_nan.txt", "j_nan.txt"),
        ("j_mm.npy", "not metres"), ("nonexistent.npy", "no such"),
    ]],
    *[(["complete", "--partial", f"{{d}}/{name}", "--joints", "demo:skirt", "--steps", "2", "--points", "64",
        "--out", "OUT"], name) for name in ["c_empty.ply", "c_short.ply", "c_nan.ply", "c_text.ply", "c_words.ply"]],
    *[(["mesh", f"{{d}}/{name}", "--out", "OUT.ply"], name) for name in ["c_empty.ply", "c_short.ply", "c_nan.ply",
                                                                          "c_text.ply"]],
    *[([*SAMPLE, "--joints", "demo:skirt", "--ckpt", f"{{d}}/{name}"], name) for name in ["ck_empty", "ck_garbage",
                                                                                             "ck_wrongformat"]],
    ([*SAMPLE, "--joints", "demo:skirt", "--sampler", "bogus"], "unknown sampler"),
    ([*SAMPLE[:-2], "--joints", "demo:skirt", "--steps", "0", "--out", "OUT"], "--steps must be >= 1"),
    ([*SAMPLE, "--joints", "demo:skirt", "--outfit", "nobody"], "nobody"),
    (["animate", "--motion", "{d}/j_23.npy", "--outfit", "skirt_a", "--out", "OUT"], "j_23.npy"),
    (["edit", "--source", "{d}/c_nan.ply", "--joints", "demo:skirt", "--source-joints", "demo:skirt", "--outfit",
      "skirt_a", "--out", "OUT"], "c_nan.ply"),
]  # fmt: skip


@pytest.mark.parametrize("argv, message", CORPUS, ids=[f"{a[0]}-{m[:24]}" for a, m in CORPUS])
def test_the_corpus_of_malformed_inputs_is_one_line_each(tmp_path, capsys, monkeypatch, argv, message):
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    _write_corpus(corpus)
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    err = _one_line(capsys, main([a.format(d=corpus) for a in argv]))
    assert message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


def test_train_checks_memory_before_the_first_step(tiny_dataset, tmp_path, capsys, monkeypatch):
    """A training step that cannot fit in the free memory: one line naming the estimate and what to
    lower, before any step, and no run folder left."""
    from pocoloco.engine import trainer
    from pocoloco.methods.pocoloco.config import training_point_bytes
    from pocoloco.methods.pocoloco import train_preset

    need = training_point_bytes(train_preset("latent_tiny")) * 2 * 4096
    monkeypatch.setattr(trainer, "available_memory_bytes", lambda device: need // 2)
    argv = ["train", "--data", str(tiny_dataset), "--preset", "latent_tiny", "--steps", "1", "--batch-size", "2",
            "--num-points", "4096", "--lr", "1e-3", "--no-progress", "--out", str(tmp_path / "run")]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "one training step needs" in err and "lower --batch-size or --num-points" in err
    assert not (tmp_path / "run").exists()
