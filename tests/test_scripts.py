"""The tools kept in scripts/ are maintained: each answers --help with its usage, without a checkout's results."""

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
PYTHON = sorted(SCRIPTS.glob("*.py"))


def test_few_scripts():
    """scripts/ holds tools, not experiments (issue 52: at most 8 files)."""
    assert len(list(SCRIPTS.iterdir())) <= 8


@pytest.mark.parametrize("script", PYTHON, ids=[p.name for p in PYTHON])
def test_python_script_help(script, tmp_path):
    out = subprocess.run([sys.executable, str(script), "--help"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage:"), out.stdout[:200]


def test_gpu_session_help(tmp_path):
    script = SCRIPTS / "gpu_session.sh"
    out = subprocess.run(["bash", str(script), "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "QUICK=1" in out.stdout, out.stdout
    out = subprocess.run(["bash", str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "usage: scripts/gpu_session.sh" in out.stderr



def test_gpu_prepare_help_and_a_missing_shared_folder(tmp_path):
    """scripts/gpu_prepare.sh answers --help without fetching anything, and names the folder it could not find."""
    import os

    script = SCRIPTS / "gpu_prepare.sh"
    out = subprocess.run(["bash", str(script), "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "SHARED" in out.stdout and "GPU_PYTHON" in out.stdout, out.stdout
    env = {**os.environ, "SHARED": str(tmp_path / "nowhere")}
    out = subprocess.run(["bash", str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 2 and f"{tmp_path / 'nowhere'}/gpu/prepare.sh not found" in out.stderr, out.stderr

# What the lent GPU machine's image holds (shared/gpu/README.md names these and says "..."; scipy and pillow come
# with scikit-image and matplotlib), and the one dependency the device never needs.
GPU_IMAGE = {"torch", "numpy", "h5py", "scikit-image", "scipy", "matplotlib", "pillow", "pyyaml", "tqdm", "pytest",
             "hypothesis", "jinja2", "requests", "psutil"}
NOT_ON_DEVICE = {"parsl"}  # imported only by `diffshadow parsl-fit`, a login-node command


def test_every_dependency_reaches_the_gpu_machine():
    """Each runtime dependency in pyproject.toml is on the GPU machine's image, in the shared wheel list, or among
    the wheels scripts/gpu_prepare.sh adds: otherwise `import diffshadow` fails there on the first rule (it did for
    threadpoolctl, rehearsed in a virtual environment of the image's packages)."""
    import re
    import tomllib

    wheels = Path(__file__).resolve().parents[2] / "shared" / "gpu" / "wheels.txt"
    if not wheels.exists():
        pytest.skip("../shared/gpu/wheels.txt is absent")

    def name(req: str) -> str:
        return re.split(r"[\s\[<>=!~;]", req.strip(), maxsplit=1)[0].lower().replace("_", "-")

    shared = {name(line) for line in wheels.read_text().splitlines() if line.strip() and not line.startswith("#")}
    extra = re.search(r"^extra=\((.*)\)", (SCRIPTS / "gpu_prepare.sh").read_text(), re.M)
    assert extra, "scripts/gpu_prepare.sh: no extra=(...) line"
    added = {name(req) for req in extra.group(1).split()}
    project = tomllib.loads((SCRIPTS.parent / "pyproject.toml").read_text())["project"]
    missing = {name(req) for req in project["dependencies"]} - GPU_IMAGE - shared - added - NOT_ON_DEVICE
    assert not missing, f"not carried to the GPU machine: {sorted(missing)} (add to scripts/gpu_prepare.sh's extra)"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
def test_what_browser_py_starts_dies_with_it(tmp_path):
    """A driver killed without its cleanup (SIGKILL; a `timeout` signals its own group, and Chromium runs in a
    session of its own) takes the processes it started with it: an orphaned Chromium drew at 80 % of a core."""
    import os
    import signal
    import time

    driver = (f"import subprocess, sys; sys.path.insert(0, {str(SCRIPTS)!r}); from browser import _dies_with_driver\n"
              "p = subprocess.Popen(['sleep', '300'], start_new_session=True, preexec_fn=_dies_with_driver("
              "no_priority=True))\nprint(p.pid, flush=True)\nimport time; time.sleep(300)\n")
    proc = subprocess.Popen([sys.executable, "-c", driver], stdout=subprocess.PIPE, text=True)
    child = int(proc.stdout.readline())
    os.kill(child, 0)  # alive while the driver is
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:  # gone, or dead and not yet reaped by whoever adopted it
            if Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                return
        except (FileNotFoundError, ProcessLookupError):
            return
        time.sleep(0.05)
    os.kill(child, signal.SIGKILL)
    pytest.fail(f"process {child} outlived its driver")


def test_the_viewer_check_makes_a_new_direction_as_the_cache_answers_it(tmp_path):
    """browser.py renders a new direction's SIREN with the run's cache to compare with the viewer's canvas: at model
    share 0 the blend answers (it had rendered the model alone: 45.7 dB, 5 levels off in a README run), at 1 the
    model alone, between them both at the share; cache: blend, the stored SIRENs only."""
    sys.path.insert(0, str(SCRIPTS))
    from browser import new_direction_source

    mix = {"weights": "results/nucleon/weights.zarr", "blend_k": 4, "blend_weights": "triangle"}
    blend = ["--blend", str(tmp_path / "weights.zarr"), "--blend-k", "4", "--blend-weights", "triangle"]
    for share in (0.0, 0.7):
        made = {"cache": "diffusion", "mix": {**mix, "model_share": share}}
        assert new_direction_source(tmp_path, made, "d.ckpt") == ["--diffusion", "d.ckpt", *blend, "--model-share",
                                                                  repr(share)]
    model_alone = ["--diffusion", "d.ckpt"]
    assert new_direction_source(tmp_path, {"cache": "diffusion", "mix": {**mix, "model_share": 1.0}}, "d.ckpt") == \
        model_alone
    assert new_direction_source(tmp_path, {"cache": "diffusion"}, "d.ckpt") == model_alone  # before the mix
    made = {"cache": "blend", "blend_k": 3, "blend_weights": "inverse-angle"}
    assert new_direction_source(tmp_path, made, "w.zarr") == ["--blend", "w.zarr", "--blend-k", "3",
                                                              "--blend-weights", "inverse-angle"]
