"""The whole-ray inr kernel's resources per tile (rays per program) and warps, compiled for a GPU without one
(`diffshadow.bench.kernels`): registers, spills, programs and warps per SM, instructions and MUFU per trip.

    python scripts/kernel_tiles.py --arch 90
    python scripts/kernel_tiles.py --blocks 64 --warps 4 --registers 0 168 128   # capped registers per thread
"""

from __future__ import annotations

import argparse
import itertools

from diffshadow.bench.kernels import compile_kernel, kernel_shapes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--blocks", type=int, nargs="+", default=[32, 64, 128])
    ap.add_argument("--warps", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--registers", type=int, nargs="+", default=[0], help="cap per thread (0: none)")
    a = ap.parse_args()
    name, constants = kernel_shapes()["march (inr, whole rays)"]
    for block, warps, cap in itertools.product(a.blocks, a.warps, a.registers):
        r = compile_kernel(name, {**constants, "BLOCK": block}, a.arch, warps, registers=cap or None)
        print(f"sm_{a.arch} {block:3d} rays x {warps} warps, cap {cap or '-':>3}: {r['registers']:3d} registers, "
              f"{r['stack_bytes']:5d} B stack, {r['programs_per_sm']} programs = {r['programs_per_sm'] * warps:2d} "
              f"warps/SM; {r['instructions']:6,} instructions, {r['mufu']:4d} MUFU, {r['local']:5d} local", flush=True)


if __name__ == "__main__":
    main()
