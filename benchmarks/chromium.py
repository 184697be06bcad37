"""Headless Chromium driven over the Chrome DevTools Protocol (a websocket speaking JSON), for the viewer's
end-to-end test and benchmark: find (or install) the browser, open a page, run JavaScript, send input
events, read the console and take screenshots.

The protocol: https://chromedevtools.github.io/devtools-protocol/ (Page, Runtime, Input, DOM, Log).
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from websockets.sync.client import ClientConnection, connect

NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")
FLAGS = (
    "--headless=new",
    "--no-sandbox",  # root (CI, containers) has no user namespace sandbox
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-gpu-sandbox",
    "--disable-extensions",
    "--disable-background-networking",
    "--use-angle=swiftshader",  # WebGL on the CPU: the same pixels on every machine
    "--enable-unsafe-swiftshader",
    "--hide-scrollbars",
    "--mute-audio",
)


class BrowserUnavailableError(RuntimeError):
    """No Chromium could be found or installed (the message says what was tried)."""


def find_chromium(install: bool = False) -> str:
    """The path of a Chromium executable: ``$BODYFIT_CHROMIUM``, else the first of :data:`NAMES` on PATH.
    With ``install``, a missing browser is installed from Debian's packages (``apt-get install chromium``)
    where apt-get runs as root.

    Raises:
        BrowserUnavailableError: none found (and none could be installed).
    """
    given = os.environ.get("BODYFIT_CHROMIUM")
    if given:
        if Path(given).is_file():
            return given
        raise BrowserUnavailableError(f"BODYFIT_CHROMIUM={given} is not a file")
    for name in NAMES:
        path = shutil.which(name)
        if path:
            return path
    if install and shutil.which("apt-get") and os.geteuid() == 0:
        _apt_install()
        path = shutil.which("chromium")
        if path:
            return path
    raise BrowserUnavailableError(
        f"no Chromium found (looked for {', '.join(NAMES)} on PATH and $BODYFIT_CHROMIUM)"
        + ("" if install else "; install it with `apt-get install chromium`")
        + ("; apt-get could not install it" if install else "")
    )


def _apt_install() -> None:
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "chromium"]):
        try:
            subprocess.run(cmd, env=env, capture_output=True, timeout=600, check=False)
        except (OSError, subprocess.TimeoutExpired):
            return


@dataclass
class Page:
    """One browser tab over its DevTools websocket. ``console`` collects every console message and
    uncaught exception as ``(level, text)``; :meth:`errors` the error-level ones."""

    ws: ClientConnection
    console: list[tuple[str, str]] = field(default_factory=list)
    _next: int = 0

    def call(self, method: str, timeout_s: float = 60.0, **params: Any) -> dict[str, Any]:
        """Send one protocol command and return its result, collecting the events that arrive meanwhile.

        Raises:
            RuntimeError: the browser answered with an error.
            TimeoutError: no answer within ``timeout_s``.
        """
        self._next += 1
        ident = self._next
        self.ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"{method}: no answer within {timeout_s:g} s")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == ident:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                result: dict[str, Any] = msg.get("result", {})
                return result
            self._event(msg)

    def _event(self, msg: dict[str, Any]) -> None:
        method, params = msg.get("method"), msg.get("params", {})
        if method == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in params.get("args", []))
            self.console.append((params.get("type", "log"), text))
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            text = details.get("exception", {}).get("description") or details.get("text", "")
            self.console.append(("error", f"uncaught: {text}"))
        elif method == "Log.entryAdded":
            entry = params.get("entry", {})
            text = f"{entry.get('url', '')} {entry.get('text', '')}"
            self.console.append((entry.get("level", "info"), text))

    def errors(self) -> list[str]:
        """The error-level console messages and uncaught exceptions so far."""
        self.pump()
        return [text for level, text in self.console if level == "error"]

    def pump(self) -> None:
        """Read the events waiting on the socket (console messages) without blocking."""
        self.evaluate("0")

    def evaluate(self, expression: str, timeout_s: float = 60.0) -> Any:
        """The value of ``expression`` in the page (promises awaited; JSON values returned).

        Raises:
            RuntimeError: the expression threw (with its message).
        """
        result = self.call(
            "Runtime.evaluate",
            timeout_s,
            expression=expression,
            awaitPromise=True,
            returnByValue=True,
        )
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise RuntimeError(details.get("exception", {}).get("description") or details.get("text"))
        return result.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0, poll_s: float = 0.05) -> Any:
        """Poll ``expression`` until it is truthy; return its value.

        Raises:
            TimeoutError: still falsy after ``timeout_s`` (with the console's errors).
        """
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(poll_s)
        raise TimeoutError(
            f"{expression!r} still false after {timeout_s:g} s; console errors: {self.errors()}"
        )

    def navigate(self, url: str, timeout_s: float = 30.0) -> None:
        """Open ``url`` and wait until its load event fired."""
        self.call("Page.navigate", url=url)
        self.wait_for("document.readyState === 'complete'", timeout_s)

    def screenshot(self, path: Path | None = None) -> bytes:
        """The viewport as PNG bytes (also written to ``path`` when given)."""
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        return data

    def set_files(self, selector: str, paths: list[Path]) -> None:
        """Choose ``paths`` in the file input ``selector`` (what a user does in the file dialog)."""
        root = self.call("DOM.getDocument", depth=0)["root"]["nodeId"]
        node = self.call("DOM.querySelector", nodeId=root, selector=selector)["nodeId"]
        if not node:
            raise RuntimeError(f"no element matches {selector!r}")
        self.call("DOM.setFileInputFiles", nodeId=node, files=[str(p.resolve()) for p in paths])

    def hover(self, x: float, y: float) -> None:
        """Move the mouse to (x, y) CSS pixels of the viewport."""
        self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)

    def press(self, key: str, code: int) -> None:
        """Press and release ``key`` (DOM key name, e.g. "End") with Windows virtual key ``code`` (35) on
        the focused element."""
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", type=kind, key=key, code=key, windowsVirtualKeyCode=code)

    def drop_files(self, selector: str, paths: list[Path]) -> None:
        """Drag ``paths`` from outside the browser and drop them on the centre of ``selector``."""
        box = self.evaluate(
            f"(() => {{ const r = document.querySelector({json.dumps(selector)}).getBoundingClientRect();"
            " return [r.x + r.width / 2, r.y + r.height / 2]; })()"
        )
        data = {"items": [], "files": [str(p.resolve()) for p in paths], "dragOperationsMask": 1}
        for kind in ("dragEnter", "dragOver", "drop"):
            self.call("Input.dispatchDragEvent", type=kind, x=box[0], y=box[1], data=data)


@contextmanager
def browser(width: int = 1280, height: int = 800, install: bool = False) -> Iterator[Page]:
    """A headless Chromium with one blank tab, closed on exit (its profile in a temporary folder).

    Raises:
        BrowserUnavailableError: no browser (see :func:`find_chromium`).
        RuntimeError: the browser did not start (with the end of its output).
    """
    exe = find_chromium(install)
    # ignore_cleanup_errors: a helper process of the browser may still write to the profile as it ends
    with (
        tempfile.TemporaryDirectory(prefix="bodyfit-chromium-", ignore_cleanup_errors=True) as profile,
        open(Path(profile) / "chromium.log", "w+") as log,
    ):
        proc = subprocess.Popen(
            [
                exe,
                *FLAGS,
                f"--window-size={width},{height}",
                f"--user-data-dir={profile}",
                "--remote-debugging-port=0",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=log,  # a file, never a pipe: a chatty browser would block on a full one
            start_new_session=True,  # its own process group: its helper processes end with it
        )
        try:
            port = _devtools_port(proc, Path(profile))
            tabs = httpx.get(f"http://127.0.0.1:{port}/json/list", timeout=10).json()
            url = next(t["webSocketDebuggerUrl"] for t in tabs if t.get("type") == "page")
            with connect(url, max_size=2**28, open_timeout=10) as ws:
                page = Page(ws)
                for domain in ("Page", "Runtime", "Log", "DOM"):
                    page.call(f"{domain}.enable")
                page.call(
                    "Emulation.setDeviceMetricsOverride",
                    width=width,
                    height=height,
                    deviceScaleFactor=1,
                    mobile=False,
                )
                yield page
        finally:
            _stop(proc)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """End the browser, then whatever helper process of its group outlived it."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


def _devtools_port(proc: subprocess.Popen[bytes], profile: Path, timeout_s: float = 30.0) -> int:
    """The port Chromium chose: it writes it to DevToolsActivePort in its profile once listening."""
    marker = profile / "DevToolsActivePort"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = (profile / "chromium.log").read_text(errors="replace")
            raise RuntimeError(f"Chromium exited ({proc.returncode}): {err[-2000:]}")
        if marker.is_file():
            lines = marker.read_text().splitlines()
            if lines and lines[0].isdigit():
                return int(lines[0])
        time.sleep(0.05)
    raise RuntimeError(f"Chromium did not open its DevTools port within {timeout_s:g} s")
