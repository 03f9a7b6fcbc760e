import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from diffshadow.io import atomic_path
from diffshadow.siren import SirenConfig, WeightLayout
from diffshadow.store import StoreError, collect_subsets, open_store, read_subset, write_store, write_subset

CFG = SirenConfig(4, 1)
LAYOUT = WeightLayout.for_siren(CFG)
LIGHTS = np.eye(3)[[0, 1, 2, 0]] * np.array([[1], [1], [1], [-1]])


def subset(path, idx, layout=LAYOUT, extinction="0123456789abcdef"):
    write_subset(path, weights=np.full((len(idx), layout.n_params), idx[0], np.float32), light_index=idx,
                 lights=LIGHTS[idx], psnr=np.full(len(idx), 40.0), psnr_visible=np.full(len(idx), 42.0),
                 layout=layout, siren=CFG, config={"fit": {"steps": 3}}, extinction=extinction)


def test_collect_round_trip(tmp_path):
    subset(tmp_path / "subset_0.npz", [0, 1])
    subset(tmp_path / "subset_1.npz", [2, 3])
    store = collect_subsets([tmp_path / "subset_0.npz", tmp_path / "subset_1.npz"], 4, LIGHTS)
    write_store(tmp_path / "weights.zarr", store, made_by="collect_weights")
    back = open_store(tmp_path / "weights.zarr")
    np.testing.assert_array_equal(back.weights[:, 0], [0, 0, 2, 2])
    assert back.layout == LAYOUT and back.siren == CFG and back.config == {"fit": {"steps": 3}}
    assert back.extinction == "0123456789abcdef"  # what the SIRENs shade travels with them
    np.testing.assert_array_equal(back.lights, LIGHTS)
    import zarr
    assert zarr.open_group(str(tmp_path / "weights.zarr"), mode="r")["weights"].chunks == (1, LAYOUT.n_params)
    write_store(tmp_path / "weights.zarr", store, made_by="collect_weights")  # replacing an existing store works
    assert open_store(tmp_path / "weights.zarr").weights.shape == (4, LAYOUT.n_params)


def test_missing_subset_is_named(tmp_path):
    subset(tmp_path / "subset_0.npz", [0, 1])
    with pytest.raises(StoreError, match=r"lights \[2, 3\] are in no subset file"):
        collect_subsets([tmp_path / "subset_0.npz"], 4, LIGHTS)


def test_duplicate_light_and_layout_mismatch(tmp_path):
    subset(tmp_path / "a.npz", [0, 1])
    subset(tmp_path / "b.npz", [1, 2])
    with pytest.raises(StoreError, match=r"b.npz: light 1 is also in .*a.npz"):
        collect_subsets([tmp_path / "a.npz", tmp_path / "b.npz"], 4, LIGHTS)
    subset(tmp_path / "c.npz", [2, 3], layout=WeightLayout.for_siren(SirenConfig(5, 1)))
    with pytest.raises(StoreError, match=r"c.npz: its SIREN layout differs"):
        collect_subsets([tmp_path / "a.npz", tmp_path / "c.npz"], 4, LIGHTS)


def test_subsets_fitted_to_another_scene_are_not_collected(tmp_path):
    """A subset refitted after the volume or its opacity changed shades another scene: collected with the others,
    the store would mix two scenes' shadows under one light set."""
    subset(tmp_path / "a.npz", [0, 1])
    subset(tmp_path / "b.npz", [2, 3], extinction="fedcba9876543210")
    with pytest.raises(StoreError, match=r"^\S*b.npz: made for another volume or opacity than \S*a.npz \(extinction "
                                         r"field fedcba9876543210 against 0123456789abcdef\); rerun fit_siren"):
        collect_subsets([tmp_path / "a.npz", tmp_path / "b.npz"], 4, LIGHTS)


@pytest.mark.parametrize("damage", ["foreign", "truncated", "folder"])
def test_corrupt_subset_file_is_named(tmp_path, damage):
    """Any damage, a truncated copy among them (a zip's head without its directory: zipfile's BadZipFile, which is
    no OSError or ValueError), is one StoreError naming the file and the job that rewrites it."""
    path = tmp_path / "subset_1.npz"
    if damage == "foreign":
        path.write_bytes(b"not a zip")
    elif damage == "truncated":
        subset(path, [2, 3])
        path.write_bytes(path.read_bytes()[:1000])
    else:
        path.mkdir()
    with pytest.raises(StoreError, match=r"^\S*subset_1.npz: not a readable subset file \(\w+: .*\); rerun the "
                                         r"fit_siren job that writes it$"):
        read_subset(path)


