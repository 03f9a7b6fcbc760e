"""What the viewer shows, without the browser: a finished scene's renderer, its lights, and the shadow cache
(`generated.zarr` for the listed lights, the diffusion model for any other direction, generated on demand and
kept per direction). The files are read by the readers the stages use."""

from __future__ import annotations

import math
import shlex
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from diffshadow.artifacts import load_checkpoint, load_render_scene, load_scene_file
from diffshadow.lights import as_direction, nearest, read_lights
from diffshadow.render import Camera, RenderScene
from diffshadow.store import BlendSampler, WeightStore, open_store

# the files a finished scene needs, and the rule that makes each
SCENE_FILES = {"volume.zarr": "prepare_volume", "lights.json": "lights", "data_inr.pt": "train_data_inr",
               "generated.zarr": "sample_shadows"}
VIEW_MODES = ("inr", "noshadow", "gt", "naive", "inr | gt", "|inr - gt| x4")
GENERATED_KEEP = 64  # SIRENs generated on demand kept per viewer (a few KiB each)
SAME_LIGHT = 1e-9  # a direction this close to a listed light is that light


class ViewerError(ValueError):
    """A scene the viewer cannot open; the message names the file and the rule that makes it."""


def direction(azimuth: float, elevation: float) -> np.ndarray:
    """A unit direction from azimuth and elevation in degrees (z up, like `Camera.orbit`)."""
    az, el = math.radians(azimuth), math.radians(elevation)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def azimuth_elevation(light) -> tuple[float, float]:
    """Degrees, the inverse of `direction`."""
    w = as_direction(light)
    return math.degrees(math.atan2(w[1], w[0])), math.degrees(math.asin(float(np.clip(w[2], -1, 1))))


@dataclass(frozen=True)
class LightInfo:
    """Where a light direction stands: a training light, an unseen test light or a new direction, its angle to
    the nearest training light, and how long its shadow SIREN took to generate (None: stored or cached)."""

    kind: str
    index: int | None
    nearest_deg: float | None
    generate_s: float | None = None

    def describe(self) -> str:
        name = {"training": f"training light {self.index}", "unseen": f"unseen test light {self.index}",
                "new": "new direction"}[self.kind]
        if self.nearest_deg is not None:
            name += f", {self.nearest_deg:.1f}° from the nearest training light"
        return name


