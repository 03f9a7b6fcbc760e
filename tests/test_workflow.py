"""The Snakemake workflow end to end on a tiny configuration (one test module, one real run)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import installed

from diffshadow.config import defaults
from diffshadow.config import memory_keys as config_memory_keys
from diffshadow.diffusion.mix import SHARES
from diffshadow.lights import read_lights, subset_indices
from diffshadow.store import open_store

REPO = Path(__file__).resolve().parents[1]
CUDA = torch.cuda.is_available()
TINY = {
    "lights": {"sphere": 40, "count": 4, "center": [0.0, 0.0, 1.0], "unseen": 2, "seed": 0},
    "siren": {"width": 8, "blocks": 1},
    "subset_size": 2,
    "preoptimize": {"steps": 5, "lr": 1.0e-3},
    # min_psnr 0: six steps fit nothing well; the floor itself is tested in tests/stress/test_siren_stress.py
    # target_psnr 0: the sizes as given (the ladder that grows them is tested in tests/test_capacity.py)
    "fit": {"steps": 6, "points": 128, "eval_points": 256, "grid_upsample": 1, "chunk": 0, "min_psnr": 0.0,
            "target_psnr": 0.0, "blend_per_light": 2, "blend_points": 32},
    "diffusion": {"preset": "tiny", "epochs": 3, "batch_size": 2, "geometry_points": 16, "presample_points": 64,
                  "checkpoint_every": 1, "ddim_steps": 5, "pool_lights": 4, "pool_points": 32,
                  # the gap check on, as the package has it (config/config.yaml turns it off for the README run)
                  "max_epochs": 5, "target_gap": defaults()["diffusion"]["target_gap"]},
    "finetune": {"views": 1, "image_size": 16, "pixels": 4, "epochs": 2, "batch_size": 4, "nproc": 2,
                 "checkpoint_every": 1, "val_lights": 4, "val_points": 1024},
    "mix": {"val_lights": 8, "val_points": 128},
    "correction": {"steps": 20, "lights": 64, "points": 32, "batch_lights": 8, "batch_points": 32, "hidden": 16,
                   "held_out": 16},
    "evaluate": {"wide_lights": 16, "wide_points": 128},
    "data_inr": {"width": 8, "blocks": 1, "steps": 20, "points": 512, "target_psnr": 0.0},
    "render": {"image_size": 16, "views": 1, "lights_per_set": 1, "bench_sizes": [8], "bench_repeats": 1,
               "bench_memory_sizes": [16]},
}


def snakemake(workdir: Path, *args: str, config: dict = TINY, check: bool = True,
              runner: tuple[str, ...] = ("-m", "snakemake"), repo: Path = REPO,
              cores: str | None = None) -> subprocess.CompletedProcess:
    """Snakemake on the tiny config in `workdir`; `runner` is what follows the interpreter (a script that runs
    Snakemake in its own process and inspects it, for one); `repo`: where the Snakefile and its scene files are;
    `cores`: `--cores` (default 2, 4 on a GPU machine)."""
    cmd, env = snakemake_command(workdir, *args, config=config, runner=runner, repo=repo, cores=cores)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def snakemake_command(workdir: Path, *args: str, config: dict = TINY, runner: tuple[str, ...] = ("-m", "snakemake"),
                      repo: Path = REPO, cores: str | None = None) -> tuple[list[str], dict[str, str]]:
    """`snakemake`'s command line and environment, its config file written."""
    cfg = workdir / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(config))
    env = {**os.environ, "PATH": f"{installed('diffshadow').parent}{os.pathsep}{os.environ['PATH']}"}
    if CUDA:
        # on a GPU the stages run on CUDA, where one seed gives the same bytes only under the documented switch;
        # the determinism test below then checks that switch for the whole workflow
        env["DIFFSHADOW_DETERMINISTIC"] = "1"
    # a GPU machine's jobs wait mostly on starting PyTorch and CUDA (4-5 s each on the H200): four at a time there
    cores = cores or ("4" if CUDA and (os.cpu_count() or 1) >= 4 else "2")
    cmd = [sys.executable, *runner, "-s", str(repo / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(cfg), "--cores", cores, *args]
    return cmd, env


def planned(proc: subprocess.CompletedProcess) -> dict[str, int]:
    """Job counts from a dry run's 'Job stats' table."""
    text = proc.stdout + proc.stderr
    if "Nothing to be done" in text:
        return {}
    table = text.split("Job stats:")[1].split("total")[0]
    return {m[1]: int(m[2]) for m in re.finditer(r"^(\w+)\s+(\d+)\s*$", table, re.M)}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("workflow")
    proc = snakemake(workdir)
    (workdir / "snakemake.out").write_text(proc.stdout + proc.stderr)
    return workdir


def test_a_finished_run_says_what_to_open(finished):
    """The run's last words: the report's command and the viewer's, for each scene that is whole."""
    assert ("results/nucleon is complete: `snakemake --profile local --report report.html` writes the report, "
            "`diffshadow view results/nucleon` opens the viewer") in (finished / "snakemake.out").read_text()


def test_a_fit_may_borrow_the_runs_idle_cores(finished):
    """fit_siren and fit_correction ask Snakemake for one thread and take the run's second core while it idles
    (runtime.SpareThreads; their bytes are the same on any threads: tests/test_fit.py, tests/test_correction.py);
    on a GPU they do not."""
    logs = [(finished / f"results/nucleon/logs/{job}.log").read_text()
            for job in ("fit_siren_0", "fit_siren_1", "fit_correction")]
    assert all(("fitted on 1 thread(s), 2 for " in log) != CUDA for log in logs), logs


def test_builds_the_weight_store(finished):
    store = open_store(finished / "results/nucleon/weights.zarr")
    assert store.weights.shape == (4, store.layout.n_params)
    assert np.isfinite(store.weights).all() and np.isfinite(store.psnr).all()
    assert sorted(p.name for p in (finished / "results/nucleon/sirens").glob("*.npz")) == \
        ["subset_0.npz", "subset_1.npz"]


def test_stage2_outputs(finished):
    import json
    metrics = json.loads((finished / "results/nucleon/voxel_metrics.json").read_text())
    for key in ("generated_psnr_median", "stage1_psnr_median"):
        assert np.isfinite(metrics["seen"][key])
    for key in ("generated_psnr_median", "nearest_psnr_median", "blend_psnr_median", "siren_blend_psnr_median"):
        assert np.isfinite(metrics["unseen"][key])
    assert set(metrics["storage_bytes"]) == {"model", "sirens", "grids", "correction"}  # correction.pt's network
    assert set(metrics["seconds_per_inr"]) == {"ddim", "ddpm"}
    # the workflow tests' config names the tiny preset: a named preset is used as given, never 'auto'-resolved
    assert metrics["diffusion_model"]["preset"] == "tiny" and metrics["diffusion_model"]["parameters"] > 0
    # the seen-light gap measured after three epochs, and every epoch after it that was trained (up to 5)
    dm = metrics["diffusion_model"]
    from diffshadow.diffusion.config import native_bfloat16
    assert dm["precision"] == ("bfloat16" if native_bfloat16() else "float32")  # `auto` as this CPU resolved it
    assert 3 <= dm["epochs"] <= 5 and [c["epoch"] for c in dm["gap_checks"]] == list(range(3, dm["epochs"] + 1))
    assert "within the target" in dm["stopped"] or "max_epochs" in dm["stopped"]
    generated = open_store(finished / "results/nucleon/generated.zarr")
    assert generated.seen.tolist() == [True] * 4 + [False] * 2 and np.isfinite(generated.psnr).all()
    # the model's SIRENs mixed with the stored ones' blend at a share chosen on 8 validation lights; evaluate_voxels
    # scores the model alone beside the mix
    mix = generated.config["mix"]
    assert mix["chosen"] == "validation lights" and mix["validation"] == {"lights": 8, "points": 128, "seed": 0}
    assert mix["model_share"] in SHARES and [r["share"] for r in mix["curve"]] == list(SHARES)
    assert metrics["mix"] == {"model_share": mix["model_share"], "chosen": "validation lights", "blend_k": 4,
                              "blend_weights": "triangle"}
    # the blend it mixes in is corrected by fit_correction's correction.pt (TINY's 20 steps), and says so
    assert mix["correction"] == {"path": "results/nucleon/correction.pt", "config": mix["correction"]["config"]}
    assert mix["correction"]["config"]["steps"] == 20 and metrics["corrected"] is True
    check = metrics["correction_check"]  # its fit's held-out check (TINY's 16 lights), which kept it
    assert check["lights"] == 16 and check["kept"] and set(check) == {"lights", "significant", "kept", "box", "visible"}
    assert np.isfinite(metrics["seen"]["model_alone_psnr_median"])
    assert np.isfinite(metrics["unseen"]["model_alone_psnr_median"])
    # the further test lights: the same comparison at the run's share, with its own draw and counts
    wide = metrics["wide"]
    assert (wide["lights"], wide["points"], wide["seed"], wide["model_share"], wide["blend_k"]) == \
        (16, 128, 2, mix["model_share"], 4) and wide["corrected"] is True
    assert 0 <= wide["better_than_weight_blend"] <= 16 and 0 <= wide["better_than_model_alone"] <= 16
    lo, hi = wide["weight_blend_gap_interval95_db"]
    assert lo <= hi and np.isfinite([lo, hi, wide["generated_psnr_median"], wide["model_alone_psnr_median"]]).all()


def test_the_wide_comparison_at_share_0_is_the_blend_and_at_share_1_the_model(finished):
    """The cache's answer on the further test lights is the weight blend at share 0 (no light better, a zero gap)
    and the model alone at share 1; its lights are none of the test, validation or pool lights."""
    from diffshadow import artifacts
    from diffshadow.evaluate import wide_comparison
    from diffshadow.lights import training_pool, validation_lights, wide_test_lights
    from diffshadow.volume import load_prepared

    res = finished / "results/nucleon"
    lights, state = read_lights(res / "lights.json"), artifacts.load_checkpoint(res / "diffusion.ckpt")
    volume, tf = load_prepared(res / "volume.zarr")
    ends = {share: wide_comparison(state, open_store(res / "weights.zarr"), lights, volume, tf, share=share, lights=12,
                                   points=64, seed=3, blend_k=2, weighting="triangle") for share in (0.0, 1.0)}
    blend, model = ends[0.0], ends[1.0]
    assert blend["generated_psnr_median"] == blend["weight_blend_psnr_median"] == model["weight_blend_psnr_median"]
    assert blend["better_than_weight_blend"] == 0 and blend["weight_blend_gap_interval95_db"] == [0.0, 0.0]
    assert model["generated_psnr_median"] == model["model_alone_psnr_median"] == blend["model_alone_psnr_median"]
    assert model["better_than_model_alone"] == 0 and model["model_alone_gap_interval95_db"] == [0.0, 0.0]
    # the lower tail likewise, each under its median
    assert blend["generated_psnr_p10"] == blend["weight_blend_psnr_p10"] < blend["weight_blend_psnr_median"]
    assert model["generated_psnr_p10"] == model["model_alone_psnr_p10"] < model["model_alone_psnr_median"]
    wide = wide_test_lights(lights["train"], lights["center"], 12, seed=3)
    others = np.concatenate([lights["unseen"], validation_lights(lights["train"], lights["center"], 12, seed=3),
                             training_pool(lights["train"], lights["center"], 12, seed=3)])
    assert np.abs(wide @ others.T).max() < 1 - 1e-9  # no further test light is any of those
    with pytest.raises(ValueError, match=r"evaluate.wide_lights, evaluate.wide_points\): expected at least 1 light "
                       r"and 1 point, got -3 and 64"):
        wide_comparison(state, open_store(res / "weights.zarr"), lights, volume, tf, share=0.5, lights=-3, points=64,
                        seed=3, blend_k=2, weighting="triangle")



def test_without_a_model_the_wide_comparison_is_the_caches_blend(finished, tmp_path):
    """No model (`cache: blend` or a codec): the further lights are those a diffusion run draws, the weight blend's
    median is the one it reports; `cache: blend` answers with that blend (no gap to state), a codec with its decoded
    store's blend (the fp32 store itself: a zero gap; fp16: within 0.05 dB, no model keys either way), and a store
    of other lights is refused by name, before the work."""
    import dataclasses

    from diffshadow import artifacts
    from diffshadow.evaluate import wide_comparison
    from diffshadow.volume import load_prepared

    res = finished / "results/nucleon"
    lights, state = read_lights(res / "lights.json"), artifacts.load_checkpoint(res / "diffusion.ckpt")
    volume, tf = load_prepared(res / "volume.zarr")
    stage1 = open_store(res / "weights.zarr")
    args = dict(share=0.5, lights=12, points=64, seed=3, blend_k=2, weighting="triangle")
    model = wide_comparison(state, stage1, lights, volume, tf, **args)
    blend = wide_comparison(None, stage1, lights, volume, tf, **args)
    assert blend["generated_psnr_median"] == blend["weight_blend_psnr_median"] == model["weight_blend_psnr_median"]
    assert not {"model_share", "model_alone_psnr_median", "weight_blend_gap_interval95_db", "codec"} & set(blend)
    same = wide_comparison(None, stage1, lights, volume, tf, cache=stage1, **args)
    assert same["weight_blend_gap_interval95_db"] == [0.0, 0.0] and same["better_than_weight_blend"] == 0
    half = dataclasses.replace(stage1, weights=np.asarray(stage1.weights, np.float16).astype(np.float32),
                               config={**stage1.config, "codec": "fp16"})
    fp16 = wide_comparison(None, stage1, lights, volume, tf, cache=half, **args)
    assert fp16["codec"] == "fp16" and "model_alone_psnr_median" not in fp16
    assert abs(fp16["generated_psnr_median"] - fp16["weight_blend_psnr_median"]) < 0.05
    # a store of other lights (here the generated one: training and unseen) is refused before any work is done
    from diffshadow.stages.stage2 import evaluate_voxels
    n = len(stage1.lights)
    with pytest.raises(ValueError, match=f"--cache-weights {res / 'generated.zarr'}: {n + 2} lights, not the {n} of "
                       f"--weights {res / 'weights.zarr'} in their order"):
        evaluate_voxels(None, res / "weights.zarr", res / "generated.zarr", res / "eval_truth.zarr",
                        res / "volume.zarr", res / "lights.json", tmp_path / "v.json", blend_k=2, weighting="triangle",
                        ddpm_lights=0, wide_lights=12, cache_path=res / "generated.zarr")
    assert not (tmp_path / "v.json").exists()


def test_a_damaged_volume_fails_evaluate_voxels_before_its_work(finished, tmp_path, monkeypatch):
    """The further lights' volume is read, its checksum checked, before the metrics and the sampler curve (8 s on
    the README run): a damaged chunk failed the job only after them."""
    import shutil

    from diffshadow.io import StoreError
    from diffshadow.stages import stage2

    res = finished / "results/nucleon"
    volume = tmp_path / "volume.zarr"
    shutil.copytree(res / "volume.zarr", volume)
    chunk = max((p for p in (volume / "scalar").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])

    def work(*a, **k):
        raise AssertionError("the metrics ran before the volume was read")

    monkeypatch.setattr(stage2, "voxel_metrics", work)
    with pytest.raises(StoreError, match=r"volume.zarr: array 'scalar' cannot be read .*rerun `prepare_volume`"):
        stage2.evaluate_voxels(None, res / "weights.zarr", res / "generated.zarr", res / "eval_truth.zarr", volume,
                               res / "lights.json", tmp_path / "v.json", blend_k=2, weighting="triangle",
                               ddpm_lights=0, wide_lights=12)
    assert not (tmp_path / "v.json").exists()


def test_the_stored_sirens_are_the_models_mixed_with_the_blend_at_the_share_recorded(finished, tmp_path):
    """generated.zarr = share x (sample_shadows at share 1: the model alone) + (1 - share) x (at share 0: each
    training light's own stored SIREN, each unseen light's blend of its nearest stored SIRENs, corrected by the
    run's correction.pt)."""
    from diffshadow.correction import load_correction
    from diffshadow.diffusion.mix import mix_weights
    from diffshadow.stages.stage2 import sample_shadows
    from diffshadow.store import BlendSampler

    results = finished / "results/nucleon"
    generated = open_store(results / "generated.zarr")
    ends = {}
    for share in (1, 0):
        out = tmp_path / f"share{share}.zarr"
        sample_shadows(finished / generated.config["checkpoint"], results / "eval_truth.zarr",
                       results / "lights.json", out, device=torch.device("cuda" if CUDA else "cpu"),
                       mix={"model_share": share}, weights_path=results / "weights.zarr", blend_k=4,
                       correction_path=results / "correction.pt")
        ends[share] = open_store(out)
        assert ("mix" in ends[share].config) == (share == 0)
    stored = open_store(results / "weights.zarr")
    assert np.array_equal(ends[0].weights[:4], stored.weights)
    unseen = read_lights(results / "lights.json")["unseen"]
    blend = BlendSampler(stored, 4, "triangle", load_correction(results / "correction.pt", stored.lights))
    assert np.allclose(ends[0].weights[4:], np.stack([blend(w) for w in unseen]), atol=1e-7)
    plain = BlendSampler(stored, 4, "triangle")
    assert not np.allclose(ends[0].weights[4:], np.stack([plain(w) for w in unseen]), atol=1e-7)
    expected = mix_weights(ends[1].weights, ends[0].weights, generated.config["mix"]["model_share"])
    np.testing.assert_allclose(generated.weights, expected, rtol=0, atol=1e-5 if CUDA else 0)


def test_viewer_in_a_browser(finished, tmp_path):
    """`diffshadow view` on the finished scene, driven in headless Chromium: the still frame is drawn at the
    canvas's own size; an unseen test light picked from the list, a new direction typed in (its SIREN made as the
    run's cache makes one: diffusion, blend or their mix), mode gt at two lights and a light outside the cache's
    region (drawn exactly, and said) each put on the canvas, pixel for pixel left of the panel's shadow, what
    `diffshadow render` draws from the viewer's starting camera with that light; in every mode the panel's
    commands are its frame's; `inr | gt` is labelled and the difference states its scale;
    a second tab records apart from the first."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    from browser import drive_viewer, find_browser

    from diffshadow.viewer.scene import mix_name

    if find_browser() is None:
        pytest.skip("no Chromium on PATH (Debian: apt-get install chromium): the viewer's browser test needs one")
    figures = drive_viewer(finished / "results/nucleon", tmp_path)
    assert figures["still_size"] == figures["canvas_size"], figures
    for name in ("unseen", "new", "gt_before", "gt_after", "outside"):
        assert figures[f"{name}_psnr_vs_render"] >= 40, (name, figures)
        assert figures[f"{name}_max_diff_vs_render"] <= 1, (name, figures)  # pixel for pixel, left of the panel
        assert figures[f"{name}_frame_vs_panel_max_diff"] <= 1, (name, figures)
    assert figures["new_light"].startswith("new direction"), figures
    # moving the light changes the image well beyond the 40 dB match (the exact shadow: this run's 6-step SIRENs
    # hardly depend on the light, the README run's do: 34 dB between training light 0 and unseen light 1)
    assert figures["gt_changed_psnr"] < 35, figures
    assert figures["outside_shown"] == "gt" and figures["outside_panel"], figures
    assert "outside the cache: exact shadow" in figures["outside_status"], figures
    assert all(v is True for v in figures["commands_match"].values()), figures["commands_match"]
    share = open_store(finished / "results/nucleon/generated.zarr").config["mix"]["model_share"]
    assert figures["side_by_side_labels"] == [f"cache ({mix_name(share, corrected=True)})", "exact (gt)"], figures
    assert figures["side_by_side_label_band"] > 0.3, figures  # the dark band behind the label is drawn
    assert figures["diff_scale"] in (1, 2, 4, 8, 16, 32, 64) and "white is a difference" in figures["diff_status"]
    assert figures["second_tab_folder"] and figures["first_tab_kept"], figures


def test_the_cache_region_travels_with_the_stores_and_checkpoints_and_render_keeps_to_it(finished):
    """The light region (the cap of the training lights) is written with the stage-1 store, the checkpoints and the
    generated store; `render` with a light outside it refuses in one line naming the region and the light's angle
    to it (exit code 2) unless --outside-region asks, and renders a light inside it quietly."""
    from diffshadow.artifacts import load_checkpoint
    from diffshadow.diffusion.sample import checkpoint_region
    from diffshadow.lights import LightRegion, read_lights

    res = finished / "results/nucleon"
    sets = read_lights(res / "lights.json")
    expect = LightRegion.of(sets["train"], sets["unseen"], sets["center"]).to_dict()
    assert open_store(res / "weights.zarr").region == expect == open_store(res / "generated.zarr").region
    for ckpt in ("diffusion_geometry.ckpt", "diffusion.ckpt"):
        assert checkpoint_region(load_checkpoint(res / ckpt)).to_dict() == expect
    base = [sys.executable, "-m", "diffshadow.cli", "render", "--volume", str(res / "volume.zarr"), "--data-inr",
            str(res / "data_inr.pt"), "--diffusion", str(res / "diffusion.ckpt"), "--mode", "inr", "--size", "16"]
    out = subprocess.run([*base, "--light", "1", "0", "0.2", "--out", str(finished / "x.png")], capture_output=True,
                         text=True)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and not (finished / "x.png").exists()
    assert "outside the cache's region (a " in out.stderr and "past its edge" in out.stderr, out.stderr
    anyway = subprocess.run([*base, "--light", "1", "0", "0.2", "--outside-region", "--out", str(finished / "y.png")],
                            capture_output=True, text=True)
    assert anyway.returncode == 0 and anyway.stdout.startswith("warning: the light is outside"), anyway.stdout
    near = sets["unseen"][0]  # as near a training light as the evaluation went: quiet
    inside = subprocess.run([*base, "--light", *(repr(float(x)) for x in near), "--out", str(finished / "z.png")],
                            capture_output=True, text=True)
    assert inside.returncode == 0 and inside.stdout.startswith("wrote") and "warning" not in inside.stdout
    # this tiny run's 4 lights sit ~10 degrees from +z's neighbourhood: +z itself is inside, but farther out than
    # its unseen lights went, so it renders with a one-line note
    far = subprocess.run([*base, "--light", "0.05", "0.05", "1", "--out", str(finished / "f.png")],
                         capture_output=True, text=True)
    assert far.returncode == 0 and far.stdout.startswith("warning: the light is inside the cache's region but")


def test_a_stored_rows_shadow_is_drawn_only_under_its_own_light(finished, tmp_path, capsys):
    """`render --weights S --light-index N --mode inr` draws row N's shadow SIREN: with --light its own direction
    (as the viewer's panel commands give it) it renders, with another it is refused in one line (it rendered row N's
    shadow as if it were that light's); --mode gt takes --light whatever the row."""
    from diffshadow.cli import main

    res = finished / "results/nucleon"
    own = open_store(res / "generated.zarr").lights[1]
    base = ["render", "--volume", str(res / "volume.zarr"), "--data-inr", str(res / "data_inr.pt"), "--weights",
            str(res / "generated.zarr"), "--light-index", "1", "--size", "16"]
    main([*base, "--mode", "inr", "--light", *map(repr, own.tolist()), "--out", str(tmp_path / "own.png")])
    main([*base, "--mode", "gt", "--light", "0", "0.3", "1", "--out", str(tmp_path / "gt.png")])
    with pytest.raises(SystemExit) as exit_info:
        main([*base, "--mode", "inr", "--light", "0", "0.3", "1", "--out", str(tmp_path / "other.png")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1 and "is not light 1 of" in err, err
    assert (tmp_path / "own.png").exists() and (tmp_path / "gt.png").exists() and not (tmp_path / "other.png").exists()


def test_every_cache_names_the_scene_it_was_made_for(finished, tmp_path, capsys):
    """Stage 1's SIRENs, the model and the generated store carry the extinction field they shade
    (`volume.extinction_id`), the data INR its grid's checksum. `render` refuses them on another scene in one line
    (a denser TF, another grid), and takes them under a recoloured TF, whose shadows are the same; `view` refuses a
    results folder put together from two runs."""
    import shutil

    from diffshadow.artifacts import load_checkpoint, load_data_inr
    from diffshadow.cli import main
    from diffshadow.transfer import TransferFunction
    from diffshadow.viewer.scene import ViewerError, ViewerScene
    from diffshadow.volume import Volume, extinction_id, load_prepared, save_prepared

    res = finished / "results/nucleon"
    volume, tf = load_prepared(res / "volume.zarr")
    here = extinction_id(volume, tf)
    assert open_store(res / "weights.zarr").extinction == open_store(res / "generated.zarr").extinction == here
    assert load_checkpoint(res / "diffusion.ckpt")["extinction"] == here
    assert load_data_inr(res / "data_inr.pt").volume == volume.checksum
    denser = TransferFunction.from_config({**tf.to_config(), "density_scale": 2 * tf.density_scale})
    recoloured = TransferFunction.from_config({**tf.to_config(), "color": [[0, 1, 0, 0], [1, 0, 0, 1]]})
    flipped = Volume(np.ascontiguousarray(volume.data[::-1]), volume.extent, volume.name)
    for name, v, t in (("denser", volume, denser), ("recoloured", volume, recoloured), ("flipped", flipped, tf)):
        save_prepared(tmp_path / f"{name}.zarr", v, t)

    def render(scene: str, *args: str) -> tuple[int, str]:
        out = tmp_path / f"{scene}.png"
        try:
            main(["render", "--volume", str(tmp_path / f"{scene}.zarr"), *args, "--size", "16", "--out", str(out)])
        except SystemExit as e:
            assert not out.exists()
            return e.code, capsys.readouterr().err
        return 0, ""

    own = open_store(res / "generated.zarr").lights[0]
    row = ["--weights", str(res / "generated.zarr"), "--light-index", "0", "--mode", "inr"]
    model = ["--diffusion", str(res / "diffusion.ckpt"), "--light", *map(repr, own.tolist()), "--mode", "inr"]
    assert render("recoloured", *row, "--data-inr", str(res / "data_inr.pt")) == (0, "")
    import json  # the run's own volume.zarr recoloured on the command line: its cache still shades it
    main(["render", "--volume", str(res / "volume.zarr"), "--tf-json", json.dumps(recoloured.to_config()), *row,
          "--data-inr", str(res / "data_inr.pt"), "--size", "16", "--out", str(tmp_path / "tf.png")])
    assert (tmp_path / "tf.png").exists()
    for cache in (row, model):
        code, err = render("denser", *cache)
        assert code == 2 and err.count("\n") == 1, err
        assert f"made for another volume or opacity than the volume rendered (extinction field {here} against" in err
    code, err = render("flipped", "--data-inr", str(res / "data_inr.pt"), "--mode", "noshadow")
    assert code == 2 and err.count("\n") == 1 and "data_inr.pt: fitted to another volume than" in err, err
    for scene, why in (("denser", "weights.zarr: made for another volume or opacity"),
                       ("flipped", "data_inr.pt: fitted to another volume than")):  # bench render: before any timing
        with pytest.raises(SystemExit):
            main(["bench", "render", "--volume", str(tmp_path / f"{scene}.zarr"), "--data-inr",
                  str(res / "data_inr.pt"), "--weights", str(res / "weights.zarr"), "--out", str(tmp_path / "b.json")])
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and why in err and not (tmp_path / "b.json").exists(), err
    mixed = tmp_path / "nucleon"
    shutil.copytree(res, mixed, ignore=shutil.ignore_patterns("logs", "images", "report", "benchmarks", "sirens"))
    save_prepared(mixed / "volume.zarr", volume, denser)
    with pytest.raises(ViewerError, match=r"generated.zarr: made for another volume or opacity than .*volume.zarr"):
        ViewerScene.from_results(mixed, torch.device("cpu"))
    main(["check-store", str(res)])  # one scene: every store that records it agrees
    assert f"{res / 'volume.zarr'}: scalar: checksums match" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        main(["check-store", str(mixed)])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1, err
    assert f"{mixed}: its stores were made for 2 different scenes (extinction fields: " in err
    assert f"volume.zarr for {extinction_id(volume, denser)}" in err and f"weights.zarr for {here}" in err
    # a folder of scenes (results/): each scene's folder checked on its own
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "a").symlink_to(res)
    (runs / "b").symlink_to(mixed)
    with pytest.raises(SystemExit):
        main(["check-store", str(runs)])
    out, err = capsys.readouterr()
    assert f"{runs / 'a' / 'weights.zarr'}: " in out and f"{runs / 'b'}: its stores were made for 2 different" in err


def test_render_outputs(finished):
    import json
    res = finished / "results/nucleon"
    images = json.loads((res / "image_metrics.json").read_text())
    # one training and one unseen light, one view: stage-1 only for the training light
    assert images["modes"]["inr_stage1"]["count"] == 1 and images["modes"]["inr_generated"]["count"] == 2
    for mode in ("inr_stage1", "inr_generated", "inr_generated_data_inr", "naive", "noshadow"):
        assert np.isfinite(images["modes"][mode]["psnr"]) and 0 < images["modes"][mode]["ssim"] <= 1
    assert images["lpips"].startswith(("available", "unavailable"))
    # training light: gt, stage 1, generated, generated + data INR, naive, noshadow; unseen: no stage 1, no naive,
    # and the plain weight blend beside the answer (the corrected blend)
    assert len(list((res / "images").glob("*.png"))) == 6 + 5
    assert images["weight_blend_images"]["images"] == images["modes"]["inr_weight_blend"]["count"] == 1
    assert not list((res / "images").glob("unseen*_naive.png"))
    bench = json.loads((res / "bench.json").read_text())
    row = bench["sizes"]["8"]
    assert set(row["fps"]) == set(row["peak_mem_bytes"]) == {"noshadow", "inr", "naive"}
    # peak memory: the frames' tensors, at the bench size and the memory-only one past it
    assert min(row["peak_mem_bytes"].values()) > 0
    assert {m: set(r) for m, r in bench["memory_scaling"].items()} == {"noshadow": {"8", "16"}, "inr": {"8", "16"}}
    # no timing bar here (a busy machine made naive faster than inr at 8x8 once): the work, which does not drift
    assert row["speedup"] > 0 and row["overhead"] > 0
    assert row["samples"]["naive"]["secondary"] > 10 * row["samples"]["inr"]["primary"] > 0
    assert row["counts"]["naive"]["ops"] > row["counts"]["inr"]["ops"] > row["counts"]["noshadow"]["ops"]
    assert (res / "bench.png").stat().st_size > 1000


# Determinism (tests/stress, issue 8): a second run of the whole tiny workflow with the same seed must write
# the same bytes, stage by stage. Timings are the exception: files that are measurements of time or memory are
# left out, and in JSON the timing keys are dropped before comparing.
STAGE_OUTPUTS = {
    "prepare_volume": ["volume.zarr"],
    "lights": ["lights.json"],
    "preoptimize": ["siren_init.pt"],
    "fit_siren": ["sirens/subset_0.npz", "sirens/subset_1.npz"],
    "collect_weights": ["weights.zarr"],
    "presample": ["geometry_points.zarr"],
    "eval_truth": ["eval_truth.zarr"],
    "train_diffusion": ["diffusion_geometry.ckpt"],
    "render_targets": ["targets.zarr"],
    "finetune_render": ["diffusion.ckpt", "finetune_metrics.json"],
    "fit_correction": ["correction.pt"],
    "sample_shadows": ["generated.zarr"],
    "evaluate_voxels": ["voxel_metrics.json"],
    "caches": ["caches.json", "report/caches.png"],
    "train_data_inr": ["data_inr.pt"],
    "naive_images": ["naive_images.zarr"],
    "bench_naive": ["bench_naive.json"],  # counts and peak bytes, which do not drift: why it runs beside stage 1
    "evaluate_images": ["image_metrics.json", "images"],
    "report_figures": ["report/config.yaml", "report/siren_psnr.png", "report/generated_psnr.png",
                       "report/generated_psnr.csv", "report/image_grid.png", "report/storage.png"],
}
TIMED = {"bench.json", "bench.png", "bench_shadow.json", "bench_shadow.png", "report/ddim_curve.png",
         "report/shadow_curve.png", "benchmarks", "stage_costs.tsv", "report/timeline.png",
         "report/summary.html", "report/landing.rst"}  # measurements of time or memory by design (or tables of them)
TIMING_KEY = re.compile(r"second|_s$|fps|speedup|peak_mem")
HOW_IT_RAN = {"processes", "ranks"}  # finetune_metrics.json: its DDP processes (-j1: one), each with its timings


def _without_timings(x):
    if isinstance(x, dict):
        return {k: _without_timings(v) for k, v in x.items() if not TIMING_KEY.search(k) and k not in HOW_IT_RAN}
    if isinstance(x, list):
        return [_without_timings(v) for v in x]
    return x


def _first_difference(x, y, where: str = "") -> str:
    """Where two JSON values or byte strings first differ (for the failure message)."""
    if isinstance(x, dict) and isinstance(y, dict):
        for k in sorted(set(x) | set(y)):
            if x.get(k) != y.get(k):
                return _first_difference(x.get(k), y.get(k), f"{where}.{k}")
    if isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
        for i, (a, b) in enumerate(zip(x, y, strict=True)):
            if a != b:
                return _first_difference(a, b, f"{where}[{i}]")
    if isinstance(x, bytes) and isinstance(y, bytes):
        n = next((i for i, (a, b) in enumerate(zip(x, y, strict=False)) if a != b), min(len(x), len(y)))
        return f"byte {n} of {len(x)} vs {len(y)}"
    return f"{where or 'value'}: {x!r} vs {y!r}"


@pytest.fixture(scope="module")
def second_run(finished, tmp_path_factory):
    workdir = tmp_path_factory.mktemp("workflow_again")
    # only what is compared: the benchmark (timings by design) is left out, which keeps `pytest -m stress` short.
    # On one core (`-j1`): every rule on one thread and fine-tuning in one process, where the first run had two,
    # so the same bytes say both that a rerun repeats and that `-j` is no part of the result
    targets = [p for paths in STAGE_OUTPUTS.values() for p in paths]
    snakemake(workdir, *(f"results/nucleon/{p}" for p in targets), cores="1")
    return workdir


def test_every_output_belongs_to_a_compared_stage_or_is_a_timing(finished):
    res = finished / "results/nucleon"
    covered = {p for paths in STAGE_OUTPUTS.values() for p in paths} | TIMED | {"logs"}
    covered |= {p.split("/")[0] for p in covered}
    tops = {p.relative_to(res).as_posix() for p in res.iterdir()} | \
        {p.relative_to(res).as_posix() for p in (res / "report").iterdir()}
    assert tops - {"report"} <= covered, sorted(tops - covered - {"report"})


@pytest.mark.stress
@pytest.mark.parametrize("stage", sorted(STAGE_OUTPUTS))
def test_a_second_run_writes_identical_bytes(finished, second_run, stage):
    import json
    for rel in STAGE_OUTPUTS[stage]:
        a, b = finished / "results/nucleon" / rel, second_run / "results/nucleon" / rel
        files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file()) if a.is_dir() else [Path()]
        assert files == (sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()) if b.is_dir() else [Path()])
        for f in files:
            x, y = (a / f).read_bytes(), (b / f).read_bytes()
            if (a / f).suffix == ".json":
                # every float to its last digit: JSON holds Python's shortest repr of the float64
                x, y = (_without_timings(json.loads(v)) for v in (x, y))
            assert x == y, f"{stage}: {rel}/{f} differs between two runs with one seed: {_first_difference(x, y)}"


def test_nothing_left_to_do(finished):
    assert planned(snakemake(finished, "-n")) == {}


def test_diffusion_settings_do_not_refit(finished):
    changed = {**TINY, "diffusion": {**TINY["diffusion"], "epochs": 4, "seed": 3}}
    assert "fit_siren" not in planned(snakemake(finished, "-n", config=changed))
    refit = {**TINY, "fit": {**TINY["fit"], "steps": 7}}  # the control: a fit setting does refit
    assert planned(snakemake(finished, "-n", config=refit))["fit_siren"] == 2


def test_a_colour_change_redraws_and_refits_nothing(finished, tmp_path):
    """The TF's colours change the images, not a shadow: recoloured in its scene file, the scene is prepared again and
    what draws images reruns, and nothing that reads only the extinction field (workflow/rules/common.smk,
    `extinction_volume`); with another density_scale, all of it reruns. On a copy of the workflow, whose scene file
    is changed, over the finished run."""
    import shutil

    copy = tmp_path / "repo"
    for name in ("workflow", "config"):
        shutil.copytree(REPO / name, copy / name)
    shutil.copy2(REPO / "Snakefile", copy / "Snakefile")
    scene = copy / "config/scenes/nucleon.yaml"
    original = yaml.safe_load(scene.read_text())
    assert planned(snakemake(finished, "-n", repo=copy)) == {}  # the copy is the same workflow
    tf = original["transfer_function"]
    field_only = {"preoptimize", "fit_siren", "collect_weights", "presample", "train_diffusion", "eval_truth",
                  "train_data_inr", "shadow_bench"}
    for change, refits in (({"color": [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 1.0]]}, False),
                           ({"density_scale": 2 * tf["density_scale"]}, True)):
        scene.write_text(yaml.safe_dump({**original, "transfer_function": {**tf, **change}}))
        jobs = planned(snakemake(finished, "-n", repo=copy))
        assert {"prepare_volume", "render_targets", "naive_images", "evaluate_images", "benchmark"} <= set(jobs), jobs
        assert (field_only <= set(jobs)) if refits else not field_only & set(jobs), (change, jobs)


