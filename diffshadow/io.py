"""Safe output and input: write to a temporary name in the same folder, flush it to disk, give it the mode the
user's umask gives any new file, then rename; Zarr stores carry a checksum of every array, verified on reading.

A killed job or a crashed node therefore never leaves a file that looks finished (docs/design.md §1), group members
of a shared project folder can read what the umask lets them, and a damaged store is named, never read as
zeros. A temporary is named after its output, its process and its host (`.weights.zarr.partial.<pid>.<host>.<random>`),
so that the next write of that output can tell one whose writer was killed (SIGKILL at a PBS walltime, the OOM
killer, a lost node) and remove it, instead of leaving a hidden copy per kill.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import re
import shutil
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.phases import phase, timed

if TYPE_CHECKING:
    import torch
    import zarr


def umask() -> int:
    """The process's umask, read without changing it (Linux reports it in /proc; elsewhere a brief set and reset)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as e:
        # Some network and shared-folder file systems (SMB, VirtualBox's, some FUSE mounts) refuse to flush a
        # folder with EINVAL. The files in it are flushed, and the rename is still atomic; only a crash right
        # after could lose the rename, which leaves the output missing, as if the job had not run. Any other
        # error is a real one.
        if e.errno != errno.EINVAL or not os.path.isdir(path):
            raise
    finally:
        os.close(fd)


def _finish(tmp: Path, *, directory: bool = False) -> None:
    """Flush `tmp` (every file under it, for a folder) and give it the mode a new file or folder gets under the
    umask: `mkstemp` and `mkdtemp` create theirs private (0600, 0700) and a rename keeps the mode."""
    mask = umask()
    if directory:
        for root, dirs, files in os.walk(tmp):
            for d in dirs:
                os.chmod(Path(root) / d, 0o777 & ~mask)
            for f in files:
                _fsync(Path(root) / f)
            _fsync(Path(root))
        os.chmod(tmp, 0o777 & ~mask)
    else:
        _fsync(tmp)
        os.chmod(tmp, 0o666 & ~mask)


# A temporary from another host cannot be asked whether its process lives: one untouched this long is taken as
# left by a killed writer. Every write here lasts seconds to minutes and touches its temporary as it goes.
STALE_AFTER_S = 3600.0


def _host() -> str:
    """This host's name as it appears in a temporary's name: no dots, so that the name parses back."""
    return re.sub(r"[^A-Za-z0-9-]", "_", socket.gethostname()) or "_"


def _temporary_prefix(path: Path) -> str:
    return f".{path.name}.partial.{os.getpid()}.{_host()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _untouched_for(path: Path) -> float:
    """Seconds since anything in `path` (a file, or a folder and everything under it) last changed."""
    newest = path.lstat().st_mtime
    if path.is_dir():
        for root, dirs, files in os.walk(path):
            for name in dirs + files:
                newest = max(newest, (Path(root) / name).lstat().st_mtime)
    return time.time() - newest


def remove_leftovers(path: Path) -> None:
    """Remove the temporaries of earlier writes of `path` whose writer is gone: on this host, one whose process
    no longer runs; from another host, one untouched for `STALE_AFTER_S`. A live writer's temporary is kept, so a
    second writer of the same output does not break the first."""
    prefix = f".{path.name}.partial."
    try:
        names = [e.name for e in os.scandir(path.parent) if e.name.startswith(prefix)]
    except OSError:  # an unreadable folder: the write itself says why
        return
    here = _host()
    for name in names:
        match = re.fullmatch(r"(\d+)\.([A-Za-z0-9_-]+)\..+", name[len(prefix):])
        if match is None:
            continue
        pid, host, leftover = int(match[1]), match[2], path.parent / name
        try:
            if host == here:
                if _alive(pid):
                    continue
                why = f"process {pid} no longer runs"
            else:
                idle = _untouched_for(leftover)
                if idle < STALE_AFTER_S:
                    continue
                why = f"written on {host}, untouched for {idle / 3600:.1f} h"
            if leftover.is_dir() and not leftover.is_symlink():
                shutil.rmtree(leftover)
            else:
                leftover.unlink()
        except FileNotFoundError:  # removed meanwhile by another writer of this output
            continue
        print(f"removed {leftover}: an unfinished write of {path.name} ({why})", file=sys.stderr)


