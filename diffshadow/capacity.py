"""Capacity that adapts to the volume: a stage with a quality target grows what it fits until the target is
reached — a wider SIREN (in stage 1 more steps first) — and records every size it tried, so the report can say
what the scene cost and a missed target is named, not silently delivered.

The ladder from a configured (width, steps) is (w, s), (w, 2s), (2w, 2s), (4w, 2s), … up to `max_width`. Stage 1
gives it the points a step too (p): its wider rungs then keep the second rung's points in all (2s x p) but take
them in larger steps, (2w, s, 2p), (4w, s/2, 4p), …: the batch in proportion to the width. Measured on stage 1
(docs/performance.md): at width 32 nucleon's new lights gain 2.8 dB from 8000 steps of 256 points over 4000 of
512 (the same points), while at width 64 tooth's lose 6 dB from 16000 steps of 256 points against 8000 of 512, and
1 dB from 4000 of 1,024: a wider SIREN needs the less noisy gradient.
Measured on four volumes (c2d5d55): a SIREN's PSNR rises 4.5–6 dB per width doubling on the
shared volumes, while doubling the steps gives 0.5–2 dB, so the ladder spends at most one step-doubling
before it widens. A width doubling that gains less than MIN_WIDTH_GAIN_DB ends the climb: the volume is then
limited by something width does not buy (tooth's data INR: 39.6 → 40.4 → 40.6 dB at widths 64, 128, 256, the
ceiling of its voxel-scale CT noise), and each doubling costs 2-4x in fitting and rendering. The climb keeps its
best size even so: tooth's data INR held at width 64 cost its images 1.2 dB against the 128 kept for 0.7 dB.
The data INR's ladder doubles only its width, (w, s), (2w, s), …: with s = 6000 that is the stepped ladder from
s/2 without its first rung, which was kept only on the scenes whose data INR met the target there, and whose
images the rung cost 0.9-1.3 dB against (w, s) (docs/performance.md, "The data INR").
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
    points: int | None = None  # a step's points, where the ladder sizes them (stage 1)

    def size(self) -> dict:
        """The rung as a Choice records it: width and steps, and points where the ladder sized them."""
        return {"width": self.width, "steps": self.steps} | ({"points": self.points} if self.points else {})

    def describe(self) -> str:
        return size_text(self.size())


def size_text(size: dict) -> str:
    """A rung as the logs and warnings name it: its width and steps, and its points where it has them."""
    return f"width {size['width']}, {steps_text(size)}"


def steps_text(size: dict) -> str:
    """A rung's steps, and their points where it has them."""
    points = size.get("points")
    return f"{size['steps']} steps" + (f" of {points} points" if points else "")


def ladder(width: int, steps: int, max_width: int, points: int | None = None, *,
           double_steps: bool = True) -> list[Rung]:
    """The sizes to try in order: (w, s), (w, 2s), then the width doubled up to `max_width`, with 2s steps — or,
    given a step's `points`, with the points doubled and the steps halved each time (2s x p points in all).
    Without `double_steps` (the data INR): (w, s), (2w, s), (4w, s), …"""
    if width < 1 or steps < 1 or (points is not None and points < 1):
        raise ValueError(f"ladder: width, steps and points must be >= 1, got width {width}, steps {steps}, "
                         f"points {points}")
    if not double_steps and points is not None:
        raise ValueError("ladder: points are sized only on a ladder that doubles its steps (stage 1)")
    wider, w = [], 2 * width  # the widths past the first, each doubled, up to max_width
    while w <= max_width:
        wider.append(w)
        w *= 2
    if not double_steps:
        return [Rung(width, steps)] + [Rung(w, steps) for w in wider]
    rungs = [Rung(width, steps, points), Rung(width, 2 * steps, points)]
    for w in wider:
        if points is None:
            rungs.append(Rung(w, 2 * steps))
        else:
            rungs.append(Rung(w, max(1, round(2 * steps * width / w)), points * w // width))
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
        return {"target_psnr": self.target, "met": self.met, **self.chosen, "rungs": self.rungs,
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
                    f"gained < {MIN_WIDTH_GAIN_DB:g} dB, so width is not what limits it (kept {size_text(c)}); lower "
                    f"the target")
        return (f"WARNING: {what} reached {c['psnr']:.2f} dB, below its target {self.target:g} dB, the best of "
                f"{len(self.rungs)} sizes tried (kept {size_text(c)}); raise {knobs}, or lower the target")


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
        choice.rungs.append(rung.size() | {"psnr": value if value == value else None})
        if value == value:
            log(f"{what}: {rung.describe()}: {value:.2f} dB ({time.perf_counter() - t0:.0f} s)")
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
            log(f"{what}: {value:.2f} dB at {rung.describe()} is below the target {target:g} dB; trying "
                f"{nxt.describe()}")
    return kept, choice