def test_caches_table_every_cache_with_its_bytes_and_psnr(finished):
    """caches.json: the stored SIRENs, at least one codec, the model in fp32 and fp16, the dense grids; each
    with its bytes and seen and unseen PSNR; the model's fp32 row is the one voxel_metrics.json scores."""
    import json

    res = finished / "results/nucleon"
    table = json.loads((res / "caches.json").read_text())
    rows = {r["cache"]: r for r in table["caches"]}
    assert {r["kind"] for r in rows.values()} == {"stored", "codec", "corrected", "model", "mix", "grids"}
    for r in rows.values():
        assert r["bytes"] > 0 and np.isfinite(r["seen_psnr"]) and np.isfinite(r["unseen_psnr"]), r
    assert rows["diffusion model fp16"]["bytes"] * 2 == rows["diffusion model fp32"]["bytes"]
    assert rows["stored SIRENs fp16"]["bytes"] * 2 == rows["stored SIRENs fp32"]["bytes"]
    voxel = json.loads((res / "voxel_metrics.json").read_text())
    assert rows["diffusion model fp32"]["seen_psnr"] == pytest.approx(voxel["seen"]["model_alone_psnr_median"])
    assert rows["stored SIRENs fp32"]["unseen_psnr"] == pytest.approx(voxel["unseen"]["weight_blend_psnr_median"])
    # the mix kept in fp32 is what sample_shadows stored; in fp16 it keeps both parts at half the bytes
    share = voxel["mix"]["model_share"]
    mixed = rows[f"model {share:g} + stored SIRENs {1 - share:g}, both fp32"]
    assert mixed["seen_psnr"] == pytest.approx(voxel["seen"]["generated_psnr_median"])
    assert mixed["unseen_psnr"] == pytest.approx(voxel["unseen"]["generated_psnr_median"])
    # the stored SIRENs with the blend's correction: its bytes on top, in every cache that blends with it
    fix = rows["stored SIRENs fp32, corrected"]["bytes"] - rows["stored SIRENs fp32"]["bytes"]
    assert fix > 0 and rows["stored SIRENs fp32, corrected"]["seen_psnr"] == rows["stored SIRENs fp32"]["seen_psnr"]
    assert mixed["bytes"] == rows["diffusion model fp32"]["bytes"] + rows["stored SIRENs fp32"]["bytes"] + fix
    half = rows[f"model {share:g} + stored SIRENs {1 - share:g}, both fp16"]
    assert half["bytes"] == rows["diffusion model fp16"]["bytes"] + rows["stored SIRENs fp16"]["bytes"] + fix


