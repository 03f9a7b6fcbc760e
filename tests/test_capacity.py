"""Capacity that adapts to the volume: the ladder's order, where it stops, what it records and warns, the
data INR and stage-1 layout grown by it, and preoptimize's file round trip."""

import numpy as np
import pytest
from conftest import identity_tf

from diffshadow.analytic import gaussian_blob
from diffshadow.artifacts import ArtifactError, load_siren_init, save_siren_init
from diffshadow.capacity import Choice, Rung, climb, ladder
from diffshadow.data_inr import DataInrConfig, fit_data_inr
from diffshadow.fit import FitConfig, choose_layout, probe_light
from diffshadow.siren import SirenConfig
from diffshadow.volume import Volume


def test_ladder_doubles_steps_once_then_width():
    assert ladder(32, 700, 128) == [Rung(32, 700), Rung(32, 1400), Rung(64, 1400), Rung(128, 1400)]
    assert ladder(64, 10, 32) == [Rung(64, 10), Rung(64, 20)]  # max_width below the start: steps only
    with pytest.raises(ValueError, match="width, steps and points"):
        ladder(0, 10, 32)
    with pytest.raises(ValueError, match="points 0"):
        ladder(32, 10, 64, points=0)


def test_the_data_inr_ladder_doubles_only_the_width():
    assert ladder(64, 6000, 256, double_steps=False) == [Rung(64, 6000), Rung(128, 6000), Rung(256, 6000)]
    assert ladder(64, 6000, 32, double_steps=False) == [Rung(64, 6000)]  # max_width below the start: that size
    with pytest.raises(ValueError, match="only on a ladder that doubles its steps"):
        ladder(32, 10, 64, points=16, double_steps=False)


def test_stage1_ladder_widens_the_batch_at_the_second_rungs_points():
    rungs = ladder(32, 8000, 256, points=256)
    assert rungs == [Rung(32, 8000, 256), Rung(32, 16000, 256), Rung(64, 8000, 512), Rung(128, 4000, 1024),
                     Rung(256, 2000, 2048)]
    assert {r.steps * r.points for r in rungs[1:]} == {16000 * 256}  # the same points in all past the first rung
    assert rungs[2].describe() == "width 64, 8000 steps of 512 points"
    assert ladder(16, 3, 64, points=10)[-1] == Rung(64, 2, 40)  # steps rounded, never below 1


def test_climb_stops_at_the_first_rung_that_reaches_the_target():
    psnr = {16: 30.0, 32: 36.0, 64: 41.0, 128: 45.0}
    tried = []

    def attempt(rung):
        tried.append(rung)
        return rung.width, psnr[rung.width] + (1.0 if rung.steps > 10 else 0.0)

    result, choice = climb(ladder(16, 10, 128), 40.0, attempt, log=lambda m: None)
    assert result == 64 and choice.met
    assert [r["width"] for r in choice.rungs] == [16, 16, 32, 64]
    assert choice.to_dict()["psnr"] == 42.0 and choice.warning("x", "y") is None


def test_a_missed_target_is_recorded_and_warned():
    _, choice = climb(ladder(8, 5, 16), 99.0, lambda r: (None, 20.0 + r.width / 8), log=lambda m: None)
    assert not choice.met and len(choice.rungs) == 3
    line = choice.warning("the data INR's voxel PSNR", "data_inr.max_width")
    assert line.startswith("WARNING") and "22.00 dB" in line and "99 dB" in line and "data_inr.max_width" in line
    assert "\n" not in line


def test_a_missed_target_keeps_the_best_size_not_the_last():
    # a wider SIREN can diverge (tooth's data INR: 39.6 dB at width 64, 20.7 dB at 128)
    psnr = {8: 30.0, 16: 35.0, 32: 21.0}
    result, choice = climb(ladder(8, 5, 32), 99.0, lambda r: (r, psnr[r.width] + r.steps / 100), log=lambda m: None)
    assert result == Rung(16, 10) and choice.kept == 2 and choice.chosen["width"] == 16
    assert choice.to_dict()["kept"] == 2 and choice.to_dict()["psnr"] == 35.1
    assert "kept width 16, 10 steps" in choice.warning("x", "y") and choice.plateau
    back = Choice.from_dict(choice.to_dict())
    assert back.chosen == choice.chosen and back.to_dict() == choice.to_dict()


