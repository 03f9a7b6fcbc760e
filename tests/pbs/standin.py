"""A stand-in PBS Pro for tests: `qsub`, `qstat -fx`, `qdel` that check what ALCF would reject and run the
job script in the background on this machine. State lives in $STANDIN_PBS_SPOOL; $STANDIN_PBS_SYSTEM is
`polaris` (default) or `sophia`.

What ALCF does to a job, on request:
- STANDIN_PBS_HELD_S, STANDIN_PBS_QUEUED_S: seconds a job sits held (H), then queued (Q), before it runs (R);
- STANDIN_PBS_WALLTIME_S: the walltime every job gets, in seconds (else its -l walltime): past it the job is
  killed (SIGTERM, then SIGKILL) and finishes with Exit_status 271 (256 + SIGTERM, as PBS reports it);
- STANDIN_PBS_PREEMPT="TEXT=GLOB": a job whose script contains TEXT is preempted once, when a file matching
  GLOB (relative to its working directory) appears: killed like the walltime kill, then, if it was submitted
  rerunnable (-r y), queued again under the same job id and run from the start of its script; if not, it
  finishes with Exit_status 271. `<job>.runs` counts its runs.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

SPOOL = Path(os.environ.get("STANDIN_PBS_SPOOL", "/tmp/standin-pbs"))
SYSTEM = os.environ.get("STANDIN_PBS_SYSTEM", "polaris")
QUEUES = {"polaris": {"debug", "debug-scaling", "preemptable", "prod", "demand"}, "sophia": {"by-gpu", "by-node"}}
# real qsub does not carry the caller's environment over; these few are all a job sees
PASS_ENV = ("HOME", "USER", "LANG", "DIFFSHADOW_ENV", "STANDIN_PBS_SPOOL", "STANDIN_PBS_SYSTEM", "TMPDIR")


def fail(msg: str, code: int = 1):
    print(f"qsub: {msg}", file=sys.stderr)
    sys.exit(code)


def parse(argv: list[str]) -> tuple[dict, str | None]:
    opts: dict = {"l": []}
    script = None
    i = 0
    while i < len(argv):
        a = argv[i]
        if a in ("-A", "-q", "-N", "-r", "-j", "-o", "-e", "-v", "-W", "-l"):
            if i + 1 >= len(argv):
                fail(f"option {a} needs a value")
            if a == "-l":
                opts["l"].extend(argv[i + 1].split(","))
            else:
                opts[a[1:]] = argv[i + 1]
            i += 2
        elif a == "-V":
            opts["V"] = True
            i += 1
        elif a.startswith("-"):
            fail(f"illegal option -- {a}")
        else:
            script = a
            i += 1
    return opts, script


def qsub(argv: list[str]) -> None:
    opts, script = parse(argv)
    if script is None or not Path(script).is_file():
        fail(f"no job script (got {script!r})")
    text = Path(script).read_text()
    for line in text.splitlines():  # directives in the script
        if line.startswith("#PBS"):
            more, _ = parse(shlex.split(line[4:]))
            opts["l"] += more.pop("l")
            opts.update({k: v for k, v in more.items() if k not in opts})
    res = dict(x.split("=", 1) if "=" in x else (x, "") for x in opts["l"])
    account = opts.get("A", "")
    if not account or account.startswith("$"):
        fail("Account_Name is required: every ALCF job needs -A PROJECT")
    if "walltime" not in res or not re.fullmatch(r"\d+:\d\d:\d\d", res["walltime"]):
        fail(f"-l walltime=HH:MM:SS is required (got {res.get('walltime')!r})")
    if "filesystems" not in res or not res["filesystems"]:
        fail("-l filesystems=... is required (e.g. home:eagle)")
    queue = opts.get("q", "")
    if queue not in QUEUES[SYSTEM]:
        fail(f"unknown queue {queue!r} on {SYSTEM} (known: {sorted(QUEUES[SYSTEM])})")
    chunks = res.get("select", "")  # `-l select=N:system=polaris` arrives as select -> "N:system=polaris"
    select = f"select={chunks}" if chunks else ""
    if SYSTEM == "polaris":
        if "system=polaris" not in chunks:
            fail(f"Polaris needs -l select=N:system=polaris (got {select or 'no select'})")
        nodes = int(chunks.split(":")[0]) if chunks.split(":")[0].isdigit() else 0
        if queue == "prod" and nodes < 10:
            fail(f"queue prod needs at least 10 nodes (asked for {nodes})")
    SPOOL.mkdir(parents=True, exist_ok=True)
    counter = SPOOL / "counter"
    n = int(counter.read_text()) + 1 if counter.exists() else 1
    counter.write_text(str(n))
    job = f"{n}.standin"
    workdir = os.getcwd()
    (SPOOL / f"{job}.json").write_text(json.dumps({"argv": argv, "options": opts, "resources": res,
                                                   "script": text, "workdir": workdir}))
    env = {k: os.environ[k] for k in PASS_ENV if k in os.environ}
    env.update({"PATH": "/usr/local/bin:/usr/bin:/bin", "PBS_JOBID": job, "PBS_O_WORKDIR": workdir,
                "PBS_QUEUE": queue, "PBS_ACCOUNT": account})
    h, m, sec = (int(x) for x in res["walltime"].split(":"))
    (SPOOL / f"{job}.sh").write_text(text)  # PBS runs its own copy: a requeued job reruns it
    plan = {"script": str(SPOOL / f"{job}.sh"), "env": env, "rerunnable": opts.get("r", "n") == "y",
            "walltime_s": float(os.environ.get("STANDIN_PBS_WALLTIME_S") or 3600 * h + 60 * m + sec),
            "held_s": float(os.environ.get("STANDIN_PBS_HELD_S", "0")),
            "queued_s": float(os.environ.get("STANDIN_PBS_QUEUED_S", "0")),
            "preempt": os.environ.get("STANDIN_PBS_PREEMPT", "")}
    (SPOOL / f"{job}.plan").write_text(json.dumps(plan))
    (SPOOL / f"{job}.state").write_text("H" if plan["held_s"] else "Q")
    proc = subprocess.Popen([sys.executable, __file__, "supervise", job], cwd="/", start_new_session=True,
                            env={**os.environ}, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    (SPOOL / f"{job}.pid").write_text(str(proc.pid))
    print(job)


def _kill(proc: subprocess.Popen, grace_s: float = 5.0) -> None:
    """What PBS does to a job it ends: SIGTERM to the whole session, SIGKILL after a grace period."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(grace_s)
            return
        except subprocess.TimeoutExpired:
            continue


