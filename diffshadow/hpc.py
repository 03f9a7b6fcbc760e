"""Running on HPC systems: the environment every job runs in, a node-local GPU lock, the DDP launcher, the PBS
job state for Snakemake, the profiles' install, the name of the device a figure was measured on, the host's free
memory before a large allocation. Nothing here imports PyTorch on import (the launcher and `device_name` import
it when called): the Snakefile imports this module in Snakemake's process and, on PBS, once more in every job's.

Snakemake does not assign GPU ids inside a node (snakemake issue #281). When several single-GPU jobs share
a node (Polaris packs four `fit_siren` jobs per node), each job claims a GPU by taking an exclusive
`flock` on one file per GPU and sets `CUDA_VISIBLE_DEVICES` before CUDA starts. The lock lives as long
as the process, so a finished or killed job frees its GPU.
"""

from __future__ import annotations

import fcntl
import filecmp
import json
import os
import platform
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import yaml

if TYPE_CHECKING:
    import torch

_held: list[int] = []  # open lock file descriptors, kept for the life of the process


# what a GPU build of PyTorch needs to see a GPU: NVIDIA's driver, AMD's (ROCm), WSL's GPU bridge
GPU_DRIVER_FILES = ("/proc/driver/nvidia", "/dev/kfd", "/dev/dxg")


# The environment every job runs in, set by the workflow (workflow/rules/common.smk) and the Parsl configs, not
# by the library. MKL (PyTorch's CPU BLAS on x86) splits a long matrix product's inner sum across threads, so by
# default its last bits depend on the thread count: sample-shadows rerun with other threads wrote other bytes.
# Strict conditional numerical reproducibility fixes the split and keeps the fastest code path (docs/numerics.md);
# MKL reads it at its first call. A user's own MKL_CBWR wins.
JOB_ENVIRONMENT = {"MKL_CBWR": "AUTO,STRICT"}
# the cores of the workflow's run (Snakemake's -jN), in its jobs' environment: what a job may borrow while they idle
# (runtime.SpareThreads), where the scheduler counted it at fewer
RUN_CORES_ENV = "DIFFSHADOW_RUN_CORES"

# How every rule's command ends: its output to the terminal and to the rule's log. `tee` ignores SIGINT and SIGTERM,
# which Ctrl-C and PBS (a walltime, a preemption) send to every process of a job, so that the job's last line, where
# it says it stopped and which checkpoint it wrote (diffshadow.stopping), still reaches the log; tee ends when the job
# closes the pipe, however the job ends. (The rules' text is Snakemake's `code` rerun trigger: changing this reruns
# every finished job.)
JOB_LOG = " 2>&1 | (trap '' INT TERM; exec tee {log})"


def kernel_cache_environment(root: str | os.PathLike) -> dict[str, str]:
    """Where a run's jobs keep compiled kernels, so that no job recompiles what an earlier one compiled: Triton's
    cache (the fused renderer kernels) under `root` (the workflow passes `results/.kernel-cache`, an absolute path on
    the file system every node of a PBS run shares). A user's own TRITON_CACHE_DIR wins."""
    return {"TRITON_CACHE_DIR": os.path.join(os.path.abspath(root), "triton")}


def device_setting(flag: str | None = None, config: str | None = None) -> tuple[str, str]:
    """A stage's device setting, unresolved, and where it came from: flag → DIFFSHADOW_DEVICE → config → auto."""
    if flag:
        return flag, "--device"
    if os.environ.get("DIFFSHADOW_DEVICE"):
        return os.environ["DIFFSHADOW_DEVICE"], "DIFFSHADOW_DEVICE"
    return config or "auto", "device"


def gpu_possible(flag: str | None = None, config: str | None = None) -> bool:
    """Whether the device setting can resolve to a GPU here, answered without PyTorch: not for cpu, nor for auto on
    a machine without a GPU driver."""
    spec, _ = device_setting(flag, config)
    if spec == "cpu":
        return False
    return spec != "auto" or any(os.path.exists(f) for f in GPU_DRIVER_FILES)


# where NVIDIA's driver lists the GPUs this machine (or container) has: one folder each in NVIDIA_GPUS, one device
# node each (nvidia0, nvidia1, ...) in DEVICE_NODES
NVIDIA_GPUS = "/proc/driver/nvidia/gpus"
DEVICE_NODES = "/dev"
ROCM_DRIVER = "/dev/kfd"


