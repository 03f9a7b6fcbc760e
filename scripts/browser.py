"""Headless Chromium driven over the DevTools protocol (no browser-automation package: the websocket client is
viser's, a dependency already): the viewer's browser test (tests/test_workflow.py) and what a person looks at.

    python scripts/browser.py viewer results/nucleon --screenshot docs/images/viewer.png   # the test's checks
    python scripts/browser.py viewer-fps results/nucleon --sizes 0 128 --out viewer_fps.json
    python scripts/browser.py report report.html --out shots   # shots/landing.png is docs/images/report.png

Needs Chromium on PATH (Debian: apt-get install chromium); WebGL runs on SwiftShader, no GPU needed.
"""

from __future__ import annotations

import base64
import contextlib
import io
import itertools
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
DIFFSHADOW = Path(sys.executable).parent / "diffshadow"  # this environment's command


def find_browser() -> str | None:
    return next((path for name in BROWSERS if (path := shutil.which(name))), None)


def _dies_with_driver(*, no_priority: bool = False) -> Callable[[], None] | None:
    """What a process this script starts runs before its exec, on Linux: it is killed with the thread that started
    it (a killed driver left Chromium, in its own session, drawing at 80 % of a core, and the viewer serving), and
    with `no_priority` it cannot raise its own priority: as root Chromium puts its GPU process, SwiftShader drawing
    the page, at nice -8, ahead of the viewer it drives on the same cores, where a user's Chromium (not root)
    stays at the user's priority. None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here: the child only calls it
    pr_set_pdeathsig, pr_capbset_drop, cap_sys_nice = 1, 24, 23  # <linux/prctl.h>, <linux/capability.h>

    def child() -> None:
        prctl(pr_set_pdeathsig, signal.SIGKILL)
        if no_priority:
            prctl(pr_capbset_drop, cap_sys_nice)  # fails without CAP_SETPCAP: then it had no such right to drop

    return child


class Browser:
    """One headless page. WebGL runs on SwiftShader (no GPU needed); one CSS pixel is one screen pixel."""

    def __init__(self, url: str, *, width: int, height: int, timeout: float = 60.0):
        from websockets.sync.client import connect

        exe = find_browser()
        if exe is None:
            raise RuntimeError(f"no Chromium on PATH (looked for {', '.join(BROWSERS)})")
        # Chromium's helper processes can still write to the profile as it is removed (seen under load: "Directory
        # not empty" failed a test whose checks had passed); they are stopped with it as one process group below
        self.profile = tempfile.TemporaryDirectory(prefix="diffshadow-chromium-", ignore_cleanup_errors=True)
        self.proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--no-first-run", "--no-default-browser-check",
             "--disable-background-networking", "--disable-extensions", "--disable-dev-shm-usage",
             "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--force-device-scale-factor=1", f"--window-size={width},{height}", "--remote-debugging-port=0",
             f"--user-data-dir={self.profile.name}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
            preexec_fn=_dies_with_driver(no_priority=True))
        port = None
        deadline = time.monotonic() + timeout
        while port is None and time.monotonic() < deadline:
            line = self.proc.stderr.readline()
            if not line and self.proc.poll() is not None:
                raise RuntimeError(f"{exe} exited with {self.proc.returncode} before its DevTools port opened")
            if m := re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line):
                port = int(m.group(1))
        if port is None:
            raise RuntimeError(f"{exe}: no DevTools port after {timeout:.0f} s")
        threading_drain(self.proc.stderr)
        pages = []
        while not pages and time.monotonic() < deadline:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as r:
                pages = [t for t in json.load(r) if t["type"] == "page"]
            time.sleep(0.1)
        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=2 ** 28)
        self.ids = itertools.count(1)

    def send(self, method: str, **params):
        i = next(self.ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def js(self, expression: str):
        r = self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"page script failed: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60.0, what: str = ""):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if value := self.js(expression):
                return value
            time.sleep(0.1)
        raise TimeoutError(f"waited {timeout:.0f} s for {what or expression}")

    def click(self, x: float, y: float) -> None:
        for kind in ("mousePressed", "mouseReleased"):
            self.send("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)

    def click_text(self, text: str, selector: str = "*") -> None:
        """Click the centre of the last visible element matching `selector` whose own text is `text` (scrolled
        into view)."""
        find = f"""(() => {{
            const all = [...document.querySelectorAll({json.dumps(selector)})].filter(e =>
                [...e.childNodes].some(n => n.nodeType === 3 && n.textContent.trim() === {json.dumps(text)}));
            const vis = all.filter(e => e.getBoundingClientRect().width > 0);
            const e = vis[vis.length - 1];
            if (!e) return null;
            let r = e.getBoundingClientRect();
            if (r.bottom > innerHeight || r.top < 0) {{
                e.scrollIntoView({{block: 'nearest'}});
                r = e.getBoundingClientRect();
            }}
            return r ? [r.x + r.width / 2, r.y + r.height / 2] : null; }})()"""
        rect, settled = None, False
        while not settled:  # a menu that opens moves its items into place
            time.sleep(0.2)
            last, rect = rect, self.wait_for(find, what=f"an element '{text}'")
            settled = rect == last
        self.click(*rect)

    def choose(self, x: float, y: float, option: str) -> None:
        """Pick `option` in the searchable list whose input is at (x, y): type it, then click it."""
        self.click(x, y)
        self.select_all()
        self.send("Input.insertText", text=option)
        self.click_text(option)
        self.wait_for("""![...document.querySelectorAll('[role="listbox"]')].some(e =>
            e.getBoundingClientRect().height > 0)""", timeout=10, what="the list to close")

    def select_all(self) -> None:
        for kind in ("keyDown", "keyUp"):
            self.send("Input.dispatchKeyEvent", type=kind, key="a", code="KeyA", modifiers=2, windowsVirtualKeyCode=65)

    def type_into(self, x: float, y: float, text: str) -> None:
        """Click an input, replace its text and press Enter."""
        self.click(x, y)
        self.select_all()
        self.send("Input.insertText", text=text)
        for kind in ("keyDown", "keyUp"):
            self.send("Input.dispatchKeyEvent", type=kind, key="Enter", code="Enter", windowsVirtualKeyCode=13)

    def input_beside(self, label: str) -> tuple[float, float]:
        """The centre of the text input on the same row as the label `label` (scrolled into view)."""
        return self.wait_for(_on_row_of(label, """const r = [...document.querySelectorAll('input')]
            .map(e => e.getBoundingClientRect()).filter(r => r.width > 0 && r.x > l.x && onRow(r)).pop();
            return r ? [r.x + r.width / 2, r.y + r.height / 2] : null;"""), what=f"an input beside '{label}'")

    def dismiss_notifications(self) -> int:
        """Close the page's notifications (viser tells a software-WebGL browser so, over the canvas); how many."""
        return self.js("""(() => { const b = [...document.querySelectorAll('[role="alert"] button')];
            b.forEach(e => e.click()); return b.length; })()""")

    def canvas_rect(self) -> dict:
        return self.wait_for("""(() => { const c = [...document.querySelectorAll('canvas')]
            .map(e => e.getBoundingClientRect()).sort((a, b) => b.width * b.height - a.width * a.height)[0];
            return c && c.width > 0 ? {x: c.x, y: c.y, width: c.width, height: c.height} : null; })()""",
                             what="the viewer's canvas")

    def canvas_size(self) -> list[int]:
        rect = self.canvas_rect()
        return [round(rect["width"]), round(rect["height"])]

    def screenshot(self, clip: dict | None = None) -> np.ndarray:
        """(H, W, 3) uint8 of the page, or of `clip` ({x, y, width, height} in CSS pixels)."""
        from PIL import Image

        params = {"format": "png"}
        if clip is not None:
            params["clip"] = {**clip, "scale": 1}
        data = base64.b64decode(self.send("Page.captureScreenshot", **params)["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def close(self) -> None:
        try:
            self.ws.close()
        finally:
            group = os.getpgid(self.proc.pid) if self.proc.poll() is None else None
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
            if group is not None:  # the renderer, GPU and crash-handler processes, which outlive the browser's
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(group, signal.SIGKILL)
            self.profile.cleanup()


def threading_drain(stream) -> None:
    """Read a pipe to its end in the background, so that a chatty browser never blocks on a full pipe."""
    import threading

    threading.Thread(target=lambda: [None for _ in stream], daemon=True).start()


# ------------------------------------------------------------------------------------------------ the viewer


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    err = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / max(err, 1e-12)))


