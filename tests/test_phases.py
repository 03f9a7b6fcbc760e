"""Where a job's time goes (`diffshadow.phases`) and how stage_costs.tsv sums it per rule."""

import json
import os
import time

import pytest
from PIL import Image

from diffshadow import phases
from diffshadow.report import PHASE_COLUMNS, stage_costs


@pytest.fixture(autouse=True)
def clean_clock():
    phases.reset()
    yield
    phases.reset()


def test_phases_do_not_nest_and_add_up_to_the_process_life():
    with phases.phase("io"):
        time.sleep(0.05)
        with phases.phase("compile"):  # inside io: counted to io, not twice
            time.sleep(0.05)
    with phases.phase("device"):
        time.sleep(0.02)
    t = phases.totals()
    assert t["io"] == pytest.approx(0.10, abs=0.03) and t["compile"] == 0.0
    assert t["device"] == pytest.approx(0.02, abs=0.02)
    assert sum(t.values()) == pytest.approx(phases.process_age(), abs=0.01)
    assert t["compute"] >= 0


def test_timed_counts_every_call_and_unknown_phases_are_refused():
    @phases.timed("io")
    def read():
        time.sleep(0.01)
        return 3

    assert read() + read() == 6 and phases.totals()["io"] >= 0.02
    with pytest.raises(ValueError, match="phase: expected one of import, device, compile, io, got 'compute'"):
        with phases.phase("compute"):
            pass


def test_imports_before_main_count_as_import():
    phases.mark_imports_done()
    t = phases.totals()
    assert t["import"] > 0 and t["import"] <= phases.process_age()


USAGE = """
import json, sys, time
import numpy as np
from diffshadow import phases
before = phases.usage()
block = np.ones(300 * 2**20 // 8)  # 300 MiB, every page written
del block
end = time.process_time() + 0.5
while time.process_time() < end:  # half a second of this process's CPU
    pass
print(json.dumps({"before": before, "after": phases.usage()}))
"""


def test_a_process_counts_its_own_cpu_seconds_and_peak_memory():
    """A fresh process: 300 MiB written and freed, then half a CPU-second spun, show in `usage` afterwards and not
    before; a freed block still counts, as the peak it was. Started by a shell, as the workflow starts its jobs: a
    process forked straight from this (large) one would start at its resident set (`phases.usage`)."""
    import shlex
    import subprocess
    import sys

    command = f"{shlex.quote(sys.executable)} -c {shlex.quote(USAGE)}; exit $?"  # not the shell's last command
    done = subprocess.run(["/bin/sh", "-c", command], capture_output=True, text=True, check=True)
    rec = json.loads(done.stdout)
    before, after = rec["before"], rec["after"]
    assert before["max_rss_mib"] < 290 <= after["max_rss_mib"]
    assert after["cpu_s"] - before["cpu_s"] >= 0.48  # os.times counts in clock ticks (10 ms)


HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def test_stage_costs_sum_each_rules_phases_and_the_launch_outside_its_process(tmp_path):
    for name, wall, rec in (("fit_siren_0", 10.0, dict(import_s=1, device_s=0.5, compile_s=0, io_s=0.5, compute_s=6)),
                            ("fit_siren_1", 12.0, dict(import_s=1, device_s=0.5, compile_s=2, io_s=0.5, compute_s=7)),
                            ("lights", 1.0, None)):  # a job of an older run: no phases file
        path = tmp_path / f"{name}.tsv"
        path.write_text(HEADER + f"{wall}\t0:00:10\t100\t0\t0\t0\t0\t0\t0\t{wall}\n")
        if rec:
            (tmp_path / f"{name}.phases.json").write_text(json.dumps({**rec, "process_s": sum(rec.values())}))
        os.utime(path, (100.0, 100.0))
    benchmarks = [tmp_path / f"{name}.tsv" for name in ("fit_siren_0", "fit_siren_1", "lights")]
    rows = {r["stage"]: r for r in stage_costs(benchmarks, tmp_path / "out" / "costs.tsv")}
    fit = rows["fit_siren"]
    assert (fit["import_s"], fit["compile_s"], fit["compute_s"], fit["launch_s"]) == (2, 2, 13, 3.0)
    assert sum(fit[k] for k in PHASE_COLUMNS) == pytest.approx(fit["wall_s"])
    assert rows["lights"]["compute_s"] is None and rows["total (sum over jobs)"]["io_s"] is None
    lines = (tmp_path / "out" / "costs.tsv").read_text().splitlines()
    assert lines[0].split("\t")[-len(PHASE_COLUMNS) - 1:] == [*PHASE_COLUMNS, "critical_s"]
    lights = next(line for line in lines if line.startswith("lights\t")).split("\t")
    assert lights[-len(PHASE_COLUMNS) - 1:-1] == ["NA"] * len(PHASE_COLUMNS)
    (tmp_path / "fit_siren_0.phases.json").write_text("{}")
    with pytest.raises(ValueError, match=r"fit_siren_0.phases.json: expected a phases file \(import_s"):
        stage_costs(benchmarks, tmp_path / "out" / "costs.tsv")


