"""MKL strict reproducibility (MKL_CBWR=AUTO,STRICT, set by `import diffshadow`) against MKL's default
(AUTO): wall time of three stages on the main job's nucleon results, interleaved (2 runs each, median),
and whether the output bytes depend on --threads under each.

    python scripts/mkl_cbwr.py          # after `snakemake --profile local -j2`; writes bench/mkl_cbwr.json
"""

import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

R = Path("results/nucleon")
FIT = json.dumps({"siren": {"width": 32, "blocks": 2}, "subset_size": 16,
                  "fit": {"steps": 60, "points": 4096, "eval_points": 4096, "chunk": 512, "min_psnr": 0}})
STAGES = {
    "fit-siren (16 lights, 60 steps)": ["fit-siren", "--volume", R / "volume.zarr", "--lights", R / "lights.json",
                                        "--init", R / "siren_init.pt", "--subset", "0", "--config-json", FIT],
    "sample-shadows (80 lights, DDIM 50)": ["sample-shadows", "--checkpoint", R / "diffusion.ckpt",
                                            "--volume", R / "volume.zarr", "--lights", R / "lights.json"],
    "render inr 128x128": ["render", "--volume", R / "volume.zarr", "--mode", "inr", "--weights",
                           R / "weights.zarr", "--size", "128"],
}
SUFFIX = {"fit-siren": ".npz", "sample-shadows": ".zarr", "render": ".png"}


def digest(p: Path) -> str:
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    return hashlib.sha1(b"".join(f.read_bytes() for f in files)).hexdigest()[:12]


def run(args: list, cbwr: str, threads: int, tmp: Path) -> tuple[float, str]:
    out = tmp / f"out{SUFFIX[args[0]]}"
    cmd = [sys.executable, "-m", "diffshadow.cli", *map(str, args), "--threads", str(threads), "--out", str(out)]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, env={**os.environ, "MKL_CBWR": cbwr})
    seconds = time.perf_counter() - t
    d = digest(out)
    subprocess.run(["rm", "-rf", str(out)], check=True)
    return seconds, d


def main() -> None:
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, args in STAGES.items():
            times = {"AUTO": [], "AUTO,STRICT": []}
            bytes_by_threads = {}
            for _rep in range(2):
                for cbwr in times:
                    seconds, d = run(args, cbwr, 2, Path(tmp))
                    times[cbwr].append(seconds)
                    bytes_by_threads.setdefault(cbwr, {})[2] = d
            for cbwr in times:
                bytes_by_threads[cbwr][1] = run(args, cbwr, 1, Path(tmp))[1]
            med = {k: statistics.median(v) for k, v in times.items()}
            result[name] = {"seconds_median": med, "seconds": times,
                            "strict_over_auto": med["AUTO,STRICT"] / med["AUTO"],
                            "same_bytes_1_and_2_threads": {k: v[1] == v[2] for k, v in bytes_by_threads.items()}}
            print(f"{name:38s} AUTO {med['AUTO']:6.2f} s  STRICT {med['AUTO,STRICT']:6.2f} s  "
                  f"ratio {result[name]['strict_over_auto']:.3f}  same bytes at 1 and 2 threads: "
                  f"{result[name]['same_bytes_1_and_2_threads']}", flush=True)
    Path("bench/mkl_cbwr.json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
