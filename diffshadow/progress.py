"""Progress of a stage's loop as one short phrase for its periodic log line: time spent and time left; and
where its loss first stopped being finite, kept on the device until the host reads anyway.

Long stages write a line every ~10% of their work (into the job's log through `tee`); the phrase says how
long the stage has run and, from the rate since it (re)started, how long it still needs, so a user reading
a log mid-run sees where a long job is. A resumed stage counts its rate from the resume, not from step 0.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch


def eta(done: int, total: int, t0: float, *, start: int = 0, now: float | None = None) -> str:
    """`'12 s, ~40 s left'` after `done` of `total` units, `start` of them done before `t0` (a resume); `now`: the
    clock's reading (default: read now)."""
    spent = (time.perf_counter() if now is None else now) - t0
    ran = done - start
    if ran <= 0 or done >= total:
        return f"{spent:.0f} s"
    return f"{spent:.0f} s, ~{spent / ran * (total - done):.0f} s left"


def resumed_at(epoch: int, total: int, within: dict | None) -> str:
    """`'epoch 3/6'`, or `'epoch 3/6, step 1 of epoch 4'` for a checkpoint written inside an epoch (`within`: its
    record of the batches done there), as a resume's log line names it."""
    inside = f", step {within['batches']} of epoch {epoch + 1}" if within else ""
    return f"epoch {epoch}/{total}{inside}"


TICK_S = 60.0  # a long piece of work's log line at most every minute


class Ticker:
    """Log lines for a piece of work that may be long (a naive frame, the data INR's lattice on a large volume), at
    most one every `every_s` seconds (default TICK_S): none for work that ends sooner, so a small scene's log stays
    short, and a large one's does not go silent for many minutes. Called with the units done of `total`, it says
    how far and how long is left; called with nothing, how long so far. It returns False, so that a frame can take
    it as its `interrupt` (asked on the host before each iteration: the frame does not depend on it)."""

    def __init__(self, what: str, total: int | None = None, *, log: Callable[[str], None] = print,
                 every_s: float | None = None, clock: Callable[[], float] = time.perf_counter):
        self.what, self.total, self.log, self.clock = what, total, log, clock
        self.every_s = TICK_S if every_s is None else every_s
        self.start = clock()
        self.next = self.start + self.every_s

    def __call__(self, done: int | None = None) -> bool:
        now = self.clock()
        if now >= self.next:
            if done is None or not self.total:
                self.log(f"{self.what}: {now - self.start:.0f} s so far")
            else:
                self.log(f"{self.what}: {done / self.total:.0%}, {eta(done, self.total, self.start, now=now)}")
            self.next = now + self.every_s
        return False


class FirstNonFinite:
    """Where a training loss (one value, or one per model) first stopped being finite, kept on the device:
    `record` every step costs no host read (on a GPU one per step keeps the host from queueing the next step
    while this one runs); `first` is read where the host reads anyway (log lines, checks, checkpoints)."""

    def __init__(self, shape: tuple[int, ...], device: torch.device | str):
        self.step = torch.full(shape, -1, dtype=torch.long, device=device)
        self.value = torch.zeros(shape, device=device)

    def record(self, loss: torch.Tensor, step: int) -> None:
        new = ~torch.isfinite(loss) & (self.step < 0)
        self.step = torch.where(new, step, self.step)
        self.value = torch.where(new, loss, self.value)

    def first(self) -> tuple[int, torch.Tensor, torch.Tensor] | None:
        """None while every loss was finite; else the earliest bad step, which entries went bad at it, and
        their values."""
        bad = self.step >= 0
        if not bool(bad.any()):
            return None
        step = int(self.step[bad].min())
        return step, self.step == step, self.value
