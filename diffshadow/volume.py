"""Scalar volumes: loading, normalisation and the box they live in; prepare_volume's store of one with its TF.

Grid convention (docs/design.md §2, used everywhere): a volume of X×Y×Z voxels is stored as a float32
array `(Z, Y, X)`; it fills a box whose longest side is 1. Vertex-centred: voxel `i` of `n` along an
axis sits at `i / (n - 1) · extent`; values between voxels are trilinear; μ = 0 outside the box.
"""

from __future__ import annotations

import errno
import hashlib
import json
import math
import re
import warnings
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path

import numpy as np

from diffshadow.io import VerifiedGroup, array_checksum, did_you_mean, write_zarr_group
from diffshadow.transfer import TransferFunction

RAW_NAME = re.compile(r"_(\d+)x(\d+)x(\d+)_([a-z]+\d*)\.raw$")
RAW_DTYPES = {
    "uint8": np.uint8,
    "int8": np.int8,
    "uint16": np.uint16,
    "int16": np.int16,
    "uint32": np.uint32,
    "int32": np.int32,
    "float32": np.float32,
    "float64": np.float64,
}

BUNDLED = {"nucleon": "nucleon_41x41x41_uint8.raw"}


class VolumeError(ValueError):
    """A volume file that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class Volume:
    """A scalar field on a vertex-centred grid, normalised to [0, 1]."""

    data: np.ndarray  # (Z, Y, X) float32 in [0, 1]
    extent: np.ndarray  # (3,) box size along (x, y, z); longest side 1
    name: str

    @property
    def dims(self) -> tuple[int, int, int]:
        """Voxel counts along (x, y, z)."""
        z, y, x = self.data.shape
        return x, y, z

    @cached_property
    def checksum(self) -> str:
        """`io.array_checksum` of the grid: what the files made from it record (hashed once per volume)."""
        return array_checksum(self.data)

    @property
    def voxel_size(self) -> np.ndarray:
        """Distance between neighbouring voxels along (x, y, z), in box units."""
        return self.extent / (np.asarray(self.dims, dtype=np.float64) - 1)


def extinction_id(volume: Volume, tf: TransferFunction) -> str:
    """What every shadow of a scene is computed from, as 16 hex digits: the normalised grid's values, its box, the
    opacity polyline and `density_scale` (the extinction field). The TF's colours are left out: they change the image,
    not the shadow, so a cache stays valid under a recoloured TF. Shadow caches carry it (subset files, weight stores,
    diffusion checkpoints) so that `render` and `view` refuse a cache made for another scene."""
    field = {"volume": volume.checksum, "extent": np.asarray(volume.extent, np.float64).tolist(),
             "opacity": np.asarray(tf.opacity_points, np.float64).tolist(), "density_scale": float(tf.density_scale)}
    return hashlib.sha256(json.dumps(field, sort_keys=True).encode()).hexdigest()[:16]


def check_extinction(made_for: str | None, here: str | None, *, cache: str, scene: str, remedy: str,
                     error: type[ValueError] = ValueError) -> None:
    """Refuse, in one line, shadows (`cache` names them) made for another extinction field (`made_for`,
    `extinction_id`) than `scene`'s (`here`); `remedy` ends the line. Where either is unknown (a file written before
    the field travelled with caches: None) nothing is checked."""
    if None not in (made_for, here) and made_for != here:
        raise error(f"{cache}: made for another volume or opacity than {scene} (extinction field {made_for} against "
                    f"{here}); {remedy}")


def refined_shape(shape: tuple[int, ...], factor: int) -> tuple[int, ...]:
    """The shape of a grid `refine`d `factor` times."""
    return tuple((n - 1) * factor + 1 for n in shape)


# `fit.grid_upsample: auto`: stage 1's target grids are refined 4 times where that grid has at most this many voxels,
# else 3 times where that fits, else twice. A sweep's grid costs time in its voxels (bi2o3's 80³ at 4x, 317³: ~4.7 s
# a light on one thread), while twice-refined grids missed the exact shadow by more than the SIRENs did on the small
# volumes (nucleon's targets 48 dB, its stage 1 47.3; at 4x 59 and 52.0: docs/performance.md, `fit.grid_upsample`)
AUTO_UPSAMPLE_VOXELS = 1 << 25
AUTO_UPSAMPLES = (4, 3)


def upsample_factor(setting: int | str, shape: tuple[int, ...]) -> int:
    """`fit.grid_upsample` for a volume of `shape`: an integer as given; "auto" the largest of AUTO_UPSAMPLES whose
    refined grid has at most AUTO_UPSAMPLE_VOXELS voxels, else 2."""
    if setting != "auto":
        return int(setting)
    return next((f for f in AUTO_UPSAMPLES if math.prod(refined_shape(shape, f)) <= AUTO_UPSAMPLE_VOXELS), 2)


def refine(volume: Volume, factor: int) -> Volume:
    """The same trilinear field sampled `factor` times more finely (exact: a trilinear function
    restricted to a sub-cell is reproduced by trilinear interpolation of the sub-cell's corners)."""
    if factor == 1:
        return volume
    import torch
    import torch.nn.functional as F

    from diffshadow.hpc import check_host_room

    size = list(refined_shape(volume.data.shape, factor))
    check_host_room(4 * math.prod(size), f"the volume refined {factor} times ({'x'.join(map(str, size))} voxels)")
    data = F.interpolate(torch.from_numpy(np.ascontiguousarray(volume.data))[None, None], size=size, mode="trilinear",
                         align_corners=True)[0, 0]
    return Volume(data=data.numpy(), extent=volume.extent, name=volume.name)


def bundled_path(name: str = "nucleon") -> Path:
    """Path of a volume shipped inside the package (the default scene needs nothing else)."""
    if name not in BUNDLED:
        raise VolumeError(f"no bundled volume {name!r}; bundled: {sorted(BUNDLED)}")
    return Path(str(resources.files("diffshadow") / "data" / BUNDLED[name]))


def resolve_path(spec: str | Path) -> Path:
    """`bundled:NAME` → the packaged file; anything else is a filesystem path."""
    text = str(spec)
    if text.startswith("bundled:"):
        return bundled_path(text.split(":", 1)[1])
    return Path(text)


def run_path(spec: str | Path, run_dir: str | Path = ".") -> str:
    """The volume file as a workflow names it as an input: relative to the run's directory where it lies inside
    it, else as resolved. Snakemake reruns a job whose input set changed, and a bundled volume's resolved path is
    absolute inside the checkout (an editable install, or a virtual environment in the checkout): a moved or
    copied checkout would rerun its finished scene from the volume on."""
    path = resolve_path(spec)
    if not path.is_absolute():  # as the user wrote it: already moves with the run
        return str(path)
    for base, inside in ((Path(run_dir).absolute(), path), (Path(run_dir).resolve(), path.resolve())):
        if inside.is_relative_to(base):
            return str(inside.relative_to(base))
    return str(path)  # outside the run's directory: a move of the run does not move it


def load_volume(
    path: str | Path,
    *,
    dims: tuple[int, int, int] | None = None,
    dtype: str | None = None,
    key: str | None = None,
    value_range: tuple[float, float] | None = None,
    spacing: tuple[float, float, float] | None = None,
) -> Volume:
    """Load `.raw`, `.npy`, `.h5/.hdf5` or `.zarr` into a normalised `Volume`.

    `dims` is (x, y, z) and `dtype` a numpy name, both parsed from `name_XxYxZ_dtype.raw` when not
    given. `key` picks the HDF5 dataset or Zarr array. `value_range` replaces the data's min/max for
    normalisation; `spacing` (x, y, z) makes the box anisotropic.
    """
    path = resolve_path(path)
    if not path.exists():
        raise VolumeError(f"{path}: no such file{did_you_mean(path)}")
    suffix = path.suffix.lower()
    if suffix == ".raw":
        raw = _read_raw(path, dims, dtype)
    elif suffix == ".npy":
        with open(path, "rb") as f:
            magic = np.lib.format.MAGIC_PREFIX
            if f.read(len(magic)) != magic:  # else NumPy reads the bytes as a pickle, and its error suggests pickles
                raise VolumeError(f"{path}: not a .npy file (it does not begin with NumPy's header; "
                                  f"write it with numpy.save)")
        try:
            raw = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as e:  # a truncated file: "mmap length is greater than file size"
            raise VolumeError(f"{path}: not a readable .npy file ({e})") from None
    elif suffix in (".h5", ".hdf5"):
        raw = _read_hdf5(path, key)
    elif suffix == ".zarr":
        raw = _read_zarr(path, key)
    else:
        raise VolumeError(f"{path}: unsupported file type {suffix!r}; expected .raw, .npy, .h5/.hdf5 or .zarr")
    return _to_volume(path, raw, value_range, spacing)


def _read_raw(path: Path, dims, dtype) -> np.ndarray:
    match = RAW_NAME.search(path.name)
    if dims is None:
        if match is None:
            raise VolumeError(
                f"{path}: cannot tell the dimensions: the name is not 'name_XxYxZ_dtype.raw' and no dims are given "
                f"(a scene file's load: {{dims: [X, Y, Z], dtype: uint8}})"
            )
        dims = tuple(int(v) for v in match.group(1, 2, 3))
    if dtype is None:
        if match is None:
            raise VolumeError(f"{path}: cannot tell the dtype: the name has none and no dtype is given (a scene "
                              f"file's load: {{dtype: ...}}, one of {', '.join(RAW_DTYPES)})")
        dtype = match.group(4)
    if dtype not in RAW_DTYPES:
        raise VolumeError(f"{path}: unsupported dtype {dtype!r}; supported: {', '.join(RAW_DTYPES)}")
    if len(dims) != 3 or any(int(d) < 1 for d in dims):
        raise VolumeError(f"{path}: dims must be three positive integers (x, y, z), got {dims}")
    np_dtype = np.dtype(RAW_DTYPES[dtype]).newbyteorder("<")
    expected = int(np.prod(dims)) * np_dtype.itemsize
    actual = path.stat().st_size
    if actual != expected:
        x, y, z = dims
        raise VolumeError(
            f"{path}: file has {actual} bytes but {x}x{y}x{z} {dtype} needs {expected} bytes"
        )
    x, y, z = (int(d) for d in dims)
    return np.fromfile(path, dtype=np_dtype).reshape(z, y, x)


def _read_hdf5(path: Path, key: str | None) -> np.ndarray:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:  # h5py's "file signature not found" names no file
        if "unable to lock file" not in str(e):
            raise VolumeError(f"{path}: not an HDF5 file ({e})") from None
        if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
            raise VolumeError(f"{path}: open for writing in another process (HDF5's file lock); read it once that "
                              f"process has closed the file") from None
        # A file system without locks (ENOSYS, ENOLCK, ENOTSUP: some Lustre and NFS mounts, where HDF5 1.10+
        # fails every open): there is no lock to take against a writer, so the input is read without one, as
        # HDF5_USE_FILE_LOCKING=FALSE would do for every file.
        try:
            f = h5py.File(path, "r", locking=False)
        except OSError as again:
            raise VolumeError(f"{path}: not readable as HDF5 ({again})") from None
    with f:
        names: list[str] = []
        f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
        key = _only_one(path, names, "dataset") if key is None else key
        if key not in f or not isinstance(f[key], h5py.Dataset):
            raise VolumeError(f"{path}: no dataset {key!r}; present: {names}")
        return f[key][()]


def _read_zarr(path: Path, key: str | None) -> np.ndarray:
    import zarr

    try:
        node = zarr.open(str(path), mode="r")
    except zarr.errors.NodeNotFoundError:  # a folder (or file) of other things: zarr's message names a StorePath
        raise VolumeError(f"{path}: not a Zarr store (no Zarr group or array metadata in it)") from None
    if isinstance(node, zarr.Array):
        if key is not None:
            raise VolumeError(f"{path}: is a single array, but load: {{key: {key}}} was given; drop the key")
        return node[...]
    names = sorted(name for name, _ in node.arrays())
    key = _only_one(path, names, "array") if key is None else key
    if key not in names:
        raise VolumeError(f"{path}: no array {key!r}; present: {names}")
    return node[key][...]


def _only_one(path: Path, names: list[str], kind: str) -> str:
    """The file's one `kind` ("dataset", "array"), where no key was given; else what to write in a scene file."""
    if not names:
        raise VolumeError(f"{path}: no {kind} in it; expected a 3-D one (the volume)")
    if len(names) != 1:
        raise VolumeError(f"{path}: {len(names)} {kind}s ({', '.join(names)}); say which is the volume with a scene "
                          f"file's load: {{key: {names[0]}}}")
    return names[0]


def _to_volume(path: Path, raw: np.ndarray, value_range, spacing) -> Volume:
    raw = np.asarray(raw)
    if raw.ndim != 3:
        raise VolumeError(f"{path}: expected a 3-D array, got shape {raw.shape}")
    if not (np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)):
        raise VolumeError(f"{path}: unsupported dtype {raw.dtype}; expected integers or floats")
    if min(raw.shape) < 2:
        raise VolumeError(f"{path}: every axis needs at least 2 voxels, got shape (z, y, x) = {raw.shape}")
    if np.issubdtype(raw.dtype, np.floating):  # integers are finite
        bad, first = 0, None
        for sl in plane_slabs(raw.shape):
            where = ~np.isfinite(raw[sl])
            if where.any():
                bad += int(where.sum())
                first = np.argwhere(where)[0] + [sl.start, 0, 0] if first is None else first
        if bad:
            z, y, x = first
            raise VolumeError(f"{path}: {bad} NaN/Inf voxels; first at (x, y, z) = ({x}, {y}, {z})")
    if value_range is None:
        # float64's min and max are the raw values' (the conversion keeps order), without a float64 copy
        lo, hi = float(raw.min()), float(raw.max())
    else:
        lo, hi = (float(v) for v in value_range)
        if not hi > lo:
            raise VolumeError(f"{path}: value_range must be (low, high) with high > low, got {value_range}")
    data = np.zeros(raw.shape, dtype=np.float32)
    if hi > lo:
        # Scaled into [-1, 1] first (found by the stress suite): with float64 data near ±1.8e308, hi - lo
        # overflowed to inf and inf/inf left NaN voxels, silently. In float64, a slab at a time: the whole
        # volume's float64 copy and its temporaries were 8.6 float32 grids at once (4.4 GiB on 512³)
        scale = max(abs(lo), abs(hi))
        lo_s, hi_s = lo / scale, hi / scale
        for sl in plane_slabs(raw.shape):
            d = raw[sl].astype(np.float64)
            d /= scale
            d -= lo_s
            d /= hi_s - lo_s
            data[sl] = np.clip(d, 0.0, 1.0, out=d)
    else:
        warnings.warn(f"{path}: the volume is constant ({lo}); it normalises to all zeros", stacklevel=3)
    dims = np.array(raw.shape[::-1], dtype=np.float64)  # (x, y, z)
    spacing_arr = np.ones(3) if spacing is None else np.asarray(spacing, dtype=np.float64)
    if spacing_arr.shape != (3,) or not np.all(spacing_arr > 0):
        raise VolumeError(f"{path}: spacing must be three positive numbers (x, y, z), got {spacing}")
    size = (dims - 1) * spacing_arr
    extent = size / size.max()
    name = RAW_NAME.sub("", path.name) if RAW_NAME.search(path.name) else path.stem
    return Volume(data=data, extent=extent, name=name)