def _rewrite(path, **change):
    """The subset file at `path` written again with some arrays replaced (as another version or a hand edit)."""
    from diffshadow.store import write_npz

    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    write_npz(path, {**arrays, **change})


@pytest.mark.parametrize("change, said", [
    ({"meta": np.array("{}")}, r"not a readable subset file \(KeyError: 'layout'\)"),
    ({"weights": np.zeros((2, LAYOUT.n_params + 1), np.float32)},
     rf"weights has shape \(2, {LAYOUT.n_params + 1}\), expected \(2, {LAYOUT.n_params}\) \(its 2 light indices; "
     rf"its SIREN layout's {LAYOUT.n_params} parameters\)"),
    ({"weights": np.zeros((3, LAYOUT.n_params), np.float32)}, r"weights has shape \(3, \d+\), expected \(2, \d+\)"),
    ({"lights": LIGHTS[:2, :2]}, r"lights has shape \(2, 2\), expected \(2, 3\)"),
    ({"psnr": np.zeros(1)}, r"psnr has shape \(1,\), expected \(2,\)"),
    ({"light_index": np.array(2)}, r"light_index has shape \(\), expected one index a light"),
    ({"weights": np.where(np.arange(2)[:, None] == 1, np.nan, np.zeros((2, LAYOUT.n_params), np.float32))},
     r"the weights of light\(s\) \[3\] are not finite"),
])
def test_a_subset_file_of_another_version_or_edited_is_named(tmp_path, change, said):
    """A readable subset file whose arrays disagree with each other or with its layout, or whose weights are not
    finite, is one StoreError naming the file, what is wrong and the job that rewrites it. Shapes that did not
    match were a broadcast error naming no file (more weights than parameters), or went unseen (a row too many);
    NaN weights were stored in weights.zarr."""
    path = tmp_path / "subset_1.npz"
    subset(path, [2, 3])
    assert read_subset(path)["weights"].shape == (2, LAYOUT.n_params)
    _rewrite(path, **change)
    with pytest.raises(StoreError, match=rf"^\S*subset_1.npz: {said}.*; rerun the fit_siren job that writes it$"):
        read_subset(path)


def test_interrupted_write_leaves_nothing(tmp_path):
    target = tmp_path / "out.npz"
    with pytest.raises(KeyboardInterrupt), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_geometry_points_round_trip_with_pool_lights(tmp_path):
    import torch

    from diffshadow import artifacts
    from diffshadow.lights import blend_weights

    subset(tmp_path / "subset_0.npz", [0, 1, 2, 3])
    write_store(tmp_path / "weights.zarr", collect_subsets([tmp_path / "subset_0.npz"], 4, LIGHTS),
                made_by="collect_weights")
    pts, vals = torch.rand(4, 8, 3), torch.rand(4, 8)
    pool = np.array([[0.6, 0.8, 0.0], [0.0, 0.6, 0.8]])
    pool_pts, pool_vals = torch.rand(2, 5, 3), torch.rand(2, 5)
    artifacts.write_geometry_points(tmp_path / "plain.zarr", pts, vals, LIGHTS, [1, 1, 1])
    check = (torch.rand(6, 3), torch.rand(4, 6))
    artifacts.write_geometry_points(tmp_path / "pool.zarr", pts, vals, LIGHTS, [1, 1, 1], (pool, pool_pts, pool_vals),
                                    check)
    plain, _ = artifacts.read_training_data(tmp_path / "weights.zarr", tmp_path / "plain.zarr")
    data, _ = artifacts.read_training_data(tmp_path / "weights.zarr", tmp_path / "pool.zarr")
    assert plain.pool is None and plain.check is None and torch.equal(data.points, pts)
    assert all(torch.equal(a, b) for a, b in zip(data.check, check, strict=True))
    assert np.allclose(data.pool.lights.numpy(), pool) and torch.equal(data.pool.values, pool_vals)
    assert torch.equal(data.pool.points, pool_pts)
    idx, w = blend_weights(LIGHTS, pool, 4, "inverse-angle")
    np.testing.assert_array_equal(data.pool.neighbours.numpy(), idx)
    assert np.allclose(data.pool.blend.numpy(), w) and np.allclose(data.pool.blend.sum(1).numpy(), 1)


