"""A stand-in PBS Pro for tests: `qsub`, `qstat -fx`, `qdel` that check what ALCF would reject and run the
job script in the background on this machine. State lives in $STANDIN_PBS_SPOOL; $STANDIN_PBS_SYSTEM is
`polaris` (default) or `sophia`."""

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
    out = SPOOL / f"{job}.out"
    exit_file = SPOOL / f"{job}.exit"
    runner = f"bash {shlex.quote(script)} > {shlex.quote(str(out))} 2>&1; echo $? > {shlex.quote(str(exit_file))}"
    proc = subprocess.Popen(["bash", "-c", runner], env=env, cwd="/", start_new_session=True,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    (SPOOL / f"{job}.pid").write_text(str(proc.pid))
    print(job)


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
        exit_file = SPOOL / f"{job}.exit"
        code = exit_file.read_text().strip() if exit_file.exists() else ""
        found[job] = {"job_state": "F", "Exit_status": int(code)} if code else {"job_state": "R"}
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
            try:
                os.killpg(int(pid_file.read_text()), signal.SIGTERM)
            except ProcessLookupError:
                pass
            exit_file = SPOOL / f"{job}.exit"
            if not exit_file.exists():
                exit_file.write_text("271\n")


if __name__ == "__main__":
    {"qsub": qsub, "qstat": qstat, "qdel": qdel}[sys.argv[1]](sys.argv[2:])
