"""Sharded generation (``data synth --shard K/N``, ``--finalize-only``, ``--launch``): shards give the
same bytes as one process, start safely at once, resume after a kill; bad input is one line."""

import dataclasses
import json
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pocoloco.cli import main
from pocoloco.synth.config import SYNTH_PRESETS, synth_preset
from pocoloco.data.format import DatasetLayout, read_card, read_frame, write_card
from pocoloco.synth.pipeline import (
    CLOTH_COST,
    finalize_dataset,
    job_cost,
    list_jobs,
    missing_jobs,
    prepare_output,
    shard_assignment,
    synthesize_shard,
)

TIMING = ("wall_seconds_last_run", "cpu_seconds_per_frame")


def _comparable_card(path: Path, ignore: tuple[str, ...]) -> dict:
    card = json.loads((path / "card.json").read_text())
    card.pop("created")
    card["generation"] = {k: v for k, v in card["generation"].items() if k not in TIMING + ignore}
    return card


def assert_same_dataset(a: Path, b: Path, ignore: tuple[str, ...] = ()) -> None:
    """Every file of ``a`` and ``b`` is the same bytes, except the timings in sequence.json and
    card.json (and the card's creation time; ``ignore``: more keys of the card's ``generation``).
    submitit's job folder is not compared."""
    def files(root: Path) -> list[Path]:
        return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file() and ".submitit" not in p.parts)

    assert files(a) == files(b)
    for rel in files(a):
        if rel.name == "sequence.json":
            ra, rb = (json.loads((root / rel).read_text()) for root in (a, b))
            assert {**ra, "seconds": None} == {**rb, "seconds": None}, rel
        elif rel.name != "card.json":
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), f"{rel} differs"
    assert _comparable_card(a, ignore) == _comparable_card(b, ignore)


def _cli(capsys, *args: str) -> tuple[int, str]:
    """``pocoloco ARGS`` in this process: (exit code, stderr)."""
    code = main(list(args))
    return code, capsys.readouterr().err


# ------------------------------------------------------------------------------ the assignment
@pytest.mark.parametrize("preset, shards", [("tiny", 1), ("tiny", 3), ("tiny", 7), ("loose", 7), ("loose", 100)])
def test_shard_assignment_covers_every_job_once_and_balances_the_cost(preset, shards):
    config = synth_preset(preset)
    jobs = list_jobs(config)
    assignment = shard_assignment(config, shards)
    assert len(assignment) == shards
    assert sorted(i for s in assignment for i in s) == list(range(len(jobs)))
    assert all(s == sorted(s) for s in assignment)  # a shard runs its jobs in list_jobs order
    assert assignment == shard_assignment(config, shards)  # every shard computes the same
    cost = [sum(job_cost(jobs[i]) for i in s) for s in assignment]
    assert max(cost) - min(cost) <= max(job_cost(j) for j in jobs)  # LPT: within one job
    if preset == "loose":  # tight (cheap) sequences spread over the shards: each gets about its share
        tight = [sum(jobs[i].subject.garment == "tight" for i in s) for s in assignment]
        share = sum(j.subject.garment == "tight" for j in jobs) / shards
        assert all(abs(t - share) <= CLOTH_COST for t in tight), tight


