"""Headless Chromium driven over the DevTools protocol, for the viewer's browser test.

Chromium renders WebGL in software (SwiftShader) without a display. The DevTools connection uses
`websockets`, which viser already depends on.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from programs import require_program

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
INSTALL = "apt-get install chromium (Debian, Ubuntu), or any Chromium or Chrome on PATH"


def require_browser() -> str:
    """The first Chromium-family executable on PATH; without one the calling test skips (fails
    under CI=true), naming the install command (`programs.require_program`)."""
    return require_program(BROWSERS, "this test drives a headless Chromium", INSTALL)


class Chromium:
    """One headless browser with one page; a context manager that ends the process."""

    def __init__(self, executable: str, size: tuple[int, int] = (1000, 700)):
        self._profile = tempfile.mkdtemp(prefix="nmjax-chromium-")
        # A file, not a pipe: Chromium keeps logging, and a full pipe would block it.
        self._log = open(Path(self._profile) / "stderr.log", "w+")
        self._process = subprocess.Popen(
            [
                executable,
                "--headless",
                "--no-sandbox",  # tests run as root in CI containers
                "--enable-unsafe-swiftshader",  # WebGL without a GPU
                "--use-angle=swiftshader",
                f"--window-size={size[0]},{size[1]}",
                "--remote-debugging-port=0",
                f"--user-data-dir={self._profile}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=self._log,
        )
        try:
            self._socket = self._connect()
        except BaseException:
            self.close()
            raise
        self._id = 0
        self._session: str | None = None

    def _connect(self, timeout: float = 60.0) -> Any:
        from websockets.sync.client import connect

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self._process.poll() is None:
            self._log.seek(0)
            found = re.search(r"DevTools listening on (ws://\S+)", self._log.read())
            if found:  # Chromium announces its DevTools endpoint on stderr
                return connect(found.group(1), max_size=None)
            time.sleep(0.1)
        raise RuntimeError(f"chromium opened no DevTools endpoint: {self._log.read()[-500:]}")

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command (on the page once `open` attached it); events are skipped."""
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if self._session is not None and not method.startswith("Target."):
            message["sessionId"] = self._session
        self._socket.send(json.dumps(message))
        while True:
            reply = json.loads(self._socket.recv())
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def open(self, url: str) -> None:
        target = self.call("Target.createTarget", url=url)["targetId"]
        self._session = self.call("Target.attachToTarget", targetId=target, flatten=True)[
            "sessionId"
        ]

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 of the page as it is now."""
        import imageio.v3 as iio

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(iio.imread(data))[..., :3]

    def screenshot_until(
        self, accept: Callable[[np.ndarray], bool], timeout: float = 30.0
    ) -> np.ndarray:
        """Screenshots every half second until `accept(image)` or `timeout`; the last one."""
        deadline = time.monotonic() + timeout
        while True:
            image = self.screenshot()
            if accept(image) or time.monotonic() > deadline:
                return image
            time.sleep(0.5)

    def close(self) -> None:
        if getattr(self, "_socket", None) is not None:
            self._socket.close()
        self._process.terminate()
        try:
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._log.close()
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
