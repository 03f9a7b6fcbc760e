"""Parsl on Polaris: one `prod` job of 10 nodes (prod's minimum), one worker per GPU (4 per node).

Needs PBS_ACCOUNT and DIFFSHADOW_ENV (the script that activates the environment) in the environment.
"""

import os

from parsl.config import Config
from parsl.executors import HighThroughputExecutor
from parsl.launchers import MpiExecLauncher
from parsl.providers import PBSProProvider

from diffshadow.hpc import JOB_ENVIRONMENT

config = Config(
    executors=[HighThroughputExecutor(
        label="polaris",
        available_accelerators=4,  # one worker per GPU, each with its own CUDA_VISIBLE_DEVICES
        max_workers_per_node=4,
        cores_per_worker=8,
        provider=PBSProProvider(
            account=os.environ["PBS_ACCOUNT"],
            queue=os.environ.get("PBS_QUEUE", "prod"),
            select_options="ngpus=4",
            scheduler_options="#PBS -l filesystems=home:eagle\n#PBS -l place=scatter",
            worker_init=(f"source {os.environ['DIFFSHADOW_ENV']}; export TMPDIR=/tmp; "
                         "export DIFFSHADOW_DEVICE=cuda; cd $PBS_O_WORKDIR; "
                         + "; ".join(f"export {k}=${{{k}:-{v}}}" for k, v in JOB_ENVIRONMENT.items())),
            nodes_per_block=int(os.environ.get("PARSL_NODES", "10")),
            init_blocks=1, max_blocks=1,
            walltime=os.environ.get("PARSL_WALLTIME", "01:00:00"),
            launcher=MpiExecLauncher(bind_cmd="--cpu-bind", overrides="--depth=64 --ppn 1"),
        ),
    )],
    strategy="none",
    run_dir="results/parsl",  # its logs and submit scripts beside the results, not in ./runinfo in the checkout
)
