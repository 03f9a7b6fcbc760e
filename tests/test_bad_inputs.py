"""The table of bad inputs a user can give: each gets one line on stderr that names the file, key or value, and
a non-zero exit; never a traceback. (argparse's own usage lines, printed before its one error line, are not
counted.)"""

import json
import subprocess
import sys

import numpy as np
import pytest

TF = {"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 5}


def scene_file(tmp_path, name: str, **tf):
    path = tmp_path / f"{name}.yaml"
    volume = tf.pop("volume", "bundled:nucleon")
    path.write_text(json.dumps({"volume": volume, "transfer_function": {**TF, **tf}}))  # JSON is YAML
    return str(path)


def npy(tmp_path, name: str, truncate: bool = False) -> str:
    path = tmp_path / name
    np.save(path, np.random.default_rng(0).random((6, 6, 6), dtype=np.float32))
    if truncate:
        path.write_bytes(path.read_bytes()[:120])
    return str(path)


def _render(volume_args, *extra):
    return ["render", *volume_args, "--mode", "noshadow", "--size", "8", "--out", "x.png", *extra]


def _config_json(tmp_path, settings: str):
    return ["train-data-inr", "--volume", npy(tmp_path, "v.npy"), "--out", "d.pt", "--config-json", settings]


# (name, arguments from tmp_path, environment, what the line must say)
CASES = [
    ("opacity above 1", lambda t: _render(["--scene-config", scene_file(t, "a", opacity=[[0, 0], [1, 1.5]])]), {},
     r"a.yaml: key transfer_function: opacity values must lie in \[0, 1\]"),
    ("colour below 0", lambda t: _render(["--scene-config", scene_file(t, "b", color=[[0, -1, 1, 1], [1, 1, 1, 1]])]),
     {}, r"b.yaml: key transfer_function: color values must lie in \[0, 1\]"),
    ("unsorted TF points", lambda t: _render(["--scene-config", scene_file(t, "c", opacity=[[0.5, 0], [0.1, 1]])]),
     {}, r"c.yaml: key transfer_function: opacity points must be sorted by s"),
    ("opacity 0 everywhere", lambda t: _render(["--scene-config", scene_file(t, "d", opacity=[[0, 0], [1, 0]])]), {},
     "opacity is 0 at every point"),
    ("an unknown bundled volume", lambda t: _render(["--scene-config", scene_file(t, "e", volume="bundled:nucleus")]),
     {}, "no bundled volume 'nucleus'"),
    ("more lights than the sphere", lambda t: ["lights", "--sphere", "40", "--count", "100", "--center", "0", "0",
                                               "1", "--unseen", "2", "--out", "l.json"], {}, "count must be in 1..40"),
    ("an .h5 that is not HDF5", lambda t: _render(["--volume", str(_write(t / "v.h5", b"not hdf5")), "--tf-json",
                                                  json.dumps(TF)]), {}, r"v.h5: not an HDF5 file"),
    ("a truncated .npy", lambda t: _render(["--volume", npy(t, "cut.npy", truncate=True), "--tf-json",
                                            json.dumps(TF)]), {}, r"cut.npy: not a readable .npy file"),
    ("DIFFSHADOW_GPU_LOCK=four", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)]),
     {"DIFFSHADOW_GPU_LOCK": "four"}, "DIFFSHADOW_GPU_LOCK: expected the number of GPUs per node"),
    ("DIFFSHADOW_DETERMINISTIC=maybe", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)]),
     {"DIFFSHADOW_DETERMINISTIC": "maybe"}, "DIFFSHADOW_DETERMINISTIC: expected 0 or 1"),
    ("an image named .jpg", lambda t: [*_render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)])[:-2],
                                       "--out", "x.jpg"], {}, r"--out x.jpg: the image is written as a PNG"),
    ("an unknown kernel", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)], "--kernel",
                                            "bogus"), {}, "argument --kernel: invalid choice: 'bogus'"),
    ("--config-json: a string for a number", lambda t: _config_json(t, '{"data_inr": {"steps": "many"}}'), {},
     r"--config-json: key data_inr.steps: 'many' is not of type 'integer'"),
    ("--config-json: true for a number", lambda t: _config_json(t, '{"data_inr": {"steps": true}}'), {},
     r"--config-json: key data_inr.steps: True is not of type 'integer'"),
    ("--config-json: a list for a section", lambda t: _config_json(t, '{"data_inr": [1]}'), {},
     r"--config-json: key data_inr: \[1\] is not of type 'object'"),
    ("--config-json: an unknown key", lambda t: _config_json(t, '{"data_inr": {"stepz": 3}}'), {},
     r"--config-json: key data_inr: Additional properties are not allowed \('stepz' was unexpected\)"),
    # below the run schema's bounds, as a run file is at plan time: data_inr.checkpoint_every 0 ended in a
    # ZeroDivisionError's traceback, data_inr.points 0 in "fit diverged", fit.eval_points 0 wrote a NaN PSNR
    ("--config-json: below a bound", lambda t: _config_json(t, '{"data_inr": {"checkpoint_every": 0}}'), {},
     r"--config-json: key data_inr.checkpoint_every: 0 is less than the minimum of 1"),
    ("--config-json: not JSON", lambda t: _config_json(t, "{bad"), {}, "--config-json: not valid JSON"),
    ("parsl-fit: a Parsl config that is not there", lambda t: ["parsl-fit", "--config", "nope.py"], {},
     r"--config nope.py: no such Parsl config file"),
    ("a negative --threads", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)],
                                               "--threads", "-3"), {}, r"--threads: expected at least 0, got -3"),
    ("a negative --seed", lambda t: ["lights", "--sphere", "40", "--count", "8", "--center", "0", "0", "1",
                                     "--unseen", "2", "--seed", "-1", "--out", "l.json"], {},
     r"argument --seed: expected at least 0, got -1"),  # was numpy's traceback, once the job had started
    ("a --seed past 64 bits", lambda t: ["lights", "--sphere", "40", "--count", "8", "--center", "0", "0", "1",
                                         "--unseen", "2", "--seed", str(2**64), "--out", "l.json"], {},
     r"argument --seed: expected at most 2\^63-1, got 18446744073709551616"),
    ("--tf-json: a file that is not there", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", "tf.json"]),
     {}, r"--tf-json: expected a JSON object or a file holding one, got 'tf.json' \(no such file\)"),
    ("--tf-json: a file of bad JSON", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json",
                                                         str(_write(t / "tf.json", b'{"opacity": '))]), {},
     r"--tf-json .*tf.json: not valid JSON"),
    ("--up without the free camera", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)],
                                                       "--up", "0", "1", "0"), {},
     r"render: --up turns the free camera; give --eye and --target with it"),
    ("a truncated diffusion checkpoint", lambda t: _render_inr(t, str(_write(t / "cut.ckpt", _torch_bytes()[:200]))),
     {}, r"cut.ckpt: unreadable \(RuntimeError: .*\); expected a diffusion checkpoint"),
    ("a folder for a diffusion checkpoint", lambda t: _render_inr(t, str(t)), {}, r": a folder; expected a diffusion"),
    ("bench render with no timed frame", lambda t: ["bench", "render", "--volume", npy(t, "v.npy"), "--tf-json",
                                                    json.dumps(TF), "--repeats", "0", "--out", "b.json"], {},
     r"bench render: --repeats: expected at least 1 timed frame per mode, got 0"),  # was statistics' empty median
    ("bench render: --naive-counts not the naive counts' file",
     lambda t: ["bench", "render", "--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF), "--naive-counts",
                str(_write(t / "n.json", b'{"counts": {"ops": 3}}')), "--out", "b.json"], {},
     r"--naive-counts .*n.json: expected the JSON of `diffshadow bench naive-counts` \(its counts: ops, syncs, "
     r"host_tensors, peak_bytes\), could not read it"),  # before any frame or fit
    ("bench init-spread of one light", lambda t: ["bench", "init-spread", "--lights", "1", "--results", str(t),
                                                  "--out", "b"], {},
     r"bench init-spread: --lights: expected at least 2 \(a spread across lights\), got 1"),  # was a traceback
    ("bench render: a SIREN of width 0", lambda t: ["bench", "render", "--volume", npy(t, "v.npy"), "--siren-width",
                                                    "0", "--out", "b.json"], {},
     r"argument --siren-width: expected at least 1, got 0"),  # was a ZeroDivisionError's traceback
    ("bench kernels for sm_70", lambda t: ["bench", "kernels", "--arch", "70"], {},
     r"argument --arch: expected at least 75, got 70"),  # was an IndexError's traceback (sm_12: LLVM's abort)
    ("a data INR that is not one", lambda t: _render_inr(t, str(_write(t / "d.ckpt", _torch_bytes())), "--scalar",
                                                         "inr", "--data-inr", str(t / "d.ckpt")), {},
     r"d.ckpt: not a data INR file \(train_data_inr's data_inr.pt\): no key 'layout'"),
    # a mistyped path: it said the volume "needs a transfer function (--tf-json ...)", as for a raw volume
    ("a volume that is not there", lambda t: _render(["--volume", "results/nucleonn/volume.zarr"]), {},
     r"results/nucleonn/volume.zarr: no such file; expected a prepared volume.zarr.*--tf-json$"),
    ("a mistyped --data-inr", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)],
                                                "--data-inr", f"{_write(t / 'data_inr.pt', b'')}h",
                                                "--scalar", "inr"), {},
     r"data_inr.pth: no such file; expected a data INR file .*; did you mean .*data_inr.pt\?$"),
    ("a zero --light", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)], "--mode", "gt",
                                         "--light", "0", "0", "0"), {},
     r"error: --light: must be non-zero, got \[0.0, 0.0, 0.0\]$"),  # it named the library's "light_dir"
    # zarr's words were "No group found in store 'diffusion.ckpt' at path ''"
    ("a checkpoint for --blend", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)], "--mode",
                                                   "inr", "--light", "1", "0", "0", "--blend",
                                                   str(_write(t / "d.ckpt", _torch_bytes()))), {},
     r"d.ckpt: a file; expected a weight store \(a .zarr folder\)$"),
    ("bench stages outside the repository", lambda t: ["bench", "stages", "--out", "b"], {},
     r"--configfile config/config.yaml: no such file \(a run config; its scenes are read from --scenes-dir "
     r"config/scenes: run it in the repository's folder, or give both\)$"),
    ("a store that is not there", lambda t: _render(["--volume", npy(t, "v.npy"), "--tf-json", json.dumps(TF)],
                                                    "--mode", "inr", "--weights", "generatd.zarr"), {},
     r"generatd.zarr: no such store; expected a weight store \(a .zarr folder\)$"),
]


