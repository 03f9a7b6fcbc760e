# Path helpers and per-scene config shared by the rules (no logic beyond looking things up).
import yaml


def scene_config(scene):
    """The scene file merged over the defaults' per-scene sections."""
    path = os.path.join(workflow.basedir, "config", "scenes", f"{scene}.yaml")
    with open(path) as f:
        scene_cfg = yaml.safe_load(f) or {}
    return {"lights": {**config["lights"], **scene_cfg.get("lights", {})}, **{
        k: v for k, v in scene_cfg.items() if k != "lights"}}