def torch_has_cuda() -> bool:
    """Whether the installed PyTorch is a CUDA build (its CUDA library is there), answered without importing it."""
    import importlib.util

    spec = importlib.util.find_spec("torch")
    return bool(spec and spec.submodule_search_locations and
                any((Path(d) / "lib" / "libtorch_cuda.so").exists() for d in spec.submodule_search_locations))


def visible_nvidia_gpus() -> int | None:
    """How many NVIDIA GPUs PyTorch would count here (`torch.cuda.device_count()`), answered without importing it:
    the driver's GPUs (its folders and device nodes, the fewer: a container may see only some nodes), through
    CUDA_VISIBLE_DEVICES as CUDA reads a list of indices (up to the first one out of range). None where only
    PyTorch can tell: a CPU build of PyTorch, no NVIDIA driver, an AMD one beside it, GPUs named by UUID or MIG
    instance, an index given twice. A count too high (a GPU CUDA cannot start) is caught by the ranks:
    `runtime.distributed` runs them on the CPU, saying so."""
    if not torch_has_cuda() or not os.path.isdir(NVIDIA_GPUS) or os.path.exists(ROCM_DRIVER):
        return None
    nodes = sum(1 for name in os.listdir(DEVICE_NODES) if name.startswith("nvidia") and name[6:].isdigit())
    n = min(len(os.listdir(NVIDIA_GPUS)), nodes)
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is None:
        return n
    ids = [v.strip() for v in visible.split(",")] if visible.strip() else []
    if not all(v.lstrip("-").isdigit() for v in ids) or len(set(ids)) != len(ids):
        return None
    count = 0
    for v in ids:
        if not 0 <= int(v) < n:
            break
        count += 1
    return count


def ddp_processes(requested: int, gpus: int | None) -> tuple[int, str]:
    """How many DDP processes to launch for `requested`, given the GPUs visible (None: the device is the CPU), and a
    one-line reason: on CUDA one process per visible GPU at most (NCCL cannot put two ranks on one GPU); on CPU as
    asked."""
    if requested < 1:  # the schema holds the workflow's value; this is the command's own
        raise ValueError(f"--nproc (finetune.nproc): expected at least 1 process, got {requested}")
    if gpus is None:
        return requested, f"{requested} CPU process(es) (gloo)"
    if requested > gpus:
        return gpus, f"finetune.nproc is {requested} but {gpus} GPU(s) are visible: running {gpus} process(es)"
    return requested, f"{requested} process(es), one GPU each (NCCL)"


def run_gpus(config: str | None = None) -> int | None:
    """How many NVIDIA GPUs the run's device setting (`config`, under DIFFSHADOW_DEVICE) reaches on this machine,
    answered without PyTorch: None where it is the CPU, a GPU not visible here, or only PyTorch could tell
    (`visible_nvidia_gpus`)."""
    spec, _ = device_setting(None, config)
    if spec not in ("auto", "cuda") and not spec.startswith("cuda:"):
        return None
    gpus = visible_nvidia_gpus()  # None without NVIDIA's driver
    if not gpus or spec in ("auto", "cuda"):
        return gpus or None
    index = spec.split(":", 1)[1]
    return 1 if index.isdigit() and int(index) < gpus else None


def job_threads(threads: int, gpus: int | None, *, processes: bool = False) -> int:
    """The CPU threads a job whose work runs on the run's device asks the scheduler for, given `run_gpus`: on a GPU
    one (the GPU computes; a second thread would only keep the job beside it waiting: on the H200 the geometry
    stage, asking two, waited 17 s for the data INR's fit), or with `processes` (finetune_render's DDP ranks, one
    thread each) one per GPU it can use; elsewhere `threads`."""
    if not gpus:
        return threads
    return min(threads, gpus) if processes else 1


