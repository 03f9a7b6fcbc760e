import pytest
import torch

from diffshadow.siren import BatchedSiren, Siren, SirenConfig, WeightLayout, box_to_siren, init_siren


@pytest.mark.parametrize("cfg", [SirenConfig(16, 0), SirenConfig(32, 2), SirenConfig(24, 3)])
def test_batched_equals_separate_sirens(cfg):
    gen = torch.Generator().manual_seed(0)
    layout = WeightLayout.for_siren(cfg)
    weights = torch.stack([layout.flatten(init_siren(cfg, gen)) for _ in range(5)])
    x = torch.rand(5, 300, 3, generator=gen) * 2 - 1
    batched = BatchedSiren(weights, layout, cfg.blocks)(x)
    for i in range(5):
        single = Siren.from_flat(weights[i], layout)(x[i])
        assert (batched[i] - single).abs().max() <= 1e-5


def test_siren_is_the_textbook_formula():
    """ω0 and the residual weight are applied to the weights (cheaper than to the activations); the function
    must stay sin(ω0 (W h + b)) with NeurComp's residual averaging, here written out in float64."""
    from diffshadow.siren import OMEGA, RES_WEIGHT

    cfg = SirenConfig(16, 2)
    gen = torch.Generator().manual_seed(3)
    p = {k: v.double() for k, v in init_siren(cfg, gen).items()}
    x = (torch.rand(200, 3, generator=gen) * 2 - 1).double()

    def lin(name, h):
        return h @ p[f"{name}.weight"].T + p[f"{name}.bias"]

    h = torch.sin(OMEGA * lin("first", x))
    for i in range(cfg.blocks):
        inner = torch.sin(OMEGA * lin(f"blocks.{i}.l1", RES_WEIGHT * h))
        h = RES_WEIGHT * (h + torch.sin(OMEGA * lin(f"blocks.{i}.l2", inner)))
    expected = 0.5 * lin("last", h).squeeze(-1) + 0.5
    layout = WeightLayout.for_siren(cfg)
    got = Siren.from_flat(layout.flatten({k: v.float() for k, v in p.items()}), layout)(x.float())
    assert (got.double() - expected).abs().max() < 2e-5


def test_layout_round_trip_and_order():
    cfg = SirenConfig(8, 2)
    layout = WeightLayout.for_siren(cfg)
    assert [n for n, _ in layout.entries][:2] == ["first.weight", "first.bias"]
    assert layout.n_params == 8 * 3 + 8 + 2 * 2 * (8 * 8 + 8) + 8 + 1
    flat = torch.randn(4, layout.n_params)
    assert torch.equal(layout.flatten(layout.unflatten(flat)), flat)
    assert WeightLayout.from_config(layout.to_config()) == layout
    model = Siren.from_flat(flat[2], layout)
    assert torch.equal(model.flat(), flat[2])


def test_gradients_reach_the_flat_vector():
    cfg = SirenConfig(8, 1)
    layout = WeightLayout.for_siren(cfg)
    w = layout.flatten(init_siren(cfg)).expand(3, -1).clone().requires_grad_(True)
    BatchedSiren(w, layout, 1)(torch.rand(3, 10, 3)).sum().backward()
    assert w.grad is not None and torch.isfinite(w.grad).all() and (w.grad.abs().sum(1) > 0).all()


def test_bad_shapes_are_named():
    cfg = SirenConfig(8, 1)
    layout = WeightLayout.for_siren(cfg)
    with pytest.raises(ValueError, match=f"weight vector has 5 values, layout needs {layout.n_params}"):
        layout.unflatten(torch.zeros(5))
    with pytest.raises(ValueError, match=r"points must be \(K=2, N, 3\)"):
        BatchedSiren(torch.zeros(2, layout.n_params), layout, 1)(torch.zeros(3, 4, 3))
    with pytest.raises(ValueError, match="layout does not match"):
        Siren.from_flat(torch.zeros(layout.n_params), layout, SirenConfig(16, 1))


def test_box_to_siren_maps_box_corners_to_unit_cube():
    extent = torch.tensor([1.0, 0.5, 0.25])
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.5, 0.25], [0.5, 0.25, 0.125]])
    torch.testing.assert_close(box_to_siren(pts, extent), torch.tensor([[-1.0] * 3, [1.0] * 3, [0.0] * 3]))


def test_cosine_lr_decays_and_scales_down_above_lr_width():
    from types import SimpleNamespace

    from diffshadow.siren import LR_WIDTH, cosine_lr

    cfg = SimpleNamespace(lr=1e-3, lr_final=0.01, steps=100)
    assert cosine_lr(0, cfg, LR_WIDTH) == pytest.approx(1e-3)
    assert cosine_lr(100, cfg, LR_WIDTH) == pytest.approx(1e-5)
    assert cosine_lr(50, cfg, 16) == cosine_lr(50, cfg, LR_WIDTH) == pytest.approx(0.5 * (1e-3 + 1e-5))
    for step in (0, 37, 100):  # a SIREN twice as wide: half the step size all along the schedule
        assert cosine_lr(step, cfg, 2 * LR_WIDTH) == pytest.approx(0.5 * cosine_lr(step, cfg, LR_WIDTH))


