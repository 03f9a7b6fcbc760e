"""The blend's correction (diffshadow/correction.py): zero at every training light whatever its network, none until
fitted, fitted it lowers the error of lights it never saw, a round trip through its file, and the one-line errors.
The whole path (fit_correction, the corrected mix and blend, the viewer's and render's answer) runs in
tests/test_workflow.py."""

import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from diffshadow import correction as corr
from diffshadow.config import ConfigError
from diffshadow.layout import SirenConfig, WeightLayout
from diffshadow.lights import PoolLights, blend_weights, make_light_sets, unseen_directions
from diffshadow.siren import BatchedSiren, box_to_siren, init_siren
from diffshadow.store import BlendSampler, blend_rows

SIREN = SirenConfig(8, 1)
LAYOUT = WeightLayout.for_siren(SIREN)
SETS = make_light_sets(64, 12, [0.0, 0.0, 1.0], 0)
TRAIN, CENTER = np.asarray(SETS["train"]["cartesian"]), np.asarray(SETS["center"])
EXTENT = torch.ones(3)
INIT = LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0)))
DIRECTION = torch.randn(LAYOUT.n_params, generator=torch.Generator().manual_seed(1))


def truth_weights(lights: np.ndarray) -> torch.Tensor:
    """A SIREN per light that moves non-linearly with the light: what the stored SIRENs' blend can only follow
    linearly between them."""
    d = torch.as_tensor(np.asarray(lights), dtype=torch.float32)
    return INIT + 0.05 * torch.sin(6 * d[:, :1]) * torch.cos(5 * d[:, 1:2]) * DIRECTION


def truth_at(lights: np.ndarray, points: torch.Tensor) -> torch.Tensor:
    return BatchedSiren(truth_weights(lights), LAYOUT, SIREN.blocks)(box_to_siren(points, EXTENT))


def config(**kw) -> corr.CorrectionConfig:
    base = dict(steps=400, lights=256, points=64, batch_lights=16, batch_points=64, visible_fraction=0.5, hidden=32,
                light_freqs=2, lr=3e-3, seed=0, held_out=32)
    return corr.CorrectionConfig(**{**base, **kw})


def store() -> SimpleNamespace:
    return SimpleNamespace(weights=truth_weights(TRAIN).numpy(), lights=TRAIN, layout=LAYOUT, siren=SIREN,
                           extinction=None)


def synthetic_lights(volume, tf, train, lights, cfg, *, k, weighting, point_seed,
                     between_steps=None) -> corr.CorrectionLights:
    """correction_lights' stand-in: the truth SIRENs' values at random points (the "visible" ones in a corner of
    the box), not a marched shadow."""
    points = torch.rand(len(lights), 2 * cfg.points, 3, generator=torch.Generator().manual_seed(point_seed + 2))
    points[:, cfg.points:] *= 0.5
    idx, mix = blend_weights(train, lights, k, weighting)
    pool = PoolLights(torch.as_tensor(lights), points, truth_at(lights, points).detach(), torch.as_tensor(idx),
                      torch.as_tensor(mix, dtype=torch.float32))
    return corr.CorrectionLights(pool, EXTENT, cfg.points)


def random_correction(seed: int = 3) -> corr.BlendCorrection:
    net = corr.make_net(LAYOUT.n_params, 16, 2)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(seed)))
    return corr.BlendCorrection(net, torch.full((LAYOUT.n_params,), 0.1), TRAIN, 2,
                                {"weights_sha256": corr.weights_digest(store().weights)})


def test_the_correction_is_zero_at_every_training_light_whatever_its_network():
    """A training light's blend is its own stored SIREN, and so is its corrected blend, to the bit."""
    fix = random_correction()
    idx, mix = blend_weights(TRAIN, TRAIN, 4, "triangle")
    assert np.array_equal(fix.delta(TRAIN, idx, mix), np.zeros((len(TRAIN), LAYOUT.n_params)))
    sampler = BlendSampler(SimpleNamespace(**vars(store()), light_region=lambda: None), 4, "triangle", fix)
    assert np.array_equal(sampler.many(TRAIN), store().weights)
    between = unseen_directions(TRAIN, CENTER, 8, seed=5)
    assert np.abs(sampler.many(between) - BlendSampler(sampler.store, 4, "triangle").many(between)).max() > 1e-3