def stored(tmp_path):
    subset(tmp_path / "subset_0.npz", [0, 1])
    subset(tmp_path / "subset_1.npz", [2, 3])
    path = tmp_path / "weights.zarr"
    write_store(path, collect_subsets([tmp_path / "subset_0.npz", tmp_path / "subset_1.npz"], 4, LIGHTS),
                made_by="collect_weights")
    return path


def test_a_deleted_chunk_is_named_not_read_as_zeros(tmp_path):
    path = stored(tmp_path)
    chunk = path / "weights" / "c" / "2" / "0"  # light 2's row (one light per chunk)
    assert chunk.is_file()
    chunk.unlink()
    with pytest.raises(StoreError, match=r"weights.zarr: array 'weights' does not match its checksum \(a chunk is "
                       r"missing or was changed\); it is damaged, rerun `collect_weights` to rewrite it "
                       r"\(`snakemake --profile <yours> -f .*weights.zarr`\)$"):
        open_store(path)


def test_a_truncated_chunk_is_one_line_naming_the_store(tmp_path):
    path = stored(tmp_path)
    chunk = path / "weights" / "c" / "3" / "0"
    chunk.write_bytes(chunk.read_bytes()[:5])
    with pytest.raises(StoreError, match=r"weights.zarr: array 'weights' cannot be read .*rerun `collect_weights`"):
        open_store(path)


def test_a_store_without_its_metadata_says_so(tmp_path):
    """A folder that lost its zarr.json (or never had one) is named as no store, not in zarr's words (a StorePath
    and "path ''")."""
    path = stored(tmp_path)
    (path / "zarr.json").unlink()
    with pytest.raises(StoreError, match=r"weights.zarr: not a weight store \(no Zarr group metadata in it\)"):
        open_store(path)


def test_a_changed_value_is_found(tmp_path):
    import zarr

    path = stored(tmp_path)
    zarr.open_group(str(path), mode="r+")["psnr"][1] = 99.0  # written through zarr: only the checksum can tell
    with pytest.raises(StoreError, match="'psnr' does not match its checksum"):
        open_store(path)


@pytest.mark.parametrize("rows", [1, 3, 64])
def test_an_array_read_a_few_rows_at_a_time_is_checked_as_a_whole(tmp_path, rows):
    """VerifiedGroup.read_rows (targets.zarr's images, read a few lights at a time): what `keep` makes of each slab,
    joined, is what it makes of the whole array, for any slab height; a value changed in any slab still fails
    the array's checksum, named."""
    import zarr

    from diffshadow.io import VerifiedGroup

    path = stored(tmp_path)
    group = VerifiedGroup(path, "a weight store")
    whole = group.read("weights")
    assert np.array_equal(group.read_rows("weights", lambda slab: slab[:, ::2], rows=rows), whole[:, ::2])
    zarr.open_group(str(path), mode="r+")["weights"][3, 1] += 1.0  # the last light's row, in the last slab
    with pytest.raises(StoreError, match="'weights' does not match its checksum"):
        VerifiedGroup(path, "a weight store").read_rows("weights", lambda slab: slab, rows=rows)


