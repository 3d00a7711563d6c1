"""Generate a dataset as shards on a cluster (slurm) or as local processes, through submitit.

``launch_synth(config, out, LaunchSettings(backend="slurm", shards=50))`` submits one job per
shard (a slurm job array; ``backend="local"``: one subprocess per shard on this machine, all at
once), each running :func:`run_shard` -- ``synth.pipeline.synthesize_shard`` for its share of the
sequences -- into ``out`` (a folder every job sees: a shared filesystem). It waits, reporting
shards done, then writes the dataset card (``synth.pipeline.finalize_dataset``).

Rerunning the same launch resumes: only shards with sequences still missing are submitted, and
those skip their finished sequences. A job stopped at its time limit (or preempted) is requeued
by submitit and resumes the same way (:class:`ShardJob`). submitit is the optional ``cluster`` extra
(``pip install pocoloco[cluster]``); its job files and logs go to ``out/.submitit`` unless
``log_dir`` is given.
"""

from __future__ import annotations

import os
import re
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .config import SynthConfig

__all__ = ["BACKENDS", "LaunchSettings", "ShardJob", "launch_synth", "run_shard"]

BACKENDS = ("slurm", "local")


@dataclass(frozen=True)
class LaunchSettings:
    """How to run the shards.

    backend: ``"slurm"`` (one job array of ``shards`` tasks) or ``"local"`` (``shards``
        subprocesses on this machine, all at once; submitit's LocalExecutor).
    shards: number of shards N (jobs); shard K runs ``synth.pipeline.shard_assignment(config, N)[K-1]``.
    cpus_per_shard: CPUs each job asks for; its sequences run in as many worker processes.
    time_minutes: each job's time limit (slurm ``--time``; local jobs are stopped after it too).
    partition: slurm partition (default: the cluster's default).
    log_dir: submitit's job files and logs (default: ``OUT/.submitit``).
    poll_seconds: how often the jobs' states are checked while waiting.
    """

    backend: str = "slurm"
    shards: int = 1
    cpus_per_shard: int = 1
    time_minutes: int = 24 * 60
    partition: str | None = None
    log_dir: str | os.PathLike | None = None
    poll_seconds: float = 5.0

    def check(self) -> None:
        """ValueError naming the first bad setting."""
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        for name in ("shards", "cpus_per_shard", "time_minutes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.poll_seconds <= 0:
            raise ValueError(f"poll_seconds must be positive, got {self.poll_seconds}")


def run_shard(config_dict: dict, out: str, shard: int, num_shards: int, workers: int = 1) -> dict:
    """What each submitted job runs: shard ``shard`` of ``num_shards`` of ``config_dict``'s dataset
    into ``out``. Prints a line per finished sequence (the job's log). Returns
    ``{"shard", "sequences", "frames_stored"}``."""
    from .pipeline import synthesize_shard  # lazy: the synth extra (newton, warp, open3d)

    config = SynthConfig.from_dict(config_dict)
    per = config.frames_per_sequence

    def progress(done: int, total: int) -> None:
        if done % per == 0 or done == total:
            print(f"shard {shard}/{num_shards}: {done}/{total} frames", flush=True)

    records = synthesize_shard(config, out, shard, num_shards, workers=workers, progress=progress)
    return {"shard": shard, "sequences": len(records), "frames_stored": sum(r["num_stored"] for r in records)}


class ShardJob:
    """The callable submitted per shard: :func:`run_shard`, and requeued with the same arguments when
    slurm (or the local executor) stops it at its time limit or preempts it (submitit calls
    ``checkpoint``); the requeued job resumes the shard from the files already written."""

    def __call__(self, config_dict: dict, out: str, shard: int, num_shards: int, workers: int = 1) -> dict:
        return run_shard(config_dict, out, shard, num_shards, workers)

    def checkpoint(self, *args, **kwargs):
        """submitit's hook on timeout / preemption: the same call again."""
        from submitit.helpers import DelayedSubmission

        return DelayedSubmission(self, *args, **kwargs)


def _submitit():
    try:
        import submitit
    except ImportError:
        raise ValueError("launching shards needs submitit: pip install 'pocoloco[cluster]'") from None
    return submitit


def _error_line(exc: BaseException) -> str:
    """The last ``SomeError: message`` line of a failed job's traceback text (else its first line)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    errors = [ln for ln in lines if re.match(r"^[\w.]+(Error|Exception|Interrupt|Exit)\b", ln)]
    return (errors or lines or [type(exc).__name__])[-1 if errors else 0]


def launch_synth(
    config: SynthConfig,
    out: str | os.PathLike,
    settings: LaunchSettings,
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Generate (or resume) a dataset as ``settings.shards`` submitit jobs, wait for them and write
    the card. Returns the final card.

    progress(shards_done, shards) is called as shards finish (shards that had nothing left to do
    count as done at once). Raises ValueError (one line) when submitit is missing, a setting is bad,
    the jobs cannot be submitted or a shard fails (naming it and its log; rerun to resume). An
    interrupt (Ctrl-C) cancels the jobs still running.
    """
    from .pipeline import (
        finalize_dataset,
        list_jobs,
        missing_jobs,
        prepare_output,
        shard_assignment,
        write_subject,
    )

    settings.check()
    submitit = _submitit()
    t0 = time.perf_counter()
    out = Path(out)
    prepare_output(config, out)
    for subject in config.subjects:  # once here rather than raced by every shard
        write_subject(config, out, subject)
    n = settings.shards
    missing = {(j.subject.name, j.split, j.name) for j in missing_jobs(config, out)}  # (a job holds dicts)
    keys = [(j.subject.name, j.split, j.name) for j in list_jobs(config)]
    todo = [k + 1 for k, idx in enumerate(shard_assignment(config, n)) if any(keys[i] in missing for i in idx)]
    if progress:
        progress(n - len(todo), n)
    if todo:
        log_dir = Path(settings.log_dir) if settings.log_dir is not None else out / ".submitit"
        params = {"name": "pocoloco-synth", "timeout_min": settings.time_minutes, "nodes": 1, "tasks_per_node": 1,
                  "cpus_per_task": settings.cpus_per_shard}  # fmt: skip
        if settings.backend == "slurm":
            params.update(slurm_partition=settings.partition, slurm_array_parallelism=len(todo))
        m = len(todo)
        try:
            executor = submitit.AutoExecutor(folder=log_dir / "%j", cluster=settings.backend)
            executor.update_parameters(**params)
            submitted = executor.map_array(ShardJob(), [config.to_dict()] * m, [os.fspath(out)] * m, todo, [n] * m,
                                           [settings.cpus_per_shard] * m)  # fmt: skip
        except (OSError, RuntimeError, subprocess.SubprocessError) as e:  # not a slurm host, sbatch refused ...
            raise ValueError(f"could not submit the {settings.backend} jobs: {str(e).splitlines()[0]}") from None
        _wait(submitted, todo, n, settings.poll_seconds, progress)
    return finalize_dataset(config, out, workers=settings.cpus_per_shard, wall_seconds=time.perf_counter() - t0,
                            shards=n)  # fmt: skip


def _wait(submitted: list, shards: list[int], n: int, poll_seconds: float, progress) -> None:
    """Wait for the jobs; ValueError naming the failed shards (and the first one's error and log)."""
    pending = dict(zip(shards, submitted))
    failed: list[tuple[int, object]] = []
    try:
        while pending:
            for k, job in list(pending.items()):
                if job.done():
                    del pending[k]
                    if job.exception() is not None:
                        failed.append((k, job))
                    if progress:
                        progress(n - len(pending), n)
            if pending:
                time.sleep(poll_seconds)
    except KeyboardInterrupt:
        for job in pending.values():
            job.cancel(check=False)
        raise
    if failed:
        k, job = failed[0]
        raise ValueError(f"{len(failed)} of {n} shards failed; shard {k}/{n}: {_error_line(job.exception())} "
                         f"(log: {job.paths.stderr}); rerun the same command to resume")  # fmt: skip