def test_concurrent_starts_create_one_card(tmp_path):
    """Shards starting at the same moment on an empty folder all pass prepare_output (no 'folder is not
    empty' from seeing another's temporary card) and leave one valid card."""
    config = synth_preset("tiny")

    def start(out: Path, barrier: threading.Barrier, errors: list) -> None:
        barrier.wait()
        try:
            prepare_output(config, out)
        except Exception as e:  # noqa: BLE001 (collected, asserted below)
            errors.append(e)

    for attempt in range(10):  # the old check failed 9 attempts in 10
        out = tmp_path / f"d{attempt}"
        barrier = threading.Barrier(8)
        errors: list = []
        threads = [threading.Thread(target=start, args=(out, barrier, errors)) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors, errors
        assert read_card(out)["status"] == "incomplete"
        assert [p.name for p in out.iterdir()] == ["card.json"]


@pytest.mark.parametrize("hard_links", [True, False])
def test_exclusive_card_write_never_replaces_a_card(tmp_path, monkeypatch, hard_links):
    """write_card(exclusive=True) creates card.json or leaves the existing one (and no temporary
    file); without hard links (some filesystems) it falls back to a checked rename."""
    if not hard_links:
        monkeypatch.setattr("os.link", lambda *a, **k: (_ for _ in ()).throw(PermissionError("no links")))
    config = synth_preset("tiny")
    prepare_output(config, tmp_path / "d")
    first = (tmp_path / "d" / "card.json").read_text()
    card = {**json.loads(first), "status": "complete"}
    assert not write_card(tmp_path / "d", card, exclusive=True)
    assert (tmp_path / "d" / "card.json").read_text() == first
    assert [p.name for p in (tmp_path / "d").iterdir()] == ["card.json"]
    assert write_card(tmp_path / "e", card, exclusive=True)
    assert read_card(tmp_path / "e")["status"] == "complete"


# ------------------------------------------------------------------------------ same bytes
def test_two_shards_then_finalize_equal_one_process(tiny_dataset, tmp_path):
    """(a) Shards 1/2 and 2/2 one after the other in this process, then the card: every file is the
    same bytes as the one-process run's, the card the same apart from timings. (This process may hold
    the skirt's cloth settled by the fixture's run: a shard then reuses it where the fixture settled
    afresh; the submitit test below settles afresh where the fixture reused it.)"""
    config = synth_preset("tiny")
    out = tmp_path / "d"
    records = synthesize_shard(config, out, 1, 2)
    assert [r["name"] for r in records] and read_card(out)["status"] == "incomplete"
    assert len(missing_jobs(config, out)) == len(list_jobs(config)) - len(records)
    synthesize_shard(config, out, 2, 2)
    assert not missing_jobs(config, out)
    assert read_card(out)["status"] == "incomplete"  # shards never finalise
    card = finalize_dataset(config, out)
    assert card["status"] == "complete" and card["generation"]["workers"] == 1
    assert_same_dataset(tiny_dataset, out)


def test_submitit_local_launch_gives_the_same_bytes(tiny_dataset, tmp_path):
    """(b) ``launch_synth`` with submitit's LocalExecutor: 2 shards as real subprocesses, then the
    card; the same bytes as the one-process run. A second launch has nothing left to submit."""
    pytest.importorskip("submitit")
    from pocoloco.synth.distributed import LaunchSettings, launch_synth

    config = synth_preset("tiny")
    out = tmp_path / "d"
    seen = []
    settings = LaunchSettings(backend="local", shards=2, time_minutes=30, poll_seconds=0.5)
    card = launch_synth(config, out, settings, progress=lambda done, total: seen.append((done, total)))
    assert card["status"] == "complete" and card["generation"]["shards"] == 2
    assert seen[0] == (0, 2) and seen[-1] == (2, 2)
    assert len(list((out / ".submitit").glob("*/*_result.pkl"))) == 2
    assert_same_dataset(tiny_dataset, out, ignore=("shards",))
    seen.clear()
    launch_synth(config, out, settings, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(2, 2)]
    assert len(list((out / ".submitit").glob("*/*_result.pkl"))) == 2  # nothing resubmitted


def test_failed_shards_are_one_line_naming_the_shard_and_its_log(tmp_path):
    """A shard that raises (here: a file where its first sequence's folder goes) fails the launch
    with one line: how many shards failed, the first one's error and its log."""
    pytest.importorskip("submitit")
    from pocoloco.synth.distributed import LaunchSettings, launch_synth

    config = synth_preset("tiny")
    out = tmp_path / "d"
    prepare_output(config, out)
    layout = DatasetLayout(out)
    for job in list_jobs(config):
        blocker = layout.sequence_dir(job.subject.name, job.split, job.name)
        blocker.parent.mkdir(parents=True, exist_ok=True)
        blocker.write_text("not a folder")
    settings = LaunchSettings(backend="local", shards=2, time_minutes=10, poll_seconds=0.5)
    with pytest.raises(ValueError) as e:
        launch_synth(config, out, settings)
    msg = str(e.value)
    assert re.search(r"2 of 2 shards failed; shard [12]/2: FileExistsError", msg) and "_log.err" in msg, msg
    assert "\n" not in msg and read_card(out)["status"] == "incomplete"


def test_a_timed_out_shard_job_is_requeued_with_the_same_call():
    """submitit calls ``checkpoint`` when a job reaches its time limit or is preempted; the job is
    resubmitted with what it returns (the shard then resumes from its files)."""
    pytest.importorskip("submitit")
    from pocoloco.synth.distributed import ShardJob

    job = ShardJob()
    again = job.checkpoint({"seed": 0}, "/data/d", 3, 8, workers=2)
    assert again.function is job and again.args == ({"seed": 0}, "/data/d", 3, 8) and again.kwargs == {"workers": 2}


# ------------------------------------------------------------------------------ user errors
@pytest.mark.parametrize("args, message", [
    (["--shard", "3/2"], "--shard must be K/N with 1 <= K <= N"),
    (["--shard", "0/4"], "--shard must be K/N"),
    (["--shard", "two"], "--shard must be K/N"),
    (["--shard", "1/2", "--finalize-only"], "cannot be combined"),
    (["--shard", "1/2", "--launch", "local", "--shards", "2"], "cannot be combined"),
    (["--shards", "4"], "--shards needs --launch"),
    (["--launch", "local"], "--launch needs --shards N"),
    (["--launch", "local", "--shards", "2", "--slurm-partition", "cpu"], "need --launch slurm"),
    (["--launch", "slurm", "--shards", "0"], "--shards must be >= 1"),
    (["--launch", "slurm", "--shards", "2", "--slurm-time", "0"], "--slurm-time must be >= 1"),
    (["--launch", "local", "--shards", "2", "--cpus-per-shard", "0"], "--cpus-per-shard must be >= 1"),
    (["--launch", "local", "--shards", "2", "--workers", "2"], "--workers does not apply to --launch"),
    (["--finalize-only"], "not a pocoloco dataset"),
])  # fmt: skip
def test_bad_shard_options_give_one_line_errors(capsys, tmp_path, args, message):
    code, err = _cli(capsys, "data", "synth", "--preset", "tiny", "--out", str(tmp_path / "d"), *args)
    assert code == 2 and message in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "d").exists()