@contextmanager
def atomic_path(path: str | Path, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success flush it, give it the umask's mode and rename it to
    `path`; on error remove it. An earlier write's temporary whose writer was killed is removed first."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(path)
    with naming_output(path):
        fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path), suffix=suffix or ".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        with phase("io"), naming_output(path):  # the caller's writing and the flush
            yield tmp_path
            _finish(tmp_path)
            os.replace(tmp_path, path)
            _fsync(path.parent)  # the rename itself, on a file system that keeps it in memory
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextmanager
def naming_output(path: Path) -> Iterator[None]:
    """An error writing `path` names the output, so that the command's one-line error says which file could not
    be written: a write that fails for want of room (a full disk, a quota; on a parallel file system often only at
    the flush) raises an OSError naming no file, and one in the temporary beside the output names that random name
    (`.out.json.partial.<pid>.<host>.k2j3abcd.tmp` in a folder one may not write to)."""
    try:
        yield
    except (OSError, RuntimeError) as e:
        # torch.save's archive writer raises its own RuntimeError on the way out of a write that failed
        failed = e if isinstance(e, OSError) else e.__context__
        temporary = str(path.parent / f".{path.name}.")  # the prefix of `atomic_path`'s and `write_zarr_group`'s
        if (not isinstance(failed, OSError) or failed.errno is None
                or not (failed.filename is None or str(failed.filename).startswith(temporary))):
            raise
        raise OSError(failed.errno, failed.strerror, str(path)) from e


def require_png(path: str | Path, flag: str, what: str = "image") -> None:
    """Refuse, before any work, an output name that does not end in .png for a file written as a PNG (under
    another name it opens wrongly, or not at all)."""
    if Path(path).suffix.lower() != ".png":
        raise ValueError(f"{flag} {path}: the {what} is written as a PNG; give a name ending in .png")


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_save(path: str | Path, save: Callable[[Path], None], *, suffix: str | None = None) -> None:
    """Call `save(tmp_path)` and move the result into place (for writers that insist on a suffix)."""
    with atomic_path(path, suffix=suffix) as tmp:
        save(tmp)


def atomic_torch_save(path: str | Path, obj: object) -> None:
    """`torch.save` atomically, through a file object: given a path, torch names the archive's folder after
    the (random) temporary name, so two identical runs wrote different bytes (stress suite)."""
    import torch

    with atomic_path(path, suffix=".pt") as tmp, open(tmp, "wb") as f:
        torch.save(obj, f)


class StoreError(ValueError):
    """A store that is missing, not what a reader expects, or damaged; the message names it and what remakes it."""


@timed("io")
def write_zarr_group(path: str | Path, fill: Callable[[zarr.Group], None], *, made_by: str) -> None:
    """Build a Zarr v3 group with `fill(root)` beside `path`, record a checksum of every array and `made_by`
    (the step that writes it, named when a reader finds it damaged), flush it, then swap it in (atomic for
    readers)."""
    import zarr

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(path)
    with naming_output(path):
        tmp = Path(tempfile.mkdtemp(prefix=_temporary_prefix(path), dir=path.parent))
    try:
        with naming_output(path):
            root = zarr.open_group(str(tmp), mode="w", zarr_format=3)
            fill(root)
            root.attrs.update({"checksums": {name: _stored_checksum(arr) for name, arr in sorted(root.arrays())},
                               "made_by": made_by})
            _finish(tmp, directory=True)
        old = None
        if path.exists():
            old = path.with_name(f"{_temporary_prefix(path)}old")
            os.replace(path, old)
        os.replace(tmp, path)
        _fsync(path.parent)
        if old is not None:
            shutil.rmtree(old)
    except OSError:
        # zarr writes an array's chunks concurrently: those still queued when one failed find the folder gone
        # (removed below) and would be reported, as abandoned asyncio tasks, when the process ends, after the
        # command's own one-line error
        logging.getLogger("asyncio").disabled = True
        raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def array_checksum(values: ArrayLike) -> str:
    """sha256 of an array's values, shape and dtype (what a reader gets, whatever the chunks and codecs)."""
    values = np.ascontiguousarray(values)
    h = _checksum_of(values.dtype, values.shape)
    h.update(values)  # its buffer: `tobytes` hashed the same bytes from a copy (512 MiB more for a 512³ volume)
    return h.hexdigest()


CHECKSUM_SLAB_BYTES = 64 << 20  # read back at a time when a written array's checksum is taken


