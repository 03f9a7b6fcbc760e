import h5py
import numpy as np
import pytest
import zarr

from diffshadow.volume import VolumeError, bundled_path, load_volume, run_path


def test_raw_name_gives_dims_and_dtype(tmp_path):
    data = np.arange(4 * 3 * 2, dtype=np.uint16).reshape(2, 3, 4)  # (Z, Y, X) for X=4, Y=3, Z=2
    path = tmp_path / "thing_4x3x2_uint16.raw"
    data.astype("<u2").tofile(path)
    vol = load_volume(path)
    assert vol.data.shape == (2, 3, 4) and vol.data.dtype == np.float32
    assert vol.dims == (4, 3, 2)
    np.testing.assert_allclose(vol.data, data / data.max(), atol=1e-7)
    np.testing.assert_allclose(vol.extent, [1.0, 2 / 3, 1 / 3])  # (n - 1) spacing, longest side 1
    assert vol.name == "thing"


def test_npy_h5_zarr_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.uniform(-3, 5, size=(5, 6, 7)).astype(np.float32)
    expected = (data - data.min()) / (data.max() - data.min())
    np.save(tmp_path / "v.npy", data)
    with h5py.File(tmp_path / "v.h5", "w") as f:
        f["group/density"] = data
        f["other"] = data[0]
    root = zarr.open_group(str(tmp_path / "v.zarr"), mode="w")
    root.create_array("density", data=data)
    for vol in (load_volume(tmp_path / "v.npy"), load_volume(tmp_path / "v.h5", key="group/density"),
                load_volume(tmp_path / "v.zarr", key="density"), load_volume(tmp_path / "v.zarr")):
        np.testing.assert_allclose(vol.data, expected, atol=1e-6)
        assert vol.data.min() == 0.0 and vol.data.max() == 1.0


def test_an_hdf5_file_behind_a_lock_is_named_or_read_where_locks_are_missing(tmp_path, monkeypatch):
    """HDF5 locks a file as it opens it. A file another process holds for writing was refused as 'not an HDF5
    file'; it is now named as such. On a file system without locks (errno 38, ENOSYS: some Lustre and NFS
    mounts, where every open fails) the input is read without one, the same values."""
    import errno
    import subprocess
    import sys

    data = np.arange(27, dtype=np.float32).reshape(3, 3, 3)
    with h5py.File(tmp_path / "v.h5", "w") as f:
        f.create_dataset("d", data=data)
    holder = subprocess.Popen([sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'a'); "
                               "print('open', flush=True); time.sleep(60)", str(tmp_path / "v.h5")],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        with pytest.raises(VolumeError, match=r"^\S*v\.h5: open for writing in another process \(HDF5's file lock\); "
                                              r"read it once that process has closed the file$"):
            load_volume(tmp_path / "v.h5")
    finally:
        holder.kill()
        holder.wait()
    real_file, opened = h5py.File, []

    def no_locks(path, mode="r", **kw):  # what h5py raises where the file system has no locks
        opened.append(kw.get("locking"))
        if kw.get("locking") is not False:
            raise OSError(errno.ENOSYS, "Unable to synchronously open file (unable to lock file, errno = 38, error "
                                        "message = 'Function not implemented')")
        return real_file(path, mode, **kw)

    reference = load_volume(tmp_path / "v.h5").data
    with monkeypatch.context() as m:
        m.setattr(h5py, "File", no_locks)
        assert np.array_equal(load_volume(tmp_path / "v.h5").data, reference)
    assert opened == [None, False]
    (tmp_path / "not.h5").write_bytes(b"plain bytes")
    with pytest.raises(VolumeError, match=r"not\.h5: not an HDF5 file"):
        load_volume(tmp_path / "not.h5")


def test_given_range_and_spacing(tmp_path):
    np.save(tmp_path / "v.npy", np.full((3, 3, 3), 5.0))
    np.save(tmp_path / "w.npy", np.linspace(0, 20, 27).reshape(3, 3, 3))
    vol = load_volume(tmp_path / "w.npy", value_range=(0, 10), spacing=(1, 1, 4))
    assert vol.data.max() == 1.0 and vol.data.min() == 0.0
    np.testing.assert_allclose(vol.extent, [0.25, 0.25, 1.0])