def test_the_timeline_puts_each_job_on_the_runs_clock_without_a_reruns_idle_days(tmp_path):
    """A job ran from its benchmark file's time back by its wall seconds. A stretch of over a minute with no job
    running (a rerun the next day) leaves the clock, a shorter one (Snakemake between two jobs) stays; start-up is
    imports, device start and the time outside the process; the figure and `stage-costs --timeline` draw it."""
    from diffshadow.cli import main
    from diffshadow.report import IDLE_S, job_spans

    jobs = (("prepare_volume", 2.0, 102.0, None),  # an older run's job: no phases file, no start-up known
            ("fit_siren_0", 10.0, 110.0, dict(import_s=1, device_s=0.5, compile_s=0, io_s=0.5, compute_s=6)),
            ("fit_siren_1", 10.0, 115.0, dict(import_s=1, device_s=0.5, compile_s=2, io_s=0.5, compute_s=5)),
            ("train_diffusion", 20.0, 145.0, dict(import_s=1, device_s=0, compile_s=0, io_s=0, compute_s=18)),
            ("summary", 1.0, 145.0 + 86400 + 1.0, dict(import_s=0.2, device_s=0, compile_s=0, io_s=0,
                                                          compute_s=0.5)))
    for name, wall, end, rec in jobs:
        path = tmp_path / f"{name}.tsv"
        path.write_text(HEADER + f"{wall}\t0:00:10\t100\t0\t0\t0\t0\t0\t0\t{wall}\n")
        if rec:
            (tmp_path / f"{name}.phases.json").write_text(json.dumps({**rec, "process_s": sum(rec.values())}))
        os.utime(path, (end, end))
    benchmarks = [tmp_path / f"{name}.tsv" for name, *_ in reversed(jobs)]
    spans, gaps = job_spans(benchmarks)
    assert [(j["job"], j["start"], j["end"]) for j in spans] == [
        ("fit_siren_0", 0, 10), ("prepare_volume", 0, 2), ("fit_siren_1", 5, 15),  # equal starts: by name
        ("train_diffusion", 25, 45),  # 10 s after the fits with nothing running: kept, under IDLE_S
        ("summary", 45, 46)]  # a day later: the day left out
    assert gaps == [45] and 10 < IDLE_S < 86400
    assert [j["stage"] for j in spans] == ["fit_siren", "prepare_volume", "fit_siren", "train_diffusion", "summary"]
    assert (spans[1]["startup"], spans[2]["startup"], spans[2]["compile"]) == (0, 1 + 0.5 + 1.0, 2)
    with pytest.raises(ValueError, match="no benchmark files"):
        job_spans([])
    main(["stage-costs", "--benchmarks", *map(str, benchmarks), "--out", str(tmp_path / "costs.tsv"),
          "--timeline", str(tmp_path / "report" / "timeline.png")])
    with Image.open(tmp_path / "report" / "timeline.png") as png:
        assert png.format == "PNG" and png.width == 900  # 9 x 100 dpi


def test_the_critical_path_is_the_chain_of_jobs_the_runs_end_waited_on(tmp_path):
    """From the job that ended last, back through the job whose end each one's start waited on (its input's
    maker, or a slot's: train_diffusion waits for naive_images, not for collect_weights), to the first; a job
    that started long after any end (a queue's wait) keeps the time between in the path's length, not its work.
    stage_costs.tsv and the summary's run-cost row say it per rule."""
    from diffshadow.report import critical_path, job_spans
    from diffshadow.summary import critical_words

    jobs = (("lights", 0, 1), ("prepare_volume", 0, 2), ("fit_siren_0", 2, 12), ("fit_siren_1", 2, 10),
            ("naive_images", 3, 30), ("collect_weights", 12, 13), ("train_diffusion", 30, 50),
            ("sample_shadows", 50.3, 55), ("benchmark", 50, 250), ("report_figures", 240, 260))
    for name, start, end in jobs:
        path = tmp_path / f"{name}.tsv"
        path.write_text(HEADER + f"{end - start}\t0:00:10\t100\t0\t0\t0\t0\t0\t0\t1\n")
        os.utime(path, (1000.0 + end, 1000.0 + end))
    benchmarks = [tmp_path / f"{name}.tsv" for name, *_ in jobs]
    path = critical_path(job_spans(benchmarks)[0])
    assert [j["job"] for j in path] == ["prepare_volume", "naive_images", "train_diffusion", "sample_shadows",
                                        "report_figures"]
    assert critical_path([]) == []
    rows = {r["stage"]: r for r in stage_costs(benchmarks, tmp_path / "costs.tsv")}
    assert rows["naive_images"]["critical_s"] == 27 and rows["fit_siren"]["critical_s"] == 0
    assert rows["total (sum over jobs)"]["critical_s"] == pytest.approx(2 + 27 + 20 + 4.7 + 20)
    assert rows["elapsed (a job running)"]["critical_s"] == 260
    lines = (tmp_path / "costs.tsv").read_text().splitlines()
    costs = [dict(zip(lines[0].split("\t"), line.split("\t"), strict=True)) for line in lines[1:]]
    assert critical_words(costs) == (
        "; the critical path (the timeline's framed jobs) 4.3 min: naive_images 27 s, train_diffusion 20 s, "
        "report_figures 20 s, sample_shadows 5 s and 1 more rule, and 3.1 min between its jobs while others ran "
        "(a batch queue's waits)")
    assert critical_words([{k: v for k, v in r.items() if k != "critical_s"} for r in costs]) == ""  # an older run


