"""The browser viewer (`diffshadow view`), built on viser: each browser tab gets its own panel and a render
thread that draws the scene from the tab's camera as the page's background image: at the canvas's own pixel size
once the camera and the light have been still for `STILL_S` (or at the height the panel asks), smaller while they
move (half that height, less where that would take longer than `PREVIEW_BUDGET_S`). A still frame that would take
longer than `STEP_UP_S` is drawn first at a quarter of its height, and any still frame is given up as soon as the view
changes. In the exact shadow's modes a light whose shadow grid is not marched yet is previewed with the shear
sweep's grid. Outside the cache's light region the cache's modes draw the exact shadow, and say so."""

from __future__ import annotations

import contextlib
import errno
import io
import json
import logging
import math
import queue
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from diffshadow.grid import check_step
from diffshadow.io import atomic_save, atomic_write_text
from diffshadow.render import Camera, Interrupted, RenderError
from diffshadow.viewer.scene import ViewerError, ViewerScene, azimuth_elevation, direction, region_chart

if TYPE_CHECKING:  # viser is imported where the viewer serves
    import viser

STILL_S = 0.3  # no change for this long: draw at full size
PREVIEW = 2  # while moving, the image height is divided by this ...
PREVIEW_BUDGET_S = 0.25  # ... or more, so that a moving frame takes about this long (a CPU at canvas size)
PREVIEW_MIN = 32
STEP_UP_S = 2.0  # a still frame predicted to take longer is drawn at a quarter of its height first (and so on)
STEP_UP = 4  # ... a quarter: 1/16 of the pixels, so the still frame costs 6 % more (a half: 25 % more)
# A preview, and its new light's SIREN, on one of PyTorch's threads. On more, each of their hundreds of small ops kept
# the other cores spinning in OpenMP's wait for the next, and the browser and the server's thread waited: in Chromium
# on the same 2 cores, dragging the light 3.0 fps (a SIREN generated in 0.19 s) against 6.6 fps (0.08 s)
# (docs/performance.md, "The viewer"). Still frames take every thread.
PREVIEW_THREADS = 1
MAX_SIZE = 2048  # the still frame's height at most (--size and the panel's slider)
STEP_RANGE = (0.125, 2.0)  # the panel's slider of the marching step in voxels, widened to hold a run's own
FREE = "(azimuth / elevation)"


def port_problem(host: str, port: int) -> str | None:
    """Why the viewer cannot listen on `host`:`port`, in words for `--port` or `--host`; None if it can."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, port))
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            return f"port {port} on {host} is in use (another viewer?); choose another with --port"
        return f"--host {host}: cannot listen there ({e.strerror or e}); 127.0.0.1 serves this machine, 0.0.0.0 all"
    return None


def camera_of(cam: viser.CameraHandle, height: int) -> Camera:
    """The renderer's camera for a viser client camera (box coordinates are the viewer's world), `height`
    pixels high at the browser canvas' aspect."""
    width = max(1, round(height * cam.aspect))
    return Camera.look_at(tuple(cam.position), tuple(cam.look_at), up=tuple(cam.up_direction),
                          fov=math.degrees(cam.fov), size=(width, height))


class TorchThread:
    """The one thread that runs the viewer's PyTorch work: the scene's loading and every tab's frames (`run` waits for
    the call's result there). PyTorch's CPU ops run on an OpenMP thread team of the thread that calls them, and GNU
    OpenMP stops spinning between parallel regions once its teams hold more threads than there are cores: every op
    then waits for its team to wake. With the scene loaded on the main thread and the frames drawn on a tab's thread,
    a 256² `inr` frame of nucleon took 5.4 s against 1.4 s with both on one thread (2 CPU cores, 2 threads;
    docs/performance.md, "The viewer")."""

    def __init__(self):
        self._calls: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name="viewer-torch", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while (call := self._calls.get()) is not None:
            fn, args, kwargs, result = call
            try:
                result.set_result(fn(*args, **kwargs))
            except BaseException as e:  # noqa: BLE001 - handed to the caller, who raises it
                result.set_exception(e)

    def run(self, fn: Callable, /, *args: Any, **kwargs: Any) -> Any:
        result: Future = Future()
        self._calls.put((fn, args, kwargs, result))
        return result.result()

    def close(self) -> None:
        """End the thread once the calls already asked for are done (its OpenMP team ends with it)."""
        self._calls.put(None)


