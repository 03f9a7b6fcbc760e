"""The light-count sweep's machinery (diffshadow.scaling, scripts/scaling_sweep.py) on two tiny points: power laws
recovered exactly from costs that follow one, the storage crossover from bytes per light, the JSON, figures, page
and workflow profile written, and a point that is not a finished run named."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from diffshadow import config, scaling

REPO = Path(__file__).resolve().parent.parent
STAGES = {"fit_siren": (2.0, 1.0), "train_diffusion": (10.0, 0.5), "preoptimize": (6.0, 0.0),
          "caches": (3.0, 0.8)}  # wall = a n^b


def _point(root: Path, n: int, epochs: int | None = None, layout: str | None = None) -> Path:
    """A finished run's files as the sweep reads them, at `n` training lights (a `layout` as lights.json records
    it; None: none, as before the key)."""
    res = root / f"lights_{n}" / "results" / "nucleon"
    res.mkdir(parents=True)
    rows = ["stage\tjobs\twall_s\tcpu_s\tmax_rss_mib"]
    for stage, (a, b) in STAGES.items():
        rows.append(f"{stage}\t1\t{a * n ** b}\t{a * n ** b}\t{100 + n}")
    rows.append("total (sum over jobs)\t3\t0\t0\t0")
    (res / "stage_costs.tsv").write_text("\n".join(rows) + "\n")
    metrics = {"seen": {"count": n, "generated_psnr_median": 40.0, "stage1_psnr_median": 41.0},
               "unseen": {"count": 8, "generated_psnr_median": 33.0, "weight_blend_psnr_median": 32.0 + n / 100,
                          "siren_blend_psnr_median": 27.0, "nearest_psnr_median": 23.0},
               "storage_bytes": {"model": 1000 * 4, "sirens": 40 * n, "grids": 400 * n},
               "stage1": {"parameters": 10}, "diffusion_model": {"parameters": 1000, "epochs": epochs}}
    if n >= 32:  # a run with the mix scores the model alone too; one from before it does not
        metrics["seen"]["model_alone_psnr_median"] = 39.0
    (res / "voxel_metrics.json").write_text(json.dumps(metrics))
    (res / "lights.json").write_text(json.dumps({"sphere": 4 * n, **({"layout": layout} if layout else {})}))
    return res


def test_power_laws_crossover_and_files(tmp_path):
    runs = [_point(tmp_path, n) for n in (8, 32)]
    data = scaling.sweep(runs[::-1])  # any order
    assert [p["lights"] for p in data["points"]] == [8, 32]
    for stage, (a, b) in STAGES.items():
        fit = data["fits"][stage]["wall_s"]
        assert fit["exponent"] == pytest.approx(b, abs=1e-9) and fit["factor"] == pytest.approx(a, rel=1e-9)
        assert scaling.predict(fit, 2000) == pytest.approx(a * 2000 ** b, rel=1e-9)
    # 40 bytes per light in fp32 against a 4,000-byte model: smaller past 100 lights (200 in fp16)
    assert data["crossover_lights"] == {"sirens_fp32": pytest.approx(100), "sirens_fp16": pytest.approx(200)}
    assert data["points"][1]["quality"]["unseen"]["weight_blend"] == pytest.approx(32.32)
    scaling.write_sweep(data, tmp_path / "scaling.json")
    assert json.loads((tmp_path / "scaling.json").read_text())["fits"].keys() == data["fits"].keys()
    for name in ("scaling_costs.png", "scaling_quality.png", "scaling_storage.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page = (tmp_path / "scaling.html").read_text()
    assert "scaling_costs.png" in page and "past 100 lights (fp32)" in page
    assert "light layout <code>cap</code>" in page  # runs from before lights.layout: the paper's region
    # the model alone on seen lights: a number where the run measured it, nan where it did not
    assert [p["quality"]["seen"]["model_alone"] for p in data["points"]] == [None, 39.0]
    assert "<th>seen: the model alone (the paper)</th>" in page
    assert "<tr><td>8</td>" in page and "<td>nan</td><td>41.00</td></tr>" in page and "<td>39.00</td>" in page


def test_projection_and_its_workflow_profile(tmp_path):
    """The projection scales each stage by its exponent, the H200's measured speed-up (at least 1) and the
    paper's work per light; the profile's walltimes are its requests, capped at the queue's longest."""
    data = scaling.sweep([_point(tmp_path, n) for n in (8, 32)])
    run = config.load_run(REPO / "config" / "config.yaml")
    gpu = {"fit_siren": {"wall_s": 2.0 * 8 / 4, "max_rss_mib": 1e6}, "train_diffusion": {"wall_s": 10.0 * 8 ** 0.5 * 2},
           "preoptimize": {"wall_s": 1.0}, "caches": {"wall_s": 1.0}}  # fit 4x faster on the GPU; diffusion 2x slower
    proj = scaling.project(data, run, run, gpu, lights=200, subset=50, stage1_nodes=1)
    fit, diff, pre = (proj["stages"][s] for s in ("fit_siren", "train_diffusion", "preoptimize"))
    # caches was timed at the paper's sizes: that measurement, not a carry, whatever the sweep and the GPU say
    assert "caches" not in proj["stages"]
    assert (f'caches:  # {scaling.PAPER_CPU_SOURCE}\n    walltime: "01:19:00"\n    mem_mb: 17100'
            in scaling.polaris_profile(proj))  # 3,125 s and 10,818 MiB, x 1.5
    # evaluate_voxels too (1,169 s and 6,277 MiB on one thread), with its measured peak as its memory request
    assert "evaluate_voxels" not in proj["stages"]
    assert (f'evaluate_voxels:  # {scaling.PAPER_CPU_SOURCE}\n    walltime: "00:30:00"\n    mem_mb: 9900'
            in scaling.polaris_profile(proj))
    # memory: what the job held on the GPU where that is more than the CPU sweep carries to 200 lights, and a job's
    # peak at the paper's sizes on a CPU where that was measured and is more
    assert fit["rss_mib"] == 1e6 and pre["rss_mib"] == pre["rss_mib_run_config"] < 1e6
    assert diff["rss_mib_run_config"] < diff["rss_mib"] == scaling.PAPER_CPU_RSS_MIB["train_diffusion"]
    assert fit["speedup_used"] == pytest.approx(4.0) and diff["speedup_used"] == 1.0
    assert pre["speedup_used"] == pytest.approx(4.0)  # one fit: fit_siren's speed-up, not its own start-up
    # the same config: work factor 1 for every stage
    assert fit["work_factor"] == diff["work_factor"] == 1.0
    assert fit["a100_s_total"] == pytest.approx(2.0 * 200 / 4 * scaling.A100_PER_H200)
    # 4 jobs of 50 lights in 3 rounds (2, 1, 1: fit.rounds), a node job each on one node: 3 jobs' time, and each
    # node job holds its node for a job's time
    per_job = fit["a100_s_total"] / 4
    assert proj["fit_rounds"] == [2, 1, 1] and proj["stage1_nodes"] == 1
    assert fit["wall_s"] == pytest.approx(3 * per_job) and fit["node_hours"] == pytest.approx(3 * per_job / 3600)
    assert diff["a100_s_total"] == pytest.approx(10.0 * math.sqrt(200) * scaling.A100_PER_H200)
    text = scaling.polaris_profile(proj)
    assert f'walltime: "{scaling.walltime(diff["walltime_request_h"])}"' in text
    assert scaling.walltime(1.0) == "01:00:00" and scaling.walltime(0.001) == "00:01:00"
    assert scaling.walltime(72.0) == "72:00:00"
    # the page lists the rules measured at the paper's sizes too; its total counts those a run of the paper config
    # has (evaluate_voxels, caches), not cache: auto's choice or a codec's encoding
    table = scaling.projection_html({**proj, "storage_bytes": {}}, [])
    assert "<td>evaluate_voxels</td><td colspan=3>one CPU thread" in table and "not in the total" in table
    total = (sum(r["node_hours"] for r in proj["stages"].values())
             + (scaling.PAPER_CPU_S["evaluate_voxels"] + scaling.PAPER_CPU_S["caches"]) / 3600)
    assert f"<td>total</td><td></td><td></td><td></td><td></td>\n<td>{total:,.1f}</td>" in table


