"""The `diffshadow` command: one subcommand per workflow rule, plus `bench` and `install-profiles`."""

from __future__ import annotations

import argparse
import filecmp
import os
import sys
from pathlib import Path


def _lights(args: argparse.Namespace) -> None:
    from diffshadow.lights import make_light_sets, write_lights

    lights = make_light_sets(args.sphere, args.count, args.center, args.unseen, seed=args.seed)
    write_lights(args.out, lights)
    print(f"wrote {args.out}: {args.count} training and {args.unseen} unseen directions "
          f"(region of a {args.sphere}-point Fibonacci sphere around {lights['center']})")


def _bench_shadow(args: argparse.Namespace) -> None:
    from diffshadow.bench import bench_shadow, default_volumes

    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    volumes = [Path(v) for v in args.volumes] if args.volumes else default_volumes()
    bench_shadow(volumes, Path(args.out), device=args.device)


def config_home() -> Path:
    return Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")


def _same_profile(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    if not (a.is_dir() and b.is_dir()):
        return False
    cmp = filecmp.dircmp(a, b)
    return not (cmp.left_only or cmp.right_only or cmp.diff_files or cmp.funny_files)


def install_profiles(source: Path, target_root: Path, *, force: bool = False) -> list[Path]:
    """Link each profile folder of `source` into `target_root` (Snakemake's search path).

    An existing profile of the same name is left alone when it is this one (or identical) and
    refused otherwise, unless `force`.
    """
    if not source.is_dir():
        raise SystemExit(f"install-profiles: no profiles folder at {source} (run from the repository root "
                         f"or pass --source)")
    target_root.mkdir(parents=True, exist_ok=True)
    installed = []
    for profile in sorted(p for p in source.iterdir() if p.is_dir()):
        target = target_root / profile.name
        if target.exists() or target.is_symlink():
            if _same_profile(profile, target):
                installed.append(target)
                continue
            if not force:
                raise SystemExit(f"install-profiles: {target} exists and differs from {profile}; "
                                 f"remove it or pass --force")
            if target.is_symlink() or target.is_file():
                target.unlink()
            else:
                raise SystemExit(f"install-profiles: {target} is a real folder; remove it by hand")
        target.symlink_to(profile.resolve(), target_is_directory=True)
        installed.append(target)
    return installed


def _install_profiles(args: argparse.Namespace) -> None:
    root = Path(args.target) if args.target else config_home() / "snakemake"
    for path in install_profiles(Path(args.source), root, force=args.force):
        print(f"profile {path.name}: {path} -> {path.resolve()}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diffshadow", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("lights", help="training and unseen light directions as JSON")
    p.add_argument("--sphere", type=int, default=8000, help="points on the Fibonacci sphere (paper: 8000)")
    p.add_argument("--count", type=int, default=2000, help="training directions kept (paper: 2000)")
    p.add_argument("--center", type=float, nargs=3, default=(0.0, 0.0, 1.0), metavar=("X", "Y", "Z"))
    p.add_argument("--unseen", type=int, default=500, help="held-out directions (paper: 500)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_lights)

    bench = sub.add_parser("bench", help="benchmarks that print and save figures")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    p = bench_sub.add_parser("shadow", help="time vs error of the ground-truth shadow methods")
    p.add_argument("--volumes", nargs="*", help="volume files (default: bundled nucleon + ../shared/data)")
    p.add_argument("--out", default="bench", help="folder for bench_shadow.json and bench_shadow.png")
    p.add_argument("--device", default=None)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.set_defaults(func=_bench_shadow)

    p = sub.add_parser("install-profiles", help="make the repo's Snakemake profiles usable by bare name")
    p.add_argument("--source", default="profiles", help="folder of profiles (default: ./profiles)")
    p.add_argument("--target", default=None, help="default: ${XDG_CONFIG_HOME:-~/.config}/snakemake")
    p.add_argument("--force", action="store_true", help="replace a different profile that is a symlink")
    p.set_defaults(func=_install_profiles)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except ValueError as e:  # the library's input errors: one line, no traceback
        print(f"diffshadow {args.command}: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
