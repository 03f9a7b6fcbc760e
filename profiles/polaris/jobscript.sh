#!/bin/bash
# diffshadow job on a PBS compute node (Polaris/Sophia). Snakemake fills in the job below.
# properties = {properties}
set -e
cd "${{PBS_O_WORKDIR:-.}}"
# qsub does not carry the login environment over: set it up here. DIFFSHADOW_ENV names a script that
# activates the environment holding diffshadow (e.g. /eagle/<project>/venvs/diffshadow/bin/activate);
# without it, the ALCF conda module is loaded.
if [ -n "${{DIFFSHADOW_ENV:-}}" ]; then
    source "$DIFFSHADOW_ENV"
elif [ -d /soft/modulefiles ]; then
    module use /soft/modulefiles && module load conda && conda activate
fi
export TMPDIR="${{TMPDIR:-/tmp}}"
export DIFFSHADOW_DEVICE="${{DIFFSHADOW_DEVICE:-cuda}}"
export DIFFSHADOW_GPU_LOCK="${{DIFFSHADOW_GPU_LOCK:-4}}"  # GPUs per node, for jobs packed on one node
{exec_job}