def _on_threads(threads: int | None, fn: Callable, *args: Any, **kwargs: Any):
    """`fn` on `threads` of PyTorch's CPU threads (None: as set)."""
    if threads is None:
        return fn(*args, **kwargs)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return fn(*args, **kwargs)
    finally:
        torch.set_num_threads(before)


class Session:
    """One browser tab: its panel, its light, and the thread that decides what to draw for it (and has `run`, the
    viewer's `TorchThread`, draw it)."""

    def __init__(self, viewer: ViewerScene, client: viser.ClientHandle, *, size: int, step: float, record: Path | None,
                 start: Camera, run: Callable):
        self.viewer, self.client, self.start, self.run = viewer, client, start, run
        # each tab records into its own folder: a second tab numbers its frames from 1 without overwriting
        self.record = None if record is None else record / f"client_{client.client_id}"
        if self.record is not None:
            self.record.mkdir(parents=True, exist_ok=True)
        self.placed = False  # the browser's camera moved to `start` (its first camera is its own default)
        self.lock, self.wake = threading.Lock(), threading.Event()
        self.version, self.changed_at = 0, time.monotonic()
        self.drawn = {"full": -1, "preview": -1}
        self.rungs: tuple[int, list[int]] = (-1, [])  # a view's still-frame heights still to draw (`_rungs`)
        self.per_pixel: dict[str, float] = {}  # the last frame's seconds per pixel, per mode
        self.still_per_pixel: dict[str, float] = {}  # the same of still frames (a preview's includes more overhead)
        self.frames = 0
        listed = viewer.listed()
        self.light = listed[0][1] if listed else direction(60.0, 40.0)
        self.gt_light = None
        self.charted = self.light
        self._syncing = False
        gui = client.gui
        self.mode = gui.add_dropdown("mode", viewer.modes, initial_value=viewer.modes[0])
        with gui.add_folder("light"):
            self.pick = gui.add_dropdown("pick", [FREE] + [label for label, _ in listed],
                                         initial_value=listed[0][0] if listed else FREE)
            az, el = azimuth_elevation(self.light)
            self.azimuth = gui.add_slider("azimuth", -180.0, 180.0, 0.5, round(az * 2) / 2)
            self.elevation = gui.add_slider("elevation", -90.0, 90.0, 0.5, round(el * 2) / 2)
            self.light_note = gui.add_markdown("")
            self.gizmo = (gui.add_image(self._chart(), label="light region", format="png")
                          if viewer.region is not None else None)
        with gui.add_folder("image"):
            # 0: the canvas's own height (sharp at any window size); else a fixed height at the canvas's aspect
            self.size = gui.add_slider("height (px, 0: canvas)", 0, MAX_SIZE, 16, int(size))
            self.step = gui.add_slider("step (voxels)", min(STEP_RANGE[0], step), max(STEP_RANGE[1], step), 0.125,
                                       float(step))
        self.status = gui.add_markdown("starting")
        self.command = gui.add_markdown("")
        self.labels = dict(listed)
        self.pick.on_update(lambda _: self._picked())
        for slider in (self.azimuth, self.elevation):
            slider.on_update(lambda _: self._dragged())
        for control in (self.mode, self.size, self.step):
            control.on_update(lambda _: self.changed())
        client.camera.on_update(lambda _: self.changed())
        self.closed = False
        self.thread = threading.Thread(target=self._loop, name=f"render-{client.client_id}", daemon=True)
        self.thread.start()

    # ------------------------------------------------------------------------------------ panel events

    def changed(self) -> None:
        with self.lock:
            self.version += 1
            self.changed_at = time.monotonic()
        self.wake.set()

    def _picked(self) -> None:
        if self._syncing or self.pick.value == FREE:
            return
        self.light = np.asarray(self.labels[self.pick.value])
        az, el = azimuth_elevation(self.light)
        self._syncing = True
        try:  # the sliders follow the picked light without moving it
            self.azimuth.value, self.elevation.value = round(az * 2) / 2, round(el * 2) / 2
        finally:
            self._syncing = False
        self.changed()

    def _dragged(self) -> None:
        if self._syncing:
            return
        self.light = direction(self.azimuth.value, self.elevation.value)
        self._syncing = True
        try:
            self.pick.value = FREE
        finally:
            self._syncing = False
        self.changed()

    def close(self) -> None:
        self.closed = True
        self.wake.set()

    def _kind(self, version: int, still_s: float) -> str | None:
        """What to draw of view `version`, still for `still_s`: a "preview" while it changes, else the "full" frame;
        None when its preview is drawn and it is not still yet. A view first seen when already still gets a preview
        too if its still frame must march a new light's exact shadow first (6-7 s on tooth, 2 CPU cores): until then
        the canvas would show the light before the change."""
        if still_s < STILL_S:
            return None if version == self.drawn["preview"] else "preview"
        if version != self.drawn["preview"] and self.viewer.marches(self.mode.value, self.light):
            return "preview"
        return "full"

    def _preview_height(self, mode: str, full: int) -> int:
        """A moving frame's height: half the still frame's, lower where that would take longer than
        PREVIEW_BUDGET_S by the mode's last cost per pixel (a 480-pixel canvas on 2 CPU cores: ~90 px)."""
        height = full // PREVIEW
        if (cost := self.per_pixel.get(mode)) is not None:
            aspect = max(float(self.client.camera.aspect or 1.0), 1e-3)
            height = min(height, int(math.sqrt(PREVIEW_BUDGET_S / cost / aspect)))
        return max(PREVIEW_MIN, height)

    def _rungs(self, version: int, mode: str, full: int) -> list[int]:
        """The heights of view `version`'s still frame still to draw, the full height last: before it, quarters of
        it while the mode's last cost per pixel predicts more than STEP_UP_S for the frame above, down to the
        preview's height. On 2 CPU cores a 480-pixel canvas gets 120, 480; on a GPU the full frame alone."""
        if self.rungs[0] != version:
            heights = [full]
            if (cost := self.still_per_pixel.get(mode, self.per_pixel.get(mode))) is not None:
                aspect = max(float(self.client.camera.aspect or 1.0), 1e-3)
                while (heights[0] // STEP_UP > self._preview_height(mode, full)
                       and cost * aspect * heights[0] ** 2 > STEP_UP_S):
                    heights.insert(0, heights[0] // STEP_UP)
            self.rungs = (version, heights)
        return self.rungs[1]

    def _chart(self) -> np.ndarray:
        v = self.viewer
        return region_chart(v.region, v.train, v.unseen, self.light)

    # ------------------------------------------------------------------------------------ drawing

    def _loop(self) -> None:
        while not self.closed:
            self.wake.wait(0.05)
            self.wake.clear()
            with self.lock:
                version, changed_at = self.version, self.changed_at
            if version == self.drawn["full"]:
                continue
            kind = self._kind(version, time.monotonic() - changed_at)
            if kind is None:
                continue  # drawn small already; wait until it is still
            try:
                self.client.camera.update_timestamp  # noqa: B018 - raises until the browser sent its camera
            except AssertionError:
                continue
            if not self.placed:
                self._place_camera()
                continue
            full = int(self.size.value) or int(self.client.camera.image_height) or 128
            if kind == "full":
                rungs = self._rungs(version, self.mode.value, full)
                height, kind = rungs[0], "full" if len(rungs) == 1 else "sharpening"
            else:
                height = self._preview_height(self.mode.value, full)
            try:
                if not self._draw(kind, version, height):
                    continue  # given up for a newer view: its preview comes next
            except (ViewerError, RenderError, ValueError) as e:
                self.status.content = f"**cannot draw:** {e}"
                kind = "full"
            if kind == "sharpening":
                self.rungs[1].pop(0)
                continue
            self.drawn[kind] = version

    def _place_camera(self) -> None:
        """Every tab starts from the same orbit view (also what `diffshadow render`'s defaults show): a browser
        may report its own default camera before it has applied the server's initial one."""
        cam = self.client.camera
        cam.up_direction = self.start.up
        cam.position = self.start.eye  # moves the look-at point with it
        cam.look_at = self.start.target
        cam.fov = math.radians(self.start.fov)
        self.placed = True
        self.changed()

    def _draw(self, kind: str, version: int, height: int) -> bool:
        """Draw view `version` `height` pixels high as a still frame ("full", or "sharpening" on the way to it) or a
        preview; False if it was given up for a newer view."""
        mode, step = self.mode.value, float(self.step.value)
        camera = camera_of(self.client.camera, max(16, height))
        light = self.light
        if self.viewer.needs_gt(mode, light):
            if self.gt_light is not None and not np.array_equal(self.gt_light, light):
                self.run(self.viewer.scene.forget_gt, self.gt_light)  # one light's exact shadow kept, not all
            self.gt_light = light
            if kind != "preview" and self.viewer.marches(mode, light):
                self.status.content = "computing the exact shadow for this light (once per light) ..."
        t0 = time.perf_counter()
        # a still frame (20 s at 480² on 2 CPU cores) is given up as soon as the view changes. A preview is not: it
        # is short, and while the light is dragged the view changes every few milliseconds, so none would be shown.
        interrupt = None if kind == "preview" else (lambda: self.version != version)
        try:
            threads = PREVIEW_THREADS if kind == "preview" else None
            image, notes = self.run(_on_threads, threads, self.viewer.frame, mode, camera, light, step=step,
                                    interrupt=interrupt, preview=kind == "preview")
        except Interrupted:
            self._log_frame({"kind": kind, "view": version, "mode": mode, "width": camera.width,
                             "height": camera.height, "seconds": time.perf_counter() - t0, "interrupted": True})
            return False
        self.client.scene.set_background_image(image, format="png")
        seconds = time.perf_counter() - t0
        # the exact shadow's grid is paid once per light, not per pixel: left out of what predicts the next frame.
        # A frame drawn from a view's kept samples predicts no other view's: the cost stays the last marched one's
        if not notes.get("replayed"):
            self.per_pixel[mode] = (seconds - notes.get("grid_s", 0.0)) / (camera.width * camera.height)
            if kind != "preview":
                self.still_per_pixel[mode] = self.per_pixel[mode]
        self.frames += 1
        # the commands that redraw this frame (the panel shows them, the record keeps them)
        commands = self.viewer.render_commands(mode, camera, light, step=step)
        if self.gizmo is not None and not np.array_equal(self.charted, light):
            self.gizmo.image, self.charted = self._chart(), light
        self._notes(kind, mode, camera, light, notes, seconds, commands)
        made = notes["light"].generate_s if notes.get("light") else None
        self._log_frame({"kind": kind, "view": version, "mode": mode, "shown": notes.get("shown", mode),
                         "width": camera.width, "height": camera.height, "seconds": seconds, "generate_s": made,
                         "grid_s": notes.get("grid_s"), "exact_by": notes.get("exact_by"),
                         "replayed": notes.get("replayed", False)})
        if self.record is not None and kind == "full":
            self._record(image, mode, camera, light, notes, commands)
        return True

    def _log_frame(self, entry: dict) -> None:
        """Every frame's cost, drawn or given up, with the time it ended (frames.jsonl; for measuring the viewer)."""
        if self.record is not None:
            with open(self.record / "frames.jsonl", "a") as f:
                f.write(json.dumps({**entry, "time": time.time()}) + "\n")

    def _notes(self, kind, mode, camera, light, notes, seconds, commands) -> None:
        info = notes.get("light") or self.viewer.light_info(light)
        line = info.describe()
        if info.generate_s is not None:
            line += f"; its shadow SIREN made now in {info.generate_s:.2f} s ({self.viewer.cache_name})"
        self.light_note.content = line
        # this frame's time and rate, not an average: a 5 s frame reads 0.2 fps
        said = {"preview": " (moving: preview)", "sharpening": " (still: a sharper frame follows)"}.get(kind, "")
        status = (f"{camera.width}×{camera.height}{said} in "
                  f"{seconds * 1000:.0f} ms ({1 / max(seconds, 1e-9):.1f} fps) on {self.viewer.scene.device.type}")
        if (by := notes.get("exact_by")) is not None and by != (still := self.viewer.scene.gt_method):
            status += f"  \nexact shadow by the quick {by} while moving (the {still} when still)"
        if notes.get("shown") == "gt":
            status = (f"**outside the cache: exact shadow, {notes['render_s'] * 1000:.0f} ms** (the cache was not "
                      f"trained for this light)  \n" + status)
        if "psnr_vs_gt" in notes:
            status += f"  \ninr against gt: {notes['psnr_vs_gt']:.2f} dB (whole frame)"
        if "diff_scale" in notes:
            k = notes["diff_scale"]
            status += f"  \n|inr − gt| × {k}: white is a difference of {255 / k:.0f} of 255 levels"
        self.status.content = status
        what = ("the inr and gt frames shown side by side" if mode == "inr | gt" and len(commands) == 2
                else "the inr and gt frames whose difference is shown" if len(commands) == 2 else "this frame")
        self.command.content = f"{what} from the command line:\n\n" + "\n\n".join(
            f"```\n{c}\n```" for c in commands)

    def _record(self, image, mode, camera, light, notes, commands) -> None:
        from PIL import Image as PILImage

        stem = self.record / f"frame_{self.frames:05d}"
        atomic_save(stem.with_suffix(".png"), lambda tmp: PILImage.fromarray(image).save(tmp, format="PNG"),
                    suffix=".png")
        info = notes.get("light")
        atomic_write_text(stem.with_suffix(".json"), json.dumps({
            "mode": mode, "shown": notes.get("shown", mode), "light": list(map(float, light)),
            "command": commands[0], "commands": commands, "width": camera.width, "height": camera.height,
            "canvas": [int(self.client.camera.image_width), int(self.client.camera.image_height)],
            "light_kind": info.describe() if info else None, "outside": bool(info and info.outside),
            "far": bool(info and info.region is not None and info.region.far), "labels": notes.get("labels", []),
            "psnr_vs_gt": notes.get("psnr_vs_gt"), "diff_scale": notes.get("diff_scale"),
            "status": self.status.content, "generate_s": info.generate_s if info else None,
            "render_s": notes.get("render_s"), "exact_by": notes.get("exact_by")}, indent=1) + "\n")


def serve(*, results: Path | None, scene_config: Path | None, device: torch.device, host: str = "127.0.0.1",
          port: int = 8080, size: int = 128, step: float = 0.5, render: dict | None = None,
          record: Path | None = None, stop: threading.Event | None = None) -> None:
    """Serve the viewer until Ctrl-C (or `stop` is set)."""
    if not 1 <= port <= 65535:
        raise ViewerError(f"--port {port}: expected a TCP port, 1 to 65535")
    if not 0 <= size <= MAX_SIZE:
        raise ViewerError(f"--size {size}: expected a still frame's height in pixels, 0 (the canvas's) to {MAX_SIZE}")
    try:  # the renderer's own check, now: else every frame would fail in it, after the viewer started
        check_step(step)
    except ValueError as e:
        raise ViewerError(f"--step {step:g}: expected a positive marching step in voxels ({e})") from None
    if (problem := port_problem(host, port)) is not None:
        raise ViewerError(problem)
    torch_thread = TorchThread()
    try:
        load, source = ((ViewerScene.from_results, results) if results is not None
                        else (ViewerScene.from_scene_config, scene_config))
        viewer = torch_thread.run(load, source, device, render)
        _serve(viewer, torch_thread.run, host=host, port=port, size=size, step=step, record=record, stop=stop)
    finally:
        torch_thread.close()


def aim_initial_camera(initial: viser.InitialCameraConfig, start: Camera) -> None:
    """Where a new tab starts and what "Reset View" returns to. viser names the up vector `up` here, where a
    client's camera calls it `up_direction`: a misnamed field would be a silent new attribute, not an error."""
    initial.position, initial.look_at = start.eye, start.target
    initial.up, initial.fov = start.up, math.radians(start.fov)


def _serve(viewer: ViewerScene, run: Callable, *, host: str, port: int, size: int, step: float,
           record: Path | None, stop: threading.Event | None) -> None:
    import viser

    if record is not None:
        record.mkdir(parents=True, exist_ok=True)
    logging.getLogger("websockets").setLevel(logging.CRITICAL)  # a browser's aborted probe is no error of ours
    with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the line below says where to look
        server = viser.ViserServer(host=host, port=port, verbose=False)
    if server.get_port() != port:
        server.stop()
        raise ViewerError(f"port {port} on {host} was taken while the viewer started; choose another with --port")
    server.gui.configure_theme(control_layout="fixed", show_share_button=False, show_logo=False)
    server.scene.set_up_direction("+z")
    start = run(viewer.scene.framed, azimuth=30.0, elevation=25.0, fov=60.0)  # what `diffshadow render` shows
    aim_initial_camera(server.initial_camera, start)
    sessions: dict[int, Session] = {}

    @server.on_client_connect
    def _(client: viser.ClientHandle) -> None:
        sessions[client.client_id] = Session(viewer, client, size=size, step=step, record=record, start=start,
                                             run=run)

    @server.on_client_disconnect
    def _(client: viser.ClientHandle) -> None:
        if (s := sessions.pop(client.client_id, None)) is not None:
            s.close()

    shown = "localhost" if host in ("127.0.0.1", "::1") else host
    print(f"diffshadow view: {viewer.name} ({', '.join(viewer.modes)}) on {viewer.scene.device.type} at "
          f"http://{shown}:{port}  (Ctrl-C stops it)", flush=True)
    try:
        while not (stop is not None and stop.is_set()):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        for s in sessions.values():
            s.close()
        server.stop()
