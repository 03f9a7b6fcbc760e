"""The sweep (or a GPU's `bench stages`) carried to the paper's scale on Polaris: each stage's A100 time,
node-hours, walltime requests and memory, and the workflow profile that asks for them."""

from __future__ import annotations

import functools
import json
import math

from diffshadow.scaling.sweep import predict

# An assumption, not a measurement: an A100 takes this many times an H200's time for this project's work. The
# HBM bandwidth ratio (4.8 / 2.0 TB/s); fp32 peaks differ by 3.4x, launch-bound small kernels by ~1x.
A100_PER_H200 = 2.4
GPUS_PER_NODE = 4  # Polaris


def model_size(cfg: dict) -> tuple[int, int]:
    """(parameters, tokens) of the diffusion model a run config builds."""
    return _model_size(json.dumps(cfg["siren"], sort_keys=True), json.dumps(cfg["diffusion"], sort_keys=True))


@functools.lru_cache(maxsize=8)
def _model_size(siren_json: str, diffusion_json: str) -> tuple[int, int]:
    # built once per config: the paper's model has 172 million parameters
    from diffshadow.diffusion.config import DiffusionConfig, build_model
    from diffshadow.siren import SirenConfig, WeightLayout

    siren = SirenConfig.from_config(json.loads(siren_json))
    diffusion = DiffusionConfig.from_config(json.loads(diffusion_json)).for_siren(siren.width)
    model = build_model(WeightLayout.for_siren(siren), diffusion)
    return model.n_params(), len(model.sizes) + 2


def model_cost(cfg: dict) -> float:
    """Parameters x tokens of the diffusion model a run config builds: its forward cost up to a constant."""
    params, tokens = model_size(cfg)
    return float(params * tokens)


# The run config's sections that `work_factors` reads: a sweep records them (scaling.json's `run_config`), since
# config/config.yaml moves on after its points ran
RUN_CONFIG_SECTIONS = ("fit", "siren", "diffusion", "finetune")


def work_factors(run: dict, paper: dict) -> dict[str, float]:
    """Per stage, the paper config's work per light (or per job) over the run config's, from what each stage
    computes (the light count is the sweep's exponent's business): fitting costs steps x points x width² per
    light; the diffusion stages cost their model's parameters x tokens per sample, times epochs (and views and
    sampled pixels, over GPUs, for fine-tuning); evaluating and rendering SIRENs costs width²; the fine-tuning
    targets (exact shadows, no SIREN: a grid swept per light, which does not grow, then views x pixels read from
    it) at most views x pixels. Other stages: 1.
    Upper bounds on a GPU: small networks leave it idle, large ones use it better."""
    fit = {k: paper["fit"][k] / run["fit"][k] for k in ("steps", "points")}
    width2 = (paper["siren"]["width"] / run["siren"]["width"]) ** 2
    model = model_cost(paper) / model_cost(run)
    epochs = paper["diffusion"]["epochs"] / run["diffusion"]["epochs"]
    ft = paper["finetune"]
    # a step samples `pixels` per view per light (the target images' size changes only render_targets)
    finetune = (ft["epochs"] / run["finetune"]["epochs"]) * (ft["views"] / run["finetune"]["views"]) * (
        ft["pixels"] / run["finetune"]["pixels"]) * model / (ft["nproc"] / run["finetune"]["nproc"])
    targets = (ft["views"] / run["finetune"]["views"]) * (ft["image_size"] / run["finetune"]["image_size"]) ** 2
    fitting = fit["steps"] * fit["points"] * width2
    return {"fit_siren": fitting, "preoptimize": fitting, "train_diffusion": epochs * model,
            "finetune_render": finetune, "sample_shadows": model,
            "evaluate_images": width2, "render_targets": targets, "benchmark": width2}


QUEUE_MAX_H = 72.0  # Polaris' preemptable queue's longest walltime (ALCF's documentation; check `qstat -Qf`)
MARGIN = 1.5  # requests are the projection times this
# A stage timed by `bench stages` asks at least this: the bench times steps, not a job's start-up, its
# checkpoints, its periodic checks or its outputs (at the README's sizes on the H200 those were 14 of
# fit_siren's 19 s, stage_costs.tsv against 1,000 steps of 5.6 ms)
BENCH_FLOOR_H = 0.5


def fit_rounds(paper: dict, lights: int, subset: int) -> list[int]:
    """Stage 1's fit jobs per round (`fit.rounds`: a subset waits for the earlier-round neighbours it holds) for
    the paper config at `lights` training lights in subsets of `subset`, its sphere grown with the light count (the
    same cap fraction): [15, 11, 8, 6] at the paper's 2,000 in 40 subsets; one round without `fit.rounds`."""
    from diffshadow.seams import subset_inputs

    ls = paper["lights"]
    sphere = max(int(ls["sphere"]), round(int(ls["sphere"]) * lights / int(ls["count"])))
    rounds, _ = subset_inputs({**paper, "subset_size": subset, "lights": {**ls, "count": lights, "sphere": sphere}})
    return [rounds.count(r) for r in range(max(rounds) + 1)]


