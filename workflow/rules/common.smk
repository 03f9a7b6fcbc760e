# Per-scene configuration and path helpers shared by the rules (look-ups only, no logic).
import json

import yaml
from snakemake.utils import validate

SECTIONS = ("lights", "siren", "subset_size", "preoptimize", "fit", "diffusion", "finetune", "data_inr", "render")
_SCENES = {}


def scene_config(scene):
    """config/scenes/<scene>.yaml over the defaults, validated (a typo fails at parse time)."""
    if scene not in _SCENES:
        path = os.path.join(workflow.basedir, "config", "scenes", f"{scene}.yaml")
        if not os.path.exists(path):
            raise ValueError(f"scene {scene!r}: no file {path}")
        with open(path) as f:
            own = yaml.safe_load(f) or {}
        validate(own, os.path.join(workflow.basedir, "workflow", "schemas", "scene.schema.yaml"))
        merged = {k: config[k] for k in SECTIONS}
        for key, value in own.items():
            merged[key] = {**merged[key], **value} if isinstance(merged.get(key), dict) else value
        validate({**{k: merged[k] for k in SECTIONS}, "scenes": config["scenes"]},
                 os.path.join(workflow.basedir, "workflow", "schemas", "config.schema.yaml"))
        _SCENES[scene] = merged
    return _SCENES[scene]


def n_subsets(scene):
    cfg = scene_config(scene)
    return -(-cfg["lights"]["count"] // cfg["subset_size"])


def subset_files(wildcards):
    return expand("results/{scene}/sirens/subset_{subset}.npz", scene=wildcards.scene,
                  subset=range(n_subsets(wildcards.scene)))


def as_json(scene, *keys):
    """The config sections a rule depends on, as one JSON argument (and its params: rerun trigger)."""
    cfg = scene_config(scene)
    return json.dumps({k: cfg[k] for k in keys}, sort_keys=True)


def sampler_checkpoint(wildcards):
    """The diffusion model that samples: fine-tuned with the rendering loss when the scene enables it."""
    if scene_config(wildcards.scene)["finetune"]["enabled"]:
        return f"results/{wildcards.scene}/diffusion.ckpt"
    return f"results/{wildcards.scene}/diffusion_geometry.ckpt"
