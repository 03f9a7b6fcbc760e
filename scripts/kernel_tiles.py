"""The whole-ray inr kernel's resources per tile (rays per program) and warps, compiled for a GPU without one
(`diffshadow.bench.kernels`): registers, spills, programs and warps per SM, instructions and MUFU per trip.

    python scripts/kernel_tiles.py --sines poly approx --arch 90
"""

from __future__ import annotations

import argparse

from diffshadow.bench.kernels import compile_kernel, kernel_shapes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sines", nargs="+", default=["poly", "approx"], choices=["poly", "libdevice", "approx"])
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--precision", default="tf32", choices=["tf32", "ieee"])
    ap.add_argument("--blocks", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--warps", type=int, nargs="+", default=[2, 4, 8])
    a = ap.parse_args()
    for sine in a.sines:
        name, constants = kernel_shapes(a.precision, sine)["march (inr, whole rays)"]
        for block in a.blocks:
            for warps in a.warps:
                r = compile_kernel(name, {**constants, "BLOCK": block}, a.arch, warps)
                print(f"sm_{a.arch} {a.precision} {sine:9s} {block:3d} rays x {warps} warps: {r['registers']:3d} "
                      f"registers, {r['stack_bytes']:5d} B stack, {r['programs_per_sm']} programs = "
                      f"{r['programs_per_sm'] * warps:2d} warps/SM; {r['instructions']:6,} instructions, "
                      f"{r['mufu']:4d} MUFU, {r['local']:5d} local", flush=True)


if __name__ == "__main__":
    main()
