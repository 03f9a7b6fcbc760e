"""The report's renderer table and bench.png: what `diffshadow bench render` measured, every size shown; where
the samplers were timed."""

import pytest

from diffshadow.summary import _sampled_on, cache_verdict, renderer_rows

MIB = 2**20


def bench(memory_scaling: bool = True) -> dict:
    """A bench.json as `bench render --sizes 64 256 --memory-sizes 1024` writes it (naive's memory and counts at
    the smallest size only)."""
    out = {
        "device": "cpu", "step": 0.5,
        "sizes": {
            "64": {"fps": {"noshadow": 20.0, "inr": 16.0, "naive": 0.5},
                   "peak_mem_bytes": {"noshadow": 10 * MIB, "inr": 11 * MIB, "naive": 30 * MIB},
                   "counts": {"noshadow": {"ops": 600, "syncs": 12}, "inr": {"ops": 700, "syncs": 12},
                              "naive": {"ops": 15000, "syncs": 390}}},
            "256": {"fps": {"noshadow": 2.0, "inr": 1.5, "naive": 0.02},
                    "peak_mem_bytes": {"noshadow": 40 * MIB, "inr": 41 * MIB},
                    "counts": {"noshadow": {"ops": 1200, "syncs": 20}, "inr": {"ops": 1400, "syncs": 20}}},
        },
        "step_curve": {"reference_step": 0.125, "points": [{"step": 1.0, "seconds": 0.1, "psnr": 80.0},
                                                           {"step": 0.5, "seconds": 0.2, "psnr": 90.0}]},
    }
    if memory_scaling:
        out["memory_scaling"] = {"noshadow": {"64": 10 * MIB, "256": 40 * MIB, "1024": 90 * MIB},
                                 "inr": {"64": 11 * MIB, "256": 41 * MIB, "1024": 95 * MIB}}
    return out


def test_memory_only_sizes_get_a_row_of_their_own_in_numeric_order():
    header, rows = renderer_rows(bench())
    assert header == ["image", "noshadow fps", "inr fps", "naive fps", "noshadow peak MiB", "inr peak MiB",
                      "naive peak MiB", "noshadow ops / syncs", "inr ops / syncs", "naive ops / syncs"]
    assert [r[0] for r in rows] == ["64²", "256²", "1024²"]  # "1024" sorts before "256" as a string
    last = dict(zip(header, rows[2], strict=True))
    assert last["inr peak MiB"] == "95" and last["noshadow peak MiB"] == "90"
    assert last["inr fps"] == last["naive peak MiB"] == last["inr ops / syncs"] == "n/a"  # memory only


def test_counts_and_peaks_come_from_their_own_size():
    header, rows = renderer_rows(bench())
    first, second = (dict(zip(header, r, strict=True)) for r in rows[:2])
    assert first["naive ops / syncs"] == "15,000 / 390" and first["inr ops / syncs"] == "700 / 12"
    assert first["naive peak MiB"] == "30" and second["naive peak MiB"] == "n/a"
    assert second["inr fps"] == "1.50" and second["inr ops / syncs"] == "1,400 / 20"


def test_inr_with_the_light_moved_gets_its_column_where_measured():
    """bench.json's fps_light_moved (inr from a view's kept samples) beside the fps; none where the fused kernels
    kept nothing, and no column in a bench.json from before it."""
    b = bench()
    b["sizes"]["64"]["fps_light_moved"], b["sizes"]["256"]["fps_light_moved"] = 60.0, None
    header, rows = renderer_rows(b)
    assert header[:5] == ["image", "noshadow fps", "inr fps", "naive fps", "inr fps, light moved"]
    assert [r[4] for r in rows] == ["60.00", "n/a", "n/a"]
    assert "inr fps, light moved" not in renderer_rows(bench())[0]


def test_a_bench_from_before_memory_scaling_and_counts_still_reads():
    old = bench(memory_scaling=False)
    for row in old["sizes"].values():
        del row["counts"]
    header, rows = renderer_rows(old)
    assert [r[0] for r in rows] == ["64²", "256²"]
    assert not any("ops" in h for h in header)


