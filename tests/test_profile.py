"""`bench.profile`: the peak memory a call's tensors add, from the profiler's allocation events; what counts as
one op."""

import os

import torch
from conftest import needs_cpu_fused_adamw

from diffshadow.bench.profile import _without_kineto_chatter, op_counts, peak_bytes

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


def test_a_call_recorded_in_pieces_counts_what_it_counts_whole():
    """With `pieces` the record is cut where the call asks (a frame's `interrupt`) and each piece tallied alone;
    a tensor made in one piece and freed in a later one still counts once, so ops, syncs, host tensors and the
    peak are those of the whole record: here 1,000 + 3,000 floats at once, then a host read and a host tensor."""
    cuts = []

    def work(cut=lambda: False):
        a = torch.ones(1000)
        cuts.append(cut())  # as an interrupt: never "stop"
        b = a + 1.0
        b = torch.cat([b, b, b])  # 3,000 floats while `a` lives: 16,000 bytes with it
        del a
        cuts.append(cut())
        return float(b.sum()), torch.tensor([2.0])

    whole = op_counts(work, memory=CPU)
    assert whole == op_counts(work, memory=CPU, pieces=True) and cuts == [False] * 4  # each call cut twice
    assert whole["peak_bytes"] >= 16_000 and whole["syncs"] == 1 and whole["host_tensors"] == 1
    assert peak_bytes(work, CPU) == peak_bytes(work, CPU, pieces=True) == whole["peak_bytes"]


@needs_cpu_fused_adamw
def test_a_multi_tensor_op_counts_one_op_whatever_its_tensors():
    """A GPU runs `_foreach_lerp_` over ten tensors as one call (a few launches); a CPU as ten lerps underneath,
    which the count leaves out, so a CPU's count says what a GPU launches. The same lerps one by one are ten."""
    xs, ys = [torch.zeros(3) for _ in range(10)], [torch.ones(3) for _ in range(10)]
    assert op_counts(lambda: torch._foreach_lerp_(xs, ys, 0.5))["ops"] == 1
    assert op_counts(lambda: [x.lerp_(y, 0.5) for x, y in zip(xs, ys, strict=True)])["ops"] == 10
    params = [torch.nn.Parameter(torch.ones(4)) for _ in range(6)]
    for p in params:
        p.grad = torch.ones(4)
    opt = torch.optim.AdamW(params, lr=0.1, fused=True)
    opt.step()  # the first step makes the state
    assert op_counts(opt.step)["ops"] == 2  # the step counters' foreach add and the fused update, not 6 of each


def test_a_tensor_built_from_host_data_counts_once_and_arithmetic_on_tensors_never():
    """On a GPU a tensor built from host numbers or an array is a blocking copy (a stream synchronise), which no
    op or sync count sees: each one counts as a host tensor, whatever builds it; a Python number in arithmetic is
    passed to the kernel and a tensor already made is not built again."""
    import numpy as np

    x = torch.ones(3)
    array = np.arange(3.0)
    assert op_counts(lambda: torch.tensor([1.0, 2.0]))["host_tensors"] == 1
    assert op_counts(lambda: [torch.as_tensor(array, dtype=torch.float32), torch.from_numpy(array)]) == {
        "ops": 1, "syncs": 0, "host_tensors": 2}  # the one op: as_tensor's conversion to float32
    assert op_counts(lambda: [x * 2.0, torch.as_tensor(x), x.new_full((3,), 2.0)])["host_tensors"] == 0


def test_counting_writes_nothing_to_stderr_and_passes_other_lines_on(capfd):
    """The profiler's own start and stop lines (PyTorch 2.13's Kineto writes them to file descriptor 2) do not reach
    a job's log; another line written while they are held back does, and so does what the call itself writes."""
    op_counts(lambda: os.write(2, b"the call's own line\n"))
    assert capfd.readouterr().err == "the call's own line\n"
    with _without_kineto_chatter():
        os.write(2, b"USDT:2026-11-29 03:24:31 30640:30640 SyncActivityProfilerHandler.cpp:52] profiler_start\n"
                    b"a warning\n")
    assert capfd.readouterr().err == "a warning\n"
