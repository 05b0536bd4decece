"""Headless Chromium for the `dla view` page: the one command line the page's benchmark
(`dla bench speed --suite view`) and its browser tests run it with (software WebGL2 through
SwiftShader, the Debian package `chromium`), and a DevTools client that calls the page's JS API
in real time."""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
from PIL import Image


def chromium() -> str | None:
    """The Chromium executable on PATH, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


def chromium_command(
    url: str, profile: Path, width: int, height: int, *action: str, budget_ms: int | None = 30000
) -> list[str]:
    """One headless run of `url` at width x height CSS pixels (device scale 1) after `budget_ms` of
    virtual time (the page's awaits and animation frames run; synchronous JS takes real time;
    None: real time, e.g. under --remote-debugging-pipe), doing `action` (e.g. --dump-dom,
    --screenshot=PNG)."""
    exe = chromium()
    if exe is None:
        raise FileNotFoundError("headless Chromium not installed (Debian: apt-get install chromium)")
    return [
        exe,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-extensions",
        "--no-first-run",
        "--force-device-scale-factor=1",
        "--force-color-profile=srgb",
        "--hide-scrollbars",
        f"--user-data-dir={profile}",
        f"--window-size={width},{height}",
        *([f"--virtual-time-budget={budget_ms}"] if budget_ms is not None else []),
        *action,
        url,
    ]


class DevToolsPage:
    """Headless Chromium driven over the DevTools protocol on a pipe (--remote-debugging-pipe:
    the browser reads NUL-terminated JSON commands on fd 3 and answers on fd 4), in real time,
    for what a one-shot --screenshot cannot do: call the page's JS API while it plays."""

    def __init__(self, profile: Path, width: int, height: int):
        to_chrome, self._out = os.pipe()
        self._in, from_chrome = os.pipe()

        def fds():  # in the child: the pipe ends on fds 3 and 4
            a, b = os.dup(to_chrome), os.dup(from_chrome)
            os.dup2(a, 3)
            os.dup2(b, 4)

        cmd = chromium_command("about:blank", profile, width, height, "--remote-debugging-pipe", budget_ms=None)
        self.proc = subprocess.Popen(
            cmd, pass_fds=(3, 4), preexec_fn=fds, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        os.close(to_chrome)
        os.close(from_chrome)
        self._buf, self._id, self.session = b"", 0, None
        page = next(t for t in self.send("Target.getTargets")["targetInfos"] if t["type"] == "page")
        self.session = self.send("Target.attachToTarget", {"targetId": page["targetId"], "flatten": True})["sessionId"]
        self.send(
            "Emulation.setDeviceMetricsOverride",
            {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
        )

    def send(self, method: str, params: dict | None = None) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}}
        if self.session is not None:
            message["sessionId"] = self.session
        os.write(self._out, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._in, 1 << 16)
                if not chunk:
                    raise RuntimeError("Chromium closed the DevTools pipe")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"DevTools {method}: {reply['error']}")
                return reply["result"]

    def js(self, expression: str):
        result = self.send("Runtime.evaluate", {"expression": expression, "awaitPromise": True, "returnByValue": True})
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, seconds: float = 60.0):
        """Poll until `expression` is truthy (a liveness bound, not a speed check)."""
        deadline = time.monotonic() + seconds
        while not (value := self.js(expression)):
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out waiting for {expression}")
            time.sleep(0.05)
        return value

    def screenshot(self) -> np.ndarray:
        data = base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(30)
        os.close(self._out)
        os.close(self._in)


def time_page(page: Path, width: int, height: int, frames: int, profile: Path) -> dict:
    """The page's own timing (viewer.js `timeFrames`) of `frames` successive frames at
    width x height in real time: {"fps", "js_ms", "gl_ms", "frame"} (frame: what the page shows
    afterwards). Raises RuntimeError if the page reports an error."""
    chrome = DevToolsPage(profile, width, height)
    try:
        chrome.send("Page.navigate", {"url": f"{page.resolve().as_uri()}#ui=0&play=0"})
        chrome.wait_for("window.dlaReady === true || !!document.documentElement?.dataset.dlaError", 300.0)
        error = chrome.js("document.documentElement.dataset.dlaError || ''")
        if error:
            raise RuntimeError(f"the page failed: {error}")
        out = chrome.js(f"window.dlaView.timeFrames({int(frames)})")
        out["frame"] = chrome.js("window.dlaView.state().frame")
        return out
    finally:
        chrome.close()
