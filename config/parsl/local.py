"""Parsl on this machine (laptop, CI): one HighThroughputExecutor worker per core pair, LocalProvider."""

from parsl.config import Config
from parsl.executors import HighThroughputExecutor
from parsl.providers import LocalProvider

from diffshadow.hpc import JOB_ENVIRONMENT

# the job environment the workflow gives its jobs (MKL's strict mode), a user's own setting kept
_exports = "; ".join(f"export {k}=${{{k}:-{v}}}" for k, v in JOB_ENVIRONMENT.items())

config = Config(
    executors=[HighThroughputExecutor(label="local", max_workers_per_node=2, cores_per_worker=1,
                                      provider=LocalProvider(init_blocks=1, max_blocks=1, worker_init=_exports))],
    strategy="none",
    run_dir="results/parsl",  # its logs and submit scripts beside the results, not in ./runinfo in the checkout
)