@pytest.mark.parametrize("scaling", [True, False])
def test_bench_png_shows_memory_at_every_size_rendered(scaling):
    import matplotlib.pyplot as plt

    from diffshadow.bench.render import figure

    fig = figure(bench(scaling))
    memory = fig.axes[1]
    assert memory.get_ylabel() == "peak memory added (MiB)"
    labels = [t.get_text() for t in memory.get_xticklabels()]
    assert labels == (["64²", "256²", "1024²"] if scaling else ["64²", "256²"])
    heights = sorted(p.get_height() for p in memory.patches if p.get_height() == p.get_height())  # not NaN
    assert heights[-1] == (95 if scaling else 41)
    plt.close(fig)


def voxel(model: int, generated: float, weight_blend: float) -> dict:
    return {"storage_bytes": {"model": model, "sirens": 100 * 1000, "grids": 1}, "seen": {"count": 100},
            "unseen": {"generated_psnr_median": generated, "weight_blend_psnr_median": weight_blend}}


def test_the_cache_verdict_says_which_is_smaller_and_which_is_better():
    big = cache_verdict(voxel(model=250_000, generated=35.0, weight_blend=34.0))
    assert big.startswith("the model is 2.5x the 100 stored SIRENs (smaller past 250 lights")
    assert "beats their weight blend on unseen lights by 1.00 dB" in big
    small = cache_verdict(voxel(model=50_000, generated=38.0, weight_blend=39.5))
    assert small.startswith("the model is 2.0x smaller than the 100 stored SIRENs")
    assert "their weight blend beats it on unseen lights by 1.50 dB: `cache: blend`" in small
    assert cache_verdict(voxel(model=0, generated=38.0, weight_blend=39.5)) == ""  # cache: blend, no model


def test_a_gap_within_its_interval_over_resampled_lights_is_called_a_tie():
    """bi2o3: the model 26.18 dB, the weight blend 26.11 on 32 unseen lights: +0.07 dB is no win when other test
    lights could reverse it (the interval holds 0); a gap whose interval excludes 0 keeps its verdict and says it."""
    tie = voxel(model=250_000, generated=26.18, weight_blend=26.11)
    tie["unseen"].update(weight_blend_gap_interval95_db=[-0.62, 0.71], better_than_weight_blend=14, count=32)
    assert ("it ties with their weight blend on unseen lights: +0.07 dB (better on 14 of 32 lights; 95 % interval "
            "over resampled test lights -0.62 to +0.71 dB), so other test lights could reverse it; the stored SIRENs "
            "alone (`cache: blend`, or a codec of it) would answer as well, without stage 2") in cache_verdict(tie)
    smaller = voxel(model=50_000, generated=26.18, weight_blend=26.11)  # a tie, but the model keeps fewer bytes
    smaller["unseen"].update(weight_blend_gap_interval95_db=[-0.62, 0.71], better_than_weight_blend=14, count=32)
    assert "could reverse it. " in cache_verdict(smaller) and "cache: blend" not in cache_verdict(smaller)
    win = voxel(model=250_000, generated=35.74, weight_blend=34.04)
    win["unseen"].update(weight_blend_gap_interval95_db=[0.96, 4.61], better_than_weight_blend=26, count=32)
    assert "it beats their weight blend on unseen lights by 1.70 dB (better on 26 of 32 lights; 95 % interval " \
           "over resampled test lights +0.96 to +4.61 dB)" in cache_verdict(win)
    loss = voxel(model=50_000, generated=38.0, weight_blend=39.5)
    loss["unseen"].update(weight_blend_gap_interval95_db=[-2.0, -1.0], better_than_weight_blend=3, count=32)
    assert "their weight blend beats it on unseen lights by 1.50 dB (better on 3 of 32 lights; 95 %" in \
        cache_verdict(loss)


