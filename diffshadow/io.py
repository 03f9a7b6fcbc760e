"""Atomic output: write to a temporary name in the same folder, then rename.

A killed job therefore never leaves a file that looks finished (DESIGN.md §3).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np


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


def write_zarr_group(path, fill) -> None:
    """Build a Zarr v3 group with `fill(root)` beside `path`, then swap it in (atomic for readers)."""
    import zarr

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        fill(zarr.open_group(str(tmp), mode="w", zarr_format=3))
        old = None
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def resume(checkpoint: str | Path | None, fingerprint: str, *, log=print, map_location="cpu",
           weights_only: bool = False, key: str = "fingerprint") -> dict | None:
    """The state saved in `checkpoint` when it was written for this `fingerprint` (same inputs and
    settings), else None; a checkpoint of other inputs is left alone and said so."""
    import torch

    if checkpoint is None or not Path(checkpoint).exists():
        return None
    state = torch.load(checkpoint, map_location=map_location, weights_only=weights_only)
    if state.get(key) == fingerprint:
        return state
    log(f"ignoring {checkpoint}: it belongs to other inputs or settings")
    return None


def finite_json(value):
    """JSON has no infinity: an exact match (PSNR +inf) is written as the string "inf"."""
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    return value
