import os
import platform
from pathlib import Path

import numpy as np
import pytest
from conftest import imported_modules

from diffshadow.cli import main

REPO = Path(__file__).resolve().parents[1]


def test_install_profiles_honours_xdg_and_refuses_a_different_profile(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    main(["install-profiles", "--source", str(REPO / "profiles")])
    link = tmp_path / "cfg" / "snakemake" / "local"
    assert link.is_symlink() and (link / "config.yaml").read_text() == (REPO / "profiles/local/config.yaml").read_text()
    main(["install-profiles", "--source", str(REPO / "profiles")])  # again: nothing to do, no error
    other = tmp_path / "other" / "snakemake" / "local"
    other.mkdir(parents=True)
    (other / "config.yaml").write_text("cores: 64\n")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "other"))
    with pytest.raises(SystemExit, match="exists and differs from .*local; remove it or pass --force"):
        main(["install-profiles", "--source", str(REPO / "profiles")])
    assert (other / "config.yaml").read_text() == "cores: 64\n"


def test_install_profiles_replaces_a_link_to_a_deleted_clone_and_skips_workflow_profiles(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    root = tmp_path / "cfg" / "snakemake"
    root.mkdir(parents=True)
    (root / "local").symlink_to(tmp_path / "deleted_clone" / "profiles" / "local", target_is_directory=True)
    main(["install-profiles", "--source", str(REPO / "profiles")])
    assert (root / "local").resolve() == (REPO / "profiles" / "local").resolve()
    assert (root / "polaris").is_symlink()
    # profiles/paper only sets per-rule resources: used by path with --workflow-profile, not installed by name
    assert not (root / "paper").exists() and (REPO / "profiles" / "paper" / "config.yaml").is_file()


def test_bad_input_is_one_line_without_traceback(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["prepare-volume", "--config-json", '{"volume": "missing.raw", "transfer_function": '
              '{"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 1}}',
              "--out", str(tmp_path / "v.zarr")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "missing.raw: no such file" in err
    assert not (tmp_path / "v.zarr").exists()


def test_a_libraries_error_says_where_diffshadow_called_it(tmp_path, capsys, monkeypatch):
    """A ValueError from numpy or torch, not from a check of diffshadow's, is still one line, and says so: where in
    the package the library was called, to report (numpy's bare "kth(=3) out of bounds (3)" once looked like the
    user's mistake). A check of diffshadow's own says nothing more."""
    from diffshadow.stages import stage1

    monkeypatch.setattr(stage1, "make_light_sets", lambda *a, **k: np.argpartition(np.zeros((2, 3)), 3, axis=1))
    argv = ["lights", "--sphere", "40", "--count", "4", "--unseen", "2", "--center", "0", "0", "1",
            "--out", str(tmp_path / "l.json")]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.strip().count("\n") == 0, err
    assert err.startswith("diffshadow lights: error: kth(=3) out of bounds (3) (raised inside numpy, called at "
                          "diffshadow/stages/stage1.py:"), err
    assert "please report it" in err
    monkeypatch.undo()
    with pytest.raises(SystemExit):
        main([*argv[:-6], "--center", "0", "0", "0", *argv[-2:]])
    assert capsys.readouterr().err == "diffshadow lights: error: center: must be non-zero, got [0.0, 0.0, 0.0]\n"


CUDA_OOM = ("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 39.39 GiB of which 1.20 GiB "
            "is free. Including non-PyTorch memory, this process has 38.17 GiB memory in use. Of the allocated memory "
            "36.00 GiB is allocated by PyTorch. If reserved but unallocated memory is large try setting "
            "PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True to avoid fragmentation.")


def _cpu_allocator():  # for real: the CPU allocator refuses at once
    import torch

    torch.empty(2**62, dtype=torch.uint8)


def _numpy():  # for real
    np.empty(2**62, dtype=np.uint8)


def _cuda():  # as CUDA words it
    import torch

    raise torch.cuda.OutOfMemoryError(CUDA_OOM)


def _not_memory():
    raise RuntimeError("mat1 and mat2 shapes cannot be multiplied")


@pytest.mark.parametrize("allocate, reason", [
    (_cpu_allocator, "DefaultCPUAllocator: can't allocate memory: you tried to allocate 4611686018427387904 bytes."),
    (_numpy, "Unable to allocate 4.00 EiB for an array"),
    (_cuda, "CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 39.39 GiB of which 1.20 "
     "GiB is free.);"),
])
def test_running_out_of_memory_is_one_line_naming_the_keys_that_size_the_stage(tmp_path, capsys, monkeypatch,
                                                                                allocate, reason):
    from diffshadow.stages import stage2

    monkeypatch.setattr(stage2, "train_diffusion", lambda *a, **k: allocate())
    argv = ["train-diffusion", "--weights", "w.zarr", "--points", "p.zarr", "--config-json", '{"diffusion": {}}',
            "--out", str(tmp_path / "d.ckpt")]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 1 and err.strip().count("\n") == 0, err
    assert err.startswith("diffshadow train-diffusion: error: out of memory (") and reason in err, err
    assert "lower diffusion.batch_size or diffusion.geometry_points" in err and "expandable_segments" not in err
    # any other RuntimeError keeps its traceback (an unchecked case to report, not the user's size)
    monkeypatch.setattr(stage2, "train_diffusion", lambda *a, **k: _not_memory())
    with pytest.raises(RuntimeError, match="mat1 and mat2"):
        main(argv)


def test_an_interrupted_command_says_so_in_one_line(tmp_path, capsys, monkeypatch):
    """Ctrl-C on a command typed by hand: one line and the shell's status for SIGINT, not a traceback from wherever
    the step was."""
    from diffshadow.stages import stage2

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(stage2, "train_diffusion", interrupted)
    with pytest.raises(SystemExit) as exit_info:
        main(["train-diffusion", "--weights", "w.zarr", "--points", "p.zarr", "--config-json", '{"diffusion": {}}',
              "--out", str(tmp_path / "d.ckpt")])
    assert exit_info.value.code == 130
    assert capsys.readouterr().err == ("diffshadow train-diffusion: interrupted; no earlier output was replaced, and "
                                       "run again it resumes from its last checkpoint\n")
    monkeypatch.setattr(stage2, "presample", interrupted)  # a stage that keeps no checkpoint says so
    with pytest.raises(SystemExit):
        main(["presample", "--volume", "v.zarr", "--lights", "l.json", "--config-json", '{"diffusion": {}}',
              "--out", str(tmp_path / "p.zarr")])
    assert capsys.readouterr().err.endswith("and run again it starts from the beginning (it keeps no checkpoint)\n")


def test_a_ddp_process_whose_peer_stopped_says_so_in_one_line(tmp_path):
    """Under torchrun, a rank waiting in a collective when another process stops gets the backend's error (gloo's
    "Connection closed by peer" is a plain RuntimeError from inside torch.distributed): one line naming the rank and
    the backend's reason, not ~25 lines of traceback around the failing process's own line. Two real gloo
    processes: rank 0 stops after a first barrier, rank 1 waits at a second. Any other RuntimeError keeps its
    traceback. The rendezvous store is this process's, as under torchrun, where its agent holds it: hosted by rank 0,
    a rank 1 still setting up its process group when rank 0 stopped printed c10d's warning and a C++ stack first
    (1 run in 20)."""
    import socket
    import subprocess
    import sys

    from torch.distributed import TCPStore

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    _store = TCPStore("127.0.0.1", port, world_size=2, is_master=True, wait_for_workers=False)  # held for the ranks
    script = """
import os, sys
import torch, torch.distributed as dist
from diffshadow import cli
from diffshadow.stages import stage2

def stage(*a, **k):
    if sys.argv[1] == "bug":
        return torch.zeros(2) @ torch.zeros(3)
    dist.init_process_group("gloo")
    dist.barrier()  # both ranks set up: rank 1 then waits in a collective, not in the rendezvous
    if dist.get_rank() == 0:
        os._exit(3)  # a process that stops
    dist.barrier()

stage2.finetune_render = stage
cli.main(["finetune-render", "--checkpoint", "g.ckpt", "--weights", "w.zarr", "--points", "p.zarr", "--targets",
          "t.zarr", "--config-json", '{"finetune": {}}', "--metrics", "m.json", "--out", "d.ckpt"])
"""
    env = {**os.environ, "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
           "TORCHELASTIC_USE_AGENT_STORE": "True"}
    ranks = [subprocess.Popen([sys.executable, "-c", script, "peer"], cwd=tmp_path, env={**env, "RANK": str(r)},
                              stderr=subprocess.PIPE, text=True) for r in (0, 1)]
    (_, err0), (_, err1) = (p.communicate(timeout=120) for p in ranks)
    assert ranks[0].returncode == 3, err0
    assert ranks[1].returncode == 1 and err1.count("\n") == 1, err1
    assert err1.startswith("diffshadow finetune-render: rank 1: error: the job's processes lost touch (") and \
        err1.endswith("); a process that stopped first says why\n"), err1
    bug = subprocess.run([sys.executable, "-c", script, "bug"], cwd=tmp_path, env={**env, "RANK": "0"},
                         capture_output=True, text=True, timeout=120)
    assert bug.returncode == 1 and "Traceback" in bug.stderr and "lost touch" not in bug.stderr


def test_a_config_json_without_the_stage_section_is_one_line(tmp_path, capsys):
    # the diffusion section itself instead of {"diffusion": {...}}: named, not a KeyError from deep inside
    with pytest.raises(SystemExit) as exit_info:
        main(["train-diffusion", "--weights", str(tmp_path / "w.zarr"), "--points", str(tmp_path / "p.zarr"),
              "--config-json", '{"epochs": 5}', "--out", str(tmp_path / "d.ckpt")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "--config-json: no 'diffusion' section (it has ['epochs'])" in err


def test_bench_out_takes_a_folder_and_refuses_an_unwritable_name_before_timing(tmp_path, capsys):
    # a folder receives the bench's default file name (it used to end the timings in IsADirectoryError)
    main(["bench", "stages", "--stages", "preoptimize", "--budget", "0", "--max-steps", "2", "--threads", "1",
          "--device", "cpu", "--out", str(tmp_path)])
    assert "preoptimize" in (tmp_path / "bench_stages.json").read_text()
    capsys.readouterr()
    (tmp_path / "notes").write_text("")
    for argv in (["stages", "--stages", "preoptimize"], ["kernels"], ["render"]):
        with pytest.raises(SystemExit) as exit_info:
            main(["bench", *argv, "--out", str(tmp_path / "notes" / "b.json")])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert err.strip().count("\n") == 0 and f"{tmp_path / 'notes'} is a file, not a folder" in err, argv
    with pytest.raises(SystemExit):
        main(["bench", "siren", "--out", str(tmp_path / "notes")])
    assert "expected a folder for the bench's files, found a file" in capsys.readouterr().err
    # a missing volume: named before the analytic case is timed (it was named after)
    with pytest.raises(SystemExit):
        main(["bench", "shadow", "--volumes", str(tmp_path / "none.zarr"), "--out", str(tmp_path / "shadow")])
    said = capsys.readouterr()
    assert f"{tmp_path / 'none.zarr'}: no such file" in said.err and "[bench shadow]" not in said.out
    # sizes that would time nothing: named, not a NaN per step or a ZeroDivisionError
    for argv, message in ((["stages", "--max-steps", "0"], "--max-steps: expected at least 1 timed step, got 0"),
                          (["siren", "--k", "0"], "--k: expected positive integers, got 0"),
                          (["siren", "--widths", "32", "0"], "--widths: expected positive integers, got 32 0")):
        with pytest.raises(SystemExit):
            main(["bench", *argv, "--out", str(tmp_path / "figures")])
        assert message in capsys.readouterr().err, argv


def test_stage_costs_sums_a_fanned_out_rule_and_names_a_bad_file(tmp_path):
    from diffshadow.report import ELAPSED_ROW, stage_costs

    header = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    # the two fits ran side by side from t=100 (ending at 102 and 103); `lights` was rerun a day later
    for name, s, rss, cpu, end in (("fit_siren_0", 2.0, 100, 1.5, 102.0), ("fit_siren_1", 3.0, 120, 2.5, 103.0),
                                   ("lights", 0.5, 50, 0.4, 86_500.0)):
        path = tmp_path / f"{name}.tsv"
        path.write_text(header + f"{s}\t0:00:0{int(s)}\t{rss}\t0\t0\t0\t0\t0\t0\t{cpu}\n")
        os.utime(path, (end, end))
    rows = stage_costs(sorted(tmp_path.glob("*.tsv")), tmp_path / "costs.tsv")
    fit = next(r for r in rows if r["stage"] == "fit_siren")
    assert (fit["jobs"], fit["wall_s"], fit["cpu_s"], fit["max_rss_mib"]) == (2, 5.0, 4.0, 120)
    total, elapsed = rows[-2:]
    assert total["stage"].startswith("total") and total["jobs"] == 3 and total["wall_s"] == 5.5
    # elapsed: the overlapping fits count once (100..103), the rerun its own half second, not the day between
    assert elapsed["stage"] == ELAPSED_ROW and elapsed["wall_s"] == pytest.approx(3.5)
    bad = tmp_path / "broken.tsv"
    bad.write_text("s\n")
    with pytest.raises(ValueError, match="broken.tsv: expected a Snakemake benchmark file"):
        stage_costs([bad], tmp_path / "x.tsv")


def test_a_path_that_cannot_be_read_and_a_port_out_of_range_are_one_line(tmp_path, capsys):
    gone = tmp_path / "gone.tsv"
    (tmp_path / "c.tsv").write_text("")
    for argv, message in ((["stage-costs", "--benchmarks", str(gone), "--out", str(tmp_path / "c.tsv")],
                           f"{gone}: No such file or directory"),
                          (["view", "--scene-config", str(REPO / "config/scenes/nucleon.yaml"), "--port", "99999"],
                           "--port 99999: expected a TCP port, 1 to 65535"),
                          (["stage-costs", "--benchmarks", str(gone), "--out", str(gone), "--timeline", "t.jpg"],
                           "--timeline t.jpg: the figure is written as a PNG"),
                          (["view", "--scene-config", str(REPO / "config/scenes/nucleon.yaml"), "--step", "0"],
                           "--step 0: expected a positive marching step in voxels"),
                          (["stage-costs", "--benchmarks", str(tmp_path / "c.tsv" / "b.tsv"), "--out", str(gone)],
                           f"{tmp_path / 'c.tsv'}: a file, where a folder is needed"),
                          (["install-profiles", "--target", str(tmp_path / "c.tsv")],
                           f"{tmp_path / 'c.tsv'}: a file, where a folder is needed")):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert err.strip().count("\n") == 0 and message in err, argv


@pytest.mark.parametrize("argv", [["stage-costs", "--benchmarks", "{d}/lights.tsv", "--out", "{d}/costs.tsv"],
                                  ["install-profiles", "--source", str(REPO / "profiles"), "--target", "{d}/p"]])
def test_bookkeeping_subcommands_do_not_import_torch(tmp_path, argv):
    # torch's import is ~2 s, most of these jobs' run: stage-costs and summary end every run
    import subprocess
    import sys

    header = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    (tmp_path / "lights.tsv").write_text(header + "0.5\t0:00:00\t50\t0\t0\t0\t0\t0\t0\t0.4\n")
    code = ("import sys; from diffshadow.cli import main; main(sys.argv[1:]); "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    run = subprocess.run([sys.executable, "-c", code, *(a.format(d=tmp_path) for a in argv)], capture_output=True,
                         text=True)
    assert run.returncode == 0, run.stderr


def test_a_rendered_image_says_how_long_so_far_while_it_renders(tmp_path, capsys, monkeypatch):
    """`diffshadow render` gives its frame a ticker (here one that speaks at every march iteration): a naive or gt
    frame of a large view takes minutes on a CPU."""
    import re

    import diffshadow.progress as progress

    monkeypatch.setattr(progress, "TICK_S", 0.0)
    main(["render", "--scene-config", str(REPO / "config/scenes/nucleon.yaml"), "--mode", "gt", "--light", "0", "0",
          "1", "--size", "16", "--out", str(tmp_path / "gt.png")])
    lines = capsys.readouterr().out.splitlines()
    assert sum(bool(re.fullmatch(r"render: gt at 16x16: \d+ s so far", line)) for line in lines) > 1, lines
    assert lines[-1].startswith(f"wrote {tmp_path / 'gt.png'}: gt, 16x16 in ")


def test_render_previews_a_scene_file_and_names_its_typo(tmp_path, capsys):
    from PIL import Image

    scene = (REPO / "config/scenes/nucleon.yaml").read_text()
    good = tmp_path / "mine.yaml"
    good.write_text(scene)
    out = tmp_path / "tf.png"
    main(["render", "--scene-config", str(good), "--mode", "noshadow", "--size", "24", "--out", str(out)])
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape == (24, 24, 3) and len(np.unique(img.reshape(-1, 3), axis=0)) > 1  # the volume shows
    bad = tmp_path / "typo.yaml"
    bad.write_text(scene.replace("transfer_function:", "transfer_functon:"))
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--scene-config", str(bad), "--mode", "noshadow", "--out", str(tmp_path / "x.png")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "typo.yaml" in err and "transfer_functon" in err
    with pytest.raises(SystemExit):  # neither a volume nor a scene file
        main(["render", "--mode", "noshadow", "--out", str(tmp_path / "y.png")])
    assert "give --volume" in capsys.readouterr().err


@pytest.mark.parametrize("value, on", [("false", False), ("no", False), ("0", False), ("", False), ("1", True),
                                       ("True", True)])
def test_deterministic_switch_reads_its_words(monkeypatch, value, on):
    """DIFFSHADOW_DETERMINISTIC=false or no turned deterministic mode on (any non-empty string did)."""
    import torch

    from diffshadow.runtime import set_deterministic_from_env

    monkeypatch.setenv("DIFFSHADOW_DETERMINISTIC", value)
    before = torch.are_deterministic_algorithms_enabled()
    try:
        assert set_deterministic_from_env() is on
        assert torch.are_deterministic_algorithms_enabled() is (on or before)
    finally:
        torch.use_deterministic_algorithms(before)


ALLOCATION_HEAVY = """
import hashlib, sys, torch
from diffshadow.runtime import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
g = torch.Generator().manual_seed(0)
x, w = torch.randn(200_000, 32, generator=g), torch.randn(32, 32, generator=g)
h = hashlib.sha256()
for _ in range(4):  # tensors of 25 MiB, allocated and freed in turn: the pattern the setting changes
    x = torch.sin(x @ w + 0.1 * x.sum())
    h.update(x.numpy().tobytes())
print(h.hexdigest())
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_keeping_freed_memory_changes_no_value_and_a_users_malloc_settings_win(monkeypatch):
    """The CLI asks glibc to keep freed memory (fewer page faults, docs/performance.md "The allocator"): a
    computation gives the same bytes with and without it, and a user's own malloc tuning is left alone."""
    import subprocess
    import sys

    from diffshadow.runtime import keep_freed_memory

    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}
    runs = [subprocess.run([sys.executable, "-c", ALLOCATION_HEAVY, mode], capture_output=True, text=True,
                           check=True, env=env).stdout.strip() for mode in ("keep", "default")]
    assert len(runs[0]) == 64 and runs[0] == runs[1]
    for key in ("GLIBC_TUNABLES", "MALLOC_TRIM_THRESHOLD_"):
        with monkeypatch.context() as m:
            m.setenv(key, "")
            assert keep_freed_memory() is False


BLAS_THREADS = """
import numpy, threadpoolctl
def blas():
    return {i["num_threads"] for i in threadpoolctl.threadpool_info() if "openblas64" in i["filepath"]}
before = blas()
from diffshadow.runtime import set_threads
set_threads(1)
print(sorted(before), sorted(blas()))
"""


def test_threads_set_numpys_blas_as_snakemake_sets_it_for_a_rule():
    """`--threads` caps numpy's OpenBLAS as Snakemake's OPENBLAS_NUM_THREADS does for a rule, so a command typed
    by hand splits a float64 SVD as the workflow's job did and writes its bytes (docs/performance.md)."""
    import subprocess
    import sys

    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}  # a shell's default on a machine of two cores or more
    done = subprocess.run([sys.executable, "-c", BLAS_THREADS], capture_output=True, text=True, env=env, check=True)
    before, after = done.stdout.split()
    if before != "[2]":
        pytest.skip(f"numpy's OpenBLAS starts at {before} threads here, not 2")
    assert after == "[1]"


def test_lights_prepare_volume_and_collect_weights_start_without_torch_and_record_their_phases(tmp_path):
    """The workflow jobs that compute nothing with torch import none (`python -X importtime` lists every module a
    process imports), and `--phases` writes where their time went; the prepared volume reads back whole."""
    import json
    import subprocess
    import sys

    from diffshadow.layout import SirenConfig, WeightLayout
    from diffshadow.lights import read_lights
    from diffshadow.store import write_subset

    def run(*argv: str) -> dict:
        phases = tmp_path / f"{argv[0]}.phases.json"
        # forked by a shell (not exec'd by it), as a workflow job is: Linux starts a process's peak RSS at its forking
        # parent's, and this test's process may hold over a GiB after the tests before it (1,462 MiB once)
        shell = ["bash", "-c", '"$@"; exit $?', "job"]
        done = subprocess.run([*shell, sys.executable, "-X", "importtime", "-m", "diffshadow.cli", "--phases",
                               str(phases), *argv], capture_output=True, text=True, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        imported = imported_modules(done.stderr)
        assert "diffshadow.argparsing" in imported and not [m for m in imported if m.split(".")[0] == "torch"]
        return json.loads(phases.read_text())

    from diffshadow.analytic import gaussian_blob
    from diffshadow.volume import load_prepared

    np.save(tmp_path / "blob.npy", gaussian_blob(9) * 3.0)
    tf = {"opacity": [[0.0, 0.0], [1.0, 1.0]], "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
          "density_scale": 10.0}
    rec = run("prepare-volume", "--config-json", json.dumps({"volume": "blob.npy", "transfer_function": tf}),
              "--out", "volume.zarr")
    volume, back = load_prepared(tmp_path / "volume.zarr")
    assert rec["io_s"] > 0 and volume.data.shape == (9, 9, 9) and back.to_config() == tf
    assert volume.data.min() == 0 and volume.data.max() == 1  # normalised on the way in

    rec = run("lights", "--sphere", "100", "--count", "4", "--center", "0", "0", "1", "--unseen", "2", "--out",
              "lights.json")
    assert rec["command"] == "lights" and rec["device_s"] == 0 and rec["import_s"] > 0
    assert "cpu_capability" not in rec  # recorded only where torch was imported (test below)
    assert 0 < rec["cpu_s"] and 0 < rec["max_rss_mib"] < 1024  # the process's own count (phases.usage)
    assert sum(rec[f"{k}_s"] for k in ("import", "device", "compile", "io", "compute")) == pytest.approx(
        rec["process_s"], abs=0.01)
    siren = SirenConfig(width=4, blocks=1)
    layout = WeightLayout.for_siren(siren)
    lights = read_lights(tmp_path / "lights.json")
    for i, rows in enumerate(([0, 1], [2, 3])):
        write_subset(tmp_path / f"subset_{i}.npz", weights=np.full((2, layout.n_params), float(i), np.float32),
                     light_index=rows, lights=lights["train"][rows], psnr=np.full(2, 40.0),
                     psnr_visible=np.full(2, 40.0), layout=layout, siren=siren, config={},
                     extinction="0" * 16)
    rec = run("collect-weights", "--lights", "lights.json", "--subsets", "subset_0.npz", "subset_1.npz",
              "--out", "weights.zarr")
    assert rec["io_s"] > 0 and (tmp_path / "weights.zarr").is_dir()


def test_report_figures_code_imports_no_torch():
    """report_figures sits on the run's last stretch and only draws: its command skips torch (cli._NO_TORCH), and
    nothing it imports (the CLI, report, store, lights, matplotlib's figures) brings torch in."""
    import subprocess
    import sys

    from diffshadow.cli import _NO_TORCH

    assert "report-figures" in _NO_TORCH
    done = subprocess.run([sys.executable, "-X", "importtime", "-c", "import diffshadow.cli, diffshadow.report, "
                           "diffshadow.store, diffshadow.lights; diffshadow.report.pyplot()"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    imported = imported_modules(done.stderr)
    assert "diffshadow.store" in imported and not [m for m in imported if m.split(".")[0] == "torch"]


def test_view_takes_the_runs_render_section_under_its_flags(tmp_path, capsys):
    """`diffshadow view results/<scene>` renders as the run did (its config's render section over the scene
    file's): the kernel and the step; --kernel wins; without a run config for the scene, the package defaults
    and one line saying so."""
    from diffshadow.cli import build_parser, run_render
    from diffshadow.config import ConfigError

    cfg = tmp_path / "run.yaml"
    cfg.write_text("scenes: [nucleon]\nrender: {kernel: eager, step: 0.25}\n")
    scenes = REPO / "config" / "scenes"

    def render(*args):
        return run_render(build_parser().parse_args(["view", *args, "--configfile", str(cfg), "--scenes-dir",
                                                     str(scenes)]))

    for scene in ("nucleon", "elsewhere"):
        (tmp_path / "results" / scene / "volume.zarr").mkdir(parents=True)
    got = render(str(tmp_path / "results" / "nucleon"))
    assert (got["kernel"], got["step"]) == ("eager", 0.25)
    assert render(str(tmp_path / "results" / "nucleon"), "--kernel", "fused")["kernel"] == "fused"
    assert render(str(tmp_path / "results" / "elsewhere")) == {}
    assert "no run config for scene 'elsewhere'" in capsys.readouterr().err
    # a folder that is not there, or no scene's (results/ itself): the viewer's error alone says so, not a line
    # about its config first
    assert render(str(tmp_path / "results" / "missing")) == {} and capsys.readouterr().err == ""
    assert render(str(tmp_path / "results")) == {} and capsys.readouterr().err == ""
    # a config file named but not there is refused, not replaced by the defaults
    with pytest.raises(ConfigError, match=r"--configfile .*nope.yaml: no such file"):
        run_render(build_parser().parse_args(["view", str(tmp_path / "results" / "nucleon"), "--configfile",
                                              str(tmp_path / "nope.yaml")]))


def test_a_torch_command_ends_without_pythons_teardown_once_its_output_is_written(tmp_path):
    """`run`, the console command: after a command that used PyTorch succeeds, the process ends at once (atexit
    handlers do not run), its output in place and its lines printed; so does a command that failed with its one
    line (tests/test_store.py -k among_many: what the teardown printed after it); one that succeeded without
    PyTorch ends the normal way."""
    import subprocess
    import sys

    code = "import atexit; atexit.register(lambda: print('teardown ran')); from diffshadow.cli import run; run()"

    def command(*argv):
        return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True)

    scene = str(REPO / "config/scenes/nucleon.yaml")
    rendered = command("render", "--scene-config", scene, "--mode", "noshadow", "--size", "16", "--out",
                       str(tmp_path / "a.png"))
    assert rendered.returncode == 0, rendered.stderr
    assert (tmp_path / "a.png").exists() and "wrote" in rendered.stdout and "teardown ran" not in rendered.stdout
    failed = command("render", "--scene-config", str(tmp_path / "none.yaml"), "--out", str(tmp_path / "b.png"))
    assert failed.returncode == 2 and failed.stderr.count("\n") == 1 and "none.yaml" in failed.stderr
    assert "teardown ran" not in failed.stdout
    lights = command("lights", "--sphere", "64", "--count", "8", "--center", "0", "0", "1", "--unseen", "2",
                     "--out", str(tmp_path / "lights.json"))
    assert lights.returncode == 0 and "teardown ran" in lights.stdout, lights.stderr


@pytest.mark.parametrize("capability, flags, forced, warned", [
    ("DEFAULT", {"avx2", "fma", "sse4_2"}, "", True),  # the silent fallback: a CPU with AVX2, scalar kernels
    ("NO AVX", {"avx2", "fma", "sse4_2"}, "", True),  # the same under torch 2.3, which names them so
    ("DEFAULT", {"avx2", "fma"}, "default", False),   # asked for (ATEN_CPU_CAPABILITY)
    ("AVX2", {"avx2", "fma"}, "", False),
    ("AVX512", {"avx2", "fma", "avx512f"}, "", False),
    ("DEFAULT", {"sse4_2"}, "", False),  # an older x86 CPU: scalar is all there is
    ("DEFAULT", set(), "", False),  # no flags (macOS, an ARM CPU's 'Features')
])
def test_scalar_cpu_kernels_on_an_avx2_cpu_are_warned_of(capability, flags, forced, warned):
    from diffshadow.runtime import vector_unit_warning

    said = vector_unit_warning(capability, flags, forced)
    assert (said is not None) is warned
    if warned:
        assert said.startswith("WARNING: PyTorch runs its scalar CPU kernels") and "\n" not in said


def test_a_torch_job_records_its_cpu_kernels_and_warns_only_when_unasked(tmp_path):
    """Every job that imports torch records which CPU kernels PyTorch chose (`cpu_capability` in its phases file)
    and on how many threads (`threads`): both change the last bits of its results; a job told to run the scalar
    ones records that and is not warned."""
    import json
    import subprocess
    import sys

    import torch

    from diffshadow.analytic import gaussian_blob

    np.save(tmp_path / "blob.npy", gaussian_blob(9))
    tf = json.dumps({"opacity": [[0.0, 0.0], [1.0, 1.0]], "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
                     "density_scale": 10.0})
    records = {}
    for name, extra in (("own", {"OMP_NUM_THREADS": "1"}), ("scalar", {"ATEN_CPU_CAPABILITY": "default",
                                                                      "OMP_NUM_THREADS": "2"})):
        env = {k: v for k, v in os.environ.items() if k != "ATEN_CPU_CAPABILITY"} | extra
        done = subprocess.run([sys.executable, "-m", "diffshadow.cli", "--phases", f"{name}.json", "render",
                               "--volume", "blob.npy", "--tf-json", tf, "--mode", "noshadow", "--size", "8",
                               "--out", f"{name}.png"], capture_output=True, text=True, cwd=tmp_path, env=env)
        assert done.returncode == 0 and "WARNING: PyTorch" not in done.stderr, done.stderr
        records[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert records["own"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert (records["own"]["threads"], records["scalar"]["threads"]) == (1, 2)  # reductions split by thread
    from diffshadow.runtime import SCALAR_KERNELS

    assert records["scalar"]["cpu_capability"] in SCALAR_KERNELS


def test_render_out_of_memory_names_its_size_flag(tmp_path, capsys, monkeypatch):
    """`diffshadow render` has no config section: a frame too large for the machine names --size, not "the sizes in
    this command's config section" (`render --size 100000` said that)."""
    from diffshadow.stages import images

    np.save(tmp_path / "v.npy", np.random.default_rng(0).random((6, 6, 6), dtype=np.float32))
    tf = '{"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 1}'
    monkeypatch.setattr(images, "render_image", lambda *a, **k: _cpu_allocator())
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--volume", str(tmp_path / "v.npy"), "--tf-json", tf, "--out", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 1 and "error: out of memory (" in err, err
    assert "; lower --size (the image's pixels), or run it where there is more memory" in err, err


def test_every_key_an_out_of_memory_error_names_is_a_config_key():
    """The keys the out-of-memory line tells a user to lower exist in defaults.yaml (a renamed key would send them
    looking for nothing)."""
    import re

    from diffshadow import config

    defaults = config.defaults()
    named = {k for text in config.MEMORY_KEYS.values() for k in re.findall(r"\b([a-z_]+(?:\.[a-z_]+)?)\b", text)
             if "." in k or k == "subset_size"}
    assert "fit.grid_upsample" in named and "subset_size" in named
    for key in named:
        node = defaults
        for part in key.split("."):
            assert isinstance(node, dict) and part in node, key
            node = node[part]


def test_the_commands_said_to_resume_are_commands():
    """`config.RESUMABLE` names subcommands (a renamed one would make a killed job's line say it starts again)."""
    from diffshadow import config
    from diffshadow.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert config.RESUMABLE <= set(sub.choices), config.RESUMABLE - set(sub.choices)


def test_spare_threads_take_the_cores_other_processes_leave_idle_and_give_them_back(monkeypatch):
    """fit_siren's threads follow the machine: raised to `most` while the other cores idle, back to its own as
    soon as another process computes, and left alone where /proc/stat cannot be read."""
    from diffshadow import runtime

    clock = {"t": 0.0, "busy": 0.0, "own": 0.0}
    monkeypatch.setattr(runtime.time, "monotonic", lambda: clock["t"])
    monkeypatch.setattr(runtime.time, "process_time", lambda: clock["own"])
    monkeypatch.setattr(runtime, "_busy_seconds", lambda cpus: clock["busy"])
    monkeypatch.setattr(runtime.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    set_to = []
    monkeypatch.setattr(runtime.torch, "set_num_threads", set_to.append)

    def second(own_cores: float, other_cores: float) -> int:
        clock["t"] += 1.0
        clock["own"] += own_cores
        clock["busy"] += own_cores + other_cores
        spare.poll()
        return spare.threads

    spare = runtime.SpareThreads(1, 2)
    assert second(1.0, 1.0) == 1  # a side job on the other core
    assert second(1.0, 0.05) == 2  # it ended: Snakemake's own polling is no job
    clock["t"] += 0.5
    spare.poll()  # polled twice a second: read once
    assert second(1.6, 0.0) == 2 and spare.raised_s == 1.5  # raised since the last reading
    assert second(1.3, 0.7) == 1  # another process started
    assert set_to == [2, 1]
    spare.release()
    assert spare.threads == 1 and set_to == [2, 1]

    monkeypatch.setattr(runtime, "_busy_seconds", lambda cpus: None)  # not Linux
    spare = runtime.SpareThreads(1, 2)
    assert second(1.0, 0.0) == 1 and set_to == [2, 1]


def test_borrowing_gives_the_threads_back_however_the_steps_end(monkeypatch, capsys):
    """A job's steps under `runtime.borrowing`: back on its own threads after them, also where they fail (the
    stage's error then stands alone, with no line saying how long it borrowed); no poll without a spare."""
    from diffshadow import runtime

    monkeypatch.setattr(runtime, "_busy_seconds", lambda cpus: 0.0)
    set_to = []
    monkeypatch.setattr(runtime.torch, "set_num_threads", set_to.append)
    with runtime.borrowing(None, "fitted") as poll:
        assert poll is None
    spare = runtime.SpareThreads(1, 2)
    with runtime.borrowing(spare, "fitted") as poll:
        spare._set(2)  # what a poll does while the other cores idle
    assert set_to == [2, 1] and spare.threads == 1
    assert capsys.readouterr().out.startswith("fitted on 1 thread(s), 2 for ")
    spare = runtime.SpareThreads(1, 2)
    with pytest.raises(ValueError, match="^a step failed$"), runtime.borrowing(spare, "fitted"):
        spare._set(2)
        raise ValueError("a step failed")
    assert set_to == [2, 1, 2, 1] and capsys.readouterr().out == ""
