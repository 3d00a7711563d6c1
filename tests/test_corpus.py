"""The project's own corpus of bad input, faults and concurrent writers (issue 24), generated from the
command line's own parser so that a new option is covered the day it is added:

* every numeric option of every command, given a value of the wrong type: one line, exit 2,
  nothing written (several hundred cases, in-process);
* every numeric option of ``sample``, ``complete``, ``edit``, ``animate`` and ``mesh``, given
  negative, zero, non-finite and absurdly large values on an otherwise valid command: either it
  runs and writes its output, or it is refused in one line with exit 2 and nothing written; never
  a traceback, never a half-written folder;
* in real subprocesses: ``kill -9`` of a training run, resumed, ends with the same weights as an
  uninterrupted run; two ``train`` started into one folder at once: one trains, the other is refused
  in one line naming the holder, and nothing of the refused one is left.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from pocoloco.cli import build_parser, main

JUNK = ("abc", "", "1,5")


def _numeric_options(parser: argparse.ArgumentParser, path: list[str]) -> list[tuple[list[str], str, type]]:
    """(command path, option, type) of every int / float option, sub-commands included."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += _numeric_options(sub, [*path, name])
        elif action.option_strings and action.type in (int, float):
            out.append((path, action.option_strings[-1], action.type))
    return out


