"""Where a job's time goes: interpreter and imports, device start, compilation, reading and writing, compute.

Each `diffshadow` process keeps one clock (`phase`); the CLI writes it beside the job's Snakemake benchmark
file when given `--phases FILE`, and `report.stage_costs` adds the phases to each rule's row. Phases do not
nest: time inside an inner phase counts to the outer one (a checkpoint written inside a compiled region is
compile time), so the phases of a process add up to its life. `compute` is the remainder: the process's life
less every named phase. The process's life is read from the kernel (Linux: /proc/self/stat, 10 ms ticks), so
interpreter start-up and module imports before `main` count as `import`.

This module imports nothing heavy: jobs that need no torch must stay without it (docs/performance.md).
"""

from __future__ import annotations

import functools
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

PHASES = ("import", "device", "compile", "io", "compute")  # the order of the report's columns

_totals: dict[str, float] = dict.fromkeys(PHASES, 0.0)
_active: list[str] = []
_MODULE_LOADED = time.monotonic()


@contextmanager
def phase(name: str) -> Iterator[None]:
    """Count the time inside the block to `name` (one of PHASES except compute), unless a phase is already open."""
    if name not in PHASES or name == "compute":
        raise ValueError(f"phase: expected one of {', '.join(PHASES[:-1])}, got {name!r}")
    if _active:
        yield
        return
    _active.append(name)
    start = time.perf_counter()
    try:
        yield
    finally:
        _totals[name] += time.perf_counter() - start
        _active.pop()


def timed(name: str) -> Callable:
    """A decorator: every call of the function counts to phase `name`."""
    def wrap(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def inner(*args, **kwargs):
            with phase(name):
                return fn(*args, **kwargs)
        return inner
    return wrap


def process_age() -> float:
    """Seconds since this process started: from the kernel where it says (Linux), else since this module loaded."""
    try:
        # field 22 (starttime) counts clock ticks since boot; the command name (field 2) may hold spaces
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return time.monotonic() - _MODULE_LOADED


def mark_imports_done() -> None:
    """Count everything so far that no phase claimed (interpreter start-up, module imports) as `import`."""
    _totals["import"] = max(0.0, process_age() - sum(v for k, v in _totals.items() if k != "import"))


def totals() -> dict[str, float]:
    """Seconds per phase so far, `compute` the remainder of the process's life."""
    life = process_age()
    named = {k: v for k, v in _totals.items() if k != "compute"}
    return {**named, "compute": max(0.0, life - sum(named.values()))}


def reset() -> None:
    """Zero the clock (for tests, and a process that times several jobs)."""
    for key in _totals:
        _totals[key] = 0.0


def usage() -> dict[str, float]:
    """This process's CPU seconds (user and system, its threads and the children it waited for) and its peak
    resident set in MiB (the largest of itself and any one such child), from the kernel's own accounting.
    Snakemake's benchmark samples a job's processes every 30 s once it has run 15 s, so it misses a job's last
    stretch and any peak between samples (`report.stage_costs` takes the larger of the two). Linux starts a
    process's peak at its parent's resident set when the parent forked it: a job's process, forked by the job's
    shell, starts near 0; a DDP rank, forked by torchrun, at torchrun's."""
    t = os.times()
    out = {"cpu_s": t.user + t.system + t.children_user + t.children_system, "max_rss_mib": 0.0}
    try:
        import resource

        unit = 1 if sys.platform == "darwin" else 1024  # ru_maxrss: bytes on macOS, KiB on Linux
        peak = max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
        out["max_rss_mib"] = peak * unit / 2**20
    except (ImportError, OSError):  # no resource module (Windows): the peak stays unknown, 0
        pass
    return out


# the libraries whose release can change a job's numbers, recorded where the job imported them
NUMERIC_LIBRARIES = ("numpy", "scipy", "torch", "triton", "zarr")


def versions() -> dict[str, str]:
    """Python's version and each of `NUMERIC_LIBRARIES` this process imported (none is imported here)."""
    found = {"python": ".".join(map(str, sys.version_info[:3]))}
    for name in NUMERIC_LIBRARIES:
        if name in sys.modules:
            found[name] = str(getattr(sys.modules[name], "__version__", "?"))
    return found


def record(command: str) -> dict:
    """The clock as a JSON-able record (`<phase>_s`, and `process_s`, the process's life) of `command`, with the
    process's `usage` (`cpu_s`, `max_rss_mib`), the `versions` it ran under and, where it imported PyTorch, the
    CPU kernels PyTorch chose (`cpu_capability`: DEFAULT, AVX2, AVX512, ...) and its CPU threads (`threads`)."""
    out: dict = {f"{k}_s": round(v, 3) for k, v in totals().items()}
    out["process_s"] = round(sum(out.values()), 3)
    out.update({k: round(v, 3) for k, v in usage().items()})
    if "torch" in sys.modules:  # the CPU kernels it ran (its vector unit changes the last bits): no import here
        out["cpu_capability"] = sys.modules["torch"].backends.cpu.get_cpu_capability()
        out["threads"] = sys.modules["torch"].get_num_threads()  # its reductions split by thread: last bits too
    out["versions"] = versions()
    out["command"] = command
    return out
