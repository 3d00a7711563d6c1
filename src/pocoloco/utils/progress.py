"""Progress of long work: a rich bar on a terminal, plain lines in a log.

:class:`Progress` is what every long command and the training loop use. On a terminal it draws a
rich bar on stderr. A rich bar draws nothing into a file, so a job started with
``nohup ... > job.log`` would say nothing until it ends; where stderr is not a terminal
:class:`LogProgress` writes a plain line instead, at most every ``LOG_PROGRESS_EVERY_S`` seconds
(``frames: 1,234 / 19,040 (6 %), 12:34 elapsed, ~3:05:10 left``), and a last one at the end if it
wrote any; a job shorter than the interval writes nothing.
"""

from __future__ import annotations

import sys
import time
from typing import Any

#: seconds between two progress lines in a log
LOG_PROGRESS_EVERY_S = 60.0


def now() -> float:
    """The clock the progress lines use (monotonic seconds; replaced in tests)."""
    return time.monotonic()


def stderr_is_terminal() -> bool:
    return sys.stderr.isatty()


def duration(seconds: float) -> str:
    """``1:02:03`` from an hour on, ``2:03`` below."""
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def time_left(by_count: float | None, deadline: float | None) -> tuple[float | None, bool]:
    """(seconds left, whether the deadline decides): the count's estimate ``by_count`` capped by
    the ``deadline`` (a :func:`now` time; None: none)."""
    if deadline is None:
        return by_count, False
    by_clock = max(deadline - now(), 0.0)
    if by_count is None or by_clock < by_count:
        return by_clock, True
    return by_count, False


class LogProgress:
    """Plain progress lines on stderr (module docstring). ``update(done, total=None, **fields)``;
    a ``loss`` field is shown when ``loss``; :meth:`finish` writes the last line if any was written.
    ``deadline_s``: the work stops this many seconds after the start whatever the count (a training
    time budget); the time left is then the smaller of the two."""

    def __init__(self, label: str, total: int | None = None, loss: bool = False, done: int | None = None,
                 deadline_s: float | None = None):  # fmt: skip
        self.label, self.total, self.loss = label, total, loss
        self.start = self.last = now()
        self.deadline = None if deadline_s is None else self.start + deadline_s
        self.done = done or 0
        # the time left is estimated from the work done since the first count (a resumed job
        # reports what it had finished before as done at once)
        self.first, self.first_time = done, self.start
        self.fields: dict = {}
        self.printed = False

    def line(self) -> str:
        elapsed = now() - self.start
        text = f"{self.label}: {self.done:,}"
        if self.total:
            text += f" / {self.total:,} ({100.0 * self.done / self.total:.0f} %)"
        text += f", {duration(elapsed)} elapsed"
        if self.total and self.first is not None and self.first < self.done < self.total:
            rate = (self.done - self.first) / max(now() - self.first_time, 1e-9)
            left = time_left((self.total - self.done) / rate, self.deadline)
            text += f", ~{duration(left[0])} left" + (" (time budget)" if left[1] else "")
        if self.loss and "loss" in self.fields:
            text += f", loss {self.fields['loss']}"
        return text

    def update(self, done: int, total: int | None = None, **fields) -> None:
        if self.first is None:
            self.first, self.first_time = done, now()
        self.done = done
        self.total = total if total is not None else self.total
        self.fields.update(fields)
        if now() - self.last >= LOG_PROGRESS_EVERY_S:
            self.emit()

    def emit(self) -> None:
        print(self.line(), file=sys.stderr, flush=True)
        self.last, self.printed = now(), True

    def finish(self) -> None:
        if self.printed:
            self.emit()


class Progress:
    """Progress of one long piece of work: a rich bar on a terminal (stderr), :class:`LogProgress`
    lines where stderr is not a terminal, nothing when not ``enabled``.

    ``update(done, total=None, **fields)`` sets the count (and any column's field: ``loss``, shown
    when ``loss``); ``advance(**fields)`` counts one more; ``close()`` (or leaving the ``with``
    block) ends it. ``done``: the count before this run (a resumed job), shown at once.
    ``transient``: the bar disappears from the terminal at the end. ``deadline_s``: the work stops
    this many seconds from now whatever the count (``train --time-budget``); the time left shown
    is the smaller of the count's estimate and the clock's.
    """

    def __init__(self, label: str, total: int | None = None, loss: bool = False, done: int = 0,
                 transient: bool = True, enabled: bool = True, deadline_s: float | None = None):  # fmt: skip
        self.done = done
        self.bar: Any = None
        self.log: LogProgress | None = None
        if not enabled:
            return
        if not stderr_is_terminal():
            self.log = LogProgress(label, total, loss, done=done if done else None, deadline_s=deadline_s)
            return
        from rich import progress as rp
        from rich.console import Console

        columns: list[Any] = [rp.TextColumn(label), rp.BarColumn(), rp.MofNCompleteColumn()]
        if loss:
            columns.append(rp.TextColumn("loss {task.fields[loss]}"))
        columns += [rp.TimeElapsedColumn(), rp.TimeRemainingColumn() if deadline_s is None else
                    _budgeted_time_remaining(now() + deadline_s)]  # fmt: skip
        self.bar = rp.Progress(*columns, transient=transient, console=Console(stderr=True))
        self.bar.start()
        self.task = self.bar.add_task(label, total=total, completed=done, **({"loss": "-"} if loss else {}))

    def update(self, done: int, total: int | None = None, **fields) -> None:
        self.done = done
        if self.bar is not None:
            self.bar.update(self.task, completed=done, **({"total": total} if total is not None else {}), **fields)
        elif self.log is not None:
            self.log.update(done, total, **fields)

    def advance(self, **fields) -> None:
        self.update(self.done + 1, **fields)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
        elif self.log is not None:
            self.log.finish()
        self.bar = self.log = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _budgeted_time_remaining(deadline: float) -> Any:
    """rich's time-remaining column capped by ``deadline`` (a :func:`now` time); rich is imported
    only when a bar is drawn."""
    from rich.progress import ProgressColumn
    from rich.text import Text

    class BudgetedTimeRemaining(ProgressColumn):
        def render(self, task) -> Text:
            left, by_clock = time_left(task.time_remaining, deadline)  # never None: there is a deadline
            return Text(duration(left) + (" (budget)" if by_clock else ""), style="progress.remaining")

    return BudgetedTimeRemaining()
