"""Counts that do not drift with the machine's load: kernel-launching ops and host syncs of a call.

Counted with torch.profiler on any device. An *op* is a leaf aten op that does work (a kernel launch on
a GPU): views, reshapes, allocations and scalar reads are left out, and a composite op counts through
its leaves; a fused Triton kernel (`diffshadow.render.fused`) counts one op per launch. A *host sync* is an op
whose result the host must wait for: a scalar read (`_local_scalar_dense`, behind `.item()`, `bool()`,
`int()`), `nonzero` (behind boolean indexing) and the other ops whose output shape depends on data. A *host
tensor* is a tensor built from host numbers or arrays (`torch.tensor`, `as_tensor`, `from_numpy`: the profiler's
`aten::lift_fresh`). On a GPU each one built there is a blocking host-to-device copy, which PyTorch follows with a
wait for the device's queue (a stream synchronise): a sync that no op count sees, since on a CPU it is no op at all.
Counted apart from the syncs because a CPU count cannot tell the ones a GPU run builds on the device (inputs,
constants) from those it keeps on the host.

On a CPU every tensor is on the host, so a count taken there cannot tell a scalar that a GPU run keeps on the
host from one it would have to fetch. One such case is known and named: PyTorch's Adam and AdamW without
`fused` or `capturable` keep their step counter as a CPU tensor on every device and read it in `step`
(torch/optim/adam.py), a host read and no device sync. `host_scopes` lists the profiler scopes whose scalar
reads are such host reads: counted as `host_reads`, not `syncs`.

A multi-tensor op (`_foreach_*`, `_fused_*`: the EMA's lerp, the gradient clip's norms and scaling, fused AdamW)
counts one op on every device: a GPU runs it as a few launches over all the tensors, a CPU as one op per tensor
underneath, which would count the CPU's loop (608 of the geometry stage's 1,026 ops a step at the README's
sizes) where a GPU has one call.

Given a device, the same profiled call also gives its peak memory: the most bytes its tensors held at once on
that device's allocator, from the profiler's allocation events (frees count negative). On CUDA that is what
`max_memory_allocated` says; on a CPU it needs no sampling of the resident set, and like the op count it does
not drift with the machine's load.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from torch._C._profiler import _EventType  # the event tree's tags; torch.profiler's own memory tools read it
from torch.autograd.profiler import profile  # torch.profiler's recorder (why not torch.profiler: `_record`)

from diffshadow.render.fused import LAUNCH

NO_WORK = frozenset({
    "aten::view", "aten::reshape", "aten::_reshape_alias", "aten::expand", "aten::expand_as", "aten::as_strided",
    "aten::slice", "aten::select", "aten::unsqueeze", "aten::squeeze", "aten::t", "aten::transpose",
    "aten::permute", "aten::detach", "aten::detach_", "aten::alias", "aten::empty", "aten::empty_strided",
    "aten::empty_like", "aten::resolve_conj", "aten::resolve_neg", "aten::_unsafe_view", "aten::split",
    "aten::split_with_sizes", "aten::unbind", "aten::chunk", "aten::narrow", "aten::lift_fresh",
    "aten::lift_fresh_copy", "aten::result_type", "aten::view_as", "aten::numpy_T", "aten::contiguous",
    "aten::to", "aten::_to_copy", "aten::set_", "aten::is_nonzero", "aten::item", "aten::_local_scalar_dense",
    "aten::dim", "aten::size", "aten::stride",
})
SYNCS = frozenset({"aten::_local_scalar_dense", "aten::nonzero", "aten::masked_select", "aten::_unique2",
                   "aten::unique_consecutive", "aten::unique_dim"})


MULTI_TENSOR = ("aten::_foreach_", "aten::_fused_")
OPTIMIZER_STEP = "Optimizer.step#"  # the profiler's scope of torch.optim's `step` (Optimizer.step#Adam.step)


def op_counts(fn: Callable[..., object], host_scopes: tuple[str, ...] = (),
              memory: torch.device | None = None, *, pieces: bool = False) -> dict[str, int]:
    """{"ops": kernel-launching ops, "syncs": host syncs, "host_tensors": tensors built from host data} of one
    call of `fn`; given `host_scopes` (scope-name prefixes, see the module docstring), also "host_reads": the
    scalar reads inside them, not counted as syncs; given `memory`, a device, also "peak_bytes": the peak bytes
    the call's tensors added on its allocator.

    With `pieces`, `fn` is given a callback to call between pieces of its work (a frame's `interrupt`, asked
    before every iteration of its marches; it returns False): the record is cut there and each piece tallied as
    it ends, so the profiler holds one piece's events at a time, not the call's. The same counts and peak (a
    running sum carried over the cuts); a naive 64² frame of tooth, 228,513 ops, had taken the benchmark job to
    10 GB at once."""
    counts = {"ops": 0, "syncs": 0, "host_reads": 0, "host_tensors": 0}
    peak = _record(fn, shapes=True, memory=memory, pieces=pieces, tally=lambda p: _tally(p, host_scopes, counts))
    return {"ops": counts["ops"], "syncs": counts["syncs"], "host_tensors": counts["host_tensors"],
            **({"host_reads": counts["host_reads"]} if host_scopes else {}),
            **({"peak_bytes": peak} if memory is not None else {})}


def _tally(prof: profile, host_scopes: tuple[str, ...], counts: dict[str, int]) -> None:
    """Add one record's ops, syncs, host reads and host tensors to `counts` (`op_counts`)."""
    for e in _ops(prof):
        if e.name == LAUNCH:
            counts["ops"] += 1
        if not e.name.startswith("aten::") or _inside(e, (LAUNCH,)):  # Triton's interpreter runs aten ops there
            continue
        if e.name == "aten::lift_fresh":
            counts["host_tensors"] += 1
        if e.name in SYNCS:
            if e.name == "aten::_local_scalar_dense" and _inside(e, host_scopes):
                counts["host_reads"] += 1
            else:
                counts["syncs"] += 1
        if _inside(e, MULTI_TENSOR):  # a CPU's per-tensor loop inside one multi-tensor op
            continue
        if e.name.startswith(MULTI_TENSOR):
            counts["ops"] += 1
            continue
        if e.name in NO_WORK or any(c.tag == _EventType.TorchOp and c.name.startswith("aten::")
                                    and c.name not in NO_WORK for c in e.children):
            continue
        if e.name == "aten::copy_" and e.extra_fields.inputs and getattr(e.extra_fields.inputs[0], "sizes", 0) == []:
            continue  # a Python number wrapped and converted on the host (`x * 0.5`): no kernel on a GPU
        counts["ops"] += 1