def test_stage_one_is_projected_in_its_rounds():
    """Under fit.rounds the paper's 40 fit jobs run in 4 rounds (15, 11, 8, 6): four to a node job, 11 node jobs,
    each round one wave on 10 nodes, so stage 1's wall is 4 jobs' time (one without rounds: 40 jobs, 10 node
    jobs, one wave); a round wider than the nodes takes more waves."""
    from diffshadow.scaling.projection import _schedule, fit_rounds

    paper = config.run_config(config.merge(config.read_yaml(REPO / "config" / "config.yaml"),
                                           config.read_yaml(REPO / "config" / "paper.yaml")), "paper")
    assert fit_rounds(paper, 2000, 50) == [15, 11, 8, 6]
    assert fit_rounds({**paper, "fit": {**paper["fit"], "rounds": False}}, 2000, 50) == [40]
    total = 40 * 600.0  # 10 minutes a job
    rounds = _schedule("fit_siren", total, [15, 11, 8, 6], 10)
    assert rounds["wall_s"] == pytest.approx(4 * 600) and rounds["node_hours"] == pytest.approx(11 * 600 / 3600)
    assert rounds["walltime_request_h"] == pytest.approx(600 * scaling.MARGIN / 3600)  # a job's, as before
    one = _schedule("fit_siren", total, [40], 10)
    assert one["wall_s"] == pytest.approx(600) and one["node_hours"] == pytest.approx(10 * 600 / 3600)
    assert _schedule("fit_siren", total, [15, 11, 8, 6], 2)["wall_s"] == pytest.approx((2 + 2 + 1 + 1) * 600)


