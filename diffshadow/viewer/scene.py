"""What the viewer shows, without the browser: a finished scene's renderer, its lights, and the shadow cache
(`generated.zarr` for the listed lights, the diffusion model for any other direction, generated on demand and
kept per direction). The files are read by the readers the stages use."""

from __future__ import annotations

import math
import shlex
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.artifacts import load_checkpoint, load_render_scene, load_scene_file
from diffshadow.diffusion.mix import MixedSampler
from diffshadow.io import did_you_mean
from diffshadow.lights import LightRegion, RegionCheck, as_direction, nearest, read_lights
from diffshadow.render import Camera, RenderScene
from diffshadow.render.scene import KEEP_SAMPLES_BYTES
from diffshadow.report import label_image as label
from diffshadow.store import BlendSampler, WeightStore, open_store
from diffshadow.volume import check_extinction

# the files a finished scene needs, and the rule that makes each
SCENE_FILES = {"volume.zarr": "prepare_volume", "lights.json": "lights", "data_inr.pt": "train_data_inr",
               "generated.zarr": "sample_shadows"}
DIFF = "|inr - gt|"
VIEW_MODES = ("inr", "noshadow", "gt", "naive", "inr | gt", DIFF)
CACHE_MODES = ("inr", "inr | gt", DIFF)  # what the shadow cache answers (outside its region: the exact shadow)
GENERATED_KEEP = 64  # SIRENs generated on demand kept per viewer (a few KiB each)
SAME_LIGHT = 1e-9  # a direction this close to a listed light is that light


class ViewerError(ValueError):
    """A scene the viewer cannot open; the message names the file and the rule that makes it."""


def direction(azimuth: float, elevation: float) -> np.ndarray:
    """A unit direction from azimuth and elevation in degrees (z up, like `Camera.orbit`)."""
    az, el = math.radians(azimuth), math.radians(elevation)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def azimuth_elevation(light: ArrayLike) -> tuple[float, float]:
    """Degrees, the inverse of `direction`."""
    w = as_direction(light)
    return math.degrees(math.atan2(w[1], w[0])), math.degrees(math.asin(float(np.clip(w[2], -1, 1))))


@dataclass(frozen=True)
class LightInfo:
    """Where a light direction stands: a training light, an unseen test light or a new direction, its angle to
    the nearest training light, where it stands to the cache's light region (None: no cache), and how long its
    shadow SIREN took to generate (None: stored or cached)."""

    kind: str
    index: int | None
    nearest_deg: float | None
    generate_s: float | None = None
    region: RegionCheck | None = None

    @property
    def outside(self) -> bool:
        return self.region is not None and not self.region.inside

    def describe(self) -> str:
        name = {"training": f"training light {self.index}", "unseen": f"unseen test light {self.index}",
                "new": "new direction"}[self.kind]
        if self.nearest_deg is not None:
            name += f", {self.nearest_deg:.1f}° from the nearest training light"
        if self.region is not None and (self.outside or self.region.far):
            name += f" — {self.region.message()}"
        return name


def remake(results: Path, name: str) -> str:
    """The command that makes a scene's missing file: named as a target, since a plain run, finding the files made
    from it, has nothing to do."""
    return f"`snakemake --profile <yours> results/{Path(results).name}/{name}` makes it"


