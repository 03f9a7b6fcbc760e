"""`bench.profile`: the peak memory a call's tensors add, from the profiler's allocation events."""

import torch

from diffshadow.bench.profile import op_counts, peak_bytes

CPU = torch.device("cpu")


def allocate_and_free():
    """1,000 and then 3,000 floats live at once (16,000 bytes), then 500 more after the first is freed (14,000)."""
    a = torch.empty(1000)
    b = torch.empty(3000)
    del a
    c = torch.empty(500)
    return b, c


def test_peak_bytes_is_the_most_bytes_live_at_once():
    assert peak_bytes(allocate_and_free, CPU) == 16_000
    assert op_counts(allocate_and_free, memory=CPU)["peak_bytes"] == 16_000
    assert "peak_bytes" not in op_counts(allocate_and_free)


def test_peak_bytes_is_what_the_call_added():
    """Tensors alive before the call do not count, and a call that allocates nothing adds nothing."""
    before = torch.ones(10_000)
    assert peak_bytes(lambda: before + before, CPU) == 40_000
    assert peak_bytes(lambda: None, CPU) == 0
