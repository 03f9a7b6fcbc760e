"""Running on shared GPU nodes: a node-local GPU lock and the PBS job-state mapping.

Snakemake does not assign GPU ids inside a node (snakemake issue #281). When several single-GPU jobs share
a node (Polaris packs four `fit_siren` jobs per node), each job claims a GPU by taking an exclusive
`flock` on one file per GPU and sets `CUDA_VISIBLE_DEVICES` before CUDA starts. The lock lives as long
as the process, so a finished or killed job frees its GPU.
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

_held: list[int] = []  # open lock file descriptors, kept for the life of the process


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


def pbs_state(qstat_text: str) -> str:
    """`qstat -fx` output → Snakemake's running | success | failed."""
    fields = {}
    for line in qstat_text.splitlines():
        if " = " in line:
            key, value = line.strip().split(" = ", 1)
            fields[key.strip()] = value.strip()
    state = fields.get("job_state", "")
    if state in ("Q", "H", "W", "R", "E", "B", "T", "S", "U"):  # queued, held, waiting, running, exiting...
        return "running"
    if state in ("F", "X"):  # finished (X: a finished subjob)
        return "success" if fields.get("Exit_status") == "0" else "failed"
    return "failed"  # unknown to PBS: a job that never ran cannot have succeeded