def test_a_written_arrays_checksum_is_taken_a_slab_at_a_time_as_of_the_whole(monkeypatch):
    """write_zarr_group reads each array back in slabs along its first axis to take its checksum (a 512³ volume was
    read back whole, then copied for hashing: 1 GiB more): for any slab size, the same sha256 as `array_checksum` of
    the whole array, for arrays of any rank, dtype and an empty first axis."""
    import zarr

    import diffshadow.io as io

    rng = np.random.default_rng(3)
    root = zarr.open_group(store=zarr.storage.MemoryStore(), mode="w", zarr_format=3)
    arrays = {"volume": rng.random((9, 5, 4), dtype=np.float32), "flat": rng.integers(0, 9, 17).astype(np.int16),
              "mask": rng.random((6, 3)) > 0.5, "scalar": np.float64(2.5), "empty": np.zeros((0, 4), np.float32)}
    for name, values in arrays.items():
        shape = np.asarray(values).shape  # chunks of two rows: a slab spans chunks and cuts them
        root.create_array(name, data=np.asarray(values), chunks=(2, *shape[1:]) if shape else "auto")
    for slab_bytes in (1, 7, 40, 1 << 20):
        monkeypatch.setattr(io, "CHECKSUM_SLAB_BYTES", slab_bytes)
        for name, values in arrays.items():
            assert io._stored_checksum(root[name]) == io.array_checksum(values), (name, slab_bytes)


def test_check_store_verifies_every_array(tmp_path):
    import subprocess
    import sys

    path = stored(tmp_path)
    ok = subprocess.run([sys.executable, "-m", "diffshadow.cli", "check-store", str(path)], capture_output=True,
                        text=True)
    assert ok.returncode == 0 and "lights, psnr, psnr_visible, weights: checksums match" in ok.stdout, ok.stderr
    (path / "psnr" / "c" / "0").unlink()
    bad = subprocess.run([sys.executable, "-m", "diffshadow.cli", "check-store", str(path)], capture_output=True,
                         text=True)
    assert bad.returncode != 0 and bad.stderr.count("\n") == 1 and "'psnr' does not match" in bad.stderr


def test_results_honour_the_umask(tmp_path):
    import os

    from diffshadow.io import atomic_write_text

    old = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "a.json", "{}")
        path = stored(tmp_path)
    finally:
        os.umask(old)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o640  # mkstemp alone: 0600
    assert path.stat().st_mode & 0o777 == 0o750  # mkdtemp alone: 0700
    assert (path / "weights").stat().st_mode & 0o777 == 0o750
    assert (path / "zarr.json").stat().st_mode & 0o777 == 0o640


def test_a_corrupt_checkpoint_is_set_aside(tmp_path):
    from diffshadow.io import resume

    ckpt = tmp_path / "subset_0.npz.ckpt"
    ckpt.write_bytes(b"PK\x03\x04 truncated")
    said = []
    assert resume(ckpt, "abc", log=said.append) is None
    aside = list(tmp_path.glob("subset_0.npz.ckpt.corrupt-*"))
    assert not ckpt.exists() and len(aside) == 1 and aside[0].read_bytes().startswith(b"PK")
    assert said and "unreadable" in said[0] and "set aside as subset_0.npz.ckpt.corrupt-" in said[0]


def test_results_are_flushed_before_the_rename(tmp_path, monkeypatch):
    """A node crash after the rename must not leave a renamed but empty file: the data is fsynced first, then
    the folder that records the rename."""
    import os

    from diffshadow import io

    order = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(io.os, "fsync", lambda fd: (order.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))),
                                                   real_fsync(fd))[1])
    monkeypatch.setattr(io.os, "replace", lambda a, b: (order.append(("replace", str(b))), real_replace(a, b))[1])
    io.atomic_write_text(tmp_path / "a.json", "{}")
    assert [kind for kind, _ in order] == ["fsync", "replace", "fsync"]
    assert order[0][1].startswith(str(tmp_path / ".a.json.")) and order[2][1] == str(tmp_path)


def test_checksums_are_written_in_name_order(tmp_path):
    """The same arrays give the same zarr.json bytes whatever order the store lists them in (it followed the
    file system's listing, which changed between two runs of the README's workflow)."""
    import json

    import numpy as np

    from diffshadow.io import write_zarr_group

    def fill(order):
        def f(root):
            for name in order:
                root.create_array(name, data=np.arange(3.0) * len(name))
        return f

    for i, order in enumerate((["zeta", "alpha", "mid"], ["mid", "zeta", "alpha"])):
        write_zarr_group(tmp_path / f"{i}.zarr", fill(order), made_by="test")
    texts = [(tmp_path / f"{i}.zarr" / "zarr.json").read_text() for i in range(2)]
    assert list(json.loads(texts[0])["attributes"]["checksums"]) == ["alpha", "mid", "zeta"]
    assert texts[0] == texts[1]