def _run(argv: list[str]) -> tuple[object, str, str]:
    """(exit code, stdout, stderr) of the CLI in-process; an exception that escapes is returned as such."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = main(argv)
        except SystemExit as e:
            code = e.code
        except BaseException as e:  # a traceback would reach the user: the test reports it
            code = f"{type(e).__name__}: {e}"
    return code, out.getvalue(), err.getvalue()


def _one_line_refusal(code, out: str, err: str) -> str | None:
    """Why this is not a one-line refusal (None if it is)."""
    lines = [line for line in err.splitlines() if line.strip()]
    if code != 2:
        return f"exit {code!r}"
    if len(lines) != 1 or not lines[0].startswith("pocoloco: error: "):
        return f"stderr {err!r}"
    if "Traceback" in err or out.strip():
        return f"stdout {out!r}"
    return None


OPTIONS = _numeric_options(build_parser(), [])


def test_the_corpus_covers_every_numeric_option():
    assert len(OPTIONS) >= 100 and len(OPTIONS) * len(JUNK) >= 300  # the corpus is several hundred cases


def test_every_numeric_option_refuses_a_value_of_the_wrong_type_in_one_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    failures = []
    for path, option, _ in OPTIONS:
        for value in JUNK:
            code, out, err = _run([*path, option, value, "--out", "OUT"] if path else [option, value])
            why = _one_line_refusal(code, out, err)
            if why or "invalid" not in err:
                failures.append(f"{' '.join(path)} {option} {value!r}: {why or err}")
            if os.listdir(tmp_path):
                failures.append(f"{' '.join(path)} {option} {value!r}: wrote {os.listdir(tmp_path)}")
                for p in tmp_path.iterdir():
                    shutil.rmtree(p) if p.is_dir() else p.unlink()
    assert not failures, "\n".join(failures[:20])


def _app_inputs(d: Path) -> dict[str, list[str]]:
    """Valid, cheap commands of the apps (the shipped default, demo poses, a small cloud)."""
    from pocoloco.data.poses import load_joints
    from pocoloco.data.published import write_ply

    good = load_joints("demo:skirt")
    np.save(d / "motion.npy", np.stack([good, good + 0.01, good + 0.02]))
    pts = np.random.default_rng(0).normal(size=(600, 3)).astype(np.float32) * 0.2 + good[0]
    write_ply(d / "cloud.ply", pts, normals=np.tile(np.float32([0, 0, 1]), (600, 1)))
    cloud, motion = str(d / "cloud.ply"), str(d / "motion.npy")
    return {
        "sample": ["sample", "--joints", "demo:skirt", "--num", "1", "--points", "16", "--steps", "2", "--no-render"],
        "complete": ["complete", "--partial", cloud, "--joints", "demo:skirt", "--points", "32", "--steps", "2"],
        "edit": ["edit", "--source", cloud, "--joints", "demo:skirt", "--points", "32", "--steps", "2"],
        "animate": ["animate", "--motion", motion, "--outfit", "skirt_a", "--points", "16", "--steps", "2"],
        "mesh": ["mesh", cloud, "--depth", "5"],
    }  # fmt: skip


BAD_NUMBERS = {int: ("-1", "0", "99999999999999999999"), float: ("-1", "nan", "inf", "1e30")}


@pytest.mark.parametrize("command", ["sample", "complete", "edit", "animate", "mesh"])
def test_every_numeric_option_of_an_app_is_honoured_or_refused_in_one_line(tmp_path, monkeypatch, command):
    """Negative, zero, non-finite and huge values on an otherwise valid command: the command either
    runs and writes its output, or refuses in one line, exit 2, writing nothing; a request larger
    than the free memory is refused before any work (never a MemoryError, never a hang)."""
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    base = _app_inputs(inputs)[command]
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    out_args = ["--out", "OUT.ply"] if command == "mesh" else ["--out", "OUT"]
    options = [(o, t) for p, o, t in OPTIONS if p == [command]]
    assert options
    failures = []
    for option, kind in options:
        for value in BAD_NUMBERS[kind]:
            argv = list(base)
            if option in argv:
                argv[argv.index(option) + 1] = value
            else:
                argv += [option, value]
            t0 = time.perf_counter()
            code, out, err = _run([*argv, *out_args])
            written = sorted(os.listdir(work))
            if code == 0:
                if not written:
                    failures.append(f"{option} {value}: exit 0 but nothing written")
            else:
                why = _one_line_refusal(code, out, err)
                if why:
                    failures.append(f"{option} {value}: {why}")
                elif written:
                    failures.append(f"{option} {value}: refused but wrote {written}")
            if time.perf_counter() - t0 > 60:
                failures.append(f"{option} {value}: took {time.perf_counter() - t0:.0f} s")
            for p in work.iterdir():
                shutil.rmtree(p) if p.is_dir() else p.unlink()
    assert not failures, "\n".join(failures)


# ------------------------------------------------------------------ faults and concurrent writers
def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "pocoloco", *args]


def _train_argv(data: Path, out: Path, steps: int) -> list[str]:
    return _cli("train", "--data", str(data), "--out", str(out), "--preset", "tiny", "--steps", str(steps),
                "--batch-size", "2", "--num-points", "64", "--ckpt-every", "1", "--sample-every", "0", "--no-progress",
                "--threads", "1")  # fmt: skip


def _weights(run: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    ck = sorted((run / "checkpoints").glob("step_*"))[-1]
    return {**load_file(ck / "model.safetensors"), **{f"ema.{k}": v for k, v in load_file(ck / "ema.safetensors").items()}}


def test_kill_9_during_training_then_resume_ends_with_the_same_weights(tiny_dataset, tmp_path):
    """SIGKILL a real `pocoloco train` process once it has written checkpoints (possibly in the middle
    of the next one); the same command with --resume finishes, and its final weights equal, bit for
    bit, those of a run that was never interrupted."""
    steps = 30
    straight = tmp_path / "straight"
    assert subprocess.run(_train_argv(tiny_dataset, straight, steps), capture_output=True).returncode == 0
    killed = tmp_path / "killed"
    proc = subprocess.Popen(_train_argv(tiny_dataset, killed, steps), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.time() + 120
    while time.time() < deadline and len(list((killed / "checkpoints").glob("step_*"))) < 2:
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "the run ended before it could be killed"
    from pocoloco.engine.checkpoint import load_checkpoint

    assert 1 <= load_checkpoint(killed).step < steps  # killed part way, with a checkpoint to resume from
    resumed = subprocess.run([*_train_argv(tiny_dataset, killed, steps), "--resume"], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    a, b = _weights(straight), _weights(killed)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_two_trains_started_together_into_one_folder_one_is_refused(tiny_dataset, tmp_path):
    """Two `pocoloco train` processes started at the same moment into one --out with different seeds:
    exactly one trains (exit 0, its own seed in every checkpoint); the other exits 2 with one line
    naming the holder; metrics.jsonl holds only whole records."""
    import json

    run = tmp_path / "run"
    procs = [subprocess.Popen([*_train_argv(tiny_dataset, run, 3), "--seed", str(seed)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for seed in (1, 2)]  # fmt: skip
    results = [(p.wait(), *p.communicate()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    refused = next(r for r in results if r[0] == 2)
    lines = [line for line in refused[2].splitlines() if line.strip()]
    assert len(lines) == 1 and "in use by pocoloco train (pid" in lines[0], refused[2]
    winner_seed = 1 if results[0][0] == 0 else 2
    for ck in (run / "checkpoints").glob("step_*"):
        assert json.loads((ck / "meta.json").read_text())["config"]["seed"] == winner_seed
    for line in (run / "metrics.jsonl").read_text().splitlines():
        json.loads(line)  # every record whole
