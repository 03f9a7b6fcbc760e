"""Cameras in box coordinates: a pinhole `Camera` (its rays), orbit views for evaluation and the Fibonacci
views of the rendering loss."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.lights import fibonacci_sphere
from diffshadow.sampling import visible_voxels
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume


class RenderError(ValueError):
    """Bad renderer input; the message names the argument."""


# box lengths between the eye and its target at most: the rays are float32, and at 1e3 their positions carry
# ~6e-5 of rounding, 0.5 % of nucleon's 0.5-voxel step; a 1e-6° field of view framed the volume from 2e6 away,
# and every sample fell between two floats (an empty image, silently)
MAX_EYE_DISTANCE = 1e3


def _check_view(fov: float, width: int, height: int) -> None:
    if not (0 < fov < 180):
        raise RenderError(f"camera fov: expected degrees in (0, 180), got {fov}")
    if width < 1 or height < 1:
        raise RenderError(f"camera image size: expected positive, got {width}x{height}")


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in box coordinates; `fov` is vertical, in degrees."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov: float = 60.0
    width: int = 128
    height: int = 128

    def __post_init__(self):
        _check_view(self.fov, self.width, self.height)
        forward = np.asarray(self.target, float) - np.asarray(self.eye, float)
        with np.errstate(over="ignore"):
            far = float(np.linalg.norm(forward))
        if not np.all(np.isfinite(forward)) or far == 0:
            raise RenderError(f"camera: eye {self.eye} and target {self.target} must differ and be finite")
        if not far <= MAX_EYE_DISTANCE:
            said = f"{far:.3g}" if np.isfinite(far) else "over 1e308"
            raise RenderError(f"camera: the eye is {said} box lengths from its target, past {MAX_EYE_DISTANCE:g}, "
                              f"where float32 rays no longer resolve a step; move the camera in (with the framed "
                              f"default view: widen the field of view, {self.fov:g}° now)")

    @classmethod
    def look_at(cls, eye: ArrayLike, target: ArrayLike, *, up: ArrayLike | None = None, fov: float = 60.0,
                size: int | tuple[int, int] = 128) -> Camera:
        """From `eye` toward `target`; `up` None: `default_up` of the view direction."""
        w, h = (size, size) if isinstance(size, int) else size
        if up is None:
            up = default_up(np.subtract(eye, target, dtype=float))
        return cls(tuple(map(float, eye)), tuple(map(float, target)), tuple(map(float, up)), float(fov), w, h)

    @classmethod
    def orbit(cls, extent: ArrayLike, *, azimuth: float, elevation: float, distance: float = 2.2, fov: float = 60.0,
              size: int | tuple[int, int] = 128) -> Camera:
        """Looking at the box centre from (azimuth, elevation) in degrees; `distance` in box half-diagonals."""
        if not distance > 0:  # a negative one would look from the opposite side, not the azimuth asked for
            raise RenderError(f"camera distance: expected a positive number of box half-diagonals, got {distance}")
        center = np.asarray(extent, dtype=float) / 2
        return cls._from_direction(center, distance * np.linalg.norm(center), azimuth, elevation, fov, size)

    @classmethod
    def framed(cls, sphere: tuple, *, azimuth: float = 30.0, elevation: float = 25.0, fov: float = 60.0,
               size: int | tuple[int, int] = 128, margin: float = 1.05) -> Camera:
        """Looking from (azimuth, elevation) at the centre of `sphere` ((centre, radius): around the visible part
        of a volume, `visible_sphere`), from where it just fits the narrower of the view's two angles (times
        `margin`): the default view of `render`, the viewer and the report's images. The box-based `orbit` shows
        a sparse volume small (nucleon: 9 % of the viewer's canvas)."""
        center, radius = np.asarray(sphere[0], dtype=float), max(float(sphere[1]), 1e-6)
        w, h = (size, size) if isinstance(size, int) else size
        _check_view(fov, w, h)  # before the distance, which divides by both
        half_v = math.radians(fov) / 2
        half = min(half_v, math.atan(math.tan(half_v) * w / h))
        return cls._from_direction(center, margin * radius / math.sin(half), azimuth, elevation, fov, size)

    @classmethod
    def _from_direction(cls, center: np.ndarray, distance: float, azimuth: float, elevation: float, fov: float,
                        size: int | tuple[int, int]) -> Camera:
        """Looking at `center` from `distance` away toward (azimuth, elevation) in degrees, z up."""
        if not math.isfinite(azimuth):
            raise RenderError(f"camera azimuth: expected finite degrees, got {azimuth}")
        if not -90 <= elevation <= 90:  # past a pole the orbit would look from azimuth + 180, upside down
            raise RenderError(f"camera elevation: expected degrees in [-90, 90], got {elevation}")
        az, el = math.radians(azimuth), math.radians(elevation)
        direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        return cls.look_at(center + distance * direction, center, up=default_up(direction), fov=fov, size=size)

    def rays(self, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """Origins and unit directions (H·W, 3), row 0 at the top of the image."""
        eye = np.asarray(self.eye, float)
        fwd = np.asarray(self.target, float) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(self.up, float))
        if np.linalg.norm(right) < 1e-9:
            raise RenderError(f"camera: up {self.up} is parallel to the view direction")
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        half_h = math.tan(math.radians(self.fov) / 2)
        half_w = half_h * self.width / self.height
        # per pixel on the device, in float64 like the camera frame: made on the host, the directions of a 1024²
        # image took 42 ms here (numpy) and a copy, a third of a GPU frame. The frame's four vectors go over in
        # one copy: on a GPU each tensor built from host numbers is a copy the host waits for
        f64 = {"dtype": torch.float64, "device": device}
        u = ((torch.arange(self.width, **f64) + 0.5) / self.width * 2 - 1) * half_w
        v = (1 - (torch.arange(self.height, **f64) + 0.5) / self.height * 2) * half_h
        eye_t, fwd_t, right_t, up_t = torch.as_tensor(np.stack([eye, fwd, right, up]), **f64)
        d = fwd_t + u[None, :, None] * right_t + v[:, None, None] * up_t
        d = d / (d * d).sum(-1, keepdim=True).sqrt()
        dirs = d.reshape(-1, 3).to(torch.float32)
        origins = eye_t.to(torch.float32).expand_as(dirs).contiguous()
        return origins, dirs


def default_views(sphere: tuple, n: int, *, size: int = 128, elevation: float = 25.0,
                  fov: float = 60.0) -> list[Camera]:
    """`n` cameras evenly spaced in azimuth, each framing `sphere` (`Camera.framed`): the evaluation's views."""
    return [Camera.framed(sphere, azimuth=30.0 + 360.0 * i / n, elevation=elevation, fov=fov, size=size)
            for i in range(n)]


def visible_sphere(volume: Volume, tf: TransferFunction) -> tuple[np.ndarray, float]:
    """(centre, radius) in box coordinates of the smallest sphere about the visible voxels' bounding-box centre
    that holds them all (opacity > 0), widened by a voxel; the box's own where none is visible."""
    extent, voxel = np.asarray(volume.extent, float), np.asarray(volume.voxel_size, float)

    def visible_xyz():  # box coordinates, a slab at a time (`sampling.visible_voxels`)
        return (zyx.flip(1).numpy().astype(float) * voxel for zyx in visible_voxels(volume, tf) if len(zyx))

    # two passes (the box, then the farthest voxel from its centre): every visible voxel's coordinates at once, with
    # the TF over the whole grid, were 9.3 GiB on a 512³ volume; the same numbers
    lo = hi = None
    for xyz in visible_xyz():
        lo = xyz.min(0) if lo is None else np.minimum(lo, xyz.min(0))
        hi = xyz.max(0) if hi is None else np.maximum(hi, xyz.max(0))
    if lo is None:
        return extent / 2, float(np.linalg.norm(extent)) / 2
    center = (lo + hi) / 2
    farthest = max(((xyz - center) ** 2).sum(1).max() for xyz in visible_xyz())
    return center, float(np.sqrt(farthest)) + float(np.linalg.norm(voxel))


def default_up(direction: ArrayLike) -> tuple[float, float, float]:
    """+z, unless `direction` (from the target to the eye, any length) is within ~2.6° of the z axis: then +y."""
    d = np.asarray(direction, float)
    n = np.linalg.norm(d)
    return (0.0, 0.0, 1.0) if n == 0 or abs(d[2]) < 0.999 * n else (0.0, 1.0, 0.0)


def fibonacci_views(extent: ArrayLike, n: int, *, size: int, fov: float = 60.0, distance: float = 2.2) -> list[Camera]:
    """`n` cameras on a Fibonacci sphere around the box, looking at its centre (the authors' views)."""
    extent = np.asarray(extent, dtype=float)
    center = extent / 2
    out = []
    for d in fibonacci_sphere(n) if n > 1 else np.array([[0.6, 0.6, 0.52915026]]):
        out.append(Camera.look_at(center + distance * np.linalg.norm(center) * d, center, up=default_up(d), fov=fov,
                                  size=size))
    return out
