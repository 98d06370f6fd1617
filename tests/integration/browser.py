"""A headless Chromium driven over the DevTools protocol, for tests of web pages.

Debian's chromium (``deploy/browser.sh`` installs it when missing) started with
``--remote-debugging-port=0``; its page target is driven with the protocol's own
commands over a websocket (websocket-client): navigate, evaluate JavaScript, take a
screenshot. The flags keep Chromium off the network it is not given (this machine
refuses its background connections).
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import subprocess
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import websocket

from swarmrec.runtime.hosting import terminate

__all__ = ["Browser", "chromium_path"]

REPO = Path(__file__).resolve().parents[2]

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--no-first-run",
    "--remote-allow-origins=*",
)


def chromium_path() -> str:
    """The browser's path (installed from Debian by deploy/browser.sh when missing)."""
    done = subprocess.run(
        [str(REPO / "deploy/browser.sh")], capture_output=True, text=True, timeout=900, check=False
    )
    assert done.returncode == 0, f"deploy/browser.sh failed:\n{done.stderr}"
    return done.stdout.strip().splitlines()[-1]


class Browser:
    """One headless Chromium with one page; a context manager."""

    def __init__(self, path: str, profile: Path, width: int = 1400, height: int = 1000) -> None:
        log = profile.with_suffix(".log")
        with log.open("w") as sink:  # the child keeps its own descriptor
            self.proc = subprocess.Popen(
                [path, *FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
                 f"--window-size={width},{height}", "about:blank"],
                stdout=subprocess.DEVNULL,
                stderr=sink,
                # Its scratch files (org.chromium.Chromium.*) go beside the profile, not in /tmp.
                env={**os.environ, "TMPDIR": str(profile.parent)},
            )  # fmt: skip
        deadline = time.monotonic() + 60
        port = None
        while port is None:
            found = re.search(
                r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", log.read_text(errors="replace")
            )
            port = int(found.group(1)) if found else None
            if port is None:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(
                        f"chromium did not open its DevTools port:\n{log.read_text()[-2000:]}"
                    )
                time.sleep(0.1)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as reply:
            targets = json.loads(reply.read())
        page = next(t for t in targets if t["type"] == "page")
        self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=30)
        self.ids = itertools.count(1)
        # The page's own viewport, whatever the browser's window keeps for itself.
        self.call(
            "Emulation.setDeviceMetricsOverride",
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command and its result (events in between are skipped)."""
        n = next(self.ids)
        self.ws.send(json.dumps({"id": n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == n:
                if "error" in msg:
                    raise AssertionError(f"{method}: {msg['error']}")
                result: dict[str, Any] = msg["result"]
                return result

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise AssertionError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, ok: Callable[[Any], bool], timeout_s: float, what: str) -> Any:
        """Evaluate ``expression`` until ``ok`` holds for its value; that value. An expression
        that throws (the element is not on the page yet: a busy machine renders it late) is
        evaluated again until the time is up."""
        deadline = time.monotonic() + timeout_s
        value: Any = None
        while time.monotonic() < deadline:
            try:
                value = self.evaluate(expression)
            except AssertionError as e:
                value = f"(it throws: {e})"
            else:
                if ok(value):
                    return value
            time.sleep(0.2)
        raise AssertionError(f"{what}: the page still shows {value!r} after {timeout_s} s")

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def close(self) -> None:
        try:
            self.ws.close()
        finally:
            terminate(self.proc)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