def test_the_correction_moves_continuously_with_the_light():
    """A light moved by a thousandth of a radian moves its correction by about as little: the blend's weights move
    continuously, and so does the network's input."""
    fix = random_correction()
    a = unseen_directions(TRAIN, CENTER, 16, seed=6)
    b = a + 1e-3 * np.cross(a, [0.0, 0.0, 1.0])
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    da, db = (fix.delta(x, *blend_weights(TRAIN, x, 4, "triangle")) for x in (a, b))
    far = fix.delta(a[::-1].copy(), *blend_weights(TRAIN, a[::-1].copy(), 4, "triangle"))
    assert np.abs(da - db).max() < 0.02 * np.abs(da - far).max()


def test_an_unfitted_correction_is_none():
    net = corr.make_net(LAYOUT.n_params, 16, 2)
    fix = corr.BlendCorrection(net, torch.ones(LAYOUT.n_params), TRAIN, 2)
    q = unseen_directions(TRAIN, CENTER, 5, seed=1)
    assert not fix.delta(q, *blend_weights(TRAIN, q, 4, "triangle")).any()


def test_fitted_it_lowers_the_error_of_lights_it_never_saw(monkeypatch):
    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    fix = corr.fit_correction(store(), None, None, TRAIN, CENTER, config(), k=4, weighting="triangle",
                              log=lambda m: None)
    held = unseen_directions(TRAIN, CENTER, 64, seed=[7, 7])
    points = torch.rand(len(held), 128, 3, generator=torch.Generator().manual_seed(8))
    want = truth_at(held, points)
    idx, mix = blend_weights(TRAIN, held, 4, "triangle")
    plain = blend_rows(store().weights, idx, mix)

    def error(w: np.ndarray) -> float:
        pred = BatchedSiren(torch.as_tensor(w, dtype=torch.float32), LAYOUT, SIREN.blocks)(box_to_siren(points, EXTENT))
        return float(((pred - want) ** 2).mean())

    before, after = error(plain), error(plain + fix.delta(held, idx, mix))
    assert after < 0.6 * before, (before, after)  # 0.42 here
    assert fix.record["config"]["steps"] == 400 and fix.record["blend_weights"] == "triangle"


def test_a_stopped_fit_resumes_to_the_bytes_of_one_never_stopped(monkeypatch, tmp_path):
    """A kill (here `stop_after_step`) leaves a checkpoint; the rerun takes the network, Adam's moments and the
    draws' generator from it, and ends where a fit never stopped ends; the checkpoint is then removed. One written
    for other settings is left alone and the fit starts again."""
    from diffshadow.stopping import Stopped

    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    ckpt = tmp_path / "correction.pt.ckpt"

    def fit(**kw) -> corr.BlendCorrection:
        return corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=30, **kw), k=4,
                                   weighting="triangle", log=said.append, checkpoint=ckpt)

    said = []
    whole = fit()
    assert not ckpt.exists()
    with pytest.raises(Stopped):
        corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=30), k=4, weighting="triangle",
                            log=said.append, checkpoint=ckpt, stop_after_step=13)
    assert ckpt.exists()
    said.clear()
    resumed = fit()
    assert f"resuming from {ckpt} at step 13/30" in said and not ckpt.exists()
    for a, b in zip(whole.net.parameters(), resumed.net.parameters(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(Stopped):
        corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=30), k=4, weighting="triangle",
                            log=said.append, checkpoint=ckpt, stop_after_step=13)
    said.clear()
    other = fit(lr=1e-3)  # another config: not this checkpoint's fit
    assert not any(m.startswith("resuming") for m in said)
    assert not torch.equal(other.net[-1].weight, whole.net[-1].weight)


def test_the_same_seed_fits_the_same_bytes(monkeypatch):
    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    fits = [corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=30), k=4, weighting="triangle",
                                log=lambda m: None) for _ in range(2)]
    for a, b in zip(fits[0].net.parameters(), fits[1].net.parameters(), strict=True):
        assert torch.equal(a, b)


