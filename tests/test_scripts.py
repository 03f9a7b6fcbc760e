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
