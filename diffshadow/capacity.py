"""Capacity that adapts to the volume: a stage with a quality target grows what it fits until the target is
reached — more steps first, then a wider SIREN — and records every size it tried, so the report can say
what the scene cost and a missed target is named, not silently delivered.

The ladder from a configured (width, steps) is (w, s), (w, 2s), (2w, 2s), (4w, 2s), … up to `max_width`.
Measured on four volumes (c2d5d55): a SIREN's PSNR rises 4.5–6 dB per width doubling on the
shared volumes, while doubling the steps gives 0.5–2 dB, so the ladder spends at most one step-doubling
before it widens. A width doubling that gains less than MIN_WIDTH_GAIN_DB ends the climb: the volume is then
limited by something width does not buy (tooth's data INR: 39.6 → 40.4 → 40.6 dB at widths 64, 128, 256, the
ceiling of its voxel-scale CT noise), and each doubling costs 2-4x in fitting and rendering.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

T = TypeVar("T")

MIN_WIDTH_GAIN_DB = 1.0


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
    kept: int = -1  # index into rungs of the result kept: the first to meet the target, else the best
    plateau: bool = False  # the climb stopped because widening gained < MIN_WIDTH_GAIN_DB

    @property
    def chosen(self) -> dict:
        return self.rungs[self.kept]

    @property
    def met(self) -> bool:
        return self.target <= 0 or self.chosen["psnr"] >= self.target

    def to_dict(self) -> dict:
        return {"target_psnr": self.target, "met": self.met, "width": self.chosen["width"],
                "steps": self.chosen["steps"], "psnr": self.chosen["psnr"], "rungs": self.rungs,
                "kept": self.kept % len(self.rungs), "plateau": self.plateau}

    @classmethod
    def from_dict(cls, d: dict) -> Choice:
        return cls(float(d["target_psnr"]), list(d["rungs"]), int(d.get("kept", -1)), bool(d.get("plateau", False)))

    def warning(self, what: str, knobs: str) -> str | None:
        """One line when the target was missed: the value, the target, what to change."""
        if self.met:
            return None
        c = self.chosen
        if self.plateau:
            return (f"WARNING: {what} reached {c['psnr']:.2f} dB, below its target {self.target:g} dB; widening "
                    f"gained < {MIN_WIDTH_GAIN_DB:g} dB, so width is not what limits it (kept width {c['width']}, "
                    f"{c['steps']} steps); lower the target")
        return (f"WARNING: {what} reached {c['psnr']:.2f} dB, below its target {self.target:g} dB, the best of "
                f"{len(self.rungs)} sizes tried (kept width {c['width']}, {c['steps']} steps); raise {knobs}, or lower "
                f"the target")


def climb(rungs: list[Rung], target: float, attempt: Callable[[Rung], tuple[T, float]],
          *, log: Callable[[str], None] = print, what: str = "fit") -> tuple[T, Choice]:
    """Run `attempt` on each rung until its PSNR reaches `target` (only the first rung when target <= 0) or a
    wider rung gains less than MIN_WIDTH_GAIN_DB over the best before it; return the result of the rung that
    reached the target — else of the best one (a larger size can do worse: a wider SIREN that diverged must
    not replace a narrower one that did not) — and the record of every rung."""
    choice = Choice(float(target))
    kept, best = None, float("-inf")
    for i, rung in enumerate(rungs):
        t0 = time.perf_counter()
        result, value = attempt(rung)
        value = float(value)  # NaN: not measured (no target)
        choice.rungs.append({"width": rung.width, "steps": rung.steps, "psnr": value if value == value else None})
        if value == value:
            log(f"{what}: width {rung.width}, {rung.steps} steps: {value:.2f} dB ({time.perf_counter() - t0:.0f} s)")
        gain = value - best
        if kept is None or value > best:  # a rung that meets the target is always the best so far
            kept, best, choice.kept = result, value, i
        if target <= 0 or value >= target:
            break
        if i > 0 and rung.width > rungs[i - 1].width and gain < MIN_WIDTH_GAIN_DB:
            log(f"{what}: widening to {rung.width} gained {gain:+.2f} dB (< {MIN_WIDTH_GAIN_DB:g} dB); not widening "
                f"further")
            choice.plateau = True
            break
        if i + 1 < len(rungs):
            nxt = rungs[i + 1]
            log(f"{what}: {value:.2f} dB at width {rung.width}, {rung.steps} steps is below the target "
                f"{target:g} dB; trying width {nxt.width}, {nxt.steps} steps")
    return kept, choice
