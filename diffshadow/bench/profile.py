"""Counts that do not drift with the machine's load: kernel-launching ops and host syncs of a call.

Counted with torch.profiler on any device. An *op* is a leaf aten op that does work (a kernel launch on
a GPU): views, reshapes, allocations and scalar reads are left out, and a composite op counts through
its leaves; a fused Triton kernel (`diffshadow.render.fused`) counts one op per launch. A *host sync* is an op
whose result the host must wait for: a scalar read (`_local_scalar_dense`, behind `.item()`, `bool()`,
`int()`), `nonzero` (behind boolean indexing) and the other ops whose output shape depends on data.

On a CPU every tensor is on the host, so a count taken there cannot tell a scalar that a GPU run keeps on the
host from one it would have to fetch. One such case is known and named: PyTorch's Adam and AdamW without
`fused` or `capturable` keep their step counter as a CPU tensor on every device and read it in `step`
(torch/optim/adam.py), a host read and no device sync. `host_scopes` lists the profiler scopes whose scalar
reads are such host reads: counted as `host_reads`, not `syncs`.
"""

from __future__ import annotations

from collections.abc import Callable

from torch.profiler import ProfilerActivity, profile

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


OPTIMIZER_STEP = "Optimizer.step#"  # the profiler's scope of torch.optim's `step` (Optimizer.step#Adam.step)


def op_counts(fn: Callable[[], object], host_scopes: tuple[str, ...] = ()) -> dict[str, int]:
    """{"ops": kernel-launching ops, "syncs": host syncs} of one call of `fn`; given `host_scopes` (scope-name
    prefixes, see the module docstring), also "host_reads": the scalar reads inside them, not counted as syncs."""
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        fn()
    ops = syncs = host_reads = 0
    for e in prof.events():
        if e.name == LAUNCH:
            ops += 1
        if not e.name.startswith("aten::") or _inside(e, (LAUNCH,)):  # Triton's interpreter runs aten ops there
            continue
        if e.name in SYNCS:
            if e.name == "aten::_local_scalar_dense" and _inside(e, host_scopes):
                host_reads += 1
            else:
                syncs += 1
        if e.name in NO_WORK or any(c.name.startswith("aten::") and c.name not in NO_WORK for c in e.cpu_children):
            continue
        if e.name == "aten::copy_" and e.input_shapes and e.input_shapes[0] == []:
            continue  # a Python number wrapped and converted on the host (`x * 0.5`): no kernel on a GPU
        ops += 1
    return {"ops": ops, "syncs": syncs, **({"host_reads": host_reads} if host_scopes else {})}


def _inside(event, prefixes: tuple[str, ...]) -> bool:
    """Whether a profiler scope above `event` has a name starting with one of `prefixes`."""
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith(prefixes):
            return True
        parent = parent.cpu_parent
    return False