def test_the_model_alone_reads_no_stored_sirens_and_a_new_share_resamples_only(finished):
    """mix.model_share 1: sample_shadows' command reads no stored SIRENs (the model alone); another share reruns
    sample_shadows and what reads its store, never stage 2's training."""
    alone = {**TINY, "mix": {**TINY["mix"], "model_share": 1}}
    shell = snakemake(finished, "-n", "-p", "-f", "results/nucleon/generated.zarr", config=alone).stdout
    line = next(x for x in shell.splitlines() if " sample-shadows " in x)
    assert "--weights" not in line and "--model-share" not in line, line
    fixed = planned(snakemake(finished, "-n", config={**TINY, "mix": {**TINY["mix"], "model_share": 0.5}}))
    assert "sample_shadows" in fixed and "evaluate_voxels" in fixed and "train_diffusion" not in fixed, fixed


def test_the_sampler_curve_resumes_where_an_interrupted_evaluation_stopped(finished, tmp_path):
    """evaluate_voxels stopped after two of its five sampler rows resumes at the third: the same metrics as one
    uninterrupted evaluation, the first two rows' timings those measured before the stop, the checkpoint gone at
    the end; a checkpoint made for other lights is not resumed."""
    from conftest import Killed, stop_at

    from diffshadow import artifacts
    from diffshadow.evaluate import voxel_metrics
    from diffshadow.stages.stage2 import prepared_voxels

    res, ckpt = finished / "results/nucleon", tmp_path / "voxel_metrics.json.ckpt"
    lights = read_lights(res / "lights.json")
    state, geometry = (artifacts.load_checkpoint(res / name) for name in ("diffusion.ckpt", "diffusion_geometry.ckpt"))

    def evaluate(log, light_sets=lights):
        return voxel_metrics(state, open_store(res / "weights.zarr"), open_store(res / "generated.zarr"),
                             artifacts.read_eval_truth(res / "eval_truth.zarr"), light_sets, blend_k=2,
                             weighting="triangle", ddpm_lights=2, grid_voxels=prepared_voxels(res / "volume.zarr"),
                             geometry_state=geometry, curve_checkpoint=ckpt, log=log)

    whole = evaluate(log=lambda m: None)
    with pytest.raises(Killed):
        evaluate(log=stop_at("[evaluate voxels] ddim 10 steps"))
    before = torch.load(ckpt, weights_only=True)["curve"]
    said = []
    resumed = evaluate(log=said.append)
    assert f"[evaluate voxels] resuming from {ckpt} after 2 of 5 sampler rows" in said
    assert not any(m.startswith(("[evaluate voxels] ddim 5 ", "[evaluate voxels] ddim 10 ")) for m in said)
    assert resumed["sampling"]["curve"][:2] == before and not ckpt.exists()
    timed = ("seconds_per_inr", "speedup")
    strip = [{k: v for k, v in r.items() if k not in timed} for r in (whole["sampling"], resumed["sampling"])]
    for r in strip:
        r["curve"] = [{k: v for k, v in row.items() if k not in timed} for row in r["curve"]]
    assert strip[0] == strip[1]
    assert {k: v for k, v in whole.items() if k not in ("sampling", *timed)} == \
        {k: v for k, v in resumed.items() if k not in ("sampling", *timed)}
    with pytest.raises(Killed):
        evaluate(log=stop_at("[evaluate voxels] ddim 10 steps"))
    said.clear()
    other = {**lights, "train": lights["train"][::-1].copy()}
    evaluate(log=said.append, light_sets=other)
    assert f"ignoring {ckpt}: it belongs to other inputs or settings" in said and not ckpt.exists()


