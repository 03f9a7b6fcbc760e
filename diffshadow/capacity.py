"""Capacity that adapts to the volume: a stage with a quality target grows what it fits until the target is
reached — more steps first, then a wider SIREN — and records every size it tried, so the report can say
what the scene cost and a missed target is named, not silently delivered.

The ladder from a configured (width, steps) is (w, s), (w, 2s), (2w, 2s), (4w, 2s), … up to `max_width`.
Measured on four volumes (docs/tuning.md): a SIREN's PSNR rises 4.5–6 dB per width doubling on the
shared volumes, while doubling the steps gives 0.5–2 dB, so the ladder spends at most one step-doubling
before it widens.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Rung:
    width: int
    steps: int


def ladder(width: int, steps: int, max_width: int) -> list[Rung]:
    """The sizes to try in order: (w, s), (w, 2s), then the width doubled with 2s steps up to `max_width`."""
    if width < 1 or steps < 1:
        raise ValueError(f"ladder: width and steps must be >= 1, got width {width}, steps {steps}")
    rungs = [Rung(width, steps), Rung(width, 2 * steps)]
    w = 2 * width
    while w <= max_width:
        rungs.append(Rung(w, 2 * steps))
        w *= 2
    return rungs


@dataclass
class Choice:
    """What a stage tried and kept: each rung's PSNR and seconds, the target, whether it was reached."""

    target: float  # dB; 0: no target (the configured size only)
    # {"width", "steps", "psnr"} in the order tried; no timings (the files holding it are byte-deterministic:
    # each rung's seconds go to the log, the stage's to Snakemake's benchmark file)
    rungs: list[dict] = field(default_factory=list)

    @property
    def chosen(self) -> dict:
        return self.rungs[-1]

    @property
    def met(self) -> bool:
        return self.target <= 0 or self.chosen["psnr"] >= self.target

    def to_dict(self) -> dict:
        return {"target_psnr": self.target, "met": self.met, "width": self.chosen["width"],
                "steps": self.chosen["steps"], "psnr": self.chosen["psnr"], "rungs": self.rungs}

    def warning(self, what: str, knobs: str) -> str | None:
        """One line when the target was missed: the value, the target, what to change."""
        if self.met:
            return None
        c = self.chosen
        return (f"WARNING: {what} reached {c['psnr']:.2f} dB, below its target {self.target:g} dB, at the largest "
                f"size tried (width {c['width']}, {c['steps']} steps); raise {knobs}, or lower the target")


def climb(rungs: list[Rung], target: float, attempt: Callable[[Rung], tuple[T, float]],
          *, log: Callable[[str], None] = print, what: str = "fit") -> tuple[T, Choice]:
    """Run `attempt` on each rung until its PSNR reaches `target` (only the first rung when target <= 0);
    return the last result and the record of every rung."""
    choice = Choice(float(target))
    result = None
    for i, rung in enumerate(rungs):
        t0 = time.perf_counter()
        result, value = attempt(rung)
        value = float(value)  # NaN: not measured (no target)
        choice.rungs.append({"width": rung.width, "steps": rung.steps, "psnr": value if value == value else None})
        if value == value:
            log(f"{what}: width {rung.width}, {rung.steps} steps: {value:.2f} dB ({time.perf_counter() - t0:.0f} s)")
        if target <= 0 or value >= target:
            break
        if i + 1 < len(rungs):
            nxt = rungs[i + 1]
            log(f"{what}: {value:.2f} dB at width {rung.width}, {rung.steps} steps is below the target "
                f"{target:g} dB; trying width {nxt.width}, {nxt.steps} steps")
    return result, choice