def test_train_diffusion_projects_its_cost_per_epoch(tmp_path):
    """The gap check trains past `epochs` on its own judgement: the projection carries the cost per epoch (here
    flat: twice the time for twice the epochs at 4x the lights, with wall = 10 n^0.5) at the config's epochs."""
    data = scaling.sweep([_point(tmp_path, 8, epochs=500), _point(tmp_path, 32, epochs=1000)])
    per_epoch = data["fits"]["train_diffusion"]["wall_s_per_epoch"]
    assert per_epoch["exponent"] == pytest.approx(0.0, abs=1e-9)
    assert data["fits"]["train_diffusion"]["wall_s"]["exponent"] == pytest.approx(0.5)  # the raw walls, as measured
    run = config.load_run(REPO / "config" / "config.yaml")
    gpu = {"train_diffusion": {"wall_s": 10.0 * 8 ** 0.5}}  # as fast as the CPU
    proj = scaling.project(data, run, run, gpu, lights=200, subset=50, stage1_nodes=1)
    diff = proj["stages"]["train_diffusion"]
    assert diff["exponent"] == pytest.approx(0.0, abs=1e-9)
    epoch_s = 10.0 * 8 ** 0.5 / 500
    assert diff["a100_s_total"] == pytest.approx(epoch_s * run["diffusion"]["epochs"] * scaling.A100_PER_H200)


def test_fine_tunings_memory_counts_each_of_its_processes():
    """Fine-tuning's peak at the paper's sizes was measured in one process; a node runs `finetune.nproc` of them,
    each holding its own targets and model. A stage never measured there adds nothing."""
    import copy

    paper = config.load_run(REPO / "config" / "config.yaml")
    for nproc in (1, 4):
        paper = copy.deepcopy(paper)
        paper["finetune"]["nproc"] = nproc
        assert scaling.paper_cpu_rss_mib("finetune_render", paper) == nproc * scaling.PAPER_CPU_RSS_MIB[
            "finetune_render"] > 0
    assert scaling.paper_cpu_rss_mib("train_diffusion", paper) == scaling.PAPER_CPU_RSS_MIB["train_diffusion"]
    assert scaling.paper_cpu_rss_mib("fit_siren", paper) == 0.0