def test_evaluate_ddpm_lights_0_drops_the_sampler_curve_alone(finished, tmp_path):
    """`evaluate.ddpm_lights: 0` (the schema's least) once failed evaluate_voxels in numpy ("need at least one array
    to stack"). It leaves out the sampler curve and DDPM and keeps everything else: the same figures as with a
    curve but for the samplers' rows, DDIM's time per INR still timed; the report's figure and front page say so."""
    import json
    import shutil

    from diffshadow import artifacts
    from diffshadow.evaluate import voxel_metrics
    from diffshadow.report import ddim_curve_figure
    from diffshadow.stages.stage2 import prepared_voxels
    from diffshadow.summary import RunResults

    res = finished / "results/nucleon"
    state, geometry = (artifacts.load_checkpoint(res / name) for name in ("diffusion.ckpt", "diffusion_geometry.ckpt"))

    def evaluate(ddpm_lights: int) -> dict:
        return voxel_metrics(state, open_store(res / "weights.zarr"), open_store(res / "generated.zarr"),
                             artifacts.read_eval_truth(res / "eval_truth.zarr"), read_lights(res / "lights.json"),
                             blend_k=2, weighting="triangle", ddpm_lights=ddpm_lights, geometry_state=geometry,
                             grid_voxels=prepared_voxels(res / "volume.zarr"), log=lambda m: None)

    none, some = evaluate(0), evaluate(2)
    assert set(none["sampling"]) == {"ddim_steps", "lights", "device", "threads"} and none["sampling"]["lights"] == 0
    assert set(none["seconds_per_inr"]) == {"ddim"} and none["seconds_per_inr"]["ddim"] > 0
    assert {k: v for k, v in none.items() if k not in ("sampling", "seconds_per_inr")} == \
        {k: v for k, v in some.items() if k not in ("sampling", "seconds_per_inr")}
    ddim_curve_figure(none["sampling"], tmp_path / "ddim_curve.png")
    assert (tmp_path / "ddim_curve.png").stat().st_size > 0
    for name in ("image_metrics.json", "bench.json", "finetune_metrics.json"):
        shutil.copy(res / name, tmp_path / name)
    (tmp_path / "voxel_metrics.json").write_text(json.dumps(none))
    run = RunResults(tmp_path, "nucleon")
    assert "Sampling: DDIM against" not in run.tables()
    timed = f"{none['seconds_per_inr']['ddim']:.3f} s on cpu"
    assert dict(run.headline())["time per shadow INR (DDIM)"].startswith(timed)


