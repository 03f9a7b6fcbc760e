import itertools
import re

import numpy as np
import pytest
import torch
from conftest import identity_tf

from diffshadow.artifacts import read_eval_truth, write_eval_truth
from diffshadow.evaluate import blend_baseline, pick
from diffshadow.lights import fibonacci_sphere
from diffshadow.shadow import transmittance
from diffshadow.siren import SirenConfig, WeightLayout, init_siren
from diffshadow.truth import EvalTruth, TruthPoints
from diffshadow.volume import Volume


def _blob(n: int = 12) -> Volume:
    x = np.linspace(-1, 1, n)
    data = np.exp(-4 * (x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2)).astype(np.float32)
    return Volume(data=data, extent=np.ones(3), name="blob")


def test_eval_truth_is_the_exact_march_and_survives_a_round_trip(tmp_path):
    volume, tf = _blob(), identity_tf()
    lights = fibonacci_sphere(6)
    truth = EvalTruth.compute(volume, tf, lights, 64, seed=3)
    for i, w in enumerate(lights):
        for name, pts in truth.points.items():
            assert torch.equal(truth.values[name][i], transmittance(volume, tf, w, pts))
    write_eval_truth(tmp_path / "t.zarr", truth)
    back = read_eval_truth(tmp_path / "t.zarr")
    assert set(back.points) == set(truth.points) and np.array_equal(back.lights, truth.lights)
    for name in truth.points:
        assert torch.equal(back.points[name], truth.points[name])
        assert torch.equal(back.values[name], truth.values[name])
    # the same points as a TruthPoints of the same seed: one evaluation sample whoever asks
    assert torch.equal(TruthPoints(volume, tf, 64, seed=3).sets["box"], truth.points["box"])
    # the box set alone (the mix's validation lights): the same points and values, no visible set marched
    box = EvalTruth.compute(volume, tf, lights, 64, seed=3, sets=("box",))
    assert set(box.points) == set(box.values) == {"box"} and "visible" in truth.points
    assert torch.equal(box.points["box"], truth.points["box"]) and torch.equal(box.values["box"], truth.values["box"])


def test_a_truth_marches_its_sets_together_in_groups_of_at_least_a_cpu_chunks_rays(monkeypatch):
    # small marches are bound by their per-iteration ops: 64 lights at 512 points a set were 22 marches of
    # 3,072 rays, and are now one; the values are each light's own march (rays are independent)
    import diffshadow.truth as truth_mod

    marched = []
    real = truth_mod.transmittance_per_light

    def counting(field, tf, lights, points, **kw):
        marched.append(len(lights) * len(points))
        return real(field, tf, lights, points, **kw)

    monkeypatch.setattr(truth_mod, "transmittance_per_light", counting)
    volume, tf = _blob(), identity_tf()
    points = TruthPoints(volume, tf, 512, seed=1)
    assert set(points.sets) == {"box", "visible"}
    lights = fibonacci_sphere(64)
    values = points.truth(lights)
    assert marched == [64 * 1024]
    for name, pts in points.sets.items():
        # each set a tensor of its own (a view of both sets' march would be saved with the other's values too)
        assert values[name].shape == (64, 512) and values[name].untyped_storage().nbytes() == 64 * 512 * 4
        for i in (0, 37, 63):
            assert torch.equal(values[name][i], transmittance(volume, tf, lights[i], pts))
    marched.clear()
    lines = []
    points.truth(fibonacci_sphere(200), lines.append)  # 64 lights of 1,024 points a march at least
    assert truth_mod.MIN_RAYS_PER_MARCH == 64 * 1024
    assert marched == [64 * 1024] * 3 + [8 * 1024] and len(lines) == 4 and "200/200" in lines[-1]
    marched.clear()
    lines.clear()
    points.truth(fibonacci_sphere(700), lines.append)  # ~10 groups where each has the rays, a line after each
    assert marched == [70 * 1024] * 10 and len(lines) == 10 and lines[0].startswith("ground truth, lights: 70/700")


