"""Headless Chromium driven over the DevTools protocol, for the baked viewer's checks and
benchmarks: open a page, wait for a JavaScript condition, evaluate expressions (promises
awaited), and list every URL the page requested.

    with Browser(gl="llvmpipe") as b:
        b.open("http://127.0.0.1:8000/?view=0", ready="window.shells && window.shells.ready")
        frame = b.evaluate("window.shells.pixels()")

``gl``: "llvmpipe" (Mesa's software GL through ANGLE's EGL backend, ``--use-angle=gl-egl``)
or "swiftshader" (Chromium's own software GL). ``offline``: every host name but 127.0.0.1
resolves to nothing, so a page that needs the network fails to load what it needs.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.request
from typing import Any

from shells.errors import InputError

FLAGS = ("--headless", "--no-sandbox", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--disable-quic",
         "--disable-gpu-vsync", "--disable-frame-rate-limit", "--ignore-gpu-blocklist")
GL_FLAGS = {"llvmpipe": ("--use-angle=gl-egl",),
            "swiftshader": ("--use-angle=swiftshader", "--enable-unsafe-swiftshader")}


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Browser:
    def __init__(self, gl: str = "llvmpipe", offline: bool = True, size: tuple[int, int] =
                 (1024, 1024), timeout: float = 60.0):
        exe = chromium()
        if exe is None:
            raise InputError("chromium not found; apt-get install chromium")
        if gl not in GL_FLAGS:
            raise InputError(f"--gl {gl}: one of {', '.join(GL_FLAGS)}")
        self.timeout = timeout
        self.port = free_port()
        self.profile = tempfile.TemporaryDirectory(prefix="shells-chromium-",
                                                   ignore_cleanup_errors=True)
        args = [exe, *FLAGS, *GL_FLAGS[gl], f"--user-data-dir={self.profile.name}",
                f"--window-size={size[0]},{size[1]}", f"--remote-debugging-port={self.port}"]
        if offline:
            args.append("--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1")
        self.proc = subprocess.Popen(args + ["about:blank"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        self.requests: list[str] = []
        self.failed: list[str] = []
        self.console: list[str] = []
        self._id = 0
        self.ws = None

    def __enter__(self) -> "Browser":
        from websockets.sync.client import connect

        t0 = time.time()
        while True:
            try:
                targets = json.loads(urllib.request.urlopen(
                    f"http://127.0.0.1:{self.port}/json", timeout=2).read())
                page = next(t for t in targets if t.get("type") == "page")
                break
            except (OSError, StopIteration):
                if time.time() - t0 > 30 or self.proc.poll() is not None:
                    self.close()
                    raise RuntimeError("chromium did not start")
                time.sleep(0.2)
        self.ws = connect(page["webSocketDebuggerUrl"], max_size=None)
        for method in ("Network.enable", "Runtime.enable", "Page.enable"):
            self.call(method)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        if self.ws is not None:
            self.ws.close()
            self.ws = None
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.profile.cleanup()

    def _event(self, msg: dict[str, Any]) -> None:
        method, p = msg.get("method"), msg.get("params", {})
        if method == "Network.requestWillBeSent":
            self.requests.append(p["request"]["url"])
        elif method == "Network.loadingFailed":
            self.failed.append(f"{p.get('errorText')} ({p.get('requestId')})")
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            self.console.append("exception: " + str(d.get("exception", {}).get(
                "description", d.get("text"))))
        elif method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "warning"):
            self.console.append(p["type"] + ": " + " ".join(
                str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))

    def call(self, method: str, timeout: float | None = None, **params: Any) -> dict[str, Any]:
        """One DevTools command; its result (events that arrive meanwhile are recorded)."""
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.time() + (timeout or self.timeout)
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, deadline - time.time())))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def evaluate(self, expression: str, timeout: float | None = None) -> Any:
        """The value of a JavaScript expression (a promise is awaited), as JSON."""
        r = self.call("Runtime.evaluate", timeout=timeout, expression=expression,
                      awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise RuntimeError(f"{expression}: " + str(d.get("exception", {}).get(
                "description", d.get("text"))))
        return r.get("result", {}).get("value")

    def open(self, url: str, ready: str, timeout: float | None = None) -> None:
        """Navigate to ``url`` and wait until the expression ``ready`` is true."""
        self.call("Page.navigate", url=url)
        deadline = time.time() + (timeout or self.timeout)
        while not self.evaluate(f"Boolean({ready})"):
            if time.time() > deadline:
                raise RuntimeError(f"{url}: not ready after {timeout or self.timeout:.0f} s; "
                                   f"console: {self.console[-5:]}")
            time.sleep(0.2)