def test_further_test_lights_decide_the_verdict_and_the_test_lights_gap_is_said_beside():
    """512 training lights: on the 32 test lights the mix's +0.33 dB over the weight blend lies within its interval
    (a tie); on 1,024 further lights drawn like them its +0.68 dB does not, so the verdict is a win, on those lights,
    naming both gaps."""
    mixed = voxel(model=250_000, generated=39.96, weight_blend=39.63)
    mixed["mix"] = {"model_share": 0.3, "chosen": "validation lights", "blend_k": 4}
    mixed["unseen"].update(weight_blend_gap_interval95_db=[-0.37, 0.81], better_than_weight_blend=27, count=32)
    assert "the mix ties with their weight blend" in cache_verdict(mixed)
    mixed["wide"] = {"lights": 1024, "generated_psnr_median": 39.26, "weight_blend_psnr_median": 38.58,
                     "weight_blend_gap_interval95_db": [0.57, 0.85], "better_than_weight_blend": 812}
    assert ("the mix beats their weight blend on unseen lights by 0.68 dB (on 1,024 further test lights: better on "
            "812, 95 % interval +0.57 to +0.85 dB; on the 32 test lights +0.33 dB)") in cache_verdict(mixed)
    mixed["wide"].update(weight_blend_gap_interval95_db=[-0.05, 0.12], generated_psnr_median=38.61)
    assert "the mix ties with their weight blend on unseen lights: +0.03 dB (on 1,024" in cache_verdict(mixed)


def test_at_model_share_0_the_verdict_says_the_model_adds_nothing():
    """1,024 training lights: the validation lights chose share 0, so the mix is the weight blend (a zero gap to it);
    the verdict says so and what the blend gains over the model alone, not a tie."""
    mixed = voxel(model=250_000, generated=41.69, weight_blend=41.69)
    mixed["mix"] = {"model_share": 0.0, "chosen": "validation lights", "blend_k": 4, "blend_weights": "triangle"}
    mixed["unseen"].update(model_alone_psnr_median=38.45, weight_blend_gap_interval95_db=[0.0, 0.0], count=32)
    assert ("the cache's answer is their weight blend alone, +3.24 dB against the model alone on the 32 test lights; "
            "the model adds nothing, and `cache: blend` (or a codec of it, `cache: fp16`) would skip stage 2 and its "
            "bytes. Against the light count") in cache_verdict(mixed)
    mixed["wide"] = {"lights": 256, "generated_psnr_median": 41.42, "weight_blend_psnr_median": 41.42,
                     "model_alone_psnr_median": 38.04, "model_alone_gap_interval95_db": [3.18, 3.59],
                     "weight_blend_gap_interval95_db": [0.0, 0.0], "better_than_weight_blend": 0}
    assert "+3.38 dB against the model alone on 256 further test lights, 95 % interval +3.18 to +3.59 dB" in \
        cache_verdict(mixed)
    assert "ties" not in cache_verdict(mixed)


def test_a_mixed_cache_counts_both_its_parts_and_says_how_it_answers(tmp_path):
    """With sample_shadows' mix (voxel_metrics' `mix`), the verdict is the mix's and counts the model's and the
    stored SIRENs' bytes together; the headline states the answer and the model alone beside the mix."""
    import json

    from diffshadow.summary import RunResults, mix_words

    mixed = voxel(model=250_000, generated=36.82, weight_blend=34.04)
    mixed["mix"] = {"model_share": 0.7, "chosen": "validation lights", "blend_k": 4}
    verdict = cache_verdict(mixed)
    assert "mixing the two, the cache keeps both (0.33 MiB)" in verdict  # 250,000 + 100,000 bytes
    assert "the mix beats their weight blend on unseen lights by 2.78 dB" in verdict
    assert mix_words(mixed["mix"]) == ("0.7 x the diffusion model's SIREN + 0.3 x the weight blend of the 4 nearest "
                                       "stored SIRENs (mix.model_share chosen on validation lights; both are kept)")
    mixed["seen"].update(generated_psnr_median=40.72, generated_minus_stage1_median_db=-0.55, stage1_psnr_median=41.27,
                         model_alone_psnr_median=40.23)
    mixed["unseen"].update(model_alone_psnr_median=35.74, blend_psnr_median=27.5, nearest_psnr_median=23.8,
                           blend_k=4, count=32)
    (tmp_path / "voxel_metrics.json").write_text(json.dumps(mixed))
    (tmp_path / "image_metrics.json").write_text(json.dumps({"modes": {}}))
    rows = dict(RunResults(tmp_path, "blob").headline())
    assert rows["generated, seen lights"] == "40.72 dB (-0.55 dB against stage 1; the model alone 40.23 dB)"
    assert rows["generated, unseen lights"].endswith("nearest training SIREN 23.80 dB; the model alone 35.74 dB)")
    assert rows["the cache's answer"] == mix_words(mixed["mix"])
    assert not any(name.startswith("WARNING") for name in rows)
    # a run resumed after an upgrade: its front page says so, naming the jobs
    (tmp_path / "benchmarks").mkdir()
    for job, release in (("fit_siren_0", "2.13.0"), ("fit_siren_1", "2.3.0"), ("lights", None)):
        (tmp_path / "benchmarks" / f"{job}.tsv").write_text("s\n1\n")
        (tmp_path / "benchmarks" / f"{job}.phases.json").write_text(json.dumps(
            {"compute_s": 1.0, "versions": {"python": "3.11.7", **({"torch": release} if release else {})}}))
    rows = dict(RunResults(tmp_path, "blob").headline())
    assert rows["WARNING: mixed runtimes"] == ("this run's jobs ran under different releases of torch (2.13.0: "
                                               "fit_siren_0 (1 job); 2.3.0: fit_siren_1 (1 job)); their results "
                                               "may differ")


