"""The blend's correction: a light-conditioned network that corrects the stored SIRENs' weight blend between the
training lights (docs/design.md, "The blend's correction").

A new light's SIREN is the triangle blend of the stored SIRENs (`lights.blend_weights`). Stage 1 fits the SIRENs so
that such blends are good (its blend loss), but a blend of three SIRENs is linear in their weights and the shadow
is not linear in the light: between the training lights the blend lies 3-7 dB under what a training light's own
SIREN scores. The correction adds, for light l with blend weights w_i(l) at corners l_i,

    delta(l) = sigma * (net(l) - sum_i w_i(l) net(l_i)),

with `net` a small MLP of the light's NeRF encoding and `sigma` each weight's spread over the stored SIRENs. The
second term is the correction's own blend at the corners, so delta vanishes at every training light (its answer
stays its stored SIREN, to the bit) and moves continuously with the light, as the blend's weights do. The network
is fitted by the geometry loss alone: the corrected SIRENs of random lights in the training cap against their
exact shadows at random points, half in the box and half around visible voxels (box points alone fitted the
empty box and left the visible shadows, which the images show, as they were: tooth -0.47 dB there).

The fit checks itself on `held_out` lights of its own stream, never fitted on: the plain and the corrected blend
at their exact shadows, at each log line. Where at the end a sign test does not find the corrected blend better
at one point set at least, or finds it worse at one, the correction is declined: its file records the check, and
the plain blend answers (`load_correction` gives None).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from diffshadow.adam import Adam, set_lr
from diffshadow.config import ConfigError, section
from diffshadow.diffusion.model import light_encoding
from diffshadow.io import atomic_torch_save, resume
from diffshadow.layout import SirenConfig, WeightLayout
from diffshadow.lights import PoolLights, blend_weights, unseen_directions
from diffshadow.metrics import psnr
from diffshadow.progress import eta
from diffshadow.sampling import CORRECTION_HELD_OUT_SEED, LightStream, seeded, to_device
from diffshadow.siren import BatchedSiren, box_to_siren
from diffshadow.stopping import stop_signals
from diffshadow.store import WeightStore
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

CHUNK_LIGHTS = 64  # the exact shadows are marched this many lights at a time, each chunk at points of its own
SIGN_TEST_ALPHA = 0.05  # the held-out check's one-sided sign test: a gain or a loss counts where chance gives it < 5 %
MIN_HELD_OUT = 5  # the fewest held-out lights on which that test can find anything (1/32 < 0.05)


class CorrectionError(ValueError):
    pass


@dataclass(frozen=True)
class CorrectionConfig:
    steps: int  # 0: no correction (the plain blend answers)
    lights: int  # exact-shadow lights in the training cap that the network is fitted on
    points: int  # exact-shadow points per light in each set: the box, and around visible voxels
    batch_lights: int  # lights per step
    batch_points: int  # points per light per step
    visible_fraction: float  # the share of a step's points from the visible set (the rest from the box)
    hidden: int  # the MLP's width (two hidden layers)
    light_freqs: int  # NeRF encoding of the direction: sin/cos(2^k pi w), k < light_freqs
    lr: float  # Adam, cosine decay to 0
    seed: int
    held_out: int  # lights of its own stream the fit is checked on (0: none, and the correction is always kept)

    def __post_init__(self):
        for key in ("steps", "lights", "points", "batch_lights", "batch_points", "hidden", "light_freqs",
                    "held_out"):
            if getattr(self, key) < 0:
                raise ConfigError(f"correction.{key}: expected 0 or more, got {getattr(self, key)}")
        if self.steps and (self.lights < 1 or self.points < 1 or self.batch_lights < 1 or self.batch_points < 1
                           or self.hidden < 1):
            raise ConfigError("correction: lights, points, batch_lights, batch_points and hidden must be at least 1 "
                              "when steps is over 0")
        if not 0 <= self.visible_fraction <= 1:
            raise ConfigError(f"correction.visible_fraction: expected 0 to 1, got {self.visible_fraction}")
        if self.steps and 0 < self.held_out < MIN_HELD_OUT:
            raise ConfigError(f"correction.held_out: expected 0 (no check) or at least {MIN_HELD_OUT}, got "
                              f"{self.held_out}: on fewer lights the check's sign test can find nothing")
        if self.steps and self.batch_points > 2 * self.points:
            raise ConfigError(f"correction.batch_points ({self.batch_points}) is more than twice correction.points "
                              f"({self.points}), the points each light has in its two sets")

    @classmethod
    def from_config(cls, d: dict | None = None) -> CorrectionConfig:
        """defaults.yaml's `correction` section overridden by `d`."""
        return section(cls, "correction", d)