def test_a_point_that_did_not_finish_is_named(tmp_path):
    res = _point(tmp_path, 8)
    (res / "voxel_metrics.json").unlink()
    with pytest.raises(scaling.SweepError, match=r"voxel_metrics.json: missing; the sweep reads finished runs"):
        scaling.sweep([res, _point(tmp_path, 16)])
    with pytest.raises(scaling.SweepError, match=r"two light counts at least, got \[16\]"):
        scaling.sweep([tmp_path / "lights_16" / "results" / "nucleon"])


def test_a_sweep_records_its_light_layout_and_refuses_two(tmp_path):
    """Each point records its runs' lights.layout (lights.json; none written: "cap", the layout before the key),
    the page names it, and runs of two layouts do not make one quality curve."""
    data = scaling.sweep([_point(tmp_path / "a", n, layout="rim") for n in (8, 32)])
    assert [p["layout"] for p in data["points"]] == ["rim", "rim"]
    assert "light layout <code>rim</code>" in scaling.page(data)
    with pytest.raises(scaling.SweepError, match=r"share one lights.layout, got \{8: 'cap', 32: 'rim'\}"):
        scaling.sweep([_point(tmp_path / "b", 8), _point(tmp_path / "b", 32, layout="rim")])


def test_the_sweep_script_collects_finished_points(tmp_path):
    for n in (8, 32):
        _point(tmp_path, n)
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "scaling_sweep.py"), "--lights", "8", "32",
                          "--out", str(tmp_path), "--collect", "--profile-out", str(tmp_path / "p" / "config.yaml")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    data = json.loads((tmp_path / "scaling.json").read_text())
    assert data["projection"]["lights"] == 2000 and "fit_siren" in data["projection"]["stages"]
    assert "set-resources:" in (tmp_path / "p" / "config.yaml").read_text()
    # the sweep records the run config its points ran at; projected again later, the work per light is counted
    # against that record, not against config/config.yaml as it has become
    assert data["run_config"]["fit"]["steps"] == config.load_run(REPO / "config" / "config.yaml")["fit"]["steps"]
    factor = data["projection"]["stages"]["fit_siren"]["work_factor"]
    data["run_config"]["fit"]["steps"] *= 2
    (tmp_path / "old.json").write_text(json.dumps(data))
    again = subprocess.run([sys.executable, str(REPO / "scripts" / "scaling_sweep.py"), "--from-json",
                            str(tmp_path / "old.json"), "--out", str(tmp_path / "again")],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]
    data = json.loads((tmp_path / "again" / "scaling.json").read_text())
    assert data["projection"]["stages"]["fit_siren"]["work_factor"] == pytest.approx(factor / 2)
    fit = data["run_config"]["fit"]  # and the page says what the points ran at
    assert f"stage 1 at {fit['steps']:,} steps of {fit['points']:,} points" in (tmp_path / "again" / "scaling.html"
                                                                                ).read_text()
    # points run under a --configfile overlay ran at its settings: the record says so
    (tmp_path / "o.yaml").write_text("fit: {steps: 123}\n")
    over = subprocess.run([sys.executable, str(REPO / "scripts" / "scaling_sweep.py"), "--lights", "8", "32",
                           "--out", str(tmp_path), "--collect", "--configfile", str(tmp_path / "o.yaml")],
                          capture_output=True, text=True, timeout=300)
    assert over.returncode == 0, over.stderr[-2000:]
    assert json.loads((tmp_path / "scaling.json").read_text())["run_config"]["fit"]["steps"] == 123