# voxels a whole-volume pass reads at once (the normalisation here, the visible voxels in `sampling`): 32 MiB of
# float64; a pass over every voxel at once held 5-12 grids' bytes (GiB on a 512³ volume)
SLAB_VOXELS = 1 << 22


def plane_slabs(shape: tuple[int, ...]) -> list[slice]:
    """Slices along the first axis of a (Z, Y, X) grid, whole planes of about SLAB_VOXELS voxels each (at least
    one plane), covering it in order."""
    step = max(1, SLAB_VOXELS // max(1, shape[1] * shape[2]))
    return [slice(z, min(z + step, shape[0])) for z in range(0, shape[0], step)]


# ------------------------------------------------------------- the prepared volume (prepare_volume's store)
# Here and not in `artifacts` with the other files: PyTorch is not needed to write or read it, so the first job
# of every run starts without it (1.1 s on a 2-core CPU, 4 s with a CUDA build).


def save_prepared(path: str | Path, volume: Volume, tf: TransferFunction, source: dict | None = None) -> None:
    """`prepare_volume`'s output: the normalised grid, its box and the TF (Zarr v3); `source`: what the grid was made
    from (`volume_source`), read back by `prepared_from`."""

    def fill(root) -> None:
        root.create_array("scalar", data=volume.data)
        root.attrs.update({"extent": volume.extent.tolist(), "name": volume.name,
                           "transfer_function": tf.to_config(), "extinction": extinction_id(volume, tf)})
        if source is not None:
            root.attrs["source"] = source

    write_zarr_group(path, fill, made_by="prepare_volume")


def load_prepared(path: str | Path) -> tuple[Volume, TransferFunction]:
    """(Volume, TransferFunction) from `prepare_volume`'s Zarr store."""
    path = Path(path)
    try:
        group = VerifiedGroup(path, "a prepared volume")
        attrs = group.attrs
        scalar = group.read("scalar")  # hashed as it is read, against the checksum written with it
        volume = Volume(data=np.asarray(scalar, dtype=np.float32),
                        extent=np.asarray(attrs["extent"], dtype=np.float64), name=attrs["name"])
        if scalar.dtype == np.float32 and group.checksums:  # that hash is `Volume.checksum`'s: not taken twice
            volume.__dict__["checksum"] = group.checksums["scalar"]
        return volume, TransferFunction.from_config(attrs["transfer_function"])
    except KeyError as e:
        raise VolumeError(f"{path}: not a prepared volume (missing {e})") from None


def volume_source(scene: dict) -> dict:
    """What a scene's grid is made from: its volume as named and the load keys (a file replaced in place since is
    found by its time, `prepared_from`; not recorded, so that two clones prepare the same bytes)."""
    return json.loads(json.dumps({"volume": str(scene["volume"]), "load": scene.get("load", {})}))


def prepared_from(path: str | Path, scene: dict) -> bool:
    """Whether the prepared volume at `path` holds `scene`'s extinction field as the scene has it now: made from the
    same volume file, not modified after the store was written (the test Snakemake itself makes of a file), with
    the same load keys, opacity and density_scale. Its TF's colours may differ: they change the images, not the
    field. False where there is no such store, or it does not say what it was made from (one written before it
    did), or anything cannot be read: then it is taken as changed."""
    if not is_prepared(path):
        return False
    try:  # asked while a workflow is planned: anything unreadable is "changed", which reruns, never an error there
        attrs = VerifiedGroup(path, "a prepared volume").attrs
        made, now = TransferFunction.from_config(attrs["transfer_function"]), TransferFunction.from_config(
            scene["transfer_function"])
        newer = resolve_path(scene["volume"]).stat().st_mtime_ns > (Path(path) / "zarr.json").stat().st_mtime_ns
        return (attrs.get("source") == volume_source(scene) and not newer and made.density_scale == now.density_scale
                and np.array_equal(made.opacity_points, now.opacity_points))
    except Exception:  # noqa: BLE001
        return False


def prepared_voxels(path: str | Path) -> int:
    """The voxel count of a prepared volume, from its metadata (the grid is not read)."""
    import zarr

    try:
        return int(np.prod(zarr.open_group(str(path), mode="r")["scalar"].shape))
    except (FileNotFoundError, KeyError) as e:
        raise VolumeError(f"{path}: not a prepared volume (missing {e})") from None


def is_prepared(path: str | Path) -> bool:
    """Whether `path` is prepare_volume's store (a group with its `scalar` array), not a user's own .zarr volume."""
    return Path(path).suffix == ".zarr" and (Path(path) / "scalar" / "zarr.json").exists()


def scene_volume(scene: dict) -> tuple[Volume, TransferFunction]:
    """A scene's volume (its file and `load:` keys) and transfer function, refused where nothing of it can show."""
    where = f"scene {scene['volume']}"
    tf = TransferFunction.from_config(scene["transfer_function"]).require_visible(where)  # before the grid is read
    volume = load_volume(scene["volume"], **scene.get("load", {}))
    require_visible(volume, tf, where)  # this grid's
    return volume, tf


def require_visible(volume: Volume, tf: TransferFunction, where: str) -> None:
    """`tf.require_visible` over this grid's own values and box (tighter than the any-grid bound of a plan)."""
    tf.require_visible(where, values=(volume.data.min(), volume.data.max()), extent=volume.extent)