def corner_rows(idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The training lights that blends with corners `idx` (Q, k, on the CPU) use, once each in ascending order, and
    where each corner sits among them (Q, k). Made by numpy on the host: on a GPU, torch.unique's size is a wait for
    the device, one a step."""
    used, where = np.unique(idx.numpy(), return_inverse=True)
    return torch.from_numpy(used), torch.from_numpy(where.reshape(idx.shape))


def corrected_delta(net: torch.nn.Sequential, features: torch.Tensor, corner_features: torch.Tensor,
                    used: torch.Tensor, where: torch.Tensor, mix: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """sigma * (net(l) - sum_i w_i net(l_i)) for lights of `features` (Q, F) whose blends take the training lights
    `used[where]` (`corner_rows`: (Q, k)) with weights `mix` (Q, k); `corner_features` (N, F) of every training
    light, of which only those used are evaluated (at the paper's 2,000 lights all of them would be a 2,000-row
    output a call). The last layer is linear, so it is applied once to the hidden features' difference,
    W (h(l) - sum_i w_i h(l_i)) + b (1 - sum_i w_i): one row a light through the widest product (hidden x the
    SIREN's weights), not one for the light and one for each corner (a step at config/paper.yaml's sizes 0.6x the
    time, docs/performance.md)."""
    body, last = net[:-1], net[-1]
    at = body(corner_features[used])
    # index_select, not at[where]: its backward adds the rows in index order on any thread count, where indexing's
    # accumulating index_put splits them between threads (docs/numerics.md, defect 12)
    corners = at.index_select(0, where.reshape(-1)).view(*where.shape, -1)
    return sigma * (last(body(features) - (corners * mix[..., None]).sum(1)) - last.bias * mix.sum(1, keepdim=True))


def make_net(n_params: int, hidden: int, light_freqs: int) -> torch.nn.Sequential:
    """The MLP, its last layer zero: an untrained correction is none."""
    net = torch.nn.Sequential(torch.nn.Linear(3 + 6 * light_freqs, hidden), torch.nn.SiLU(),
                              torch.nn.Linear(hidden, hidden), torch.nn.SiLU(), torch.nn.Linear(hidden, n_params))
    torch.nn.init.zeros_(net[-1].weight)
    torch.nn.init.zeros_(net[-1].bias)
    return net


class BlendCorrection:
    """delta(l) for the stored SIRENs it was fitted to (module docstring): `net`, `sigma` (n_params,) and the
    training lights (N, 3) whose corner terms it subtracts."""

    def __init__(self, net: torch.nn.Sequential, sigma: torch.Tensor, train: np.ndarray, light_freqs: int,
                 record: dict | None = None):
        self.net, self.sigma, self.light_freqs = net.requires_grad_(False).eval(), sigma.float(), light_freqs
        self.train = np.asarray(train, dtype=np.float64)
        self._corners = self._features(self.train)  # every call's corner terms read these rows
        self.record = record or {}
        self.path: Path | None = None  # the file it was read from (load_correction)

    def _features(self, lights: np.ndarray) -> torch.Tensor:
        return light_encoding(torch.as_tensor(np.asarray(lights, dtype=np.float64), dtype=torch.float32),
                              self.light_freqs)

    def delta(self, lights: np.ndarray, idx: np.ndarray, mix: np.ndarray) -> np.ndarray:
        """(Q, n_params) float64: the correction of the blends (`idx`, `mix`: their corners and weights) of
        `lights` (Q, 3)."""
        if len(lights) == 0:
            return np.zeros((0, len(self.sigma)))
        # on one thread: MKL rounded a small product (the corners' first layer, 4 x 21 by 21 x 16) by the thread
        # count on an AMD EPYC even in its strict mode, so a -j1 and a -j2 run blended other bytes (docs/numerics.md,
        # defect 14); these products are small, one thread costs little
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with torch.no_grad():
                d = corrected_delta(self.net, self._features(lights), self._corners,
                                    *corner_rows(torch.as_tensor(idx)), torch.as_tensor(mix, dtype=torch.float32),
                                    self.sigma)
                return d.double().numpy()
        finally:
            torch.set_num_threads(threads)

    @property
    def declined(self) -> bool:
        """Its fit's held-out check found it no better than the plain blend (module docstring)."""
        return (self.record.get("held_out") or {}).get("kept") is False

    def check_weighting(self, weighting: str) -> None:
        """Refuse, in one line, blends weighted otherwise than those it was fitted to correct."""
        fitted = self.record.get("blend_weights")
        if fitted is not None and fitted != weighting:
            raise CorrectionError(f"{self.path or 'the blend correction'}: fitted for {fitted} blends, asked to "
                                  f"correct {weighting} ones; rerun fit_correction with this evaluate.blend_weights")

    @property
    def nbytes(self) -> int:
        """What it adds to a cache: its network and scales in float32."""
        return 4 * (sum(p.numel() for p in self.net.parameters()) + len(self.sigma))

    def state(self) -> dict:
        return {"net": self.net.state_dict(), "sigma": self.sigma, "train_lights": self.train.tolist(),
                "light_freqs": self.light_freqs, "hidden": self.net[0].out_features, "record": self.record}

    @classmethod
    def from_state(cls, state: dict) -> BlendCorrection:
        net = make_net(len(state["sigma"]), int(state["hidden"]), int(state["light_freqs"]))
        net.load_state_dict(state["net"])
        return cls(net, state["sigma"], np.asarray(state["train_lights"]), int(state["light_freqs"]),
                   state.get("record"))


def save_correction(path: str | Path, correction: BlendCorrection) -> None:
    atomic_torch_save(path, correction.state())


def weights_digest(weights: np.ndarray) -> str:
    """What a correction was fitted to: the stored SIRENs' float32 bytes, hashed."""
    return hashlib.sha256(np.ascontiguousarray(weights, dtype=np.float32).tobytes()).hexdigest()


def load_correction(path: str | Path, train: np.ndarray | None = None,
                    weights: np.ndarray | None = None) -> BlendCorrection | None:
    """The correction in `path`, or None where its fit declined it (the plain blend answers); with `train` (and
    `weights`), checked to be fitted for those training lights (and those stored SIRENs), one line if not."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
        correction = BlendCorrection.from_state(state)
    except FileNotFoundError:
        raise CorrectionError(f"{path}: no such file (made by the rule `fit_correction`)") from None
    except Exception as e:  # a truncated or foreign file: torch and the state dict raise many kinds
        raise CorrectionError(f"{path}: not a blend correction ({type(e).__name__}: {e}); "
                              f"rerun fit_correction") from None
    correction.path = Path(path)
    if train is not None:
        train = np.asarray(train, dtype=np.float64)
        if train.shape != correction.train.shape or not np.allclose(train, correction.train):
            raise CorrectionError(f"{path}: fitted for other training lights ({len(correction.train)}) than the "
                                  f"stored SIRENs' ({len(train)}); rerun fit_correction")
    made_for = correction.record.get("weights_sha256")
    if weights is not None and made_for is not None and made_for != weights_digest(weights):
        raise CorrectionError(f"{path}: fitted for other stored SIRENs than these (stage 1 was refitted since); "
                              f"rerun fit_correction")
    return None if correction.declined else correction


def fit_check(path: str | Path) -> dict | None:
    """The held-out check (`held_out_check`'s record) that the fit of the correction in `path` made, whether it
    kept the correction or declined it; None where it made none (`correction.held_out: 0`). Read after
    `load_correction`, which says in one line what is wrong with a file."""
    state = torch.load(path, map_location="cpu", weights_only=False)
    return (state.get("record") or {}).get("held_out")


@dataclass
class CorrectionLights:
    """The lights the correction is fitted on, as pool lights (`lights.PoolLights`: directions, exact shadows at
    their points, their blends' corners and weights), each chunk of CHUNK_LIGHTS lights at points of its own: a
    light's first `box` points in the box, the rest around visible voxels (none where the transfer function shows
    nothing)."""
    pool: PoolLights
    extent: torch.Tensor
    box: int


def draw_points(box: int, total: int, cfg: CorrectionConfig, gen: torch.Generator) -> torch.Tensor:
    """One step's (batch_lights, batch_points) picks among a light's points: `visible_fraction` of them from its
    visible ones (rows `box` to `total`), the rest from its box ones (all from the box where none is visible)."""
    n_vis = round(cfg.batch_points * cfg.visible_fraction) if total > box else 0
    shape = (cfg.batch_lights,)
    picks = [torch.randint(0, box, (*shape, cfg.batch_points - n_vis), generator=gen)]
    if n_vis:
        picks.append(torch.randint(box, total, (*shape, n_vis), generator=gen))
    return torch.cat(picks, dim=1)


def correction_lights(volume: Volume, tf: TransferFunction, train: np.ndarray, lights: np.ndarray,
                      cfg: CorrectionConfig, *, k: int, weighting: str, point_seed: int,
                      between_steps: Callable[[], None] | None = None) -> CorrectionLights:
    """`lights` (L, 3) with exact shadows at `cfg.points` box points and as many around visible voxels each
    (eval_truth's march), each chunk of CHUNK_LIGHTS at points of its own (seed `point_seed` + the chunk's first
    row), and their blends of the training lights `train`."""
    from diffshadow.truth import EvalTruth

    points, values = [], []
    for c in range(0, len(lights), CHUNK_LIGHTS):
        part = lights[c:c + CHUNK_LIGHTS]
        truth = EvalTruth.compute(volume, tf, part, cfg.points, point_seed + c)
        sets = [k for k in ("box", "visible") if k in truth.points]
        points.append(torch.cat([truth.points[k] for k in sets])[None].expand(len(part), -1, -1))
        values.append(torch.cat([truth.values[k] for k in sets], dim=1))
        if between_steps is not None:
            between_steps()
    idx, mix = blend_weights(train, lights, k, weighting)
    pool = PoolLights(torch.as_tensor(lights), torch.cat(points).contiguous(), torch.cat(values),
                      torch.as_tensor(idx), torch.as_tensor(mix, dtype=torch.float32))
    return CorrectionLights(pool, truth.extent, cfg.points)


def held_out_psnr(lights: CorrectionLights, x: torch.Tensor, layout: WeightLayout,
                  siren: SirenConfig) -> dict[str, torch.Tensor]:
    """Per-light PSNR (float64) of the SIRENs `x` (L, n_params) at `lights`' exact shadows, per point set (box,
    and visible where there is any)."""
    with torch.no_grad():
        pred = BatchedSiren(x, layout, siren.blocks)(box_to_siren(lights.pool.points, lights.extent))
    sets = {"box": slice(0, lights.box)}
    if lights.pool.points.shape[1] > lights.box:
        sets["visible"] = slice(lights.box, None)
    return {key: psnr(pred[:, at], lights.pool.values[:, at], dim=1) for key, at in sets.items()}


def sign_test_count(n: int, alpha: float = SIGN_TEST_ALPHA) -> int:
    """The fewest of `n` lights on which one blend must beat the other for chance alone (each light a fair coin)
    to give as many or more with probability at most `alpha`; n + 1 where no count does."""
    tail = 0.0
    for k in range(n, -1, -1):
        tail += math.comb(n, k) / 2**n
        if tail > alpha:
            break
    return k + 1


def held_out_check(plain: dict[str, torch.Tensor], corrected: dict[str, torch.Tensor]) -> dict:
    """The record of the check: per point set the plain and the corrected blend's median PSNR and on how many
    lights the corrected one is better and worse. `kept` where a sign test (`sign_test_count`: 40 of 64) finds it
    better at one set at least and worse at none: a median's move of a few hundredths of a dB is no finding (the
    README run's correction is better on 62 and 64 of 64; neghip's on 43 at box points and a coin's 30 at visible
    ones, its medians there 41.14 against 41.15 dB)."""
    n = len(next(iter(plain.values())))
    out: dict = {"lights": n, "significant": sign_test_count(n)}
    for key in plain:
        out[key] = {"plain_psnr_median": float(plain[key].median()),
                    "corrected_psnr_median": float(corrected[key].median()),
                    "better": int((corrected[key] > plain[key]).sum()),
                    "worse": int((corrected[key] < plain[key]).sum())}
    sets = [out[key] for key in plain]
    out["kept"] = (any(s["better"] >= out["significant"] for s in sets)
                   and all(s["worse"] < out["significant"] for s in sets))
    return out


def check_words(check: dict) -> str:
    """"box 50.12 dB (plain 49.03, better on 60 of 64), visible ..." for a log line."""
    return ", ".join(f"{key} {c['corrected_psnr_median']:.2f} dB (plain {c['plain_psnr_median']:.2f}, better on "
                     f"{c['better']} of {check['lights']})" for key in ("box", "visible") if (c := check.get(key)))


class CorrectionFit:
    """The correction's fit a step at a time (`fit_correction` drives it, `bench stages` times its step): the
    network, Adam and the draws' generator on `device`, fitted to `data` (`CorrectionLights`) as corrections of
    the blends of `weights` (N, n_params) at the training lights `train`. A step reads nothing from the device:
    its draws, and the corners its blends use, are made on the host."""

    def __init__(self, weights: torch.Tensor, data: CorrectionLights, train: np.ndarray, layout: WeightLayout,
                 siren: SirenConfig, cfg: CorrectionConfig, device: torch.device | str = "cpu",
                 held: CorrectionLights | None = None):
        self.cfg, self.layout, self.siren, self.device = cfg, layout, siren, torch.device(device)
        self.box, self.host_neighbours = data.box, data.pool.neighbours
        self.stored = weights.to(self.device)
        self.sigma = (weights.std(0) + 1e-6).to(self.device)  # its scale per weight: the stored SIRENs' spread
        self.pool, self.extent = data.pool.to(self.device), data.extent.to(self.device)
        torch.manual_seed(cfg.seed)
        self.net = make_net(weights.shape[1], cfg.hidden, cfg.light_freqs).to(self.device)
        self.features = light_encoding(self.pool.lights.float(), cfg.light_freqs)
        self.corners = light_encoding(torch.as_tensor(np.asarray(train, dtype=np.float64), dtype=torch.float32),
                                      cfg.light_freqs).to(self.device)
        self.opt = Adam(self.net.parameters(), cfg.lr)
        self.gen = seeded(cfg.seed, LightStream.CORRECTION)
        self.held = None
        if held is not None:  # what the check reads at every log line, made once: its lights, corners and plain blend
            corners = tuple(t.to(self.device) for t in corner_rows(held.pool.neighbours))
            held = CorrectionLights(held.pool.to(self.device), held.extent.to(self.device), held.box)
            x0 = held.pool.x0(self.stored, torch.arange(len(held.pool.lights), device=self.device))
            self.held = (held, x0, light_encoding(held.pool.lights.float(), cfg.light_freqs), corners,
                         held_out_psnr(held, x0, layout, siren))

    def step(self, step: int) -> torch.Tensor:
        """Adam step `step` of `cfg.steps` (cosine decay); its loss, on the device."""
        cfg, device = self.cfg, self.device
        set_lr(self.opt, cfg.lr * 0.5 * (1 + math.cos(math.pi * step / cfg.steps)))
        j_host = torch.randint(0, len(self.host_neighbours), (cfg.batch_lights,), generator=self.gen)
        pick = to_device(draw_points(self.box, self.pool.points.shape[1], cfg, self.gen), device)
        used, where = (to_device(t, device) for t in corner_rows(self.host_neighbours[j_host]))
        j = to_device(j_host, device)
        delta = corrected_delta(self.net, self.features[j], self.corners, used, where, self.pool.blend[j], self.sigma)
        # the step's blends made here, not all lights' at once (4,096 x the SIREN's weights: 1.1 GB at the paper's)
        pts, truth = self.pool.samples(j, pick)
        pred = BatchedSiren(self.pool.x0(self.stored, j) + delta, self.layout, self.siren.blocks)(
            box_to_siren(pts, self.extent))
        loss = ((pred - truth) ** 2).mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return loss.detach()

    def check(self) -> dict | None:
        """The held-out check (`held_out_check`) of the network as it stands against the plain blend at the held-out
        lights; None without them. No gradient and no draw: it changes no byte of the fit."""
        if self.held is None:
            return None
        held, x0, features, (used, where), plain = self.held
        with torch.no_grad():
            delta = corrected_delta(self.net, features, self.corners, used, where, held.pool.blend, self.sigma)
        return held_out_check(plain, held_out_psnr(held, x0 + delta, self.layout, self.siren))


def fit_correction(store: WeightStore, volume: Volume, tf: TransferFunction, train: np.ndarray, center: np.ndarray,
                   cfg: CorrectionConfig, *, k: int, weighting: str, device: torch.device | str = "cpu",
                   log: Callable[[str], None] = print, between_steps: Callable[[], None] | None = None,
                   checkpoint: Path | None = None, stop_after_step: int | None = None) -> BlendCorrection:
    """Fit the correction of `store`'s blends (`weighting`, `k`; its SIRENs at the training lights `train`) on
    `cfg.lights` exact-shadow lights of the training cap (marched on the CPU), `cfg.steps` Adam steps with a
    cosine decay on `device`; the correction comes back on the CPU. `between_steps` is called after each chunk
    of the march and each step (runtime.SpareThreads.poll: the threads change no byte). With `checkpoint` it
    saves there at every log line and on SIGTERM / SIGINT, and resumes from it (the march is made again: it is
    deterministic); `stop_after_step` stops there as a kill would (tests use it). With `cfg.held_out` it checks
    itself on that many lights it never fits (module docstring) and records the check (`record["held_out"]`,
    `held_out_check`), declined where it does not find the corrected blend better."""
    if cfg.steps < 1:
        raise CorrectionError("correction.steps is 0: there is no correction to fit")
    device = torch.device(device)
    weights = torch.as_tensor(np.asarray(store.weights, dtype=np.float32))
    digest = weights_digest(store.weights)
    fingerprint = hashlib.sha256(json.dumps([asdict(cfg), k, weighting, digest, store.extinction,
                                             np.asarray(train, dtype=np.float64).tolist()]).encode()).hexdigest()
    t0 = time.perf_counter()
    # the fitted lights (never a test, validation or pool light) and the held-out ones, each from its own stream
    fitted = unseen_directions(train, center, cfg.lights, seed=[cfg.seed, LightStream.CORRECTION])
    data = correction_lights(volume, tf, train, fitted, cfg, k=k, weighting=weighting, point_seed=cfg.seed,
                             between_steps=between_steps)
    held = None
    if cfg.held_out:
        extra = cfg.seed + CORRECTION_HELD_OUT_SEED
        held = correction_lights(volume, tf, train, unseen_directions(train, center, cfg.held_out,
                                                                      seed=[extra, LightStream.CORRECTION]),
                                 cfg, k=k, weighting=weighting, point_seed=extra, between_steps=between_steps)
    log(f"correction: exact shadows of {cfg.lights} lights (and {cfg.held_out} held out) at {cfg.points} points "
        f"each in the box and around visible voxels ({time.perf_counter() - t0:.1f} s)")
    fit = CorrectionFit(weights, data, train, store.layout, store.siren, cfg, device, held)
    t0, window, start = time.perf_counter(), [], 0
    log(f"correction: an MLP of {sum(p.numel() for p in fit.net.parameters()):,} parameters (width {cfg.hidden}) "
        f"fitted for {cfg.steps} steps of {cfg.batch_lights} lights x {cfg.batch_points} points on {device}")
    if state := resume(checkpoint, fingerprint, log=log, map_location=device):
        fit.net.load_state_dict(state["net"])
        fit.opt.load_state_dict(state["optimizer"])
        fit.gen.set_state(state["generator"])
        start = int(state["step"])
        log(f"resuming from {checkpoint} at step {start}/{cfg.steps}")
    every = max(1, cfg.steps // 10)
    with stop_signals(checkpoint is not None) as stop:
        for step in range(start, cfg.steps):
            window.append(fit.step(step))
            if between_steps is not None:
                between_steps()
            done = step + 1
            if done % every == 0 or done == cfg.steps:
                mse = float(torch.stack(window).mean())
                window.clear()
                if not math.isfinite(mse):
                    raise CorrectionError(f"correction: the loss became {mse} at step {done}; lower correction.lr "
                                          f"(now {cfg.lr})")
                said = fit.check()
                held_words = f"  held out: {check_words(said)}" if said else ""
                log(f"step {done}/{cfg.steps}  geometry {mse:.3e} ({-10 * math.log10(max(mse, 1e-30)):.1f} dB)"
                    f"{held_words}  {eta(done, cfg.steps, t0, start=start)}")
            stopping = (stop.requested or done == stop_after_step) and done < cfg.steps
            if checkpoint is not None and (done % every == 0 and done < cfg.steps or stopping):
                atomic_torch_save(checkpoint, {"fingerprint": fingerprint, "step": done, "net": fit.net.state_dict(),
                                               "optimizer": fit.opt.state_dict(), "generator": fit.gen.get_state()})
            if stopping:
                raise stop.stopped(f"at step {done}/{cfg.steps}", checkpoint)
    if checkpoint is not None and checkpoint.exists():
        checkpoint.unlink()
    record = {"config": asdict(cfg), "blend_k": k, "blend_weights": weighting, "weights_sha256": digest,
              "extinction": store.extinction}
    if (said := fit.check()) is not None:
        record["held_out"] = said
        log(f"held out, {cfg.held_out} lights: the corrected blend {check_words(said)}: "
            + ("kept" if said["kept"] else f"declined, not better on {said['significant']} of them at one point set "
               f"and worse at none (a sign test at {SIGN_TEST_ALPHA:.0%}): the plain blend answers"))
    return BlendCorrection(fit.net.cpu(), fit.sigma.cpu(), train, cfg.light_freqs, record)
