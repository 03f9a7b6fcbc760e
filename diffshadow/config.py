"""The one configuration: the package's `defaults.yaml` is the only source of run defaults, a run's own
file (`config/config.yaml`) overrides its keys, a scene file (`config/scenes/<scene>.yaml`) its sections, and
the merge is validated once against the package's `schemas/` — for Snakemake (the Snakefile and
`workflow/rules/common.smk`), Parsl and the CLI alike. Both ship inside the package, so an installed
`diffshadow` needs no checkout.

Config dataclasses (`FitConfig`, `DiffusionConfig`, ...) declare fields without defaults; `section`
fills them from `defaults.yaml` and rejects unknown keys, naming the section.
"""

from __future__ import annotations

import copy
import difflib
import functools
import json
import math
import re
from pathlib import Path
from typing import Any, TypeVar

import yaml

from diffshadow.io import did_you_mean
from diffshadow.transfer import TransferFunction, TransferFunctionError

PACKAGE = Path(__file__).resolve().parent
DEFAULTS_FILE = PACKAGE / "defaults.yaml"
SCHEMAS = PACKAGE / "schemas"
# the sections a scene file may override (everything in defaults.yaml but the run-wide keys)
SECTIONS = ("lights", "siren", "subset_size", "cache", "cache_auto", "mix", "correction", "preoptimize", "fit",
            "diffusion", "finetune", "data_inr", "evaluate", "render")

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration file or key that is missing or wrong; the message names the file and the key."""


class YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader (YAML 1.1), reading `1e-6` as the number it is in YAML 1.2 and JSON: 1.1 wants a dot
    (`1.0e-6`), and `density_scale: 1e-6` failed the schema as the string '1e-06'. A key given twice in one
    mapping is an error: PyYAML keeps the last silently, so of two `transfer_function:` blocks the one a user
    edited could be the one ignored."""

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict:
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                if isinstance(key, str | int | float | bool) and key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {key!r} given twice (first at line {seen[key] + 1})", key_node.start_mark)
                seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9][0-9_]*\.?[0-9_]*|\.[0-9_]+)"
                                                                       r"[eE][-+]?[0-9]+$"), list("-+0123456789."))


