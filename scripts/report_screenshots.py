"""Screenshots of a Snakemake report in headless Chromium: the landing page, and one result item opened in
the report's own viewer (Results → subcategory → eye button), as a reader would click through it.

    pip install websocket-client          # the DevTools protocol client (not a package dependency)
    python scripts/report_screenshots.py report.html --item summary --out shots

Needs Debian's `chromium` on PATH. Writes <out>/landing.png and <out>/<item>.png.
"""

from __future__ import annotations

import argparse
import base64
import json
import subprocess
import time
import urllib.request
from pathlib import Path

PORT = 9333


class Page:
    """One headless Chromium tab driven over the DevTools protocol."""

    def __init__(self, width: int, height: int):
        import websocket

        self.proc = subprocess.Popen(
            ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
             f"--remote-debugging-port={PORT}", "--remote-allow-origins=*", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for _ in range(100):
            try:
                tabs = json.load(urllib.request.urlopen(f"http://127.0.0.1:{PORT}/json"))
                break
            except OSError:
                time.sleep(0.2)
        else:
            raise SystemExit("chromium did not open its DevTools port")
        self.ws = websocket.create_connection(next(t for t in tabs if t["type"] == "page")["webSocketDebuggerUrl"])
        self.n = 0
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                  mobile=False)

    def call(self, method: str, **params):
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.n:
                return msg.get("result", {})

    def js(self, expr: str):
        return self.call("Runtime.evaluate", expression=expr, returnByValue=True)["result"].get("value")

    def click_link(self, text: str) -> None:
        found = self.js(f"(() => {{ const a = Array.from(document.querySelectorAll('a'))"
                        f".find(a => a.textContent.trim() == {json.dumps(text)}); if (a) a.click(); return !!a; }})()")
        if not found:
            raise SystemExit(f"the report has no link {text!r}")
        time.sleep(1)

    def shot(self, path: Path) -> None:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))
        print(f"wrote {path}")

    def close(self) -> None:
        self.proc.terminate()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path)
    ap.add_argument("--item", default="summary", help="the report subcategory whose first item to open")
    ap.add_argument("--out", type=Path, default=Path("shots"))
    ap.add_argument("--height", type=int, default=2900, help="viewport height for the item (tall tables)")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    page = Page(1400, 1100)
    try:
        page.call("Page.navigate", url=a.report.resolve().as_uri())
        time.sleep(3)
        page.shot(a.out / "landing.png")
        page.call("Emulation.setDeviceMetricsOverride", width=1400, height=a.height, deviceScaleFactor=1, mobile=False)
        page.click_link("Results")
        page.click_link(a.item)
        page.js("document.querySelector('td a').click()")  # the first item's eye button
        time.sleep(2)
        page.shot(a.out / f"{a.item}.png")
    finally:
        page.close()


if __name__ == "__main__":
    main()
