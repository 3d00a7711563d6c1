"""The benchmark scripts' timer (pocoloco.utils.timing)."""

import pytest

from pocoloco.utils import timing


def test_median_seconds_warms_up_then_takes_the_median_of_the_timed_calls(monkeypatch):
    clock = iter([0.0, 5.0, 10.0, 11.0, 20.0, 23.0])  # timed calls of 5, 1 and 3 s
    monkeypatch.setattr(timing.time, "perf_counter", lambda: next(clock))
    calls = []
    assert timing.median_seconds(lambda: calls.append(1), repeats=3, warmup=2) == 3.0
    assert len(calls) == 5  # two untimed warm-up calls, three timed
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        timing.median_seconds(lambda: None, repeats=0)
