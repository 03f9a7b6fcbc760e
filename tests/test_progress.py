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
