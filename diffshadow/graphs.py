"""A training step replayed as a CUDA graph (config `diffusion.cuda_graph`, `fit.cuda_graph`,
`data_inr.cuda_graph`).

At the README's sizes every training step on a GPU is bound by its host: the geometry stage's step is ~420
kernel launches at ~40 µs each, the GPU idle most of the time (on an H200 22.7 ms a step eager, 4.0 ms replayed;
docs/performance.md). A CUDA graph records a step's kernels once and replays them
with one launch. What a replay needs from the step, and what the geometry stage's step provides:
- no host reads inside and nothing copied from the host (the schedule's and standardizer's tables are moved to the
  device once; tests/test_syncs.py counts both, the copies on the "meta" device);
- its inputs in tensors the graph owns: each call copies the batch into them, then replays;
- the optimizer's state and learning rate on the device (AdamW `capturable`, a tensor lr that `adam.step_lr` fills);
- gradients that stay where they are (zeroed in place, not dropped: `keep_grads`).
What varies per step outside the tensors (the EMA's warm-up, the epoch a non-finite loss is recorded at) stays
outside the graph, in the caller. A fit's update (`fit.SubsetFit.update`) and the data INR's
(`data_inr.DataInrFit.update`) follow the same rules: their step's points (and pool picks) are drawn on the host
first and are the graph's inputs, their Adam `capturable` with the cosine learning rate a device tensor that each
step fills (`diffshadow.adam.Adam(capturable=True)`, `set_lr`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import torch

WARMUP_CALLS = 3  # eager calls before the first capture, on a side stream (as PyTorch's CUDA graph notes ask)


class StepGraphs:
    """`step(inputs)` — a dataclass of tensors (or None) in, tensors out — as one captured CUDA graph per input
    shape (an epoch's short last batch gets its own). The first `warmup` calls run eagerly: they create the
    optimizer's state and the libraries' handles outside any capture. Outputs of a replay are the graph's own
    tensors, overwritten by the next replay."""

    def __init__(self, device: torch.device, warmup: int = WARMUP_CALLS):
        if device.type != "cuda":
            raise ValueError(f"CUDA graphs: expected a CUDA device, got {device}")
        self.device, self.warmup, self.calls = device, warmup, 0
        self.graphs: dict[tuple, tuple[torch.cuda.CUDAGraph, Any, Any]] = {}

    def __call__(self, step: Callable[[Any], Any], inputs: Any) -> Any:
        self.calls += 1
        stream = torch.cuda.current_stream(self.device)
        if self.calls <= self.warmup:
            side = torch.cuda.Stream(self.device)
            side.wait_stream(stream)
            with torch.cuda.stream(side):
                out = step(inputs)
            stream.wait_stream(side)
            return out
        key = shapes(inputs)
        if key not in self.graphs:
            static = dataclasses.replace(inputs, **{k: None if v is None else v.clone()
                                                    for k, v in tensor_fields(inputs).items()})
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                out = step(static)
            self.graphs[key] = (graph, static, out)
        graph, static, out = self.graphs[key]
        for name, value in tensor_fields(inputs).items():
            if value is not None:
                getattr(static, name).copy_(value)
        graph.replay()
        return out


def requested(setting: bool | str, key: str, device: torch.device, log: Callable[[str], None] = print, *,
              unsupported: str = "") -> StepGraphs | None:
    """A stage's graphs where its `cuda_graph` setting (`key`) asks for them ("auto" or True) and the device (and
    the stage's other settings: `unsupported` says why they cannot be captured) allows them. True where they
    cannot be says so in the log; "auto" stays silent."""
    if setting is False:
        return None
    if device.type != "cuda" or unsupported:
        if setting is True:
            why = f"CUDA graphs need a CUDA device; stepping eagerly on {device}" if device.type != "cuda" else \
                f"{unsupported}; stepping eagerly"
            log(f"{key}: {why}")
        return None
    return StepGraphs(device)


def tensor_fields(inputs: Any) -> dict[str, torch.Tensor | None]:
    """The dataclass's fields by name (each a tensor or None)."""
    return {f.name: getattr(inputs, f.name) for f in dataclasses.fields(inputs)}


def shapes(inputs: Any) -> tuple:
    """What a graph is captured for: each field's shape and dtype (None for an absent one)."""
    return tuple(None if v is None else (tuple(v.shape), v.dtype) for v in tensor_fields(inputs).values())