def test_widening_that_gains_under_a_db_ends_the_climb():
    psnr = {8: 30.0, 16: 30.6, 32: 40.0, 64: 50.0}  # 32 and 64 would reach the target, but are never tried
    lines = []
    result, choice = climb(ladder(8, 5, 64), 45.0, lambda r: (r, psnr[r.width]), log=lines.append)
    assert [(r["width"], r["steps"]) for r in choice.rungs] == [(8, 5), (8, 10), (16, 10)]
    assert result == Rung(16, 10) and choice.plateau and not choice.met
    assert any("gained +0.60 dB" in m for m in lines)
    line = choice.warning("the data INR's voxel PSNR", "data_inr.max_width")
    assert "width is not what limits it" in line and "lower the target" in line and "max_width" not in line


def test_no_target_tries_only_the_configured_size():
    _, choice = climb(ladder(8, 5, 64), 0.0, lambda r: (None, float("nan")), log=lambda m: None)
    assert choice.met and len(choice.rungs) == 1
    assert {k: choice.rungs[0][k] for k in ("width", "steps", "psnr")} == {"width": 8, "steps": 5, "psnr": None}


@pytest.fixture(scope="module")
def blob():
    return Volume(data=gaussian_blob(13, 0.2), extent=np.ones(3), name="blob")


def test_data_inr_grows_until_its_target(blob):
    tf = identity_tf(10.0)
    base = dict(width=8, blocks=1, steps=40, points=512, checkpoint_every=1000)
    easy = fit_data_inr(blob, tf, DataInrConfig.from_config({**base, "target_psnr": 1.0}), log=lambda m: None)
    assert easy.config["capacity"]["met"] and len(easy.config["capacity"]["rungs"]) == 1
    lines = []
    hard = fit_data_inr(blob, tf, DataInrConfig.from_config({**base, "target_psnr": 200.0, "max_width": 16}),
                        log=lines.append)
    cap = hard.config["capacity"]
    assert [(r["width"], r["steps"]) for r in cap["rungs"]] == [(8, 40), (16, 40)]  # the width alone grows
    best = max(range(2), key=lambda i: cap["rungs"][i]["psnr"])
    assert cap["kept"] == best and hard.model.cfg.width == cap["rungs"][best]["width"] == hard.config["width"]
    assert hard.psnr == cap["psnr"] == cap["rungs"][best]["psnr"] and not cap["met"]
    assert sum(m.startswith("WARNING") for m in lines) == 1


def test_stage1_layout_is_probed_grown_and_round_trips(blob, tmp_path):
    tf = identity_tf(4.0)
    lights = np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 0.954], [0.0, -0.6, 0.8]])
    assert probe_light(lights) == 2
    fit = FitConfig.from_config(dict(steps=6, points=64, eval_points=64, grid_upsample=1, chunk=0, min_psnr=0.0,
                                     target_psnr=200.0, max_width=16))
    siren = SirenConfig(8, 1)
    lines = []
    chosen = choose_layout(blob, tf, lights, siren, fit, preoptimize_steps=3, preoptimize_lr=1e-3, log=lines.append)
    rungs = chosen.choice.rungs
    assert [(r["width"], r["steps"], r["points"]) for r in rungs] == [(8, 6, 64), (8, 12, 64), (16, 6, 128)]
    kept = rungs[max(range(3), key=lambda i: rungs[i]["psnr"])]  # target missed: the best size
    assert chosen.siren == SirenConfig(kept["width"], 1)
    assert (chosen.steps, chosen.points) == (kept["steps"], kept["points"])
    assert len(chosen.init) == chosen.layout.n_params
    assert any(m.startswith("WARNING") and "stage 1's probe light 2" in m and "target 200 dB" in m for m in lines)
    # each width's init is pre-optimised in the steps its fits take
    assert [m for m in lines if m.startswith("pre-optimising")] == [
        "pre-optimising one SIREN of width 8 on light 0 for 3 steps of 64 points",
        "pre-optimising one SIREN of width 16 on light 0 for 3 steps of 128 points"]
    # each probe fit reports its progress (minutes at the paper's sizes on a CPU), marked as the probe's
    assert sum(m.startswith("probe: step 6/6 ") for m in lines) == 2 and any(
        m.startswith("probe: step 12/12 ") for m in lines)

    save_siren_init(tmp_path / "init.pt", chosen)
    back = load_siren_init(tmp_path / "init.pt", siren, 6, 64)
    assert (back.siren, back.steps, back.points) == (chosen.siren, chosen.steps, chosen.points)
    assert back.choice.to_dict() == chosen.choice.to_dict()
    with pytest.raises(ArtifactError, match="made for siren .*'width': 8.* the config says .*'width': 32"):
        load_siren_init(tmp_path / "init.pt", SirenConfig(32, 1))
    with pytest.raises(ArtifactError, match="made for fit.steps = 6, the config says 700; rerun preoptimize"):
        load_siren_init(tmp_path / "init.pt", siren, 700)
    with pytest.raises(ArtifactError, match="made for fit.points = 64, the config says 512; rerun preoptimize"):
        load_siren_init(tmp_path / "init.pt", siren, 6, 512)

    fixed = choose_layout(blob, tf, lights, siren, FitConfig.from_config({**fit.__dict__, "target_psnr": 0.0}),
                          preoptimize_steps=3, preoptimize_lr=1e-3, log=lambda m: None)
    assert (fixed.siren, fixed.steps, fixed.points) == (siren, 6, 64) and fixed.choice.rungs[0]["psnr"] is None


