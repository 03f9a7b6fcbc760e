"""Ray bundles for the rendering loss (paper §3.3): per view, the light-independent samples of each foreground
pixel with their weight × colour, so a pixel's colour under any shadow is one weighted sum (`bundle_colors`),
and the `gt` target images they are compared to."""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from diffshadow.grid import ray_span
from diffshadow.io import atomic_torch_save, resume
from diffshadow.progress import eta
from diffshadow.render.camera import Camera
from diffshadow.render.fields import GridScalar
from diffshadow.render.marcher import BACKGROUND, front_to_back
from diffshadow.render.scene import KEEP_SAMPLES_BYTES, RenderScene
from diffshadow.transfer import FOREGROUND_ALPHA, TransferFunction
from diffshadow.volume import Volume

TARGETS_CHECKPOINT_S = 300.0  # seconds of rendering between saves: a preempted job loses at most this much


@dataclass
class RayBundle:
    """Per view: foreground pixel ids (V, F), their samples (V, F, N, 3) with weights w·c (V, F, N, 3)
    (zero-padded), the background term T·bg (V, F, 3) and the number of foreground pixels (V,)."""

    pix: torch.Tensor
    pts: torch.Tensor
    wc: torch.Tensor
    base: torch.Tensor
    count: torch.Tensor

    def to(self, device: torch.device | str) -> RayBundle:
        return RayBundle(*(t.to(device) for t in (self.pix, self.pts, self.wc, self.base, self.count)))


def foreground(images: torch.Tensor, bundle: RayBundle) -> torch.Tensor:
    """The target images (L, V, H·W, 3) at each view's foreground pixels, in the bundle's row order: (L, V, F, 3),
    F the bundle's width (rows past a view's count hold pixel 0's colour, never read). Fine-tuning reads no other
    pixel, and at the paper's 7 views of 128² about one pixel in eight is foreground (nucleon): the whole images
    held 2.6 GiB in every process and on every GPU."""
    views = torch.arange(images.shape[1])[:, None]
    return images[:, views, bundle.pix.to(images.device)]


