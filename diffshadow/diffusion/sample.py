"""Sampling the diffusion model (paper §3.3): SIREN weights for any light direction, DDIM or DDPM, and
the sampler rebuilt from a checkpoint."""

from __future__ import annotations

import copy
import dataclasses
import weakref

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.diffusion.config import DiffusionConfig, DiffusionError, build_model
from diffshadow.diffusion.model import WeightTransformer
from diffshadow.diffusion.schedule import Schedule
from diffshadow.diffusion.standardize import Standardizer
from diffshadow.graphs import StepGraphs
from diffshadow.lights import LightRegion, as_direction
from diffshadow.sampling import Stream, seeded
from diffshadow.siren import SirenConfig, WeightLayout


def sampler_weights(state: dict) -> dict:
    """The weights a checkpoint samples from: its EMA where it has one, else its trained weights."""
    return state["ema"] if state.get("ema") else state["model"]


def load_sampler(state: dict, device: torch.device | str = "cpu"
                 ) -> tuple[WeightTransformer, Standardizer, WeightLayout, SirenConfig]:
    """(model for sampling, standardizer, layout, siren) from a checkpoint state."""
    layout = WeightLayout.from_config(state["layout"])
    cfg = DiffusionConfig.of_checkpoint(state)
    model = build_model(layout, cfg)
    model.load_state_dict(sampler_weights(state))
    model.to(device).eval()
    std = Standardizer(layout, state["standardizer"]["mean"], state["standardizer"]["std"])
    return model, std, layout, SirenConfig.from_config(state["siren"])


@dataclasses.dataclass
class _Denoise:
    """One denoiser call's inputs: what a captured graph copies in before each replay."""
    x: torch.Tensor
    t: torch.Tensor
    w: torch.Tensor


# each model's captured denoiser graphs, with the addresses of the parameters they read: kept across `generate`
# calls (the viewer's lights, evaluate's sampler rows), captured again where the parameters moved
_GRAPHS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _graphs(model: torch.nn.Module, device: torch.device) -> StepGraphs:
    addresses = tuple(p.data_ptr() for p in model.parameters())
    held = _GRAPHS.get(model)
    if held is None or held[0] != addresses:
        held = _GRAPHS[model] = (addresses, StepGraphs(device))
    return held[1]


@torch.no_grad()
def generate(model: WeightTransformer, std: Standardizer, lights: ArrayLike, *, method: str = "ddim", steps: int = 50,
             seed: int = 0, batch: int = 64, temperature: float = 1.0, device: torch.device | str = "cpu",
             dtype: torch.dtype = torch.float32, cuda_graph: bool = True) -> torch.Tensor:
    """SIREN weights (N, n_params) for light directions (N, 3) (any direction, seen or not).

    `dtype` float16/bfloat16 runs the network in half precision (a copy of it); the sampler's noise is
    drawn in float32 and de-standardisation is float64 either way. On CUDA (unless `cuda_graph` is False) each
    denoiser call after the first few replays a captured graph, kept with the model for later calls: one launch for
    the forward's ~90 kernels, which bound a step there; the same kernels, so the same numbers."""
    lights = np.stack([as_direction(w, name=f"light {i}") for i, w in enumerate(np.asarray(lights).reshape(-1, 3))])
    if dtype != torch.float32:
        model = copy.deepcopy(model).to(dtype)
    graphs = _graphs(model, torch.device(device)) if cuda_graph and torch.device(device).type == "cuda" else None
    schedule = Schedule()
    out = []
    for b0 in range(0, len(lights), batch):
        w = torch.as_tensor(lights[b0:b0 + batch], dtype=torch.float32, device=device)
        # each step's timestep and largest |x0| stay on the device (amax keeps a NaN: finite iff all of x0 is) and
        # are read once per batch, not at every step: on a GPU the host then queues the next step while this one runs
        steps_seen: list[torch.Tensor] = []
        peaks: list[torch.Tensor] = []

        def forward(inputs: _Denoise) -> torch.Tensor:
            return model(inputs.x.to(dtype), inputs.t, inputs.w.to(dtype)).float()

        def denoise(x, t, w=w, steps_seen=steps_seen, peaks=peaks):
            # a replay's output is the graph's own tensor: the samplers use it before the next call
            out = forward(_Denoise(x, t, w)) if graphs is None else graphs(forward, _Denoise(x, t, w))
            steps_seen.append(t[0])
            peaks.append(out.abs().amax())
            return out

        gen = seeded(seed, Stream.SAMPLE_NOISE, b0)
        shape = (len(w), std.layout.n_params)
        if method == "ddim":
            z = schedule.ddim_sample(denoise, shape, steps=steps, generator=gen, temperature=temperature,
                                     device=device)
        elif method == "ddpm":
            z = schedule.ddpm_sample(denoise, shape, generator=gen, device=device)
        else:
            raise ValueError(f"method: expected 'ddim' or 'ddpm', got {method!r}")
        finite = torch.isfinite(torch.stack(peaks)).cpu()
        if not finite.all():
            first = int(torch.stack(steps_seen)[int((~finite).nonzero()[0])])
            raise DiffusionError(f"generate: the model's x0 is not finite at timestep {first} ({dtype}, lights "
                                 f"{b0}..{b0 + len(w) - 1}); sample in float32")
        out.append(std.destandardize(z.double()).float().cpu())
    return torch.cat(out)


def checkpoint_region(state: dict) -> LightRegion:
    """The light region a checkpoint was trained for: as saved with it, else (a checkpoint from before regions
    were saved) the cap around its training lights' mean direction."""
    return LightRegion.recorded(state.get("region"), np.asarray(state["train_lights"]))


class ShadowSampler:
    """A checkpoint ready to generate shadow SIRENs for any light, the way `sample_shadows` does (DDIM at the
    checkpoint's `ddim_steps`, `seed` and `temperature`). One light at a time gives the same SIREN every time
    for that light; a row of `generated.zarr` came from a batch, so its noise differs."""

    def __init__(self, state: dict, device: torch.device | str = "cpu"):
        self.model, self.std, self.layout, self.siren = load_sampler(state, device)
        self.config, self.device = state["config"], torch.device(device)
        self.region, self.extinction = checkpoint_region(state), state.get("extinction")

    def __call__(self, light: ArrayLike) -> torch.Tensor:
        """(n_params,) float32 weights of the shadow SIREN of one light direction."""
        return generate(self.model, self.std, [as_direction(light)], method="ddim", steps=self.config["ddim_steps"],
                        seed=self.config["seed"], temperature=self.config["temperature"], device=self.device)[0]
