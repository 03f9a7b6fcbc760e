"""The data INR: it fits, it round-trips through its file, it resumes, and its macro-cell ranges hold it."""

import numpy as np
import pytest
import torch

from diffshadow.analytic import gaussian_blob
from diffshadow.artifacts import load_data_inr, save_data_inr
from diffshadow.data_inr import DataInrConfig, fit_data_inr, inr_cell_ranges
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
    short = DataInrConfig(**{**CFG.__dict__, "steps": 60, "checkpoint_every": 20})
    whole = fit_data_inr(blob, TF, short, log=lambda m: None)

    class Stop(Exception):
        pass

    def stop_at_40(msg):
        if msg.startswith("step 42/"):
            raise Stop

    with pytest.raises(Stop):
        fit_data_inr(blob, TF, short, checkpoint=ckpt, log=stop_at_40)
    assert list(tmp_path.glob("inr.ckpt*"))  # one checkpoint per size tried
    messages = []
    resumed = fit_data_inr(blob, TF, short, checkpoint=ckpt, log=messages.append)
    assert any("resuming" in m and "step 40" in m for m in messages)
    assert torch.equal(resumed.model.flat(), whole.model.flat())
    assert not list(tmp_path.glob("inr.ckpt*"))


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
    with pytest.raises(ValueError, match="no such data INR"):
        load_data_inr(tmp_path / "missing.pt")