PANEL_SHADOW_PX = 24  # the canvas's right columns that viser's control panel shadows (15 px measured with viser 1.1)


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def next_frame(record, seen: int, accept, timeout: float = 120.0) -> dict:
    """The first recorded still frame after the `seen` first ones that `accept`s, with its image."""
    from PIL import Image

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for path in sorted(record.glob("frame_*.json"))[seen:]:
            meta = json.loads(path.read_text())
            if accept(meta):
                return {**meta, "path": path, "image": np.asarray(Image.open(path.with_suffix(".png")))}
        time.sleep(0.1)
    last = [{k: m[k] for k in ("mode", "width", "height", "light_kind")}
            for m in (json.loads(p.read_text()) for p in sorted(record.glob("frame_*.json"))[-3:])]
    raise TimeoutError(f"no frame in {record} in {timeout:.0f} s that passes the test; the last ones: {last}")


def shown(browser: Browser, frame: dict, timeout: float = 60.0) -> np.ndarray:
    """The canvas once it shows `frame`: the same size and, left of the panel's shadow, its pixels to within one
    level. A PSNR bound let the frame before through when the two were alike (an unseen light after the first
    frame: 46 dB apart), and under load the canvas had not changed yet (27 levels off the render)."""
    deadline = time.monotonic() + timeout
    best, closest = -1.0, None
    while time.monotonic() < deadline:
        if browser.dismiss_notifications():
            time.sleep(0.5)  # they fade out
        rect = browser.canvas_rect()
        shot = browser.screenshot(rect)
        if shot.shape == frame["image"].shape:
            best = max(best, psnr(shot, frame["image"]))
            diff = max_diff(left_of_panel(shot), left_of_panel(frame["image"]))
            closest = diff if closest is None else min(closest, diff)
            if diff <= 1:
                return shot
        time.sleep(0.2)
    raise AssertionError(f"the browser never showed {frame['path'].name} ({frame['width']}x{frame['height']}): "
                         f"best PSNR {best:.1f} dB, least largest difference left of the panel {closest}, "
                         f"canvas {browser.canvas_rect()}")