def test_a_blend_takes_between_one_and_every_stored_siren(tmp_path):
    """k = 1 gives the nearest stored SIREN itself; k outside 1..N is named in one line (render --blend-k), where
    the blend takes k (inverse-angle weights)."""
    from diffshadow.store import BlendSampler

    store = open_store(stored(tmp_path))
    assert np.array_equal(BlendSampler(store, 1, "inverse-angle")(LIGHTS[2] + [0, 0.01, 0]), store.weights[2])
    for k in (0, 5):
        with pytest.raises(ValueError, match=rf"^blend k: expected 1 to 4 \(the stored SIRENs\), got {k}$"):
            BlendSampler(store, k, "inverse-angle")
        # the triangle's corners take no k: a run's evaluate.blend_k past its few lights is not an error there
        assert np.array_equal(BlendSampler(store, k, "triangle")(LIGHTS[2]), store.weights[2])


def test_a_generated_stores_blend_record_is_its_mix_or_its_own_and_an_old_one_reads_as_inverse_angle(tmp_path):
    """`blend_record` finds the blend a generated store answers with where it lives: a mixed model's `mix`, a blend
    cache's own config; the model alone has none. `BlendSampler.recorded` blends as the record says, and a record
    from before `blend_weights` existed as the weighting of that time (OLD_WEIGHTING, inverse-angle)."""
    from dataclasses import replace

    from diffshadow.store import BlendSampler, blend_record

    store = open_store(stored(tmp_path))
    mix = {"blend_k": 2, "blend_weights": "triangle", "model_share": 0.5}
    assert blend_record(replace(store, config={"cache": "model", "mix": mix})) is mix
    cache = {"cache": "blend", "blend_k": 3, "blend_weights": "inverse-angle"}
    assert blend_record(replace(store, config=cache)) is cache
    assert blend_record(replace(store, config={"cache": "model"})) is None
    assert blend_record(replace(store, config=None)) is None
    light = np.array([0.48, 0.6, 0.64])
    old = BlendSampler.recorded(store, {"blend_k": 2})
    assert (old.k, old.weighting) == (2, "inverse-angle")
    assert np.array_equal(old(light), BlendSampler(store, 2, "inverse-angle")(light))
    assert not np.array_equal(BlendSampler.recorded(store, mix)(light), old(light))


def test_a_loaded_checkpoint_outlives_the_next_one_written_over_it(tmp_path):
    """load_checkpoint maps the file (a sampler reads its EMA weights, not the optimizer's moments): the state
    keeps its values when training writes the next checkpoint to the same path, and when the caller changes its
    tensors the file is not changed. A file in torch's old, unmappable format still loads."""
    import io

    import torch

    from diffshadow.artifacts import load_checkpoint
    from diffshadow.io import atomic_torch_save

    path = tmp_path / "diffusion.ckpt"

    def state(value: float) -> dict:
        return {"model": {"w": torch.full((4096,), value)}, "standardizer": {}, "layout": [], "config": {}}

    atomic_torch_save(path, state(1.0))
    first = load_checkpoint(path)
    atomic_torch_save(path, state(2.0))
    assert torch.equal(first["model"]["w"], torch.full((4096,), 1.0))
    second = load_checkpoint(path)
    second["model"]["w"].add_(1.0)
    assert torch.equal(load_checkpoint(path)["model"]["w"], torch.full((4096,), 2.0))
    buf = io.BytesIO()
    torch.save(state(3.0), buf, _use_new_zipfile_serialization=False)
    path.write_bytes(buf.getvalue())
    assert torch.equal(load_checkpoint(path)["model"]["w"], torch.full((4096,), 3.0))