def launch_ranks(argv: list[str]) -> int:
    """torchrun with its own arguments `argv`; its exit status. Where ranks fail, one line says which and how
    (`ranks_failed`), and where the launcher is signalled, one line says so, in place of torchrun's traceback from
    inside its launcher (~40 lines that ended every failed fine-tuning log, below the ranks' own one-line
    errors). The ranks are launched as torchrun launches them: the environment is torchrun's to set (under
    Snakemake a rule's job already has OMP_NUM_THREADS, its threads, so torchrun leaves it)."""
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import determine_local_world_size, parse_args, run

    args = parse_args(argv)
    try:  # torchrun's own check of its argument, before the launch, named as ours
        determine_local_world_size(args.nproc_per_node)
    except ValueError as e:
        raise ValueError(f"--nproc_per_node: {e}") from None
    try:
        run(args)
    except ChildFailedError as e:
        line, code = ranks_failed({rank: failure.exitcode for rank, failure in e.failures.items()})
        print(f"diffshadow torchrun: {line}", file=sys.stderr, flush=True)
        return code
    except SignalException as e:  # the launcher itself was signalled (a scheduler's walltime): it stops the ranks
        name = signal.Signals(e.sigval).name
        print(f"diffshadow torchrun: ended by {name}, and its ranks with it", file=sys.stderr, flush=True)
        return 128 + int(e.sigval)
    return 0


def ranks_failed(exit_codes: dict[int, int]) -> tuple[str, int]:
    """One line on a DDP job's failed ranks (rank: exit code, negative for a signal, as torchrun reports them) and
    the job's exit status. torchrun counts the ranks it stopped itself (SIGTERM) among the failures and dates each
    failure to the second, so its "first observed failure" could name a rank it stopped: the causes are the
    others, a rank ended by a signal before one that exited with an error (a rank that loses its peer exits
    with 1, a consequence); the status is the first cause's (128 + the signal's number, as a shell says it)."""
    stopped = {r for r, c in exit_codes.items() if c == -signal.SIGTERM}
    causes = sorted(set(exit_codes) - stopped or stopped, key=lambda r: (exit_codes[r] >= 0, r))

    def how(code: int) -> str:
        if code >= 0:
            return f"exited with code {code}"
        try:
            return f"was ended by {signal.Signals(-code).name}"
        except ValueError:
            return f"was ended by signal {-code}"

    line = "; ".join(f"rank {r} {how(exit_codes[r])}" for r in causes)
    if rest := sorted(set(exit_codes) - set(causes)):
        line += f"; torchrun then stopped rank(s) {', '.join(map(str, rest))}"
    first = exit_codes[causes[0]]
    status = 128 - first if first < 0 else first or 1
    return line + "; each rank's own error, where it printed one, is above", status


