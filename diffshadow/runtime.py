"""Where and how a stage runs: the device (chosen once, here), threads, the node-local GPU lock, and a
DDP context that pairs process-group set-up with teardown. Concept modules receive a `torch.device` and
never work one out; only the stage layer and the CLI call this module.

Device order: the `--device` flag, then `DIFFSHADOW_DEVICE` (the PBS job scripts set it on GPU nodes),
then the config key `device` (`auto | cpu | cuda | cuda:N`); `auto` is CUDA when a GPU is visible.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy  # noqa: F401  (loads its OpenBLAS, so that set_threads reaches it)
import threadpoolctl
import torch

from diffshadow.hpc import device_setting

CPU = torch.device("cpu")
DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"


def resolve_device(flag: str | None = None, config: str | None = None) -> torch.device:
    """The device of a stage: flag → DIFFSHADOW_DEVICE → config → auto."""
    spec, source = device_setting(flag, config)
    if spec == "auto":
        return torch.device("cuda") if torch.cuda.is_available() else CPU
    try:
        device = torch.device(spec)
    except (RuntimeError, ValueError):
        raise ValueError(f"{source}: expected {DEVICE_CHOICES}, got {spec!r}") from None
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"{source}: expected {DEVICE_CHOICES}, got {spec!r}")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{source} is {spec!r} but this torch sees no CUDA device (torch {torch.__version__}, "
                             f"built with CUDA {torch.version.cuda}); use 'cpu' or 'auto'")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"{source} is {spec!r} but only {torch.cuda.device_count()} GPU(s) are visible")
    return device


def start_device(device: torch.device) -> torch.device:
    """Create the device's context now (CUDA's takes seconds), so that a job's device start is one timed phase and
    not hidden in its first tensor; nothing to do on a CPU."""
    if device.type == "cuda":
        torch.empty(1, device=device)  # the context and the caching allocator, once
    return device


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)


def mallopt(settings: dict[int, int]) -> bool:
    """glibc's `mallopt(parameter, value)` for each setting, in order; True when every one took, False where the C
    library has no mallopt (macOS) or refused one."""
    try:
        call = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    call.argtypes, call.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all([call(param, value) == 1 for param, value in settings.items()])


# glibc's malloc by default serves every block over a threshold (128 KiB, rising to at most 32 MiB as blocks are
# freed) with its own mmap and hands freed memory back to the kernel, so a stage that allocates and frees
# activation-sized tensors in a loop pays a page fault for every page of every tensor, every time: evaluate-images
# on the README scene spent 9 of its 34 s in the kernel, 4.9 million faults (docs/performance.md, "The
# allocator"). Kept in the process, freed memory is reused without faults; the price is a higher peak resident
# size where a stage frees big tensors in turn (1.4-1.7x there). Addresses change, values do not (PyTorch aligns
# every CPU tensor to 64 bytes either way).
def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed memory for reuse (up to 1 GiB at the top of the heap, and blocks under
    1 GiB from the heap rather than a fresh mapping each). True when set; False where the C library is not glibc
    or the user tuned malloc through the environment (theirs wins)."""
    if any(key.startswith("MALLOC_") or key == "GLIBC_TUNABLES" for key in os.environ):
        return False
    return mallopt({M_TRIM_THRESHOLD: 1 << 30, M_MMAP_THRESHOLD: 1 << 30})


DETERMINISTIC_VALUES = {"": False, "0": False, "false": False, "no": False, "off": False,
                        "1": True, "true": True, "yes": True, "on": True}


def set_deterministic_from_env() -> bool:
    """DIFFSHADOW_DETERMINISTIC=1 (the workflow sets it from config `deterministic`): the same bytes from the same
    seed on one GPU too, at some speed cost.

    CPU runs are deterministic anyway. On CUDA this asks PyTorch for deterministic kernels (an op
    without one raises instead of varying) and cuBLAS for a fixed workspace; it must happen before the
    first CUDA call, so the CLI calls it when it resolves the device.
    """
    value = os.environ.get("DIFFSHADOW_DETERMINISTIC", "").strip().lower()
    if value not in DETERMINISTIC_VALUES:
        raise ValueError(f"DIFFSHADOW_DETERMINISTIC: expected 0 or 1 (or true/false), got {value!r}")
    if not DETERMINISTIC_VALUES[value]:
        return False
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True)
    torch.backends.cudnn.benchmark = False
    return True