def test_a_subset_below_the_target_its_probe_met_is_named():
    """The probe fits one light alone; a subset whose held-out median misses the target the probe met gets one
    line (bi2o3: probe 39.33 dB, subset median 37.29); none when it meets it, when there is no target, or when the
    probe missed it too (preoptimize said so already)."""
    from diffshadow.stages.stage1 import below_probe_target

    probe = [{"width": 64, "steps": 2000, "psnr": 39.33}]
    met = Choice(39.0, probe, 0)
    line = below_probe_target(met, np.array([36.0, 37.29, 38.1]), 3)
    assert line == ("WARNING: subset 3: held-out median 37.29 dB is below fit.target_psnr 39 dB, which preoptimize's "
                    "probe light reached alone (39.33 dB at width 64, 2000 steps); raising fit.target_psnr by the gap "
                    "makes the probe choose a larger size")
    assert below_probe_target(met, np.array([39.0, 41.0]), 3) is None
    assert below_probe_target(Choice(0.0, probe, 0), np.array([20.0]), 3) is None
    assert below_probe_target(Choice(40.0, probe, 0), np.array([20.0]), 3) is None  # missed by the probe too


def test_the_collected_median_below_the_target_says_whether_the_probe_met_it():
    """collect_weights' line on a stage-1 median under fit.target_psnr: it said the probe had met the target even
    where the probe had missed it too (bi2o3: probe 35.73 dB at width 128, target 42, median 38.20)."""
    from diffshadow.stages.stage1 import median_below_target

    missed = Choice(42.0, [{"width": 64, "steps": 8000, "points": 512, "psnr": 35.4},
                           {"width": 128, "steps": 4000, "points": 1024, "psnr": 35.73}], 1, plateau=True).to_dict()
    assert median_below_target(missed, 38.2) == (
        "WARNING: stage-1 SIRENs reached a median 38.20 dB, below fit.target_psnr = 42 dB, which preoptimize's probe "
        "light missed too (35.73 dB at width 128, 4000 steps of 1024 points; its log says why); lower "
        "fit.target_psnr")
    met = Choice(42.0, [{"width": 32, "steps": 8000, "points": 256, "psnr": 46.11}], 0).to_dict()
    assert median_below_target(met, 41.25) == (
        "WARNING: stage-1 SIRENs reached a median 41.25 dB, below fit.target_psnr = 42 dB that preoptimize's probe "
        "light met; raise fit.steps or siren.width, or lower fit.target_psnr")
    assert median_below_target(met, 42.0) is None
    assert median_below_target({**met, "target_psnr": 0.0}, 20.0) is None
    assert median_below_target(None, 20.0) is None