def test_a_gpu_bench_of_the_paper_config_replaces_the_cpu_upper_bounds(tmp_path):
    """Stages that `bench stages` timed on a GPU are projected from it (step x the paper's steps, x the A100
    factor; fit_siren per job, jobs four to a node); the others keep the CPU-based upper bound, and the profile
    names each rule's source; no benched stage asks under BENCH_FLOOR_H. A bench from a CPU is refused."""
    data = scaling.sweep([_point(tmp_path, n) for n in (8, 32)])
    run = config.load_run(REPO / "config" / "config.yaml")
    gpu = {"fit_siren": {"wall_s": 2.0 * 8 / 4}, "train_diffusion": {"wall_s": 10.0 * 8 ** 0.5 * 2},
           "preoptimize": {"wall_s": 1.0}}
    proj = scaling.project(data, run, run, gpu, lights=200, subset=50, stage1_nodes=1)
    bench = {"device": "NVIDIA H200", "device_type": "cuda", "torch": "2.x", "cuda": "13.0", "config": "paper",
             "stages": {"fit_siren": {"projected_s": 3600.0, "units": 50},
                        "finetune_render": {"projected_s": 7200.0, "units": 1},
                        "eval_truth": {"projected_s": 60.0, "units": 32}}}
    out = scaling.measured_projection(proj, bench)
    # a benched stage of a minute still asks the floor: the bench times steps, not a job's start-up and checks
    assert out["stages"]["eval_truth"]["walltime_request_h"] == scaling.BENCH_FLOOR_H
    fit, ft, diff = (out["stages"][s] for s in ("fit_siren", "finetune_render", "train_diffusion"))
    assert fit["walltime_request_h"] == pytest.approx(1.0 * scaling.A100_PER_H200 * scaling.MARGIN)
    # 4 jobs in the projection's 3 rounds on one node: 3 node jobs of an hour each (x the A100 factor)
    assert fit["node_hours"] == pytest.approx(3 * scaling.A100_PER_H200)
    assert fit["wall_s"] == pytest.approx(3 * 3600 * scaling.A100_PER_H200)
    assert ft["wall_s"] == pytest.approx(7200 * scaling.A100_PER_H200) and ft["rss_mib"] is None
    assert diff == {**proj["stages"]["train_diffusion"], "source": scaling.CPU_SOURCE}
    text = scaling.polaris_profile(out)
    assert "fit_siren:  # bench stages on NVIDIA H200" in text and "upper bound" in text
    assert "finetune_render:  # bench" in text
    with_rss = sum(1 for r in out["measured"].values() if r["rss_mib"])
    assert text.count("    mem_mb: ") == len(out["stages"]) - 2 + with_rss
    with pytest.raises(ValueError, match="measured on 'cpu'"):
        scaling.measured_projection(proj, {**bench, "device": "cpu", "device_type": "cpu"})


def test_equal_bytes_sets_the_model_against_the_best_stored_cache_no_larger():
    from diffshadow.scaling.rate_distortion import equal_bytes

    rows = [{"cache": "stored SIRENs fp32", "kind": "stored", "bytes": 400, "unseen_psnr": 39.0},
            {"cache": "stored SIRENs fp16", "kind": "codec", "bytes": 200, "unseen_psnr": 38.9},
            {"cache": "stored SIRENs basis-4", "kind": "codec", "bytes": 50, "unseen_psnr": 30.0},
            {"cache": "dense shadow grids fp16", "kind": "grids", "bytes": 100, "unseen_psnr": 41.0},
            {"cache": "diffusion model fp16", "kind": "model", "bytes": 300, "unseen_psnr": 38.0}]
    eq = equal_bytes(rows)
    assert eq["best"] == "stored SIRENs fp16" and eq["model_gain_db"] == pytest.approx(-0.9)  # fp32 is larger
    assert equal_bytes(rows[:4]) is None  # no model at this point
    assert equal_bytes(rows[3:])["best"] is None  # nothing stored as small