def test_a_jobs_cpu_seconds_and_peak_are_the_larger_of_snakemakes_polls_and_its_own_record(tmp_path):
    """Snakemake polls every 30 s, so a 41-s job read 15 CPU-s; the process's own count misses torchrun's other
    ranks. Each is a lower bound: the larger is taken, per job, before a rule's jobs are summed."""
    phases_of = dict(import_s=1, device_s=0, compile_s=0, io_s=0, compute_s=8)
    jobs = (("fit_siren_0", 15.0, 100, {"cpu_s": 38.5, "max_rss_mib": 60}),  # polls missed the end
            ("fit_siren_1", 15.0, 700, {"cpu_s": 2.0, "max_rss_mib": 650}),  # the record missed other processes
            ("lights", 20.0, 30, None))  # an older run's job: Snakemake's alone
    for name, cpu, rss, own in jobs:
        path = tmp_path / f"{name}.tsv"
        path.write_text(HEADER + f"40.0\t0:00:40\t{rss}\t0\t0\t0\t0\t0\t0\t{cpu}\n")
        if own:
            (tmp_path / f"{name}.phases.json").write_text(json.dumps({**phases_of, **own}))
    rows = {r["stage"]: r for r in stage_costs([tmp_path / f"{n}.tsv" for n, *_ in jobs], tmp_path / "costs.tsv")}
    assert (rows["fit_siren"]["cpu_s"], rows["fit_siren"]["max_rss_mib"]) == (38.5 + 15.0, 700)
    assert (rows["lights"]["cpu_s"], rows["lights"]["max_rss_mib"]) == (20.0, 30)
    (tmp_path / "lights.phases.json").write_text(json.dumps({**phases_of, "cpu_s": "many"}))
    with pytest.raises(ValueError, match=r"lights.phases.json: cpu_s and max_rss_mib: expected numbers, got 'many'"):
        stage_costs([tmp_path / "lights.tsv"], tmp_path / "costs.tsv")


def test_jobs_on_different_cpu_kernels_or_library_releases_are_named(tmp_path):
    """A run whose jobs ran on different PyTorch CPU kernels (their phases files' cpu_capability), or under
    different releases of a numeric library (their `versions`: a run resumed after an upgrade), is warned of, each
    kind with its jobs; jobs that agree, or recorded none (torch-free jobs, older runs), are not."""
    from diffshadow.report import mixed_runtimes

    def job(name: str, kind: str | None, torch_release: str | None = "2.13.0"):
        (tmp_path / f"{name}.phases.json").write_text(json.dumps({
            "compute_s": 1.0, **({"cpu_capability": kind} if kind else {}),
            "versions": {"python": "3.11.7", "numpy": "2.5.5", **({"torch": torch_release} if torch_release else {})}}))
        return tmp_path / f"{name}.tsv"

    agree = [job("fit_siren_0", "AVX2"), job("fit_siren_1", "AVX2"), job("lights", None, None), tmp_path / "old.tsv"]
    (tmp_path / "odd.phases.json").write_text(json.dumps({"compute_s": 1.0, "versions": "2.13"}))  # not ours
    assert mixed_runtimes([*agree, tmp_path / "odd.tsv"]) == [] and mixed_runtimes([]) == []
    said = mixed_runtimes([*agree, job("fit_siren_2", "DEFAULT")])
    assert said == ["WARNING: this run's jobs ran on different PyTorch CPU kernels (AVX2: fit_siren_0, fit_siren_1 "
                    "(2 jobs); DEFAULT: fit_siren_2 (1 job)); their results differ in the last bits"]
    said = mixed_runtimes([*agree, job("fit_siren_2", "AVX2", "2.3.0+cu121")])
    assert said == ["WARNING: this run's jobs ran under different releases of torch (2.13.0: fit_siren_0, "
                    "fit_siren_1 (2 jobs); 2.3.0+cu121: fit_siren_2 (1 job)); their results may differ"]


def test_a_jobs_record_names_the_releases_it_ran_under_without_importing_them():
    import subprocess
    import sys

    code = ("import json, sys; from diffshadow.phases import record; r = record('x'); "
            "print(json.dumps([r['versions'], sorted(m for m in ('torch', 'zarr', 'scipy') if m in sys.modules)]))")
    found, imported = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                                check=True).stdout)
    assert found == {"python": ".".join(map(str, sys.version_info[:3]))} and imported == []
    import numpy
    import torch

    from diffshadow.phases import record

    versions = record("x")["versions"]
    assert versions["torch"] == torch.__version__ and versions["numpy"] == numpy.__version__