def peak_bytes(fn: Callable[..., object], device: torch.device, *, pieces: bool = False) -> int:
    """Peak bytes one call of `fn` added on `device`'s allocator (as `op_counts(fn, memory=device)`, without
    counting ops: no slower than the call itself; `pieces` as there)."""
    return _record(fn, shapes=False, memory=device, pieces=pieces)


def _record(fn: Callable[..., object], *, shapes: bool, memory: torch.device | None, pieces: bool,
            tally: Callable[[profile], None] = lambda prof: None) -> int | None:
    """Profile one call of `fn` (with input shapes), handing each record to `tally` as it ends: one record, or with
    `pieces` one per piece (`op_counts`). Given `memory`, return the peak bytes the call added on that device's
    allocator. CUDA's allocator keeps its own peak, which is exact: the profiler's allocation events missed a free
    on the H200 (PyTorch 2.11: 18 MiB summed where 16 MiB were ever held), so they are summed only where no
    allocator counts (the CPU)."""
    cuda = memory is not None and memory.type == "cuda"
    if cuda:
        torch.cuda.synchronize(memory)
        torch.cuda.reset_peak_memory_stats(memory)
        base = torch.cuda.memory_allocated(memory)
    events = memory is not None and not cuda
    live = peak = 0
    prof = None

    def start() -> None:
        nonlocal prof
        # what torch.profiler.profile(activities=[CPU]) records, without its start's `hasattr(torch, "_inductor")`,
        # which imported PyTorch's compiler (torch._inductor, torch._dynamo): 1.3 s of the benchmark job
        prof = profile(use_kineto=True, record_shapes=shapes, profile_memory=events)
        with _without_kineto_chatter():
            prof.__enter__()

    def stop() -> None:
        nonlocal live, peak
        with _without_kineto_chatter():
            prof.__exit__(None, None, None)
        if events:
            live, peak = _allocated_peak(prof, memory, live, peak)
        tally(prof)

    def cut() -> bool:
        stop()
        start()
        return False  # as an `interrupt`: go on

    start()
    try:
        fn(cut) if pieces else fn()
        if cuda:
            torch.cuda.synchronize(memory)
    finally:
        stop()
    if memory is None:
        return None
    return torch.cuda.max_memory_allocated(memory) - base if cuda else peak


# Kineto's own log lines: "USDT:2026-11-29 03:24:31 30640:30640 SyncActivityProfilerHandler.cpp:52] profiler_start"
KINETO_CHATTER = re.compile(rb"^[A-Z]+:\S+ \S+ \d+:\d+ \w+\.cpp:\d+\] ")


@contextmanager
def _without_kineto_chatter() -> Iterator[None]:
    """Drop Kineto's log lines from what is written to the process's stderr (file descriptor 2) meanwhile.

    PyTorch 2.13's profiler writes "profiler_start" and "profiler_stop" lines there at every start and stop, which
    neither KINETO_LOG_LEVEL nor GLOG_minloglevel silences: 14 of them filled the README run's benchmark log. Only
    the start and the stop run inside this, and any other line written meanwhile is passed on."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as caught:
            os.dup2(caught.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved, 2)
                caught.seek(0)
                kept = [line for line in caught.read().splitlines(keepends=True) if not KINETO_CHATTER.match(line)]
                if kept:
                    os.write(2, b"".join(kept))
    finally:
        os.close(saved)


def _nodes(prof: profile) -> Iterator:
    """Every node of the profiled call's event tree (ops, scopes, allocations), in no particular order. Read from
    the tree, not through `prof.events()`, whose Python objects for every event took 50x longer to build: 19 s for
    a naive 64² frame's 312,000 events, where the tree is walked in 0.4 s (PyTorch 2.13, 2 CPU cores)."""
    stack = list(prof.kineto_results.experimental_event_tree())
    while stack:
        e = stack.pop()
        stack.extend(e.children)
        yield e


def _ops(prof: profile) -> Iterator:
    return (e for e in _nodes(prof) if e.tag == _EventType.TorchOp)


def _allocated_peak(prof: profile, device: torch.device, live: int = 0, peak: int = 0) -> tuple[int, int]:
    """The running sum of the profiled call's allocation events on `device`, in time order, from `live` bytes
    held before it: (bytes held at its end, the sum's maximum, at least `peak`)."""
    events = sorted((e.start_time_ns, e.extra_fields.alloc_size) for e in _nodes(prof)
                    if e.tag == _EventType.Allocation and e.extra_fields.device.type == device.type)
    for _, size in events:
        live += size
        peak = max(peak, live)
    return live, peak


def _inside(event, prefixes: tuple[str, ...]) -> bool:
    """Whether a profiler scope above `event` has a name starting with one of `prefixes`."""
    parent = event.parent
    while parent is not None:
        if parent.name.startswith(prefixes):
            return True
        parent = parent.parent
    return False