def test_eval_truth_rows_follow_the_lights_asked_for_and_a_missing_light_is_named():
    volume, tf = _blob(), identity_tf()
    lights = fibonacci_sphere(5)
    truth = EvalTruth.compute(volume, tf, lights, 32, seed=0)
    order = [4, 0, 2]
    rows = truth.of(lights[order])
    for k, v in rows.items():
        assert torch.equal(v, truth.values[k][order])
    with pytest.raises(ValueError, match=r"t\.zarr: no ground truth for light \[0\.0, 0\.0, 1\.0\]"):
        truth.of(np.array([[0.0, 0.0, 1.0]]), "t.zarr")


def test_median_psnr_scores_each_light_against_its_own_truth_row():
    volume, tf = _blob(), identity_tf()
    lights = fibonacci_sphere(3)
    truth = EvalTruth.compute(volume, tf, lights, 32, seed=0)
    cfg = SirenConfig(width=8, blocks=1)
    layout = WeightLayout.for_siren(cfg)
    w = np.stack([layout.flatten(init_siren(cfg, torch.Generator().manual_seed(i))).numpy() for i in range(3)])
    values = truth.sirens(w, layout, cfg)
    # truth rows = each light's own SIREN off by 0.1, 0.01 and 0.001: PSNR 20, 40 and 60 dB, median 40
    truth.values = {k: v + torch.tensor([0.1, 0.01, 0.001])[:, None] for k, v in values.items()}
    assert truth.median_psnr(w, layout, cfg, lights) == pytest.approx(40.0, abs=1e-3)
    assert truth.median_psnr(w[[2, 1, 0]], layout, cfg, lights[[2, 1, 0]], "visible") == pytest.approx(40.0, abs=1e-3)


@pytest.mark.parametrize("n", [1, 2, 7, 9, 33])
def test_sirens_in_chunks_give_the_bits_of_one_batch(monkeypatch, n):
    """Many SIRENs are evaluated in chunks of bounded memory (choose-cache at 1,024 lights held 9 GiB), never a
    chunk of one (a batch of one matrix takes another kernel): every chunking gives one batch's bits."""
    from diffshadow import truth as truth_module
    from diffshadow.truth import light_chunks

    for size in (1, 2, 7, 9, 33):
        for per in (1, 3, 8):
            monkeypatch.setattr(truth_module, "CHUNK_FLOATS", size * 8)
            chunks = light_chunks(n, 8 * per)
            lengths = [c.stop - c.start for c in chunks]
            assert chunks[0].start == 0 and chunks[-1].stop == n and sum(lengths) == n
            assert all(a.stop == b.start for a, b in itertools.pairwise(chunks))
            assert n == 1 or min(lengths) >= 2
    volume, tf = _blob(), identity_tf()
    truth = EvalTruth.compute(volume, tf, fibonacci_sphere(2), 256, seed=0)
    cfg = SirenConfig(width=8, blocks=1)
    layout = WeightLayout.for_siren(cfg)
    w = np.stack([layout.flatten(init_siren(cfg, torch.Generator().manual_seed(i))).numpy() for i in range(n)])
    monkeypatch.setattr(truth_module, "CHUNK_FLOATS", 1 << 40)
    whole = truth.sirens(w, layout, cfg)
    for lights_per_chunk in (1, 2, 3, 4):  # CHUNK_FLOATS for that many SIRENs of 256 points at width 8
        monkeypatch.setattr(truth_module, "CHUNK_FLOATS", lights_per_chunk * 256 * 8)
        parts = truth.sirens(w, layout, cfg)
        assert all(torch.equal(parts[k], whole[k]) for k in whole)


def test_blend_baseline_is_the_convex_blend_of_the_chosen_rows():
    rows = {"box": torch.arange(12.0).reshape(3, 4)}  # 3 training lights, 4 points
    idx = np.array([[2, 0], [1, 1]])
    out = blend_baseline(rows, idx, np.array([[0.25, 0.75], [0.4, 0.6]]))["box"]
    assert torch.allclose(out[0], 0.25 * rows["box"][2] + 0.75 * rows["box"][0])
    assert torch.allclose(out[1], rows["box"][1])  # one light twice: its own row


def test_pick_spreads_evenly_and_keeps_both_ends():
    assert pick(64, 8) == [0, 9, 18, 27, 36, 45, 54, 63]
    assert pick(3, 8) == [0, 1, 2] and pick(5, 0) == []