def view_samples(volume: Volume, tf: TransferFunction, camera: Camera, *, step: float,
                 background: float = BACKGROUND, min_weight: float = 1e-6,
                 chunk: int = 4096) -> tuple[list[int], list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """One view's foreground pixels and their light-independent samples (see the module docstring)."""
    scalar = GridScalar(volume)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    dt = step * float(np.min(volume.voxel_size))
    o, d = camera.rays()
    pix_all, pts_all, wc_all, base_all = [], [], [], []
    for r0 in range(0, len(o), chunk):
        oc, dc = o[r0:r0 + chunk], d[r0:r0 + chunk]
        t0, t1 = ray_span(oc, dc, extent)
        n = int(torch.ceil(((t1 - t0).clamp_min(0) / dt).max()).item()) + 1 if bool((t0 < t1).any()) else 1
        t = t0[:, None] + (torch.arange(n) + 0.5) * dt
        valid = t < t1[:, None]
        pts = oc[:, None] + t[..., None] * dc[:, None]
        alpha = torch.zeros(valid.shape)
        color = torch.zeros(*valid.shape, 3)
        s = scalar.value(pts[valid])
        alpha[valid] = 1 - torch.exp(-tf.extinction(s) * dt)
        color[valid] = tf.color(s)
        w, trans = front_to_back(alpha)
        fg = (1 - trans) >= FOREGROUND_ALPHA
        for i in torch.nonzero(fg).flatten().tolist():
            keep = w[i] > min_weight
            pix_all.append(r0 + i)
            pts_all.append(pts[i][keep])
            wc_all.append(w[i][keep, None] * color[i][keep])
            base_all.append(trans[i] * background * torch.ones(3))
    return pix_all, pts_all, wc_all, base_all


def build_bundle(volume: Volume, tf: TransferFunction, cameras: list[Camera], *, step: float,
                 background: float = BACKGROUND) -> RayBundle:
    views = [view_samples(volume, tf, cam, step=step, background=background) for cam in cameras]
    for v, (pix_v, *_rest) in enumerate(views):
        if not pix_v:
            raise ValueError(f"finetune view {v} (eye {np.round(cameras[v].eye, 3).tolist()}) shows no foreground "
                             f"pixel: the volume is invisible under this TF, or the camera misses it")
    f = max(1, max(len(v[0]) for v in views))
    n = max(1, max((len(p) for v in views for p in v[1]), default=1))
    nv = len(cameras)
    pix = torch.zeros(nv, f, dtype=torch.long)
    pts = torch.zeros(nv, f, n, 3)
    wc = torch.zeros(nv, f, n, 3)
    base = torch.zeros(nv, f, 3)
    count = torch.zeros(nv, dtype=torch.long)
    for v, (pv, ptv, wcv, bv) in enumerate(views):
        count[v] = len(pv)
        for j, (p, q, c, b) in enumerate(zip(pv, ptv, wcv, bv, strict=True)):
            pix[v, j] = p
            pts[v, j, :len(q)] = q
            wc[v, j, :len(c)] = c
            base[v, j] = b
    return RayBundle(pix, pts, wc, base, count)


def bundle_colors(bundle: RayBundle, g: torch.Tensor, view_idx: torch.Tensor, pix_idx: torch.Tensor) -> torch.Tensor:
    """Pixel colours (..., 3) from shadow values g (..., N) at the samples of the chosen pixels."""
    wc = bundle.wc[view_idx, pix_idx]
    return bundle.base[view_idx, pix_idx] + (wc * (0.1 + 0.9 * g)[..., None]).sum(-2)


def render_targets(volume: Volume, tf: TransferFunction, lights: np.ndarray, cameras: list[Camera], *,
                   step: float, method: str = "sweep", upsample: int = 1, device: torch.device | str = "cpu",
                   checkpoint: Path | None = None, checkpoint_s: float = TARGETS_CHECKPOINT_S,
                   log: Callable[[str], None] = print) -> torch.Tensor:
    """Ground-truth images (L, V, H, W, 3) on the CPU, rendered on `device` by the renderer's `gt` mode
    (early termination far below 8 bits) with shadow grids by `method` ("sweep" or "march") on the volume
    refined `upsample` times.

    Resumable: every `checkpoint_s` seconds of rendering the lights done so far are saved to `checkpoint`, and a
    rerun for the same inputs and settings starts at the first light not done (each light's images are rendered
    alone, so the result is the same bytes as an uninterrupted run); the checkpoint is removed at the end."""
    if method not in ("sweep", "march"):
        raise ValueError(f"finetune.targets: expected 'sweep' or 'march', got {method!r}")
    # each view's samples kept for the next lights' images (the same bytes as marching them)
    scene = RenderScene(volume, tf, device=device, gt_method=method, gt_upsample=upsample,
                        keep_samples=KEEP_SAMPLES_BYTES)
    out = torch.zeros(len(lights), len(cameras), cameras[0].height, cameras[0].width, 3)
    fingerprint = _targets_fingerprint(volume, tf, lights, cameras, step, method, upsample, scene.device)
    start = 0
    if state := resume(checkpoint, fingerprint, log=log, weights_only=True):
        start = int(state["done"])
        out[:start] = state["images"]
        log(f"resuming from {checkpoint} at light {start}/{len(lights)}")
    t0 = saved = time.perf_counter()
    for i in range(start, len(lights)):
        w = lights[i]
        for v, cam in enumerate(cameras):
            out[i, v] = scene.render("gt", cam, light=w, step=step, min_transmittance=1e-6).rgb
        scene.forget_gt(w)
        done = i + 1
        if checkpoint is not None and done < len(lights) and time.perf_counter() - saved >= checkpoint_s:
            atomic_torch_save(checkpoint, {"fingerprint": fingerprint, "done": done, "images": out[:done].clone()})
            saved = time.perf_counter()
        if done % max(1, len(lights) // 10) == 0 or done == len(lights):
            log(f"target images: {done}/{len(lights)} lights ({eta(done, len(lights), t0, start=start)})")
    if checkpoint is not None:
        Path(checkpoint).unlink(missing_ok=True)
    return out


def _targets_fingerprint(volume: Volume, tf: TransferFunction, lights, cameras: list[Camera], step: float,
                         method: str, upsample: int, device: torch.device) -> str:
    """What the target images depend on: the volume, TF, lights, views, settings and the kind of device (a GPU
    renders other bits than a CPU, and one run's images come from one kind)."""
    h = hashlib.sha256(np.ascontiguousarray(volume.data).tobytes())
    h.update(np.ascontiguousarray(lights, dtype=np.float64).tobytes())
    h.update(json.dumps([tf.to_config(), np.asarray(volume.extent).tolist(), [asdict(c) for c in cameras], step,
                         method, upsample, device.type]).encode())
    return h.hexdigest()
