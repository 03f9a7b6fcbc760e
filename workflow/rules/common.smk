# Per-scene configuration and path helpers shared by the rules (look-ups only: the merge and its
# validation are diffshadow.config's, the same for the CLI and Parsl).
import json

from diffshadow.config import ConfigError as _ConfigError
from diffshadow.config import as_json as _as_json
from diffshadow.config import scene_config as _scene_config
from diffshadow.config import halo_where_used as _halo_where_used
from diffshadow.config import stage1_json as _stage1_json
from diffshadow.diffusion.mix import model_alone as _model_alone
from diffshadow.hpc import JOB_ENVIRONMENT as _JOB_ENVIRONMENT
from diffshadow.hpc import JOB_LOG as _JOB_LOG
from diffshadow.hpc import RUN_CORES_ENV as _RUN_CORES_ENV
from diffshadow.hpc import job_threads as _job_threads
from diffshadow.hpc import kernel_cache_environment as _kernel_cache_environment
from diffshadow.hpc import run_gpus as _run_gpus
from diffshadow.lights import check_subset as _check_subset
from diffshadow.lights import n_subsets as _n_subsets
from diffshadow.seams import subset_inputs as _subset_inputs
from diffshadow.report import shading_name as _shading_name
from diffshadow.volume import prepared_from as _prepared_from
from diffshadow.volume import run_path as _run_path

_SCENES = {}
# Result-neutral settings reach the jobs through their environment, not `params` (a changed param reruns the
# job): the run's `device` (the CLI's --config-device; --device and DIFFSHADOW_DEVICE win) and the launcher of
# finetune_render's DDP processes. A PBS job parses this file again, so it gets them too.
os.environ.update(DIFFSHADOW_CONFIG_DEVICE=config.get("device", "auto"),
                  DIFFSHADOW_TORCHRUN=config.get("torchrun", "diffshadow torchrun --standalone"))
# the run's cores, which fit_siren borrows while they idle (runtime.SpareThreads: the same bytes on any threads)
try:
    os.environ[_RUN_CORES_ENV] = str(workflow.cores)
except WorkflowError:  # no core count given (a dry run, a cluster's jobs): nothing to borrow
    os.environ.pop(_RUN_CORES_ENV, None)
# MKL in strict reproducible mode, so a job's bytes do not depend on its thread count (a user's own setting wins)
for _key, _value in _JOB_ENVIRONMENT.items():
    os.environ.setdefault(_key, _value)
# one compiled-kernel cache for the run's jobs (Triton's): results/.kernel-cache/ (a user's own wins)
for _key, _value in _kernel_cache_environment("results/.kernel-cache").items():
    os.environ.setdefault(_key, _value)
# and `deterministic`, which changes no byte on a CPU and only float summation order on a GPU; a user's own wins
os.environ.setdefault("DIFFSHADOW_DETERMINISTIC", "1" if config.get("deterministic") else "0")


# the NVIDIA GPUs the run's device reaches here (None: the CPU, or only PyTorch could tell), read once without it
_RUN_GPUS = _run_gpus(config.get("device", "auto"))


def device_threads(threads, processes=False):
    """A rule's CPU threads where its work runs on the run's device: one on a GPU (`hpc.job_threads`; with
    `processes`, one per GPU it can use), `threads` on a CPU. The HPC profiles' set-threads override it."""
    return _job_threads(threads, _RUN_GPUS, processes=processes)


def scene_config(scene):
    """config/scenes/<scene>.yaml over the run's config, validated (a typo fails at parse time)."""
    if scene not in _SCENES:
        _SCENES[scene] = _scene_config(config, scene, scenes_dir=os.path.join(workflow.basedir, "config", "scenes"))
    return _SCENES[scene]


def extinction_volume(wildcards):
    """volume.zarr for a rule that reads only its extinction field (the grid, its box, the opacity and density_scale:
    all a shadow is computed from): `ancient`, its time ignored, where the volume.zarr on disk holds the field the
    scene has now (`volume.prepared_from`), so that a change of the TF's colours alone, which makes prepare_volume
    rewrite it, reruns only the rules that draw images and what follows them; else an input like any other."""
    path = f"results/{wildcards.scene}/volume.zarr"
    return ancient(path) if _prepared_from(path, scene_config(wildcards.scene)) else path


def n_subsets(scene):
    cfg = scene_config(scene)
    return _n_subsets(cfg["lights"]["count"], cfg["subset_size"])


