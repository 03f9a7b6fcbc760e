"""Ground truth at sampled points, computed once and read by later stages: the presampled points and exact
shadows of the geometry loss, the held-out check points of the seen-light gap, and `eval_truth`'s fixed
evaluation points with every light's exact shadow (the march is their cost)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.metrics import psnr
from diffshadow.progress import eta
from diffshadow.sampling import PointSampler, Stream, seeded
from diffshadow.shadow import CPU_CHUNK, SAMPLES_PER_ITER, ShadowField, transmittance_per_light
from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout, box_to_siren, passes
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume


def presample(volume: Volume, tf: TransferFunction, lights: np.ndarray, n_points: int, *, seed: int,
              stream: int = Stream.TRAIN_POINTS, visible_fraction: float = 0.5,
              device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Points (N, M, 3) and their true shadow (N, M) per light, for the geometry loss (paper §3.3); on the
    CPU, whatever device marched them (the points are drawn on the CPU: the same on every device)."""
    field = ShadowField.build(volume, tf, device=device)
    pts = PointSampler(volume, tf, visible_fraction).sample(len(lights), n_points, seeded(seed, stream))
    values = transmittance_per_light(field, tf, lights, pts).cpu()
    return pts, values


# Rays one march of TruthPoints.truth takes at least: a CPU chunk's (shadow.CPU_CHUNK samples, SAMPLES_PER_ITER a
# ray). Smaller marches are bound by their per-iteration ops, not by the samples, and leave a second thread idle:
# the blend's correction marched its 64-light chunks 6 lights and one point set (3,072 rays) at a time, 2.4x the
# time of 65,536 at two threads (docs/performance.md, "The exact march"). Rays are independent: the same values.
MIN_RAYS_PER_MARCH = CPU_CHUNK // SAMPLES_PER_ITER

CHECK_POINTS = 4096  # held-out points per scene at which the seen-light gap is measured (diffusion.target_gap)
CHECK_LIGHTS = 64  # training lights (evenly spaced rows) whose gap is measured: all of the default run's


def check_rows(n: int) -> torch.Tensor:
    """The rows of `n` training lights whose seen-light gap is measured: up to CHECK_LIGHTS, evenly spaced."""
    return torch.unique(torch.linspace(0, n - 1, min(n, CHECK_LIGHTS), device="cpu").round().long())