def test_quality_warnings_name_the_goal_missed_and_what_to_change():
    from diffshadow.stages.stage2 import quality_warnings

    result = {"seen": {"generated_minus_stage1_median_db": -3.7},
              "unseen": {"generated_psnr_median": 32.28, "blend_psnr_median": 32.74, "blend_k": 4,
                         "finetune_change_median_db": 0.0},
              "diffusion_model": {"preset": "small"}}
    seen, unseen = quality_warnings(result)
    assert seen.startswith("WARNING: generated SIRENs on seen lights are 3.70 dB under stage 1 (goal: within 1.5 dB)")
    assert seen.endswith("set a wider diffusion.preset (medium, paper) than this run's small")
    # a record made before evaluate.blend_weights: the 4 nearest; since, by default, the triangle around the light
    assert "(32.28 dB) are under the blend of 4 nearest true shadows (32.74 dB)" in unseen
    result["unseen"]["blend_weights"] = "triangle"
    assert "are under the triangle blend of the true shadows (32.74 dB)" in quality_warnings(result)[1]
    assert "raise lights.sphere" in unseen  # no angle recorded: both pieces of advice
    assert unseen.endswith("set a wider diffusion.preset (medium, paper) (docs/performance.md)")
    # test lights already close to training lights: a denser sphere is not the advice (tooth, docs/performance.md)
    result["unseen"]["nearest_angle_median_deg"] = 0.94
    unseen = quality_warnings(result)[1]
    assert "lie a median 0.9 deg from the nearest training light: set a wider diffusion.preset" in unseen
    assert "lights.sphere" not in unseen
    result["diffusion_model"]["stopped"] = "reached diffusion.max_epochs 1800 with ..."
    assert "1.5 dB); raise diffusion.max_epochs (this run stopped at it) or set a wider" in quality_warnings(result)[0]
    result["diffusion_model"] = {"preset": "paper", "stopped": "the gap stopped closing"}
    seen, unseen = quality_warnings(result)
    assert seen.endswith("this run's paper is the widest preset, and the gap stopped closing") and "()" not in seen
    assert unseen.endswith(": raise diffusion.max_epochs (docs/performance.md)")
    result["seen"]["generated_minus_stage1_median_db"] = -1.0
    result["unseen"]["generated_psnr_median"] = 34.0
    assert quality_warnings(result) == []


def test_naive_images_made_apart_give_evaluate_images_the_same_metrics_and_pngs(tmp_path):
    """The naive images rendered in a job of their own (`naive_images`) and read back are the ones
    `image_evaluation` renders itself: the same metrics and PNG bytes; read for other cameras, they are refused."""
    from types import SimpleNamespace

    from conftest import data_inr_stub

    from diffshadow.artifacts import ArtifactError, read_naive_images, write_naive_images
    from diffshadow.evaluate import image_evaluation, naive_images, naive_tags
    from diffshadow.render import Camera, RenderScene

    vol, siren = _blob(16), SirenConfig(8, 1)
    layout = WeightLayout.for_siren(siren)
    scene = RenderScene(vol, identity_tf(), data_inr_stub(8, 1))
    views = [Camera.orbit(vol.extent, azimuth=a, elevation=20, size=12) for a in (30, 150)]
    lights = {"train": fibonacci_sphere(40)[:3], "unseen": fibonacci_sphere(40)[3:5]}
    stage1 = SimpleNamespace(layout=layout, siren=siren,
                             weights=np.stack([layout.flatten(init_siren(siren, torch.Generator().manual_seed(i)))
                                               .numpy() for i in range(3)]))
    picks = dict(lights_per_set=2, naive_views=1, naive_lights=1)
    settings = dict(step=1.0, **picks)
    assert [t for t, _, _ in naive_tags(lights, views, **picks)] == ["train0_view0"]
    made = naive_images(scene, lights, views, log=lambda m: None, **settings)
    write_naive_images(tmp_path / "naive.zarr", made, lights["train"], views)
    read = read_naive_images(tmp_path / "naive.zarr", lights["train"], views)
    inline = image_evaluation(scene, lights, stage1, None, views, out_dir=tmp_path / "a", log=lambda m: None,
                              **settings)
    apart = image_evaluation(scene, lights, stage1, None, views, out_dir=tmp_path / "b", naive=read,
                             log=lambda m: None, **settings)
    assert inline["modes"] == apart["modes"] and inline["modes"]["naive"]["count"] == 1
    for png in sorted((tmp_path / "a").glob("*.png")):
        assert (tmp_path / "b" / png.name).read_bytes() == png.read_bytes(), png.name
    with pytest.raises(ArtifactError, match="naive.zarr: rendered for other lights or cameras.*rerun naive_images"):
        read_naive_images(tmp_path / "naive.zarr", lights["train"], views[::-1])