def test_launch_without_submitit_says_what_to_install(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "submitit", None)  # import submitit -> ImportError
    code, err = _cli(capsys, "data", "synth", "--preset", "tiny", "--out", str(tmp_path / "d"),
                     "--launch", "local", "--shards", "2")  # fmt: skip
    assert code == 2 and "pip install 'pocoloco[cluster]'" in err and len(err.strip().splitlines()) == 1


def test_slurm_launch_off_a_cluster_is_one_line(capsys, tmp_path):
    pytest.importorskip("submitit")
    if shutil.which("srun"):
        pytest.skip("this machine is a slurm host")
    code, err = _cli(capsys, "data", "synth", "--preset", "tiny", "--out", str(tmp_path / "d"),
                     "--launch", "slurm", "--shards", "2", "--slurm-partition", "cpu")  # fmt: skip
    assert code == 2 and "could not submit the slurm jobs" in err and len(err.strip().splitlines()) == 1, err


# ------------------------------------------------------------------------------ kill and resume
def test_killed_shard_resumes_and_finalize_only_waits_for_the_others(capsys, tmp_path):
    """(c, d) SIGKILL ``--shard 1/2`` after its first frame; the same command resumes it without
    rewriting a frame; ``--finalize-only`` then refuses (one line: how many sequences are missing) and
    the card stays incomplete. (More frames and points than tiny's: the kill lands mid-sequence.)"""
    out = tmp_path / "d"
    options = ["--preset", "tiny", "--out", str(out), "--frames", "12", "--points", "20000"]
    args = ["data", "synth", *options, "--shard", "1/2"]
    proc = subprocess.Popen([sys.executable, "-m", "pocoloco.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.time() + 600
    first: list[Path] = []
    while time.time() < deadline and proc.poll() is None and not first:
        first = sorted(out.glob("subjects/*/*/*/frames/*.npz"))
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert first, "the shard wrote no frame before the deadline"
    before = {p: (p.stat().st_ino, p.read_bytes()) for p in out.glob("subjects/*/*/*/frames/*.npz")}
    assert read_card(out)["status"] == "incomplete"

    assert _cli(capsys, *args)[0] == 0
    for p, (inode, data) in before.items():
        assert p.stat().st_ino == inode and p.read_bytes() == data, f"{p} was rewritten"
    config = dataclasses.replace(synth_preset("tiny"), frames_per_sequence=12, num_points=20000)
    jobs = list_jobs(config)
    mine = {jobs[i].subject.name + "/" + jobs[i].name for i in shard_assignment(config, 2)[0]}
    missing = missing_jobs(config, out)
    assert {j.subject.name + "/" + j.name for j in missing} == {j.subject.name + "/" + j.name for j in jobs} - mine
    layout = DatasetLayout(out)
    for key in mine:
        subject, name = key.split("/")
        split = name.split("_")[0]
        assert len(layout.frame_indices(subject, split, name)) == config.frames_per_sequence
        read_frame(layout.frame_path(subject, split, name, 0))
        assert not (layout.sequence_dir(subject, split, name) / "cloth.npz").exists()

    code, err = _cli(capsys, "data", "synth", *options, "--finalize-only")
    assert code == 2 and f"{len(missing)} of {len(jobs)} sequences are not done yet" in err, err
    assert len(err.strip().splitlines()) == 1
    assert read_card(out)["status"] == "incomplete"
    with pytest.raises(ValueError, match="different configuration"):  # a shard of another run is refused
        synthesize_shard(SYNTH_PRESETS["small"], out, 2, 2)


# ------------------------------------------------------------------------------- repair on resume
def _frame_digests(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("frames/*.npz"))}


def _card_without_run_facts(root: Path) -> dict:
    card = read_card(root)
    for key in ("generation", "created"):
        card.pop(key, None)
    return card


def test_resume_repairs_damaged_frames_byte_for_byte_and_a_failed_finalize_keeps_the_card(tiny_dataset, tmp_path, capsys):
    """A truncated, a missing and a corrupt (one flipped byte) frame file: ``data synth`` over the
    dataset generates exactly those again (one warning per sequence), with the same bytes as the
    undamaged run and the same card; ``--finalize-only`` over a damaged dataset fails in one line and
    leaves ``card.json`` byte for byte as it was."""
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    layout = DatasetLayout(data)
    frames = [p for _, _, p in layout.iter_frames("train")] + [p for _, _, p in layout.iter_frames("test")]
    truncated, missing, corrupt = frames[0], frames[len(frames) // 2], frames[-1]
    truncated.write_bytes(truncated.read_bytes()[:1000])
    missing.unlink()
    raw = bytearray(corrupt.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    corrupt.write_bytes(bytes(raw))

    card_bytes = layout.card_path.read_bytes()
    code, err = _cli(capsys, "data", "synth", "--preset", "tiny", "--out", str(data), "--finalize-only")
    assert code == 2 and len(err.strip().splitlines()) == 1 and layout.card_path.read_bytes() == card_bytes, err

    code, err = _cli(capsys, "data", "synth", "--preset", "tiny", "--out", str(data))
    assert code == 0, err
    assert err.count("damaged frame file(s)") == len({truncated.parent, missing.parent, corrupt.parent}), err
    assert _frame_digests(data) == _frame_digests(tiny_dataset)
    assert _card_without_run_facts(data) == _card_without_run_facts(tiny_dataset)
    # a resume with one sequence left (its mark removed): what was done before is reported in one
    # count before any new frame (a log's time-left estimate starts from it), the rest is made by
    # the workers, and every sequence's record comes back, in job order, with the same bytes
    tiny = synth_preset("tiny")
    jobs = list_jobs(tiny)
    layout.sequence_meta_path(jobs[-1].subject.name, jobs[-1].split, jobs[-1].name).unlink()
    calls: list[tuple[int, int]] = []
    records = synthesize_shard(tiny, data, 1, 1, workers=2, progress=lambda d, t: calls.append((d, t)))
    total = len(jobs) * tiny.frames_per_sequence
    assert calls[0] == (total - tiny.frames_per_sequence, total) and calls[-1] == (total, total), calls
    assert [r["name"] for r in records] == [j.name for j in jobs]
    assert _frame_digests(data) == _frame_digests(tiny_dataset)


def test_one_writer_per_dataset_shards_share_it(tmp_path, capsys):
    """A dataset being written is locked: a second ``data synth`` (or ``--finalize-only``) into it is
    one line naming the holder; shards hold the dataset shared (they run side by side) and their own
    shard exclusively."""
    from pocoloco.utils.atomic import exclusive_lock

    out = tmp_path / "data"
    with exclusive_lock(out, "pocoloco data synth"):
        for extra in ([], ["--finalize-only"], ["--shard", "1/2"]):
            code, err = _cli(capsys, "data", "synth", "--preset", "tiny", "--out", str(out), *extra)
            assert code == 2 and "in use by pocoloco data synth (pid" in err and len(err.strip().splitlines()) == 1, err
    with exclusive_lock(out, "shard 1/2", shared=True), exclusive_lock(out, "shard 1/2", name=".lock-shard-1-of-2"):
        with exclusive_lock(out, "shard 2/2", shared=True):  # another shard shares the dataset
            pass
        with pytest.raises(ValueError, match="in use by shard 1/2"):
            with exclusive_lock(out, "shard 1/2 again", name=".lock-shard-1-of-2"):
                pass
        with pytest.raises(ValueError, match="in use by"):
            with exclusive_lock(out, "pocoloco data synth"):
                pass
