# diffshadow workflow: config + schema validation, the stage rules, `rule all`.
# Run: snakemake --profile local -j2   (after `diffshadow install-profiles`; or --profile profiles/local)
import os

from snakemake.exceptions import WorkflowError

from diffshadow.config import ConfigError, read_yaml, run_config


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


def _profile_machine():
    """The machine a PBS profile names in its default resource `pbs_system` (profiles/polaris, profiles/sophia), or
    None. Snakemake hands the default resources on to every batch job, so the job's own parse finds it too."""
    resources = workflow.resource_settings.default_resources
    for arg in (resources.args if resources is not None else None) or ():
        key, _, value = arg.partition("=")
        if key.strip() == "pbs_system":
            return value.strip().strip("'\"")
    return None


# The machine's settings (profiles/<machine>/<machine>.yaml: the system, finetune.nproc) under the run's own: a
# profile's `configfile:` is replaced by any --configfile on the command line, and the paper's command lost them so
# (no PBS_ACCOUNT check, no results/pbs for the job logs; a run file without finetune.nproc fine-tuned on 2 GPUs).
if _machine := _profile_machine():
    _machine_file = os.path.join(workflow.basedir, "profiles", _machine, f"{_machine}.yaml")
    if not os.path.isfile(_machine_file):
        raise WorkflowError(f"the profile's default resource pbs_system={_machine!r} names no machine: "
                            f"{_machine_file} does not exist (expected polaris or sophia)")
    configfile: _machine_file


# the run's own choices (config/config.yaml, --configfile, --config) over the package's defaults, validated; each
# file read again by the package's reader too, which refuses a key given twice (Snakemake's keeps the last silently)
try:
    for _file in workflow.configfiles:
        read_yaml(_file)
    _run = run_config(config, "config/config.yaml with --configfile/--config")
except ConfigError as e:
    raise WorkflowError(str(e)) from None
config.clear()
config.update(_run)

if config.get("pbs_system"):  # set by the polaris and sophia profiles
    if not os.environ.get("PBS_ACCOUNT"):
        raise WorkflowError(
            f"profile {config['pbs_system']}: PBS_ACCOUNT is not set, and every ALCF job needs -A PROJECT; "
            "run `export PBS_ACCOUNT=<your project>` and try again"
        )
    os.makedirs("results/pbs", exist_ok=True)  # qsub -o writes each job's log here


include: "workflow/rules/common.smk"
include: "workflow/rules/lights.smk"
include: "workflow/rules/stage1.smk"
include: "workflow/rules/stage2.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/report.smk"


# jobs of a few seconds without PyTorch run where Snakemake runs, not as batch jobs (a PBS queue wait would dwarf
# them); report_figures (matplotlib, 2 s here) is one on the run's last stretch
localrules: all, lights, prepare_volume, collect_weights, report_figures, stage_costs, summary


# the report's landing page: what was run and each scene's headline numbers (results/<scene>/report/landing.rst)
report: "workflow/report/workflow.rst"


rule all:
    input:
        expand("results/{scene}/voxel_metrics.json", scene=config["scenes"]),
        expand("results/{scene}/caches.json", scene=config["scenes"]),
        expand("results/{scene}/image_metrics.json", scene=config["scenes"]),
        expand("results/{scene}/bench.json", scene=config["scenes"]),
        expand("results/{scene}/stage_costs.tsv", scene=config["scenes"]),
        # by name too: a finished run's missing timeline, read only by summary, would not rerun stage_costs
        expand("results/{scene}/report/timeline.png", scene=config["scenes"]),
        expand("results/{scene}/report/image_grid.png", scene=config["scenes"]),
        expand("results/{scene}/report/landing.rst", scene=config["scenes"]),
        # cache: auto's decision asked for by name: a finished run switched to auto decides too (Snakemake does
        # not run a checkpoint whose dependants' outputs already exist)
        [f"results/{scene}/cache_choice.json" for scene in config["scenes"] if scene_config(scene)["cache"] == "auto"],


# what to open once a scene is whole (a stranger's next step after the README's run)
onsuccess:
    for _scene in config["scenes"]:
        if os.path.exists(f"results/{_scene}/report/summary.html"):  # the PBS profiles name their system
            print(f"results/{_scene} is complete: `snakemake --profile {config.get('pbs_system') or 'local'} --report "
                  f"report.html` writes the report, `diffshadow view results/{_scene}` opens the viewer")


# a job killed by SIGKILL (exit 137) leaves no word in its own log: most often the out-of-memory killer, so say
# which keys size its memory (diffshadow.hpc.killed_lines)
onerror:
    from diffshadow.hpc import killed_lines as _killed_lines

    for _path in [log] if isinstance(log, str) else log or ():
        try:
            with open(_path) as _f:
                _text = _f.read()
        except OSError:  # no log to read: Snakemake's own error stands alone
            continue
        for _line in _killed_lines(_text):
            print(_line)
