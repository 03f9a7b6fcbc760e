# diffshadow workflow: config + schema validation, the stage rules, `rule all`.
# Run: snakemake --profile local -j2   (after `diffshadow install-profiles`; or --profile profiles/local)
import os

from snakemake.utils import validate


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


validate(config, os.path.join(workflow.basedir, "workflow", "schemas", "config.schema.yaml"))


include: "workflow/rules/common.smk"
include: "workflow/rules/lights.smk"
include: "workflow/rules/stage1.smk"
include: "workflow/rules/stage2.smk"
include: "workflow/rules/render.smk"


rule all:
    input:
        expand("results/{scene}/voxel_metrics.json", scene=config["scenes"]),
        expand("results/{scene}/image_metrics.json", scene=config["scenes"]),
        expand("results/{scene}/bench.json", scene=config["scenes"]),