def test_the_caches_study_keeps_a_full_runs_own_model_rows(tmp_path):
    """A full run's caches.json measured its model (and the mix) on the same points: those rows stay. A
    stage-1-only run's table has none, so it gets the sweep's model at its light count, naming where from."""
    from diffshadow.scaling.rate_distortion import collect, markdown

    stored = {"cache": "stored SIRENs fp32", "kind": "stored", "bytes": 400, "seen_psnr": 41.0, "unseen_psnr": 40.0}
    own = [{"cache": f"diffusion model {c}", "kind": "model", "bytes": b, "seen_psnr": 38.0, "unseen_psnr": 37.5}
           for c, b in (("fp32", 2000), ("fp16", 1000))]
    mix = {"cache": "model 0 + stored SIRENs 1, both fp16", "kind": "mix", "share": 0.0, "bytes": 1200,
           "seen_psnr": 41.0, "unseen_psnr": 40.0}
    runs = []
    for n, rows in ((8, [stored, *own, mix]), (32, [stored])):
        res = tmp_path / f"lights_{n}"
        res.mkdir()
        (res / "caches.json").write_text(json.dumps({"lights": {"train": n, "unseen": 4}, "caches": rows}))
        runs.append(res)
    # the sweep mixed the model's SIRENs with the blend: "generated" is the mix's answer, "model_alone" the model's
    sweep_points = [{"lights": n, "storage_bytes": {"model": 3000},
                     "quality": {"seen": {"generated": 41.0, "model_alone": 39.0},
                                 "unseen": {"generated": 40.0, "model_alone": 36.0}}} for n in (8, 32)]
    table = collect(runs, sweep_points, "sweep/scaling.json")
    full, stage1 = table["points"]
    assert [r["cache"] for r in full["caches"]] == [r["cache"] for r in (stored, *own, mix)]
    assert full["equal_bytes"]["model_unseen_psnr"] == 37.5  # its own model, not the sweep's 36.0
    model = [r for r in stage1["caches"] if r["kind"] == "model"]
    assert [(r["bytes"], r["seen_psnr"], r["unseen_psnr"]) for r in model] == [(3000, 39.0, 36.0), (1500, 39.0, 36.0)]
    assert model[0]["source"].startswith("sweep/scaling.json")
    # an old sweep (no mix) has only "generated", the model's own
    old = [{**p, "quality": {"seen": {"generated": 39.5}, "unseen": {"generated": 36.5}}} for p in sweep_points]
    assert [r["unseen_psnr"] for r in collect(runs, old)["points"][1]["caches"] if r["kind"] == "model"] == [36.5] * 2
    assert "| 8 | model 0 + stored SIRENs 1, both fp16 |" in markdown(table)
    # a run of another light layout than the sweep's (none recorded: cap) borrows no model rows
    (runs[1] / "lights.json").write_text(json.dumps({"layout": "rim"}))
    assert not [r for r in collect(runs, sweep_points)["points"][1]["caches"] if r["kind"] == "model"]
    assert [r for r in collect(runs, [{**p, "layout": "rim"} for p in sweep_points])["points"][1]["caches"]
            if r["kind"] == "model"]


def test_work_factors_count_what_each_stage_computes():
    """Fitting grows with steps x points x width²; the fine-tuning targets (exact shadows, no SIREN) with views x
    pixels, not with the SIRENs' width; evaluating SIRENs with width²."""
    import copy

    run = config.load_run(REPO / "config" / "config.yaml")
    paper = copy.deepcopy(run)
    paper["siren"]["width"] *= 2
    paper["fit"]["steps"] *= 3
    paper["finetune"]["views"] *= 2
    paper["finetune"]["image_size"] *= 2
    f = scaling.work_factors(run, paper)
    assert f["fit_siren"] == pytest.approx(3 * 4) and f["evaluate_images"] == pytest.approx(4)
    assert f["render_targets"] == pytest.approx(2 * 4)
    assert scaling.work_factors(run, run)["render_targets"] == 1.0