def test_a_fit_writes_the_same_bytes_on_one_thread_and_on_two(monkeypatch):
    """The workflow's threads (capped by `-j`) change no byte: the corners' rows are gathered so that their
    gradients add in index order on any thread count. A SIREN wide enough that PyTorch splits its work. The third
    fit changes its threads between steps, as one borrowing the run's idle core does (runtime.SpareThreads)."""
    here, wide = sys.modules[__name__], SirenConfig(32, 2)
    layout = WeightLayout.for_siren(wide)
    for name, value in (("SIREN", wide), ("LAYOUT", layout), ("DIRECTION", torch.randn(layout.n_params)),
                        ("INIT", layout.flatten(init_siren(wide, torch.Generator().manual_seed(0))))):
        monkeypatch.setattr(here, name, value)
    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    threads = torch.get_num_threads()
    try:
        fits, switched = [], []

        def switch() -> None:
            switched.append(3 - torch.get_num_threads())
            torch.set_num_threads(switched[-1])

        for n, between in ((1, None), (2, None), (1, switch)):
            torch.set_num_threads(n)
            fits.append(corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=20, hidden=64,
                                            batch_points=64), k=4, weighting="triangle", log=lambda m: None,
                                            between_steps=between))
    finally:
        torch.set_num_threads(threads)
    assert switched[:3] == [2, 1, 2] and len(switched) == 20
    for other in fits[1:]:
        for a, b in zip(fits[0].net.parameters(), other.net.parameters(), strict=True):
            assert torch.equal(a, b)


def test_a_step_draws_its_share_of_visible_points():
    """Of a step's points, `visible_fraction` come from a light's visible set (rows past its box ones), the rest
    from the box; a light with no visible points draws all from the box."""
    cfg, gen = config(batch_points=40, visible_fraction=0.25), torch.Generator().manual_seed(0)
    pick = corr.draw_points(64, 128, cfg, gen)
    assert pick.shape == (16, 40) and (pick[:, :30] < 64).all() and (pick[:, 30:] >= 64).all()
    assert (corr.draw_points(64, 64, cfg, gen) < 64).all()


def test_a_round_trip_through_its_file(tmp_path):
    fix = random_correction()
    path = tmp_path / "correction.pt"
    corr.save_correction(path, fix)
    back = corr.load_correction(path, TRAIN)
    q = unseen_directions(TRAIN, CENTER, 5, seed=2)
    idx, mix = blend_weights(TRAIN, q, 4, "triangle")
    assert np.array_equal(back.delta(q, idx, mix), fix.delta(q, idx, mix))
    assert back.path == path and back.nbytes == 4 * (sum(p.numel() for p in fix.net.parameters()) + LAYOUT.n_params)


def test_its_file_is_checked(tmp_path):
    path = tmp_path / "correction.pt"
    corr.save_correction(path, random_correction())
    with pytest.raises(corr.CorrectionError, match=r"correction.pt: fitted for other training lights \(12\) than "
                                                   r"the stored SIRENs' \(11\); rerun fit_correction"):
        corr.load_correction(path, TRAIN[:11])
    corr.load_correction(path, TRAIN, store().weights)  # the SIRENs it was fitted to
    with pytest.raises(corr.CorrectionError, match=r"correction.pt: fitted for other stored SIRENs than these \(stage "
                                                   r"1 was refitted since\); rerun fit_correction"):
        corr.load_correction(path, TRAIN, store().weights + 1e-3)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(corr.CorrectionError, match=r"correction.pt: not a blend correction \(.*\); rerun"):
        corr.load_correction(path)
    with pytest.raises(corr.CorrectionError, match=r"missing.pt: no such file \(made by the rule `fit_correction`\)"):
        corr.load_correction(tmp_path / "missing.pt")


def test_blends_of_another_weighting_are_refused():
    fix = random_correction()
    fix.record["blend_weights"] = "triangle"
    stored = SimpleNamespace(**vars(store()), light_region=lambda: None)
    with pytest.raises(corr.CorrectionError, match="fitted for triangle blends, asked to correct inverse-angle ones"):
        BlendSampler(stored, 4, "inverse-angle", fix)


