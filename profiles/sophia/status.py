#!/usr/bin/env python3
"""Snakemake cluster-generic status: print running | success | failed for a PBS job id (always exit 0)."""
import subprocess
import sys

from diffshadow.hpc import pbs_state

job = sys.argv[1]
try:
    out = subprocess.run(["qstat", "-fx", job], capture_output=True, text=True, timeout=60)
except (OSError, subprocess.TimeoutExpired):
    print("running")  # the server did not answer: ask again at the next check
    sys.exit(0)
print(pbs_state(out.stdout) if out.returncode == 0 else "failed")