def project(data: dict, run: dict, paper: dict, gpu_costs: dict[str, dict], *, lights: int | None = None,
            subset: int | None = None, stage1_nodes: int = 10) -> dict:
    """Each stage's wall time, node-hours and peak memory for `paper` at `lights` (default: the paper config's
    count, in subsets of its subset_size) on Polaris: the sweep's CPU
    power law carried to `lights` at the run's config, divided by the H200's speed over this CPU measured on
    the same run config at the sweep's smallest point (`gpu_costs`: stage_costs of a GPU run), times the
    paper's work per light (`work_factors`), times A100_PER_H200. Memory: the largest of the sweep's peak RSS carried
    the same way, the job's RSS on the GPU run, and the job's peak on a CPU at the paper's sizes
    (`PAPER_CPU_RSS_MIB`; per process for finetune_render, x its processes). Rules timed at the paper's sizes
    (PAPER_CPU_S) are not carried: `measured` gives their time and peak RSS there.

    Upper bounds: the small run's GPU jobs are mostly start-up, so where the H200 measured slower than the CPU
    it is taken as fast as the CPU (1x); preoptimize, one fit, takes fit_siren's speed-up. Stage 1 runs
    lights / subset jobs four to a node on `stage1_nodes` nodes; fine-tuning on one node of four GPUs; every
    other stage on one node. Requests: MARGIN x the projection, at most QUEUE_MAX_H; a stage that needs more
    resumes from its checkpoint in further jobs (`resubmits`). Under `fit.rounds` stage 1's jobs run in rounds
    (`fit_rounds`, recorded as `fit_rounds`): its wall is a job's time per wave of each round."""
    lights = lights or paper["lights"]["count"]
    subset = subset or paper["subset_size"]
    rounds = fit_rounds(paper, lights, subset)
    n0 = data["points"][0]["lights"]
    factors = work_factors(run, paper)

    def measured_ratio(stage):
        cpu_n0 = dict((int(n), y) for n, y in data["fits"][stage]["wall_s"]["points"]).get(n0)
        gpu = gpu_costs.get(stage)
        return cpu_n0 / gpu["wall_s"] if cpu_n0 and gpu else None

    rows = {}
    for stage, fit in data["fits"].items():
        if stage in PAPER_CPU_S:  # measured at the paper's sizes (polaris_profile asks for that)
            continue
        cpu_total = predict(fit["wall_s"], lights)
        exponent = fit["wall_s"]["exponent"]
        if "wall_s_per_epoch" in fit and cpu_total is not None:  # at the run config's epochs, as work_factors counts
            cpu_total = predict(fit["wall_s_per_epoch"], lights) * run["diffusion"]["epochs"]
            exponent = fit["wall_s_per_epoch"]["exponent"]
        ratio = measured_ratio("fit_siren" if stage == "preoptimize" else stage)
        if cpu_total is None or ratio is None:
            continue
        used = max(ratio, 1.0)
        a100_total = cpu_total / used * factors.get(stage, 1.0) * A100_PER_H200  # all jobs of the stage
        rss = predict(fit["max_rss_mib"], lights) or fit["max_rss_mib"]["points"][-1][1]
        # A job on a GPU node holds at least what the same job held on the H200 at the run's sizes (CUDA's host
        # context and libraries: 505 MiB for `lights`, which the CPU sweep measured at 41)
        gpu_rss = float(gpu_costs.get(stage, {}).get("max_rss_mib") or 0.0)
        paper_rss = paper_cpu_rss_mib(stage, paper)
        rows[stage] = {"exponent": exponent, "cpu_s_run_config": cpu_total,
                       "h200_over_cpu": ratio, "speedup_used": used, "work_factor": factors.get(stage, 1.0),
                       **_schedule(stage, a100_total, rounds, stage1_nodes),
                       "rss_mib_run_config": rss, "rss_mib_gpu_run": gpu_rss, "rss_mib_paper_cpu": paper_rss,
                       "rss_mib": max(rss, gpu_rss, paper_rss)}
    # the CPU rules timed at the paper's sizes: one node each for the time measured
    measured = {stage: {"wall_s": cpu_s, "node_hours": cpu_s / 3600,
                        "walltime_request_h": min(cpu_s * MARGIN / 3600, QUEUE_MAX_H),
                        "rss_mib": paper_cpu_rss_mib(stage, paper) or None, "source": PAPER_CPU_SOURCE,
                        "only_with": PAPER_CPU_ONLY_WITH.get(stage)} for stage, cpu_s in sorted(PAPER_CPU_S.items())}
    return {"lights": lights, "a100_per_h200": A100_PER_H200, "margin": MARGIN, "queue_max_h": QUEUE_MAX_H,
            "fit_rounds": rounds, "stage1_nodes": stage1_nodes, "stages": rows, "measured": measured,
            "storage_bytes": storage_at(paper, [lights, paper["lights"]["sphere"]])}