def test_bad_settings_are_named():
    with pytest.raises(ConfigError, match=r"correction.batch_points \(129\) is more than twice correction.points "
                                          r"\(64\)"):
        config(batch_points=129)
    with pytest.raises(ConfigError, match=r"correction.visible_fraction: expected 0 to 1, got 1.5"):
        config(visible_fraction=1.5)
    with pytest.raises(ConfigError, match=r"correction.steps: expected 0 or more, got -1"):
        config(steps=-1)
    assert corr.CorrectionConfig.from_config({}).steps > 0  # the defaults fit one
    with pytest.raises(corr.CorrectionError, match="correction.steps is 0"):
        corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=0), k=4, weighting="triangle")


def test_the_fit_checks_itself_on_lights_it_never_fitted(monkeypatch, tmp_path):
    """The held-out record says what the correction does at its held-out lights: recomputed from the saved
    correction's own delta there, the same medians; kept, as it betters both point sets here."""
    from diffshadow.lights import unseen_directions as draw
    from diffshadow.metrics import psnr
    from diffshadow.sampling import CORRECTION_HELD_OUT_SEED, LightStream

    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    said = []
    fix = corr.fit_correction(store(), None, None, TRAIN, CENTER, config(), k=4, weighting="triangle",
                              log=said.append)
    check = fix.record["held_out"]
    assert check["lights"] == 32 and check["significant"] == 22 and check["kept"] and not fix.declined
    assert sum("held out: box" in m for m in said) == 10 and said[-1].endswith("kept")
    extra = CORRECTION_HELD_OUT_SEED
    held = synthetic_lights(None, None, TRAIN, draw(TRAIN, CENTER, 32, seed=[extra, LightStream.CORRECTION]),
                            config(), k=4, weighting="triangle", point_seed=extra)
    idx, mix = held.pool.neighbours.numpy(), held.pool.blend.numpy()
    plain = blend_rows(store().weights, idx, mix)
    path = tmp_path / "correction.pt"
    corr.save_correction(path, fix)
    back = corr.load_correction(path, TRAIN, store().weights)
    x = box_to_siren(held.pool.points, EXTENT)
    for weights, key in ((plain, "plain_psnr_median"), (plain + back.delta(held.pool.lights.numpy(), idx, mix),
                                                        "corrected_psnr_median")):
        pred = BatchedSiren(torch.as_tensor(weights, dtype=torch.float32), LAYOUT, SIREN.blocks)(x).detach()
        for name, at in (("box", slice(0, 64)), ("visible", slice(64, None))):
            want = float(psnr(pred[:, at], held.pool.values[:, at], dim=1).median())
            assert check[name][key] == pytest.approx(want, abs=1e-3), (name, key)
    assert check["box"]["corrected_psnr_median"] > check["box"]["plain_psnr_median"] + 1


def test_the_check_changes_no_byte_of_the_fit(monkeypatch):
    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    fits = [corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=30, held_out=n), k=4,
                                weighting="triangle", log=lambda m: None) for n in (0, 32)]
    for a, b in zip(fits[0].net.parameters(), fits[1].net.parameters(), strict=True):
        assert torch.equal(a, b)
    assert "held_out" not in fits[0].record and "held_out" in fits[1].record


def test_a_correction_no_better_than_the_plain_blend_is_declined(monkeypatch, tmp_path):
    """One Adam step of lr 1 moves every output weight by about 1: a correction that ruins the blend. Its file
    records the check, loading it gives None, and the blend it would have corrected answers plain. Unchecked
    (held_out 0), the same correction is kept."""
    monkeypatch.setattr(corr, "correction_lights", synthetic_lights)
    said = []
    bad = corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=1, lr=1.0), k=4,
                              weighting="triangle", log=said.append)
    check = bad.record["held_out"]
    assert bad.declined and not check["kept"]
    assert check["box"]["corrected_psnr_median"] < check["box"]["plain_psnr_median"]
    assert said[-1].endswith("declined, not better on 22 of them at one point set and worse at none (a sign test at "
                             "5%): the plain blend answers")
    path = tmp_path / "correction.pt"
    corr.save_correction(path, bad)
    assert corr.load_correction(path, TRAIN, store().weights) is None
    from diffshadow.stages.stage2 import _correction  # what every stage that blends reads: the plain blend
    assert _correction(path, store(), "triangle") is None and _correction(path, store(), "inverse-angle") is None
    unchecked = corr.fit_correction(store(), None, None, TRAIN, CENTER, config(steps=1, lr=1.0, held_out=0), k=4,
                                    weighting="triangle", log=lambda m: None)
    corr.save_correction(path, unchecked)
    assert corr.load_correction(path, TRAIN, store().weights) is not None


