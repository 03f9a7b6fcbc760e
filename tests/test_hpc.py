"""Running at scale: the GPU lock, the PBS state mapping, the stand-in PBS's checks, and the Polaris and
Sophia profiles running the tiny scene end to end against the stand-in (packing, GPU pinning, a failed
subset rerun alone)."""

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml
from conftest import imported_modules, installed
from test_workflow import TINY

from diffshadow import scaling
from diffshadow.hpc import GPU_DRIVER_FILES, claim_gpu, pbs_state, pbs_status
from diffshadow.store import open_store

REPO = Path(__file__).resolve().parents[1]
PBS = Path(__file__).resolve().parent / "pbs"
DIFFSHADOW = installed("diffshadow")
BIN = DIFFSHADOW.parent


def test_pbs_state_mapping():
    assert pbs_state({"job_state": "R"}) == "running"
    assert pbs_state({"job_state": "Q"}) == "running"
    assert pbs_state({"job_state": "F", "Exit_status": 0}) == "success"
    assert pbs_state({"job_state": "F", "Exit_status": 271}) == "failed"
    assert pbs_state({}) == "failed"


def test_pbs_status_retries_a_transient_qstat_failure(tmp_path, monkeypatch):
    spool = tmp_path / "spool"
    spool.mkdir()
    (spool / "7.pbs.json").write_text("{}")
    (spool / "7.pbs.exit").write_text("0\n")
    monkeypatch.setenv("PATH", f"{PBS}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("STANDIN_PBS_SPOOL", str(spool))
    monkeypatch.setenv("STANDIN_PBS_QSTAT_FAILS", "1")
    # the server refuses one call: the finished job is still reported as finished, not as failed
    assert pbs_status("7.pbs", wait_s=0.01) == "success"
    (spool / "qstat_calls").unlink()
    # a server that stays down is not a failed job: Snakemake is told to ask again
    assert pbs_status("7.pbs", tries=1, wait_s=0.01) == "running"
    # PBS not knowing the job is
    assert pbs_status("8.pbs", wait_s=0.01) == "failed"


def test_gpu_lock_gives_each_process_its_own_gpu(tmp_path, monkeypatch):
    # holders keep their GPU until told to exit (a line on stdin), so no timing decides the outcome
    code = ("import sys; from diffshadow.hpc import claim_gpu; "
            f"print(claim_gpu(2, lock_dir={str(tmp_path)!r}, wait_s=float(sys.argv[1])), flush=True); "
            "sys.stdin.readline()")
    holders = [subprocess.Popen([sys.executable, "-c", code, "30"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                text=True) for _ in range(2)]
    got = sorted(int(p.stdout.readline()) for p in holders)
    assert got == [0, 1]
    late = subprocess.run([sys.executable, "-c", code, "0.5"], capture_output=True, text=True, input="\n")
    assert late.returncode != 0 and "no free GPU among 2" in late.stderr
    for p in holders:
        p.communicate("\n")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)  # claim_gpu sets it: restored after this test
    assert claim_gpu(2, lock_dir=tmp_path, wait_s=0.5) in (0, 1)  # freed when the holders exited
    assert os.environ["CUDA_VISIBLE_DEVICES"] in ("0", "1")


def qsub(tmp_path, *args, system="polaris"):
    script = tmp_path / "job.sh"
    script.write_text("#!/bin/bash\necho hello\n")
    env = {**os.environ, "STANDIN_PBS_SPOOL": str(tmp_path / "spool"), "STANDIN_PBS_SYSTEM": system}
    return subprocess.run([str(PBS / "qsub"), *args, str(script)], capture_output=True, text=True, env=env)


GOOD = ["-A", "proj", "-q", "debug", "-l", "select=1:system=polaris", "-l", "walltime=00:10:00",
        "-l", "filesystems=home:eagle"]


@pytest.mark.parametrize("drop, change, message", [
    ("-A", None, "Account_Name is required"),
    ("walltime", None, "walltime=HH:MM:SS is required"),
    ("filesystems", None, "filesystems=... is required"),
    (None, ("select=1:system=polaris", "select=1"), "Polaris needs -l select=N:system=polaris"),
    (None, ("debug", "prod"), "queue prod needs at least 10 nodes"),
])
def test_standin_qsub_rejects_what_alcf_rejects(tmp_path, drop, change, message):
    args = list(GOOD)
    if drop == "-A":
        args = args[2:]
    elif drop:
        i = next(i for i, a in enumerate(args) if a.startswith(drop))
        args = args[:i - 1] + args[i + 1:]
    if change:
        args = [change[1] if a == change[0] else a for a in args]
    proc = qsub(tmp_path, *args)
    assert proc.returncode != 0 and message in proc.stderr
    assert qsub(tmp_path, *GOOD).stdout.strip().endswith(".standin")


def _job(tmp_path, body: str, *extra, **env):
    """Submit a job script with `body` to the stand-in; its id and a qstat that returns its fields."""
    script = tmp_path / "job.sh"
    script.write_text(f"#!/bin/bash\ncd $PBS_O_WORKDIR\n{body}\n")
    environ = {**os.environ, "STANDIN_PBS_SPOOL": str(tmp_path / "spool"), **env}
    job = subprocess.run([str(PBS / "qsub"), *GOOD, *extra, str(script)], capture_output=True, text=True,
                         env=environ, cwd=tmp_path, check=True).stdout.strip()

    def state() -> dict:
        out = subprocess.run([str(PBS / "qstat"), "-fx", "-F", "json", job], capture_output=True, text=True,
                             env=environ, check=True).stdout
        return json.loads(out)["Jobs"][job]

    return job, state


def _until(state, accept, timeout: float = 60.0) -> list[str]:
    """The job states seen (each once) until `accept(fields)`."""
    import time

    seen, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        fields = state()
        if not seen or seen[-1] != fields["job_state"]:
            seen.append(fields["job_state"])
        if accept(fields):
            return seen
        time.sleep(0.05)
    raise AssertionError(f"job states {seen}, never accepted")


def test_standin_jobs_are_held_queued_run_and_finish(tmp_path):
    job, state = _job(tmp_path, "sleep 0.5; echo done > out.txt", STANDIN_PBS_HELD_S="1", STANDIN_PBS_QUEUED_S="1")
    _until(state, lambda f: f["job_state"] == "F")
    assert (tmp_path / "spool" / f"{job}.history").read_text() == "H Q R F"
    assert state()["Exit_status"] == 0 and pbs_state(state()) == "success"
    assert (tmp_path / "out.txt").read_text() == "done\n"


def test_standin_kills_a_job_at_its_walltime(tmp_path):
    job, state = _job(tmp_path, "trap 'echo got TERM > term.txt; exit 143' TERM; sleep 30 & wait",
                      STANDIN_PBS_WALLTIME_S="1")
    _until(state, lambda f: f["job_state"] == "F")
    assert state()["Exit_status"] == 271 and pbs_state(state()) == "failed"
    assert (tmp_path / "term.txt").read_text() == "got TERM\n"  # SIGTERM first, as PBS sends it


@pytest.mark.parametrize("rerunnable", [True, False])
def test_standin_preempts_and_requeues_a_rerunnable_job(tmp_path, rerunnable):
    body = "echo run >> runs.txt; touch half; sleep 2; echo finished >> runs.txt"
    job, state = _job(tmp_path, body, "-r", "y" if rerunnable else "n", STANDIN_PBS_PREEMPT="touch half=half")
    _until(state, lambda f: f["job_state"] == "F")
    runs = (tmp_path / "runs.txt").read_text().split()
    history = (tmp_path / "spool" / f"{job}.history").read_text()
    if rerunnable:  # killed once when it wrote `half`, queued again under the same id, run from the start
        assert history == "Q R Q R F" and state()["Exit_status"] == 0 and runs == ["run", "run", "finished"]
        assert (tmp_path / "spool" / f"{job}.runs").read_text() == "2"
    else:
        assert history == "Q R F" and state()["Exit_status"] == 271 and runs == ["run"]


def run_profile(workdir: Path, profile: str, *args: str, fail_subset: int | None = None, qstat_fails: int = 0,
                fit: dict | None = None, env: dict | None = None):
    """snakemake --profile PROFILE in `workdir` against the stand-in PBS (tiny scene, 4 fit_siren jobs); `fit`
    overrides the tiny scene's fit settings, `env` sets the stand-in's (STANDIN_PBS_*)."""
    shim = workdir / "shim"
    shim.mkdir(exist_ok=True)
    marker = workdir / "fail_marker"
    if fail_subset is not None:
        marker.write_text("")
    elif marker.exists():
        marker.unlink()
    # a `diffshadow` that fails for one subset while the marker exists: a job dying on its node
    (shim / "diffshadow").write_text(textwrap.dedent(f"""\
        #!/bin/bash
        if [[ " $* " == *" --subset {fail_subset if fail_subset is not None else 3} "* && -e {marker} ]]; then
            echo "injected failure" >&2; exit 1
        fi
        exec {DIFFSHADOW} "$@"
        """))
    (shim / "diffshadow").chmod(0o755)
    env_script = workdir / "env.sh"  # the documented DIFFSHADOW_ENV: what a job sources to find diffshadow
    env_script.write_text(f"export PATH={shim}:{BIN}:$PATH\nexport DIFFSHADOW_DEVICE=cpu\n"
                          f"export DIFFSHADOW_LOCK_DIR={workdir / 'locks'}\nexport OMP_NUM_THREADS=1\n")
    # no pbs_system here: the profile names its machine, whose settings outlive this --configfile (Snakefile)
    cfg = {**TINY, "lights": {**TINY["lights"], "count": 8}, "fit": {**TINY["fit"], **(fit or {})}}
    (workdir / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    env = {**os.environ, "PATH": f"{PBS}{os.pathsep}{BIN}{os.pathsep}{os.environ['PATH']}",
           "PBS_ACCOUNT": "testproj", "DIFFSHADOW_ENV": str(env_script),
           "STANDIN_PBS_SPOOL": str(workdir / "spool"), "STANDIN_PBS_SYSTEM": profile, "TMPDIR": str(workdir),
           "STANDIN_PBS_QSTAT_FAILS": str(qstat_fails), **(env or {})}
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--profile", str(REPO / "profiles" / profile), "--configfile", str(workdir / "tiny.yaml"),
           "--max-status-checks-per-second", "20", "--latency-wait", "5", "--seconds-between-status-checks", "1",
           *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)


def submissions(workdir: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((workdir / "spool").glob("*.json"))]


def test_polaris_profile_end_to_end_with_packing_and_a_failed_subset(tmp_path):
    # one thread per fit so packed jobs run side by side even on a 2-core test machine (a Polaris node
    # runs all four at once: 4 x 8 threads of its 32 cores)
    one = ("--set-threads", "fit_siren=1")
    # four fits of one round (`fit.rounds` off: with it the tiny scene's subsets meet, and each round packs alone;
    # the paper config's rounds are packed in tests/test_hpc.py::test_paper_scale_config_plans_forty_subsets_...)
    apart = {"rounds": False}
    first = run_profile(tmp_path, "polaris", *one, fit=apart)
    assert first.returncode == 0, first.stderr[-3000:]
    subs = submissions(tmp_path)
    packed = [s for s in subs if s["script"].count("fit_siren:") == 4]
    assert len(packed) == 1, "the four fit_siren jobs of a node should go in one submission"
    assert all(s["options"]["A"] == "testproj" and s["resources"]["filesystems"] == "home:eagle"
               and s["resources"]["select"] == "1:system=polaris" for s in subs)
    logs = tmp_path / "results/nucleon/logs"
    claims = [line.split("claimed GPU ")[1].split()[0] for i in range(4)
              for line in (logs / f"fit_siren_{i}.log").read_text().splitlines() if "claimed GPU" in line]
    # every packed job took a GPU through the node's lock (that two holders never share one is
    # test_gpu_lock_gives_each_process_its_own_gpu's; here the jobs may or may not overlap in time)
    assert len(claims) == 4 and set(claims) <= {"0", "1", "2", "3"}, claims
    for name in ("voxel_metrics.json", "image_metrics.json", "bench.json", "finetune_metrics.json"):
        assert (tmp_path / "results/nucleon" / name).exists()
    assert "2 process(es) on cpu" in (logs / "finetune_render.log").read_text()
    # seconds of figures, no PyTorch: where Snakemake runs, not a queue wait before the end
    assert not [s for s in subs if "report_figures" in s["script"]] and (logs / "report_figures.log").exists()

    # subset 3 fails on its node; it is rerun alone with -f, and a plain run completes the workflow
    sirens = tmp_path / "results/nucleon/sirens"
    before = {p.name: p.stat().st_mtime_ns for p in sirens.glob("*.npz") if p.name != "subset_3.npz"}
    subset_3 = (sirens / "subset_3.npz").read_bytes()
    failed = run_profile(tmp_path, "polaris", *one, "-f", "results/nucleon/sirens/subset_3.npz", fail_subset=3,
                         fit=apart)
    assert failed.returncode != 0 and "subset_3" in failed.stderr
    rerun = run_profile(tmp_path, "polaris", *one, "-f", "results/nucleon/sirens/subset_3.npz", fit=apart)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert (sirens / "subset_3.npz").exists()
    assert {p.name: p.stat().st_mtime_ns for p in sirens.glob("*.npz") if p.name in before} == before
    done = run_profile(tmp_path, "polaris", *one, fit=apart)
    assert done.returncode == 0, done.stderr[-3000:]
    # same seed, same bytes: the refitted subset equals the old one, so nothing downstream is stale
    assert (sirens / "subset_3.npz").read_bytes() == subset_3
    assert (tmp_path / "results/nucleon/report/image_grid.png").exists()


def test_a_preempted_node_is_requeued_and_its_fits_resume_to_the_same_bytes(tmp_path):
    """Polaris' preemptable queue: the node job running the four packed fit_siren jobs is killed as soon as a
    fit has checkpointed, PBS requeues it (-r y), the rerun resumes from the checkpoints, and stage 1's store is
    byte-identical to one from fits that ran uninterrupted."""
    fit = {"steps": 120, "checkpoint_every": 10, "rounds": False}  # four fits of one round, packed
    preempt = {"STANDIN_PBS_PREEMPT": "fit_siren=results/nucleon/sirens/subset_*.npz.ckpt"}
    one = ("--set-threads", "fit_siren=1")  # two fits at a time on a 2-core machine, not one (8 threads each)
    proc = run_profile(tmp_path, "polaris", "results/nucleon/weights.zarr", *one, fit=fit, env=preempt)
    assert proc.returncode == 0, proc.stderr[-3000:]
    packed = [s for s in submissions(tmp_path) if "fit_siren:" in s["script"]]
    assert len(packed) == 1
    job = next(p.stem for p in (tmp_path / "spool").glob("*.runs")
               if (tmp_path / "spool" / f"{p.stem}.json").read_text() == json.dumps(packed[0]))
    assert (tmp_path / "spool" / f"{job}.runs").read_text() == "2"  # preempted once, requeued, run again
    logs = "".join((tmp_path / f"results/nucleon/logs/fit_siren_{i}.log").read_text() for i in range(4))
    assert "resuming from" in logs and "at step " in logs, logs[-2000:]
    sirens = tmp_path / "results/nucleon/sirens"
    resumed = {p.name: p.read_bytes() for p in sirens.glob("subset_*.npz")}
    store = open_store(tmp_path / "results/nucleon/weights.zarr")
    # the same fits, uninterrupted
    again = run_profile(tmp_path, "polaris", "results/nucleon/weights.zarr", *one, "--forcerun", "fit_siren", fit=fit)
    assert again.returncode == 0, again.stderr[-3000:]
    assert {p.name: p.read_bytes() for p in sirens.glob("subset_*.npz")} == resumed
    assert open_store(tmp_path / "results/nucleon/weights.zarr").weights.tobytes() == store.weights.tobytes()


def test_sophia_profile_through_stage_1(tmp_path):
    # stage 1 only (Polaris above runs the whole workflow), with a PBS server that refuses the first two
    # status queries: a transient qstat failure must not fail a running job
    proc = run_profile(tmp_path, "sophia", "results/nucleon/weights.zarr", qstat_fails=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    subs = submissions(tmp_path)
    assert subs and all(s["options"]["q"] == "by-gpu" for s in subs)
    fits = [s for s in subs if "fit_siren:" in s["script"]]
    assert len(fits) == 4 and all(s["script"].count("fit_siren:") == 1 for s in fits)  # no packing on Sophia
    assert int((tmp_path / "spool" / "qstat_calls").read_text()) > 2
    assert (tmp_path / "results/nucleon/weights.zarr").is_dir()


def test_parsl_fit_runs_a_subset_after_the_pending_subsets_it_holds():
    """fit.rounds through Parsl: a job waits for the jobs that write the subset files it holds (a wave after
    theirs); a held file already written waits for nothing."""
    from diffshadow.parsl_fit import waves

    def job(i: int, held: list[int]) -> dict:
        return {"subset": i, "paths": {"out": f"s{i}.npz", "held": [f"s{h}.npz" for h in held]}}

    jobs = [job(0, []), job(1, [0]), job(2, [0, 1]), job(3, [9]), job(4, [1])]
    assert [[j["subset"] for j in wave] for wave in waves(jobs)] == [[0, 3], [1], [2, 4]]
    assert waves([]) == []


def test_parsl_fit_writes_what_the_rule_would(tmp_path):
    from test_workflow import planned

    base = yaml.safe_load((REPO / "config/config.yaml").read_text())
    for key, value in TINY.items():
        base[key] = {**base[key], **value} if isinstance(base.get(key), dict) else value
    (tmp_path / "config" / "scenes").mkdir(parents=True)
    (tmp_path / "config" / "config.yaml").write_text(yaml.safe_dump(base))
    (tmp_path / "config" / "scenes" / "nucleon.yaml").write_text((REPO / "config/scenes/nucleon.yaml").read_text())
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    smk = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory", str(tmp_path),
           "--configfile", str(tmp_path / "config/config.yaml"), "--cores", "2"]
    subprocess.run([*smk, "--until", "preoptimize"], env=env, check=True, capture_output=True, timeout=600)
    proc = subprocess.run([str(DIFFSHADOW), "parsl-fit", "--config", str(REPO / "config/parsl/local.py"),
                           "--configfile", str(tmp_path / "config/config.yaml"), "--results", "results"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "2 of 2 subsets pending" in proc.stdout
    sirens = sorted(p.name for p in (tmp_path / "results/nucleon/sirens").glob("*.npz"))
    assert sirens == ["subset_0.npz", "subset_1.npz"]
    assert (tmp_path / "results/parsl").is_dir() and not (tmp_path / "runinfo").exists()  # Parsl's logs: not in cwd
    plan = planned(subprocess.run([*smk, "-n"], env=env, capture_output=True, text=True, timeout=600))
    assert "fit_siren" not in plan and "collect_weights" in plan
    again = subprocess.run(proc.args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "0 of 2 subsets pending" in again.stdout
    # the same bytes as the rule's (the config it records too: it once differed in key order and a setting the
    # rule leaves out at its old behaviour, so weights.zarr's attributes depended on the route)
    fitted = (tmp_path / "results/nucleon/sirens/subset_0.npz").read_bytes()
    subprocess.run([*smk, "-f", "results/nucleon/sirens/subset_0.npz"], env=env, check=True, capture_output=True,
                   timeout=600)
    assert (tmp_path / "results/nucleon/sirens/subset_0.npz").read_bytes() == fitted


def test_local_profile_packs_jobs_by_threads(tmp_path):
    # `snakemake --profile local -j2` (the README's command) must never run two 2-thread jobs on 2 cores:
    # with `cores:` in the profile, Snakemake 9 read -j2 as two jobs of any size and did
    rules = "".join(f'''
rule job{i}:
    output: "{i}.txt"
    threads: 2
    shell: "date +%s.%N > {{output}}; sleep 1; date +%s.%N >> {{output}}"
''' for i in range(2))
    (tmp_path / "Snakefile").write_text('rule all:\n    input: "0.txt", "1.txt"\n' + rules)
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--profile", str(REPO / "profiles" / "local"), "-j2",
                           "-d", str(tmp_path), "-s", str(tmp_path / "Snakefile")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (s0, e0), (s1, e1) = ([float(t) for t in (tmp_path / f"{i}.txt").read_text().split()] for i in range(2))
    assert e0 <= s1 or e1 <= s0, "two 2-thread jobs ran at once on -j2"


def test_paper_scale_config_plans_forty_subsets_four_to_a_node(tmp_path):
    """config/paper.yaml on the Polaris profile with the sweep's workflow profile (profiles/paper): the whole DAG
    planned, 2,000 lights in 40 fit_siren jobs packed four to a node within each of their 4 rounds (`fit.rounds`:
    15, 11, 8 and 6 fits, 11 node jobs; one group for all would be one job), each rule asking for the walltime the
    sweep projected instead of the Polaris profile's guess (a dry run: nothing is submitted)."""
    env = {**os.environ, "PBS_ACCOUNT": "testproj"}
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
                           str(tmp_path), "--profile", str(REPO / "profiles" / "polaris"), "--workflow-profile",
                           str(REPO / "profiles" / "paper"), "--configfile", str(REPO / "config" / "paper.yaml"),
                           "-n"], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    assert re.search(r"^fit_siren\s+40$", out, re.M) and out.count("Group job siren") == 11, out[-3000:]
    assert [out.count(f"Group job siren{r} ") for r in range(4)] == [4, 3, 2, 2]
    projected = yaml.safe_load((REPO / "profiles" / "paper" / "config.yaml").read_text())["set-resources"]
    for rule in ("train_diffusion", "eval_truth"):
        job = out.split(f"rule {rule}:")[1].split("\n\n")[0]
        assert f"walltime={projected[rule]['walltime']}" in job, job


def submit_line(profile: str, resources: dict, env: dict | None = None) -> str:
    """The qsub line a profile's submit command becomes for a job with these resources: filled in by format, as
    Snakemake's cluster-generic executor fills it, then expanded by the shell it runs it in (echo for qsub)."""
    submit = yaml.safe_load((REPO / "profiles" / profile / "config.yaml").read_text())["cluster-generic-submit-cmd"]
    filled = submit.format(resources=type("R", (), resources)).replace("qsub ", "echo qsub ", 1)
    return subprocess.run(["bash", "-c", filled], env={"PBS_ACCOUNT": "x", **(env or {})}, capture_output=True,
                          text=True, check=True).stdout.strip()


def test_polaris_jobs_go_to_the_queue_pbs_queue_names():
    """The Polaris profile's word: preemptable by default, PBS_QUEUE=debug for quick tests (the variable was named
    there but read nowhere: every job went to preemptable)."""
    job = {"queue": "preemptable", "select": "1:system=polaris", "walltime": "00:10:00", "filesystems": "home:eagle",
           "rerunnable": "y", "pbs_log": "results/pbs"}
    assert " -q preemptable " in submit_line("polaris", job)
    assert " -q debug " in submit_line("polaris", job, {"PBS_QUEUE": "debug"})


@pytest.mark.parametrize("profile", ["polaris", "sophia"])
def test_a_pbs_profile_keeps_its_machine_under_the_runs_own_configfile(tmp_path, profile):
    """A --configfile on the command line replaces a profile's own `configfile:`, which is how config/paper.yaml's
    command lost the machine's settings. The profile names its machine in a default resource instead, and the
    Snakefile reads the machine's file under the run's: without PBS_ACCOUNT the run stops naming the profile;
    fine-tuning asks for and launches the machine's 4 GPUs' processes, or what the run's file says (a profile's
    set-threads must not stand in for finetune.nproc); the benchmark waits for the scene's other jobs, and takes
    the naive frame's counts from a job of their own, only where jobs share a node (Sophia), not on Polaris's whole
    nodes (there it counts them itself: no job more in the queue). Under the paper's workflow profile, whose
    set-resources replace the machine profile's whole, fine-tuning's qsub line still asks for its GPUs and caches
    for more than the default hour (dry runs)."""
    def plan(run: dict, *args: str, account: bool = True) -> subprocess.CompletedProcess:
        (tmp_path / "run.yaml").write_text(yaml.safe_dump(run))
        env = {k: v for k, v in os.environ.items() if k != "PBS_ACCOUNT"} | ({"PBS_ACCOUNT": "x"} if account else {})
        return subprocess.run([sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
                               str(tmp_path), "--profile", str(REPO / "profiles" / profile), "--configfile",
                               str(tmp_path / "run.yaml"), "-n", *args], env=env, capture_output=True, text=True,
                              timeout=300)

    def job(out: str, rule: str) -> str:
        return out.split(f"rule {rule}:")[1].split("\n\n")[0]

    def submitted(out: str, rule: str) -> str:
        line = next(x for x in job(out, rule).splitlines() if x.strip().startswith("resources:"))
        return submit_line(profile, dict(kv.split("=", 1) for kv in line.split(":", 1)[1].replace(" ", "").split(",")))

    unset = plan({"lights": {"count": 8}}, account=False)
    said = unset.stdout + unset.stderr  # Snakemake prints a parse error on stdout
    assert unset.returncode != 0 and f"profile {profile}: PBS_ACCOUNT is not set" in said, said[-2000:]
    # --cores as a node's: a dry run otherwise caps every job's threads, which finetune_render's launch line uses
    planned = plan({"lights": {"count": 8}}, "--cores", "64")
    assert planned.returncode == 0, planned.stderr[-3000:]
    tuning = job(planned.stdout, "finetune_render")
    assert "gpu=4" in tuning and "ddp-processes --nproc 4)" in tuning, tuning
    assert ("image_metrics.json" in job(planned.stdout, "benchmark")) == (profile == "sophia")
    # where it waits, it takes the naive frame's counts from a job beside stage 1; on Polaris it counts them itself
    assert ("--naive-counts results/nucleon/bench_naive.json" in job(planned.stdout, "benchmark")) == (
        profile == "sophia")
    assert ("rule bench_naive:" in planned.stdout) == (profile == "sophia")
    own = plan({"lights": {"count": 8}, "finetune": {"nproc": 3}}, "--cores", "64")  # the run's file wins
    assert own.returncode == 0, own.stderr[-2000:]
    assert "gpu=3" in job(own.stdout, "finetune_render") and "--nproc 3)" in job(own.stdout, "finetune_render")
    paper = plan(yaml.safe_load((REPO / "config" / "paper.yaml").read_text()), "--workflow-profile",
                 str(REPO / "profiles" / "paper"), "--cores", "64")
    assert paper.returncode == 0, paper.stderr[-3000:]
    whole_node, one_gpu = {"polaris": ("select=1:system=polaris",) * 2, "sophia": ("select=1:ngpus=4",
                                                                                   "select=1:ngpus=1")}[profile]
    assert whole_node in submitted(paper.stdout, "finetune_render"), submitted(paper.stdout, "finetune_render")
    projected = yaml.safe_load((REPO / "profiles" / "paper" / "config.yaml").read_text())["set-resources"]
    training = submitted(paper.stdout, "train_diffusion")
    assert one_gpu in training and f"walltime={projected['train_diffusion']['walltime']}" in training, training
    # caches, which the sweep did not time (52 min on one thread at these sizes): profiles/paper asks for it too
    assert f"walltime={projected['caches']['walltime']}" in submitted(paper.stdout, "caches")
    assert projected["caches"]["walltime"] == scaling.walltime(scaling.MARGIN * scaling.PAPER_CPU_S["caches"] / 3600)
    machine = yaml.safe_load((REPO / "profiles" / profile / "config.yaml").read_text())
    threads = machine.get("set-threads", {}).get("caches", 1)
    assert f"--threads {threads} " in job(paper.stdout, "caches"), job(paper.stdout, "caches")


def test_ddp_processes_caps_ranks_at_the_visible_gpus_and_asks_torch_only_where_a_gpu_may_be(tmp_path, monkeypatch):
    import diffshadow.hpc as hpc

    assert hpc.ddp_processes(4, None) == (4, "4 CPU process(es) (gloo)")
    assert hpc.ddp_processes(4, 2) == (2, "finetune.nproc is 4 but 2 GPU(s) are visible: running 2 process(es)")
    assert hpc.ddp_processes(1, 2) == (1, "1 process(es), one GPU each (NCCL)")
    with pytest.raises(ValueError, match=r"--nproc \(finetune.nproc\): expected at least 1 process, got 0"):
        hpc.ddp_processes(0, None)  # printed 0, and torchrun was asked for no process
    monkeypatch.delenv("DIFFSHADOW_DEVICE", raising=False)
    monkeypatch.setattr(hpc, "GPU_DRIVER_FILES", (str(tmp_path / "no-driver"),))
    assert not hpc.gpu_possible() and not hpc.gpu_possible(None, "cpu") and hpc.gpu_possible("cuda:1")
    monkeypatch.setenv("DIFFSHADOW_DEVICE", "cpu")
    assert not hpc.gpu_possible(None, "cuda") and hpc.gpu_possible("cuda", "cpu")  # the flag, then the environment
    monkeypatch.setenv("DIFFSHADOW_DEVICE", "")
    (tmp_path / "driver").touch()
    monkeypatch.setattr(hpc, "GPU_DRIVER_FILES", (str(tmp_path / "no-driver"), str(tmp_path / "driver")))
    assert hpc.gpu_possible() and hpc.gpu_possible(None, "auto") and not hpc.gpu_possible(None, "cpu")


def fake_nvidia_machine(root, monkeypatch, gpus: int, nodes: int, *, cuda_build: bool = True, rocm: bool = False):
    import diffshadow.hpc as hpc

    (root / "gpus").mkdir(parents=True)
    (root / "dev").mkdir()
    for i in range(gpus):
        (root / "gpus" / f"0000:{i:02x}:00.0").mkdir()
    for name in [f"nvidia{i}" for i in range(nodes)] + ["nvidiactl", "nvidia-uvm", "null"]:
        (root / "dev" / name).touch()
    monkeypatch.setattr(hpc, "NVIDIA_GPUS", str(root / "gpus"))
    monkeypatch.setattr(hpc, "DEVICE_NODES", str(root / "dev"))
    monkeypatch.setattr(hpc, "ROCM_DRIVER", str(root / ("dev/null" if rocm else "no-kfd")))
    monkeypatch.setattr(hpc, "torch_has_cuda", lambda: cuda_build)


@pytest.mark.parametrize("visible, count", [(None, 4), ("1", 1), ("3,0", 2), ("0,5,1", 1), ("-1,0", 0), ("", 0),
                                            ("GPU-8f3e2a", None), ("MIG-1", None), ("0,0", None)])
def test_the_driver_counts_visible_gpus_as_cuda_reads_cuda_visible_devices(tmp_path, monkeypatch, visible, count):
    """As `torch.cuda.device_count()`: a list of indices up to the first one out of range; names only PyTorch can
    resolve say None (tests/gpu checks the two against each other on a real GPU)."""
    import diffshadow.hpc as hpc

    fake_nvidia_machine(tmp_path, monkeypatch, gpus=4, nodes=4)
    if visible is None:
        monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    else:
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
    assert hpc.visible_nvidia_gpus() == count


def test_the_driver_count_is_none_where_only_torch_can_tell(tmp_path, monkeypatch):
    import diffshadow.hpc as hpc

    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    fake_nvidia_machine(tmp_path / "container", monkeypatch, gpus=8, nodes=2)
    assert hpc.visible_nvidia_gpus() == 2  # a container with 2 of the host's 8 GPUs' device nodes
    for name, kwargs in (("cpu", {"cuda_build": False}), ("rocm", {"rocm": True})):
        fake_nvidia_machine(tmp_path / name, monkeypatch, gpus=2, nodes=2, **kwargs)
        assert hpc.visible_nvidia_gpus() is None, name
    monkeypatch.setattr(hpc, "NVIDIA_GPUS", str(tmp_path / "no-driver"))
    assert hpc.visible_nvidia_gpus() is None


def test_a_job_on_a_gpu_asks_one_cpu_thread_and_a_ddp_job_one_per_gpu(tmp_path, monkeypatch):
    """`run_gpus` resolves the run's device setting against the driver, and `job_threads` asks for one CPU thread
    where it is a GPU (DDP ranks: one per GPU they can use), and for the rule's threads on the CPU or where only
    PyTorch could tell."""
    import diffshadow.hpc as hpc

    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.delenv("DIFFSHADOW_DEVICE", raising=False)
    fake_nvidia_machine(tmp_path / "two", monkeypatch, gpus=2, nodes=2)
    monkeypatch.setattr(hpc, "GPU_DRIVER_FILES", (str(tmp_path / "two" / "gpus"),))
    resolved = {spec: hpc.run_gpus(spec) for spec in ("auto", "cuda", "cuda:1", "cuda:2", "cuda:x", "cpu", "mps")}
    assert resolved == {"auto": 2, "cuda": 2, "cuda:1": 1, "cuda:2": None, "cuda:x": None, "cpu": None, "mps": None}
    assert hpc.job_threads(2, 2) == 1 and hpc.job_threads(4, 2, processes=True) == 2
    assert hpc.job_threads(1, 2, processes=True) == 1 and hpc.job_threads(2, None) == 2
    assert hpc.job_threads(3, None, processes=True) == 3
    monkeypatch.setenv("DIFFSHADOW_DEVICE", "cpu")  # the environment over the run's config, as every job reads it
    assert hpc.run_gpus("auto") is None
    monkeypatch.delenv("DIFFSHADOW_DEVICE")
    fake_nvidia_machine(tmp_path / "cpu-build", monkeypatch, gpus=2, nodes=2, cuda_build=False)
    assert hpc.run_gpus("auto") is None  # only PyTorch could tell: the CPU's threads, which never slow a CPU job


def test_the_workflow_asks_one_thread_for_the_geometry_stage_on_a_gpu(tmp_path):
    """On a machine whose driver shows a GPU (faked for Snakemake's process), train_diffusion asks one thread and
    finetune_render one process, so that `-j2` runs a side job beside them, and so does sample_shadows where it
    scores on the run's device too (evaluate.device: run, the default); on this machine's CPU, two each, but
    train_diffusion asks one where fit_correction starts beside it (`correction.steps` over 0, the default)."""
    fake = tmp_path / "fake"
    (fake / "gpus" / "0000:00:00.0").mkdir(parents=True)
    (fake / "dev").mkdir()
    (fake / "dev" / "nvidia0").touch()
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(textwrap.dedent(f"""
        import diffshadow.hpc as hpc
        hpc.NVIDIA_GPUS, hpc.DEVICE_NODES = {str(fake / "gpus")!r}, {str(fake / "dev")!r}
        hpc.GPU_DRIVER_FILES, hpc.ROCM_DRIVER = (hpc.NVIDIA_GPUS,), {str(fake / "no-kfd")!r}
        hpc.torch_has_cuda = lambda: True
        """))

    def asked(env: dict, *config: str) -> tuple[str, str, str]:
        # --cores: a dry run under -j caps every job's threads at one
        proc = subprocess.run([sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
                               str(tmp_path / "run"), "--cores", "4", "-n", "-p", *config], env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
        return (re.search(r"train-diffusion .* --threads (\d+)", proc.stdout)[1],
                re.search(r"ddp-processes --nproc (\d+)", proc.stdout)[1],
                re.search(r"sample-shadows .* --threads (\d+)", proc.stdout)[1])

    env = {k: v for k, v in os.environ.items() if k not in ("DIFFSHADOW_DEVICE", "CUDA_VISIBLE_DEVICES")}
    gpu = {**env, "PYTHONPATH": str(tmp_path / "site")}
    assert asked(gpu) == ("1", "1", "1")  # sample_shadows scores its SIRENs on the GPU too (evaluate.device: run)
    assert asked(gpu, "--config", "evaluate={device: cpu}") == ("1", "1", "2")  # on the CPU: two threads
    if not any(os.path.exists(f) for f in GPU_DRIVER_FILES):
        alone = ("--config", "correction={steps: 0}")
        assert asked(env, *alone) == asked(env, *alone, "evaluate={device: cpu}") == ("2", "2", "2")
        assert asked(env) == ("1", "2", "2")


def test_the_ddp_helper_takes_the_drivers_count_without_asking_torch(tmp_path, monkeypatch, capsys):
    import diffshadow.cli as cli

    fake_nvidia_machine(tmp_path, monkeypatch, gpus=2, nodes=2)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.delenv("DIFFSHADOW_DEVICE", raising=False)

    def no_torch(_):
        raise AssertionError("the device was resolved through torch")

    monkeypatch.setattr(cli, "_device", no_torch)
    monkeypatch.setattr("diffshadow.hpc.gpu_possible", lambda *_: True)
    cli.main(["ddp-processes", "--nproc", "4"])
    out = capsys.readouterr()
    assert out.out.strip() == "2" and "finetune.nproc is 4 but 2 GPU(s) are visible" in out.err
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")  # no GPU visible: torch decides (here: the CPU)
    with pytest.raises(AssertionError, match="through torch"):
        cli.main(["ddp-processes", "--nproc", "4"])


@pytest.mark.skipif(any(os.path.exists(f) for f in GPU_DRIVER_FILES),
                    reason="a GPU driver is here: the helper must ask torch")
def test_the_ddp_helper_starts_without_torch_where_no_gpu_can_be():
    """finetune_render's launch line asks `ddp-processes` first; on a CPU machine its answer needs no torch import
    (`python -X importtime` lists every module a process imports)."""
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "diffshadow.cli", "ddp-processes", "--nproc",
                           "3"], capture_output=True, text=True, env={**os.environ, "DIFFSHADOW_DEVICE": ""})
    assert done.returncode == 0, done.stderr
    imported = imported_modules(done.stderr)
    assert "diffshadow.hpc" in imported and not [m for m in imported if m.split(".")[0] == "torch"]
    assert done.stdout.strip() == "3" and "3 CPU process(es) (gloo)" in done.stderr


def _torchrun(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    return subprocess.run([str(DIFFSHADOW), "torchrun", "--standalone", "--nproc_per_node=2", "--no-python", *args],
                          capture_output=True, text=True, env=env, timeout=120)


def test_the_ddp_launcher_ends_a_failed_job_in_one_line_with_the_ranks_exit_code():
    """finetune_render's launcher (`diffshadow torchrun`): where a rank fails, the log ends with one line naming
    it, not torchrun's traceback, and the job exits with the rank's code; the ranks get the environment torchrun
    gives them (OMP_NUM_THREADS 1 where none was set)."""
    ok = _torchrun("sh", "-c", 'test "$OMP_NUM_THREADS" = 1')
    assert ok.returncode == 0, ok.stderr
    failed = _torchrun("sh", "-c", 'echo "rank $RANK: error: bad input" >&2; exit 3')
    assert failed.returncode == 3
    last = failed.stderr.strip().splitlines()[-1]
    assert re.fullmatch(r"diffshadow torchrun: rank [01] exited with code 3(; rank [01] exited with code 3|; "
                        r"torchrun then stopped rank\(s\) [01]); each rank's own error, where it printed one, is "
                        r"above", last), last
    assert "error: bad input" in failed.stderr and "Traceback" not in failed.stderr
    # (torchrun reads "$$" in its arguments as an escaped "$")
    kill = "import os; os.kill(os.getpid(), 9) if os.environ['RANK'] == '1' else __import__('time').sleep(60)"
    killed = _torchrun(sys.executable, "-c", kill)
    bad = subprocess.run([str(DIFFSHADOW), "torchrun", "--nproc_per_node=two", "-m", "x"], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr
    assert bad.stderr.startswith("diffshadow torchrun: error: --nproc_per_node: ") and "two" in bad.stderr
    assert killed.returncode == 128 + 9, killed.stderr
    assert killed.stderr.strip().splitlines()[-1].startswith("diffshadow torchrun: rank 1 was ended by SIGKILL; ")
    assert "Traceback" not in killed.stderr


def test_a_failed_ddp_jobs_line_names_the_causes_not_the_ranks_torchrun_stopped():
    from diffshadow.hpc import ranks_failed

    tail = "; each rank's own error, where it printed one, is above"
    # rank 1 killed (the OOM killer), rank 0 then lost its peer (exit 1), both dated to the same second by torchrun
    assert ranks_failed({0: 1, 1: -9}) == ("rank 1 was ended by SIGKILL; rank 0 exited with code 1" + tail, 137)
    assert ranks_failed({0: -15, 1: 2, 2: -15}) == ("rank 1 exited with code 2; torchrun then stopped rank(s) 0, 2"
                                                    + tail, 2)
    # every rank ended by SIGTERM (the scheduler's walltime): each is a cause
    assert ranks_failed({1: -15, 0: -15}) == ("rank 0 was ended by SIGTERM; rank 1 was ended by SIGTERM" + tail,
                                              143)


def test_the_ddp_launcher_signalled_stops_its_ranks_and_says_so_in_one_line():
    """A scheduler's walltime signals the launcher: the ranks end with it, and the log ends in one line (torchrun:
    a traceback from inside its agent)."""
    import signal
    import time

    proc = subprocess.Popen([str(DIFFSHADOW), "torchrun", "--standalone", "--nproc_per_node=2", "--no-python",
                             "sleep", "60"], stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while time.time() < deadline:
        ranks = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
        if len(ranks) == 2:
            break
        time.sleep(0.1)
    assert len(ranks) == 2, ranks
    proc.send_signal(signal.SIGTERM)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "diffshadow torchrun: ended by SIGTERM, and its ranks with it", err
    assert "Traceback" not in err
    # ended: gone, or a zombie its new parent (PID 1) has not reaped yet, which a loaded machine's init may leave
    # for a while (a full suite on 2 cores once found one there right after the launcher returned)
    def ended(pid: str) -> bool:
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
        except (FileNotFoundError, ProcessLookupError):
            return True

    deadline = time.time() + 10
    while not all(ended(pid) for pid in ranks) and time.time() < deadline:
        time.sleep(0.05)
    assert all(ended(pid) for pid in ranks), ranks


def test_the_free_memory_is_the_least_of_the_hosts_and_its_memory_cgroups(tmp_path):
    """MemAvailable, or less under a memory cgroup's limit: its own or an ancestor's (v2's memory.max, v1's
    memory.limit_in_bytes), less its usage but for inactive file pages; a namespaced cgroup's files at the mount's
    top; no limit ("max", v1's 2^63 rounded to a page) and unreadable files are none."""
    from diffshadow.hpc import cgroup_room, free_host_bytes

    def write(path, text):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)

    gib = 1 << 30
    meminfo = tmp_path / "meminfo"
    write(meminfo, f"MemTotal: {64 * gib // 1024} kB\nMemAvailable: {40 * gib // 1024} kB\n")
    v2, v1 = tmp_path / "v2", tmp_path / "v1"
    # v2: the job's cgroup limited to 16 GiB, 10 GiB used of which 3 GiB inactive file pages: 9 GiB of room
    write(v2 / "pbs" / "job1" / "memory.max", f"{16 * gib}\n")
    write(v2 / "pbs" / "job1" / "memory.current", f"{10 * gib}\n")
    write(v2 / "pbs" / "job1" / "memory.stat", f"anon {7 * gib}\ninactive_file {3 * gib}\nactive_file 0\n")
    write(v2 / "pbs" / "memory.max", "max\n")
    cgroups = tmp_path / "cgroup"
    write(cgroups, "0::/pbs/job1\n")
    assert cgroup_room(cgroups, v2) == 9 * gib
    assert free_host_bytes(meminfo, cgroups, v2) == 9 * gib
    # an ancestor's tighter limit binds
    write(v2 / "pbs" / "memory.max", f"{12 * gib}\n")
    write(v2 / "pbs" / "memory.current", f"{11 * gib}\n")
    assert cgroup_room(cgroups, v2) == 1 * gib
    # v1 under a cgroup namespace: the process's cgroup reads "/", its files at the memory mount's top
    write(v1 / "memory" / "memory.limit_in_bytes", f"{8 * gib}\n")
    write(v1 / "memory" / "memory.usage_in_bytes", f"{2 * gib}\n")
    write(v1 / "memory" / "memory.stat", f"inactive_file 5\ntotal_inactive_file {gib}\n")
    write(cgroups, "9:name=systemd:/\n4:memory:/\n0::/\n")
    assert cgroup_room(cgroups, v1) == 7 * gib
    # no limit: MemAvailable alone; nothing readable: None
    write(v1 / "memory" / "memory.limit_in_bytes", "9223372036854771712\n")
    assert cgroup_room(cgroups, v1) is None and free_host_bytes(meminfo, cgroups, v1) == 40 * gib
    assert free_host_bytes(tmp_path / "none", tmp_path / "none", v1) is None


def test_only_jobs_killed_by_sigkill_are_explained_in_either_way_snakemake_says_it():
    """Snakemake says a job's shell died of SIGKILL, or that it returned 137 (its pipeline's status); a job that
    failed on its own (exit 1, its error in its log) gets no line; a block without a log line names none."""
    from diffshadow.hpc import killed_lines

    def failed(rule: str, how: str, log: bool = True) -> str:
        return (f"RuleException:\nCalledProcessError in file \"x.smk\", line 4:\nCommand 'set -euo pipefail; "
                f"diffshadow ...' {how}.\n[Fri Dec  4 23:28:29 2026]\nError in rule {rule}:\n    message: None\n"
                f"    jobid: 3\n" + (f"    log: results/s/logs/{rule}.log (check log file(s) for error details)\n"
                                     if log else "") + "    shell:\n        diffshadow ...\n")

    text = "".join([failed("fit_siren", "died with <Signals.SIGKILL: 9>"),
                    failed("eval_truth", "returned non-zero exit status 1"),
                    failed("train_diffusion", "returned non-zero exit status 137"),
                    failed("summary", "died with <Signals.SIGKILL: 9>", log=False),
                    "Shutting down, this might take some time.\n"])
    said = killed_lines(text)
    assert [line.split()[0] for line in said] == ["fit_siren", "train_diffusion", "summary"]
    assert "(exit 137; its log, results/s/logs/fit_siren.log, ends without a word)" in said[0]
    assert "lower subset_size or fit.halo (SIRENs fitted together" in said[0]
    assert "lower diffusion.batch_size or diffusion.geometry_points," in said[1]
    assert "(exit 137; its log ends without a word)" in said[2] and "the sizes in this command's config" in said[2]
    # resumed where a checkpoint is kept (it said "resumes" of every job, the summary's too)
    assert [line.rsplit(". ", 1)[1] for line in said] == ["A rerun resumes from its last checkpoint"] * 2 + [
        "A rerun starts it again (it keeps no checkpoint)"]
    assert killed_lines(failed("eval_truth", "returned non-zero exit status 1")) == []