class ViewerScene:
    """One scene to view: `scene` renders; `generated` (a generated store) and `sampler` (a diffusion
    checkpoint's `ShadowSampler`, or with `cache: blend` the stored SIRENs' `BlendSampler`) supply the `inr`
    mode's shadow; without them only `noshadow` and `gt`. `checkpoint`: the file the sampler reads."""

    def __init__(self, scene: RenderScene, *, name: str, lights: dict | None = None,
                 generated: WeightStore | None = None, sampler=None, results: Path | None = None,
                 checkpoint: Path | None = None, scene_file: Path | None = None):
        self.scene, self.name, self.generated, self.sampler = scene, name, generated, sampler
        self.train = lights["train"] if lights else np.zeros((0, 3))
        self.unseen = lights["unseen"] if lights else np.zeros((0, 3))
        # where the scene came from, for the `diffshadow render` command of a frame
        self.results, self.checkpoint, self.scene_file = results, checkpoint, scene_file
        self._made: OrderedDict[tuple, torch.Tensor] = OrderedDict()

    @property
    def modes(self) -> tuple[str, ...]:
        return VIEW_MODES if self.generated is not None else ("noshadow", "gt")

    @classmethod
    def from_results(cls, results: Path, device: torch.device, render: dict | None = None) -> ViewerScene:
        """A finished scene's results folder (`results/<scene>`)."""
        results = Path(results)
        if not results.is_dir():
            raise ViewerError(f"{results}: no such results folder (run `snakemake --profile local -j2` first)")
        for name, rule in SCENE_FILES.items():
            if not (results / name).exists():
                raise ViewerError(f"{results}: not a finished scene, {name} is missing (made by the rule `{rule}`; "
                                  f"run snakemake to finish the scene)")
        generated = open_store(results / "generated.zarr")
        scene = load_render_scene(results / "volume.zarr", results / "data_inr.pt", device, render=render)
        lights = read_lights(results / "lights.json")
        if generated.config.get("cache") == "blend":  # no model: new directions blend the stored SIRENs
            weights = results / "weights.zarr"
            return cls(scene, name=results.name, lights=lights, generated=generated,
                       sampler=BlendSampler(open_store(weights)), results=results, checkpoint=weights)
        ckpt = results / Path(str(generated.config.get("checkpoint", "diffusion.ckpt"))).name
        if not ckpt.exists():
            raise ViewerError(f"{ckpt}: missing, the diffusion checkpoint that generated.zarr was sampled from "
                              f"(made by the rule `finetune_render` or `train_diffusion`)")
        from diffshadow.diffusion.sample import ShadowSampler

        return cls(scene, name=results.name, lights=lights, generated=generated,
                   sampler=ShadowSampler(load_checkpoint(ckpt), device), results=results, checkpoint=ckpt)

    @classmethod
    def from_scene_config(cls, path: Path, device: torch.device, render: dict | None = None) -> ViewerScene:
        """A scene file before any run: `noshadow` and `gt` only."""
        scene = load_scene_file(Path(path), device, render)
        return cls(scene, name=Path(path).stem, scene_file=Path(path))

    # ------------------------------------------------------------------------------------------ lights

    def listed(self) -> list[tuple[str, np.ndarray]]:
        """The lights to pick from: (label, direction)."""
        return ([(f"training {i}", w) for i, w in enumerate(self.train)]
                + [(f"unseen {i}", w) for i, w in enumerate(self.unseen)])

    def _stored_row(self, light: np.ndarray) -> int | None:
        return None if self.generated is None else _index(self.generated.lights, light)

    def light_info(self, light) -> LightInfo:
        w = as_direction(light)
        nearest_deg = None
        if len(self.train):
            nearest_deg = float(np.degrees(nearest(self.train, w[None], 1)[1][0, 0]))
        for kind, lights in (("training", self.train), ("unseen", self.unseen)):
            if (i := _index(lights, w)) is not None:
                return LightInfo(kind, i, nearest_deg)
        return LightInfo("new", None, nearest_deg)

    def shadow_weights(self, light) -> tuple[torch.Tensor, LightInfo]:
        """The cached shadow SIREN's weights for `light`: its row of generated.zarr, else generated now by the
        diffusion model (and kept for the next frames)."""
        if self.generated is None:
            raise ViewerError("mode inr: this scene has no shadow cache (view a finished scene's results folder)")
        w = as_direction(light)
        info = self.light_info(w)
        if (row := self._stored_row(w)) is not None:
            return torch.as_tensor(self.generated.weights[row]), info
        key = tuple(np.round(w, 12).tolist())
        if key in self._made:
            self._made.move_to_end(key)
            return self._made[key], info
        t0 = time.perf_counter()
        weights = torch.as_tensor(self.sampler(w))
        self._made[key] = weights
        while len(self._made) > GENERATED_KEEP:
            self._made.popitem(last=False)
        return weights, LightInfo(info.kind, info.index, info.nearest_deg, time.perf_counter() - t0)

    # ------------------------------------------------------------------------------------------ frames

    def frame(self, mode: str, camera: Camera, light, *, step: float) -> tuple[np.ndarray, dict]:
        """(H, W, 3) uint8 image of `mode` and what the panel says about it (light, timings, PSNR)."""
        if mode not in self.modes:
            raise ViewerError(f"mode: expected one of {', '.join(self.modes)}, got {mode!r}")
        notes: dict = {}
        if mode in ("inr | gt", "|inr - gt| x4"):
            cam = camera
            if mode == "inr | gt":  # two halves, each the central half of the view
                cam = Camera(camera.eye, camera.target, camera.up, camera.fov, max(1, camera.width // 2), camera.height)
            inr, n1 = self.frame("inr", cam, light, step=step)
            gt, n2 = self.frame("gt", cam, light, step=step)
            err = np.mean((inr.astype(np.float64) - gt.astype(np.float64)) ** 2) / 255.0 ** 2
            notes = {**n1, "psnr_vs_gt": 10 * math.log10(1 / max(err, 1e-30)), "gt_s": n2["render_s"]}
            if mode == "inr | gt":
                return np.concatenate([inr, gt], axis=1), notes
            diff = np.abs(inr.astype(np.int32) - gt.astype(np.int32)) * 4
            return np.clip(diff, 0, 255).astype(np.uint8), notes
        siren = None
        if mode == "inr":
            weights, info = self.shadow_weights(light)
            siren = (weights, self.generated.layout, self.generated.siren.blocks)
            notes["light"] = info
        elif mode != "noshadow":
            notes["light"] = self.light_info(light)
        t0 = time.perf_counter()
        img = self.scene.render(mode, camera, light=None if mode == "noshadow" else as_direction(light),
                                siren=siren, step=step)
        notes["render_s"] = time.perf_counter() - t0
        return img.to_uint8(), notes

    def render_command(self, mode: str, camera: Camera, light, *, step: float, out: str = "view.png") -> str:
        """The `diffshadow render` command that writes this frame (modes inr, noshadow, gt, naive)."""
        source = (["--scene-config", str(self.scene_file)] if self.results is None else
                  ["--volume", str(self.results / "volume.zarr"), "--data-inr", str(self.results / "data_inr.pt")])
        args = ["diffshadow", "render", *source, "--mode", mode, "--out", out,
                "--eye", *(f"{x:.9g}" for x in camera.eye), "--target", *(f"{x:.9g}" for x in camera.target),
                "--up", *(f"{x:.9g}" for x in camera.up), "--fov", f"{camera.fov:.9g}",
                "--size", str(camera.width), str(camera.height), "--step", f"{step:g}"]
        if mode != "noshadow":
            w = as_direction(light)
            args += ["--light", *(f"{x:.17g}" for x in w)]
            if mode == "inr":
                row = self._stored_row(w)
                if row is not None:
                    args += ["--weights", str(self.results / "generated.zarr"), "--light-index", str(row)]
                elif isinstance(self.sampler, BlendSampler):
                    args += ["--blend", str(self.checkpoint)]
                else:
                    args += ["--diffusion", str(self.checkpoint)]
        return shlex.join(args)


def _index(lights: np.ndarray, light: np.ndarray) -> int | None:
    """The row of `lights` that is `light` (within SAME_LIGHT), if any."""
    if not len(lights):
        return None
    d = np.abs(lights - light[None]).max(axis=1)
    i = int(np.argmin(d))
    return i if d[i] <= SAME_LIGHT else None
