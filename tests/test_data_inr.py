"""The data INR: it fits, it round-trips through its file, it resumes, and its macro-cell ranges hold it."""

import numpy as np
import pytest
import torch
from conftest import Killed, stop_at

from diffshadow.analytic import gaussian_blob
from diffshadow.artifacts import load_data_inr, save_data_inr
from diffshadow.config import ConfigError
from diffshadow.data_inr import ERROR_VOXELS, DataInrConfig, ErrorSampler, fit_data_inr, inr_cell_ranges, voxel_errors
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

TF = TransferFunction.from_config({"opacity": [[0, 0], [0.2, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                   "density_scale": 10})
CFG = DataInrConfig.from_config(dict(width=32, blocks=1, steps=400, points=4096, checkpoint_every=50, target_psnr=0))


@pytest.fixture(scope="module")
def blob():
    return Volume(data=gaussian_blob(17, 0.2), extent=np.ones(3), name="blob")


@pytest.fixture(scope="module")
def fitted(blob):
    return fit_data_inr(blob, TF, CFG, log=lambda m: None)


def test_fit_reaches_a_useful_psnr(fitted):
    assert fitted.psnr > 30.0
    assert 0 < fitted.max_error < 0.2


def test_file_round_trip(fitted, tmp_path, blob):
    path = tmp_path / "data_inr.pt"
    save_data_inr(path, fitted)
    back = load_data_inr(path)
    assert back.psnr == fitted.psnr and back.max_error == fitted.max_error
    pts = torch.rand(100, 3) * 2 - 1
    assert torch.equal(back.model(pts), fitted.model(pts))
    assert np.array_equal(back.cell_lo, fitted.cell_lo)


def test_resume_gives_the_same_bytes(blob, tmp_path):
    ckpt = tmp_path / "inr.ckpt"
    # a scoring of the voxels (every 30 steps) between the checkpoint resumed from and the stop: the
    # error-driven points after it must come from the checkpoint's scores
    short = DataInrConfig(**{**CFG.__dict__, "steps": 60, "checkpoint_every": 20, "error_every": 30})
    whole = fit_data_inr(blob, TF, short, log=lambda m: None)

    with pytest.raises(Killed):
        fit_data_inr(blob, TF, short, checkpoint=ckpt, log=stop_at("step 42/"))
    assert list(tmp_path.glob("inr.ckpt*"))  # one checkpoint per size tried
    messages = []
    resumed = fit_data_inr(blob, TF, short, checkpoint=ckpt, log=messages.append)
    assert any("resuming" in m and "step 40" in m for m in messages)
    assert torch.equal(resumed.model.flat(), whole.model.flat())
    assert not list(tmp_path.glob("inr.ckpt*"))


def test_cuda_graph_off_cuda_steps_eagerly_to_the_same_bytes_and_resumes_a_default_fit(blob, tmp_path):
    """`data_inr.cuda_graph` on a CPU: "auto" (the default) steps eagerly; True says that the fit steps eagerly and
    gives the same bytes; the fingerprint holds what was done (no graph), so a default fit's checkpoint resumes
    under True, and the INR records `cuda_graph: False`."""
    from dataclasses import replace

    short = DataInrConfig(**{**CFG.__dict__, "steps": 60, "checkpoint_every": 20, "error_every": 30})
    assert short.cuda_graph == "auto"
    whole = fit_data_inr(blob, TF, short, log=lambda m: None)

    with pytest.raises(Killed):
        fit_data_inr(blob, TF, short, checkpoint=tmp_path / "inr.ckpt", log=stop_at("step 42/"))
    messages = []
    graphed = fit_data_inr(blob, TF, replace(short, cuda_graph=True), checkpoint=tmp_path / "inr.ckpt",
                           log=messages.append)
    assert "data_inr.cuda_graph: CUDA graphs need a CUDA device; stepping eagerly on cpu" in messages
    assert any("resuming" in m and "step 40" in m for m in messages)
    assert torch.equal(graphed.model.flat(), whole.model.flat())
    assert graphed.config["cuda_graph"] is False


def test_cell_ranges_bound_the_inr(fitted, blob):
    lo, hi = inr_cell_ranges(fitted.model, blob, cell=4, margin=0.0)
    # random points inside cell (0, 0, 0) stay within its range up to the lattice's resolution
    p = torch.rand(2000, 3) * (4 / 16)
    with torch.no_grad():
        v = fitted.model(p * 2 - 1)
    assert float(v.min()) >= lo[0, 0, 0] - 0.02 and float(v.max()) <= hi[0, 0, 0] + 0.02


def test_bad_file_is_named(tmp_path):
    bad = tmp_path / "x.pt"
    torch.save({"weights": torch.zeros(3)}, bad)
    with pytest.raises(ValueError, match="x.pt: not a data INR"):
        load_data_inr(bad)
    with pytest.raises(ValueError, match="missing.pt: no such file; expected a data INR file"):
        load_data_inr(tmp_path / "missing.pt")


class ZeroInr(torch.nn.Module):
    """An INR that answers 0 everywhere: its error at each voxel is the voxel's value."""

    def forward(self, x):
        return torch.zeros(len(x))


def test_error_sampler_lattice_stays_within_its_budget():
    small = ErrorSampler(Volume(data=np.zeros((64, 64, 64), np.float32), extent=np.ones(3), name="s"), every=10)
    assert small.stride == 1 and len(small.lattice) == 64 ** 3 == ERROR_VOXELS
    big = ErrorSampler(Volume(data=np.zeros((103, 94, 161), np.float32), extent=np.ones(3), name="b"), every=10)
    assert big.stride == 2 and len(big.lattice) == 52 * 47 * 81 <= ERROR_VOXELS


def test_error_sampler_draws_where_the_inr_is_wrong():
    """One voxel wrong by 1, every other exact: that voxel's block gets (1 + f)/(1 + N f) ≈ 1/1.1 of the
    points, f = 0.1/N being the floor each voxel gets."""
    data = np.zeros((9, 9, 9), np.float32)
    data[4, 2, 6] = 1.0  # (z, y, x)
    vol = Volume(data=data, extent=np.full(3, 8.0), name="spike")
    sampler = ErrorSampler(vol, every=10)

    sampler.score(ZeroInr(), torch.device("cpu"))
    pts = sampler.sample(20000, torch.Generator().manual_seed(0))
    near = (pts - torch.tensor([6.0, 2.0, 4.0])).abs().max(dim=1).values <= 0.5
    n = data.size
    expected = (1 + 0.1 / n) / 1.1
    assert abs(float(near.float().mean()) - expected) < 0.01
    assert float(pts.min()) >= 0 and float(pts.max()) <= 8.0


def test_an_inr_exact_everywhere_still_gets_points_over_the_whole_box():
    vol = Volume(data=np.zeros((5, 6, 7), np.float32), extent=np.array([1.0, 0.8, 0.6]), name="empty")
    sampler = ErrorSampler(vol, every=10)

    sampler.score(ZeroInr(), torch.device("cpu"))
    pts = sampler.sample(5000, torch.Generator().manual_seed(0))
    assert torch.isfinite(pts).all()
    assert (pts.min(dim=0).values < 0.05).all() and (pts.max(dim=0).values > torch.tensor([0.95, 0.75, 0.55])).all()


def test_error_points_fit_a_sharp_edge_better():
    """A cube with a hard edge (0 to 1 between neighbouring voxels), the same steps: points drawn where the INR
    errs raise the voxel PSNR."""
    data = np.zeros((17, 17, 17), np.float32)
    data[5:12, 5:12, 5:12] = 1.0
    cube = Volume(data=data, extent=np.ones(3), name="cube")
    plain = DataInrConfig(**{**CFG.__dict__, "steps": 300, "points": 512, "visible_fraction": 0.5,
                             "error_fraction": 0.0})
    hard = DataInrConfig(**{**plain.__dict__, "visible_fraction": 0.25, "error_fraction": 0.5, "error_every": 50})
    a = fit_data_inr(cube, TF, plain, log=lambda m: None)
    b = fit_data_inr(cube, TF, hard, log=lambda m: None)
    assert b.psnr > a.psnr + 1.0, (a.psnr, b.psnr)


def test_visible_and_error_shares_over_one_is_one_line():
    with pytest.raises(ConfigError, match=r"visible_fraction \(0.6\) \+ error_fraction \(0.5\) must be at most 1"):
        DataInrConfig.from_config({"visible_fraction": 0.6, "error_fraction": 0.5})


def test_macro_cell_ranges_made_a_slab_at_a_time_are_those_of_the_whole_lattice(monkeypatch):
    """inr_cell_ranges reduces each slab of macro-cells as soon as its lattice planes are evaluated (only a slab is
    held): with one-cell slabs, the same ranges as one slab over the whole lattice (the same chunks of points: a
    SIREN's products may round otherwise in other batch sizes), which are each cell's min and max of the INR at its
    lattice points (against the lattice made whole)."""
    from diffshadow import data_inr
    from diffshadow.grid import cell_ranges
    from diffshadow.siren import Siren, SirenConfig, box_to_siren

    rng = np.random.default_rng(7)
    vol = Volume(data=rng.uniform(0, 1, (19, 12, 26)).astype(np.float32), extent=np.array([1.3, 0.6, 0.9]),
                 name="r")
    model = Siren(SirenConfig(16, 1), torch.Generator().manual_seed(0))
    whole = data_inr.inr_cell_ranges(model, vol, cell=4, refine=2, margin=0.0, chunk=101)
    axes = [torch.linspace(0, float(e), (n - 1) * 2 + 1) for e, n in zip(vol.extent[::-1], vol.data.shape, strict=True)]
    zz, yy, xx = torch.meshgrid(*axes, indexing="ij")
    with torch.no_grad():
        lattice = model(box_to_siren(torch.stack([xx, yy, zz], -1).reshape(-1, 3), torch.as_tensor(
            vol.extent, dtype=torch.float32))).view(zz.shape)
    lo, hi = cell_ranges(lattice, 8)
    assert np.allclose(whole[0], lo.numpy(), atol=1e-6) and np.allclose(whole[1], hi.numpy(), atol=1e-6)
    monkeypatch.setattr(data_inr, "RANGE_SLAB_POINTS", 1)
    sliced = data_inr.inr_cell_ranges(model, vol, cell=4, refine=2, margin=0.0, chunk=101)
    assert all(np.array_equal(a, b) for a, b in zip(whole, sliced, strict=True))


def test_lattice_points_are_voxel_points_rows_made_alone():
    """voxel_errors and inr_cell_ranges walk a lattice a chunk at a time: the chunk's points are exactly those rows
    of the whole lattice (`voxel_points`), so the INR sees the same inputs in the same batches."""
    from diffshadow.grid import lattice_points, lattice_points_at, voxel_points

    vol = Volume(data=np.zeros((7, 5, 9), np.float32), extent=np.array([1.3, 0.6, 0.9]), name="r")
    axes = [torch.linspace(0, float(e), n) for e, n in zip(vol.extent[::-1], vol.data.shape, strict=True)]
    whole = voxel_points(vol)
    for start, stop in ((0, len(whole)), (5, 301), (44, 45)):
        assert torch.equal(lattice_points(axes, start, stop), whole[start:stop])
    index = torch.randperm(len(whole), generator=torch.Generator().manual_seed(0))[:50]
    assert torch.equal(lattice_points_at(axes, index), whole[index])


def test_the_macro_cell_ranges_are_made_once_for_the_size_kept(blob, monkeypatch):
    """A capacity climb fits several sizes; only the kept one's ranges are made (8 INR evaluations a voxel: on a
    512³ volume ~13 min a rung), and they are the ranges of the INR kept."""
    from dataclasses import replace

    from diffshadow import data_inr as module

    made, real = [], module.inr_cell_ranges

    def counted(model, volume, **kwargs):
        made.append(model.layout.n_params)
        return real(model, volume, **kwargs)

    monkeypatch.setattr(module, "inr_cell_ranges", counted)
    cfg = replace(CFG, steps=20, width=8, max_width=16, target_psnr=99.0)  # unreachable: every rung is tried
    inr = fit_data_inr(blob, TF, cfg, log=lambda m: None)
    assert len(inr.config["capacity"]["rungs"]) == 2 and made == [inr.n_params]
    lo, hi = real(inr.model, blob)
    assert np.array_equal(inr.cell_lo, lo) and np.array_equal(inr.cell_hi, hi)


def test_a_long_lattice_walk_says_how_far_it_is_and_gives_the_same_values(monkeypatch):
    """voxel_errors and inr_cell_ranges log their progress (here at every chunk) and return what they return
    without a log."""
    import diffshadow.progress as progress
    from diffshadow.siren import Siren, SirenConfig

    vol = Volume(data=np.random.default_rng(0).random((20, 18, 17), dtype=np.float32), extent=np.ones(3), name="r")
    model = Siren(SirenConfig(8, 1))
    quiet = voxel_errors(model, vol, chunk=512), inr_cell_ranges(model, vol, cell=4, chunk=512)
    monkeypatch.setattr(progress, "TICK_S", 0.0)
    said = []
    told = voxel_errors(model, vol, chunk=512, log=said.append), inr_cell_ranges(model, vol, cell=4, chunk=512,
                                                                                  log=said.append)
    assert told[0] == quiet[0] and all(np.array_equal(a, b) for a, b in zip(told[1], quiet[1], strict=True))
    errors = [m for m in said if m.startswith("data INR: voxel PSNR (6,120 points): ")]
    ranges = [m for m in said if m.startswith("data INR: the renderer's macro-cell ranges (45,045 points): ")]
    # a line before each chunk of 512 points: the voxels' 20 x 18 x 17, the ranges' lattice twice as fine (39 x 35 x 33)
    assert len(errors) == 12 and len(ranges) == 88 and len(said) == len(errors) + len(ranges)
    assert errors[1].startswith("data INR: voxel PSNR (6,120 points): 8%, ")  # 512 of 6,120 points done
