"""diffshadow.adam: PyTorch's Adam and AdamW update without its optimizer class, the same bytes."""

import copy
import subprocess
import sys

import pytest
import torch
from conftest import needs_cpu_fused_adamw

from diffshadow.adam import Adam, set_lr, step_lr
from diffshadow.diffusion.config import make_optimizer

SHAPES = [(5, 3), (7,), (2, 4, 3)]


def _params(seed: int = 0) -> list[torch.nn.Parameter]:
    gen = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=gen)) for s in SHAPES]


def _grads(params, step: int) -> None:
    gen = torch.Generator().manual_seed(100 + step)
    for p in params:
        p.grad = torch.randn(p.shape, generator=gen)


def _run(opt, params, steps: range, lrs=None) -> None:
    for i in steps:
        if lrs is not None:
            set_lr(opt, lrs[i])
        _grads(params, i)
        opt.step()


def _same(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_adam_takes_torchs_steps_bit_for_bit_under_a_changing_learning_rate():
    """The fits' optimizer: plain Adam, its rate set before each step (the cosine decay)."""
    lrs = [1e-3 * (0.5 + 0.5 * (i % 7) / 7) for i in range(12)]
    ours, theirs = _params(), _params()
    _run(Adam(ours, 1e-3), ours, range(12), lrs)
    _run(torch.optim.Adam(theirs, lr=1e-3), theirs, range(12), lrs)
    assert _same(ours, theirs)


@pytest.mark.parametrize("fused", [None, pytest.param(True, marks=needs_cpu_fused_adamw)])
def test_adamw_and_step_lr_take_torchs_steps_and_rates_bit_for_bit(fused):
    """The geometry stage's optimizer (AdamW with weight decay; fused where PyTorch has the kernel) and StepLR."""
    ours, theirs = _params(1), _params(1)
    opt = Adam(ours, 1e-3, weight_decay=0.01, decoupled=True, fused=fused)
    ref = torch.optim.AdamW(theirs, lr=1e-3, weight_decay=0.01, fused=fused)
    sched = torch.optim.lr_scheduler.StepLR(ref, step_size=3, gamma=0.9)
    for epoch in range(10):
        _run(opt, ours, range(epoch * 2, epoch * 2 + 2))
        _run(ref, theirs, range(epoch * 2, epoch * 2 + 2))
        step_lr(opt, epoch + 1, 3, 0.9)
        sched.step()
        assert opt.param_groups[0]["lr"] == ref.param_groups[0]["lr"]  # the same float, not merely close
    assert opt.param_groups[0]["lr"] == 1e-3 * 0.9 * 0.9 * 0.9 != 1e-3 * 0.9 ** 3  # the chain, as StepLR's
    assert _same(ours, theirs)


@needs_cpu_fused_adamw
def test_a_capturable_optimizer_keeps_its_rate_in_one_tensor_that_step_lr_lowers_in_place():
    """What a replayed CUDA graph relies on (`diffusion.cuda_graph`): the rate is one tensor on the parameters'
    device, lowered in place (a graph captured before reads the new value), the steps are torch's capturable
    AdamW's, and a checkpoint brings back the rate into that same tensor."""
    ours, theirs = _params(2), _params(2)
    opt = make_optimizer(ours, 1e-3, 0.0, capturable=True)
    ref = torch.optim.AdamW(theirs, lr=torch.tensor(1e-3), weight_decay=0.0, fused=True, capturable=True)
    sched = torch.optim.lr_scheduler.StepLR(ref, step_size=1, gamma=0.5)
    lr = opt.param_groups[0]["lr"]
    assert isinstance(lr, torch.Tensor) and lr.device == ours[0].device
    for i in range(3):
        _run(opt, ours, range(i, i + 1))
        _run(ref, theirs, range(i, i + 1))
        step_lr(opt, i + 1, 1, 0.5)
        sched.step()
    assert opt.param_groups[0]["lr"] is lr and float(lr) == float(ref.param_groups[0]["lr"])
    assert float(lr) == pytest.approx(1e-3 / 8)
    assert _same(ours, theirs)
    again = make_optimizer(_params(), 1e-3, 0.0, capturable=True)
    kept = again.param_groups[0]["lr"]
    again.load_state_dict(opt.state_dict())
    assert again.param_groups[0]["lr"] is kept and float(kept) == float(lr)
    assert again.state_dict()["state"][0]["step"].dtype == torch.float32


@pytest.mark.parametrize("decoupled", [False, True])
def test_a_checkpoint_of_either_resumes_in_the_other_to_the_same_bytes(decoupled):
    """Checkpoints written before diffshadow had its own optimizer resume in it, and its state_dict has torch's
    layout: half the steps in one, the rest in the other, equal to all of them in torch's."""
    make = (lambda ps: torch.optim.AdamW(ps, lr=1e-3, weight_decay=0.01)) if decoupled else \
        (lambda ps: torch.optim.Adam(ps, lr=1e-3))
    mine = (lambda ps: Adam(ps, 1e-3, weight_decay=0.01, decoupled=True)) if decoupled else \
        (lambda ps: Adam(ps, 1e-3))
    whole = _params()
    _run(make(whole), whole, range(8))
    first, second = _params(), _params()
    a = make(first)
    _run(a, first, range(4))
    resumed = mine(second)
    with torch.no_grad():
        for p, q in zip(second, first, strict=True):
            p.copy_(q)
    resumed.load_state_dict(copy.deepcopy(a.state_dict()))  # as a checkpoint file holds it
    _run(resumed, second, range(4, 8))
    assert _same(second, whole)
    back = _params()
    with torch.no_grad():
        for p, q in zip(back, second, strict=True):
            p.copy_(q)
    again = make(back)
    again.load_state_dict(copy.deepcopy(resumed.state_dict()))
    _run(again, back, range(8, 10))
    _run(resumed, second, range(8, 10))
    assert _same(back, second)


def test_zeroing_in_place_keeps_each_gradient_tensor_and_dropping_drops_it():
    params = _params()
    opt = Adam(params, 1e-3)
    _grads(params, 0)
    grads = [p.grad for p in params]
    opt.zero_grad(set_to_none=False)  # a CUDA graph's kernels write to fixed addresses
    assert all(p.grad is g and not g.any() for p, g in zip(params, grads, strict=True))
    opt.zero_grad()
    assert all(p.grad is None for p in params)
    opt.step()  # nothing to update: no state made
    assert opt.state_dict()["state"] == {}


def test_a_mismatched_checkpoint_is_one_clear_error():
    opt = Adam(_params(), 1e-3)
    other = _params()[:2]
    saved = Adam(other, 1e-3)
    _run(saved, other, range(1))
    with pytest.raises(ValueError, match=r"expected one group of 3 parameters, got groups of \[2\]"):
        opt.load_state_dict(saved.state_dict())
    wrong = [torch.nn.Parameter(torch.zeros(4)) for _ in SHAPES]
    saved = Adam(wrong, 1e-3)
    _run(saved, wrong, range(1))
    with pytest.raises(ValueError, match=r"parameter 0 has shape \(4,\), expected \(5, 3\)"):
        opt.load_state_dict(saved.state_dict())
    with pytest.raises(ValueError, match="no parameters"):
        Adam([], 1e-3)


def test_training_with_it_never_imports_torch_dynamo():
    """The point of the module: torch.optim's class imports torch._dynamo on first use (1.2-1.4 s of a job);
    this optimizer's whole life, and a stage's training loop, import nothing of it."""
    code = """
import sys, torch
from diffshadow.adam import Adam, step_lr
from diffshadow.diffusion.config import make_optimizer
p = torch.nn.Parameter(torch.ones(3))
for opt in (Adam([p], 1e-3), make_optimizer([p], 1e-3, 0.01)):
    p.grad = torch.ones(3)
    opt.step(); step_lr(opt, 30, 30, 0.9); opt.zero_grad(set_to_none=False); opt.load_state_dict(opt.state_dict())
torch.nn.utils.clip_grad_norm_([p], 1.0)
print("torch._dynamo" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