def subset_lights(wildcards):
    """fit_siren's lights.json, once its subset is one the scene has: `-R results/<scene>/sirens/subset_5.npz` of a
    one-subset run then stops the plan, where its job failed after it started (on a PBS system, after its queue)."""
    cfg = scene_config(wildcards.scene)
    try:
        _check_subset(cfg["lights"]["count"], cfg["subset_size"], int(wildcards.subset))
    except ValueError as e:
        raise WorkflowError(f"results/{wildcards.scene}/sirens/subset_{wildcards.subset}.npz: {e}") from None
    return f"results/{wildcards.scene}/lights.json"


_HELD = {}


def _rounds(scene):
    """Each subset's round and held subsets (`seams.subset_inputs`), computed once per scene from its config."""
    if scene not in _HELD:
        _HELD[scene] = _subset_inputs(scene_config(scene))
    return _HELD[scene]


def held_subset_files(wildcards):
    """fit_siren's inputs under `fit.rounds`: the files of the earlier rounds' subsets in its halo; none without it
    or with one subset."""
    held = _rounds(wildcards.scene)[1]
    subset = int(wildcards.subset)
    return [f"results/{wildcards.scene}/sirens/subset_{s}.npz" for s in (held[subset] if subset < len(held) else [])]


def fit_group(wildcards):
    """fit_siren's job group where a profile packs jobs (`group-components`): `siren<round>`, one per round, whose
    jobs do not wait on one another. One group for all would be one job: Snakemake joins a group's jobs that
    depend on each other, and under `fit.rounds` every subset's fit waits on its earlier-round neighbours'."""
    rounds = _rounds(wildcards.scene)[0]
    subset = int(wildcards.subset)
    return f"siren{rounds[subset] if subset < len(rounds) else 0}"


def subset_files(wildcards):
    return expand("results/{scene}/sirens/subset_{subset}.npz", scene=wildcards.scene,
                  subset=range(n_subsets(wildcards.scene)))


def as_json(scene, *keys):
    """The config sections that a job depends on, as one JSON argument (a params entry, so a rerun trigger)."""
    return _as_json(scene_config(scene), *keys)


def render_json(scene, *omit):
    """as_json(scene, "render") without the render settings `omit`, which the job does not read."""
    cfg = scene_config(scene)
    return _as_json({**cfg, "render": {k: v for k, v in cfg["render"].items() if k not in omit}}, "render")


def fit_json(scene, *keys, halo=True):
    """as_json for stage 1's jobs (`config.stage1_json`: without `fit.halo` where it changes nothing)."""
    return _stage1_json(scene_config(scene), *keys, halo=halo)


def report_json(scene):
    """The scene's whole config for the report, `fit.halo` only where it is used (`config.halo_where_used`)."""
    return json.dumps(_halo_where_used(scene_config(scene)), sort_keys=True)


def sampler_checkpoint(wildcards):
    """The diffusion model that samples: fine-tuned with the rendering loss when the scene enables it."""
    if scene_config(wildcards.scene)["finetune"]["enabled"]:
        return f"results/{wildcards.scene}/diffusion.ckpt"
    return f"results/{wildcards.scene}/diffusion_geometry.ckpt"


def cache_choice(scene):
    """What answers a light: the config's `cache`, or with `cache: auto` what choose_cache (a checkpoint, after
    stage 1) decided: diffusion, blend, or a codec of the stored SIRENs."""
    cache = scene_config(scene)["cache"]
    if cache != "auto":
        return cache
    with open(checkpoints.choose_cache.get(scene=scene).output[0]) as f:
        return json.load(f)["choice"]


def model_checkpoint(wildcards):
    """The diffusion checkpoint that samples, as an input; none when the stored SIRENs answer (no model)."""
    if cache_choice(wildcards.scene) != "diffusion":
        return {}
    return {"checkpoint": sampler_checkpoint(wildcards)}


def shadow_source(wildcards):
    """What answers a light: the diffusion model's checkpoint (with stage 1's stored SIRENs, their blend's
    correction and the volume when `mix.model_share` mixes their blend in), the stored SIRENs (blend, with its
    correction), or their codec's decoded store (encode_cache's cache.zarr)."""
    cache = cache_choice(wildcards.scene)
    if cache == "diffusion":
        if model_alone(wildcards.scene):
            return model_checkpoint(wildcards)
        # the model's SIRENs mixed with the stored ones' blend; validation lights' exact shadows from the volume
        return {**model_checkpoint(wildcards), "stored": f"results/{wildcards.scene}/weights.zarr",
                "volume": extinction_volume(wildcards), **blend_correction(wildcards)}
    if cache == "blend":
        return {"weights": f"results/{wildcards.scene}/weights.zarr", **blend_correction(wildcards)}
    return {"weights": f"results/{wildcards.scene}/cache.zarr"}


