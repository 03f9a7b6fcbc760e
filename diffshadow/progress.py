"""Progress of a stage's loop as one short phrase for its periodic log line: time spent and time left.

Long stages write a line every ~10% of their work (into the job's log through `tee`); the phrase says how
long the stage has run and, from the rate since it (re)started, how long it still needs, so a user reading
a log mid-run sees where a long job is. A resumed stage counts its rate from the resume, not from step 0.
"""

from __future__ import annotations

import time


def eta(done: int, total: int, t0: float, *, start: int = 0) -> str:
    """`'12 s, ~40 s left'` after `done` of `total` units, `start` of them done before `t0` (a resume)."""
    spent = time.perf_counter() - t0
    ran = done - start
    if ran <= 0 or done >= total:
        return f"{spent:.0f} s"
    return f"{spent:.0f} s, ~{spent / ran * (total - done):.0f} s left"
