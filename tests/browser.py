"""Drive the system's headless Chromium over the DevTools protocol (no browser download).

Chromium runs with software GL (SwiftShader) so WebGL works without a GPU. Every wait is on a
condition (a line on a pipe, a DevTools event, a screenshot that shows what is expected) under a
watchdog deadline; nothing sleeps for a fixed time.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import subprocess
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np

CHROMIUM_FLAGS = [
    "--headless=new",
    "--no-sandbox",  # CI runs as root
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-extensions",
    "--window-size=800,600",
    "--remote-debugging-port=0",
]


#: The browsers tried, in this order, on PATH: Chromium (chromium on Debian, Arch, Alpine;
#: chromium-browser on Fedora) or Google Chrome (google-chrome, e.g. on GitHub's Ubuntu runners).
#: ``M360_BROWSER`` (a name or a path) chooses one instead. .ci/run reads this list.
BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def chromium_path() -> str | None:
    """The headless browser's executable, or None (see `missing_browser` for why)."""
    chosen = os.environ.get("M360_BROWSER")
    if chosen:
        return shutil.which(chosen)
    return next((path for name in BROWSER_NAMES if (path := shutil.which(name))), None)


def missing_browser() -> str:
    """Why `chromium_path` found no browser: the viewer test's skip (or failure) reason."""
    chosen = os.environ.get("M360_BROWSER")
    if chosen:
        return f"M360_BROWSER={chosen} is not an executable browser"
    return (
        f"no headless browser: none of {', '.join(BROWSER_NAMES)} is on PATH "
        "(install Chromium, e.g. apt-get install chromium, or set M360_BROWSER to Chrome's path)"
    )


def read_line(stream: Any, predicate: Callable[[str], bool], deadline: float) -> str:
    """The first line of ``stream`` satisfying ``predicate``, read in a thread under a deadline."""
    found: list[str] = []
    seen: list[str] = []

    def reader() -> None:
        for raw in iter(stream.readline, ""):
            seen.append(raw)
            if predicate(raw):
                found.append(raw.strip())
                return

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    thread.join(max(0.0, deadline - time.monotonic()))
    if not found:
        raise TimeoutError(f"no expected line before the deadline; got {''.join(seen)[-2000:]}")
    return found[0]


class DevTools:
    """A minimal Chrome DevTools Protocol client on one page target."""

    def __init__(self, ws_url: str) -> None:
        from websockets.sync.client import connect

        self.ws = connect(ws_url, max_size=64 * 1024 * 1024)
        self.ids = itertools.count(1)

    def call(self, method: str, deadline: float, **params: Any) -> dict[str, Any]:
        msg_id = next(self.ids)
        self.ws.send(json.dumps({"id": msg_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def wait_event(self, name: str, deadline: float) -> dict[str, Any]:
        while True:
            event = json.loads(self.ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            if event.get("method") == name:
                return event.get("params", {})

    def screenshot(self, deadline: float) -> np.ndarray:
        data = self.call("Page.captureScreenshot", deadline, format="png")["data"]
        image = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        return image[:, :, ::-1]  # RGB

    def close(self) -> None:
        self.ws.close()


@contextmanager
def chromium(profile: Path, deadline: float) -> Iterator[DevTools]:
    """Start headless Chromium, yield a DevTools client on its first page, stop it after."""
    exe = chromium_path()
    assert exe is not None
    proc = subprocess.Popen(
        [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    client = None
    try:
        line = read_line(proc.stderr, lambda s: "DevTools listening on" in s, deadline)
        port = int(line.rsplit(":", 1)[1].split("/", 1)[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            targets = json.loads(r.read())
        page = next(t for t in targets if t["type"] == "page")
        client = DevTools(page["webSocketDebuggerUrl"])
        client.call("Page.enable", deadline)
        yield client
    finally:
        if client is not None:
            client.close()
        proc.kill()
        proc.wait(timeout=30)
        assert proc.stderr is not None
        proc.stderr.close()