def test_a_subset_files_bytes_are_its_arrays_alone(tmp_path):
    """Members stored whole, dated 1980, their local headers without zip64 fields, so that the file does not depend
    on the interpreter's zipfile (np.savez's zip64 local headers differ between CPython 3.11.2 and 3.11.7); np.load
    reads it."""
    import struct
    import zipfile

    subset(tmp_path / "a.npz", [0, 1])
    raw = (tmp_path / "a.npz").read_bytes()
    with zipfile.ZipFile(tmp_path / "a.npz") as z:
        infos = z.infolist()
    assert [i.filename for i in infos] == [f"{k}.npy" for k in
                                           ("weights", "light_index", "lights", "psnr", "psnr_visible", "meta")]
    for i in infos:
        assert (i.compress_type, i.date_time, i.flag_bits & 0x08) == (zipfile.ZIP_STORED, (1980, 1, 1, 0, 0, 0), 0)
        sig, version, _, _, _, _, _, packed, size, name_len, extra_len = struct.unpack_from("<IHHHHHIIIHH", raw,
                                                                                         i.header_offset)
        assert (sig, version, packed, size, extra_len) == (0x04034B50, 20, i.file_size, i.file_size, 0), i.filename
    back = read_subset(tmp_path / "a.npz")
    assert np.array_equal(back["light_index"], [0, 1]) and back["weights"].dtype == np.float32
    assert back["config"] == {"fit": {"steps": 3}}
    subset(tmp_path / "b.npz", [0, 1])
    assert raw == (tmp_path / "b.npz").read_bytes()


@pytest.mark.parametrize("no_room", ["ENOSPC", "EDQUOT"])
def test_a_full_disk_names_the_output_and_keeps_the_one_before(tmp_path, monkeypatch, capsys, no_room):
    """A write that finds no room (a full disk, a project's quota; on a parallel file system often only at the
    flush) raised an OSError naming no file, a traceback from the command. Each writer now names its output, the
    command says it in one line, and the output already there is the one before."""
    import errno
    import logging
    import os

    import torch

    from diffshadow import io
    from diffshadow.cli import main

    code = getattr(errno, no_room)
    real_fsync = io._fsync
    monkeypatch.setattr(logging.getLogger("asyncio"), "disabled", False)  # a failed store turns it off (io)

    def full(path):  # a temporary file or folder beside an output finds no room; the rename's folder sync does
        if "/." in str(path):
            raise OSError(code, os.strerror(code))
        real_fsync(path)

    lights, ckpt, store = tmp_path / "lights.json", tmp_path / "a.ckpt", tmp_path / "a.zarr"
    args = ["lights", "--out", str(lights), "--sphere", "400", "--count", "8", "--center", "0", "0", "1",
            "--unseen", "2"]
    main(args)
    io.atomic_torch_save(ckpt, {"step": 1})
    io.write_zarr_group(store, lambda root: root.create_array("a", data=np.arange(3)), made_by="test")
    before = {p: p.read_bytes() for p in (lights, ckpt, store / "zarr.json")}
    monkeypatch.setattr(io, "_fsync", full)

    class Filling:  # a file that takes 100 bytes, then has no room: torch.save's archive writer meets it mid-way
        def __init__(self, f):
            self.f, self.room = f, 100

        def write(self, data):
            if len(data) > self.room:
                raise OSError(code, os.strerror(code))
            self.room -= len(data)
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    real_open = open
    with monkeypatch.context() as m:  # `open` in io's namespace: the writer's file, not every file
        m.setattr(io, "open", lambda *a, **k: Filling(real_open(*a, **k)), raising=False)
        with pytest.raises(OSError) as caught:
            io.atomic_torch_save(ckpt, {"step": 2, "w": torch.zeros(1000)})
        assert caught.value.errno == code and caught.value.filename == str(ckpt)
    for write, out in ((lambda: io.atomic_torch_save(ckpt, {"step": 2}), ckpt),
                       (lambda: io.write_zarr_group(store, lambda root: root.create_array("a", data=np.arange(4)),
                                                    made_by="test"), store)):
        with pytest.raises(OSError) as caught:
            write()
        assert caught.value.errno == code and caught.value.filename == str(out)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exited:
        main([*args[:-1], "3"])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert err == (f"diffshadow lights: error: {lights}: {os.strerror(code)}: free space (or quota) there and run it "
                   f"again; no earlier output was replaced\n")
    assert {p: p.read_bytes() for p in before} == before
    assert torch.load(ckpt)["step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ckpt", "a.zarr", "lights.json"]  # no temporary left