def blend_correction(wildcards):
    """fit_correction's correction.pt where the stored SIRENs' blend answers (cache: blend, or the mix) and
    `correction.steps` is over 0; a codec's blend and the model alone take none."""
    cache = cache_choice(wildcards.scene)
    blended = cache == "blend" or (cache == "diffusion" and not model_alone(wildcards.scene))
    if not blended or scene_config(wildcards.scene)["correction"]["steps"] <= 0:
        return {}
    return {"correction": f"results/{wildcards.scene}/correction.pt"}


def diffusion_threads(wildcards):
    """train_diffusion's threads: one where fit_correction starts beside it when stage 1 ends (the README run 6 min
    51 s -> 6 min 6 s; it cannot take the core back when the correction ends, as its bfloat16 products' bytes
    depend on its threads: docs/numerics.md), else two on a CPU (1.68x one's speed) and one on a GPU, so that a
    side job runs beside it."""
    return 1 if blend_correction(wildcards) else device_threads(2)


def correction_flag(input):
    """--correction for a command whose input holds the blend's correction; "" without one."""
    return f" --correction {input.correction}" if "correction" in input.keys() else ""


def codec_store(wildcards):
    """A codec's decoded store (cache.zarr) where one answers: evaluate_voxels blends it for further lights."""
    if cache_choice(wildcards.scene) in ("diffusion", "blend"):
        return {}
    return {"cache": shadow_source(wildcards)["weights"]}


def blend_args(scene):
    """How a light's stored SIRENs are blended (evaluate.blend_weights, evaluate.blend_k), as command flags."""
    ev = scene_config(scene)["evaluate"]
    return f"--blend-weights {ev['blend_weights']} --blend-k {ev['blend_k']}"


def sample_command(scene, input):
    """sample-shadows with the model's share of each SIREN (mix) and what the mix reads; at share 1 (the model
    alone) it reads no stored SIRENs."""
    cfg = scene_config(scene)
    mix = cfg["mix"]
    score = " --score-on run" if cfg["evaluate"]["device"] == "run" else ""  # evaluate.device: where SIRENs are scored
    if "stored" not in input.keys():
        return f"sample-shadows --checkpoint {input.checkpoint}{score}"
    return (f"sample-shadows --checkpoint {input.checkpoint} --model-share {mix['model_share']} --weights "
            f"{input.stored} --volume {input.volume} {blend_args(scene)} --val-lights {mix['val_lights']} "
            f"--val-points {mix['val_points']} --seed {mix['seed']}{score}{correction_flag(input)}")


def model_alone(scene):
    """`mix.model_share: 1`: the model's SIRENs answer alone, not mixed with the stored SIRENs' blend."""
    return _model_alone(scene_config(scene)["mix"]["model_share"])


def mix_settings(scene):
    """sample_shadows' settings: the stored SIRENs' blend, unless the model alone answers the mix, and where its
    SIRENs are scored where that is not the CPU (evaluate.device: run; a run's record before the key stays valid)."""
    cfg = scene_config(scene)
    return json.dumps({"blend_k": cfg["evaluate"]["blend_k"], "blend_weights": cfg["evaluate"]["blend_weights"],
                       **({} if model_alone(scene) else {"mix": cfg["mix"]}),
                       **({"score_on": "run"} if cfg["evaluate"]["device"] == "run" else {})},
                      sort_keys=True)


def geometry_checkpoint(wildcards):
    """The model before fine-tuning, for evaluate_voxels' unseen before/after (only when fine-tuning runs)."""
    if model_checkpoint(wildcards) and scene_config(wildcards.scene)["finetune"]["enabled"]:
        return {"geometry": f"results/{wildcards.scene}/diffusion_geometry.ckpt"}
    return {}


def finetune_json(scene):
    """finetune_render's settings, as `as_json` gives them, without `nproc` (how many processes, not what they
    compute)."""
    section = {k: v for k, v in scene_config(scene)["finetune"].items() if k != "nproc"}
    return _as_json({"finetune": section}, "finetune")


def stage_benchmarks(wildcards):
    """Snakemake's benchmark file of every job that this scene runs."""
    cfg = scene_config(wildcards.scene)
    rules = ["lights", "prepare_volume", "preoptimize", "collect_weights", "eval_truth", "sample_shadows",
             "evaluate_voxels", "caches", "train_data_inr", "naive_images", "evaluate_images", "shadow_bench",
             "report_figures", "benchmark"]
    if bench_naive(wildcards):
        rules += ["bench_naive"]
    cache = cache_choice(wildcards.scene)
    if cfg["cache"] == "auto":
        rules += ["choose_cache"]
    if cache == "diffusion":  # stage 2
        rules += ["presample", "train_diffusion"]
        if cfg["finetune"]["enabled"]:
            rules += ["render_targets", "finetune_render"]
    elif cache != "blend":
        rules += ["encode_cache"]
    if blend_correction(wildcards):
        rules += ["fit_correction"]
    fits = [f"fit_siren_{i}" for i in range(n_subsets(wildcards.scene))]
    return [f"results/{wildcards.scene}/benchmarks/{r}.tsv" for r in rules + fits]