def test_the_evaluation_runs_on_the_runs_device_unless_evaluate_device_is_cpu(finished):
    """evaluate.device: run (the default) gives eval_truth, evaluate_voxels and caches the run's device and has
    sample_shadows score its SIRENs there; `cpu` keeps one truth, one sampler curve and one score of each SIREN on
    every machine: those rules get --device cpu and sample_shadows (on the run's device) scores on the CPU, which
    changes their bytes on a GPU, so all four rerun."""
    targets = {"eval-truth": "results/nucleon/eval_truth.zarr", "evaluate-voxels": "results/nucleon/voxel_metrics.json",
               " caches --weights": "results/nucleon/caches.json"}
    on_cpu = {**TINY, "evaluate": {**TINY["evaluate"], "device": "cpu"}}
    assert {"eval_truth", "sample_shadows", "evaluate_voxels", "caches"} <= set(
        planned(snakemake(finished, "-n", config=on_cpu)))
    generated = "results/nucleon/generated.zarr"
    default = snakemake(finished, "-n", "-p", "-f", *targets.values(), generated).stdout.splitlines()
    shell = snakemake(finished, "-n", "-p", "-f", *targets.values(), generated, config=on_cpu).stdout.splitlines()
    for command in targets:
        assert "--device cpu" not in next(ln for ln in default if command in ln), command
        assert "--device cpu" in next(ln for ln in shell if command in ln), command
    assert "--score-on run" in next(ln for ln in default if "sample-shadows" in ln)
    assert "--score-on" not in next(ln for ln in shell if "sample-shadows" in ln)
    # the stored-SIREN caches' rules score their SIRENs the same way: cache: auto's choice, a codec's store, the blend
    for cache, target, commands in (("auto", "results/nucleon/cache_choice.json", ["choose-cache"]),
                                    ("fp16", "results/nucleon/generated.zarr", ["encode-cache", "blend-shadows"])):
        config = {**TINY, "cache": cache}
        lines = {device: snakemake(finished, "-n", "-p", "--forceall", target, config=cfg).stdout.splitlines()
                 for device, cfg in (("run", config), ("cpu", {**config, "evaluate": on_cpu["evaluate"]}))}
        for command in commands:
            assert "--device cpu" in next(ln for ln in lines["cpu"] if f" {command} " in ln), command
            assert "--device cpu" not in next(ln for ln in lines["run"] if f" {command} " in ln), command


def test_the_halo_is_a_fit_setting_only_where_the_scene_has_seams(finished):
    """fit.halo and fit.rounds change the fits of a scene of several subsets (their params rerun them) and nothing else:
    preoptimize's command never carries it, nor a one-subset scene's fit (no seam), so a run made before it was a
    setting reruns nothing for it. The finished run's subsets fitted the other subset's lights as their halo and
    kept their own (the store: 4 lights, tests above)."""
    import json

    log = (finished / "results/nucleon/logs/fit_siren_0.log").read_text()
    assert "halo ring 1: 2 lights of other subsets fitted with them, not kept" in log
    # fit.rounds: subset 1 fits after subset 0 and holds subset 0's lights in its halo at their stored SIRENs
    log = (finished / "results/nucleon/logs/fit_siren_1.log").read_text()
    assert "of them held at the stored SIRENs of earlier rounds' subsets (fit.rounds): 2" in log
    assert planned(snakemake(finished, "-n", "-R", "results/nucleon/sirens/subset_0.npz"))["fit_siren"] == 2
    no_halo = planned(snakemake(finished, "-n", config={**TINY, "fit": {**TINY["fit"], "halo": 0}}))
    assert no_halo["fit_siren"] == 2 and "preoptimize" not in no_halo

    def fit_settings(config: dict) -> dict[str, dict]:
        shell = snakemake(finished, "-n", "-p", "-f", "results/nucleon/siren_init.pt",
                          "results/nucleon/sirens/subset_0.npz", config=config).stdout
        found = re.findall(r"diffshadow .*?\b(preoptimize|fit-siren)\b.*?--config-json '(\{.*?\})'", shell)
        return {command: json.loads(cfg)["fit"] for command, cfg in found}

    for key in ("halo", "rounds"):
        assert {k: key in v for k, v in fit_settings(TINY).items()} == {"preoptimize": False, "fit-siren": True}
    one = fit_settings({**TINY, "subset_size": 4})
    assert set(one) == {"preoptimize", "fit-siren"} and not any("halo" in v or "rounds" in v for v in one.values())


def test_rerun_one_subset(finished):
    """Forcing one subset plans it alone (-f) or with everything downstream of it (-R); a corrupted subset file
    fails the collection, naming it; rerunning the subset refits it alone, to the same bytes (same seed), and
    collects the store again, leaving the other subset's file untouched and no temporary file behind."""
    sirens = finished / "results/nucleon/sirens"
    before = (sirens / "subset_0.npz").read_bytes(), (sirens / "subset_0.npz").stat().st_mtime_ns
    fitted = (sirens / "subset_1.npz").read_bytes()
    store = open_store(finished / "results/nucleon/weights.zarr").weights.tobytes()
    target = "results/nucleon/sirens/subset_1.npz"
    assert planned(snakemake(finished, "-n", "-f", target)) == {"fit_siren": 1}
    downstream = {"fit_siren": 1, "collect_weights": 1, "train_diffusion": 1, "finetune_render": 1, "fit_correction": 1,
                  "sample_shadows": 1, "evaluate_voxels": 1, "caches": 1, "evaluate_images": 1, "benchmark": 1,
                  "report_figures": 1, "stage_costs": 1, "summary": 1, "all": 1}
    assert planned(snakemake(finished, "-n", "-R", target)) == downstream
    # a subset the scene does not have stops the plan (on a PBS system its job would have queued, then failed)
    none = snakemake(finished, "-n", "-R", "results/nucleon/sirens/subset_2.npz", check=False)
    assert none.returncode != 0 and ("results/nucleon/sirens/subset_2.npz: subset 2 does not exist: 4 lights in "
                                     "subsets of 2 give subsets 0..1") in none.stdout + none.stderr
    assert "Job stats" not in none.stdout + none.stderr
    # a corrupted subset is newer than the store: collecting again fails and names the file
    (sirens / "subset_1.npz").write_bytes(b"garbage")
    proc = snakemake(finished, check=False)
    assert proc.returncode != 0 and "subset_1.npz: not a readable subset file" in proc.stdout + proc.stderr
    # up to the store only: the jobs after it take a minute here and are the same jobs as in the first run
    rerun = snakemake(finished, "results/nucleon/weights.zarr", "-R", target)
    assert re.findall(r"^(?:local)?rule (\w+):", rerun.stdout + rerun.stderr, re.M) == ["fit_siren", "collect_weights"]
    assert (sirens / "subset_1.npz").read_bytes() == fitted
    assert open_store(finished / "results/nucleon/weights.zarr").weights.tobytes() == store
    assert ((sirens / "subset_0.npz").read_bytes(), (sirens / "subset_0.npz").stat().st_mtime_ns) == before
    assert not list(sirens.glob(".*"))  # no temporary or half-written files left behind
    # the store is the same bytes, so the later outputs still hold: marked up to date for the tests after this one
    snakemake(finished, "--touch")
    assert planned(snakemake(finished, "-n")) == {}