@pytest.mark.parametrize("refused", ["EINVAL", "EIO"])
def test_a_file_system_that_will_not_flush_a_folder_still_takes_outputs(tmp_path, monkeypatch, refused):
    """Some network and shared-folder file systems (SMB, VirtualBox's shared folders, some FUSE mounts) refuse
    fsync on a folder with EINVAL: every output failed there. A folder's EINVAL is passed over (its files are
    flushed and the rename stays atomic); a file's EINVAL, and any other error, still fail the write."""
    import errno
    import os
    import stat

    from diffshadow import io

    code, real_fsync = getattr(errno, refused), os.fsync
    on_files = False

    def fsync(fd):
        if on_files or stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(code, os.strerror(code))
        real_fsync(fd)

    monkeypatch.setattr(io.os, "fsync", fsync)
    writes = {"a.json": lambda: io.atomic_write_text(tmp_path / "a.json", "{}"),
              "a.zarr": lambda: io.write_zarr_group(tmp_path / "a.zarr",
                                                    lambda root: root.create_array("a", data=np.arange(3)),
                                                    made_by="test")}
    for name, write in writes.items():
        if refused == "EINVAL":
            write()
            assert (tmp_path / name).exists()
        else:
            with pytest.raises(OSError) as caught:
                write()
            assert caught.value.errno == code
    if refused == "EINVAL":
        assert io.VerifiedGroup(tmp_path / "a.zarr", "a test store").root["a"][...].tolist() == [0, 1, 2]
        on_files = True
        with pytest.raises(OSError, match="Invalid argument"):
            io.atomic_write_text(tmp_path / "b.json", "{}")
    # with EIO the file is whole and renamed before its folder's flush fails; the store's own folders fail first
    assert sorted(p.name for p in tmp_path.iterdir()) == (["a.json", "a.zarr"] if refused == "EINVAL" else ["a.json"])


def test_a_folder_one_may_not_write_to_is_named_by_the_output_not_its_temporary(tmp_path, monkeypatch, capsys):
    """Each output is written under a random temporary name beside it; in a folder one may not write to, the
    error named that temporary ('.l.json.cje8v1u1.tmp: Operation not permitted', seen in an immutable folder). It
    names the output now, for a file, a store and a checkpoint, and the command says so in one line."""
    import errno
    import os
    import tempfile

    from diffshadow import io
    from diffshadow.cli import main

    def refused(*, prefix, dir, suffix=""):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.path.join(dir, f"{prefix}k2j3{suffix}"))

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    monkeypatch.setattr(tempfile, "mkdtemp", refused)
    for write, out in ((lambda: io.atomic_torch_save(tmp_path / "a.ckpt", {}), "a.ckpt"),
                       (lambda: io.write_zarr_group(tmp_path / "a.zarr", lambda root: None, made_by="test"), "a.zarr")):
        with pytest.raises(PermissionError) as caught:
            write()
        assert caught.value.filename == str(tmp_path / out)
    with pytest.raises(SystemExit):
        main(["lights", "--out", str(tmp_path / "l.json"), "--sphere", "400", "--count", "8", "--center", "0", "0",
              "1", "--unseen", "2"])
    assert capsys.readouterr().err == f"diffshadow lights: error: {tmp_path / 'l.json'}: {os.strerror(errno.EACCES)}\n"