def read_yaml(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file{did_you_mean(path)}")
    try:
        value = yaml.load(path.read_text(), Loader=YamlLoader) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML{_where(e)}") from None
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: expected a mapping of keys, got {type(value).__name__}")
    return value


def _where(e: yaml.YAMLError) -> str:
    """Where in the file a YAML error is and what it is: PyYAML's first line alone ("while scanning for the next
    token") named neither the line nor the problem (a tab, an unclosed bracket)."""
    mark, problem = getattr(e, "problem_mark", None), getattr(e, "problem", None)
    if mark is None or problem is None:
        return f" ({str(e).splitlines()[0]})"
    return f" at line {mark.line + 1}, column {mark.column + 1}: {problem}"


@functools.cache
def defaults() -> dict:
    """The package's defaults.yaml: every run default."""
    return read_yaml(DEFAULTS_FILE)


def check_keys(cls: type, name: str, values: dict) -> set[str]:
    """The fields of dataclass `cls`; a key of `values` that is none of them is an error naming `name`."""
    known = set(cls.__dataclass_fields__)
    unknown = set(values) - known
    if unknown:
        raise ConfigError(f"{name}: unknown key(s) {sorted(unknown)}; known: {sorted(known)}")
    return known


# the annotations a setting's value is checked against (a field annotated otherwise is not checked)
_TYPES = {"int": (int,), "float": (int, float), "str": (str,), "bool": (bool,), "None": (type(None),),
          "list": (list, tuple), "dict": (dict,)}


def check_types(cls: type, name: str, values: dict) -> None:
    """Each value of `values` has its field's annotated type (a bool is no number): one line naming the key."""
    for key, value in values.items():
        annotation = str(cls.__dataclass_fields__[key].type).replace("typing.", "")
        names = [a.strip().split("[")[0] for a in annotation.split("|")]
        if not all(n in _TYPES for n in names):
            continue
        allowed = tuple(t for n in names for t in _TYPES[n])
        if not isinstance(value, allowed) or (isinstance(value, bool) and bool not in allowed):
            raise ConfigError(f"{name}.{key}: expected {annotation}, got {value!r} ({type(value).__name__})")


def section(cls: type[T], name: str, values: dict | None = None) -> T:
    """`cls` built from defaults.yaml's section `name`, overridden by `values`; unknown keys and values of the
    wrong type are errors."""
    if values is not None and not isinstance(values, dict):
        raise ConfigError(f"{name}: expected a mapping of settings, got {values!r}")
    values = dict(values or {})
    known = check_keys(cls, name, values)
    check_types(cls, name, values)
    base = {k: v for k, v in defaults().get(name, {}).items() if k in known}
    missing = known - set(base) - set(values)
    if missing:
        raise ConfigError(f"{name}: no value for {sorted(missing)} in {DEFAULTS_FILE} or the given settings")
    return cls(**{**base, **values})


@functools.cache
def _validator(schema_file: str, partial: bool = False):
    """The jsonschema validator of one of the package's schemas (read once per process); `partial`: no top-level
    key required."""
    import jsonschema

    schema = read_yaml(SCHEMAS / schema_file)
    if partial:
        schema = {**schema, "required": []}
    return jsonschema.Draft202012Validator(schema)


def _validate(value: dict, schema_file: str, where: str, *, partial: bool = False) -> None:
    """jsonschema validation with a one-line error naming `where` and the key path."""
    import jsonschema

    error = jsonschema.exceptions.best_match(_validator(schema_file, partial).iter_errors(value))
    if error is not None:
        key = ".".join(str(p) for p in error.absolute_path) or "(top level)"
        said = _hint(error)
        raise ConfigError(f"{where}: key {key}: {error.message}" + (f" ({said})" if said else ""))


def _hint(error) -> str | None:
    """What to write instead, where the schema's message alone leaves it to guess."""
    if error.validator == "pattern":  # a regex says little; its description says what it wants
        return error.schema.get("description")
    if error.validator == "type" and error.validator_value == "array" and isinstance(error.instance, str):
        return f"a list: [{error.instance}]"  # snakemake --config scenes=tooth, for scenes=[tooth]
    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        known = error.schema.get("properties", {})
        glued = [str(k) for k in error.instance if ":" in str(k) and k not in known]
        if glued:  # YAML reads `{count:5}` as the key 'count:5': snakemake --config lights={count:5}
            name, _, value = glued[0].partition(":")
            return f"YAML wants a space after the colon: {{{name}: {value}}}"
        for key in error.instance:  # a typo: fit.stpes for fit.steps
            if key not in known and (near := difflib.get_close_matches(str(key), list(known), n=1)):
                return f"did you mean {near[0]}?"
    return None


def merge(base: dict, own: dict) -> dict:
    """`own`'s sections over `base`'s, one level deep (a section is merged key by key)."""
    merged = dict(base)
    for key, value in own.items():
        merged[key] = {**merged[key], **value} if isinstance(merged.get(key), dict) else value
    return merged


def read_scene_file(path: str | Path) -> dict:
    """One scene file on its own (volume, load, transfer function, overrides), validated."""
    own = read_yaml(path)
    _validate(own, "scene.schema.yaml", str(path))
    try:  # beyond the schema: sorted knots, values in [0, 1]; named here, where the file is known
        TransferFunction.from_config(own["transfer_function"])
    except TransferFunctionError as e:
        raise ConfigError(f"{path}: key transfer_function: {str(e).removeprefix('transfer function: ')}") from None
    return own


def scene_config(run: dict, scene: str, *, scenes_dir: str | Path) -> dict:
    """The scene file `scenes_dir/<scene>.yaml` over the run's sections, validated: what every stage of `scene`
    runs with."""
    path = Path(scenes_dir) / f"{scene}.yaml"
    if not path.is_file():
        there = sorted(p.stem for p in Path(scenes_dir).glob("*.yaml"))
        near = difflib.get_close_matches(scene, there, n=1)
        raise ConfigError(f"scene {scene!r}: no file {path}" + (f"; did you mean {near[0]}?" if near else "")
                          + (f" (the scenes there: {', '.join(there)})" if there else ""))
    own = read_scene_file(path)
    merged = merge({k: run[k] for k in SECTIONS if k in run}, own)
    try:
        _validate({**{k: merged[k] for k in SECTIONS}, "scenes": [scene]}, "config.schema.yaml",
                  f"{path} over the run's config")
    except KeyError as e:
        raise ConfigError(f"scene {scene!r}: section {e} is in neither {path} nor the run's config") from None
    try:  # any grid's bound, before a job: prepare_volume checks again with the grid's own values and box
        TransferFunction.from_config(own["transfer_function"]).require_visible(str(path))
    except TransferFunctionError as e:
        raise ConfigError(str(e)) from None
    lights = merged["lights"]
    if lights["count"] > lights["sphere"]:  # found at plan time, not when the `lights` job runs
        raise ConfigError(f"{path} over the run's config: lights.count {lights['count']} is more than the "
                          f"{lights['sphere']} directions of lights.sphere; raise lights.sphere or lower lights.count")
    center = lights["center"]  # the schema holds three numbers; a direction needs them finite and not all zero
    if not all(math.isfinite(v) for v in center) or not any(center):
        raise ConfigError(f"{path} over the run's config: lights.center {center} is no direction; expected three "
                          "finite numbers, not all zero")
    ev = merged["evaluate"]
    if ev["blend_weights"] == "inverse-angle" and ev["blend_k"] > lights["count"]:
        raise ConfigError(f"{path} over the run's config: evaluate.blend_k {ev['blend_k']} is more than the "
                          f"{lights['count']} training lights (lights.count) a blend can take; lower evaluate.blend_k")
    return merged


def run_config(own: dict, where: str) -> dict:
    """A run's own choices (`where`: the file they came from, for errors) over the defaults, validated."""
    # copies all round: a caller that changes its run must not change the cached defaults of every later one
    run = _typed(merge(copy.deepcopy(defaults()), copy.deepcopy(dict(own))), "config.schema.yaml")
    _validate(run, "config.schema.yaml", where)
    return run


def _typed(run: dict, schema_file: str) -> dict:
    """Snakemake reads every value inside `--config section='{key: value}'` as a string ('{epochs: 60}' gives
    '60'): where a string fails the schema and its YAML reading is no string (a number, a boolean, a list), that
    reading takes its place, so a key given on the command line means what it means in a file. In place."""
    for error in list(_validator(schema_file).iter_errors(run)):
        if not isinstance(error.instance, str) or not error.absolute_path:
            continue
        try:
            value = yaml.load(error.instance, Loader=YamlLoader)
        except yaml.YAMLError:
            continue
        if not isinstance(value, str):
            *parents, last = error.absolute_path
            functools.reduce(lambda node, key: node[key], parents, run)[last] = value
    return run


def load_run(configfile: str | Path | None = None) -> dict:
    """A run configuration file over the defaults (None: the defaults alone), validated."""
    if configfile is None:
        return run_config({}, str(DEFAULTS_FILE))
    return run_config(read_yaml(configfile), str(configfile))


# Settings added after runs existed, at the value that does what those runs did without them. A job's params leave
# them out at that value: the workflow reruns a job whose params change, and a finished run should not redo
# train_diffusion (days at the paper's sizes) for a new key that changes none of its bytes. A checkpoint's
# fingerprint leaves them out too, so a training stopped before the key existed resumes. The job still reads
# them: a section missing a key takes defaults.yaml's (`section`). diffusion.cuda_graph: the geometry stage
# records what it did (False: eager steps, as every run before the key), and "auto", its default since, leaves a
# finished run as it is (on a CPU it does what False does; a CUDA run finished before it keeps its eager weights);
# fit.cuda_graph and data_inr.cuda_graph likewise (False before a GPU timed them, "auto" since), and
# finetune.cuda_graph (False, untimed on a GPU: its step records False off CUDA whatever was asked); fit.target_store
# changes where the targets are kept, not their values; render.warm_kernels (true, its default) when the kernels
# compile, not what they draw (false is passed on: the jobs must receive it). diffusion.precision "auto" (its default
# since 2026-12-06) as cuda_graph's: a run finished in float32 keeps its weights, whose checkpoint says float32.
UNCHANGED_WHEN = {("diffusion", "precision"): ("auto", "float32"), ("diffusion", "cuda_graph"): ("auto", False),
                  ("fit", "cuda_graph"): ("auto", False), ("data_inr", "cuda_graph"): ("auto", False),
                  ("finetune", "cuda_graph"): (False,), ("fit", "target_store"): ("auto",),
                  ("render", "warm_kernels"): (True,)}


def changed_settings(name: str, values: dict) -> dict:
    """Section `name`'s `values` without UNCHANGED_WHEN's settings at their values."""
    # equal and of one type: False, not 0 (which the schema refuses, and which must not pass for the default)
    return {k: v for k, v in values.items()
            if not any(v is u or (type(v) is type(u) and v == u) for u in UNCHANGED_WHEN.get((name, k), ()))}


def as_json(cfg: dict, *keys: str) -> str:
    """The sections a stage depends on, as one canonical JSON argument (without UNCHANGED_WHEN's settings at
    their values)."""
    sections = {k: changed_settings(k, cfg[k]) if isinstance(cfg[k], dict) else cfg[k] for k in keys}
    return json.dumps(sections, sort_keys=True)


SEAM_SETTINGS = ("halo", "rounds")  # fit settings that act only across the seams between subsets


def halo_where_used(cfg: dict, *, halo: bool = True) -> dict:
    """`cfg` without `fit.halo` and `fit.rounds` where they change nothing: `halo` False (preoptimize's job) or a
    scene of one subset, which has no seam. Rule params built from it do not rerun a run made before they were
    settings."""
    # lights.n_subsets' count: config is the bottom layer and imports nothing of the package's (tests/test_layers.py)
    if halo and -(-int(cfg["lights"]["count"]) // int(cfg["subset_size"])) > 1:
        return cfg
    return {**cfg, "fit": {k: v for k, v in cfg["fit"].items() if k not in SEAM_SETTINGS}}


def stage1_json(cfg: dict, *keys: str, halo: bool = True) -> str:
    """as_json for stage 1's jobs, `fit.halo` only where it is used (`halo_where_used`): a subset fitted by
    Snakemake or by Parsl then records the same settings."""
    return as_json(halo_where_used(cfg, halo=halo), *keys)


class _Sections(dict):
    """A parsed --config-json whose missing section is a one-line ConfigError, not a KeyError traceback."""

    def __init__(self, value: dict, what: str) -> None:
        super().__init__(value)
        self.what = what

    def __missing__(self, key: str):
        raise ConfigError(f"{self.what}: no {key!r} section (it has {sorted(self) or 'none'}); the workflow passes "
                          f"the config's sections by name, e.g. {{\"{key}\": {{...}}}}")


def check_sections(value: dict, where: str) -> None:
    """The run config's sections among `value`'s keys (a command's --config-json: a few sections, some of their
    keys), each within the bounds a run file's are held to: a job started by hand gets the same one line as a run
    at plan time, not a stage's traceback or a NaN written (fit.eval_points 0 was stored as a NaN PSNR). Without
    any, jsonschema is not imported (~30 ms a job: prepare_volume, which every other job waits for, passes none)."""
    given = {key: value[key] for key in SECTIONS if key in value}
    if given:
        _validate(given, "config.schema.yaml", where, partial=True)


def _unique_keys(source: str, pairs: list[tuple[str, Any]]) -> dict:
    """A JSON object's members, a key given twice refused, as the YAML reader refuses one: json keeps the last
    silently, so a hand-typed '{"fit": {"lr": 1e-4, ..., "lr": 1e-3}}' ran at the second."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise ConfigError(f"{source}: key {key!r} given twice in one object")
        out[key] = value
    return out


def parse_json(text: str, what: str = "--config-json") -> dict[str, Any]:
    """A JSON object given inline or, where `text` is not an object's text, as the path of a file holding one."""
    source = what
    if not text.lstrip().startswith("{"):
        path = Path(text)
        if not path.is_file():
            raise ConfigError(f"{what}: expected a JSON object or a file holding one, got {text!r} (no such file)")
        source = f"{what} {path}"
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(f"{source}: unreadable ({type(e).__name__}: {e})") from None
    try:
        value = json.loads(text, object_pairs_hook=functools.partial(_unique_keys, source))
    except json.JSONDecodeError as e:
        raise ConfigError(f"{source}: not valid JSON ({e})") from None
    if not isinstance(value, dict):
        raise ConfigError(f"{source}: expected a JSON object")
    return _Sections(value, source)


# the config keys that size each heavy command's largest allocations, named when it runs out of memory (the CLI's
# line) or is killed for it (hpc.killed_lines)
MEMORY_KEYS = {
    "preoptimize": "fit.points or fit.grid_upsample (its target grid has grid_upsample³ x the voxels)",
    "fit-siren": "subset_size or fit.halo (SIRENs fitted together, a subset's and its halo's, a target grid each, "
                 "or fit.steps x fit.points values each with fit.target_store: table), fit.grid_upsample (a grid "
                 "holds grid_upsample³ x the voxels) or fit.points",
    "train-data-inr": "data_inr.points",
    "presample": "diffusion.presample_points",
    "train-diffusion": "diffusion.batch_size or diffusion.geometry_points",
    "finetune-render": "finetune.batch_size, finetune.pixels or finetune.val_points",
    "eval-truth": "evaluate.points (--eval-points)",
    "render-targets": "finetune.image_size or fit.grid_upsample (its shadow grid has grid_upsample³ x the voxels)",
    "evaluate-images": "render.image_size",
    "naive-images": "render.image_size",
    "render": "--size (the image's pixels)",  # a flag, not a config key: the command has none
}


# the commands that keep a checkpoint while they run (beside their output, or their output is one) and resume from it
# when run again after a kill (parsl-fit: its subsets' fits); the others start again (hpc.killed_lines, the Ctrl-C line)
RESUMABLE = frozenset({"fit-siren", "parsl-fit", "train-data-inr", "render-targets", "train-diffusion",
                       "fit-correction", "finetune-render", "evaluate-voxels", "caches"})


def memory_keys(command: str) -> str:
    """The config keys to lower where `command` (a `diffshadow` subcommand) runs out of memory."""
    return MEMORY_KEYS.get(command, "the sizes in this command's config section")