def claim_gpu(n_gpus: int, *, lock_dir: str | Path | None = None, wait_s: float = 3600.0,
              poll_s: float = 0.5) -> int:
    """Take the first free of `n_gpus` GPUs on this node; set CUDA_VISIBLE_DEVICES to it; return its id."""
    if n_gpus < 1:
        raise ValueError(f"DIFFSHADOW_GPU_LOCK: expected the number of GPUs on the node (>= 1), got {n_gpus}")
    lock_dir = Path(lock_dir or os.environ.get("DIFFSHADOW_LOCK_DIR") or os.environ.get("TMPDIR") or "/tmp")
    lock_dir.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + wait_s
    while True:
        for gpu in range(n_gpus):
            fd = os.open(lock_dir / f"diffshadow-gpu-{gpu}.lock", os.O_CREAT | os.O_RDWR, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                continue
            _held.append(fd)
            os.environ["CUDA_VISIBLE_DEVICES"] = str(gpu)
            return gpu
        if time.monotonic() > deadline:
            raise TimeoutError(f"no free GPU among {n_gpus} in {lock_dir} after {wait_s:.0f} s")
        time.sleep(poll_s)


QSTAT_UNKNOWN_JOB = 153  # PBSE_UNKJOBID (15001) as an exit status


def pbs_state(job: dict) -> str:
    """One job of `qstat -fx -F json` → Snakemake's running | success | failed."""
    state = job.get("job_state", "")
    if state in ("Q", "H", "W", "R", "E", "B", "T", "S", "U"):  # queued, held, waiting, running, exiting...
        return "running"
    if state in ("F", "X"):  # finished (X: a finished subjob)
        return "success" if str(job.get("Exit_status")) == "0" else "failed"
    return "failed"  # unknown to PBS: a job that never ran cannot have succeeded


def config_home() -> Path:
    return Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")


def _same_profile(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    if not (a.is_dir() and b.is_dir()):
        return False
    cmp = filecmp.dircmp(a, b)
    return not (cmp.left_only or cmp.right_only or cmp.diff_files or cmp.funny_files)


def is_workflow_profile(profile: Path) -> bool:
    """A profile that only sets per-rule resources (profiles/paper): given by path to `--workflow-profile`, laid
    over a named one, so it is not installed by name."""
    cfg = profile / "config.yaml"
    keys = set(yaml.safe_load(cfg.read_text()) or {}) if cfg.is_file() else set()
    return bool(keys) and keys <= {"set-resources", "set-threads"}


def install_profiles(source: Path, target_root: Path, *, force: bool = False) -> list[Path]:
    """Link each profile folder of `source` into `target_root` (Snakemake's search path), workflow profiles
    (`is_workflow_profile`) aside.

    An existing profile of the same name is left alone when it is this one (or identical), replaced when it is
    a link to a folder that is gone (a deleted clone: nothing to lose), and refused otherwise, unless `force`.
    """
    if not source.is_dir():
        raise SystemExit(f"install-profiles: no profiles folder at {source} (run from the repository root "
                         f"or pass --source)")
    target_root.mkdir(parents=True, exist_ok=True)
    installed = []
    for profile in sorted(p for p in source.iterdir() if p.is_dir() and not is_workflow_profile(p)):
        target = target_root / profile.name
        if target.is_symlink() and not target.exists():
            target.unlink()
        if target.exists() or target.is_symlink():
            if _same_profile(profile, target):
                installed.append(target)
                continue
            if not force:
                raise SystemExit(f"install-profiles: {target} exists and differs from {profile}; "
                                 f"remove it or pass --force")
            if target.is_symlink() or target.is_file():
                target.unlink()
            else:
                raise SystemExit(f"install-profiles: {target} is a real folder; remove it by hand")
        target.symlink_to(profile.resolve(), target_is_directory=True)
        installed.append(target)
    return installed


def pbs_status(job: str, *, tries: int = 3, wait_s: float = 2.0) -> str:
    """Snakemake's cluster-generic status of a PBS job: running | success | failed.

    Only PBS saying it does not know the job means failed. Any other qstat failure (server busy or
    restarting, a timeout) is retried, then answered "running" so that Snakemake asks again at its next
    check: a transient error must not fail a job that is still running.
    """
    why = ""
    for attempt in range(tries):
        if attempt:
            time.sleep(wait_s * attempt)
        try:
            out = subprocess.run(["qstat", "-fx", "-F", "json", job], capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired) as e:
            why = str(e)
            continue
        if out.returncode == 0:
            try:
                jobs = json.loads(out.stdout).get("Jobs", {})
            except json.JSONDecodeError:
                why = f"unreadable qstat output {out.stdout[:80]!r}"
                continue
            return pbs_state(next(iter(jobs.values()), {}))
        if out.returncode == QSTAT_UNKNOWN_JOB or "Unknown Job Id" in out.stderr:
            return "failed"
        why = f"qstat exit {out.returncode}: {out.stderr.strip()[:200]}"
    print(f"pbs-status {job}: {why}; reported as running, asked again at the next check", file=sys.stderr)
    return "running"


def device_name(device: torch.device | str) -> str:
    """What a figure was measured on, for the outputs that record it: the GPU's name, or the CPU's type."""
    import torch

    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"cpu ({platform.processor() or platform.machine()})"


def free_host_bytes(meminfo: str | Path = "/proc/meminfo", cgroups: str | Path = "/proc/self/cgroup",
                    cgroup_root: str | Path = "/sys/fs/cgroup") -> int | None:
    """The memory this process can still take without swapping: Linux's MemAvailable, or less where a memory cgroup
    (a PBS job's, a container's) is limited to less (`cgroup_room`); None where neither is known."""
    free = None
    try:
        with open(meminfo) as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    free = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    room = cgroup_room(cgroups, cgroup_root)
    return room if free is None else free if room is None else min(free, room)


UNLIMITED = 1 << 60  # a cgroup limit at or above this is none (v1 writes 2^63 rounded down to a page)


def cgroup_room(cgroups: str | Path = "/proc/self/cgroup", root: str | Path = "/sys/fs/cgroup") -> int | None:
    """The least room left under the memory limits of this process's cgroup and its ancestors (v2: memory.max; v1:
    memory.limit_in_bytes), each its limit less its usage but for inactive file pages, which the kernel reclaims
    before it kills (container runtimes' "working set"); None where no limit is set or none can be read. A cgroup
    namespace shows the process's own cgroup as "/", so the mount's top holds its files."""
    try:
        lines = Path(cgroups).read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        hierarchy, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if hierarchy == "0" and controllers == "":
            base, files = Path(root), ("memory.max", "memory.current", "inactive_file")
        elif "memory" in controllers.split(","):
            base, files = Path(root) / "memory", ("memory.limit_in_bytes", "memory.usage_in_bytes",
                                                  "total_inactive_file")
        else:
            continue
        parts = [p for p in path.split("/") if p]
        for depth in range(len(parts), -1, -1):  # the cgroup, then each ancestor up to the mount's top
            room = _cgroup_level_room(base.joinpath(*parts[:depth]), *files)
            if room is not None:
                rooms.append(room)
    return min(rooms) if rooms else None


def _cgroup_level_room(level: Path, limit_file: str, usage_file: str, inactive_key: str) -> int | None:
    try:
        text = (level / limit_file).read_text().strip()
        if text == "max" or int(text) >= UNLIMITED:
            return None
        usage = int((level / usage_file).read_text())
    except (OSError, ValueError):
        return None
    inactive = 0
    try:
        for line in (level / "memory.stat").read_text().splitlines():
            key, _, value = line.partition(" ")
            if key == inactive_key:
                inactive = int(value)
    except (OSError, ValueError):
        pass
    return max(0, int(text) - max(0, usage - inactive))


CHECKED_FROM_BYTES = 1 << 26  # smaller allocations are not checked (the viewer sweeps small grids often)


def check_host_room(need: int, what: str) -> None:
    """MemoryError (one line: `what`, the bytes it needs, the bytes free) before an allocation of at least `need`
    bytes on the host that cannot fit: Linux's out-of-memory killer ends a process without a word (exit 137 and
    an empty log), so the CLI could not say which setting to lower. Where the free memory is unknown, or `need` is
    under CHECKED_FROM_BYTES: nothing."""
    if need < CHECKED_FROM_BYTES:
        return
    free = free_host_bytes()
    if free is not None and need > free:
        raise MemoryError(f"{what} needs at least {need / 2**30:.1f} GiB, and {free / 2**30:.1f} GiB are free on "
                          f"this host")


# how Snakemake's log says a job's command was killed by SIGKILL: its shell's status (137), or the shell's own death
_KILLED = re.compile(r"died with <Signals\.SIGKILL: 9>|returned non-zero exit status 137\b")
_FAILED_RULE = re.compile(r"^Error in rule (\w+):")
_JOB_LOG_LINE = re.compile(r"^\s+log: (\S+)")


def killed_lines(snakemake_log: str) -> list[str]:
    """A line for each job that a run's Snakemake log says was killed by SIGKILL (exit 137): nothing in the job's
    own log says so, and on a workstation it is most often Linux's out-of-memory killer, which ends a process
    without a word. The line names the job's log, where to confirm it, the config keys that size the job's memory
    (`config.MEMORY_KEYS`) and whether a rerun resumes (`config.RESUMABLE`) or starts the job again. Snakemake's
    `onerror` prints them (the Snakefile)."""
    from diffshadow.config import RESUMABLE, memory_keys

    jobs: list[list] = []  # [rule, its log or None] of each killed job, in the order Snakemake reported them
    killed, block = False, None
    for line in snakemake_log.splitlines():
        if _KILLED.search(line):
            killed = True
        elif (found := _FAILED_RULE.match(line)) and killed:
            block, killed = [found.group(1), None], False
            jobs.append(block)
        elif block is not None and (found := _JOB_LOG_LINE.match(line)):
            block[1], block = found.group(1), None
        elif line and not line[0].isspace():
            block = None  # the rule's block ended without a log line
    lines = []
    for rule, log in jobs:
        command = rule.replace("_", "-")
        rerun = ("A rerun resumes from its last checkpoint" if command in RESUMABLE else
                 "A rerun starts it again (it keeps no checkpoint)")
        lines.append(f"{rule} was killed by SIGKILL (exit 137; its log{f', {log},' if log else ''} ends without a "
                     f"word): most often by the out-of-memory killer (`journalctl -k | grep -i oom` or `dmesg` names "
                     f"it), and then lower {memory_keys(command)}, or run it where there is more memory; else by a "
                     f"scheduler. {rerun}")
    return lines