def _render_inr(tmp_path, checkpoint: str, *extra):
    return _render(["--volume", npy(tmp_path, "v.npy"), "--tf-json", json.dumps(TF)], "--mode", "inr", "--diffusion",
                   checkpoint, "--light", "1", "0", "0", *extra)


def _torch_bytes() -> bytes:
    import io

    import torch

    buf = io.BytesIO()
    torch.save({"weights": torch.zeros(64)}, buf)
    return buf.getvalue()


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("name, args, env, message", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gets_one_line(tmp_path, monkeypatch, name, args, env, message):
    import os
    import re

    for key in ("DIFFSHADOW_GPU_LOCK", "DIFFSHADOW_DETERMINISTIC"):
        monkeypatch.delenv(key, raising=False)
    proc = subprocess.run([sys.executable, "-m", "diffshadow.cli", *args(tmp_path)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    assert proc.returncode not in (0, 1), (name, proc.returncode, proc.stderr[-2000:])  # 1: an uncaught exception
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    if lines and lines[0].startswith("usage:"):  # argparse: its usage (indented continuation lines), then one line
        lines = [line for line in lines[1:] if not line.startswith(" ")]
    assert len(lines) == 1, (name, proc.stderr)
    assert re.search(message, lines[0]), (name, lines[0])


def test_more_lights_than_the_sphere_is_refused_at_plan_time(tmp_path):
    """Before any job runs: the workflow's scene configuration is refused, naming both keys."""
    from diffshadow.config import ConfigError, load_run, merge, scene_config

    (tmp_path / "nucleon.yaml").write_text(json.dumps({"volume": "bundled:nucleon", "transfer_function": TF}))
    run = merge(load_run(), {"lights": {**load_run()["lights"], "count": 500, "sphere": 400}})
    with pytest.raises(ConfigError, match="lights.count 500 is more than the 400 directions of lights.sphere"):
        scene_config(run, "nucleon", scenes_dir=tmp_path)


@pytest.mark.parametrize("center", [[0, 0, 0], [0.0, 0.0, float("nan")], [1, float("inf"), 0]])
def test_a_center_that_is_no_direction_is_refused_at_plan_time(tmp_path, center):
    """lights.center all zero or not finite: refused before any job (the lights job would refuse it only when it
    ran), naming the key; a center of any length is a direction."""
    from diffshadow.config import ConfigError, load_run, merge, scene_config

    (tmp_path / "nucleon.yaml").write_text(json.dumps({"volume": "bundled:nucleon", "transfer_function": TF}))
    run = merge(load_run(), {"lights": {**load_run()["lights"], "center": center}})
    with pytest.raises(ConfigError, match=r"lights.center \[.*\] is no direction; expected three finite numbers"):
        scene_config(run, "nucleon", scenes_dir=tmp_path)
    ok = merge(load_run(), {"lights": {**load_run()["lights"], "center": [0, 0, 5]}})
    assert scene_config(ok, "nucleon", scenes_dir=tmp_path)["lights"]["center"] == [0, 0, 5]


def test_an_inverse_angle_blend_of_more_lights_than_trained_is_refused_at_plan_time(tmp_path):
    """evaluate.blend_k past lights.count: refused before any job with inverse-angle weights; the triangle blend
    (the default) takes no k, so 3 lights and blend_k 4 run (tests/stress/test_edges.py runs them)."""
    from diffshadow.config import ConfigError, load_run, merge, scene_config

    (tmp_path / "nucleon.yaml").write_text(json.dumps({"volume": "bundled:nucleon", "transfer_function": TF}))
    run = merge(load_run(), {"lights": {**load_run()["lights"], "count": 3, "unseen": 0}})
    assert scene_config(run, "nucleon", scenes_dir=tmp_path)["evaluate"]["blend_k"] == 4
    run = merge(run, {"evaluate": {**run["evaluate"], "blend_weights": "inverse-angle"}})
    with pytest.raises(ConfigError, match="evaluate.blend_k 4 is more than the 3 training lights"):
        scene_config(run, "nucleon", scenes_dir=tmp_path)


def test_an_invisible_scene_is_refused_at_plan_time(tmp_path):
    from diffshadow.config import ConfigError, load_run, scene_config

    clear = {**TF, "opacity": [[0, 0], [1, 0]]}
    (tmp_path / "clear.yaml").write_text(json.dumps({"volume": "bundled:nucleon", "transfer_function": clear}))
    with pytest.raises(ConfigError, match=r"clear.yaml: transfer function: opacity is 0 at every point"):
        scene_config(load_run(), "clear", scenes_dir=tmp_path)
    faint = {**TF, "density_scale": 1e-6}  # no grid in a box of longest side 1 shows one 8-bit level under it
    (tmp_path / "faint.yaml").write_text(json.dumps({"volume": "bundled:nucleon", "transfer_function": faint}))
    with pytest.raises(ConfigError, match=r"faint.yaml: transfer function: nothing can show: .* raise density_scale "
                                          r"above 0.001134$"):
        scene_config(load_run(), "faint", scenes_dir=tmp_path)


def test_a_scene_name_the_shell_would_split_is_refused_at_plan_time():
    """A scene's name becomes results/<name>/ in every rule's shell command, unquoted: 'my scene' (from a file
    config/scenes/my scene.yaml) failed each job with "invalid choice: 'scene/benchmarks/lights.phases.json'". It is
    refused before any job, naming the key, the value and what a name may hold."""
    from diffshadow.config import ConfigError, run_config

    for name in ("my scene", "tooth;rm", "$HOME", ".hidden", "a/b"):
        with pytest.raises(ConfigError, match=r"^x: key scenes\.0: .* does not match .*\(a scene's name: letters, "
                                              r"digits, _, \. and -, since config/scenes/<name>\.yaml names"):
            run_config({"scenes": [name]}, "x")
    for name in ("nucleon", "hydrogen_atom", "bi2o3", "my-scene.v2", "_draft"):
        assert run_config({"scenes": [name]}, "x")["scenes"] == [name]


@pytest.mark.parametrize("section", ["lights", "fit", "diffusion", "finetune", "data_inr", "cache_auto", "mix",
                                     "evaluate"])
def test_a_seed_numpy_or_pytorch_would_refuse_stops_the_plan(section):
    """Every section's seed is 0 to 2^63-1, refused at plan time otherwise: numpy refuses a negative seed (mix.seed
    -1 ended sample_shadows in its traceback, after a DDIM sampling) and PyTorch one past 64 bits. Both bounds
    pass, and a seed on the command line (`--config mix='{seed: 5}'`, a string) is read as the number."""
    from diffshadow.config import ConfigError, run_config

    for bad, said in ((-1, "-1 is less than the minimum of 0"),
                      (2**64, "18446744073709551616 is greater than the maximum of 9223372036854775807")):
        with pytest.raises(ConfigError, match=rf"^x: key {section}\.seed: {said}$"):
            run_config({section: {"seed": bad}}, "x")
    for good in (0, 2**63 - 1):
        assert run_config({section: {"seed": good}}, "x")[section]["seed"] == good
    assert run_config({section: {"seed": "5"}}, "x")[section]["seed"] == 5


def test_a_run_file_with_a_key_given_twice_stops_the_plan(tmp_path):
    """Snakemake reads a run's config files itself and keeps the last of two equal keys; the workflow reads each
    again with the package's reader and stops before any job, naming the file, the line and the key."""
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    (tmp_path / "run.yaml").write_text("lights: {count: 8}\nfit: {steps: 50}\nlights: {count: 16}\n")
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(repo / "Snakefile"), "--directory",
                           str(tmp_path), "--configfile", str(tmp_path / "run.yaml"), "--cores", "1", "-n"],
                          capture_output=True, text=True, timeout=300)
    said = proc.stdout + proc.stderr  # Snakemake prints a parse error on stdout
    assert proc.returncode != 0
    assert f"{tmp_path / 'run.yaml'}: not valid YAML at line 3, column 1: key 'lights' given twice (first at line 1)" \
        in said, said[-2000:]


# (command and its required options, the option, the run config's key it carries)
COUNTS = [
    (["eval-truth", "--volume", "v", "--lights", "l", "--out", "o"], "--eval-points", "evaluate.points"),
    (["sample-shadows", "--checkpoint", "c", "--truth", "t", "--lights", "l", "--out", "o"], "--val-lights",
     "mix.val_lights"),
    (["sample-shadows", "--checkpoint", "c", "--truth", "t", "--lights", "l", "--out", "o"], "--val-points",
     "mix.val_points"),
    (["sample-shadows", "--checkpoint", "c", "--truth", "t", "--lights", "l", "--out", "o"], "--blend-k",
     "evaluate.blend_k"),
    (["choose-cache", "--weights", "w", "--truth", "t", "--volume", "v", "--lights", "l", "--out", "o"],
     "--val-lights", "cache_auto.val_lights"),
    (["choose-cache", "--weights", "w", "--truth", "t", "--volume", "v", "--lights", "l", "--out", "o"],
     "--val-points", "cache_auto.val_points"),
    (["evaluate-voxels", "--weights", "w", "--generated", "g", "--truth", "t", "--volume", "v", "--lights", "l",
      "--out", "o"], "--ddpm-lights", "evaluate.ddpm_lights"),
    (["evaluate-voxels", "--weights", "w", "--generated", "g", "--truth", "t", "--volume", "v", "--lights", "l",
      "--out", "o"], "--wide-lights", "evaluate.wide_lights"),
    (["evaluate-voxels", "--weights", "w", "--generated", "g", "--truth", "t", "--volume", "v", "--lights", "l",
      "--out", "o"], "--wide-points", "evaluate.wide_points"),
    (["ddp-processes"], "--nproc", "finetune.nproc"),
]


@pytest.mark.parametrize("command, option, key", COUNTS, ids=[f"{c[0][0]} {c[1]}" for c in COUNTS])
def test_a_count_option_takes_what_its_config_key_takes(command, option, key, capsys):
    """A count given on the command line is held to its config key's minimum in the run schema: one below is
    argparse's line naming the option (--eval-points -3 was a negative-dimension traceback from PyTorch, mix's
    --val-points 0 'a validation light scored nan dB' blaming the model, --val-lights 0 numpy's 'need at least one
    array to stack'), the minimum parses."""
    from diffshadow.cli import build_parser
    from diffshadow.config import SCHEMAS, read_yaml

    section, name = key.split(".")
    least = read_yaml(SCHEMAS / "config.schema.yaml")["$defs"][section]["properties"][name]["minimum"]
    parser = build_parser()
    assert getattr(parser.parse_args([*command, option, str(least)]), option[2:].replace("-", "_")) == least
    with pytest.raises(SystemExit):
        parser.parse_args([*command, option, str(least - 1)])
    assert f"argument {option}: expected at least {least}, got {least - 1}" in capsys.readouterr().err


def test_a_warning_is_one_line_naming_the_command(tmp_path):
    """A constant volume renders (its one scalar has an opacity) with the loader's warning as the command's errors
    read: one line, `diffshadow render: warning: ...`, not Python's format with the source line that warned."""
    import numpy as np

    np.save(tmp_path / "flat.npy", np.zeros((8, 8, 8), np.float32))
    (tmp_path / "flat.yaml").write_text(
        "volume: flat.npy\ntransfer_function:\n  opacity: [[0.0, 0.3], [1.0, 0.3]]\n"
        "  color: [[0.0, 1, 1, 1], [1.0, 1, 1, 1]]\n  density_scale: 10\n")
    proc = subprocess.run([sys.executable, "-m", "diffshadow.cli", "render", "--scene-config", "flat.yaml",
                           "--mode", "noshadow", "--size", "16", "--out", "flat.png"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("diffshadow render: warning: "), proc.stderr
    assert "the volume is constant (0.0)" in lines[0] and "UserWarning" not in lines[0], lines[0]
