"""The package runs outside the checkout: its defaults and schemas ship inside the wheel, and importing it changes
no process setting."""

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_import_writes_no_environment():
    code = "import os; before = dict(os.environ); import diffshadow, diffshadow.cli; print(dict(os.environ) == before)"
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "True"


def test_wheel_renders_outside_the_checkout(tmp_path):
    """A non-editable install into a fresh venv renders a scene file from another directory, the same bytes as
    this checkout's `diffshadow render`."""
    src = tmp_path / "src"  # a copy: building in the checkout would leave build/ there
    shutil.copytree(REPO / "diffshadow", src / "diffshadow", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path / "dist")], check=True, capture_output=True, timeout=300)
    (wheel,) = (tmp_path / "dist").glob("diffshadow-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    site = next((venv / "lib").glob("python*/site-packages"))
    # the dependencies from this environment (a path in a .pth file: its own .pth files, this checkout's editable
    # install among them, are not read), the package itself only from the wheel
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "--no-deps",
                    "-q", str(wheel)], check=True, capture_output=True, timeout=300)
    work = tmp_path / "elsewhere"
    work.mkdir()
    (work / "nucleon.yaml").write_text((REPO / "config/scenes/nucleon.yaml").read_text())
    args = ["render", "--scene-config", "nucleon.yaml", "--mode", "noshadow", "--size", "24", "--device", "cpu"]
    where = subprocess.run([str(venv / "bin" / "python"), "-c", "import diffshadow; print(diffshadow.__file__)"],
                           cwd=work, capture_output=True, text=True, check=True).stdout
    assert where.startswith(str(site)), where
    out = subprocess.run([str(venv / "bin" / "diffshadow"), *args, "--out", "wheel.png"], cwd=work,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    subprocess.run([sys.executable, "-m", "diffshadow.cli", *args, "--out", "checkout.png"], cwd=work, check=True,
                   capture_output=True, timeout=300)
    assert (work / "wheel.png").read_bytes() == (work / "checkout.png").read_bytes()