def _stored_checksum(array) -> str:
    """`array_checksum` of a Zarr array as written (read back through its codecs), read along its first axis in
    slabs of about CHECKSUM_SLAB_BYTES: the same sha256 without holding the array a second time."""
    if array.ndim == 0:
        return array_checksum(array[...])
    h = _checksum_of(array.dtype, array.shape)
    row = max(1, array.dtype.itemsize * math.prod(array.shape[1:]))
    rows = max(1, CHECKSUM_SLAB_BYTES // row)
    for r0 in range(0, array.shape[0], rows):
        h.update(np.ascontiguousarray(array[r0:r0 + rows]))
    return h.hexdigest()


def _checksum_of(dtype, shape: tuple):
    """`array_checksum`'s sha256 with its header (dtype and shape) taken: the values' bytes follow, in C order,
    whole or a slab at a time (`VerifiedGroup.read_rows`)."""
    return hashlib.sha256(f"{np.dtype(dtype).str} {tuple(shape)}".encode())


class VerifiedGroup:
    """A Zarr group whose arrays are checked against the checksums written with them, as they are read."""

    @timed("io")
    def __init__(self, path: str | Path, what: str):
        import zarr

        self.path, self.what = Path(path), what
        if not self.path.is_dir():  # zarr's own words for these are "No group found in store ... at path ''"
            raise StoreError(f"{self.path}: " + ("a file" if self.path.exists() else "no such store")
                             + f"; expected {what} (a .zarr folder){did_you_mean(self.path)}")
        try:
            self.root = zarr.open_group(str(self.path), mode="r")
            self.attrs = dict(self.root.attrs)
        except zarr.errors.NodeNotFoundError:  # zarr names a StorePath and "path ''"
            raise StoreError(f"{self.path}: not {what} (no Zarr group metadata in it)") from None
        except (FileNotFoundError, KeyError, ValueError) as e:
            raise StoreError(f"{self.path}: not {what} ({type(e).__name__}: {e})") from None
        self.checksums = self.attrs.get("checksums")  # None: written before checksums (not verifiable)

    def __contains__(self, name: str) -> bool:
        return name in self.root

    def remake(self) -> str:
        """What rewrites this store: its rule, and the command that forces it (a plain run, finding the store and
        the files made from it, has nothing to do)."""
        step = self.attrs.get("made_by")
        rerun = f"rerun `{step}` to rewrite it" if step else "rerun the step that writes it"
        return f"{rerun} (`snakemake --profile <yours> -f {self.path}`)"

    def _array(self, name: str):
        try:
            return self.root[name]
        except KeyError:
            raise StoreError(f"{self.path}: not {self.what} (no array {name!r})") from None

    def _values(self, array, name: str, where=Ellipsis) -> np.ndarray:
        try:
            return np.asarray(array[where])
        except Exception as e:  # a truncated or garbled chunk fails in the codec, deep inside zarr
            raise StoreError(f"{self.path}: array {name!r} cannot be read ({type(e).__name__}: {e}); it is "
                             f"damaged, {self.remake()}") from None

    def _check(self, name: str, checksum: str) -> None:
        if self.checksums is not None and name in self.checksums and checksum != self.checksums[name]:
            raise StoreError(f"{self.path}: array {name!r} does not match its checksum (a chunk is missing or was "
                             f"changed); it is damaged, {self.remake()}")

    @timed("io")
    def read(self, name: str) -> np.ndarray:
        values = self._values(self._array(name), name)
        self._check(name, array_checksum(values))
        return values

    @timed("io")
    def read_rows(self, name: str, keep: Callable[[np.ndarray], np.ndarray], rows: int = 64) -> np.ndarray:
        """What `keep` makes of the array `name`, read `rows` rows (along its first axis) at a time and joined:
        the whole array is never held (its checksum is taken over the slabs in order, the same sha256 as `read`'s).
        `keep` maps a slab (r, ...) to an array whose first axis is r."""
        array = self._array(name)
        h, kept = _checksum_of(array.dtype, array.shape), []
        for r0 in range(0, array.shape[0], rows):
            slab = self._values(array, name, slice(r0, r0 + rows))
            h.update(np.ascontiguousarray(slab))
            kept.append(keep(slab))
        self._check(name, h.hexdigest())
        return np.concatenate(kept) if kept else keep(np.zeros((0, *array.shape[1:]), dtype=array.dtype))

    def verify(self) -> list[str]:
        """Read every array; the names checked (raises on the first damaged one)."""
        import warnings

        with warnings.catch_warnings():  # a workflow's own marker files in the folder are no part of the store
            warnings.filterwarnings("ignore", message="Object at .* is not recognized as a component")
            names = sorted(name for name, _ in self.root.arrays())
        for name in names:
            self.read(name)
        return names


def store_folders(paths: list[Path]) -> list[tuple[Path, list[Path]]]:
    """(folder, its .zarr stores) for each of `paths`: a store alone, a results folder (results/<scene>), or each
    scene folder of a folder of scenes (results/)."""
    folders = []
    for path in paths:
        if not path.exists():
            raise StoreError(f"check-store: {path}: no such store or results folder{did_you_mean(path)}")
        if path.suffix == ".zarr":
            folders.append((path, [path]))
        elif stores := sorted(path.glob("*.zarr")):
            folders.append((path, stores))
        else:
            folders += [(sub, stores) for sub in sorted(p for p in path.iterdir() if p.is_dir())
                        if (stores := sorted(sub.glob("*.zarr")))]
    if not folders:
        raise StoreError(f"check-store: no .zarr store in {', '.join(map(str, paths))}")
    return folders


def check_stores(folders: list[tuple[Path, list[Path]]]) -> Iterator[str]:
    """Verify each store of `folders` (`store_folders`' list); yields one line per store: its arrays, whether their
    checksums match (or that it predates checksums), its size and the time taken. Then, per folder, the stores that
    record the scene they were made for (the `extinction` attribute, `volume.extinction_id`) must record one: else
    the folder was put together from two runs."""
    for folder, stores in folders:
        scenes: dict[str, list[str]] = {}
        for store in stores:
            t0 = time.perf_counter()
            group = VerifiedGroup(store, "a Zarr store")
            names = group.verify()
            state = ("checksums match" if group.checksums is not None
                     else "readable (written before checksums: rerun the step that writes it to make it verifiable)")
            size = sum(f.stat().st_size for f in store.rglob("*") if f.is_file())
            if "extinction" in group.attrs:
                scenes.setdefault(str(group.attrs["extinction"]), []).append(store.name)
            yield f"{store}: {', '.join(names)}: {state} ({size / 2 ** 20:.1f} MiB in {time.perf_counter() - t0:.2f} s)"
        if len(scenes) > 1:
            made = "; ".join(f"{', '.join(names)} for {scene}" for scene, names in scenes.items())
            raise StoreError(f"check-store: {folder}: its stores were made for {len(scenes)} different scenes "
                             f"(extinction fields: {made}), a folder put together from two runs; rerun snakemake "
                             f"for this scene")


def did_you_mean(path: str | Path) -> str:
    """"; did you mean <path>?" where a path that exists differs from the missing `path` by a typo in one or more of
    its names (results/nucleonn/volume.zarr: results/nucleon/volume.zarr), else "" (nothing near enough)."""
    import difflib

    path = Path(path)
    near = Path(path.anchor) if path.is_absolute() else Path()
    for name in path.parts[len(near.parts):]:
        if not (near / name).exists():
            try:
                names = [p.name for p in near.iterdir()]
            except OSError:
                return ""
            found = difflib.get_close_matches(name, names, n=1, cutoff=0.8)
            if not found:
                return ""
            name = found[0]
        near = near / name
    return f"; did you mean {near}?" if near != path else ""


def file_in_the_way(path: str | Path) -> Path | None:
    """The first of `path` and its parents that is a file: where a folder is needed, it stops mkdir and open."""
    path = Path(path)
    return next((p for p in (path, *path.parents) if p.is_file()), None)


def error_line(e: BaseException) -> str:
    """An exception as one short line: its type and first sentence (torch's miniz error appends a paragraph)."""
    text = str(e).splitlines()[0].split(". ")[0][:160] if str(e) else ""
    return f"{type(e).__name__}: {text}"


@timed("io")
def resume(checkpoint: str | Path | None, fingerprint: str, *, log: Callable[[str], None] = print,
           map_location: str | torch.device = "cpu",
           weights_only: bool = False, key: str = "fingerprint") -> dict | None:
    """The state saved in `checkpoint` when it was written for this `fingerprint` (same inputs and
    settings), else None; a checkpoint of other inputs is left alone and said so, and one that cannot be read
    is set aside (renamed `<name>.corrupt-<time>`, kept for a post-mortem) so that the step starts afresh."""
    import torch

    if checkpoint is None or not Path(checkpoint).exists():
        return None
    try:
        state = torch.load(checkpoint, map_location=map_location, weights_only=weights_only)
        if not isinstance(state, dict):
            raise TypeError(f"holds a {type(state).__name__}, not a checkpoint's dict")
    except Exception as e:  # truncated zip, garbage, a pickle of something else: torch raises many kinds
        aside = Path(checkpoint).with_name(f"{Path(checkpoint).name}.corrupt-{time.strftime('%Y%m%dT%H%M%S')}")
        os.replace(checkpoint, aside)
        log(f"{checkpoint}: unreadable ({error_line(e)}); set aside as {aside.name}, starting afresh")
        return None
    if state.get(key) == fingerprint:
        return state
    log(f"ignoring {checkpoint}: it belongs to other inputs or settings")
    return None


def read_json(path: str | Path, what: str) -> dict:
    """The JSON object a stage wrote at `path`, or a StoreError naming the file and `what` it should be: a
    truncated or foreign file is one line, not a traceback from json."""
    path = Path(path)
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as e:  # a missing file, bad UTF-8, a cut-off object
        raise StoreError(f"{path}: unreadable ({error_line(e)}); expected {what}") from None
    if not isinstance(value, dict):
        raise StoreError(f"{path}: holds a JSON {type(value).__name__}, not an object; expected {what}")
    return value


def finite_json(value: Any) -> Any:
    """JSON has no infinity: an exact match (PSNR +inf) is written as the string "inf"."""
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    return value
