"""The cache's answer for a light: the diffusion model's SIREN mixed in weight space with the weight blend of the
stored SIRENs around the light (`lights.blend_weights`: by default the corners of its triangle among the training
lights, barycentric weights).

    answer(w) = share * model(w) + (1 - share) * blend(w)

Every stored SIREN is fitted from the same shared initial SIREN (`preoptimize`), so weight-space blends of them
are SIRENs that work, and so is a blend of the model's sample (which regenerates those SIRENs) with theirs. The two
answers err in different ways: the blend's error grows with the distance to the stored lights, the model's is its
capacity's. Their mix beat both on the lights between the stored ones while the blend was the 4 nearest by inverse
angle; against the triangle blend of SIRENs fitted for it, the validation lights give the model a share of 0-0.2 and
the mix ties with the blend (docs/performance.md, "The mix").
`share` 1 is the paper's model alone; 0 the stored SIRENs' blend alone (what `cache: blend` answers).

`mix.model_share: auto` chooses the share on validation lights (`lights.validation_lights`: random in the training
cap, like the unseen test set but never from it) with exact shadows: the share in `SHARES` whose mixed SIRENs
score the highest mean voxel PSNR there."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.volume import check_extinction

if TYPE_CHECKING:  # the mix imports no PyTorch itself: a blend alone needs none
    from diffshadow.diffusion.sample import ShadowSampler
    from diffshadow.store import BlendSampler

SHARES = tuple(round(0.1 * i, 1) for i in range(11))  # the model's shares tried by `choose_share`
# Weights mixed per pass: the float64 sum of a whole paper-size set at once (2,500 SIRENs of 66,689 weights) made
# three 1.3-GB temporaries, sample_shadows' peak (c2b03fd); each element's sum is the
# same in any pass, so the bytes are too
MIX_CHUNK = 1 << 22


def check_share(share: float, where: str = "mix.model_share") -> float:
    """`share` as a float in [0, 1], else one ValueError naming `where`."""
    try:
        value = float(share)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected auto or a number from 0 to 1 (the model's share), got {share!r}") from None
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{where}: expected a number from 0 to 1 (the model's share), got {share!r}")
    return value


def model_alone(share: float | str) -> bool:
    """Whether `mix.model_share` (auto or a number) is 1: the model's SIRENs answer alone, nothing is mixed in and
    no stored SIREN is read. A bad share raises `check_share`'s error."""
    return str(share) != "auto" and check_share(share) == 1.0


def mix_weights(model: np.ndarray, blend: np.ndarray, share: float) -> np.ndarray:
    """share * model + (1 - share) * blend, rows (N, n_params) of SIREN weights, summed in float64 and returned as
    float32. Share 1 returns the model's rows exactly, share 0 the blend's."""
    model = np.asarray(model)
    blend = np.asarray(blend)
    if model.shape != blend.shape:
        raise ValueError(f"mix: the model's SIRENs {model.shape} and the stored SIRENs' blend {blend.shape} differ "
                         f"in shape (a checkpoint trained on other stored SIRENs?)")
    share = check_share(share, "mix share")
    if share == 1.0:
        return model.astype(np.float32)
    if share == 0.0:
        return blend.astype(np.float32)
    m, b = model.reshape(-1), blend.reshape(-1)
    out = np.empty(m.shape, dtype=np.float32)
    for i in range(0, m.size, MIX_CHUNK):
        part = slice(i, i + MIX_CHUNK)
        out[part] = share * m[part].astype(np.float64) + (1.0 - share) * b[part].astype(np.float64)
    return out.reshape(model.shape)


def choose_share(model: np.ndarray, blend: np.ndarray, score: Callable[[np.ndarray], np.ndarray],
                 shares: tuple[float, ...] = SHARES) -> tuple[float, list[dict]]:
    """The share whose mixed SIRENs (`mix_weights`) get the highest mean of `score` (per-light voxel PSNR, (N,)) on
    the validation lights `model` and `blend` were made for; a tie goes to the larger share (the model's side).
    Returns it and the curve: per share, the mean and the median PSNR.

    The mean, not the median: on bundled nucleon, 256 validation lights, three seeds of the model, the mean's
    curve peaked at the same share for each seed and the median's did not (docs/performance.md, "The mix")."""
    curve = []
    for share in shares:
        psnr = np.asarray(score(mix_weights(model, blend, share)), dtype=np.float64)
        if not np.isfinite(psnr).all():
            raise ValueError(f"mix: share {share}: a validation light scored {psnr[~np.isfinite(psnr)][0]} dB; "
                             f"expected finite PSNRs (a diverged model or stored SIREN?)")
        curve.append({"share": float(share), "psnr_mean": float(psnr.mean()), "psnr_median": float(np.median(psnr))})
    best = max(curve, key=lambda row: (row["psnr_mean"], row["share"]))
    return best["share"], curve


class MixedSampler:
    """A light's shadow SIREN as `share` of the model's (`ShadowSampler`) plus the rest of the stored SIRENs' weight
    blend (`store.BlendSampler`): the answer `sample_shadows` stored for its lights, made for any other. The
    same interface as the two it mixes; its light region is the model's."""

    def __init__(self, model: ShadowSampler, blend: BlendSampler, share: float):
        if model.layout.n_params != blend.layout.n_params:
            raise ValueError(f"mix: the model makes SIRENs of {model.layout.n_params} parameters, the stored ones "
                             f"have {blend.layout.n_params}")
        check_extinction(blend.extinction, model.extinction, cache="mix: the stored SIRENs", scene="the model's",
                         remedy="mix the SIRENs the model was trained on")
        self.model, self.blend, self.share = model, blend, check_share(share)
        self.layout, self.siren, self.region = model.layout, model.siren, model.region
        self.extinction = model.extinction or blend.extinction

    def __call__(self, light: ArrayLike) -> np.ndarray:
        """(n_params,) float32 weights of the mixed shadow SIREN of one light direction. At share 0 (or 1) the side
        with no weight is not asked: the answer is the same bytes, and the model's DDIM is ~30 ms a light on one
        CPU thread against the blend's 0.3 ms (the validation lights chose share 0 on tooth and at 128 and 512
        lights)."""
        if self.share == 0.0:
            return np.asarray(self.blend(light), dtype=np.float32)
        if self.share == 1.0:
            return np.asarray(self.model(light), dtype=np.float32)
        own = np.asarray(self.model(light))
        return mix_weights(own[None], self.blend(light)[None], self.share)[0]
