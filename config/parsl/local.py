"""Parsl on this machine (laptop, CI): one HighThroughputExecutor worker per core pair, LocalProvider."""

from parsl.config import Config
from parsl.executors import HighThroughputExecutor
from parsl.providers import LocalProvider

config = Config(
    executors=[HighThroughputExecutor(label="local", max_workers_per_node=2, cores_per_worker=1,
                                      provider=LocalProvider(init_blocks=1, max_blocks=1))],
    strategy="none",
)