CPU_SOURCE = "CPU sweep x the tiny run's H200 speed-up (upper bound)"


def measured_projection(proj: dict, bench: dict) -> dict:
    """`proj` (`project`) with each stage that `bench stages` measured at the paper config on a GPU (`bench`, its
    JSON) timed from that measurement instead: its seconds per step times the paper's steps, times A100_PER_H200
    (the same stated assumption) for Polaris' A100s, asking at least BENCH_FLOOR_H. Host memory stays the
    sweep's (the bench measures the GPU's). Stage 1's rounds and nodes are the projection's.
    Every row names its `source`; stages the bench did not time keep the CPU-based upper bound."""
    if bench.get("device_type") != "cuda":
        raise ValueError(f"bench stages JSON measured on {bench.get('device')!r}: the paper-scale plan needs one "
                         f"measured on a GPU (docs/measurements/<card>_bench_stages_paper.json)")
    out = {**proj, "stages": {k: {**v, "source": CPU_SOURCE} for k, v in proj["stages"].items()},
           "bench": {k: bench.get(k) for k in ("device", "torch", "cuda", "config")}}
    for stage, row in bench["stages"].items():
        jobs = sum(proj["fit_rounds"])  # fit_siren: the bench times one job of a subset (`units` SIRENs)
        total = row["projected_s"] * A100_PER_H200 * (jobs if stage == "fit_siren" else 1)
        plan = _schedule(stage, total, proj["fit_rounds"], proj["stage1_nodes"])
        plan["walltime_request_h"] = min(max(plan["walltime_request_h"], BENCH_FLOOR_H), QUEUE_MAX_H)
        out["stages"].setdefault(stage, {"rss_mib": None}).update(
            **plan, source=f"bench stages on {bench.get('device')} x "
                                                                 f"{A100_PER_H200}")
    return out