def test_constant_volume_warns_and_is_zero(tmp_path):
    np.save(tmp_path / "c.npy", np.full((3, 4, 5), 7.0))
    with pytest.warns(UserWarning, match="constant"):
        vol = load_volume(tmp_path / "c.npy")
    assert not vol.data.any()


def test_bundled_nucleon():
    vol = load_volume(bundled_path("nucleon"))
    assert vol.data.shape == (41, 41, 41) and vol.name == "nucleon"
    assert load_volume("bundled:nucleon").data.shape == (41, 41, 41)


def test_run_path_moves_with_the_run(tmp_path):
    # a volume inside the run's directory is named relative to it (so a moved checkout plans nothing again);
    # one outside, or a relative path as written, is left as it is
    run = tmp_path / "checkout"
    (run / "data").mkdir(parents=True)
    inside = run / "data" / "v.npy"
    assert run_path(str(inside), run) == "data/v.npy"
    assert run_path(str(tmp_path / "elsewhere.npy"), run) == str(tmp_path / "elsewhere.npy")
    assert run_path("data/v.npy", run) == "data/v.npy"
    (tmp_path / "link").symlink_to(run)  # the run entered through a symlink: the same file, still relative
    assert run_path(str(inside), tmp_path / "link") == "data/v.npy"
    package = bundled_path("nucleon")
    assert run_path("bundled:nucleon", package.parent.parent) == f"data/{package.name}"


def test_size_mismatch_names_both_numbers(tmp_path):
    path = tmp_path / "bad_4x4x4_uint8.raw"
    path.write_bytes(b"\0" * 60)
    with pytest.raises(VolumeError, match=r"bad_4x4x4_uint8.raw.*60 bytes.*64 bytes"):
        load_volume(path)


def test_raw_without_dims(tmp_path):
    path = tmp_path / "nodims.raw"
    path.write_bytes(b"\0" * 8)
    # what to write, in a scene file's words (it said "no dims= given", a Python keyword no user types)
    with pytest.raises(VolumeError, match=r"nodims.raw.*no dims are given \(a scene file's load: \{dims: \[X, Y, Z\]"):
        load_volume(path)
    with pytest.raises(VolumeError, match=r"nodims.raw: cannot tell the dtype.*\(a scene file's load: "
                                          r"\{dtype: \.\.\.\}, one of .*uint8"):
        load_volume(path, dims=(2, 2, 2))
    with pytest.warns(UserWarning, match="constant"):  # the file is all zeros
        assert load_volume(path, dims=(2, 2, 2), dtype="uint8").data.shape == (2, 2, 2)


def test_unsupported_dtype(tmp_path):
    path = tmp_path / "v_2x2x2_complex64.raw"
    path.write_bytes(b"\0" * 64)
    with pytest.raises(VolumeError, match=r"v_2x2x2_complex64.raw.*unsupported dtype 'complex64'"):
        load_volume(path)


def test_nan_voxels_counted_with_first_position(tmp_path):
    data = np.zeros((4, 5, 6), dtype=np.float32)
    data[3, 1, 2] = np.nan  # (z, y, x)
    data[3, 4, 5] = np.inf
    np.save(tmp_path / "n.npy", data)
    with pytest.raises(VolumeError, match=r"n.npy: 2 NaN/Inf voxels; first at \(x, y, z\) = \(2, 1, 3\)"):
        load_volume(tmp_path / "n.npy")