def cpu_flags(path: str = "/proc/cpuinfo") -> set[str]:
    """The first CPU's feature flags as Linux lists them; empty where there is no such file (macOS) or no flags."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


# what torch.backends.cpu.get_cpu_capability() says of the scalar kernels: "DEFAULT" since torch 2.4, "NO AVX" before
SCALAR_KERNELS = ("DEFAULT", "NO AVX")


def vector_unit_warning(capability: str | None = None, flags: set[str] | None = None,
                        forced: str | None = None) -> str | None:
    """A warning when PyTorch runs its scalar CPU kernels on an x86 CPU with AVX2 and FMA, unasked (no
    ATEN_CPU_CAPABILITY): it does so silently when its CPU probe (cpuinfo) fails to start, and its scalar kernels
    round otherwise (torch.lerp and grid_sample: 1,626 of the 33³ test blob's 35,937 sweep voxels differ), so
    that job's results differ in the last bits from the same job run again on the same machine. None otherwise."""
    capability = torch.backends.cpu.get_cpu_capability() if capability is None else capability
    forced = os.environ.get("ATEN_CPU_CAPABILITY") if forced is None else forced
    if forced or capability.upper() not in SCALAR_KERNELS:
        return None
    if not {"avx2", "fma"} <= (cpu_flags() if flags is None else flags):
        return None
    return ("WARNING: PyTorch runs its scalar CPU kernels on a CPU with AVX2 (its CPU probe failed to start?): "
            "this job's results will differ in the last bits from the same job run again here")


def set_threads(n: int) -> None:
    """torch's intra-op threads and numpy's BLAS threads (0: leave both at their defaults).

    Snakemake sets `OPENBLAS_NUM_THREADS` to a rule's threads before its job starts; a command typed by hand
    gets the same BLAS threads from `--threads` here, so that it writes the workflow's bytes (how OpenBLAS
    splits a float64 SVD across threads changes its last bits; docs/performance.md, "The allocator").
    """
    if n:
        torch.set_num_threads(n)
        threadpoolctl.threadpool_limits(n, user_api="blas")  # the loaded ones: numpy's is, imported above


def _busy_seconds(cpus: set[int]) -> float | None:
    """CPU seconds spent busy so far on `cpus`, from Linux's /proc/stat (None where it cannot be read)."""
    try:
        with open("/proc/stat") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    ticks = 0
    for line in lines:
        name, _, rest = line.partition(" ")
        if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus:
            # user nice system idle iowait irq softirq steal: all but idle and iowait
            values = [int(v) for v in rest.split()[:8]]
            ticks += sum(values) - values[3] - values[4]
    return ticks / os.sysconf("SC_CLK_TCK")


class SpareThreads:
    """A job's torch threads raised from `own`, what the scheduler gave it, up to `most` while this machine's other
    cores idle, and lowered again once another process computes: for a job whose bytes do not depend on its threads
    (fit_siren: tests/test_fit.py -k one_thread_and_on_two). A scheduler can then start it on `own` threads beside
    other jobs, and it takes the cores they leave. `poll` between steps reads /proc/stat at most every `interval_s`;
    without it (not Linux) the job keeps `own`."""

    def __init__(self, own: int, most: int, interval_s: float = 1.0):
        self.own, self.most, self.interval_s = own, max(own, most), interval_s
        self.threads = own
        self.cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set(range(os.cpu_count() or 1))
        self.raised_s = 0.0  # seconds spent above `own`, for the job's log
        self._last = self._sample() if self.most > own else None

    @classmethod
    def for_run(cls, own: int, device: torch.device, most: int = 2) -> SpareThreads | None:
        """For a job on `own` threads of a workflow run whose cores (`hpc.RUN_CORES_ENV`, Snakemake's -jN) leave
        it room: up to `most` of them (two: what fit_siren's bytes were checked on, 1.46x a step at the README
        run's sizes); None on a GPU, outside a run, or with nothing to borrow."""
        from diffshadow.hpc import RUN_CORES_ENV

        cores = os.environ.get(RUN_CORES_ENV, "")
        most = min(most, int(cores)) if cores.isdigit() else 0
        return cls(own, most) if device.type == "cpu" and most > own else None

    def _sample(self) -> tuple[float, float, float] | None:
        busy = _busy_seconds(self.cpus)
        return None if busy is None else (time.monotonic(), busy, time.process_time())

    def poll(self) -> None:
        if self._last is None or time.monotonic() - self._last[0] < self.interval_s:
            return
        now = self._sample()
        if now is None:
            self._last = None
            return
        wall = now[0] - self._last[0]
        if self.threads > self.own:
            self.raised_s += wall
        # cores busy outside this process over the interval; a core is spare where it stayed (nearly) idle
        others = max(0.0, (now[1] - self._last[1]) - (now[2] - self._last[2])) / wall
        self._last = now
        self._set(min(self.most, max(self.own, int(len(self.cpus) - others + 0.25))))

    def release(self) -> None:
        """Back to `own` threads, where the job's steps end."""
        self._last = None
        self._set(self.own)

    def _set(self, threads: int) -> None:
        if threads != self.threads:
            self.threads = threads
            torch.set_num_threads(threads)


@contextlib.contextmanager
def borrowing(spare: SpareThreads | None, done: str) -> Iterator[Callable[[], None] | None]:
    """A job's steps with `spare`: yields its `poll` for them to call (None without `spare`), returns to the job's
    own threads after them, and on success prints how long it borrowed ("`done` on 1 thread(s), 2 for ...")."""
    if spare is None:
        yield None
        return
    t0 = time.perf_counter()
    try:
        yield spare.poll
    finally:
        spare.release()
    print(f"{done} on {spare.own} thread(s), {spare.most} for {spare.raised_s:.0f} s of its "
          f"{time.perf_counter() - t0:.0f} s (while the run's other cores idled)", flush=True)


def claim_gpu_lock(command: str) -> None:
    """On a node shared by several one-GPU jobs (`DIFFSHADOW_GPU_LOCK` = GPUs per node), take a free GPU."""
    gpus = os.environ.get("DIFFSHADOW_GPU_LOCK")
    if not gpus:
        return
    if not gpus.strip().isdigit() or int(gpus) < 1:
        raise ValueError(f"DIFFSHADOW_GPU_LOCK: expected the number of GPUs per node (e.g. 4), got {gpus!r}")
    from diffshadow.hpc import claim_gpu

    gpu = claim_gpu(int(gpus))
    print(f"diffshadow {command}: claimed GPU {gpu} of {gpus} (CUDA_VISIBLE_DEVICES={gpu})", flush=True)


@dataclass(frozen=True)
class Distributed:
    rank: int
    world: int
    device: torch.device


@contextlib.contextmanager
def distributed(device: torch.device, *, timeout_s: float) -> Iterator[Distributed]:
    """This process's rank, world size and device under torchrun (or rank 0 of 1 alone).

    The process group is created on entry and destroyed on exit (after a barrier on success). Under
    torchrun with more ranks than visible GPUs every rank agrees to fall back to gloo on CPU, and rank 0
    says so in one line.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if device.type == "cuda" and world > torch.cuda.device_count():
        if rank == 0:
            print(f"DDP: {world} ranks but {torch.cuda.device_count()} visible GPU(s): running gloo on CPU "
                  f"instead (launch at most that many processes to use the GPUs)", flush=True)
        device = CPU
    if device.type == "cuda":
        if world > 1 or device.index is None:  # one GPU per rank; set_device needs an index
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    if world == 1:
        yield Distributed(rank, world, device)
        return
    import torch.distributed as dist

    dist.init_process_group("nccl" if device.type == "cuda" else "gloo",
                            timeout=datetime.timedelta(seconds=timeout_s))
    ok = False
    try:
        yield Distributed(rank, world, device)
        ok = True
    finally:
        if ok:
            dist.barrier()
        dist.destroy_process_group()
