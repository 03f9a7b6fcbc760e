"""Adam and AdamW (paper §3.4): PyTorch's own update, without PyTorch's optimizer class.

`torch.optim.Optimizer` wraps its constructor, `zero_grad`, `state_dict` and `load_state_dict` to import
`torch._dynamo` on first use (for `torch.compile`, which no training stage here uses). That import took 1.2-1.4 s
of a 7 s preoptimize job on the 2-core machine, more than importing PyTorch itself, and every job that trains paid
it: preoptimize, each fit_siren subset, train_data_inr, train_diffusion (docs/performance.md, "Where a job's time
goes"). `Adam.step` calls the functional update the class calls (`torch.optim.adam.adam`, `torch.optim.adamw.adamw`,
which import nothing), with the flags the class would pass, on state made as the class makes it: the weights are
the same bytes as with `torch.optim.Adam`/`AdamW` (tests/test_adam.py). `state_dict` has the class's layout, so a
checkpoint written by either resumes in the other.

`step_lr` is `torch.optim.lr_scheduler.StepLR`'s update (which asks for the class): the learning rate times gamma
at every `step_size`-th epoch, a tensor learning rate filled in place.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch.autograd.profiler import record_function
from torch.optim.adam import adam as _adam
from torch.optim.adamw import adamw as _adamw

BETAS = (0.9, 0.999)  # PyTorch's defaults, the paper's
EPS = 1e-8


class Adam:
    """Adam over one group of parameters. `capturable` (for a step that a CUDA graph replays: `graphs.StepGraphs`)
    keeps the learning rate in a 0-d float32 tensor on the parameters' device, which `set_lr` and `step_lr` fill in
    place; else it is a number. `decoupled` weight decay is AdamW. `fused` uses PyTorch's one-kernel update
    (`fused_supported` says where it has one)."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float, *, weight_decay: float = 0.0,
                 decoupled: bool = False, fused: bool | None = None, capturable: bool = False):
        self.params = list(params)
        if not self.params:
            raise ValueError("Adam: no parameters to optimize")
        if capturable:
            lr = torch.tensor(lr, dtype=torch.float32, device=self.params[0].device)
        self.name = "AdamW" if decoupled else "Adam"  # the profiler's scope, as PyTorch's classes name it
        self.param_groups = [{"lr": lr, "betas": BETAS, "eps": EPS, "weight_decay": weight_decay,
                              "amsgrad": False, "maximize": False, "foreach": None, "capturable": capturable,
                              "differentiable": False, "fused": fused, "decoupled_weight_decay": decoupled,
                              "params": self.params}]
        self.state: dict[torch.Tensor, dict[str, torch.Tensor]] = {}

    def _new_state(self, p: torch.Tensor) -> dict[str, torch.Tensor]:
        # as torch.optim.Adam makes it: the step count on the host unless the update runs on the device
        g = self.param_groups[0]
        dtype = torch.float64 if torch.get_default_dtype() == torch.float64 and not g["fused"] else torch.float32
        if g["capturable"] or g["fused"]:
            step = torch.zeros((), dtype=dtype, device=p.device)
        else:
            step = torch.tensor(0.0, dtype=dtype, device="cpu")
        return {"step": step, "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Drop the gradients, or (`set_to_none=False`, for a CUDA graph) zero them where they are."""
        grads = []
        for p in self.params:
            if p.grad is None:
                continue
            if set_to_none:
                p.grad = None
                continue
            if p.grad.grad_fn is not None:
                p.grad.detach_()
            else:
                p.grad.requires_grad_(False)
            grads.append(p.grad)
        if grads and self.param_groups[0]["fused"]:
            torch._foreach_zero_(grads)  # one multi-tensor op, as torch.optim zeroes a fused optimizer's
        else:
            for grad in grads:
                grad.zero_()

    def step(self) -> None:
        """One update of every parameter that has a gradient."""
        g = self.param_groups[0]
        params = [p for p in self.params if p.grad is not None]
        if not params:
            return
        for p in params:
            if p not in self.state:
                self.state[p] = self._new_state(p)
        states = [self.state[p] for p in params]
        update = _adamw if g["decoupled_weight_decay"] else _adam
        with torch.no_grad(), record_function(f"Optimizer.step#{self.name}.step"):
            update(params, [p.grad for p in params], [s["exp_avg"] for s in states],
                   [s["exp_avg_sq"] for s in states], [], [s["step"] for s in states],
                   foreach=g["foreach"], capturable=g["capturable"], differentiable=False, fused=g["fused"],
                   grad_scale=None, found_inf=None, has_complex=False, amsgrad=False, beta1=g["betas"][0],
                   beta2=g["betas"][1], lr=g["lr"], weight_decay=g["weight_decay"], eps=g["eps"], maximize=False)

    def state_dict(self) -> dict:
        """torch.optim's layout: each parameter's state by its index, the group's settings with `params` as
        indices."""
        index = {p: i for i, p in enumerate(self.params)}
        group = {k: v for k, v in self.param_groups[0].items() if k != "params"}
        return {"state": {index[p]: s for p, s in self.state.items()},
                "param_groups": [{**group, "params": list(range(len(self.params)))}]}

    def load_state_dict(self, saved: dict) -> None:
        """Resume from `state_dict()`'s (or torch.optim.Adam's, AdamW's) output: the moments onto each
        parameter's device and dtype, the step count where this optimizer keeps it, and the learning rate."""
        groups = saved.get("param_groups", [])
        if len(groups) != 1 or len(groups[0].get("params", ())) != len(self.params):
            sizes = [len(g.get("params", ())) for g in groups]
            raise ValueError(f"optimizer state: expected one group of {len(self.params)} parameters, got groups of "
                             f"{sizes}")
        g = self.param_groups[0]
        on_device = g["capturable"] or g["fused"]
        position = {i: k for k, i in enumerate(groups[0]["params"])}  # saved ids, in the group's order
        self.state = {}
        for i, s in saved["state"].items():
            p = self.params[position[i]]
            if s["exp_avg"].shape != p.shape:
                raise ValueError(f"optimizer state: parameter {i} has shape {tuple(s['exp_avg'].shape)}, expected "
                                 f"{tuple(p.shape)}")
            step = s["step"].to(dtype=torch.float32, device=p.device) if on_device else s["step"]
            self.state[p] = {"step": step,
                             "exp_avg": s["exp_avg"].to(dtype=p.dtype, device=p.device),
                             "exp_avg_sq": s["exp_avg_sq"].to(dtype=p.dtype, device=p.device)}
        set_lr(self, groups[0]["lr"])


def fused_supported(params: list[torch.Tensor]) -> bool:
    """Whether this PyTorch has the fused update for these parameters' devices (the CPU since 2.4)."""
    from torch.utils._foreach_utils import _get_fused_kernels_supported_devices

    devices = _get_fused_kernels_supported_devices()
    return all(p.device.type in devices and torch.is_floating_point(p) for p in params)


def set_lr(opt: Adam, lr: float | torch.Tensor) -> None:
    """The learning rate of the next step: a capturable optimizer's tensor filled in place (a replay reads it
    there), a plain one's number replaced."""
    for group in opt.param_groups:
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(lr)
        else:
            group["lr"] = float(lr)


def step_lr(opt: Adam, epoch: int, step_size: int, gamma: float) -> None:
    """StepLR's update after `epoch` epochs: times gamma at each multiple of `step_size`, computed as StepLR
    computes it (the current rate times gamma, in the rate's own type), so the rates are the same bits."""
    if epoch > 0 and epoch % step_size == 0:
        set_lr(opt, opt.param_groups[0]["lr"] * gamma)