def volume_file(wildcards):
    """The scene's volume file (`bundled:<name>` is the copy inside the package), relative to the run's directory
    where it lies inside it, so that a moved checkout keeps its finished run (`volume.run_path`)."""
    return _run_path(scene_config(wildcards.scene)["volume"])


def evaluate_device(wildcards):
    """The device flag of eval_truth and of the rules that score SIRENs (evaluate_voxels, caches, choose_cache,
    encode_cache, blend-shadows): the CPU under evaluate.device cpu (one truth, one sampler curve and one score on
    every machine), else none (the run's device)."""
    return "--device cpu" if scene_config(wildcards.scene)["evaluate"]["device"] == "cpu" else ""


def check_scenes():
    """Every scene of the run merged and validated when the workflow is parsed: a typo in a scene file stops
    the run in one line naming the file and key, before any job starts."""
    for scene in config["scenes"]:
        try:
            scene_config(scene)
        except _ConfigError as e:
            raise WorkflowError(str(e)) from None


def summary_inputs(wildcards):
    """What the scene's summary tables read: the metrics, the bench, the stage costs and their timeline (and
    fine-tuning's), and the images (the landing page's picture)."""
    files = {name: f"results/{wildcards.scene}/{name}" for name in
             ("voxel_metrics.json", "image_metrics.json", "bench.json", "stage_costs.tsv", "report/timeline.png",
              "images")}
    cfg = scene_config(wildcards.scene)
    if cfg["finetune"]["enabled"] and cache_choice(wildcards.scene) == "diffusion":
        files["finetune_metrics.json"] = f"results/{wildcards.scene}/finetune_metrics.json"
    if cfg["cache"] == "auto":  # the summary says what auto chose and why
        files["cache_choice.json"] = f"results/{wildcards.scene}/cache_choice.json"
    return {k.replace(".", "_").replace("/", "_"): v for k, v in files.items()}


def caption_values(scene):
    """The scene's settings that the report's captions state (as `snakemake.params.run`)."""
    cfg = scene_config(scene)
    lights, render = cfg["lights"], cfg["render"]
    return {"scene": scene, "train": lights["count"], "unseen": lights["unseen"], "eval_points": cfg["fit"]["eval_points"],
            "ddim_steps": cfg["diffusion"]["ddim_steps"], "image_size": render["image_size"], "views": render["views"],
            "lights_per_set": render["lights_per_set"], "step": render["step"], "reference": render["reference"],
            "shading": _shading_name(bool(render.get("phong")))}


def bench_kernel(wildcards) -> str:
    """render.kernel, and --no-warm-kernels where asked: one param, so that a run finished before the setting keeps
    its record (a new param, even empty, reruns the job)."""
    render = scene_config(wildcards.scene)["render"]
    return render["kernel"] + ("" if render["warm_kernels"] else " --no-warm-kernels")


def bench_naive(wildcards):
    """The naive frame's counts, taken apart (rule bench_naive), where the benchmark runs after the scene's other
    jobs; on Polaris it starts beside stage 2 with whole nodes (`benchmark_waits_for`) and counts the frame itself,
    one queue wait fewer."""
    return {} if _benchmark_has_whole_nodes() else {"naive": f"results/{wildcards.scene}/bench_naive.json"}


def _benchmark_has_whole_nodes() -> bool:
    """Polaris gives every job whole nodes: there the benchmark shares no cores with the scene's other jobs."""
    return config.get("pbs_system") == "polaris"


def benchmark_waits_for(wildcards):
    """Outputs the benchmark waits for without reading them, so that no job of the scene shares its cores: its last
    job on a machine that runs several at once (Snakemake's local scheduler may start two multi-threaded jobs on
    -j2; Sophia's by-gpu queue shares a node between jobs). Polaris gives every job whole nodes, so there the
    benchmark starts as soon as its inputs exist, beside stage 2, and is no longer two queue waits on the run's
    last stretch (docs/performance.md, "Queue waits in a row")."""
    if _benchmark_has_whole_nodes():
        return []
    return [f"results/{wildcards.scene}/{name}" for name in ("image_metrics.json", "voxel_metrics.json",
                                                              "report/image_grid.png")]


check_scenes()