def test_unseen_images_score_the_plain_weight_blend_beside_the_answer_where_they_differ(tmp_path):
    """An unseen light's images get `inr_weight_blend`, stage 1's plain weight blend as the generated store
    recorded it (here inverse-angle, k 2), where the answer is not that blend; `weight_blend_images` pairs the two
    over those images. A store that records no blend, or answers with the plain blend itself, gets neither."""
    from diffshadow.evaluate import image_evaluation
    from diffshadow.render import Camera, RenderScene
    from diffshadow.store import BlendSampler, WeightStore, blend_record

    vol, siren = _blob(16), SirenConfig(8, 1)
    layout = WeightLayout.for_siren(siren)
    scene = RenderScene(vol, identity_tf())
    views = [Camera.orbit(vol.extent, azimuth=a, elevation=20, size=12) for a in (30, 150)]
    sphere = fibonacci_sphere(40)
    lights = {"train": sphere[:3], "unseen": sphere[3:5]}
    weights = np.stack([layout.flatten(init_siren(siren, torch.Generator().manual_seed(i))).numpy()
                        for i in range(3)])
    ones = np.ones(3)
    stage1 = WeightStore(weights, lights["train"], ones, ones, layout, siren, {})
    plain = BlendSampler(stage1, 2, "inverse-angle").many(lights["unseen"])
    answer = plain.copy()
    answer[0] += 0.05 * np.random.default_rng(0).standard_normal(answer.shape[1]).astype(np.float32)

    def generated(unseen, config):
        return WeightStore(np.concatenate([weights, unseen]), sphere[:5], np.ones(5), np.ones(5), layout, siren,
                           config, seen=np.array([True] * 3 + [False] * 2))

    record = {"mix": {"blend_weights": "inverse-angle", "blend_k": 2, "model_share": 0.5}}
    out = image_evaluation(scene, lights, stage1, generated(answer, record), views, step=1.0,
                           out_dir=tmp_path / "a", log=lambda m: None)
    rows = {(r["set"], r["light"], r["view"], r["mode"]): r["psnr"] for r in out["images"]}
    blended = sorted(k[:3] for k in rows if k[3] == "inr_weight_blend")
    assert blended == [("unseen", 0, 0), ("unseen", 0, 1)]  # light 1's answer is the plain blend: not again
    pairs = out["weight_blend_images"]
    assert pairs["images"] == 2 and pairs["better"] == sum(rows[(*k, "inr_generated")] > rows[(*k, "inr_weight_blend")]
                                                           for k in blended)
    assert pairs["inr_weight_blend_psnr_mean"] == pytest.approx(np.mean([rows[(*k, "inr_weight_blend")]
                                                                         for k in blended]))
    # its PNG beside the others of the image
    assert (tmp_path / "a" / "unseen0_view0_inr_weight_blend.png").exists()
    assert "gap_interval95_db" not in pairs  # one light: no interval
    assert blend_record(generated(answer, {})) is None
    same = image_evaluation(scene, lights, stage1, generated(plain, record), views, step=1.0,
                            out_dir=tmp_path / "b", log=lambda m: None)
    assert "weight_blend_images" not in same and "inr_weight_blend" not in same["modes"]