def check_points(volume: Volume, tf: TransferFunction, lights: np.ndarray, n_points: int = CHECK_POINTS, *, seed: int,
                 device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Points (C, 3) uniform in the box — how evaluate_voxels' "box" set is drawn, but other draws — and the
    true shadow (R, C) there of the lights `check_rows` picks. The geometry stage never trains on them, so the
    seen-light gap it measures there is the evaluation's: on tooth the presampled (training) points read 1.0 dB
    where the evaluation found 3.1 (docs/performance.md). On the CPU, whatever device marched them."""
    field = ShadowField.build(volume, tf, device=device)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    gen = seeded(seed, Stream.CHECK_POINTS)
    pts = torch.rand(n_points, 3, generator=gen, device=gen.device) * extent
    checked = np.asarray(lights)[check_rows(len(lights)).numpy()]
    values = transmittance_per_light(field, tf, checked, pts).cpu()
    return pts, values


class TruthPoints:
    """Fixed evaluation points (box and visible) with the true shadow of every light that is asked for."""

    def __init__(self, volume: Volume, tf: TransferFunction, n_points: int, seed: int,
                 device: torch.device | str = "cpu"):
        self.volume, self.tf = volume, tf
        self.field = ShadowField.build(volume, tf, device=device)  # points are drawn on the CPU, truth kept there
        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32)
        gen = seeded(seed, Stream.EVAL_POINTS)
        self.sets = {"box": torch.rand(n_points, 3, generator=gen, device=gen.device) * self.extent}
        vis = PointSampler(volume, tf, 1.0)
        if vis.visible_fraction:
            self.sets["visible"] = vis.sample(1, n_points, gen)[0]

    def truth(self, lights: np.ndarray, log: Callable[[str], None] | None = None,
              what: str = "lights") -> dict[str, torch.Tensor]:
        """True shadow (L, P) per point set, by the exact march; progress every ~10% when `log` is given."""
        sizes = [len(p) for p in self.sets.values()]
        points = torch.cat(list(self.sets.values()))
        start, n = time.perf_counter(), len(lights)
        # ~10 groups of lights, each marched together with every set's points, and none under MIN_RAYS_PER_MARCH
        every = max(1, n // 10, -(-MIN_RAYS_PER_MARCH // max(1, len(points))))
        out = {k: [] for k in self.sets}
        for a in range(0, n, every):
            marched = transmittance_per_light(self.field, self.tf, lights[a:a + every], points).cpu()
            for k, part in zip(self.sets, marched.split(sizes, dim=1), strict=True):
                out[k].append(part)  # a view: the set's torch.cat below copies it into a tensor of its own
            if log:
                log(f"ground truth, {what}: {min(a + every, n)}/{n} ({eta(min(a + every, n), n, start)})")
        return {k: torch.cat(v) if v else torch.zeros(0, len(self.sets[k])) for k, v in out.items()}

    def sirens(self, weights: np.ndarray, layout: WeightLayout, siren: SirenConfig) -> dict[str, torch.Tensor]:
        return _siren_values(self.sets, self.extent, weights, layout, siren)


CPU = torch.device("cpu")


@dataclass
class EvalTruth:
    """`eval_truth`'s fixed evaluation points (per set: box, visible) and the exact shadow of every light
    at them, computed once and read by `sample_shadows` and `evaluate_voxels` (the march is their cost)."""

    points: dict[str, torch.Tensor]  # set -> (P, 3)
    lights: np.ndarray  # (L, 3)
    values: dict[str, torch.Tensor]  # set -> (L, P)
    extent: torch.Tensor
    # where `sirens` evaluates the SIRENs it scores (their values come back to the CPU, as the truth is kept):
    # evaluate.device: run puts them on the run's GPU (`on`)
    device: torch.device = CPU

    def on(self, device: torch.device | str) -> EvalTruth:
        """This truth with its SIRENs evaluated on `device` (the points and the truth stay on the CPU)."""
        return dataclasses.replace(self, device=torch.device(device))

    @classmethod
    def compute(cls, volume: Volume, tf: TransferFunction, lights: np.ndarray, n_points: int, seed: int,
                log: Callable[[str], None] | None = None,
                device: torch.device | str = "cpu", sets: tuple[str, ...] | None = None) -> EvalTruth:
        """The exact shadow of every light at `n_points` points per set; `sets` keeps only those named (None: box
        and visible), the same points as the whole truth's (each set is drawn whether kept or not)."""
        points = TruthPoints(volume, tf, n_points, seed, device)
        if sets is not None:
            points.sets = {k: v for k, v in points.sets.items() if k in sets}
        return cls(points=points.sets, lights=np.asarray(lights, dtype=np.float64),
                   values=points.truth(lights, log, "all lights"), extent=points.extent)

    def of(self, lights: np.ndarray, where: str = "eval_truth") -> dict[str, torch.Tensor]:
        """The truth rows (L', P) per set for `lights`, each of which must be one this truth was made for."""
        lights = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
        dist = np.abs(lights[:, None, :] - self.lights[None, :, :]).max(axis=-1)
        rows = dist.argmin(axis=1) if len(self.lights) else np.zeros(len(lights), dtype=np.int64)
        missing = [i for i, r in enumerate(rows) if not len(self.lights) or dist[i, r] > 1e-9]
        if missing:
            raise ValueError(f"{where}: no ground truth for light {lights[missing[0]].tolist()} "
                             f"({len(missing)} of {len(lights)} missing); rerun eval_truth for these lights")
        idx = torch.as_tensor(rows)
        return {k: v[idx] for k, v in self.values.items()}

    def sirens(self, weights: np.ndarray, layout: WeightLayout, siren: SirenConfig,
               sets: tuple[str, ...] | None = None) -> dict[str, torch.Tensor]:
        """The SIRENs `weights` (L, n_params) at the points of every set, or only of those named in `sets` (each
        set costs a full evaluation)."""
        points = self.points if sets is None else {k: self.points[k] for k in sets}
        return _siren_values(points, self.extent, weights, layout, siren, device=self.device)

    def median_psnr(self, weights: np.ndarray, layout: WeightLayout, siren: SirenConfig, lights: np.ndarray,
                    point_set: str = "box") -> float:
        """Median over `lights` of the voxel PSNR of their SIRENs `weights` (L, n_params) at one point set (the
        SIRENs evaluated there only)."""
        values = self.sirens(weights, layout, siren, sets=(point_set,))
        return median(psnr(values[point_set], self.of(lights)[point_set], dim=1).numpy())


# Activations per chunk of SIRENs (64 MiB of float32): all 1,024 lights of a sweep point at once made 2-GiB
# tensors, each a fresh mapping, and 9 GiB resident (choose-cache; docs/performance.md "The allocator"). The
# README run's 32 lights at 16,384 points are one chunk.
CHUNK_FLOATS = 1 << 24


def light_chunks(n: int, per_light: int) -> list[slice]:
    """Slices of `n` SIRENs with at most CHUNK_FLOATS activations each (`per_light` apiece). No chunk holds a
    single SIREN unless `n` is 1: a batched product of one matrix takes another kernel than a batch of several and
    rounds differently, while chunks of two or more gave every SIREN the bits of one batch of all in every case
    measured (tests/test_evaluate.py)."""
    return passes(n, max(2, CHUNK_FLOATS // max(1, per_light)), least=2)  # a last single SIREN joins the chunk before


def _siren_values(sets: dict, extent: torch.Tensor, weights, layout: WeightLayout, siren: SirenConfig, *,
                  device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """The SIRENs `weights` at each set's points, evaluated on `device` in chunks; the values on the CPU."""
    w = torch.as_tensor(np.asarray(weights), dtype=torch.float32)
    out: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        for k, p in sets.items():
            # into one tensor made first: each chunk's result made between its activations (all from glibc's heap
            # under `runtime.keep_freed_memory`) grew the heap by about a chunk's activations per chunk; at the
            # paper's sizes evaluate_voxels held 15 GiB resident for 6 GiB of live tensors (docs/performance.md)
            values = out[k] = torch.empty(len(w), p.shape[-2])
            p, box = p.to(device), extent.to(device)
            for c in light_chunks(len(w), p.shape[-2] * siren.width):
                x = box_to_siren(p.expand(len(w[c]), -1, -1), box)
                values[c] = BatchedSiren(w[c].to(device), layout, siren.blocks)(x).cpu()
    return out


def psnr_per_light(pred: dict, truth: dict) -> dict[str, np.ndarray]:
    return {k: psnr(pred[k], truth[k], dim=1).numpy() for k in truth}


def median(a: ArrayLike) -> float:
    return float(np.median(a))


def p10(a: ArrayLike) -> float:
    """The 10th percentile: the lights a median does not see."""
    return float(np.percentile(a, 10))
