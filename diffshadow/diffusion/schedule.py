"""The diffusion maths, apart from the network: linear betas, forward noising, DDPM and DDIM sampling.

The model predicts x0 (paper §3.3); samplers turn that into the previous step's mean.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from diffshadow.sampling import to_device

T_STEPS = 500  # paper §3.4
BETA_START, BETA_END = 1e-4, 2e-2  # linear schedule (DDPM)

Denoiser = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (x_t, t) -> predicted x0


class Schedule:
    def __init__(self, steps: int = T_STEPS, beta_start: float = BETA_START, beta_end: float = BETA_END):
        self.steps = steps
        # host-side tables (the samplers read them as Python floats); q_sample's roots go to each device once
        self.betas = torch.linspace(beta_start, beta_end, steps, dtype=torch.float64, device="cpu")
        self.alpha_bar = torch.cumprod(1.0 - self.betas, dim=0)
        self._roots: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def _q_roots(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """√ᾱ and √(1-ᾱ), computed in float64 and cast to `like`'s dtype on its device once (as the standardizer's
        tables are): a training step then copies and casts nothing (four copies and four casts a step before), and
        copies from the host are what a step captured as a CUDA graph cannot hold."""
        key = (like.device, like.dtype)
        if key not in self._roots:
            ab = self.alpha_bar
            self._roots[key] = (ab.sqrt().to(like.device, like.dtype), (1 - ab).sqrt().to(like.device, like.dtype))
        return self._roots[key]

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """x_t = √ᾱ_t x0 + √(1-ᾱ_t) ε."""
        # Both roots in float64, then cast (found by the stress suite): 1 - ᾱ in float32 at t = 0 is
        # 1.66e-4 off in relative terms, since ᾱ_0 = 0.9999 keeps only 4 of float32's 7 digits past 1.
        root_ab, root_rest = self._q_roots(x0)
        shape = (-1, *([1] * (x0.ndim - 1)))
        return root_ab[t].view(shape) * x0 + root_rest[t].view(shape) * noise

    def ddpm_sample(self, model: Denoiser, shape: tuple[int, ...], *, generator: torch.Generator,
                    device: torch.device | str | None = None) -> torch.Tensor:
        """Ancestral sampling over all T steps with the posterior q(x_{t-1} | x_t, x0̂)."""
        x = _noise(shape, generator, device)
        ab, betas = self.alpha_bar.tolist(), self.betas.tolist()  # Python floats: no tensor read per step
        for t in range(self.steps - 1, -1, -1):
            x0 = model(x, torch.full((shape[0],), t, device=device, dtype=torch.long))
            if t == 0:
                return x0
            ab_t, ab_prev, beta = ab[t], ab[t - 1], betas[t]
            c0 = ab_prev**0.5 * beta / (1 - ab_t)
            ct = (1 - beta) ** 0.5 * (1 - ab_prev) / (1 - ab_t)
            var = beta * (1 - ab_prev) / (1 - ab_t)
            noise = _noise(shape, generator, device)
            x = c0 * x0 + ct * x + var**0.5 * noise
        return x

    def ddim_timesteps(self, n: int) -> list[int]:
        if not 1 <= n <= self.steps:
            raise ValueError(f"DDIM steps: expected 1..{self.steps}, got {n}")
        return torch.linspace(self.steps - 1, 0, n, device="cpu").round().long().unique_consecutive().tolist()

    def ddim_sample(self, model: Denoiser, shape: tuple[int, ...], *, steps: int, generator: torch.Generator,
                    eta: float = 0.0, temperature: float = 1.0,
                    device: torch.device | str | None = None) -> torch.Tensor:
        """DDIM (Song et al.) on a subsequence of timesteps; deterministic given the start noise when eta = 0.
        `temperature` scales the start noise (0: start from the mean, one path per light)."""
        x = temperature * _noise(shape, generator, device)
        ts = self.ddim_timesteps(steps)
        ab = self.alpha_bar.tolist()  # Python floats: no tensor read per step
        x0 = x
        for i, t in enumerate(ts):
            x0 = model(x, torch.full((shape[0],), t, device=device, dtype=torch.long))
            if i == len(ts) - 1:
                break
            ab_t, ab_next = ab[t], ab[ts[i + 1]]
            eps = (x - ab_t**0.5 * x0) / (1 - ab_t) ** 0.5
            sigma = eta * ((1 - ab_next) / (1 - ab_t) * (1 - ab_t / ab_next)) ** 0.5
            x = ab_next**0.5 * x0 + max(1 - ab_next - sigma**2, 0.0) ** 0.5 * eps
            if sigma > 0:
                x = x + sigma * _noise(shape, generator, device)
        # the last model call is at t = 0 (or the last step taken): its x0 is the sample
        return x0


def _noise(shape: tuple[int, ...], generator: torch.Generator, device: torch.device | str | None) -> torch.Tensor:
    """Standard normal noise drawn on the generator's device (the same numbers on every device), on `device`
    without waiting for it (`sampling.to_device`): a blocking copy at every one of DDPM's 500 steps made the host
    wait for the GPU each time."""
    draw = torch.randn(shape, generator=generator, device=generator.device)
    return draw if device is None else to_device(draw, torch.device(device))