def test_the_sign_test_counts_what_chance_gives_under_five_percent():
    """sign_test_count(n) is the fewest wins of n fair coins with P(as many or more) <= 5 %: 5 of 5 (1/32), 7 of 8
    (9/256), 40 of 64; one fewer is over 5 %."""
    from math import comb

    def tail(n: int, k: int) -> float:
        return sum(comb(n, i) for i in range(k, n + 1)) / 2**n

    assert [corr.sign_test_count(n) for n in (4, 5, 8, 64)] == [5, 5, 7, 40]
    for n in (5, 8, 16, 64, 200):
        k = corr.sign_test_count(n)
        assert tail(n, k) <= 0.05 < tail(n, k - 1), n


def test_a_gain_at_one_set_and_a_coin_at_the_other_is_kept_a_loss_at_either_declined():
    """neghip's case: better on 43 of 64 lights at box points, 30 at visible ones (its median there 0.01 dB under the
    plain blend's): kept. Worse on 40 at one set: declined whatever the other gains; better on 39 at best: declined."""
    def check(box_better: int, visible_better: int) -> dict:
        def wins(k: int) -> torch.Tensor:
            return torch.cat([torch.ones(k), -torch.ones(64 - k)]).double()
        plain = {"box": torch.zeros(64, dtype=torch.float64), "visible": torch.zeros(64, dtype=torch.float64)}
        return corr.held_out_check(plain, {"box": wins(box_better), "visible": wins(visible_better)})

    assert check(43, 30)["kept"] and check(40, 25)["kept"]
    assert not check(64, 24)["kept"]  # worse on 40 of 64 at visible points
    assert not check(39, 39)["kept"]  # better, but not on 40 of 64 anywhere
    assert check(43, 30)["visible"] == {"plain_psnr_median": 0.0, "corrected_psnr_median": -1.0, "better": 30,
                                        "worse": 34}


def test_a_held_out_set_too_small_to_decide_is_refused():
    with pytest.raises(ConfigError, match=r"correction.held_out: expected 0 \(no check\) or at least 5, got 4: on "
                                          r"fewer lights the check's sign test can find nothing"):
        config(held_out=4)
    config(held_out=0), config(held_out=5)


def test_a_delta_is_the_same_bytes_on_one_thread_and_on_two():
    """Every job that blends (sample_shadows, the evaluations, caches) asks the correction for its deltas on the
    threads it has; MKL's small products (here the 4 corners' first layer) round by the thread count on some CPUs
    (an AMD EPYC: a -j1 and a -j2 run wrote other bytes), so delta runs on one."""
    sets = make_light_sets(16, 4, [0.0, 0.0, 1.0], 0)
    train, center = np.asarray(sets["train"]["cartesian"]), np.asarray(sets["center"])
    net = corr.make_net(185, 16, 3)
    with torch.no_grad():
        for i, p in enumerate(net.parameters()):
            p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(i)))
    fix = corr.BlendCorrection(net, torch.full((185,), 0.1), train, 3)
    q = unseen_directions(train, center, 2, seed=1)
    idx, mix = blend_weights(train, q, 4, "triangle")
    threads = torch.get_num_threads()
    try:
        out = []
        for n in (1, 2, 1):
            torch.set_num_threads(n)
            out.append(fix.delta(q, idx, mix))
    finally:
        torch.set_num_threads(threads)
    assert np.array_equal(out[0], out[1]) and np.array_equal(out[0], out[2])
    assert torch.get_num_threads() == threads