def _schedule(stage: str, a100_total: float, rounds: list[int], stage1_nodes: int) -> dict:
    """A stage's A100 seconds (all its jobs) as Polaris runs them: fit_siren's jobs (`rounds`: so many per round)
    four to a node job (the polaris profile's group-components), a round's node jobs on `stage1_nodes` nodes and
    the rounds one after another, any other stage one job on one node; its wall time, node-hours (a node job holds
    its node for a fit's time, however many of its four GPUs its round filled), and a job's walltime request
    (MARGIN x its time, at most QUEUE_MAX_H, `resubmits` more jobs resuming from the checkpoint)."""
    if stage == "fit_siren":
        per_job = a100_total / sum(rounds)
        node_jobs = [-(-n // GPUS_PER_NODE) for n in rounds]
        wall = per_job * sum(-(-n // stage1_nodes) for n in node_jobs)
        node_hours = per_job * sum(node_jobs) / 3600
    else:
        wall = per_job = a100_total
        node_hours = a100_total / 3600
    request_h = per_job * MARGIN / 3600
    return {"a100_s_total": a100_total, "wall_s": wall, "node_hours": node_hours,
            "walltime_request_h": min(request_h, QUEUE_MAX_H),
            "resubmits": max(0, math.ceil(request_h / QUEUE_MAX_H) - 1)}


def walltime(hours: float) -> str:
    """PBS's HH:MM:SS, rounded up to whole minutes."""
    minutes = max(1, math.ceil(hours * 60))
    return f"{minutes // 60:02d}:{minutes % 60:02d}:00"


# Rules timed on a CPU at the paper's sizes, whose time no carry can give: `caches` runs on the CPU (so no GPU speed
# applies) and mixes costs that grow by different factors at the paper's sizes (its SIRENs' width², the model's
# DDIM). It scored 13 rows of 2,500 SIRENs of width 128 at 16,384 points (about 3 min a row) and drew every light
# once with the model's DDIM (0.47 s a light) in 3,125 s on one thread (a count from unit costs had said ~100 min).
# `choose_cache` (`cache: auto` only) scored all 8 candidates for 2,000 width-128 SIRENs in 1,086 s on one thread,
# and `encode_cache` wrote them through basis-256, the costliest codec, in 255 s. `evaluate_voxels` (the CPU's
# under `evaluate.device: cpu`) took 1,169 s with the geometry stage's checkpoint beside the model's, as in a run
# that fine-tunes; the carry, by the SIRENs' width² alone, asked 59 min. Each is asked for at MARGIN x its time,
# over any carry (docs/performance.md, "Measured at the paper's sizes").
PAPER_CPU_S = {"caches": 3125.0, "choose_cache": 1086.0, "encode_cache": 255.0, "evaluate_voxels": 1169.0}
# Peak RSS (MiB, the kernel's: `/usr/bin/time -v` or the job's getrusage) of a job at the paper's sizes on a CPU,
# the memory request (x MARGIN) of the rules in PAPER_CPU_S. For a rule timed on a GPU it bounds the job's host
# memory from above, since on a GPU the model, its gradients, Adam's moments and the activations live on the device:
# train_diffusion (one epoch, 2,256 lights with the pool; a7851f7) from the paper-size run, and sample_shadows from that
# run's command after the mix in passes and apart (docs/performance.md, "Measured at the paper's sizes" and "The
# allocator");
# finetune_render per process, from `bench stages --device cpu --threads 1 --configfile config/paper.yaml --stages
# finetune_render` (every process holds the targets of 2,000 lights x 7 views at their 2,095 foreground pixels a
# view, 0.35 GB: 9,235 MiB when it held the whole 128² images, 2.75 GB, side by side).
PAPER_CPU_RSS_MIB = {"caches": 10818.0, "choose_cache": 9504.0, "encode_cache": 7100.0, "evaluate_voxels": 6277.0,
                     "train_diffusion": 6727.0, "sample_shadows": 6823.0, "finetune_render": 7038.0}
PAPER_CPU_SOURCE = "one CPU thread at the paper's sizes, measured"
PAPER_CPU_ONLY_WITH = {"choose_cache": "cache: auto", "encode_cache": "a codec's cache"}  # not the paper's run


def paper_cpu_rss_mib(stage: str, paper: dict) -> float:
    """A job's peak host memory (MiB) measured on a CPU at the paper's sizes (0: not measured): per process, times
    fine-tuning's processes on the node."""
    rss = PAPER_CPU_RSS_MIB.get(stage, 0.0)
    return rss * paper["finetune"]["nproc"] if stage == "finetune_render" else rss


def polaris_profile(proj: dict) -> str:
    """A Snakemake workflow profile (`--workflow-profile`) whose per-rule walltimes are the projection's
    requests; laid over `--profile polaris`, it replaces the profile's guesses. `mem_mb`: the largest of the peak
    RSS carried to the light count, the job's RSS on the H200 and its peak on a CPU at the paper's sizes, x margin
    (Polaris nodes are whole: 512 GB; Snakemake checks it, qsub is not sent it).
    The rules measured at the paper's sizes (`proj["measured"]`) ask MARGIN x their time and peak RSS."""
    lines = ["# Made by scripts/scaling_sweep.py from the light-count sweep (diffshadow.scaling.project): each",
             f"# rule's projected A100 time at {proj['lights']:,} lights x {proj['margin']}, at most "
             f"{proj['queue_max_h']:.0f} h",
             "# (a longer stage resumes from its checkpoint in a further job); mem_mb: the largest of the peak RSS",
             "# carried to that light count, the job's RSS on the H200 and its peak on a CPU at the paper's sizes",
             "# (scaling.PAPER_CPU_RSS_MIB), x the margin (a Polaris node has 512 GB). Rules measured on one CPU",
             "# thread at the paper's sizes ask the margin x that time and peak RSS. Use:",
             "#   snakemake --profile polaris --workflow-profile profiles/paper --configfile config/paper.yaml",
             "set-resources:"]
    # then the rules measured at the paper's sizes, which `project` does not carry: every rule is listed, since a
    # workflow profile's set-resources replaces the machine profile's whole
    for stage, r in [*sorted(proj["stages"].items()), *proj["measured"].items()]:
        lines.append(f"  {stage}:  # {r.get('source', CPU_SOURCE)}")
        lines.append(f"    walltime: \"{walltime(r['walltime_request_h'])}\"")
        if r.get("rss_mib"):
            lines.append(f"    mem_mb: {_mem_mb(r['rss_mib'], proj['margin'])}")
    return "\n".join(lines) + "\n"


def _mem_mb(rss_mib: float, margin: float) -> int:
    """Snakemake's mem_mb (MB) for a peak of `rss_mib` MiB x `margin`, rounded up to 100 MB."""
    return math.ceil(rss_mib * margin * 1.048576 / 100) * 100


def storage_at(cfg: dict, counts: list[int]) -> dict:
    """Stored SIRENs (fp32, fp16) and the model (fp32) for a config, at each light count."""
    from diffshadow.siren import SirenConfig, WeightLayout

    per = WeightLayout.for_siren(SirenConfig.from_config(cfg["siren"])).n_params * 4
    model = model_size(cfg)[0] * 4
    return {str(n): {"sirens_fp32": per * n, "sirens_fp16": per * n // 2, "model": model} for n in counts}