class ViewerScene:
    """One scene to view: `scene` renders; `generated` (a generated store) and `sampler` (a diffusion
    checkpoint's `ShadowSampler`, or with `cache: blend` the stored SIRENs' `BlendSampler`, or the two mixed,
    `diffusion.mix.MixedSampler`) supply the `inr` mode's shadow; without them only `noshadow` and `gt`.
    `checkpoint`: the file the sampler reads; `stored`: the stored SIRENs a mixed sampler blends."""

    def __init__(self, scene: RenderScene, *, name: str, lights: dict | None = None,
                 generated: WeightStore | None = None,
                 sampler: Callable[[np.ndarray], torch.Tensor | np.ndarray] | None = None, results: Path | None = None,
                 checkpoint: Path | None = None, scene_file: Path | None = None, stored: Path | None = None):
        self.scene, self.name, self.generated, self.sampler = scene, name, generated, sampler
        # a light moved over a still view draws it from the samples kept of it: 5-6x faster on a CPU, the same bytes
        scene.keep_views(KEEP_SAMPLES_BYTES)
        self.region = getattr(sampler, "region", None)  # lights.LightRegion of the cache (None: no region known)
        self.train = lights["train"] if lights else np.zeros((0, 3))
        self.unseen = lights["unseen"] if lights else np.zeros((0, 3))
        # where the scene came from, for the `diffshadow render` command of a frame
        self.results, self.checkpoint, self.scene_file, self.stored = results, checkpoint, scene_file, stored
        self._made: OrderedDict[tuple, torch.Tensor] = OrderedDict()

    @property
    def modes(self) -> tuple[str, ...]:
        return VIEW_MODES if self.generated is not None else ("noshadow", "gt")

    @classmethod
    def from_results(cls, results: Path, device: torch.device, render: dict | None = None) -> ViewerScene:
        """A finished scene's results folder (`results/<scene>`)."""
        results = Path(results)
        if not results.is_dir():
            raise ViewerError(f"{results}: no such results folder" + (did_you_mean(results) or
                                                                      " (run `snakemake --profile local -j2` first)"))
        if not (results / "volume.zarr").exists() and (inside := scenes_in(results)):
            raise ViewerError(f"{results}: a folder of scenes ({', '.join(inside)}), not one scene's results; give "
                              f"one: diffshadow view {results / inside[0]}")
        for name, rule in SCENE_FILES.items():
            if not (results / name).exists():
                raise ViewerError(f"{results}: not a finished scene, {name} is missing (made by the rule `{rule}`: "
                                  f"{remake(results, name)})")
        generated = open_store(results / "generated.zarr")
        scene = load_render_scene(results / "volume.zarr", results / "data_inr.pt", device, render=render)
        def same_scene(made_for: str | None, cache: Path) -> None:  # a folder put together from two runs' files
            check_extinction(made_for, scene.extinction, cache=str(cache), scene=str(results / "volume.zarr"),
                             remedy="rerun snakemake for this scene", error=ViewerError)

        same_scene(generated.extinction, results / "generated.zarr")
        lights = read_lights(results / "lights.json")
        source = cache_source(results, generated)
        if generated.config.get("cache") == "blend":  # no model: new directions blend the stored SIRENs
            stored_store = open_store(source)
            blend = BlendSampler.recorded(stored_store, generated.config,
                                          _correction(results, generated.config, stored_store))
            same_scene(blend.extinction, source)
            return cls(scene, name=results.name, lights=lights, generated=generated, sampler=blend, results=results,
                       checkpoint=source)
        if not source.exists():
            raise ViewerError(f"{source}: missing, the diffusion checkpoint that generated.zarr was sampled from "
                              f"(made by the rule `finetune_render` or `train_diffusion`: "
                              f"{remake(results, source.name)})")
        from diffshadow.diffusion.sample import ShadowSampler

        sampler, stored = ShadowSampler(load_checkpoint(source), device), None
        same_scene(sampler.extinction, source)
        mix = generated.config.get("mix")
        if mix:  # sample_shadows mixed the model's SIRENs with the stored SIRENs' blend: so is a new direction's
            stored = Path(results) / Path(str(mix["weights"])).name
            if not stored.exists():
                raise ViewerError(f"{stored}: missing, the stored SIRENs that generated.zarr's SIRENs were mixed "
                                  f"with (made by the rule `collect_weights`: {remake(results, stored.name)})")
            stored_store = open_store(stored)
            blend = BlendSampler.recorded(stored_store, mix, _correction(results, mix, stored_store))
            sampler = MixedSampler(sampler, blend, float(mix["model_share"]))
        return cls(scene, name=results.name, lights=lights, generated=generated, sampler=sampler, results=results,
                   checkpoint=source, stored=stored)

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

    def light_info(self, light: ArrayLike) -> LightInfo:
        w = as_direction(light)
        # the cache's training lights are the scene's: its region check has measured the nearest one already
        region = self.region.where(w) if self.region is not None else None
        nearest_deg = region.to_nearest_deg if region is not None else None
        if region is None and len(self.train):
            nearest_deg = float(np.degrees(nearest(self.train, w[None], 1)[1][0, 0]))
        for kind, lights in (("training", self.train), ("unseen", self.unseen)):
            if (i := _index(lights, w)) is not None:
                return LightInfo(kind, i, nearest_deg, region=region)
        return LightInfo("new", None, nearest_deg, region=region)

    def shadow_weights(self, light: ArrayLike) -> tuple[torch.Tensor, LightInfo]:
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
        return weights, LightInfo(info.kind, info.index, info.nearest_deg, time.perf_counter() - t0, info.region)

    # ------------------------------------------------------------------------------------------ frames

    def shown_mode(self, mode: str, light: ArrayLike) -> str:
        """The mode drawn for `mode` at `light`: a mode of the cache at a light outside the cache's region draws
        the exact shadow instead (the cache holds nothing there; the panel says so)."""
        if mode in CACHE_MODES and self.region is not None and not self.region.contains(light):
            return "gt"
        return mode

    def needs_gt(self, mode: str, light: ArrayLike) -> bool:
        """Whether a frame of `mode` at `light` draws the light's exact shadow grid."""
        return self.shown_mode(mode, light) in ("gt", "inr | gt", DIFF)

    def marches(self, mode: str, light: ArrayLike) -> bool:
        """Whether a still frame of `mode` at `light` must first march the light's exact shadow grid (not cached)."""
        return self.needs_gt(mode, light) and not self.scene.has_gt(light)

    def frame(self, mode: str, camera: Camera, light: ArrayLike, *, step: float,
              interrupt: Callable[[], bool] | None = None, preview: bool = False) -> tuple[np.ndarray, dict]:
        """(H, W, 3) uint8 image of `mode` and what the panel says about it (light, timings, PSNR). `interrupt`:
        the renderer's (`render.Interrupted` once it returns True), asked while the exact shadow is marched too.
        `preview`: a light whose exact shadow grid is not cached gets the shear sweep's (`exact_by`: "sweep"; under
        a second where the march takes 10-16 s on a 128³ volume, 2 CPU cores: 25b0baf)."""
        if mode not in self.modes:
            raise ViewerError(f"mode: expected one of {', '.join(self.modes)}, got {mode!r}")
        if (shown := self.shown_mode(mode, light)) != mode:
            image, notes = self.frame(shown, camera, light, step=step, interrupt=interrupt, preview=preview)
            return image, {**notes, "shown": shown}
        if mode in ("inr | gt", DIFF):
            # both from full frames of the same camera, so the PSNR is one number whichever of the two is shown
            inr, n1 = self.frame("inr", camera, light, step=step, interrupt=interrupt)
            gt, n2 = self.frame("gt", camera, light, step=step, interrupt=interrupt, preview=preview)
            notes = {**n1, "psnr_vs_gt": image_psnr(inr, gt), "gt_s": n2["render_s"], "grid_s": n2["grid_s"],
                     "exact_by": n2["exact_by"], "render_s": n1["render_s"] + n2["render_s"],
                     "replayed": n1["replayed"] and n2["replayed"]}
            if mode == "inr | gt":  # each whole frame at half size, side by side
                notes["labels"] = [f"cache ({self.cache_name})", "exact (gt)"]
                return side_by_side(inr, gt, notes["labels"]), notes
            diff = np.abs(inr.astype(np.int32) - gt.astype(np.int32))
            notes["diff_scale"] = scale = diff_scale(diff)
            notes["labels"] = [f"|inr - gt| x {scale}"]
            return label(np.clip(diff * scale, 0, 255).astype(np.uint8), notes["labels"][0], 0), notes
        siren = None
        if mode == "inr":
            weights, info = self.shadow_weights(light)
            siren = (weights, self.generated.layout, self.generated.siren.blocks)
            notes = {"light": info}
        else:
            notes = {} if mode == "noshadow" else {"light": self.light_info(light)}
        t0 = time.perf_counter()
        w = None if mode == "noshadow" else as_direction(light)
        method = None
        if mode == "gt":
            scene = self.scene
            method = "sweep" if preview and not scene.has_gt(w) else scene.gt_method
            scene.gt_shadow(w, method=method, interrupt=interrupt)  # timed apart: a frame's cost leaves it out
            notes.update(grid_s=time.perf_counter() - t0, exact_by=method)
        img = self.scene.render(mode, camera, light=w, siren=siren, step=step, interrupt=interrupt,
                                gt_method=method)
        notes.update(render_s=time.perf_counter() - t0, replayed=img.replayed)
        return img.to_uint8(), notes

    @property
    def cache_name(self) -> str:
        if isinstance(self.sampler, BlendSampler):  # a codec's decoded store says which codec (cache: fp16, ...)
            codec, blend = self.sampler.store.codec, _blend_name(self.sampler)
            return blend if codec == "fp32" else f"{blend}, {codec}"
        if isinstance(self.sampler, MixedSampler):
            return mix_name(self.sampler.share, self.sampler.blend.correction is not None)
        return "diffusion"

    def render_commands(self, mode: str, camera: Camera, light: ArrayLike, *, step: float) -> list[str]:
        """The `diffshadow render` commands that write this frame: one for a single mode (the exact shadow's where
        a cache mode falls outside the region), the inr and gt frames that the composite modes show side by side
        or as their difference."""
        mode = self.shown_mode(mode, light)
        if mode in ("inr | gt", DIFF):
            return [self.render_command(m, camera, light, step=step, out=f"{m}.png") for m in ("inr", "gt")]
        return [self.render_command(mode, camera, light, step=step)]

    def render_command(self, mode: str, camera: Camera, light: ArrayLike, *, step: float, out: str = "view.png") -> str:
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
                    args += ["--blend", str(self.checkpoint), *_blend_flags(self.sampler)]
                elif isinstance(self.sampler, MixedSampler):
                    args += ["--diffusion", str(self.checkpoint), "--blend", str(self.stored),
                             *_blend_flags(self.sampler.blend), "--model-share", f"{self.sampler.share:.17g}"]
                else:
                    args += ["--diffusion", str(self.checkpoint)]
        return shlex.join(args)