def test_a_slow_naive_frame_says_it_is_alive_and_is_the_same_frame(monkeypatch):
    """`naive_images` gives each frame a ticker as its `interrupt` (here one that logs at every ask), and the frame
    is the same bytes as one rendered without it."""
    from conftest import data_inr_stub

    import diffshadow.evaluate as ev
    import diffshadow.progress as progress
    from diffshadow.render import Camera, RenderScene

    vol = _blob(16)
    scene = RenderScene(vol, identity_tf(), data_inr_stub(8, 1))
    views = [Camera.orbit(vol.extent, azimuth=30, elevation=20, size=12)]
    lights = {"train": fibonacci_sphere(40)[:2], "unseen": fibonacci_sphere(40)[2:3]}
    monkeypatch.setattr(progress, "TICK_S", 0.0)
    said = []
    made = ev.naive_images(scene, lights, views, step=1.0, lights_per_set=1, log=said.append)
    beat = r"\[naive images\] train0_view0 \(1/1\): \d+ s so far"
    assert len(said) > 2 and all(re.fullmatch(beat, m) for m in said[:-1])
    alone = scene.render("naive", views[0], light=lights["train"][0], scalar="inr", step=1.0)
    assert torch.equal(made["train0_view0"].rgb, alone.rgb)


def _truth_and_sirens(n: int = 5):
    siren = SirenConfig(8, 1)
    layout = WeightLayout.for_siren(siren)
    init = layout.flatten(init_siren(siren, torch.Generator().manual_seed(0))).numpy()
    w = (init + 0.05 * np.random.default_rng(0).standard_normal((n, layout.n_params))).astype(np.float32)
    truth = EvalTruth.compute(_blob(), identity_tf(), fibonacci_sphere(n), 128, seed=3)
    return truth, w, layout, siren


def test_a_truth_evaluates_its_sirens_where_it_is_put(monkeypatch):
    """evaluate.device: run puts the SIRENs that evaluate_voxels and caches score on the run's device
    (`EvalTruth.on`): `sirens` evaluates there, and on the CPU (the default) the values are the same bytes."""
    from diffshadow import truth as truth_module

    truth, w, layout, siren = _truth_and_sirens()
    before = truth.sirens(w, layout, siren)
    asked, values = [], truth_module._siren_values

    def recorded(*args, **kwargs):
        asked.append(kwargs.get("device"))  # None: evaluated wherever _siren_values' default is
        return values(*args, **kwargs)

    monkeypatch.setattr(truth_module, "_siren_values", recorded)
    put = truth.on("cpu")
    after = put.sirens(w, layout, siren)
    assert asked == [torch.device("cpu")] and put.device == torch.device("cpu") and truth.device.type == "cpu"
    assert put.points is truth.points and put.values is truth.values  # the truth itself stays on the CPU
    assert all(torch.equal(before[k], after[k]) for k in before)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_sirens_evaluated_on_cuda_are_the_cpus_to_float_rounding():
    truth, w, layout, siren = _truth_and_sirens()
    cpu, gpu = truth.sirens(w, layout, siren), truth.on("cuda").sirens(w, layout, siren)
    for k in cpu:
        assert gpu[k].device.type == "cpu" and float((gpu[k] - cpu[k]).abs().max()) < 1e-5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_eval_truth_on_cuda_is_the_cpus_to_float_rounding():
    """evaluate.device: run marches on the GPU; the points are the CPU's draws and the truth comes back to the CPU."""
    volume, tf, lights = _blob(), identity_tf(), fibonacci_sphere(6)
    cpu = EvalTruth.compute(volume, tf, lights, 256, seed=3)
    gpu = EvalTruth.compute(volume, tf, lights, 256, seed=3, device="cuda")
    for name in cpu.points:
        assert gpu.values[name].device.type == "cpu" and torch.equal(gpu.points[name], cpu.points[name])
        assert float((gpu.values[name] - cpu.values[name]).abs().max()) < 1e-5


