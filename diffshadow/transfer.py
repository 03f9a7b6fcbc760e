"""Transfer functions: normalised scalar → opacity, colour, extinction.

Piecewise-linear in the scalar `s` ∈ [0, 1], clamped outside the first and last control point.
Repeated `s` values make a step. Extinction μ(s) = density_scale · opacity(s), in 1 / box-length.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    import torch

# PyTorch is imported where a TF is evaluated, not with the module: prepare_volume validates and stores a TF
# without it (diffshadow.volume's prepared store), and a run's first job starts 1.1 s (a CUDA build: 4 s) sooner

FOREGROUND_ALPHA = 1.0 / 255.0  # a pixel shows (is foreground) when its opacity shows in 8 bits


class TransferFunctionError(ValueError):
    """A malformed transfer function; the message names the key and the problem."""


def _piecewise_linear(s: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """Evaluate the polyline (xs, ys[:, c]) at s; ys is (K, C). Returns s.shape + (C,)."""
    import torch

    s = s.contiguous().clamp(xs[0], xs[-1])
    # right=True puts s exactly on a repeated x into the later segment, so steps take their upper value
    hi = torch.bucketize(s, xs, right=True).clamp(1, len(xs) - 1)
    lo = hi - 1

    # table[i] through index_select: on a CPU 3-5x faster than aten::index's gather, the same values
    def at(table: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
        return table.index_select(0, i.reshape(-1)).view(*i.shape, *table.shape[1:])

    x0, x1 = at(xs, lo), at(xs, hi)
    w = ((s - x0) / (x1 - x0).clamp_min(1e-12)).clamp(0.0, 1.0)
    y0 = at(ys, lo)
    return y0 + w.unsqueeze(-1) * (at(ys, hi) - y0)


def _as_tensor(s) -> torch.Tensor:
    import torch

    if isinstance(s, torch.Tensor):
        return s.float() if s.dtype != torch.float32 else s
    return torch.from_numpy(np.asarray(s, dtype=np.float32))  # host data stays on the host


@dataclass(frozen=True)
class TransferFunction:
    """Opacity and colour as piecewise-linear functions of the normalised scalar."""

    opacity_points: np.ndarray  # (K, 2): s, alpha
    color_points: np.ndarray  # (L, 4): s, r, g, b
    density_scale: float
    # control points as tensors per (kind, device): the marcher classifies samples every iteration
    _tensors: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def from_config(cls, d: Mapping) -> TransferFunction:
        """Build from `{"opacity": [[s, a], ...], "color": [[s, r, g, b], ...], "density_scale": k}`."""
        if not isinstance(d, Mapping):
            raise TransferFunctionError(f"transfer function: expected a mapping, got {type(d).__name__}")
        unknown = set(d) - {"opacity", "color", "density_scale"}
        if unknown:
            raise TransferFunctionError(
                f"transfer function: unknown key(s) {sorted(unknown)}; expected opacity, color, density_scale"
            )
        for key in ("opacity", "color", "density_scale"):
            if key not in d:
                raise TransferFunctionError(f"transfer function: missing key {key!r}")
        opacity = _points("opacity", d["opacity"], 2)
        color = _points("color", d["color"], 4)
        try:
            k = float(d["density_scale"])
        except (TypeError, ValueError):
            raise TransferFunctionError(
                f"transfer function: density_scale must be a number, got {d['density_scale']!r}"
            ) from None
        if not np.isfinite(k) or k < 0:
            raise TransferFunctionError(f"transfer function: density_scale must be finite and >= 0, got {k}")
        return cls(opacity, color, k)

    def require_visible(self, where: str, *, values: tuple[float, float] = (0.0, 1.0),
                        extent: ArrayLike = (1.0, 1.0, 1.0)) -> TransferFunction:
        """This TF, for a scene whose normalised grid spans `values` in a box of `extent` (by default any grid: the
        largest box, its longest side 1): refused where no ray can gather one 8-bit level of opacity
        (`FOREGROUND_ALPHA`). The renderer and the shadow math take such a TF, but a scene made of it has no visible
        pixel: every stage would succeed on nothing, or the rendering loss stop on it after stage 1's fits. The test
        is an upper bound, so a scene that shows anything passes: μ ≤ density_scale · the largest opacity over
        `values`, and no ray is longer inside the box than its diagonal (doubled for a marcher's last partial step)."""
        if not np.any(self.opacity_points[:, 1] > 0):
            raise TransferFunctionError(f"{where}: transfer function: opacity is 0 at every point, so nothing is "
                                        f"visible and there is no shadow to cache; give some scalar range an opacity "
                                        f"above 0")
        lo, hi = (float(v) for v in values)
        top = float(self.max_opacity(np.array([lo]), np.array([hi]))[0])
        if top == 0:
            raise TransferFunctionError(f"{where}: transfer function: opacity is 0 over all of the grid's values "
                                        f"({lo:g} to {hi:g}, normalised), so nothing is visible; give that range an "
                                        f"opacity")
        longest = 2.0 * float(np.linalg.norm(extent))
        most = -np.expm1(-longest * self.density_scale * top)  # the largest opacity a ray can gather
        if most < FOREGROUND_ALPHA:
            raise TransferFunctionError(
                f"{where}: transfer function: nothing can show: the densest ray through the box reaches opacity "
                f"{most:.2g} at most (one 8-bit level is {FOREGROUND_ALPHA:.2g}) under density_scale "
                f"{self.density_scale:g} and the largest opacity of its values, {top:g}; raise density_scale above "
                f"{-np.log1p(-FOREGROUND_ALPHA) / (longest * top):.4g}")
        return self

    def to_config(self) -> dict:
        """The inverse of `from_config` (plain lists, for JSON/YAML/Zarr attrs)."""
        return {
            "opacity": self.opacity_points.tolist(),
            "color": self.color_points.tolist(),
            "density_scale": self.density_scale,
        }

    def _control(self, kind: str, device) -> tuple[torch.Tensor, torch.Tensor]:
        key = (kind, str(device))
        if key not in self._tensors:
            import torch

            if kind == "optics":
                points = self._optics_points()
            else:
                points = self.opacity_points if kind == "opacity" else self.color_points
            pts = torch.as_tensor(points, dtype=torch.float32, device=device)
            self._tensors[key] = (pts[:, 0].contiguous(), pts[:, 1:].contiguous())
        return self._tensors[key]

    def _optics_points(self) -> np.ndarray:
        """(M, 5) rows s, opacity, r, g, b: both polylines on the union of their knots, so one search finds a
        sample's opacity and colour. Each function is piecewise linear between the union's knots, so this is
        exact up to float32 rounding; a step in either gives two knots at its s (left and right values)."""
        tables = [(self.opacity_points[:, 0], self.opacity_points[:, 1:]),
                  (self.color_points[:, 0], self.color_points[:, 1:])]
        rows = []
        for x in np.unique(np.concatenate([xs for xs, _ in tables])):
            left = np.concatenate([_one_side(xs, ys, x, "left") for xs, ys in tables])
            right = np.concatenate([_one_side(xs, ys, x, "right") for xs, ys in tables])
            rows += [[x, *left]] if np.array_equal(left, right) else [[x, *left], [x, *right]]
        return np.asarray(rows)

    def opacity(self, s: torch.Tensor | ArrayLike) -> torch.Tensor:
        """Opacity in [0, 1] at scalar values `s` (any shape)."""
        s = _as_tensor(s)
        return _piecewise_linear(s, *self._control("opacity", s.device)).squeeze(-1)

    def extinction(self, s: torch.Tensor | ArrayLike) -> torch.Tensor:
        """μ(s) = density_scale · opacity(s), in 1 / box-length."""
        return self.density_scale * self.opacity(s)

    def color(self, s: torch.Tensor | ArrayLike) -> torch.Tensor:
        """RGB in [0, 1]; returns s.shape + (3,)."""
        s = _as_tensor(s)
        return _piecewise_linear(s, *self._control("color", s.device))

    def optics_knots(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """`optics`' table on `device`: knots s (M,) and opacity, r, g, b at each (M, 4) (cached)."""
        return self._control("optics", device)

    def optics(self, s: torch.Tensor | ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
        """(extinction, colour) at `s` from one search of both polylines' knots: what a renderer needs per
        sample, equal to (`extinction`, `color`) up to float32 rounding."""
        s = _as_tensor(s)
        both = _piecewise_linear(s, *self.optics_knots(s.device))
        return self.density_scale * both[..., 0], both[..., 1:]

    def max_opacity(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Largest opacity over each scalar interval [lo, hi] (macro-cell bounds).

        A piecewise-linear function reaches its maximum on an interval at an end or at a control point.
        """
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        xs, ys = self.opacity_points[:, 0], self.opacity_points[:, 1]
        best = np.maximum(np.interp(lo, xs, ys), np.interp(hi, xs, ys))
        for x, y in zip(xs, ys, strict=True):
            inside = (lo <= x) & (x <= hi)
            best = np.where(inside, np.maximum(best, y), best)
        # np.interp takes the left value at a step; the right one may be larger
        for i in range(len(xs) - 1):
            if xs[i] == xs[i + 1]:
                inside = (lo <= xs[i]) & (xs[i] <= hi)
                best = np.where(inside, np.maximum(best, ys[i + 1]), best)
        return best


def _one_side(xs: np.ndarray, ys: np.ndarray, x: float, side: str) -> np.ndarray:
    """The polyline (xs, ys) at x approached from `side` ("left" or "right"), clamped outside its knots."""
    if side == "right":
        i = int(np.searchsorted(xs, x, side="right")) - 1  # the last knot at or before x
        if i < 0 or i == len(xs) - 1:
            return ys[max(i, 0)]
        j = i + 1
    else:
        j = int(np.searchsorted(xs, x, side="left"))  # the first knot at or after x
        if j == 0 or j == len(xs):
            return ys[min(j, len(xs) - 1)]
        i = j - 1
    w = (x - xs[i]) / (xs[j] - xs[i])
    return ys[i] + w * (ys[j] - ys[i])


def _points(key: str, value, width: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TransferFunctionError(f"transfer function: {key} must be a list of numbers, got {value!r}") from None
    if arr.ndim != 2 or arr.shape[1] != width:
        raise TransferFunctionError(
            f"transfer function: {key} must be a list of [{', '.join(['s'] + ['v'] * (width - 1))}] rows, "
            f"got shape {arr.shape}"
        )
    if arr.shape[0] < 2:
        raise TransferFunctionError(f"transfer function: {key} needs at least 2 points, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise TransferFunctionError(f"transfer function: {key} has non-finite values")
    outside = ((arr < 0) | (arr > 1)).any(axis=1)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise TransferFunctionError(f"transfer function: {key} values must lie in [0, 1], the position s as well as "
                                    f"the {'opacity' if width == 2 else 'r, g, b'}; point {i} is {arr[i].tolist()}")
    if np.any(np.diff(arr[:, 0]) < 0):
        raise TransferFunctionError(f"transfer function: {key} points must be sorted by s, got {arr[:, 0].tolist()}")
    return arr