def test_the_sampler_timings_name_their_device():
    """voxel_metrics.json records where its samplers ran (evaluate.device); a record from before says so vaguely."""
    assert _sampled_on({"device": "cpu (x86_64)", "threads": 1}) == "cpu (x86_64), 1 thread"
    assert _sampled_on({"device": "cpu (x86_64)", "threads": 2}) == "cpu (x86_64), 2 threads"
    assert _sampled_on({"device": "NVIDIA H200", "threads": 1}) == "NVIDIA H200"
    assert _sampled_on({"ddim_steps": 10}) == "evaluate_voxels' device"


def test_the_sizes_table_sets_every_training_lights_median_beside_the_probe_light():
    """Stage 1's size is chosen on one probe light; the table also says what every training light reached, and
    when that median is below the target the probe met (bi2o3: probe 39.33 dB, median 37.29)."""
    from diffshadow.summary import RunResults

    run = RunResults.__new__(RunResults)
    cap = {"target_psnr": 39.0, "met": True, "psnr": 39.33, "steps": 2000,
           "rungs": [{"width": 64, "steps": 2000, "psnr": 39.33}]}
    run.images = {}
    for median, said in ((37.29, "39.33; every training light's median 37.29 (below it)"),
                         (41.25, "39.33; every training light's median 41.25")):
        run.voxel = {"stage1": {"width": 64, "blocks": 2, "parameters": 16961, "capacity": cap},
                     "seen": {"stage1_psnr_median": median}}
        assert run.sizes()[0][6] == said
    run.voxel["stage1"]["capacity"] = {**cap, "target_psnr": 0}  # no target: the configured size, no probe
    assert run.sizes()[0][6] == "39.33" and run.sizes()[0][4] == "2000 steps"
    rung = {"width": 64, "steps": 8000, "points": 512, "psnr": 43.7}  # stage 1's rungs name their points
    run.voxel["stage1"]["capacity"] = {**cap, **rung, "rungs": [rung]}
    assert run.sizes()[0][4] == "8000 steps of 512 points"
    assert run.sizes()[0][7] == "width 64, 8000 steps of 512 points: 43.70 dB"


