"""Atomic output: write to a temporary name in the same folder, then rename.

A killed job therefore never leaves a file that looks finished (DESIGN.md §3).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path, *, suffix: str | None = None):
    """Yield a temporary path beside `path`; on success rename it to `path`, on error remove it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or ".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_save(path: str | Path, save: Callable[[Path], None], *, suffix: str | None = None) -> None:
    """Call `save(tmp_path)` and move the result into place (for writers that insist on a suffix)."""
    with atomic_path(path, suffix=suffix) as tmp:
        save(tmp)


def atomic_torch_save(path: str | Path, obj) -> None:
    """`torch.save` atomically, through a file object: given a path, torch names the archive's folder after
    the (random) temporary name, so two identical runs wrote different bytes (stress suite)."""
    import torch

    with atomic_path(path, suffix=".pt") as tmp, open(tmp, "wb") as f:
        torch.save(obj, f)
