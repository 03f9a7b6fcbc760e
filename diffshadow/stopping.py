"""A long loop stopped by a signal writes its checkpoint before it ends.

A PBS job gets SIGTERM at its walltime and when it is preempted (Polaris's `preemptable` queue, this project's
default there), then SIGKILL once the scheduler's kill delay has passed; torchrun passes the SIGTERM it gets on
to its ranks; Ctrl-C sends SIGINT to the whole foreground process group, so a Snakemake run's jobs get it too.
Python's own answer ends the process at once, and the rerun resumes from the last periodic checkpoint: up to
`checkpoint_every`'s worth lost (at the paper's sizes on an A100, 50 epochs of train_diffusion, ~8 min, at each
preemption). Around a training loop, `stop_signals` turns the signal into a flag; the loop reads it at each step
boundary (an attribute, no host sync), writes its checkpoint there and raises `Stopped`, which the `diffshadow`
command reports in one line and ends with 128 + the signal's number, as the signal itself would have.

A second SIGTERM is the same request (PBS and torchrun each send one to a rank); a second Ctrl-C stops at once
(KeyboardInterrupt), for a user who will not wait for the step. A signal at the loop's last step, with no
checkpoint left to write, is sent again once the loop is done, to the handler that was there before. A signal the
process was started ignoring stays ignored, and outside the main thread (a Parsl thread worker) nothing is
installed: only the main thread may.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Stopped(BaseException):
    """A loop ended at a signal's request after writing its checkpoint. Not an `Exception`: like
    KeyboardInterrupt it passes through handlers of errors, up to the command."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum = signum


class StopRequest:
    """The signal that asked the running loop to stop (`signum`), or None."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.honoured = False

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is None:
            self.signum = signum
        elif signum == signal.SIGINT:
            raise KeyboardInterrupt

    def stopped(self, where: str, checkpoint: Path) -> Stopped:
        """The exception to raise once the checkpoint of `where` ("at step 400/2000") is written."""
        self.honoured = True
        signum = self.signum or signal.SIGTERM  # a DDP rank halting with a peer that got the signal first
        name = signal.Signals(signum).name
        return Stopped(signum, f"stopped by {name} {where}; checkpoint {checkpoint} written, and the same "
                                    f"command run again resumes from it")


@contextmanager
def stop_signals(enabled: bool = True) -> Iterator[StopRequest]:
    """A `StopRequest` that SIGTERM and SIGINT set while the block runs (where `enabled`: a loop with a checkpoint
    to write); the handlers there before are put back after it."""
    stop = StopRequest()
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {}
    for sig in SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, stop.handle)
    try:
        yield stop
    finally:
        for sig, handler in previous.items():  # None: a handler set outside Python, which cannot be put back
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        if stop.requested and not stop.honoured:  # it came at the loop's last step: answered as if never caught
            signal.raise_signal(stop.signum)
