import itertools

import pytest

from diffshadow import progress


@pytest.mark.parametrize("done, total, start, expected", [
    (2, 10, 0, "10 s, ~40 s left"),   # 5 s a unit, 8 to go
    (7, 10, 5, "10 s, ~15 s left"),   # a resume at 5: the rate counts the 2 units run since, not 7
    (10, 10, 0, "10 s"),              # finished: nothing left to forecast
    (5, 10, 5, "10 s"),               # nothing run since the resume: no rate yet
])
def test_eta_forecasts_from_the_rate_since_start(monkeypatch, done, total, start, expected):
    monkeypatch.setattr(progress.time, "perf_counter", lambda: 110.0)
    assert progress.eta(done, total, 100.0, start=start) == expected


def test_a_ticker_speaks_at_most_once_an_interval_and_never_interrupts():
    """A clock that moves 25 s at each ask: lines at 75 and 150 s (60 s since the last each time), none sooner; with
    a total, how far and how long is left from the rate so far; without, how long so far."""
    said = []
    tick = progress.Ticker("lattice", 1000, log=said.append, every_s=60.0, clock=itertools.count(0.0, 25.0).__next__)
    assert not any(tick(done) for done in (100, 200, 300, 400, 500, 600, 700, 800))  # at 25, 50, ..., 200 s
    assert said == ["lattice: 30%, 75 s, ~175 s left", "lattice: 60%, 150 s, ~100 s left"]
    said.clear()
    beat = progress.Ticker("frame", log=said.append, every_s=60.0, clock=itertools.count(0.0, 25.0).__next__)
    assert not any(beat() for _ in range(3))
    assert said == ["frame: 75 s so far"]