def scenes_in(folder: Path) -> list[str]:
    """The scenes whose results are in `folder` (the workflow's `results/`): its folders with a volume.zarr."""
    return sorted(p.parent.name for p in Path(folder).glob("*/volume.zarr"))


def mix_name(share: float, corrected: bool = False) -> str:
    """The viewer's name for a mixed cache at `share` (its blend `corrected` by the blend's correction or not); at
    0 or 1 one side answers alone (and only it is asked), so it is named, not a mix."""
    blend = "corrected blend" if corrected else "weight blend"
    if share == 0.0:
        return f"{blend}, model share 0"
    if share == 1.0:
        return "diffusion, model share 1"
    return f"diffusion {share:g} + {blend} {1 - share:g}"


def _blend_name(blend: BlendSampler) -> str:
    return "weight blend" if blend.correction is None else "corrected blend"


def cache_source(results: Path, generated: WeightStore) -> Path:
    """The file that answers a new direction for this run's generated.zarr: with `cache: blend` the stored SIRENs it
    blends (stage 1's own weights.zarr or a codec's decoded cache.zarr, as blend-shadows read it), else the
    diffusion checkpoint it was sampled from."""
    key, default = (("weights", "weights.zarr") if generated.config.get("cache") == "blend"
                    else ("checkpoint", "diffusion.ckpt"))
    return Path(results) / Path(str(generated.config.get(key, default))).name