def test_a_fit_below_the_psnr_floor_is_refused_and_not_stored(finished, tmp_path):
    import json
    res = finished / "results/nucleon"
    cfg = {"siren": TINY["siren"], "subset_size": TINY["subset_size"],
           "fit": {**TINY["fit"], "min_psnr": 99.0}}  # a floor no fit reaches
    out = tmp_path / "subset_0.npz"
    proc = subprocess.run([sys.executable, "-m", "diffshadow.cli", "fit-siren", "--volume", str(res / "volume.zarr"),
                           "--lights", str(res / "lights.json"), "--init", str(res / "siren_init.pt"), "--subset", "0",
                           "--config-json", json.dumps(cfg), "--threads", "1", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    named = re.search(r"diffshadow fit-siren: error: fit_siren subset 0 \(.*volume.zarr\): held-out PSNR below "
                      r"fit.min_psnr = 99.0 dB \(light (\d+): [\d.]+ dB, light (\d+): [\d.]+ dB\)", proc.stderr)
    assert named, proc.stderr
    train = read_lights(res / "lights.json")["train"]  # the lights of subset 0's patch, by index
    assert [int(i) for i in named.groups()] == subset_indices(train, TINY["subset_size"], 0)
    assert "Traceback" not in proc.stderr and not out.exists() and not list(tmp_path.iterdir())


PARSE_ONLY = """
import runpy, sys
sys.argv = ["snakemake", *sys.argv[1:]]
try:
    runpy.run_module("snakemake", run_name="__main__", alter_sys=True)
except SystemExit as done:
    assert not done.code, done.code
print("torch imported:", "torch" in sys.modules)
"""


def test_parsing_the_workflow_does_not_import_torch(tmp_path):
    """Snakemake parses the Snakefile in its own process and, on PBS, once more in every job before the job's
    command starts: importing PyTorch there cost 2.5 s a parse here (4.7 against 2.2 s for a dry run)."""
    proc = snakemake(tmp_path, "-n", "-q", runner=("-c", PARSE_ONLY))
    assert "torch imported: False" in proc.stdout, proc.stdout[-2000:]


# the longest chain of the default run: each stage's training, then the cache's sampling
CHAIN = ("preoptimize", "fit_siren", "collect_weights", "train_diffusion", "finetune_render", "fit_correction",
         "sample_shadows")


def rule_priorities() -> dict[str, int]:
    """Each rule's `priority:` in the Snakefile and workflow/ (0 where it sets none, as Snakemake has it)."""
    found: dict[str, int] = {}
    for path in [REPO / "Snakefile", *sorted((REPO / "workflow").rglob("*.smk"))]:
        rule = None
        for line in path.read_text().splitlines():
            if m := re.match(r"rule (\w+):", line):
                rule = m[1]
                found[rule] = 0
            elif rule and (m := re.match(r"\s+priority:\s*(\d+)", line)):
                found[rule] = int(m[1])
    return found


def test_the_longest_chain_outranks_every_side_job():
    """Where the side jobs are quicker than the chain (on a GPU), a freed core goes to the chain's next job: on
    an H200 finetune_render waited 5.9 s for train_data_inr, a side job it does not read, when both had none."""
    priorities = rule_priorities()
    assert set(CHAIN) <= set(priorities), sorted(set(CHAIN) - set(priorities))
    lowest = min(priorities[r] for r in CHAIN)
    assert {r: p for r, p in priorities.items() if r not in CHAIN and p >= lowest} == {}


def test_config_typo_fails_before_any_job(tmp_path):
    bad = {**TINY, "fit": {**TINY["fit"], "stpes": 3}}
    proc = snakemake(tmp_path, "-n", config=bad, check=False)
    assert proc.returncode != 0 and "stpes" in proc.stdout + proc.stderr
    wrong_type = {**TINY, "subset_size": "two"}
    proc = snakemake(tmp_path, "-n", config=wrong_type, check=False)
    assert proc.returncode != 0 and "'two' is not of type 'integer'" in proc.stdout + proc.stderr
    # Snakemake reads `--config section='{key: value}'` values as strings: they still mean numbers
    proc = snakemake(tmp_path, "-n", "-p", "--config", "finetune={epochs: 3}", "lights={unseen: 2}")
    assert '"epochs": 3,' in proc.stdout + proc.stderr
    # a scene that has no file is named when the workflow is parsed, not from inside a rule's input function
    proc = snakemake(tmp_path, "-n", config={**TINY, "scenes": ["nosuch"]}, check=False)
    assert proc.returncode != 0 and "scene 'nosuch': no file" in proc.stdout + proc.stderr
    assert "InputFunctionException" not in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


def fit_subset_command(finished: Path, tmp_path: Path, checkpoint_every: int) -> tuple[list[str], Path, Path]:
    """`diffshadow fit-siren` of the finished run's subset 1 for 3,000 steps into tmp_path, after the preoptimize it
    needs, beside a copy of subset 0's file (fit.rounds: it holds subset 0's SIRENs); the command, its output and
    its checkpoint."""
    import json
    import shutil

    cfg = json.dumps({"siren": TINY["siren"], "subset_size": 2,
                      "fit": {**TINY["fit"], "steps": 3000, "checkpoint_every": checkpoint_every}})
    res = finished / "results/nucleon"
    out = tmp_path / "subset_1.npz"
    shutil.copy(res / "sirens/subset_0.npz", tmp_path / "subset_0.npz")
    exe = str(installed("diffshadow"))
    # an init made for these settings (preoptimize records the fit steps its size was chosen for)
    pre = json.dumps({**json.loads(cfg), "preoptimize": TINY["preoptimize"]})
    init = tmp_path / "siren_init.pt"
    subprocess.run([exe, "preoptimize", "--volume", str(res / "volume.zarr"), "--lights", str(res / "lights.json"),
                    "--config-json", pre, "--out", str(init)], check=True, capture_output=True)
    cmd = [exe, "fit-siren", "--volume", str(res / "volume.zarr"),
           "--lights", str(res / "lights.json"), "--init", str(init), "--subset", "1",
           "--config-json", cfg, "--threads", "1", "--out", str(out)]
    return cmd, out, tmp_path / "subset_1.npz.ckpt"


def test_killed_fit_leaves_no_output_and_resumes(finished, tmp_path):
    import signal
    import time

    cmd, out, ckpt = fit_subset_command(finished, tmp_path, checkpoint_every=10)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert ckpt.exists(), "no checkpoint was written before the kill"
    assert not out.exists()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "resuming from" in done.stdout and out.exists() and not ckpt.exists()


def test_every_rule_ends_its_command_in_the_log_that_survives_a_stop():
    """One ending for every rule's shell (hpc.JOB_LOG), not a bare `tee`, which the signal that stops a job ends."""
    rules = [p.read_text() for p in sorted((REPO / "workflow/rules").glob("*.smk"))]
    shells = sum(text.count("    shell:") for text in rules)
    assert shells >= 20 and sum(text.count("+ _JOB_LOG") for text in rules) == shells
    assert not any("tee {log}" in text for text in rules)


def test_a_job_killed_by_sigkill_is_named_with_its_log_and_the_keys_that_size_its_memory(tmp_path):
    """As Linux's out-of-memory killer ends a job: SIGKILL, and the job's log ends without a word. The workflow's
    `onerror` says which job, where its log is, and which keys to lower if memory was the cause."""
    import signal
    import time

    steps = 99991  # a preoptimize long enough to be killed, its command told apart from any other test's by this
    cmd, env = snakemake_command(tmp_path, "results/nucleon/siren_init.pt",
                                 config={**TINY, "preoptimize": {"steps": steps, "lr": 1.0e-3}})
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log = tmp_path / "results/nucleon/logs/preoptimize.log"
    deadline = time.time() + 300
    while "step " not in (log.read_text() if log.exists() else "") and time.time() < deadline:
        time.sleep(0.1)
    pattern = f"preoptimize .*\"steps\": {steps}"  # the job's shell and its command, as the OOM killer takes both
    try:
        job = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True)
        pids = [int(p) for p in job.stdout.split() if int(p) != proc.pid]
        assert pids, f"no preoptimize job to kill: {log.read_text() if log.exists() else 'no log'}"
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=120)
    finally:  # nothing of it left running, whatever failed
        subprocess.run(["pkill", "-KILL", "-f", pattern])
        proc.kill()
    assert proc.returncode != 0
    said = [line for line in out.splitlines() if "killed by SIGKILL" in line]
    assert said == [
        f"preoptimize was killed by SIGKILL (exit 137; its log, results/nucleon/logs/preoptimize.log, ends without "
        f"a word): most often by the out-of-memory killer (`journalctl -k | grep -i oom` or `dmesg` names it), and "
        f"then lower {config_memory_keys('preoptimize')}, or run it where there is more memory; else by a "
        f"scheduler. A rerun starts it again (it keeps no checkpoint)"], out[-3000:]


