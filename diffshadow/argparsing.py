"""Argument conventions shared by the `diffshadow` subcommands (`cli`, `bench.cli`): path options,
--out, --device / --config-device, --threads, --config-json, and what they resolve to."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch


def at_least(low: float, kind: type = int) -> Callable[[str], float]:
    """An argparse type: a number of `kind` no less than `low`, refused in argparse's one line otherwise (a
    negative --threads reached torch.set_num_threads and ended in its traceback)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        if not value >= low:  # NaN too
            raise argparse.ArgumentTypeError(f"expected at least {low:g}, got {text}")
        return value

    return parse


SEED_MAX = 2**63 - 1  # as the config schema's seed ($defs/seed in config.schema.yaml)


def seed(text: str) -> int:
    """An argparse type: a random draw's seed, 0 to SEED_MAX (numpy refuses a negative one in a traceback)."""
    value = int(at_least(0)(text))
    if value > SEED_MAX:
        raise argparse.ArgumentTypeError(f"expected at most 2^63-1, got {text}")
    return value


def config_of(args: argparse.Namespace) -> dict:
    """--config-json's sections, each held to the run schema's bounds."""
    from diffshadow.config import check_sections, parse_json

    value = parse_json(args.config_json)
    check_sections(value, value.what)
    return value


def device_of(args: argparse.Namespace) -> torch.device:
    """The job's device, resolved and started once (later calls return the same device; its start is timed)."""
    if getattr(args, "_device", None) is None:
        from diffshadow.phases import phase
        from diffshadow.runtime import resolve_device, set_deterministic_from_env, start_device

        with phase("device"):
            set_deterministic_from_env()
            args._device = start_device(resolve_device(args.device, args.config_device))
    return args._device


def add_networks(p: argparse.ArgumentParser) -> None:
    """--kernel: how the renderer evaluates its SIRENs (default: the config's `render.kernel`);
    --[no-]warm-kernels."""
    p.add_argument("--kernel", choices=["auto", "eager", "fused"],
                   help="default: render.kernel (auto: fused on CUDA, else eager)")
    p.add_argument("--warm-kernels", action=argparse.BooleanOptionalAction,
                   help="compile every fused kernel the scene can launch at its first frame, at once (default: "
                   "render.warm_kernels)")


def network_flags(args: argparse.Namespace) -> dict:
    """The --kernel and --[no-]warm-kernels given, as `render` config keys (to lay over a config's section)."""
    given = {"kernel": getattr(args, "kernel", None), "warm_kernels": getattr(args, "warm_kernels", None)}
    return {key: value for key, value in given.items() if value is not None}


def add_subcommand(sub: argparse._SubParsersAction, name: str, func: Callable[[argparse.Namespace], object],
                   helptext: str, *paths: str, out: bool = True, device: bool = True,
                   config: str | None = None) -> argparse.ArgumentParser:
    """A subcommand with required path options, --out, --device/--config-device, --threads, --config-json."""
    p = sub.add_parser(name, help=helptext)
    for path in paths:
        p.add_argument(f"--{path}", required=True)
    if config:
        p.add_argument("--config-json", required=True, help=config)
    if out:
        p.add_argument("--out", required=True)
    if device:
        p.add_argument("--device", default=None, help="cpu, cuda, cuda:N or auto (default: DIFFSHADOW_DEVICE, "
                       "then --config-device, then auto)")
        p.add_argument("--config-device", default=os.environ.get("DIFFSHADOW_CONFIG_DEVICE"),
                       help="the run config's `device` (default: DIFFSHADOW_CONFIG_DEVICE, which the workflow sets)")
    p.add_argument("--threads", type=at_least(0), default=0, help="torch threads (0: torch's default)")
    p.set_defaults(func=func)
    return p