def _index(lights: np.ndarray, light: np.ndarray) -> int | None:
    """The row of `lights` that is `light` (within SAME_LIGHT), if any."""
    if not len(lights):
        return None
    d = np.abs(lights - light[None]).max(axis=1)
    i = int(np.argmin(d))
    return i if d[i] <= SAME_LIGHT else None


def image_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB between two uint8 images of the same size (every pixel and channel)."""
    err = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) / 255.0 ** 2
    return 10 * math.log10(1 / max(err, 1e-30))


def half_size(image: np.ndarray) -> np.ndarray:
    """(H // 2, W // 2, 3) uint8: the mean of each 2x2 block."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    blocks = image[:2 * h, :2 * w].astype(np.float64).reshape(h, 2, w, 2, -1)
    return np.round(blocks.mean(axis=(1, 3))).astype(np.uint8)


def side_by_side(left: np.ndarray, right: np.ndarray, labels: list[str]) -> np.ndarray:
    """Two frames of one view at half size side by side, centred in a frame of their size on the background
    (the right frame's corner pixel), each labelled: both whole, however wide or tall the view."""
    h, w = left.shape[:2]
    a, b = half_size(left), half_size(right)
    out = np.empty_like(left)
    out[:] = right[0, 0]
    top = (h - a.shape[0]) // 2
    out[top:top + a.shape[0], :a.shape[1]] = label(a, labels[0], 0)
    out[top:top + b.shape[0], w - b.shape[1]:] = label(b, labels[1], 0)
    return out


def diff_scale(diff: np.ndarray) -> int:
    """The power of two (1 to 64) that brings the 99.5th percentile of an absolute difference image to at most
    full scale: the difference view shows the error instead of near-black (a fixed x4 left nucleon's at a few
    levels of 255)."""
    top = float(np.percentile(diff, 99.5)) if diff.size else 0.0
    return int(min(64, max(1, 2 ** math.floor(math.log2(255.0 / max(top, 1.0))))))


def region_chart(region: LightRegion, train: np.ndarray, unseen: np.ndarray, light: ArrayLike, *,
                 size: int = 220) -> np.ndarray:
    """(size, size, 3) uint8: the light gizmo. Directions drawn by their angle from the region's centre (the
    chart's centre) and their bearing around it (an azimuthal equidistant map): the cache's region (green cap),
    its training lights (blue), the unseen test lights (orange), and the current light (red dot inside the
    region, black cross outside). The chart reaches 1.5x the cap, or past the light where that is farther."""
    from PIL import Image, ImageDraw

    c = np.asarray(region.center, dtype=float)
    # +x projected onto the plane at the centre points right, the centre crossed with it up: seen from above,
    # a region around +z shows +x right and +y up (+y where the centre is near +x)
    axis = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = axis - (axis @ c) * c
    u /= np.linalg.norm(u)
    v = np.cross(c, u)
    w = as_direction(light)
    light_deg = region.angle_to_center(w)
    reach = min(180.0, max(1.5 * region.radius_deg, light_deg * 1.1 + 2.0, 10.0))
    mid, scale = size / 2, (size / 2 - 14) / reach

    def xy(d) -> tuple[float, float]:
        d = np.asarray(d, dtype=float)
        ang = math.degrees(math.acos(float(np.clip(d @ c, -1, 1))))
        bearing = math.atan2(float(d @ v), float(d @ u))
        return mid + ang * scale * math.cos(bearing), mid - ang * scale * math.sin(bearing)

    img = Image.new("RGB", (size, size), (250, 250, 250))
    draw = ImageDraw.Draw(img)
    for ring in range(30, int(reach) + 1, 30):  # every 30 degrees from the centre
        r = ring * scale
        draw.ellipse((mid - r, mid - r, mid + r, mid + r), outline=(215, 215, 215))
    r = region.radius_deg * scale
    draw.ellipse((mid - r, mid - r, mid + r, mid + r), fill=(214, 240, 214), outline=(60, 150, 60), width=2)
    for points, color in ((train, (40, 90, 200)), (unseen, (235, 140, 20))):
        for d in points:
            x, y = xy(d)
            draw.ellipse((x - 2.5, y - 2.5, x + 2.5, y + 2.5), fill=color)
    x, y = xy(w)
    if region.contains(w):
        draw.ellipse((x - 5, y - 5, x + 5, y + 5), fill=(220, 30, 30), outline=(0, 0, 0))
    else:
        draw.line((x - 6, y - 6, x + 6, y + 6), fill=(0, 0, 0), width=3)
        draw.line((x - 6, y + 6, x + 6, y - 6), fill=(0, 0, 0), width=3)
    draw.text((4, 2), f"cache region: {region.radius_deg:.0f} deg cap", fill=(40, 110, 40))
    draw.text((4, size - 12), f"edge of chart: {reach:.0f} deg from its centre", fill=(110, 110, 110))
    return np.asarray(img)


def _correction(results: Path, record: dict, stored: WeightStore):
    """The blend's correction that generated.zarr's blends were made with (its config's `correction`), from this
    results folder; None where they were plain."""
    said = record.get("correction")
    if not said:
        return None
    from diffshadow.correction import CorrectionError, load_correction

    path = Path(results) / Path(str(said["path"])).name
    try:
        return load_correction(path, stored.lights, stored.weights)
    except CorrectionError as e:
        raise ViewerError(f"{e} (generated.zarr's blends were corrected by it: {remake(results, path.name)})") from None


def _blend_flags(blend: BlendSampler) -> list[str]:
    """`render`'s flags for the weight blend a viewer's sampler makes."""
    fix = [] if getattr(blend.correction, "path", None) is None else ["--correction", str(blend.correction.path)]
    return ["--blend-weights", blend.weighting, "--blend-k", str(blend.k), *fix]