def max_diff(a: np.ndarray, b: np.ndarray) -> int:
    """The largest difference between two images' pixels, in levels."""
    return int(np.abs(a.astype(int) - b.astype(int)).max())


def left_of_panel(image: np.ndarray) -> np.ndarray:
    """The canvas's columns left of the panel's drop shadow (~15 px, up to 12 levels darker, whatever the frame):
    there the canvas is the frame pixel for pixel."""
    return image[:, :image.shape[1] - PANEL_SHADOW_PX]


def client_folder(record: Path, index: int = 0, timeout: float = 60.0) -> Path:
    """The folder where the viewer records the frames of its `index`-th browser tab (`--record`)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        folders = sorted(record.glob("client_*"), key=lambda p: int(p.name.split("_")[1]))
        if len(folders) > index:
            return folders[index]
        time.sleep(0.1)
    raise TimeoutError(f"no folder for browser tab {index + 1} in {record} after {timeout:.0f} s")


def panel_commands(browser: Browser) -> list[str]:
    """The commands the panel shows (its code blocks)."""
    return browser.js("[...document.querySelectorAll('pre')].map(e => e.textContent.trim()).filter(t => t)") or []


def panel_text(browser: Browser) -> str:
    return browser.js("document.body.innerText")


def new_direction_source(results: Path, made: dict, source: str) -> list[str]:
    """`diffshadow render`'s flags that make a new direction's SIREN as the run's cache does (`made`: generated.zarr's
    config, read from the store, not from the viewer): with cache: blend the stored SIRENs' blend; else the diffusion
    checkpoint, mixed with that blend at the share sample-shadows chose below 1 (at 0 the blend alone answers)."""
    from diffshadow.lights import OLD_WEIGHTING

    if made.get("cache") == "blend":
        return ["--blend", source, "--blend-k", str(made["blend_k"]),
                "--blend-weights", made.get("blend_weights", OLD_WEIGHTING)]
    flags = ["--diffusion", source]
    mix = made.get("mix")
    if mix is not None and mix["model_share"] < 1:
        flags += ["--blend", str(results / Path(mix["weights"]).name), "--blend-k", str(mix["blend_k"]),
                  "--blend-weights", mix["blend_weights"], "--model-share", repr(mix["model_share"])]
    return flags


def drive_viewer(results, workdir, *, screenshot=None) -> dict:
    """Open `diffshadow view results` in headless Chromium as a user would and measure what it shows: the first
    still frame (drawn at the canvas's own size); an unseen test light picked from the list; a new direction
    typed in (generated by the cache on demand); mode `gt` at two lights; every mode's panel commands; a light
    outside the cache's region (the exact shadow, labelled); a second tab recording apart from the first. Each
    single-mode frame on the canvas is compared with `diffshadow render` for the same camera and light:
    `<name>_psnr_vs_render`; `*_changed_psnr` compare the canvas before and after a light change."""
    results, workdir = Path(results), Path(workdir)  # as given: the panel shows the command with this path
    frames = workdir / "frames"
    log = workdir / "view.log"
    with viewer(results, frames, size=0, log=log) as (url, _):
        # the page at a fixed pixel ratio: viser lowers it when the page draws slowly (SwiftShader on a loaded CPU)
        # without telling the viewer, which then fills a smaller canvas at the size it was told: the canvas is no
        # longer the frame, pixel for pixel (a user's GPU draws this page fast; `viewer-fps` keeps viser's default)
        url = f"{url}/?fixedDpr=1"
        browser = Browser(url, width=800, height=335)
        try:
            out = {}
            record = client_folder(frames)
            # the first frame drawn for the canvas as laid out: under load the client may report the whole
            # window's aspect before the panel takes its side, and the frame for that is replaced at once
            first = next_frame(record, 0, lambda m: [m["width"], m["height"]] == browser.canvas_size())
            out["still_size"], out["canvas_size"] = [first["width"], first["height"]], browser.canvas_size()
            before = shown(browser, first)

            from diffshadow.lights import read_lights
            from diffshadow.store import open_store
            from diffshadow.viewer.scene import cache_source

            n_train = len(read_lights(results / "lights.json")["train"])
            generated = open_store(results / "generated.zarr")
            new_source = new_direction_source(results, generated.config, str(cache_source(results, generated)))

            renders = []  # (name, `diffshadow render` arguments, the image to compare with), rendered at the end

            def check(frame: dict, name: str) -> np.ndarray:
                """The canvas against `diffshadow render` from the camera the viewer starts with (set by the
                server, orbited by nobody since: render's default view), independently of how the viewer reads
                the browser's camera; and the frame the viewer sent against the command its panel shows."""
                on_canvas = shown(browser, frame)
                mode = frame["shown"]
                args = ["--volume", str(results / "volume.zarr"), "--data-inr", str(results / "data_inr.pt"),
                        "--mode", mode, "--azimuth", "30", "--elevation", "25",
                        "--fov", "60", "--size", str(frame["width"]), str(frame["height"]), "--step", "0.5",
                        "--light", *map(repr, frame["light"])]
                if mode == "inr":
                    kind = frame["light_kind"]
                    if kind.startswith("new direction"):
                        args += new_source
                    else:
                        row = int(kind.split(",")[0].split()[-1]) + (n_train if kind.startswith("unseen") else 0)
                        args += ["--weights", str(results / "generated.zarr"), "--light-index", str(row)]
                renders.append((name, args, on_canvas))
                renders.append((f"{name}_panel", shlex.split(frame["command"])[2:], frame["image"]))
                return on_canvas

            def after(action, accept, timeout: float = 180.0) -> dict:
                n = len(list(record.glob("frame_*.json")))
                action()
                return next_frame(record, n, accept, timeout=timeout)

            unseen = after(lambda: browser.choose(*browser.input_beside("pick"), "unseen 1"),
                           lambda m: (m["light_kind"] or "").startswith("unseen test light 1"))
            out["inr_changed_psnr"] = psnr(before, check(unseen, "unseen"))
            new = after(lambda: browser.type_into(*browser.input_beside("azimuth"), "75"),
                        lambda m: (m["light_kind"] or "").startswith("new direction") and new_source[0] in m["command"])
            check(new, "new")
            out["new_light"] = new["light_kind"]
            # the exact shadow, which changes with the light whatever the model learnt
            gt_before = check(after(lambda: browser.choose(*browser.input_beside("mode"), "gt"),
                                    lambda m: m["mode"] == "gt"), "gt_before")
            gt_after = check(after(lambda: browser.type_into(*browser.input_beside("azimuth"), "-105"),
                                   lambda m: m["mode"] == "gt" and m["light"] != new["light"]), "gt_after")
            out["gt_changed_psnr"] = psnr(gt_before, gt_after)
            # outside the cache's light region (below the horizon), mode inr draws the exact shadow and says so
            outside = after(lambda: (browser.choose(*browser.input_beside("mode"), "inr"),
                                     browser.type_into(*browser.input_beside("elevation"), "-30")),
                            lambda m: m["mode"] == "inr" and m["outside"])
            check(outside, "outside")
            out["outside_shown"], out["outside_status"] = outside["shown"], outside["status"]
            out["outside_panel"] = "outside the cache" in panel_text(browser)
            # every mode's panel commands are its frame's (small frames: naive is slow on a CPU)
            browser.type_into(*browser.input_beside("elevation"), "60")
            after(lambda: browser.type_into(*browser.input_beside("height (px, 0: canvas)"), "96"),
                  lambda m: m["height"] == 96)
            out["commands_match"] = {}
            for mode in ("noshadow", "naive", "gt", "inr | gt", "|inr - gt|", "inr"):
                frame = after(lambda mode=mode: browser.choose(*browser.input_beside("mode"), mode),
                              lambda m, mode=mode: m["mode"] == mode and m["height"] == 96)
                try:
                    expected = json.dumps(json.dumps(frame["commands"], separators=(",", ":")))  # as JSON.stringify
                    browser.wait_for(f"(() => {{ const t = [...document.querySelectorAll('pre')].map(e => "
                                     f"e.textContent.trim()).filter(t => t); return JSON.stringify(t) === "
                                     f"{expected}; }})()", timeout=15, what=f"the {mode} frame's commands in the panel")
                    out["commands_match"][mode] = True
                except TimeoutError:
                    out["commands_match"][mode] = {"panel": panel_commands(browser), "frame": frame["commands"]}
                if mode == "inr | gt":
                    out["side_by_side_labels"] = frame["labels"]
                    top = (frame["height"] - frame["height"] // 2) // 2  # the half-size frames, centred
                    band = frame["image"][top + 1:top + 14, 2:40].astype(int)  # the left label's dark band
                    out["side_by_side_label_band"] = float((band <= 30).all(-1).mean())
                if mode == "|inr - gt|":
                    out["diff_scale"], out["diff_status"] = frame["diff_scale"], frame["status"]
            # a second tab records into its own folder, numbered from 1, leaving the first tab's frames as they were
            first_file = sorted(record.glob("frame_*.json"))[0]
            first_json = first_file.read_text()
            second = Browser(url, width=640, height=300)
            try:
                other = client_folder(frames, 1)
                next_frame(other, 0, lambda m: True)
                out["second_tab_folder"] = other.name != record.name
                out["first_tab_kept"] = first_file.read_text() == first_json
                out["second_tab_first"] = sorted(other.glob("frame_*.json"))[0].name
            finally:
                second.close()
            if screenshot is not None:
                browser.type_into(*browser.input_beside("height (px, 0: canvas)"), "0")
                _portrait(browser, record, screenshot)
            images = render_all([(name, args) for name, args, _ in renders], workdir)
            for name, _, seen in renders:
                if name.endswith("_panel"):
                    out[f"{name.removesuffix('_panel')}_frame_vs_panel_max_diff"] = max_diff(seen, images[name])
                else:
                    out[f"{name}_psnr_vs_render"] = psnr(seen, images[name])
                    out[f"{name}_max_diff_vs_render"] = max_diff(left_of_panel(seen), left_of_panel(images[name]))
            return out
        except Exception as e:
            raise AssertionError(f"{e}\n--- the viewer's output:\n{log.read_text()[-3000:]}") from e
        finally:
            browser.close()


RENDER_ALL = """import json, sys
from diffshadow.cli import main
for argv in json.loads(sys.argv[1]):
    main(argv)
"""


def render_all(requests: list[tuple[str, list[str]]], workdir: Path) -> dict[str, np.ndarray]:
    """`diffshadow render ARGS --out <workdir>/<name>.png` for each (name, ARGS), all in one process: the commands
    as a user runs them, without starting PyTorch ten times (3-4 s each on a 2-core machine)."""
    from PIL import Image

    argvs = [["render", *args, "--out", str(workdir / f"{name}.png")] for name, args in requests]
    proc = subprocess.run([sys.executable, "-c", RENDER_ALL, json.dumps(argvs)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"diffshadow render failed: {proc.stderr[-3000:]}")
    return {name: np.asarray(Image.open(workdir / f"{name}.png")) for name, _ in requests}


@contextmanager
def viewer(results: Path, record: Path, *, size: int, log: Path):
    """`diffshadow view results` (or `--scene-config` a scene file) on a free port, recording into `record`, its
    output in `log`; yields (its URL, its process) once it serves, and stops it after."""
    port = free_port()
    source = ["--scene-config", str(results)] if Path(results).suffix in (".yaml", ".yml") else [str(results)]
    with open(log, "w") as f:
        proc = subprocess.Popen([str(DIFFSHADOW), "view", *source, "--port",
                                 str(port), "--size", str(size), "--record", str(record)], stdout=f,
                                stderr=subprocess.STDOUT, text=True, preexec_fn=_dies_with_driver())
    try:
        while "http://" not in log.read_text():
            if proc.poll() is not None:
                raise RuntimeError("diffshadow view exited: " + log.read_text())
            time.sleep(0.1)
        yield f"http://127.0.0.1:{port}", proc
    finally:
        proc.terminate()
        proc.wait(20)


def _frames(record: Path, *, given_up: bool = False) -> list[dict]:
    """Every frame the viewer drew (its frames.jsonl), and with `given_up` the still frames it gave up for a newer
    view too."""
    frames = [json.loads(line) for line in (record / "frames.jsonl").read_text().splitlines()]
    return [f for f in frames if given_up or not f.get("interrupted")]


def _portrait(browser: Browser, record, path) -> None:
    """The page at a reading size: the cached shadow beside the exact one for an unseen test light, from the
    default (framed) view, a full frame at the canvas's size, and the light region's chart in the panel."""
    from PIL import Image

    def after(action, accept):
        n = len(list(record.glob("frame_*.json")))
        action()
        return next_frame(record, n, accept, timeout=300)

    browser.send("Emulation.setDeviceMetricsOverride", width=1000, height=560, deviceScaleFactor=1, mobile=False)
    after(lambda: browser.choose(*browser.input_beside("mode"), "inr | gt"), lambda m: m["mode"] == "inr | gt")
    after(lambda: browser.choose(*browser.input_beside("pick"), "unseen 1"),
          lambda m: (m["light_kind"] or "").startswith("unseen test light 1"))
    frame = next_frame(record, 0, lambda m: (m["light_kind"] or "").startswith("unseen test light 1")
                       and m["mode"] == "inr | gt" and [m["width"], m["height"]] == browser.canvas_size())
    shown(browser, frame)
    browser.js("document.activeElement && document.activeElement.blur()")
    Image.fromarray(browser.screenshot()).save(path)


def slider_thumb(browser: Browser, label: str) -> tuple[float, float, float, float]:
    """(x, y) of the thumb of the slider on the row of `label`, and the x range of its track."""
    return browser.wait_for(_on_row_of(label, """const rects = sel => [...document.querySelectorAll(sel)]
            .map(e => e.getBoundingClientRect()).find(r => r.width > 0 && onRow(r));
        const t = rects('[role="slider"]'), track = rects('[class*="Slider-track"]');
        return t && track ? [t.x + t.width / 2, t.y + t.height / 2, track.x, track.x + track.width] : null;"""),
                            what=f"the slider beside '{label}'")


def _on_row_of(label: str, body: str) -> str:
    """Page script: find the element whose own text is `label`, scroll it into view, then run `body`, which
    sees its rectangle `l` and `onRow(r)`: whether rectangle `r` lies on the label's row."""
    return f"""(() => {{
        const lab = [...document.querySelectorAll('*')].find(e => [...e.childNodes].some(n =>
            n.nodeType === 3 && n.textContent.trim() === {json.dumps(label)}));
        if (!lab) return null;
        lab.scrollIntoView({{block: 'center'}});
        const l = lab.getBoundingClientRect(), y = l.y + l.height / 2;
        const onRow = r => Math.abs(r.y + r.height / 2 - y) < l.height;
        {body} }})()"""


def drag(browser: Browser, start: tuple[float, float], span: tuple[float, float], seconds: float) -> float:
    """Hold the mouse down at `start` and sweep it back and forth over x in `span` for `seconds`; returns the
    time the drag began (time.time())."""
    x, y = start
    browser.send("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
    browser.send("Input.dispatchMouseEvent", type="mousePressed", x=x, y=y, button="left", buttons=1, clickCount=1)
    began, t0 = time.time(), time.monotonic()
    while (elapsed := time.monotonic() - t0) < seconds:
        phase = (elapsed / 2.0) % 2  # a sweep every 2 s
        u = phase if phase < 1 else 2 - phase
        browser.send("Input.dispatchMouseEvent", type="mouseMoved", x=span[0] + u * (span[1] - span[0]), y=y,
                     button="left", buttons=1)
        time.sleep(0.02)
    browser.send("Input.dispatchMouseEvent", type="mouseReleased", x=x, y=y, button="left", buttons=0, clickCount=1)
    return began


CANVAS = 480  # the square canvas' side when measuring, in CSS pixels


def nudge(browser: Browser, thumb: tuple[float, float], px: float) -> float:
    """Move the slider whose thumb is at `thumb` by `px` pixels and let go; returns when the press began
    (time.time())."""
    x, y = thumb
    browser.send("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
    began = time.time()
    browser.send("Input.dispatchMouseEvent", type="mousePressed", x=x, y=y, button="left", buttons=1, clickCount=1)
    browser.send("Input.dispatchMouseEvent", type="mouseMoved", x=x + px, y=y, button="left", buttons=1)
    browser.send("Input.dispatchMouseEvent", type="mouseReleased", x=x + px, y=y, button="left", buttons=0,
                 clickCount=1)
    return began


def _begun_after(record: Path, t: float) -> list[dict]:
    """The frames drawn that began after time `t` (so of the view after any change made before it)."""
    return [f for f in _frames(record) if f["time"] - f["seconds"] > t]


def _wait_for(record: Path, t: float, accept, timeout: float, what: str) -> list[dict]:
    deadline = time.monotonic() + timeout
    while not ((frames := _begun_after(record, t)) and accept(frames)):
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} in {timeout:.0f} s")
        time.sleep(0.02)
    return frames


def measure_response(browser: Browser, record: Path, *, trials: int = 4, into_still_s: float = 2.0,
                     timeout: float = 600.0) -> tuple[dict, float]:
    """What a user waits for when they move the light while a still frame is being drawn: the light's slider nudged
    `into_still_s` after the last answer (the still frame starts 0.3 s after a change), `trials` times; seconds from
    the press to the end of the first frame begun after it (a frame begun before shows the old light) and how many
    still frames were given up; and when the last press was."""
    waits, began = [], 0.0
    for i in range(trials):
        time.sleep(into_still_s)
        x, y, _, _ = slider_thumb(browser, "azimuth")
        began = nudge(browser, (x, y), 6.0 if i % 2 == 0 else -6.0)
        answer = _wait_for(record, began, lambda f: True, timeout, "frame after moving the light")[0]
        waits.append(answer["time"] - began)
    given_up = [f for f in _frames(record, given_up=True) if f.get("interrupted")]
    return {"seconds": waits, "median_s": float(np.median(waits)), "max_s": max(waits),
            "given_up": len(given_up)}, began


def measure_sharpening(browser: Browser, record: Path, since: float, *, timeout: float = 600.0) -> dict:
    """What a user sees once they stop moving the light: the frames drawn after one nudge of its slider, made once
    the viewer is idle (the still frame of the last change, at `since`, drawn), to the still frame at full size,
    each with its size and the seconds since the press."""
    def whole(frames: list[dict]) -> bool:
        return any(f["kind"] == "full" for f in frames)

    _wait_for(record, since, whole, timeout, "still frame")
    time.sleep(1.0)
    x, y, _, _ = slider_thumb(browser, "azimuth")
    began = nudge(browser, (x, y), 6.0)
    after = _wait_for(record, began, whole, timeout, "still frame after moving the light")
    frames = after[:next(i for i, f in enumerate(after) if f["kind"] == "full") + 1]
    still = [f for f in frames if f["kind"] != "preview"]
    return {"frames": [[f["kind"], f"{f['width']}x{f['height']}", round(f["time"] - began, 2)] for f in frames],
            "first_still_s": still[0]["time"] - began, "full_s": still[-1]["time"] - began}


def measure_viewer(results, workdir, *, sizes=(128, 256), seconds: float = 8.0, mode: str | None = None) -> dict:
    """The viewer's frame rate as a user gets it in Chromium on this machine, in `mode` (None: the first offered):
    the light's azimuth slider dragged for `seconds`, then the camera orbited with the mouse, then the light moved
    while a still frame draws (`measure_response`) and the frames that follow when it stops (`measure_sharpening`),
    at each image height (a square canvas); full-size frame times once still; a new direction's generation time;
    the viewer's peak resident memory. `results`: a results folder, or a scene file (modes noshadow and gt)."""
    results, out = Path(results).resolve(), {}
    for size in sizes:
        root = Path(workdir) / f"frames_{size}"
        with viewer(results, root, size=size, log=Path(workdir) / f"view_{size}.log") as (url, proc):
            browser = Browser(url, width=1100, height=(size or CANVAS) + 400)
            try:
                record = client_folder(root)
                rect = browser.canvas_rect()
                time.sleep(1)
                rect = browser.canvas_rect()
                panel = browser.js("innerWidth") - rect["width"]
                # a square canvas, the panel beside it (a narrower page puts the panel over the canvas)
                browser.send("Emulation.setDeviceMetricsOverride", width=int(panel + CANVAS), height=CANVAS,
                             deviceScaleFactor=1, mobile=False)
                next_frame(record, 0, lambda m, s=size or CANVAS: m["height"] == s)
                browser.dismiss_notifications()
                if mode is not None:
                    chosen = time.time()
                    browser.choose(*browser.input_beside("mode"), mode)
                    _wait_for(record, chosen, lambda fs: any(f["kind"] == "full" and f["mode"] == mode for f in fs),
                              600.0, f"still frame in mode {mode}")
                time.sleep(2)
                x, y, lo, hi = slider_thumb(browser, "azimuth")
                began = drag(browser, (x, y), (lo + 2, hi - 2), seconds)
                light = _rate(record, began, seconds)
                time.sleep(2)
                rect = browser.canvas_rect()
                cx, cy = rect["x"] + rect["width"] / 2, rect["y"] + rect["height"] / 2
                began = drag(browser, (cx, cy), (cx - rect["width"] / 4, cx + rect["width"] / 4), seconds)
                orbit = _rate(record, began, seconds)
                response, last_press = measure_response(browser, record)
                sharpening = measure_sharpening(browser, record, last_press)
                time.sleep(2)
            finally:
                browser.close()
            frames = _frames(record)
            full = [f["seconds"] for f in frames if f["kind"] == "full" and f["height"] == (size or CANVAS)]
            made = [f["generate_s"] for f in frames if f.get("generate_s") is not None]
            status = Path(f"/proc/{proc.pid}/status").read_text()
            peak = int(re.search(r"VmHWM:\s+(\d+) kB", status).group(1)) * 1024
            swept = [f for f in frames if f.get("exact_by") == "sweep"]
            out[size] = {"mode": mode or frames[0]["mode"], "previews_by_the_sweep": len(swept),
                         "dragging_light": light, "orbiting_camera": orbit, "light_moved_while_still": response,
                         "after_the_light_stops": sharpening,
                         "still_fps": 1 / float(np.median(full)) if full else None, "still_frames": len(full),
                         "generate_s_median": float(np.median(made)) if made else None, "generated": len(made),
                         "peak_rss_mib": peak / 2 ** 20}
            print(f"[viewer {size}] {out[size]}", flush=True)
    return out


def _rate(record, began: float, seconds: float) -> dict:
    during = [f for f in _frames(record) if began <= f["time"] <= began + seconds]
    sizes = sorted({f"{f['width']}x{f['height']}" for f in during})
    return {"fps": len(during) / seconds, "frames": len(during), "sizes": sizes}


def report_screenshots(report, out, *, item: str = "summary", height: int = 2900) -> None:
    """The report's landing page, and the first item of subcategory `item` opened in the report's own viewer
    (Results → subcategory → eye button), as a reader would click through it: <out>/landing.png, <out>/<item>.png."""
    from pathlib import Path

    from PIL import Image

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    browser = Browser(Path(report).resolve().as_uri(), width=1400, height=1100)
    try:
        browser.send("Emulation.setDeviceMetricsOverride", width=1400, height=1100, deviceScaleFactor=1, mobile=False)
        time.sleep(3)
        Image.fromarray(browser.screenshot()).save(out / "landing.png")
        browser.send("Emulation.setDeviceMetricsOverride", width=1400, height=height, deviceScaleFactor=1,
                     mobile=False)
        for text in ("Results", item):
            if not browser.js(f"""(() => {{ const a = [...document.querySelectorAll('a')].find(a =>
                    a.textContent.trim() == {json.dumps(text)}); if (a) a.click(); return !!a; }})()"""):
                raise SystemExit(f"{report}: the report has no link {text!r}")
            time.sleep(1)
        browser.js("document.querySelector('td a').click()")  # the first item's eye button
        time.sleep(2)
        Image.fromarray(browser.screenshot()).save(out / f"{item}.png")
        print(f"wrote {out / 'landing.png'} and {out / (item + '.png')}")
    finally:
        browser.close()


def main() -> None:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    v = sub.add_parser("viewer", help="the viewer's browser test on a finished scene, and a screenshot of the page")
    v.add_argument("results", help="a finished scene's results folder")
    v.add_argument("--screenshot", help="PNG of the page to write (docs/images/viewer.png)")
    f = sub.add_parser("viewer-fps", help="the viewer's frame rates as a user gets them in Chromium")
    f.add_argument("results", help="a finished scene's results folder, or a scene file (config/scenes/*.yaml)")
    f.add_argument("--mode", help="the panel's mode to measure (default: the first offered)")
    f.add_argument("--sizes", type=int, nargs="+", default=[0, 128],
                   help="image heights (square images; 0: the canvas's own, 480)")
    f.add_argument("--out", help="JSON for the figures")
    r = sub.add_parser("report", help="screenshots of a Snakemake report")
    r.add_argument("report", help="report.html")
    r.add_argument("--item", default="summary", help="the report subcategory whose first item to open")
    r.add_argument("--out", default="shots")
    r.add_argument("--height", type=int, default=2900, help="viewport height for the item (tall tables)")
    a = p.parse_args()
    if a.what == "report":
        report_screenshots(a.report, a.out, item=a.item, height=a.height)
        return
    with tempfile.TemporaryDirectory() as tmp:
        if a.what == "viewer-fps":
            figures = measure_viewer(a.results, tmp, sizes=a.sizes, mode=a.mode)
        else:
            figures = drive_viewer(a.results, tmp, screenshot=a.screenshot)
        print(json.dumps(figures, indent=1))
        if getattr(a, "out", None):
            with open(a.out, "w") as fh:
                fh.write(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
