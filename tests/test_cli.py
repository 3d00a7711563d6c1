"""The command line as a new user meets it: --version, help for every option, defaults in help,
--threads where torch works, every command README shows parses as written, the first line of a
failing command is its error, and no CUDA-driver noise from warp on a CPU machine."""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from pocoloco import __version__
from pocoloco.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def _subparsers(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, argparse.ArgumentParser]:
    """Every (sub)command's parser by its command line (``data synth``, ``train``, ...)."""
    out = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.update(_subparsers(sub, f"{prefix}{name} ") or {f"{prefix}{name}": sub})
    return out


def test_version_exits_0(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"pocoloco {__version__}"


def test_every_option_of_every_command_has_help():
    missing = []
    commands = _subparsers(build_parser())
    assert {"data synth", "data info", "data preview", "data export", "data import", "train", "sample", "complete",
            "edit", "animate", "fit", "mesh", "eval", "bench quality", "render", "view", "export-model",
            "uvmap"} <= set(commands)  # fmt: skip
    for name, parser in commands.items():
        for action in parser._actions:
            if not isinstance(action, argparse._HelpAction) and not (action.help or "").strip():
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, missing


def test_train_help_shows_defaults():
    parser = _subparsers(build_parser())["train"]
    undocumented = [a.option_strings[0] for a in parser._actions
                    if a.option_strings and not a.required and not isinstance(a, (argparse._HelpAction,))
                    and a.dest not in ("resume", "no_progress", "bf16", "no_decomposition")
                    and "default" not in (a.help or "")]  # fmt: skip
    assert not undocumented, undocumented
    text = parser.format_help()
    assert "pocoloco 20000" in text and "pop 10000" in text  # the presets' steps


@pytest.mark.parametrize("command", ["sample", "complete", "edit", "animate", "eval", "train", "fit", "bench quality"])
def test_commands_doing_torch_work_take_threads(command):
    parser = _subparsers(build_parser())[command]
    assert any("--threads" in a.option_strings for a in parser._actions)


def _documentation() -> str:
    """README and every page of the documentation site (docs/**/*.md) but the lab notebook (docs/lab:
    a record of experiments, whose command lines are kept as they were run)."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return "\n".join(p.read_text() for p in pages if "_build" not in p.parts and "lab" not in p.parts)


def _code_blocks(text: str, languages: tuple[str, ...]) -> list[str]:
    """The fenced code blocks of Markdown ``text`` whose info string is one of ``languages``
    ("" = none), fence by fence (an opening fence is never taken for a closing one)."""
    blocks, current, lang = [], None, None
    for line in text.splitlines():
        fence = re.match(r"^\s*```(\S*)", line)
        if current is None and fence:
            current, lang = [], fence.group(1)
        elif current is not None and line.strip() == "```":
            if lang in languages:
                blocks.append("\n".join(current) + "\n")
            current = None
        elif current is not None:
            current.append(line)
    return blocks


def _readme_commands() -> list[str]:
    """The ``pocoloco ...`` command lines of the code blocks of README and the site's pages:
    continuations joined, ``&&`` chains split, optional parts ``[--flag X]`` included, alternatives
    ``a|b|c`` taken at their first."""
    blocks = _code_blocks(_documentation(), ("bash", "sh", ""))
    commands = []
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            for part in line.split("&&"):
                part = re.sub(r"[\[\]]", " ", part.strip())
                words = shlex.split(part, comments=True)
                if not words:
                    continue
                if words[0] in ("pocoloco", ".venv/bin/pocoloco"):
                    rest = words[1:]
                elif words[0] == "torchrun" and "-m" in words and words[words.index("-m") + 1] == "pocoloco":
                    rest = words[words.index("-m") + 2:]
                else:
                    continue
                commands.append(shlex.join(w.split("|")[0] if "|" in w and not w.startswith("-") else w for w in rest))
    return commands


def test_every_readme_command_line_parses_as_written():
    commands = _readme_commands()
    assert len(commands) >= 20, commands
    parser = build_parser()
    failed = []
    for cmd in commands:
        try:
            parser.parse_args(shlex.split(cmd))
        except SystemExit:
            failed.append(cmd)
    assert not failed, failed


def test_a_failing_train_prints_its_error_first(tiny_run, tiny_dataset, capsys):
    """A user error (here: a run folder that already holds checkpoints) is the only output: no banner first."""
    code = main(["train", "--data", str(tiny_dataset), "--out", str(tiny_run), "--preset", "tiny", "--no-progress"])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err.strip().splitlines() == [captured.err.strip()]
    assert captured.err.startswith("pocoloco: error:") and "already holds checkpoints" in captured.err


def test_dataset_without_normalisation_names_the_command_to_fix_it(tiny_dataset, tmp_path, capsys):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    card = json.loads((data / "card.json").read_text())
    card.pop("normalisation")
    (data / "card.json").write_text(json.dumps(card))
    code = main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--preset", "tiny", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "`pocoloco data synth`" in err, err


def test_warp_starts_quietly_on_a_cpu_machine():
    """No 'CUDA driver' warning from warp's native code on every run (anny and newton load warp)."""
    code = "from pocoloco.body.anny_body import quiet_warp; quiet_warp(); import warp; warp.init(); print('ok')"
    env = {k: v for k, v in os.environ.items() if k != "POCOLOCO_VERBOSE_WARP"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr
    assert "CUDA driver" not in r.stderr and "Warp CUDA warning" not in r.stderr, r.stderr


def test_readme_python_examples_run(tmp_path, monkeypatch):
    """The Python snippets of README and the site's pages run as written (on the shipped model)."""
    import contextlib
    import io

    blocks = _code_blocks(_documentation(), ("python",))
    assert blocks
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    for code in blocks:
        with contextlib.redirect_stdout(out):
            exec(compile(code, "documentation", "exec"), {})
    assert "(2, 2048, 3)" in out.getvalue() and "(3, 2048, 3)" in out.getvalue()


def test_bf16_is_on_by_default_only_where_it_runs_natively(tmp_path, monkeypatch):
    """sample's --bf16 / --no-bf16; default: on with avx512_bf16 / AMX (or a bf16 GPU), off elsewhere."""
    from pocoloco.cli.common import resolve_bf16
    from pocoloco.utils import hardware

    monkeypatch.setattr(hardware, "cpu_flags", lambda: frozenset({"avx2"}))
    assert resolve_bf16(None, "cpu") is False and resolve_bf16(True, "cpu") is True
    monkeypatch.setattr(hardware, "cpu_flags", lambda: frozenset({"avx512f", "amx_bf16"}))
    assert resolve_bf16(None, "cpu") is True and resolve_bf16(False, "cpu") is False
    monkeypatch.undo()
    base = ["sample", "--joints", "demo:skirt", "--num", "1", "--steps", "3", "--points", "64", "--no-render"]
    assert main([*base, "--no-bf16", "--out", str(tmp_path / "a")]) == 0
    assert main([*base, "--bf16", "--out", str(tmp_path / "b")]) == 0
    a, b = (json.loads((tmp_path / d / "sample.json").read_text()) for d in ("a", "b"))
    assert a["bf16"] is False and b["bf16"] is True


def test_progress_in_a_log_is_a_plain_line_every_interval(monkeypatch, capsys):
    """stderr not a terminal (a job's log): no bar, a line at most every LOG_PROGRESS_EVERY_S seconds
    with done / total, elapsed and time left, and a last line at the end; a short job writes nothing;
    training's bar (resumed at a step) estimates the time left from this run's steps."""
    from pocoloco.cli import common
    from pocoloco.utils import progress

    now = [0.0]
    monkeypatch.setattr(progress, "now", lambda: now[0])
    monkeypatch.setattr(progress, "stderr_is_terminal", lambda: False)
    with common.progress_bar("frames", total=1000) as update:
        for done in range(0, 1001, 100):  # 100 frames every 25 s
            update(done)
            now[0] += 25.0
    lines = capsys.readouterr().err.strip().splitlines()
    # printed at 75 s (300 frames) and at 150 s (600 frames), then 75 s later at 225 s (900), then the end
    assert lines[0] == "frames: 300 / 1,000 (30 %), 1:15 elapsed, ~2:55 left"
    assert lines[1] == "frames: 600 / 1,000 (60 %), 2:30 elapsed, ~1:40 left"
    assert lines[2] == "frames: 900 / 1,000 (90 %), 3:45 elapsed, ~0:25 left"
    assert lines[-1].startswith("frames: 1,000 / 1,000 (100 %), 4:35 elapsed") and len(lines) == 4
    now[0] = 0.0
    with common.progress_bar("eval") as update:  # shorter than the interval: silent
        update(5, total=10)
        now[0] += 30.0
        update(10)
    assert capsys.readouterr().err == ""
    now[0] = 0.0
    with common.progress_bar("frames", total=1000) as update:  # resumed: 500 done before, counted at once
        update(500)
        now[0] += 60.0
        update(600)  # 100 frames in 60 s: 400 left take 4 min
    assert capsys.readouterr().err.splitlines()[0] == "frames: 600 / 1,000 (60 %), 1:00 elapsed, ~4:00 left"
    now[0] = 0.0
    bar = progress.Progress("train", 10000, loss=True, done=4000)  # training's bar, resumed at step 4,000
    for _ in range(3000):
        now[0] += 0.0625  # 16 steps/s
        bar.advance(loss="0.2500")
    bar.close()
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == "train: 4,960 / 10,000 (50 %), 1:00 elapsed, ~5:15 left, loss 0.2500", lines
    assert lines[-1].startswith("train: 7,000 / 10,000 (70 %), 3:08 elapsed") and len(lines) == 4
    now[0] = 0.0
    bar = progress.Progress("train", 100000, done=4000, deadline_s=600.0)  # --time-budget 10: the clock decides
    for _ in range(1000):
        now[0] += 0.0625
        bar.advance()
    bar.close()
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == "train: 4,960 / 100,000 (5 %), 1:00 elapsed, ~9:00 left (time budget)", lines
    monkeypatch.setattr(progress, "stderr_is_terminal", lambda: True)  # a terminal: the rich bar
    with progress.Progress("train", 10, loss=True, done=4) as bar:
        bar.advance(loss="0.5")
        bar.update(8, total=12)
        assert bar.bar.tasks[0].completed == 8 and bar.bar.tasks[0].total == 12 and bar.done == 8
    assert bar.bar is None
    now[0] = 0.0
    with progress.Progress("train", 100000, deadline_s=600.0) as bar:  # the bar's time left, capped the same way
        column = bar.bar.columns[-1]
        task = bar.bar.tasks[0]
        now[0] = 60.0
        assert column.render(task).plain == "9:00 (budget)"  # no count yet: the clock's
        monkeypatch.setattr(type(task), "time_remaining", property(lambda t: 30.0))
        assert column.render(task).plain == "0:30"  # the count's estimate is the sooner
        monkeypatch.setattr(type(task), "time_remaining", property(lambda t: 7200.0))
        assert column.render(task).plain == "9:00 (budget)"
    capsys.readouterr()
    with progress.Progress("off", 10, enabled=False) as bar:  # disabled (another rank): nothing at all
        bar.advance()
    assert capsys.readouterr().err == ""