def _replace_text(path: Path, text: str) -> None:
    """Write in one rename: qstat, reading at any moment, sees the old text or the new, never half of it."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class _State:
    """The job's state for qstat, and its history (every state it went through, for tests to read)."""

    def __init__(self, path: Path, history: Path):
        self.path, self.history = path, history
        self.history.write_text(path.read_text())

    def write_text(self, state: str) -> None:
        _replace_text(self.path, state)
        with open(self.history, "a") as f:
            f.write(f" {state}")


def supervise(argv: list[str]) -> None:
    """One job's life: held, queued, running (killed at its walltime, preempted and requeued), finished."""
    import time

    job = argv[0]
    plan = json.loads((SPOOL / f"{job}.plan").read_text())
    meta = json.loads((SPOOL / f"{job}.json").read_text())
    runs, exit_file = SPOOL / f"{job}.runs", SPOOL / f"{job}.exit"
    state = _State(SPOOL / f"{job}.state", SPOOL / f"{job}.history")
    text, _, pattern = plan["preempt"].partition("=")
    preempt = bool(text) and text in meta["script"]
    if plan["held_s"]:
        time.sleep(plan["held_s"])
        state.write_text("Q")
    time.sleep(plan["queued_s"])
    n = 0
    while True:
        n += 1
        runs.write_text(str(n))
        state.write_text("R")
        with open(SPOOL / f"{job}.out", "a") as out:
            proc = subprocess.Popen(["bash", plan["script"]], env=plan["env"], cwd="/", start_new_session=True,
                                    stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT)
        (SPOOL / f"{job}.jobpid").write_text(str(proc.pid))
        start, code = time.monotonic(), None
        while code is None:
            code = proc.poll()
            if code is not None:
                break
            if time.monotonic() - start > plan["walltime_s"]:
                _kill(proc)
                code = 271
            elif preempt and n == 1 and list(Path(meta["workdir"]).glob(pattern)):
                _kill(proc)
                if plan["rerunnable"]:
                    state.write_text("Q")  # requeued under the same id
                    time.sleep(1.0)
                    code = "requeued"
                else:
                    code = 271
            else:
                time.sleep(0.02)
        if code != "requeued":
            break
    # the exit status first, then the state: qstat must never see F without Exit_status (a finished job read
    # between the two writes was reported failed, and its Snakemake run with it)
    _replace_text(exit_file, f"{code}\n")
    state.write_text("F")


def qstat(argv: list[str]) -> None:
    # STANDIN_PBS_QSTAT_FAILS=N: the first N calls fail as a busy or restarting server does
    fails = int(os.environ.get("STANDIN_PBS_QSTAT_FAILS", "0"))
    counter = SPOOL / "qstat_calls"
    calls = int(counter.read_text()) if counter.exists() else 0
    counter.write_text(str(calls + 1))
    if calls < fails:
        print("Connection refused\nqstat: cannot connect to server pbs01 (errno=111)", file=sys.stderr)
        sys.exit(1)
    as_json = "-F" in argv and argv[argv.index("-F") + 1] == "json"
    jobs = [a for a in argv if not a.startswith("-") and a != "json"]
    found = {}
    for job in jobs:
        if not (SPOOL / f"{job}.json").exists():
            print(f"qstat: Unknown Job Id {job}", file=sys.stderr)
            sys.exit(153)
        exit_file, state = SPOOL / f"{job}.exit", SPOOL / f"{job}.state"
        code = exit_file.read_text().strip() if exit_file.exists() else ""
        found[job] = ({"job_state": "F", "Exit_status": int(code)} if code
                      else {"job_state": state.read_text().strip() if state.exists() else "Q"})
    if as_json:
        print(json.dumps({"pbs_version": "2022.1.5", "Jobs": found}, indent=4))
        return
    for job, fields in found.items():
        print(f"Job Id: {job}")
        for key, value in fields.items():
            print(f"    {key} = {value}")


def qdel(argv: list[str]) -> None:
    for job in (a for a in argv if not a.startswith("-")):
        pid_file = SPOOL / f"{job}.pid"
        if pid_file.exists():
            for pids in (pid_file, SPOOL / f"{job}.jobpid"):  # the supervisor, then the job's own session
                try:
                    os.killpg(int(pids.read_text()), signal.SIGTERM)
                except (ProcessLookupError, FileNotFoundError):
                    pass
            exit_file = SPOOL / f"{job}.exit"
            if not exit_file.exists():
                exit_file.write_text("271\n")


if __name__ == "__main__":
    {"qsub": qsub, "qstat": qstat, "qdel": qdel, "supervise": supervise}[sys.argv[1]](sys.argv[2:])
