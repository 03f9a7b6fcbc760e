"""The light-count sweep: what each stage costs, how good the cache is and how much it stores, against the
number of training lights. Reads finished runs (`results/<scene>/` of one run per light count: its
`stage_costs.tsv` and `voxel_metrics.json`), fits a power law per stage, writes one JSON, three figures and a
page. It does not run anything: `scripts/scaling_sweep.py` drives the workflow once per point.

Storage per point: the stored SIRENs (fp32 and fp16), the dense shadow grids they replace (fp32, the volume's
grid per light) and the diffusion model's weights (fp32). The model does not grow with the lights, the others
do in proportion, so the model is smaller than the SIRENs it replaces past `crossover` lights.

By concern: `sweep` reads the finished runs and fits the power laws, `projection` carries them (or a GPU's
`bench stages`) to the paper's scale on Polaris and writes its workflow profile, `figures` draws the figures
and the page, `rate_distortion` sets each point's caches (codecs of the stored SIRENs, grids) beside the model.
"""

from diffshadow.scaling.figures import cost_figure, page, projection_html, quality_figure, storage_figure, write_sweep
from diffshadow.scaling.projection import (
    A100_PER_H200,
    BENCH_FLOOR_H,
    CPU_SOURCE,
    GPUS_PER_NODE,
    MARGIN,
    PAPER_CPU_RSS_MIB,
    PAPER_CPU_S,
    PAPER_CPU_SOURCE,
    QUEUE_MAX_H,
    RUN_CONFIG_SECTIONS,
    fit_rounds,
    measured_projection,
    model_cost,
    model_size,
    paper_cpu_rss_mib,
    polaris_profile,
    project,
    storage_at,
    walltime,
    work_factors,
)
from diffshadow.scaling.sweep import UNSEEN, SweepError, crossover, power_law, predict, read_costs, read_point, sweep

__all__ = ["A100_PER_H200", "BENCH_FLOOR_H", "CPU_SOURCE", "GPUS_PER_NODE", "MARGIN",
           "PAPER_CPU_RSS_MIB", "PAPER_CPU_S", "PAPER_CPU_SOURCE", "QUEUE_MAX_H",
           "RUN_CONFIG_SECTIONS", "UNSEEN", "SweepError", "cost_figure", "crossover", "fit_rounds",
           "measured_projection", "model_cost", "model_size",
           "page", "paper_cpu_rss_mib", "polaris_profile", "power_law", "predict", "project", "projection_html",
           "quality_figure", "read_costs", "read_point", "storage_at", "storage_figure", "sweep", "walltime",
           "work_factors", "write_sweep"]