def test_the_further_rows_name_what_each_cache_answers_with():
    """The further test lights' rows: a model's cache sets its answer beside the model alone and the blend; a codec
    (no model) its decoded store's blend beside stage 1's fp32 blend; `cache: blend` one row, the blend itself."""
    from diffshadow.summary import _further_rows

    base = {"lights": 256, "points": 1024, "blend_weights": "triangle", "blend_k": 4,
            "generated_psnr_median": 39.5, "weight_blend_psnr_median": 39.49}
    compared = {"weight_blend_gap_interval95_db": [-0.01, 0.02], "better_than_weight_blend": 131}
    model = _further_rows({**base, **compared, "model_share": 0.2, "model_alone_psnr_median": 36.2}, "mixed")
    assert [r[1] for r in model] == ["mixed", "the model alone (the paper's cache)",
                                     "triangle blend of the training SIRENs' weights"]
    assert [r[2] for r in model] == ["39.50", "36.20", "39.49"] and "better than the weight blend on 131" in model[0][4]
    codec = _further_rows({**base, **compared, "codec": "fp16"}, "blended (cache: fp16)")
    assert [r[1] for r in codec] == ["blended (cache: fp16)",
                                     "triangle blend of the training SIRENs' weights (fp32)"]
    blend = _further_rows({**base, "generated_psnr_median": 39.49}, "blended (cache: blend)")
    assert [(r[0], r[1], r[2]) for r in blend] == [("further (256)", "blended (cache: blend)", "39.49")]
    assert "1,024 points per light" in blend[0][4] and "a tenth" not in blend[0][4]  # a run before the tails
    tails = _further_rows({**base, **compared, "model_alone_psnr_median": 36.2, "generated_psnr_p10": 37.91,
                           "model_alone_psnr_p10": 33.0, "weight_blend_psnr_p10": 37.9}, "mixed")
    assert [r[4].split("; ")[-1] for r in tails] == [f"a tenth of the lights under {v} dB"
                                                    for v in ("37.91", "33.00", "37.90")]
    seams = {"subset_size": 50, "halo": 0, "lights": 47, "answer_median_across": 38.69,
             "answer_median_within": 48.14}
    seamed = _further_rows({**base, "generated_psnr_median": 39.49, "seams": seams}, "blended (cache: blend)")
    assert seamed[0][4].endswith("; 47 of them blend lights of two fit_siren subsets (subset_size 50, no halo): "
                                 "median 38.69 dB there, 48.14 inside one")
    assert seamed[0][4].startswith(blend[0][4])
    ringed = _further_rows({**base, "seams": {**seams, "halo": 2}}, "blended (cache: blend)")
    assert "(subset_size 50, a halo of 2 rings)" in ringed[0][4]
    rounds = _further_rows({**base, "seams": {**seams, "halo": 1, "rounds": True}}, "blended (cache: blend)")
    assert "(subset_size 50, a halo of 1 ring, in rounds)" in rounds[0][4]


def test_a_codec_cache_has_no_model_rows_even_where_an_old_runs_files_remain(tmp_path):
    """A run switched to a codec's cache: its storage table counts the codec's bytes and no model, and the old
    diffusion run's finetune_metrics.json, still in the folder, is neither in the headline nor in the tables."""
    import json

    from diffshadow.summary import RunResults

    codec = voxel(model=0, generated=39.49, weight_blend=39.50)
    codec.update(cache="blend", codec="fp16", eval_points=16384)
    codec["storage_bytes"]["cache"] = 50 * 1000
    codec["seen"].update(stage1_psnr_median=41.58, generated_psnr_median=41.53, generated_psnr_min=39.18,
                         generated_minus_stage1_median_db=-0.06)
    codec["unseen"].update(blend_psnr_median=28.8, nearest_psnr_median=23.75, nearest_angle_median_deg=4.3,
                           blend_weights="triangle", blend_k=4, count=32)
    (tmp_path / "voxel_metrics.json").write_text(json.dumps(codec))
    images = {"modes": {}, "image_size": 128, "views": 2, "step": 0.5, "reference": "gt", "lpips": "n/a"}
    (tmp_path / "image_metrics.json").write_text(json.dumps(images))
    old = {"image_psnr_geometry_only": {"mean": 51.43, "min": 48.1}, "image_psnr_finetuned": {"mean": 50.98,
                                                                                              "min": 47.1}}
    (tmp_path / "finetune_metrics.json").write_text(json.dumps(old))
    run = RunResults(tmp_path, "blob")
    tables = run.tables()
    assert "the cache: the 100 SIRENs in fp16</td><td>0.05</td>" in tables  # 50,000 bytes
    assert "diffusion model (weights" not in tables and "fine-tuning" not in tables
    names = [name for name, _ in run.headline()]
    assert not any("fine-tuning" in name for name in names)
    assert "blended, unseen lights" in names and not any(name.startswith("generated") for name in names)
    assert "<img" not in tables  # no timeline drawn: none shown
    (tmp_path / "report").mkdir()
    (tmp_path / "report" / "timeline.png").write_bytes(b"\x89PNG timeline")
    assert "<img src='data:image/png;base64,iVBORyB0aW1lbGluZQ==" in RunResults(tmp_path, "blob").tables()