def test_sigterm_stops_a_fit_at_its_next_step_with_a_checkpoint_and_the_rerun_resumes(finished, tmp_path):
    """As PBS ends a job (walltime, preemption): SIGTERM to every process of the job's shell, the rule's own command
    line (Snakemake's strict bash, the rules' log ending); the fit writes its checkpoint at the step it is in, and
    its last line, saying so, is in the log; the rerun resumes there."""
    import shlex
    import signal
    import time

    from diffshadow.hpc import JOB_LOG

    cmd, out, ckpt = fit_subset_command(finished, tmp_path, checkpoint_every=1000)
    log = tmp_path / "fit.log"
    shell = "set -euo pipefail; " + shlex.join(cmd) + JOB_LOG.format(log=shlex.quote(str(log)))
    proc = subprocess.Popen(["bash", "-c", shell], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.time() + 120
    while "step 300/3000" not in (log.read_text() if log.exists() else "") and time.time() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGTERM)
    proc.wait(timeout=60)  # the shell ends at once (as Snakemake's job does); its pipeline finishes on its own
    while "stopped by" not in log.read_text() and time.time() < deadline + 60:
        time.sleep(0.05)
    step = torch.load(ckpt, weights_only=True)["step"]
    assert 300 <= step < 3000 and step % 1000 != 0 and not out.exists()  # the step it was in, not the last periodic
    assert log.read_text().splitlines()[-1] == (  # the last line, not a traceback on the pipe a dead `tee` left
        f"diffshadow fit-siren: stopped by SIGTERM at step {step}/3000; checkpoint {ckpt} written, and the same "
        f"command run again resumes from it")
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"resuming from {ckpt} at step {step}/3000" in done.stdout and out.exists() and not ckpt.exists()
    # by hand, where the line can be read: SIGINT (Ctrl-C) says where it stopped
    again = tmp_path / "again.npz.ckpt"
    proc = subprocess.Popen([*cmd[:-1], str(tmp_path / "again.npz")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # a terminal's
    while not proc.stdout.readline().startswith("step 300/3000") and proc.poll() is None:
        pass
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 128 + signal.SIGINT
    step = torch.load(again, weights_only=True)["step"]
    assert proc.stderr.read().strip().splitlines()[-1] == (
        f"diffshadow fit-siren: stopped by SIGINT at step {step}/3000; checkpoint {again} written, and the same "
        f"command run again resumes from it")


def finetune_ddp_command(finished: Path, tmp_path: Path, **finetune) -> tuple[list[str], Path, Path]:
    """`diffshadow torchrun` of 2 finetune-render ranks on the finished run's files, with these `finetune` settings,
    into tmp_path; the command, its output and its checkpoint."""
    import json

    res = finished / "results/nucleon"
    cfg = json.dumps({"finetune": {**TINY["finetune"], "timeout_s": 20, **finetune}})
    out = tmp_path / "diffusion.ckpt"
    cmd = [sys.executable, "-m", "diffshadow.cli", "torchrun", "--standalone", "--nproc_per_node=2", "-m",
           "diffshadow.cli", "finetune-render", "--checkpoint", str(res / "diffusion_geometry.ckpt"),
           "--weights", str(res / "weights.zarr"), "--points", str(res / "geometry_points.zarr"),
           "--targets", str(res / "targets.zarr"), "--config-json", cfg, "--threads", "1",
           "--metrics", str(tmp_path / "ft.json"), "--out", str(out)]
    return cmd, out, tmp_path / "diffusion.ckpt.part"


def test_sigterm_to_a_ddp_job_stops_its_ranks_at_one_step_and_the_rerun_resumes(finished, tmp_path):
    """PBS signals every process of the job: the launcher (which passes SIGTERM on to its ranks) and both ranks.
    The ranks agree on the step to stop at, rank 0 writes the checkpoint there, and the rerun resumes from it."""
    import signal

    # 2 steps an epoch (a light a rank): the stop may come inside an epoch or at its end
    cmd, out, part = finetune_ddp_command(finished, tmp_path, epochs=200, checkpoint_every=50, batch_size=2)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    lines = []
    while proc.poll() is None:
        lines.append(proc.stdout.readline())
        if lines[-1].startswith("epoch 20/200"):
            break
    os.killpg(proc.pid, signal.SIGTERM)
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    text = "".join(lines) + proc.stdout.read()
    saved = torch.load(part, weights_only=False)
    epoch, inside = saved["finetune_epoch"], (saved.get("within_epoch") or {}).get("batches")
    assert 20 <= epoch < 200 and (epoch % 50 != 0 or inside) and not out.exists(), text[-2000:]
    where = f"at step {inside} of epoch {epoch + 1}/200" if inside else f"at epoch {epoch}/200"
    said = [line for line in text.splitlines() if "stopped by SIGTERM" in line]
    assert said == [f"diffshadow finetune-render: stopped by SIGTERM {where}; checkpoint {part} "
                    f"written, and the same command run again resumes from it"], text[-2000:]
    assert text.strip().splitlines()[-1] == "diffshadow torchrun: ended by SIGTERM, and its ranks with it"
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    resumed = f"at epoch {epoch}/200" + (f", step {inside} of epoch {epoch + 1}" if inside else "")
    assert resumed in done.stdout + done.stderr and out.exists() and not part.exists()
    print(f"stopped {where}; resumed {resumed}")


def test_finetune_ran_under_ddp(finished):
    import json
    metrics = json.loads((finished / "results/nucleon/finetune_metrics.json").read_text())
    # finetune.nproc is 2: two gloo processes on a CPU, one NCCL process per GPU up to 2 on a GPU machine
    world, where = (min(2, torch.cuda.device_count()), "cuda") if CUDA else (2, "cpu")
    assert metrics["processes"] == world and metrics["lights"] == 4
    for key in ("image_psnr_geometry_only", "image_psnr_finetuned"):
        assert np.isfinite(metrics[key]["mean"])
    log = (finished / "results/nucleon/logs/finetune_render.log").read_text()
    assert f"{world} process(es) on {where}, global batch 4" in log


def test_killed_rank_fails_the_job_and_rerun_resumes(finished, tmp_path):
    import signal
    import time

    # 120 epochs of 0.055 s here: ~6 s still to go when the first checkpoint appears and the kill comes
    cmd, out, part = finetune_ddp_command(finished, tmp_path, epochs=120)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 120
    while not part.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert part.exists(), "no checkpoint before the kill"
    ranks = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
    assert len(ranks) == 2, ranks
    t_kill = time.time()
    os.kill(int(ranks[1]), signal.SIGKILL)
    proc.wait(timeout=90)  # torchrun notices the dead rank and stops the other: no hang
    assert proc.returncode == 128 + signal.SIGKILL and time.time() - t_kill < 60
    # the workflow's launcher ends the log with the rank that failed first, not torchrun's traceback
    assert proc.stdout.read().strip().splitlines()[-1].startswith("diffshadow torchrun: rank 1 was ended by SIGKILL")
    print(f"killed rank 1: torchrun exited {proc.returncode} after {time.time() - t_kill:.1f} s")
    assert not out.exists() and part.exists()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "resuming from" in done.stdout + done.stderr and out.exists() and not part.exists()


def test_report_embeds_every_figure(finished):
    snakemake(finished, "--report", "report.html")
    html = (finished / "report.html").read_text()
    figures = ["config.yaml", "siren_psnr.png", "generated_psnr.png", "generated_psnr.csv", "image_grid.png",
               "ddim_curve.png", "shadow_curve.png", "storage.png", "bench.png"]
    for name in figures:
        assert name in html, f"{name} is not in the report"
    for name in figures[:-1]:
        assert (finished / "results/nucleon/report" / name).stat().st_size > 100
    # the image grid's caption names the run's reference (render.reference: exact), not the shadow grid's
    assert "the shadow marched from every sample through it" in html and "marched shadow grid" not in html


def test_report_front_page_has_the_runs_numbers(finished):
    import json
    snakemake(finished, "--report", "report.html")
    page = (finished / "report.html").read_text()
    res = finished / "results/nucleon"
    voxel = json.loads((res / "voxel_metrics.json").read_text())
    tables = (res / "report/summary.html").read_text()
    for value in (voxel["seen"]["generated_psnr_median"], voxel["unseen"]["blend_psnr_median"]):
        # the landing page (RST included into the report) and the summary tables both state the run's values
        assert f"{value:.2f} dB" in page and f"{value:.2f}" in tables
    assert "Scene nucleon" in page and "summary.html" in page
    assert f"{voxel['diffusion_model']['parameters']:,} parameters" in page
    # the further test lights' rows: the cache's answer, the model alone and the blend at their medians
    wide = voxel["wide"]
    for key in ("generated_psnr_median", "model_alone_psnr_median", "weight_blend_psnr_median"):
        assert "<td>further (16)</td><td>" in tables and f"{wide[key]:.2f}" in tables
    # the pool lights' row: their count in the words, the PSNR columns empty (the count once sat in "box")
    pool = voxel["unseen"]["pool_lights"]
    row = f"<td>unseen</td><td>{pool} pool lights (exact shadows, no fitted SIREN) in training</td><td></td><td></td>"
    assert row in tables
    assert f"{voxel['diffusion_model']['epochs']} epochs: {voxel['diffusion_model']['stopped']}" in page
    assert ("trained with bfloat16 products" in page) is (voxel["diffusion_model"]["precision"] == "bfloat16")
    costs = {line.split("\t")[0]: line.split("\t") for line in (res / "stage_costs.tsv").read_text().splitlines()}
    assert f"{float(costs['elapsed (a job running)'][2]) / 60:.1f} min elapsed" in page  # the run's own wall time
    # two unseen lights: a median is their mean, so the median change is exactly the change of the medians (of the
    # model's own SIRENs: the run's cache mixes them with the stored ones' blend)
    assert "before fine-tuning" in tables and voxel["unseen"]["finetune_change_median_db"] == pytest.approx(
        voxel["unseen"]["model_alone_psnr_median"] - voxel["unseen"]["geometry_only_psnr_median"], abs=1e-9)
    assert f"{voxel['mix']['model_share']:g} x the diffusion model's SIREN" in page
    for title in ("Shadow INRs", "Sampling", "Rendering-loss fine-tuning", "Images", "Renderer", "SIREN sizes chosen",
                  "Storage", "Stage costs"):
        assert f"<h2>{title}" in tables, title


def test_stage_costs_come_from_snakemakes_benchmarks(finished):
    res = finished / "results/nucleon"
    rules = {p.stem for p in (res / "benchmarks").glob("*.tsv")}
    assert {"fit_siren_0", "fit_siren_1", "finetune_render", "benchmark", "report_figures"} <= rules
    lines = (res / "stage_costs.tsv").read_text().splitlines()
    assert lines[0].split("\t") == ["stage", "jobs", "wall_s", "cpu_s", "max_rss_mib", "import_s", "device_s",
                                    "compile_s", "io_s", "compute_s", "launch_s", "critical_s"]
    rows = {line.split("\t")[0]: line.split("\t") for line in lines[1:]}
    assert rows["fit_siren"][1] == "2" and "fit_siren_0" not in rows
    # every job recorded its phases; they add up to its wall time (launch_s: the rest, outside its process), up to
    # the skew of two clocks: Snakemake's benchmark starts and stops its own (it polls), the process reads its
    # start from /proc; a loaded machine put the process 0.2 s over its job's wall once (launch_s is then 0)
    for stage, row in rows.items():
        if stage.startswith("elapsed"):
            continue
        phases = [float(x) for x in row[5:11]]
        assert sum(phases) == pytest.approx(float(row[2]), abs=0.5 * int(row[1])), stage
    assert float(rows["train_diffusion"][5]) > 0 and float(rows["train_diffusion"][9]) > 0  # imports, compute
    assert float(rows["presample"][8]) > 0  # its store written
    assert int(rows["total (sum over jobs)"][1]) == len(rules)
    # the run's elapsed time: no shorter than its longest job, no longer than all jobs one after another
    longest = max(float(r[2]) for r in rows.values() if r[1] == "1")
    elapsed = float(rows["elapsed (a job running)"][2])
    assert longest <= elapsed <= float(rows["total (sum over jobs)"][2])
    # the critical path's jobs follow one another (file times: each may start up to CHAIN_SLACK_S before the end it
    # waited on) and span the run; the little between them is Snakemake's own
    on_path, span = float(rows["total (sum over jobs)"][11]), float(rows["elapsed (a job running)"][11])
    assert sum(float(r[11]) for s, r in rows.items() if not s.startswith(("total", "elapsed"))) == pytest.approx(
        on_path, abs=0.1 * len(rows))
    assert on_path == pytest.approx(span, rel=0.1) and span == pytest.approx(elapsed, rel=0.1)


def test_cache_blend_skips_stage_two(finished, tmp_path):
    """`cache: blend`: no diffusion model; a finished run switched to it redoes only what comes after the cache
    (stage 1 and the side jobs stand); the generated store holds every training light's stored SIREN and every
    unseen light's weight blend of its nearest, the same SIRENs evaluate_voxels scores as its weight-blend
    baseline, so their PSNRs agree; the viewer and `render --blend` make a new direction's SIREN the same way."""
    import json
    import shutil

    from diffshadow.store import BlendSampler

    # a blend k other than the package's 4: the viewer and `render --blend` must take the run's
    # the plain blend (correction.steps 0: no correction job; the corrected one below)
    blend = {**TINY, "cache": "blend", "evaluate": {**TINY["evaluate"], "blend_k": 3},
             "correction": {**TINY["correction"], "steps": 0}}
    (tmp_path / "fresh").mkdir()
    fresh = planned(snakemake(tmp_path / "fresh", "-n", config=blend))
    assert {"fit_siren", "eval_truth", "sample_shadows"} <= set(fresh), fresh
    assert not {"presample", "train_diffusion", "render_targets", "finetune_render"} & set(fresh), fresh
    for folder in ("results", ".snakemake"):  # the finished run, its file times and Snakemake's records
        shutil.copytree(finished / folder, tmp_path / folder, symlinks=True)
    after = {"sample_shadows", "evaluate_voxels", "caches", "evaluate_images", "report_figures", "benchmark",
             "stage_costs", "summary", "all"}
    assert set(planned(snakemake(tmp_path, "-n", config=blend))) == after
    snakemake(tmp_path, config=blend)
    res = tmp_path / "results/nucleon"
    stage1, generated = open_store(res / "weights.zarr"), open_store(res / "generated.zarr")
    seen = generated.seen
    assert np.array_equal(generated.weights[seen], stage1.weights)
    assert generated.config["blend_k"] == 3
    blend = BlendSampler(stage1, 3, generated.config["blend_weights"])
    for light, w in zip(generated.lights[~seen], generated.weights[~seen], strict=True):
        assert np.array_equal(w, blend(light))
    metrics = json.loads((res / "voxel_metrics.json").read_text())
    assert metrics["cache"] == "blend" and metrics["storage_bytes"]["model"] == 0 and "sampling" not in metrics
    unseen = metrics["unseen"]
    assert unseen["generated_psnr_median"] == pytest.approx(unseen["weight_blend_psnr_median"], abs=1e-3)
    # the further test lights without a model: the blend alone, on the lights the diffusion run drew
    wide, drawn = metrics["wide"], json.loads((finished / "results/nucleon/voxel_metrics.json").read_text())["wide"]
    assert (wide["lights"], wide["points"], wide["blend_k"]) == (drawn["lights"], drawn["points"], 3)
    assert wide["generated_psnr_median"] == wide["weight_blend_psnr_median"] and "model_alone_psnr_median" not in wide
    assert f"<td>further ({wide['lights']})</td><td>blended (cache: blend)</td>" in \
        (res / "report/summary.html").read_text()
    assert metrics["seen"]["generated_psnr_median"] == pytest.approx(metrics["seen"]["stage1_psnr_median"], abs=1e-3)
    summary = (res / "report/summary.html").read_text()
    assert "cache: blend" in summary
    assert "fine-tuning" not in summary  # the diffusion run's finetune_metrics.json is still there, and not read
    kinds = {r["kind"] for r in json.loads((res / "caches.json").read_text())["caches"]}
    assert kinds == {"stored", "codec", "grids"}  # no model to weigh
    costs = (res / "stage_costs.tsv").read_text()
    assert "sample_shadows" in costs and "train_diffusion" not in costs

    from diffshadow.render import Camera
    from diffshadow.viewer.scene import ViewerScene

    view = ViewerScene.from_results(res, torch.device("cpu"))
    new = np.array([0.3, 0.2, 0.93])
    weights, info = view.shadow_weights(new)
    assert info.kind == "new" and np.array_equal(weights.numpy(), blend(new))
    cam = Camera.orbit(view.scene.volume.extent, azimuth=30.0, elevation=25.0, size=16)
    command = view.render_command("inr", cam, new, step=0.5, out=str(tmp_path / "x.png"))
    assert f"--blend {res / 'weights.zarr'} --blend-weights triangle --blend-k 3" in command
    out = subprocess.run([str(installed("diffshadow")), *command.split()[1:]], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0 and (tmp_path / "x.png").is_file(), out.stderr[-2000:]


def test_cache_blend_with_the_correction_blends_the_corrected_sirens(finished, tmp_path):
    """`cache: blend` with the blend's correction (the finished run's correction.pt): each training light keeps its
    stored SIREN, each unseen light gets its corrected blend, as `render --blend --correction` and the viewer make a
    new direction's; the store's config names the correction, which voxel_metrics.json then says."""
    from diffshadow.correction import load_correction
    from diffshadow.stages.stage2 import blend_shadows
    from diffshadow.store import BlendSampler

    res = finished / "results/nucleon"
    out = tmp_path / "generated.zarr"
    blend_shadows(res / "weights.zarr", res / "eval_truth.zarr", res / "lights.json", out, blend_k=4,
                  weighting="triangle", correction_path=res / "correction.pt")
    stage1, generated = open_store(res / "weights.zarr"), open_store(out)
    assert np.array_equal(generated.weights[generated.seen], stage1.weights)
    fixed = BlendSampler(stage1, 4, "triangle", load_correction(res / "correction.pt", stage1.lights))
    plain = BlendSampler(stage1, 4, "triangle")
    unseen = generated.lights[~generated.seen]
    assert np.array_equal(generated.weights[~generated.seen], fixed.many(unseen))
    assert not np.array_equal(generated.weights[~generated.seen], plain.many(unseen))
    assert generated.config["correction"]["path"] == str(res / "correction.pt")
    with pytest.raises(ValueError, match="fitted for other training lights"):
        blend_shadows(res / "weights.zarr", res / "eval_truth.zarr", res / "lights.json", tmp_path / "x.zarr",
                      blend_k=4, weighting="triangle", correction_path=_other_lights_correction(res, tmp_path))


def _other_lights_correction(res: Path, tmp_path: Path) -> Path:
    """The finished run's correction.pt with one training light moved: a file made for other stored SIRENs."""
    state = torch.load(res / "correction.pt", weights_only=False)
    state["train_lights"][0] = [0.0, 1.0, 0.0]
    path = tmp_path / "other.pt"
    torch.save(state, path)
    return path


def test_cache_auto_plans_stage_two_only_when_no_stored_cache_reaches_the_target(finished):
    """`cache: auto` decides after stage 1 (the checkpoint choose_cache): with a target no stored-SIREN cache
    reaches, the DAG holds the diffusion model's jobs; with one the smallest codec reaches, a dry run plans the
    codec's cache and no stage-2 job at all. Stage 1 itself is not redone either way."""
    import json

    stage2 = {"presample", "train_diffusion", "render_targets", "finetune_render"}
    for target, expected in ((1000.0, "diffusion"), (-1000.0, "fp16")):
        cfg = {**TINY, "cache": "auto", "cache_auto": {"target_psnr": target, "candidates": ["blend", "fp16"]}}
        if expected == "diffusion":  # a finished run switched to auto decides too (rule all asks for the choice)
            assert planned(snakemake(finished, "-n", config=cfg))["choose_cache"] == 1
        snakemake(finished, "results/nucleon/cache_choice.json", config=cfg)
        choice = json.loads((finished / "results/nucleon/cache_choice.json").read_text())
        assert choice["choice"] == expected and [r["cache"] for r in choice["candidates"]] == ["blend", "fp16"]
        dag = snakemake(finished, "--dag", config=cfg).stdout
        plan = planned(snakemake(finished, "-n", config=cfg))
        assert not {"fit_siren", "preoptimize", "eval_truth"} & set(plan)
        if expected == "diffusion":
            assert all(f"label = \"{r}\"" in dag for r in ("train_diffusion", "finetune_render"))
            assert "encode_cache" not in dag
        else:
            assert not any(f"label = \"{r}\"" in dag for r in stage2) and not stage2 & set(plan)
            assert plan["encode_cache"] == 1 and plan["sample_shadows"] == 1
            # the further test lights' answer blends the codec's decoded store, not stage 1's fp32 one
            commands = snakemake(finished, "-n", "-p", "results/nucleon/voxel_metrics.json", config=cfg).stdout
            assert "--cache-weights results/nucleon/cache.zarr" in commands, commands[-3000:]