@pytest.mark.parametrize("dtype", ["uint8", "int16", "int64", "float16", "float32", "float64"])
def test_normalising_a_slab_at_a_time_gives_the_whole_volumes_bytes(monkeypatch, dtype):
    """The volume is normalised a few z-planes at a time (a 512³ volume's float64 copy and its temporaries were
    4.4 GiB at once): for any slab height, the bytes of the whole array's float64 formula, and the same NaN count
    and first position; the value range found without a float64 copy is the float64 one."""
    from pathlib import Path

    import diffshadow.volume as V

    rng = np.random.default_rng(7)
    for trial in range(12):
        shape = tuple(int(n) for n in rng.integers(2, 13, 3))
        if dtype.startswith("float"):
            raw = (rng.standard_normal(shape) * (1e4 if dtype != "float64" else 1e300)).astype(dtype)
        else:
            info = np.iinfo(dtype)
            raw = rng.integers(info.min // 2, info.max // 2, shape, dtype=dtype)
        value_range = None if trial % 3 else (float(raw.min()) / 2 - 1, float(raw.max()) / 2 + 1)
        data = raw.astype(np.float64)  # the whole array's formula
        lo, hi = value_range or (float(data.min()), float(data.max()))
        scale = max(abs(lo), abs(hi))
        expected = np.clip((data / scale - lo / scale) / (hi / scale - lo / scale), 0, 1).astype(np.float32)
        monkeypatch.setattr(V, "SLAB_VOXELS", int(rng.integers(1, 400)))
        got = V._to_volume(Path("v.raw"), raw, value_range, None).data
        assert got.dtype == np.float32 and got.tobytes() == expected.tobytes(), (dtype, trial)
        if dtype.startswith("float"):
            raw[-1, 0, 1] = np.nan  # in the last slab, after an infinity in another
            raw[shape[0] // 2, 1, 0] = np.inf
            with pytest.raises(VolumeError, match=rf"v.raw: 2 NaN/Inf voxels; first at \(x, y, z\) = "
                                                  rf"\(0, 1, {shape[0] // 2}\)"):
                V._to_volume(Path("v.raw"), raw, None, None)


def test_missing_keys_list_those_present(tmp_path):
    with h5py.File(tmp_path / "v.h5", "w") as f:
        f["a"] = np.zeros((2, 2, 2))
        f["b"] = np.zeros((2, 2, 2))
    with pytest.raises(VolumeError, match=r"v.h5: no dataset 'c'; present: \['a', 'b'\]"):
        load_volume(tmp_path / "v.h5", key="c")
    # which to write, in a scene file's words (it said "give key=", a Python keyword)
    with pytest.raises(VolumeError, match=r"v.h5: 2 datasets \(a, b\); say which is the volume with a scene "
                                          r"file's load: \{key: a\}$"):
        load_volume(tmp_path / "v.h5")
    with h5py.File(tmp_path / "empty.h5", "w"):
        pass
    with pytest.raises(VolumeError, match=r"empty.h5: no dataset in it; expected a 3-D one"):  # was "present: []"
        load_volume(tmp_path / "empty.h5")
    root = zarr.open_group(str(tmp_path / "v.zarr"), mode="w")
    root.create_array("x", data=np.zeros((2, 2, 2)))
    with pytest.raises(VolumeError, match=r"v.zarr: no array 'y'; present: \['x'\]"):
        load_volume(tmp_path / "v.zarr", key="y")
    root.create_array("z", data=np.zeros((2, 2, 2)))
    with pytest.raises(VolumeError, match=r"v.zarr: 2 arrays \(x, z\); say which is the volume with a scene "
                                          r"file's load: \{key: x\}$"):
        load_volume(tmp_path / "v.zarr")


def test_not_3d(tmp_path):
    np.save(tmp_path / "flat.npy", np.zeros((4, 4)))
    with pytest.raises(VolumeError, match=r"flat.npy: expected a 3-D array, got shape \(4, 4\)"):
        load_volume(tmp_path / "flat.npy")


def test_a_file_that_is_not_its_format_says_so(tmp_path):
    """A file of other bytes named .npy, and a folder named .zarr that is no store: named as what they are not, not
    in NumPy's words about pickles or zarr's about a StorePath."""
    (tmp_path / "v.npy").write_bytes(b"\x00" * 256)
    with pytest.raises(VolumeError, match=r"v.npy: not a \.npy file \(it does not begin with NumPy's header; write "
                                          r"it with numpy.save\)$"):
        load_volume(tmp_path / "v.npy")
    (tmp_path / "v.zarr").mkdir()
    (tmp_path / "v.zarr" / "notes.txt").write_text("x")
    with pytest.raises(VolumeError, match=r"v.zarr: not a Zarr store \(no Zarr group or array metadata in it\)$"):
        load_volume(tmp_path / "v.zarr")


def test_missing_file_and_unknown_suffix(tmp_path):
    with pytest.raises(VolumeError, match="no such file"):
        load_volume(tmp_path / "nothing.npy")
    (tmp_path / "v.vtk").write_text("x")
    with pytest.raises(VolumeError, match=r"v.vtk: unsupported file type"):
        load_volume(tmp_path / "v.vtk")


def test_shared_volumes_load(shared_data):
    vol = load_volume(shared_data / "tooth_103x94x161_uint8.raw")
    assert vol.data.shape == (161, 94, 103)
    assert vol.extent[2] == 1.0
    bi = load_volume(shared_data / "bi2o3_ch0_80x80x80_float32.raw")
    assert bi.data.max() == 1.0


def test_the_extinction_field_id_follows_what_a_shadow_depends_on():
    """A shadow depends on the grid's values, its box, the opacity and density_scale, not on the TF's colours: the id
    changes with each of the first four alone, not with the colours, and is the same for an equal volume and TF."""
    from dataclasses import replace

    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import Volume, extinction_id

    rng = np.random.default_rng(0)
    data = rng.uniform(0, 1, (5, 6, 7)).astype(np.float32)
    volume = Volume(data=data, extent=np.array([1.0, 5 / 6, 4 / 6]), name="v")
    tf = {"opacity": [[0, 0], [1, 0.8]], "color": [[0, 1, 1, 1], [1, 1, 0, 0]], "density_scale": 10.0}
    base = extinction_id(volume, TransferFunction.from_config(tf))
    assert len(base) == 16 and base == extinction_id(Volume(data.copy(), volume.extent.copy(), "other name"),
                                                     TransferFunction.from_config(dict(tf)))
    assert base == extinction_id(volume, TransferFunction.from_config({**tf, "color": [[0, 0, 0, 1], [1, 0, 1, 0]]}))
    nudged = data.copy()
    nudged[2, 3, 4] = np.nextafter(nudged[2, 3, 4], np.float32(2))
    changed = [replace(volume, data=nudged), replace(volume, extent=volume.extent * [1, 1, 0.5])]
    ids = [extinction_id(v, TransferFunction.from_config(tf)) for v in changed]
    ids += [extinction_id(volume, TransferFunction.from_config({**tf, **change}))
            for change in ({"opacity": [[0, 0], [1, 0.81]]}, {"density_scale": 10.5})]
    assert len({base, *ids}) == 5, ids


def test_a_scene_that_can_show_nothing_is_refused_and_one_that_can_is_not(tmp_path):
    """A TF under which no ray can gather one 8-bit level of opacity is refused (it failed at render_targets, after
    stage 1's fits): for any grid at plan time, for the grid's own values and box by `scene_volume`. The test is an
    upper bound: on a grid opaque everywhere (the worst case), a TF refused at 0.99 x the density it names draws no
    pixel of even 1/255 in a view along the box's diagonal, while at 2.5 x the diagonal rays show; at 1.01 x it is
    accepted."""
    from diffshadow.render import Camera, RenderScene
    from diffshadow.transfer import FOREGROUND_ALPHA, TransferFunction, TransferFunctionError
    from diffshadow.volume import scene_volume

    rng = np.random.default_rng(1)
    np.save(tmp_path / "v.npy", rng.uniform(0.5, 1.0, (9, 12, 16)).astype(np.float32))
    opaque = {"opacity": [[0, 1], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]]}
    volume, _ = scene_volume({"volume": str(tmp_path / "v.npy"), "transfer_function": {**opaque, "density_scale": 1}})

    def tf(density: float) -> TransferFunction:
        return TransferFunction.from_config({**opaque, "density_scale": density})

    with pytest.raises(TransferFunctionError) as refused:
        tf(1e-6).require_visible("scene v", values=(0, 1), extent=volume.extent)
    message = str(refused.value)
    assert "\n" not in message and message.startswith("scene v: transfer function: nothing can show: ")
    need = float(message.rsplit("raise density_scale above ", 1)[1])
    with pytest.raises(TransferFunctionError, match="nothing can show"):
        tf(0.99 * need).require_visible("scene v", values=(0, 1), extent=volume.extent)
    tf(1.01 * need).require_visible("scene v", values=(0, 1), extent=volume.extent)
    diagonal = Camera.look_at(volume.extent * 2.0, volume.extent / 2, up=(0, 0, 1), fov=40.0, size=48)
    for factor, shows in ((0.99, False), (2.5, True)):
        alpha = RenderScene(volume, tf(factor * need)).render("noshadow", diagonal, step=0.25).alpha
        assert bool((alpha >= FOREGROUND_ALPHA).any()) == shows, (factor, float(alpha.max()))
    # a longer box can show what this one cannot: the bound for any grid (its largest box) passes it
    tf(0.99 * need).require_visible("scene v")
    with pytest.raises(TransferFunctionError, match=f"scene {tmp_path / 'v.npy'}: transfer function: nothing can"):
        scene_volume({"volume": str(tmp_path / "v.npy"), "transfer_function": {**opaque, "density_scale": 1e-6}})
    zero_here = {"opacity": [[0, 1], [0.4, 1], [0.5, 0], [1, 0]], "color": opaque["color"], "density_scale": 1e3}
    np.save(tmp_path / "v.npy", np.linspace(0.6, 1.0, 27, dtype=np.float32).reshape(3, 3, 3))
    with pytest.raises(TransferFunctionError, match=r"opacity is 0 over all of the grid's values \(0.6 to 1,"):
        scene_volume({"volume": str(tmp_path / "v.npy"), "transfer_function": zero_here,
                      "load": {"value_range": [0, 1]}})


def test_a_prepared_volume_knows_the_extinction_field_it_was_made_from(tmp_path):
    """`prepared_from`: the store holds the scene's field while the volume file (unchanged since), its load keys, the
    opacity and density_scale are as the scene has them; the TF's colours may differ. Anything else, a store that
    does not say what it was made from, or none at all, counts as changed (the workflow then reruns as for any
    changed input)."""
    import os

    from diffshadow.stages.stage1 import prepare_volume
    from diffshadow.volume import prepared_from, save_prepared, scene_volume

    np.save(tmp_path / "v.npy", np.linspace(0, 1, 4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6))
    tf = {"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 20}
    scene = {"volume": str(tmp_path / "v.npy"), "transfer_function": tf}
    store = tmp_path / "volume.zarr"
    assert not prepared_from(store, scene)  # none yet
    prepare_volume(store, scene)
    assert prepared_from(store, scene)
    assert prepared_from(store, {**scene, "transfer_function": {**tf, "color": [[0, 1, 0, 0], [1, 0, 0, 1]]}})
    for changed in ({**scene, "transfer_function": {**tf, "opacity": [[0, 0], [1, 0.9]]}},
                    {**scene, "transfer_function": {**tf, "density_scale": 21}},
                    {**scene, "load": {"value_range": [0, 2]}}):
        assert not prepared_from(store, changed), changed
    written = os.stat(store / "zarr.json").st_mtime_ns
    os.utime(tmp_path / "v.npy", ns=(written, written))  # not after the store: the same file
    assert prepared_from(store, scene)
    os.utime(tmp_path / "v.npy", ns=(written, written + 1_000_000_000))  # replaced in place after it
    assert not prepared_from(store, scene)
    prepare_volume(tmp_path / "again.zarr", scene)  # the file's time is not recorded: two clones, the same bytes
    assert (tmp_path / "again.zarr" / "zarr.json").read_bytes() == (store / "zarr.json").read_bytes()
    save_prepared(store, *scene_volume(scene))  # a store from before it recorded its source
    assert not prepared_from(store, scene)


def test_a_prepared_volumes_checksum_is_its_grids_without_hashing_it_again(tmp_path, monkeypatch):
    """`load_prepared` verifies the grid's sha256 as it reads it; `Volume.checksum` (what the caches' extinction id
    hashes) takes that one: the same value as hashing the grid, and no second hash (0.76 s at 512³)."""
    import diffshadow.volume as volume_module
    from diffshadow.io import array_checksum
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import Volume, load_prepared, save_prepared

    data = np.random.default_rng(2).random((4, 5, 6), dtype=np.float32)
    tf = TransferFunction.from_config({"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": 5.0})
    save_prepared(tmp_path / "v.zarr", Volume(data, np.array([1.0, 0.8, 0.6]), "v"), tf)
    volume, _ = load_prepared(tmp_path / "v.zarr")
    monkeypatch.setattr(volume_module, "array_checksum", lambda *_: pytest.fail("the grid was hashed again"))
    assert volume.checksum == array_checksum(data)