@pytest.mark.parametrize("damage", ["truncated", "a list", "not UTF-8"])
def test_a_damaged_metrics_file_is_named(tmp_path, damage):
    """The front page reads the stages' JSON files: a cut-off, foreign or non-UTF-8 one is one StoreError naming
    the file and what wrote it, not json's traceback (a truncated voxel_metrics.json reached report-figures as
    "raised inside json ... an input diffshadow does not check yet")."""
    import json

    from diffshadow.io import StoreError
    from diffshadow.summary import RunResults

    (tmp_path / "voxel_metrics.json").write_text(json.dumps(voxel(model=1, generated=30.0, weight_blend=29.0)))
    text = {"truncated": b'{"modes": {"inr"', "a list": b"[1, 2]", "not UTF-8": b'{"modes": "\xff"}'}[damage]
    (tmp_path / "image_metrics.json").write_bytes(text)
    with pytest.raises(StoreError, match=r"^\S*image_metrics.json: (unreadable \(\w+: .+\)|holds a JSON list, not an "
                                         r"object); expected the image metrics of evaluate_images$"):
        RunResults(tmp_path, "blob")


def test_the_report_says_whether_the_blends_correction_was_kept_and_why():
    """voxel_metrics' `correction_check` in words: kept with its held-out figures, or declined and why (the plain
    blend then answers); without a visible set, the box alone."""
    from diffshadow.summary import correction_words

    check = {"lights": 64, "significant": 40, "kept": True,
             "box": {"plain_psnr_median": 38.57, "corrected_psnr_median": 39.55, "better": 43, "worse": 21},
             "visible": {"plain_psnr_median": 41.15, "corrected_psnr_median": 41.14, "better": 30, "worse": 34}}
    assert correction_words(check) == (
        "kept: on its 64 held-out lights the corrected blend scores 39.55 dB at box points (plain 38.57; better on "
        "43, worse on 21) and 41.14 dB at visible points (plain 41.15; better on 30, worse on 34); a sign test (40 of "
        "64 lights, 5 %) finds it better at one point set at least and worse at none")
    check.update(kept=False, visible={"plain_psnr_median": 45.9, "corrected_psnr_median": 45.5, "better": 20,
                                      "worse": 44})
    assert correction_words(check).startswith("declined: on its 64 held-out lights")
    assert correction_words(check).endswith("45.50 dB at visible points (plain 45.90; better on 20, worse on 44); a "
                                            "sign test (40 of 64 lights, 5 %) does not find it better at one point "
                                            "set, or finds it worse at one, so the plain blend answers")
    del check["visible"]
    assert "visible" not in correction_words(check)


def test_the_images_table_sets_the_answer_beside_the_plain_blend_on_the_same_images():
    from diffshadow.summary import _blend_images

    said = _blend_images({"images": 4, "inr_generated_psnr_mean": 48.123, "inr_weight_blend_psnr_mean": 48.567,
                          "better": 1})
    assert "on those 4 images inr_generated 48.12 dB against 48.57, better in 1 of 4." in said
    wide = _blend_images({"images": 64, "inr_generated_psnr_mean": 39.5, "inr_weight_blend_psnr_mean": 39.6,
                          "better": 25, "lights": 32, "gap_interval95_db": [-0.456, 0.204]})
    assert ("39.50 dB against 39.60 (the gap's 95 % interval over the 32 lights -0.46 to +0.20 dB), better in 25 of "
            "64.") in wide
    assert _blend_images(None) == "" and _blend_images({}) == ""