def test_a_damaged_chunk_among_many_is_one_line(tmp_path):
    """zarr reads a store's chunks concurrently: when one fails, the others are left pending in its event loop,
    and Python's teardown printed each (~35 lines of "Task was destroyed but it is pending!" and a traceback after
    the error line, on the README run's weights.zarr). A failed command ends at its one line."""
    import subprocess
    import sys

    from diffshadow.store import WeightStore

    n = 256
    rng = np.random.default_rng(0)
    lights = rng.normal(size=(n, 3))
    store = WeightStore(weights=rng.normal(size=(n, LAYOUT.n_params)).astype(np.float32),
                        lights=lights / np.linalg.norm(lights, axis=1, keepdims=True), psnr=np.full(n, 40.0),
                        psnr_visible=np.full(n, 40.0), layout=LAYOUT, siren=CFG, config={})
    path = tmp_path / "weights.zarr"
    write_store(path, store, made_by="collect_weights")
    chunk = path / "weights" / "c" / "17" / "0"
    chunk.write_bytes(chunk.read_bytes()[:10])  # a cut-off copy: its codec fails before any checksum
    bad = subprocess.run([sys.executable, "-m", "diffshadow.cli", "check-store", str(path)], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr
    assert bad.stderr.startswith(f"diffshadow check-store: error: {path}: array 'weights' cannot be read (")


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_killed_writes_temporaries_are_removed_by_the_next_write(tmp_path, capsys):
    from diffshadow import io

    # a writer killed inside each kind of write (SIGKILL: no `finally` runs), as a PBS walltime or the OOM killer
    # ends one; the zarr writer is killed after moving the old store aside, before swapping the new one in
    io.write_zarr_group(tmp_path / "a.zarr", lambda root: root.create_array("a", data=np.arange(3)), made_by="test")
    killed = textwrap.dedent(f"""
        import os, signal, numpy as np
        from diffshadow import io
        with io.atomic_path({str(tmp_path / "a.json")!r}) as tmp:
            tmp.write_text("half")
            real = os.replace
            def replace(src, dst):
                if str(dst).endswith("a.zarr"):
                    os.kill(os.getpid(), signal.SIGKILL)
                real(src, dst)
            os.replace = replace
            io.write_zarr_group({str(tmp_path / "a.zarr")!r}, lambda root: root.create_array("a", data=np.arange(4)),
                                made_by="test")
        """)
    assert subprocess.run([sys.executable, "-c", killed]).returncode == -signal.SIGKILL
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))
    assert len(left) == 3 and all(".partial." in name for name in left), left  # a.json's, a.zarr's new and old
    io.atomic_write_text(tmp_path / "a.json", "whole")
    io.write_zarr_group(tmp_path / "a.zarr", lambda root: root.create_array("a", data=np.arange(5)), made_by="test")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "a.zarr"]
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 3 and all(re.fullmatch(r"removed \S+/\.a\.(json|zarr)\.partial\.\S+: an unfinished write of "
                                               r"a\.(json|zarr) \(process \d+ no longer runs\)", s) for s in said), said


def test_a_live_writers_temporary_and_other_outputs_are_kept(tmp_path, capsys):
    from diffshadow import io

    host, dead = io._host(), _dead_pid()
    kept = [f".a.npz.partial.{os.getpid()}.{host}.k2j3abcd.tmp",  # a live writer here (this process)
            f".a.npz.ckpt.partial.{dead}.{host}.k2j3abcd.pt",  # another output's (the checkpoint beside it)
            f".a.npz.{dead}.k2j3abcd.tmp",  # not named as a temporary is
            f".a.npz.partial.{dead}.elsewhere.k2j3abcd.tmp"]  # another host's, touched a moment ago
    stale = f".a.npz.partial.{dead}.elsewhere.x9y8z7w6.tmp"
    for name in kept + [stale]:
        (tmp_path / name).write_text("half")
    hours_ago = time.time() - io.STALE_AFTER_S - 60
    os.utime(tmp_path / stale, (hours_ago, hours_ago))
    io.atomic_write_text(tmp_path / "a.npz", "whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(kept + ["a.npz"])
    assert re.fullmatch(rf"removed \S+/{re.escape(stale)}: an unfinished write of a\.npz \(written on elsewhere, "
                        r"untouched for 1\.0 h\)\n", capsys.readouterr().err)


def test_a_missing_path_gets_the_existing_one_a_typo_away(tmp_path, monkeypatch):
    from diffshadow.io import did_you_mean

    (tmp_path / "results/nucleon/volume.zarr").mkdir(parents=True)
    (tmp_path / "results/nucleon/data_inr.pt").write_bytes(b"")
    near = tmp_path / "results/nucleon/volume.zarr"
    assert did_you_mean(tmp_path / "results/nucleonn/volume.zarr") == f"; did you mean {near}?"  # a folder's typo
    assert did_you_mean(tmp_path / "results/nuclon/volume.zar") == f"; did you mean {near}?"  # two names' typos
    monkeypatch.chdir(tmp_path)
    assert did_you_mean("results/nucleon/data_inr.pth") == "; did you mean results/nucleon/data_inr.pt?"
    assert did_you_mean("results/xyz/volume.zarr") == ""  # nothing near
    assert did_you_mean("results/nucleon/volume.zarr") == ""  # there: no guess