def test_the_median_gap_interval_is_paired_fixed_and_says_when_a_gap_is_the_draw():
    """The bootstrap interval of median(a) - median(b) over lights resampled in pairs: a constant offset is exact
    whatever the lights, swapping the two negates it, it is the same every call, and it holds 0 for a gap that
    is only noise while it excludes 0 for a real one."""
    from diffshadow.evaluate import median_gap_interval

    rng = np.random.default_rng(5)
    b = rng.normal(35.0, 2.0, 32)
    assert median_gap_interval(b + 1.5, b) == pytest.approx([1.5, 1.5])
    noise = b + rng.normal(0.0, 1.0, 32)
    lo, hi = median_gap_interval(noise, b)
    assert median_gap_interval(noise, b) == [lo, hi] and lo < 0 < hi
    assert median_gap_interval(b, noise) == pytest.approx([-hi, -lo])
    assert median_gap_interval(noise + 3.0, b)[0] > 0


def test_the_seam_split_sets_the_answer_across_subsets_beside_the_answer_inside_one():
    """`wide.seams`: the answer's median on the lights whose blend spans two fit_siren subsets and on the rest, with
    the subset size and halo the store records; nothing for one subset or a store that records no subset size."""
    from diffshadow.evaluate import seam_split
    from diffshadow.lights import across_subsets, blend_weights, fibonacci_sphere, select_region, training_pool

    sphere = fibonacci_sphere(1600)
    train = sphere[select_region(sphere, [0, 0, 1], 100)]
    query = training_pool(train, [0, 0, 1], 256, seed=2)
    idx, mix = blend_weights(train, query, 4, "triangle")
    score = np.random.default_rng(0).normal(45.0, 3.0, len(query))
    across = across_subsets(train, idx, mix, 50)
    split = seam_split(score, train, idx, mix, {"subset_size": 50, "fit": {"halo": 1, "rounds": True}})
    assert split == {"subset_size": 50, "halo": 1, "rounds": True, "lights": int(across.sum()),
                     "answer_median_across": pytest.approx(float(np.median(score[across]))),
                     "answer_median_within": pytest.approx(float(np.median(score[~across])))}
    assert 0 < split["lights"] < len(query)
    assert seam_split(score, train, idx, mix, {"subset_size": 100, "fit": {"halo": 1}}) == {}
    assert seam_split(score, train, idx, mix, {"fit": {}}) == {} == seam_split(score, train, idx, mix, None)
    before = seam_split(score, train, idx, mix, {"subset_size": 50, "fit": {}})  # a store before the keys
    assert (before["halo"], before["rounds"]) == (0, False)
    assert not seam_split(score, train, idx, mix, {"subset_size": 50, "fit": {"halo": 0, "rounds": True}})["rounds"]


def test_an_unknown_image_reference_is_refused_naming_the_key(tmp_path):
    """`render.reference` is checked before any image is rendered (the CLI takes a --config-json the schema does not
    see when called without the workflow)."""
    from diffshadow.evaluate import image_evaluation

    with pytest.raises(ValueError, match=r"^render.reference: expected one of exact, grid, got 'march'$"):
        image_evaluation(None, {}, None, None, [], step=0.5, out_dir=tmp_path, reference="march")


def test_the_images_gap_interval_resamples_lights_not_their_views():
    """`_paired`'s interval of the mean gap: each light's views share its blend, so lights are resampled. Lights
    whose two views' gaps are g - 5 and g + 5 (g from -0.2 to +0.2) give an interval as narrow as the g's own, not
    the images' spread of 10 dB; under PAIRED_INTERVAL_LIGHTS lights, none."""
    from diffshadow.evaluate import PAIRED_INTERVAL_LIGHTS, _paired, mean_gap_interval

    g = np.linspace(-0.2, 0.2, 12)
    rows = [r for i, gap in enumerate(g) for v, d in enumerate((-5.0, 5.0))
            for r in ({"set": "unseen", "light": i, "view": v, "mode": "a", "psnr": 40.0 + gap + d},
                      {"set": "unseen", "light": i, "view": v, "mode": "b", "psnr": 40.0})]
    out = _paired(rows, "a", "b")
    lo, hi = out["gap_interval95_db"]
    assert out["lights"] == 12 and out["images"] == 24 and out["better"] == 12
    assert -0.2 < lo < 0 < hi < 0.2 and out["gap_interval95_db"] == pytest.approx(mean_gap_interval(g))
    few = [r for r in rows if r["light"] < PAIRED_INTERVAL_LIGHTS - 1]
    assert "gap_interval95_db" not in _paired(few, "a", "b")
