# Per-scene configuration and path helpers shared by the rules (look-ups only: the merge and its
# validation are diffshadow.config's, the same for the CLI and Parsl).
import json

from diffshadow.config import as_json as _as_json
from diffshadow.config import scene_config as _scene_config
from diffshadow.lights import n_subsets as _n_subsets
from diffshadow.volume import resolve_path as _resolve_path

_SCENES = {}
DEVICE = config.get("device", "auto")  # passed as --config-device: --device and DIFFSHADOW_DEVICE win
LAUNCHER = config.get("torchrun", "torchrun --standalone")  # how finetune_render starts its DDP processes


def scene_config(scene):
    """config/scenes/<scene>.yaml over the run's config, validated (a typo fails at parse time)."""
    if scene not in _SCENES:
        _SCENES[scene] = _scene_config(config, scene, scenes_dir=os.path.join(workflow.basedir, "config", "scenes"))
    return _SCENES[scene]


def n_subsets(scene):
    cfg = scene_config(scene)
    return _n_subsets(cfg["lights"]["count"], cfg["subset_size"])


def subset_files(wildcards):
    return expand("results/{scene}/sirens/subset_{subset}.npz", scene=wildcards.scene,
                  subset=range(n_subsets(wildcards.scene)))


def as_json(scene, *keys):
    """The config sections a rule depends on, as one JSON argument (and its params: rerun trigger)."""
    return _as_json(scene_config(scene), *keys)


def sampler_checkpoint(wildcards):
    """The diffusion model that samples: fine-tuned with the rendering loss when the scene enables it."""
    if scene_config(wildcards.scene)["finetune"]["enabled"]:
        return f"results/{wildcards.scene}/diffusion.ckpt"
    return f"results/{wildcards.scene}/diffusion_geometry.ckpt"


def finetune_json(scene):
    """finetune_render's settings without `nproc` (how many processes, not what they compute)."""
    return json.dumps({"finetune": {k: v for k, v in scene_config(scene)["finetune"].items() if k != "nproc"}},
                      sort_keys=True)


def stage_benchmarks(wildcards):
    """Snakemake's benchmark file of every job that this scene runs."""
    rules = ["lights", "prepare_volume", "preoptimize", "collect_weights", "presample", "eval_truth",
             "train_diffusion", "sample_shadows", "evaluate_voxels", "train_data_inr", "evaluate_images",
             "report_figures", "benchmark"]
    if scene_config(wildcards.scene)["finetune"]["enabled"]:
        rules += ["render_targets", "finetune_render"]
    fits = [f"fit_siren_{i}" for i in range(n_subsets(wildcards.scene))]
    return [f"results/{wildcards.scene}/benchmarks/{r}.tsv" for r in rules + fits]


def volume_file(wildcards):
    """The scene's volume file (`bundled:<name>` is the copy inside the package)."""
    return str(_resolve_path(scene_config(wildcards.scene)["volume"]))
