"""Ground-truth shadows: an analytic case, convergence, invariances, extremes and bad input."""

import functools
import re
import warnings

import numpy as np
import pytest
import torch
from conftest import Asker, cores, default_device_meta, identity_tf

from diffshadow import shadow as shadow_module
from diffshadow import volume as volume_module
from diffshadow.analytic import BLOB_DENSITY as K
from diffshadow.analytic import BLOB_SIGMA as SIGMA
from diffshadow.analytic import blob_cases, blob_transmittance, gaussian_blob
from diffshadow.grid import Interrupted, voxel_points
from diffshadow.lights import LightError
from diffshadow.shadow import (
    AUTO_SKIP_FRACTION,
    ShadowField,
    seen_voxels,
    shadow_grid,
    transmittance,
    transmittance_per_light,
)
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume, load_volume, refine


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    path = tmp_path_factory.mktemp("blob") / "blob.npy"
    np.save(path, gaussian_blob(65, SIGMA))
    return load_volume(path)


def errors(blob, step):
    field = ShadowField.build(blob, identity_tf(K))
    errs = []
    for w, pts in blob_cases():
        got = transmittance(field, field.tf, w, pts, step=step).numpy()
        errs.extend(abs(float(g) - blob_transmittance(p, w)) for g, p in zip(got, pts, strict=True))
    return np.asarray(errs)


def test_analytic_gaussian_at_default_step(blob):
    err = errors(blob, step=0.5)
    assert len(err) == 1000
    assert err.max() <= 3e-3 and err.mean() <= 5e-4, (err.max(), err.mean())


def test_the_shadow_benchs_closed_form_check_scores_every_point_as_marched_one_light_at_a_time(blob):
    """`bench shadow` marches the blob's directions in groups: the same 1,000 errors as one direction at a time."""
    from diffshadow.bench.shadow import bench_analytic

    err = errors(blob, step=1.0)
    got = bench_analytic(steps=(1.0,))[1.0]
    assert got == {"max_err": float(err.max()), "mean_err": pytest.approx(float(err.mean()), rel=1e-12),
                   "points": 1000}


def test_converges_as_step_halves(blob):
    """Midpoint rule: the change between successive halvings shrinks about 4x (second order)."""
    field = ShadowField.build(blob, identity_tf(K))
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 1, size=(300, 3))
    w = np.array([0.3, -0.5, 0.8])
    g = [transmittance(field, field.tf, w, pts, step=s).double() for s in (2.0, 1.0, 0.5, 0.25)]
    diffs = [float((a - b).abs().max()) for a, b in zip(g, g[1:], strict=False)]
    assert diffs[0] > diffs[1] > diffs[2]
    assert diffs[0] / diffs[1] > 2.5 and diffs[1] / diffs[2] > 2.5


def test_sweep_agrees_with_march(blob):
    tf = identity_tf(K)
    field = ShadowField.build(blob, tf)
    idx = torch.randint(0, 65, (3000, 3), generator=torch.Generator().manual_seed(1))  # (z, y, x)
    pts = idx.flip(1).float() / 64
    for w in [(1, 0, 0), (0.3, -0.5, 0.8), (-1, -1, 1)]:
        ref = transmittance(field, tf, w, pts, step=0.25)
        sweep = shadow_grid(blob, tf, w, method="sweep")[idx[:, 0], idx[:, 1], idx[:, 2]]
        err = (sweep - ref).abs()
        assert err.max() < 5e-3 and err.mean() < 5e-4, (w, err.max(), err.mean())


def test_sweep_exit_faces_are_unshadowed(blob):
    g = shadow_grid(blob, identity_tf(100.0), (0.3, -0.5, 0.8), method="sweep")
    assert torch.equal(g[:, :, -1], torch.ones_like(g[:, :, -1]))  # +x face
    assert torch.equal(g[:, 0, :], torch.ones_like(g[:, 0, :]))  # -y face
    assert torch.equal(g[-1], torch.ones_like(g[-1]))  # +z face
    assert g[:, :, 0].min() < 0.5  # the face the light enters through is shadowed