def test_folding_once_gives_the_same_values_and_gradients():
    """Fitting folds ω0 into the flat weight vectors in one product, inference folds once per network; both
    must give exactly what folding each tensor at each call gives (the module's path)."""
    from diffshadow.siren import FoldedSiren, fold, forward_folded

    cfg = SirenConfig(16, 2)
    layout = WeightLayout.for_siren(cfg)
    gen = torch.Generator().manual_seed(5)
    w = torch.stack([layout.flatten(init_siren(cfg, gen)) for _ in range(3)]).requires_grad_(True)
    ref_w = w.detach().clone().requires_grad_(True)
    x = torch.rand(3, 200, 3, generator=gen) * 2 - 1
    got = BatchedSiren(w, layout, cfg.blocks)(x)
    ref = forward_folded(fold(layout.unflatten(ref_w), cfg.blocks), x)
    assert torch.equal(got, ref)
    got.square().sum().backward()
    ref.square().sum().backward()
    assert torch.equal(w.grad, ref_w.grad)
    model = Siren.from_flat(w[1].detach(), layout)
    with torch.no_grad():
        assert torch.equal(FoldedSiren(fold(model.named_tensors(), cfg.blocks))(x[1]), model(x[1]))


def test_passes_cover_every_row_once_and_none_is_short():
    from diffshadow.siren import passes

    for n in (0, 1, 5, 63, 64, 65, 127, 128, 129, 1000, 4096):
        for size, least in ((64, None), (64, 2), (7, None)):
            slices = passes(n, size, least)
            assert [i for s in slices for i in range(n)[s]] == list(range(n))
            if len(slices) > 1:
                assert all(s.stop - s.start >= (least or size) for s in slices)
                assert all(s.stop - s.start < size + (least or size) for s in slices)



def _spied(monkeypatch, elements: int) -> list:
    """Passes of `elements` activations, and the row count of every pass the SIREN's forward is given."""
    from diffshadow import siren as S

    rows, forward = [], S.forward_folded
    monkeypatch.setattr(S, "CPU_PASS_ELEMENTS", elements)
    monkeypatch.setattr(S, "forward_folded", lambda layers, h: rows.append(h.shape[-2]) or forward(layers, h))
    return rows


@pytest.mark.parametrize("k", [None, 1, 4])
def test_inference_in_passes_gives_each_point_the_bits_of_one_pass(monkeypatch, k):
    """On a CPU a SIREN's inference goes through in passes that fit the cache; a point's value must not depend on
    the points beside it in its pass (under the jobs' MKL_CBWR=AUTO,STRICT, which conftest.py sets), so images and
    PSNRs are the bytes of one pass over all. No pass holds much more than its share of activations."""
    from diffshadow.siren import MIN_PASS_ROWS, FoldedSiren, fold, fold_flat, forward_folded

    cfg = SirenConfig(64, 2)
    gen = torch.Generator().manual_seed(5)
    layout = WeightLayout.for_siren(cfg)
    if k is None:
        layers, x = fold(init_siren(cfg, gen), cfg.blocks), torch.rand(5000, 3, generator=gen) * 2 - 1
    else:
        w = torch.stack([layout.flatten(init_siren(cfg, gen)) for _ in range(k)])
        layers, x = fold_flat(w, layout, cfg.blocks), torch.rand(k, 5000, 3, generator=gen) * 2 - 1
    whole = forward_folded(layers, x)
    rows = _spied(monkeypatch, 64 * 300)
    assert torch.equal(FoldedSiren(layers)(x), whole)
    share = max(300 // (k or 1), MIN_PASS_ROWS)
    assert len(rows) > 1 and sum(rows) == 5000 and all(share <= r < 2 * share for r in rows)


def test_training_evaluates_in_one_pass_so_its_gradients_sum_as_before(monkeypatch):
    cfg = SirenConfig(32, 1)
    gen = torch.Generator().manual_seed(6)
    layout = WeightLayout.for_siren(cfg)
    w = torch.stack([layout.flatten(init_siren(cfg, gen)) for _ in range(2)])
    x = torch.rand(2, 3000, 3, generator=gen) * 2 - 1
    rows = _spied(monkeypatch, 32 * 1000)
    with torch.no_grad():
        BatchedSiren(w, layout, cfg.blocks)(x)
    assert rows == [500] * 6  # inference: in passes of 1,000 activations per SIREN
    rows.clear()
    BatchedSiren(w.requires_grad_(), layout, cfg.blocks)(x).sum().backward()
    assert rows == [3000]
