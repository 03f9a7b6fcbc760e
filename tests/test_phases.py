"""Where a job's time goes (`diffshadow.phases`) and how stage_costs.tsv sums it per rule."""

import json
import os
import time

import pytest

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
    assert lines[0].split("\t")[-len(PHASE_COLUMNS):] == list(PHASE_COLUMNS)
    lights = next(line for line in lines if line.startswith("lights\t")).split("\t")
    assert lights[-len(PHASE_COLUMNS):] == ["NA"] * len(PHASE_COLUMNS)
    (tmp_path / "fit_siren_0.phases.json").write_text("{}")
    with pytest.raises(ValueError, match=r"fit_siren_0.phases.json: expected a phases file \(import_s"):
        stage_costs(benchmarks, tmp_path / "out" / "costs.tsv")