@pytest.mark.parametrize("cell", [1, 2, 8, 16])
def test_skipping_changes_nothing(cell):
    rng = np.random.default_rng(2)
    data = np.zeros((30, 26, 23), np.float32)
    data[5:12, 14:20, 3:9] = rng.uniform(0.3, 1, size=(7, 6, 6))  # sparse blocks in an empty volume
    data[20:26, 4:9, 12:20] = rng.uniform(0.3, 1, size=(6, 5, 8))
    from diffshadow.volume import Volume
    vol = Volume(data=data, extent=np.array([22, 25, 29]) / 29, name="blocks")
    tf = TransferFunction.from_config({"opacity": [[0, 0], [0.2, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": 30})
    field = ShadowField.build(vol, tf, cell=cell)
    assert 0.3 < field.empty.float().mean() < 1.0
    voxels = voxel_points(vol)
    for w in [(0.2, 0.9, -0.3), (-1, 0, 0), (0.5, 0.5, 0.7)]:
        a = transmittance(field, tf, w, voxels, skip_empty=True)
        b = transmittance(field, tf, w, voxels, skip_empty=False)
        assert (a - b).abs().max() <= 1e-6
        assert a.min() < 0.5  # the blocks do cast shadows here


@pytest.mark.parametrize("cell", [3, 6, -8, 8.0, True])
def test_a_macro_cell_is_a_power_of_two_of_voxels(blob, cell):
    # the march finds a sample's cell by a true division, exact only by a power of two
    with pytest.raises(ValueError, match=rf"cell: expected 0 \(no skipping\) or a power of two of voxels, got "
                                         rf"{re.escape(repr(cell))}"):
        ShadowField.build(blob, identity_tf(), cell=cell)


def test_chunking_and_samples_per_iteration_do_not_matter(blob):
    tf = identity_tf(K)
    pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(0))
    w = (0.1, 0.7, -0.2)
    base = transmittance(blob, tf, w, pts)
    for chunk, spi in [(64, 1), (1000, 8), (37, 3)]:
        torch.testing.assert_close(transmittance(blob, tf, w, pts, chunk=chunk, samples_per_iter=spi), base,
                                   atol=1e-6, rtol=0)
    # each ray is marched alone, whatever rays share its chunk: no chunk (a CPU's, a GPU's, 37 rays) changes a bit
    for chunk in (shadow_module.CHUNK, shadow_module.CPU_CHUNK, 1000, 37 * 4):
        for skip in (False, True):
            assert torch.equal(transmittance(blob, tf, w, pts, chunk=chunk, skip_empty=skip),
                               transmittance(blob, tf, w, pts, skip_empty=skip)), (chunk, skip)


def test_a_march_is_given_up_when_its_interrupt_says_so_and_is_the_same_values_when_it_does_not(blob):
    """`interrupt` (the viewer leaving a light) is asked before every iteration of every chunk; a march it never
    stops gives the same values, and once it says stop the march ends with `Interrupted` without asking again."""
    tf = identity_tf(K)
    pts = voxel_points(blob)[::7]
    w = (0.1, 0.7, -0.2)
    chunks = -(-len(pts) // 1000)  # `chunk` counts samples: 4 a ray per iteration
    plain, never = transmittance(blob, tf, w, pts, chunk=4000), Asker()
    assert torch.equal(transmittance(blob, tf, w, pts, chunk=4000, interrupt=never), plain)
    assert never.asked > 10 * chunks, (never.asked, chunks)  # several iterations a chunk, each asked
    whole = Asker()  # shadow_grid's march passes it on
    asked = shadow_grid(blob, tf, w, method="march", interrupt=whole)
    assert torch.equal(asked, shadow_grid(blob, tf, w, method="march"))
    for stop_at in (1, whole.asked // 2):
        stop = Asker(stop_at)
        with pytest.raises(Interrupted):
            shadow_grid(blob, tf, w, method="march", interrupt=stop)
        assert stop.asked == stop_at


@pytest.mark.parametrize("skip", [False, True, None])
def test_a_march_reads_the_host_once_an_iteration_and_three_times_skipping(blob, skip):
    """On a GPU every boolean mask and scalar read waits for the device: an iteration of the march reads the host
    for its live rays, and skipping empty cells for its occupied samples and the rays that jump (seven to eleven
    reads before the rows were gathered by index); the trilinear lookup reads none. A call reads it twice more (the
    points' finiteness, the rays that start live): the step's length and the share of empty cells (`skip_empty`
    None) are the field's host numbers, not read at each call. Nor does an iteration build a tensor from host
    numbers, a copy a GPU waits for: the march builds a few per call, not two per iteration."""
    from diffshadow.bench.profile import op_counts
    from diffshadow.grid import trilinear
    from diffshadow.volume import Volume

    data = np.where(blob.data > 0.05, blob.data, 0).astype(np.float32)  # empty cells around the blob to jump
    vol = Volume(data=data, extent=blob.extent, name="sparse blob")
    field = ShadowField.build(vol, identity_tf(K))
    assert bool(field.empty.any()) and not bool(field.empty.all())
    pts = voxel_points(vol)[::5]
    asker = Asker()
    march = functools.partial(transmittance, field, field.tf, (0.3, -0.5, 0.8), pts, skip_empty=skip)
    march()  # the first call on a grid shape builds its lattice's constants, once (`grid.lattice`)
    counts = op_counts(lambda: march(interrupt=asker))
    skipping = field.empty_share >= AUTO_SKIP_FRACTION if skip is None else skip
    assert skip is not None or skipping  # the auto choice skips on this grid
    assert asker.asked > 10 and counts["syncs"] <= (3 if skipping else 1) * asker.asked + 2, (asker.asked, counts)
    assert counts["host_tensors"] <= 4, (asker.asked, counts)
    lookup = op_counts(lambda: trilinear(field.scalar[0], pts / field.voxel_size))
    assert lookup["syncs"] == 0 and lookup["host_tensors"] == 0, lookup


def test_empty_volume_is_exactly_one(blob):
    from diffshadow.volume import Volume
    vol = Volume(data=np.zeros((9, 9, 9), np.float32), extent=np.ones(3), name="empty")
    pts = torch.rand(100, 3)
    assert torch.equal(transmittance(vol, identity_tf(K), (0, 0, 1), pts), torch.ones(100))
    for method in ("march", "sweep"):
        assert torch.equal(shadow_grid(vol, identity_tf(K), (0.3, 0.1, 1), method=method), torch.ones(9, 9, 9))
    # and a zero density scale makes any volume transparent
    pts = torch.rand(2000, 3)
    assert torch.equal(transmittance(blob, identity_tf(0.0), (1, 2, 3), pts), torch.ones(2000))


def test_huge_density_is_zero_without_nan_or_warnings(blob, tmp_path):
    np.save(tmp_path / "small.npy", gaussian_blob(33, SIGMA))
    small = load_volume(tmp_path / "small.npy")
    tf = identity_tf(1e6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        centre = transmittance(blob, tf, (0, 0, 1), [[0.5, 0.5, 0.5], [0.5, 0.5, 0.1]])
        grids = [shadow_grid(small, tf, (0.3, -0.2, 1), method=m) for m in ("march", "sweep")]
    assert centre.max() < 1e-12
    for g in grids:
        assert torch.isfinite(g).all() and g.min() >= 0 and g.max() <= 1
        assert g[16, 16, 16] < 1e-12


@pytest.mark.parametrize("w", [(1, 0, 0), (-1, 0, 0), (0, -1, 0), (0, 0, -1), (1e-7, 1, 0),
                               (1, 1e-9, -1e-9), (-0.3, -0.4, -0.5), (0.0, -0.0, 1.0)])
def test_axis_grazing_and_negative_directions(blob, w):
    tf = identity_tf(K)
    pts = np.array([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.0, 0.5], [0.2, 0.7, 1.0]])
    got = transmittance(blob, tf, w, pts).numpy()
    wn = np.asarray(w, float) / np.linalg.norm(w)
    for g, p in zip(got, pts, strict=True):
        assert abs(g - blob_transmittance(p, wn)) < 3e-3
    grid = shadow_grid(blob, tf, w, method="sweep")
    assert torch.isfinite(grid).all() and 0 <= grid.min() and grid.max() <= 1


def test_points_outside_the_box_march_from_where_they_enter(blob):
    tf = identity_tf(K)
    w = np.array([0.0, 0.0, 1.0])
    outside = transmittance(blob, tf, w, [[0.5, 0.5, -0.3], [1.5, 0.5, 0.5], [0.5, 0.5, 1.2]])
    inside = transmittance(blob, tf, w, [[0.5, 0.5, 0.0]])
    assert outside[0] == pytest.approx(float(inside[0]), abs=1e-6)
    assert outside[1] == 1.0 and outside[2] == 1.0  # misses the box / beyond it toward the light


@pytest.mark.parametrize("w, message", [((0, 0, 0), "must be non-zero"), ((np.nan, 0, 1), "must be finite"),
                                        ((0, np.inf, 1), "must be finite"), ((1, 2), "expected 3 numbers")])
def test_bad_light_direction(blob, w, message):
    with pytest.raises(LightError, match=f"light_dir: .*{message}|light_dir: {message}"):
        transmittance(blob, identity_tf(), w, [[0.5, 0.5, 0.5]])
    with pytest.raises(LightError, match=message):
        shadow_grid(blob, identity_tf(), w, method="sweep")


def test_bad_step_method_and_points(blob):
    tf = identity_tf()
    with pytest.raises(ValueError, match="step: expected a positive number"):
        transmittance(blob, tf, (0, 0, 1), [[0.5, 0.5, 0.5]], step=0)
    # a step that would march for hours, refused at once (the finest taken is 2^-10 voxel)
    with pytest.raises(ValueError, match=r"step: 1e-09 voxels is finer than the finest step marched"):
        transmittance(blob, tf, (0, 0, 1), [[0.5, 0.5, 0.5]], step=1e-9)
    assert transmittance(blob, tf, (0, 0, 1), [[0.5, 0.5, 0.5]], step=2.0 ** -10).shape == (1,)
    # one sample a ray at most, taken past the ray's far end and clamped to the grid's face: refused, as the
    # renderer refuses it, by both marches and the march of a whole grid
    diagonal = float(np.linalg.norm(blob.extent) / np.min(blob.voxel_size))
    for march in (functools.partial(transmittance, blob, tf, (0, 0, 1), [[0.5, 0.5, 0.5]]),
                  functools.partial(transmittance_per_light, blob, tf, [(0, 0, 1)], [[0.5, 0.5, 0.5]]),
                  functools.partial(shadow_grid, blob, tf, (0, 0, 1), method="march")):
        with pytest.raises(ValueError, match=r"step: [\d.]+ voxels is longer than the volume.s diagonal \(\d+ voxels"):
            march(step=diagonal * 1.01)
    assert transmittance(blob, tf, (0, 0, 1), [[0.5, 0.5, 0.5]], step=diagonal * 0.99).shape == (1,)
    with pytest.raises(ValueError, match="sweep needs 1/k voxels"):
        shadow_grid(blob, tf, (0, 0, 1), method="sweep", step=0.3)
    with pytest.raises(ValueError, match="method: expected 'march' or 'sweep'"):
        shadow_grid(blob, tf, (0, 0, 1), method="raytrace")
    with pytest.raises(ValueError, match=r"points: expected shape \(P, 3\)"):
        transmittance(blob, tf, (0, 0, 1), [0.5, 0.5, 0.5])


@pytest.mark.parametrize("factor", [1, 2])
@pytest.mark.parametrize("dot", [(2, 3, 4), (0, 0, 0), (5, 6, 7), (0, 6, 3)])
def test_the_seen_voxels_of_one_visible_voxel_are_the_corners_of_its_cells(factor, dot):
    """A single voxel where μ > 0 makes the (up to) 8 unit cells it is a corner of visible; their corners, on the
    volume refined `factor` times, are the (2·factor + 1)³ block around it, cut by the volume's faces."""
    data = np.zeros((6, 7, 8), np.float32)
    data[dot] = 1.0
    seen = seen_voxels(Volume(data=data, extent=np.ones(3), name="dot"), identity_tf(), factor)
    expect = torch.zeros([(n - 1) * factor + 1 for n in data.shape], dtype=torch.bool)
    expect[tuple(slice(max(0, (d - 1) * factor), (d + 1) * factor + 1) for d in dot)] = True
    assert seen.dtype == torch.bool and torch.equal(seen, expect)


def test_a_march_of_the_seen_voxels_alone_is_the_full_marchs_there_and_one_elsewhere(monkeypatch):
    blob = Volume(data=gaussian_blob(33, SIGMA), extent=np.ones(3), name="blob")
    tf = TransferFunction.from_config({"opacity": [[0.0, 0.0], [0.2, 0.0], [1.0, 0.8]], "density_scale": 25.0,
                                       "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]]})
    w = (0.3, -0.5, 0.8)
    for factor in (1, 2):
        fine = refine(blob, factor)
        seen = seen_voxels(blob, tf, factor)
        assert 0.01 < float(seen.float().mean()) < 0.5  # the blob's corners are empty under this TF
        full = shadow_grid(fine, tf, w, method="march")
        part = shadow_grid(fine, tf, w, method="march", voxels=seen)
        assert torch.equal(part[seen], full[seen]) and (part[~seen] == 1).all()
        # marched a slab of planes at a time (their coordinates made for the slab alone): the same bits
        with monkeypatch.context() as m:
            m.setattr(volume_module, "SLAB_VOXELS", 4099)
            assert torch.equal(shadow_grid(fine, tf, w, method="march"), full)
            assert torch.equal(shadow_grid(fine, tf, w, method="march", voxels=seen), part)
    with pytest.raises(ValueError, match=r"voxels: expected a bool mask of shape \(33, 33, 33\), got torch.float32"):
        shadow_grid(blob, tf, w, method="march", voxels=seen.float())
    with pytest.raises(TypeError, match=r"shadow_grid\(method='sweep'\) takes no \['voxels'\]"):
        shadow_grid(blob, tf, w, voxels=seen_voxels(blob, tf))


LIGHTS = np.array([[0.2, 0.3, 0.9], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [-0.5, 0.7, 0.1], [0.3, -0.2, -0.9]])


@pytest.mark.parametrize("rays_per_march", [1 << 21, 96])
def test_lights_marched_together_equal_light_by_light(blob, monkeypatch, rays_per_march):
    """Same bytes as one `transmittance` per light, at each light's own points and at shared points, in one
    group or split into groups (96 rays: two lights per group), with points outside the box too."""
    monkeypatch.setattr(shadow_module, "RAYS_PER_MARCH", rays_per_march)
    field = ShadowField.build(blob, identity_tf(K))
    pts = torch.rand(len(LIGHTS), 40, 3, generator=torch.Generator().manual_seed(0)) * 1.4 - 0.2
    one_by_one = torch.stack([transmittance(field, field.tf, w, p) for w, p in zip(LIGHTS, pts, strict=True)])
    assert torch.equal(transmittance_per_light(field, field.tf, LIGHTS, pts), one_by_one)
    shared = torch.stack([transmittance(field, field.tf, w, pts[0]) for w in LIGHTS])
    assert torch.equal(transmittance_per_light(field, field.tf, LIGHTS, pts[0].numpy()), shared)
    assert transmittance_per_light(field, field.tf, np.zeros((0, 3)), pts[0]).shape == (0, 40)
    with default_device_meta():  # tensors made where they are used (the CUDA path's guard)
        assert torch.equal(transmittance_per_light(field, field.tf, LIGHTS, pts), one_by_one)


def test_lights_marched_together_reject_bad_input(blob):
    tf = identity_tf()
    with pytest.raises(LightError, match=r"lights\[1\]: .*non-zero"):
        transmittance_per_light(blob, tf, [[0, 0, 1], [0, 0, 0]], [[0.5, 0.5, 0.5]])
    with pytest.raises(LightError, match=r"lights: expected \(L, 3\) directions"):
        transmittance_per_light(blob, tf, [[0, 0, 1, 0, 1]], [[0.5, 0.5, 0.5]])
    with pytest.raises(ValueError, match=r"points: expected one set per light \(2\), got 3"):
        transmittance_per_light(blob, tf, [[0, 0, 1], [0, 1, 0]], np.full((3, 4, 3), 0.5))
    with pytest.raises(ValueError, match="step: expected a positive number"):
        transmittance_per_light(blob, tf, [[0, 0, 1]], [[0.5, 0.5, 0.5]], step=-1)


SAME_BYTES = """
import hashlib, sys
import numpy as np
import torch
from diffshadow.analytic import gaussian_blob
from diffshadow.shadow import shadow_grid
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume
vol = Volume(data=gaussian_blob(33, 0.15), extent=np.ones(3), name="blob")
tf = TransferFunction.from_config({"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                   "density_scale": 10.0})
grid = shadow_grid(vol, tf, (0.2, 0.3, 0.9), method=sys.argv[1]).numpy()
np.save(sys.argv[2], grid)  # kept for the failure message: which voxels differ, and by how much
try:  # the CPU this process ran on (a virtual machine may move between hosts): model, microcode, its flags' hash
    info = {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in
                                              open("/proc/cpuinfo").read().split("\\n\\n")[0].splitlines()
                                              if ":" in line)}
    cpu = "|".join([info.get("model name", "?"), info.get("microcode", "?"),
                    hashlib.sha256(info.get("flags", "").encode()).hexdigest()[:8]]).replace(" ", "_")
except OSError:
    cpu = "unknown"
print(hashlib.sha256(grid.tobytes()).hexdigest(), torch.get_num_threads(), torch.backends.cpu.get_cpu_capability(),
      "input=" + hashlib.sha256(vol.data.tobytes()).hexdigest()[:12], cpu)
"""


@pytest.mark.parametrize("method", ["sweep", "march"])
def test_same_input_same_bytes_in_separate_processes(method, tmp_path):
    """Two fresh processes (a new allocator, new thread pools each), one with a single thread: the same bytes.
    It failed once in a whole-suite run on a loaded machine and never again in over 250 reruns, so a mismatch says
    what differed: each process's threads, vector unit, input volume and CPU (model, microcode, flags), and the
    voxels apart."""
    import os
    import subprocess
    import sys

    # a thread per core in the first, named (a pytest-xdist worker's processes get their share: tests/conftest.py)
    n = str(cores())
    done = [subprocess.run([sys.executable, "-c", SAME_BYTES, method, str(tmp_path / f"{i}.npy")],
                           capture_output=True, text=True, check=True, env={**os.environ, **env})
            for i, env in enumerate(({"OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n},
                                     {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}))]
    runs = [d.stdout.split() for d in done]
    assert len(runs[0][0]) == 64
    if runs[0][0] != runs[1][0]:
        a, b = np.load(tmp_path / "0.npy"), np.load(tmp_path / "1.npy")
        apart = np.argwhere(a != b)
        first = tuple(int(i) for i in apart[0])
        # PyTorch falls back to its scalar kernels, other bytes, where cpuinfo fails to start: it says so on stderr
        said = [d.stderr.strip()[-300:] or "nothing" for d in done]
        pytest.fail(f"{method}: processes (threads, vector unit, input, CPU) {runs[0][1:]} and {runs[1][1:]} differ at "
                    f"{len(apart)} of {a.size} voxels, by at most {np.abs(a - b).max():.3g}; first at (z, y, x) = "
                    f"{first}: {float(a[first])!r} against {float(b[first])!r}; on stderr they said {said}")


@pytest.mark.parametrize("method", ["sweep", "march"])
def test_shadow_bytes_do_not_depend_on_the_thread_count(method):
    """torch splits an op's work by its thread count, not by the cores there are, so one to four threads on any
    machine cover the splits that other machines' defaults make: the same bytes from each, in two light octants."""
    from diffshadow.volume import Volume

    vol = Volume(data=gaussian_blob(33, 0.15), extent=np.ones(3), name="blob")
    before = torch.get_num_threads()
    try:
        for light in ((0.2, 0.3, 0.9), (-0.7, 0.1, -0.3)):
            grids = []
            for threads in (1, 2, 3, 4):
                torch.set_num_threads(threads)
                grids.append(shadow_grid(vol, identity_tf(), light, method=method))
            assert all(torch.equal(g, grids[0]) for g in grids[1:]), f"{method}, light {light}"
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("shape", [(1, 3, 4), (7, 5, 6), (40, 2, 3)])
def test_sequential_cumsum_is_the_cpus_cumsum_bit_for_bit(shape):
    """The sweep's cumsum under the determinism switch on CUDA (where torch refuses a floating-point cumsum):
    slices summed one after another give the CPU cumsum's bits, so the switch changes no result there."""
    from diffshadow.shadow import _cumsum_slices, _sequential_cumsum

    x = torch.randn(*shape, generator=torch.Generator().manual_seed(0)) * 1e3
    assert torch.equal(_sequential_cumsum(x), torch.cumsum(x, 0))
    assert torch.equal(_cumsum_slices(x), torch.cumsum(x, 0))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(blob):
    tf = identity_tf()
    for method in ("march", "sweep"):
        cpu = shadow_grid(blob, tf, (0.2, 0.3, 0.9), method=method)
        gpu = shadow_grid(blob, tf, (0.2, 0.3, 0.9), method=method, device="cuda").cpu()
        assert (cpu - gpu).abs().max() < 1e-5


def test_check_points_hold_the_exact_shadow_of_the_checked_lights(blob):
    """The held-out points that measure the geometry stage's seen-light gap: uniform in the box, the same draw
    every time, and the analytic shadow of exactly the lights check_rows picks."""
    from diffshadow.truth import check_points, check_rows
    rng = np.random.default_rng(3)
    lights = rng.normal(size=(70, 3))
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    pts, values = check_points(blob, identity_tf(K), lights, 64, seed=0)
    rows = check_rows(70)
    assert len(rows) == 64 and rows[0] == 0 and rows[-1] == 69 and values.shape == (64, 64)
    assert ((pts >= 0) & (pts <= torch.as_tensor(blob.extent))).all()
    for i in (0, 33, 63):
        exact = [blob_transmittance(p, lights[rows[i]]) for p in pts.numpy() / blob.extent]
        assert np.abs(values[i].numpy() - exact).max() <= 3e-3
    again = check_points(blob, identity_tf(K), lights, 64, seed=0)
    assert torch.equal(again[0], pts) and torch.equal(again[1], values)


@pytest.mark.parametrize("w", [(0.3, -0.5, 0.8), (-1.0, 0.2, 0.1), (0.0, 1.0, 0.0)])
def test_a_sweep_looked_up_a_few_samples_at_a_time_gives_the_same_bits(monkeypatch, w):
    """The sweep bounds its memory by sampling μ a few slices at a time, by reading each block's line depths as it
    sums them, and by finding the empty cells a slab at a time (grid.MACRO_CELLS_PER_PASS): each sample, depth and
    cell is its own, so the smallest passes give the bits of one pass, on a sparse volume (lines past the occupied
    slices) and a light from below (its slices swept in reverse)."""
    from diffshadow import grid as grid_module

    rng = np.random.default_rng(3)
    data = np.zeros((21, 18, 25), np.float32)
    data[4:15, 2:16, 5:20] = rng.uniform(0, 1, (11, 14, 15))
    vol = Volume(data=data, extent=np.array([25, 18, 21]) / 25, name="sparse")
    tf = identity_tf(20.0)
    whole = shadow_grid(vol, tf, w, method="sweep", step=0.5)
    monkeypatch.setattr(shadow_module, "SWEEP_SAMPLES_PER_CALL", 1)
    monkeypatch.setattr(grid_module, "MACRO_CELLS_PER_PASS", 1)
    assert torch.equal(shadow_grid(vol, tf, w, method="sweep", step=0.5), whole)
    assert whole.min() < 0.5 and whole.max() == 1.0


def test_a_volumes_sweeps_find_its_occupied_box_once_and_turn_it_for_each_light(monkeypatch):
    """The sweeps of one volume and TF find the box of its occupied cells once, in the volume's own axes, and
    turn it for each light (axes permuted, the dominant one flipped where the light comes from its far end). The
    box only spares work: a sweep over the whole volume draws the same grid to float32 rounding, for lights along
    every axis both ways and oblique ones, so a box turned wrongly (cutting off occupied cells) would show.
    Another TF, or another volume with the same values, finds its own."""
    from diffshadow import grid as grid_module

    found = []
    real = grid_module.occupied_bounds
    monkeypatch.setattr(shadow_module, "occupied_bounds", lambda s, tf: found.append(tuple(s.shape)) or real(s, tf))
    rng = np.random.default_rng(5)
    data = np.zeros((19, 23, 27), np.float32)
    data[3:9, 12:20, 2:11] = rng.uniform(0, 1, (6, 8, 9))  # off centre: a box flipped or swapped misses it
    vol = Volume(data=data, extent=np.array([27, 23, 19]) / 27, name="corner")
    tf = identity_tf(20.0)
    lights = [tuple(v) for v in np.eye(3)] + [tuple(-v) for v in np.eye(3)] + [(0.3, -0.5, 0.8), (-0.7, 0.6, -0.2)]
    grids = [shadow_grid(vol, tf, w, method="sweep") for w in lights]
    assert found == [data.shape]
    with monkeypatch.context() as m:  # every sweep over the whole volume
        m.setattr(shadow_module, "_occupied_box", lambda volume, tf, s: [(0, n - 1) for n in s.shape])
        for w, grid in zip(lights, grids, strict=True):
            whole = shadow_grid(vol, tf, w, method="sweep")
            # the lines' coordinates start at the box, so a few bits differ: a box turned wrongly differs by ~1
            assert float((grid - whole).abs().max()) <= 1e-5 and grid.min() < 0.1, w
    found.clear()
    shadow_grid(vol, identity_tf(5.0), lights[0], method="sweep")
    shadow_grid(Volume(data=data.copy(), extent=vol.extent, name="copy"), tf, lights[0], method="sweep")
    assert len(found) == 2


def test_empty_cells_found_a_slab_at_a_time_are_those_found_at_once(monkeypatch):
    from diffshadow import grid as grid_module

    rng = np.random.default_rng(4)
    scalar = torch.as_tensor(rng.uniform(0, 1, (37, 20, 23)).astype(np.float32) ** 4)
    tf = TransferFunction.from_config({"opacity": [[0, 0], [0.5, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": 5.0})
    whole = {cell: grid_module.macro_cells(scalar, tf, cell) for cell in (1, 3, 16)}
    monkeypatch.setattr(grid_module, "MACRO_CELLS_PER_PASS", 1)
    assert 0 < whole[1].sum() < whole[1].numel()  # some cells empty, some not
    for cell, cells in whole.items():
        assert torch.equal(grid_module.macro_cells(scalar, tf, cell), cells), cell



def test_the_occupied_cells_box_read_from_coarse_cells_is_the_unit_cells_box():
    """`grid.occupied_bounds` reads coarse cells first and unit cells only in the first and last occupied coarse
    slab of each axis: the box is the one the whole unit-cell mask gives, for dense, sparse, single-voxel and empty
    volumes of any shape (coarse cells cut at the edges), under ramps, narrow spikes (a coarse cell spanning a spike
    that none of its unit cells would, were the union not one interval), steps and random TFs."""
    from diffshadow.grid import macro_cells, occupied_bounds

    def box(scalar, tf):
        occupied = ~macro_cells(scalar, tf, 1)
        if not occupied.any():
            return None
        return [(int(h[0]), int(h[-1]) + 1) for h in (torch.nonzero(occupied.any(dim=[a for a in range(3) if a != x]))
                                                     .flatten() for x in range(3))]

    rng = np.random.default_rng(5)
    tfs = [[[0, 0], [0.1, 0], [1, 1]], [[0, 0], [0.49, 0], [0.5, 1], [0.51, 0], [1, 0]],
           [[0, 0], [128 / 255, 0], [128 / 255, 0.8], [1, 0.8]],
           [[0, 0], [0.2, 0.5], [0.4, 0], [0.7, 0], [0.9, 1], [1, 0]]]
    kinds, partial = set(), 0
    for case in range(240):
        shape = tuple(int(n) for n in rng.integers(1, 30, 3))
        data = [rng.random(shape), (rng.random(shape) < 0.01) * rng.random(shape),
                np.round(rng.random(shape) * 255) / 255 * (rng.random(shape) < 0.05), np.zeros(shape)][case % 4]
        if case % 4 == 3 and case % 8 == 3:
            data[tuple(int(rng.integers(0, n)) for n in shape)] = 0.5
        scalar = torch.as_tensor(data, dtype=torch.float32)
        tf = TransferFunction.from_config({"opacity": tfs[case % 5 % 4] if case % 5 < 4 else
                                           [[0, 0], *sorted(rng.random((4, 2)).tolist()), [1, 0]],
                                           "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 10.0})
        expected = box(scalar, tf)
        for coarse in (2, 3, 8):
            assert occupied_bounds(scalar, tf, coarse) == expected, (case, shape, coarse)
        kinds.add(expected is None)
        partial += expected is not None and expected != [(0, max(1, n - 1)) for n in shape]
    assert kinds == {True, False} and partial > 40

def test_the_shadow_bench_marches_a_large_volume_at_every_kth_row(tmp_path, monkeypatch):
    """Past `MARCHED_VOXELS` the bench marches whole rows of voxels, every k-th, about that many, and scales their
    seconds to the grid; its errors are those of the whole grids read at those voxels, and it says how many."""
    from diffshadow.bench import shadow as bench

    assert bench.marched_voxels((10, 10, 10), 1000) is None
    mask = bench.marched_voxels((20, 16, 24), 1000)  # 320 rows of 24: every 8th, 40 rows, 960 voxels
    rows = mask.view(-1, 24)
    assert int(mask.sum()) == 960 and bool(rows.all(1).sum() == 40) and not (rows.any(1) & ~rows.all(1)).any()
    rng = np.random.default_rng(6)
    data = np.zeros((20, 16, 24), np.float32)
    data[3:17, 2:14, 4:20] = rng.uniform(0.2, 1, (14, 12, 16))
    np.save(tmp_path / "v.npy", data)
    monkeypatch.setattr(bench, "MARCHED_VOXELS", 1000)
    monkeypatch.setattr(bench, "bench_analytic", lambda: {})
    out = bench.bench_shadow([tmp_path / "v.npy"], tmp_path / "out", march_steps=(0.5,), sweep_steps=(1.0,))
    got = out["volumes"]["v"]
    assert (got["marched_voxels"], got["voxels"]) == (960, 20 * 16 * 24)
    vol, tf = load_volume(tmp_path / "v.npy"), TransferFunction.from_config(bench.BENCH_TF)
    ref = shadow_grid(vol, tf, bench.BENCH_LIGHT, method="march", step=bench.REFERENCE_STEP)[mask]
    sweep = shadow_grid(vol, tf, bench.BENCH_LIGHT, method="sweep")[mask]
    row = next(r for r in got["rows"] if r["method"] == "sweep")
    assert row["max_err"] == float((sweep - ref).abs().max()) > 0


def test_a_grid_that_cannot_fit_the_hosts_free_memory_is_refused_before_it_is_made(tmp_path, monkeypatch):
    """Linux's out-of-memory killer ends a job without a word; so a sweep (and a refined volume) that cannot fit
    the host's free memory (MemAvailable) is refused first, in one line with its sizes (a MemoryError, which the
    CLI turns into its out-of-memory line naming the keys to lower). With the room, the same grid as before."""
    from diffshadow import hpc
    from diffshadow import volume as volume_module

    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       32000 kB\nMemFree:         1000 kB\nMemAvailable:    2048 kB\n")
    no_cgroup = tmp_path / "no-cgroup"  # this machine's own cgroup limit, if any, kept out
    assert hpc.free_host_bytes(meminfo, no_cgroup) == 2048 * 1024
    assert hpc.free_host_bytes(tmp_path / "missing", no_cgroup) is None
    vol = Volume(data=gaussian_blob(20, SIGMA), extent=np.ones(3), name="blob")
    free = {"bytes": 10**12}
    monkeypatch.setattr(hpc, "free_host_bytes", lambda: free["bytes"])
    monkeypatch.setattr(hpc, "CHECKED_FROM_BYTES", 0)
    light = [0.3, 0.5, 0.81]
    before = shadow_grid(vol, identity_tf(), light)
    least = shadow_module.SWEEP_GRIDS_AT_LEAST
    free["bytes"] = int(least * 4 * 20**3) - 1  # one byte short of SWEEP_GRIDS_AT_LEAST grids
    with pytest.raises(MemoryError, match=rf"^the sweep of a 20x20x20 shadow grid \({least:g} x its 0.0 GiB\) needs "
                                          r"at least 0.0 GiB, and 0.0 GiB are free on this host$"):
        shadow_grid(vol, identity_tf(), light)
    free["bytes"] += 1
    assert torch.equal(shadow_grid(vol, identity_tf(), light), before)
    # the refined volume: its one grid
    free["bytes"] = 4 * 17**3 - 1
    small = Volume(data=np.zeros((9, 9, 9), np.float32), extent=np.ones(3), name="zeros")
    with pytest.raises(MemoryError, match=r"^the volume refined 2 times \(17x17x17 voxels\) needs at least"):
        volume_module.refine(small, 2)
    free["bytes"] += 1
    assert volume_module.refine(small, 2).data.shape == (17, 17, 17)
    # under CHECKED_FROM_BYTES (64 MiB), nothing is asked
    monkeypatch.undo()
    monkeypatch.setattr(hpc, "free_host_bytes", lambda: 0)
    assert torch.equal(shadow_grid(vol, identity_tf(), light), before)
