"""Headless Chromium driven over the DevTools protocol, for the live page's bench and tests.

The browser is Debian's ``chromium`` (:data:`CHROMIUM`); the protocol runs over a pair of pipes
(``--remote-debugging-pipe``: commands in on the browser's file descriptor 3, answers and events out
on 4, each message JSON ended by a NUL byte), so no port is opened and no WebSocket client is needed.
The browser runs with a fresh profile in a temporary folder, no network but what the page asks for
(no sync, updates or background requests) and its timers not throttled in the background.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["CHROMIUM", "Browser", "BrowserError", "ScriptError", "chromium_path"]

#: where Debian's package puts the browser
CHROMIUM = "/usr/bin/chromium"

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-default-apps", "--disable-extensions", "--disable-dev-shm-usage",
         "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
         "--disable-backgrounding-occluded-windows", "--remote-debugging-pipe")


class BrowserError(RuntimeError):
    """The browser answered a command with an error, did not answer in time, or exited."""


class ScriptError(BrowserError):
    """An expression evaluated in the page threw."""


def chromium_path() -> str | None:
    """The Chromium executable (``CHROMIUM``, else ``chromium`` on the PATH), None when there is none."""
    return CHROMIUM if os.access(CHROMIUM, os.X_OK) else shutil.which("chromium")


class Browser:
    """One headless Chromium (module doc); a context manager that closes it and removes its profile.

    ``open(url)`` gives a page's session id; ``evaluate``, ``wait_for``, ``insert_text`` and ``press``
    act in it. ``timeout`` (s) bounds each command's answer; ``nice``: added to the browser's
    niceness (all its processes), 0 = this process's priority."""

    def __init__(self, exe: str | None = None, timeout: float = 60.0, window: tuple[int, int] = (1280, 900),
                 nice: int = 0):
        exe = exe or chromium_path()
        if exe is None:
            raise BrowserError(f"no Chromium: install Debian's chromium package ({CHROMIUM})")
        self.timeout = timeout
        self._profile = tempfile.mkdtemp(prefix="hbma-chromium-")
        cmd_r, self._cmd_w = os.pipe()
        self._out_r, out_w = os.pipe()
        args = [exe, *FLAGS, f"--user-data-dir={self._profile}", f"--window-size={window[0]},{window[1]}", "about:blank"]
        # bash gives the pipes the descriptors the browser expects (3 in, 4 out; sh takes only one digit)
        script = f'exec "$@" 3<&{cmd_r} 4>&{out_w}'
        if nice:
            args = ["nice", "-n", str(int(nice)), *args]
        self._proc = subprocess.Popen(["bash", "-c", script, "bash", *args], pass_fds=(cmd_r, out_w),
                                      stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(out_w)
        self._next = 0
        self._lock = threading.Lock()
        self._answers: dict[int, dict] = {}
        self._ready = threading.Condition()
        self._reader = threading.Thread(target=self._read, name="chromium-devtools", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        buf = b""
        with os.fdopen(self._out_r, "rb", buffering=0) as fh:
            while True:
                chunk = fh.read(65536)
                if not chunk:
                    break
                buf += chunk
                *msgs, buf = buf.split(b"\0")
                for raw in msgs:
                    msg = json.loads(raw)
                    if "id" in msg:
                        with self._ready:
                            self._answers[msg["id"]] = msg
                            self._ready.notify_all()
        with self._ready:
            self._answers[-1] = {"error": {"message": "the browser exited"}}
            self._ready.notify_all()

    def send(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        """One DevTools command; its result (BrowserError on an error or no answer within ``timeout``)."""
        with self._lock:
            self._next += 1
            k = self._next
            msg = {"id": k, "method": method, "params": params or {}}
            if session is not None:
                msg["sessionId"] = session
            os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        with self._ready:
            while k not in self._answers:
                left = deadline - time.monotonic()
                if -1 in self._answers or left <= 0:
                    raise BrowserError(f"{method}: " + ("the browser exited" if -1 in self._answers else
                                                        f"no answer within {self.timeout:g} s"))
                self._ready.wait(left)
            ans = self._answers.pop(k)
        if "error" in ans:
            raise BrowserError(f"{method}: {ans['error'].get('message')}")
        return ans.get("result", {})

    def open(self, url: str) -> str:
        """A new page at ``url``; its session id."""
        target = self.send("Target.createTarget", {"url": url})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.send("Runtime.enable", session=session)
        return session

    def evaluate(self, session: str, expression: str) -> Any:
        """The value of a JavaScript expression in the page (awaited when it is a promise)."""
        r = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True},
                      session=session)
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise ScriptError(f"{expression[:60]}: {(d.get('exception') or {}).get('description') or d.get('text')}")
        return r.get("result", {}).get("value")

    def wait_for(self, session: str, expression: str, timeout: float = 60.0, every: float = 0.1) -> Any:
        """Poll ``expression`` until it is truthy; its value (BrowserError after ``timeout`` s). An expression
        that throws (the page is still loading) counts as false; the last error is in the message."""
        deadline = time.monotonic() + timeout
        why = ""
        while True:
            try:
                v = self.evaluate(session, expression)
            except ScriptError as exc:
                v, why = None, f" (last: {exc})"
            if v:
                return v
            if time.monotonic() > deadline:
                raise BrowserError(f"not true within {timeout:g} s: {expression}{why}")
            time.sleep(every)

    def insert_text(self, session: str, text: str) -> None:
        """Type ``text`` into the focused element, as a keyboard would."""
        self.send("Input.insertText", {"text": text}, session=session)

    def press(self, session: str, key: str = "Enter") -> None:
        """Press and release a key (Enter by default) in the focused element."""
        codes = {"Enter": 13, "Tab": 9, "Escape": 27}
        base = {"key": key, "code": key, "windowsVirtualKeyCode": codes.get(key, 0)}
        self.send("Input.dispatchKeyEvent", {"type": "keyDown", **base, **({"text": "\r"} if key == "Enter" else {})},
                  session=session)
        self.send("Input.dispatchKeyEvent", {"type": "keyUp", **base}, session=session)

    def screenshot(self, session: str, path: Path) -> Path:
        """A PNG of the page's viewport."""
        import base64

        data = self.send("Page.captureScreenshot", {"format": "png"}, session=session)["data"]
        Path(path).write_bytes(base64.b64decode(data))
        return Path(path)

    def close(self) -> None:
        """Close the browser (kill it when it does not go) and remove its profile."""
        try:
            if self._proc.poll() is None:
                self.timeout = 5.0
                self.send("Browser.close")
        except BrowserError:
            pass
        try:
            self._proc.wait(10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(10)
        try:
            os.close(self._cmd_w)
        except OSError:
            pass
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
