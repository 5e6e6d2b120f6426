"""Open a page in headless Chromium through the DevTools protocol (test helper).

Collects what a user would see as broken: console errors, uncaught exceptions,
log errors, and every network request (the report must need none), then
evaluates a JavaScript expression and takes a full-page screenshot.  Uses
tornado's WebSocket client (a dependency of dask.distributed) so no extra
package is needed.
"""

from __future__ import annotations

import asyncio
import base64
import json
import shutil
import subprocess
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # WebGL (plotly's 3D view) through SwiftShader; without this flag Chromium still falls
    # back to it but logs a deprecation message on the page's console.
    "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
    "--remote-debugging-port=0", "--remote-allow-origins=*",
]


def chromium_binary() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@dataclass
class PageResult:
    console_errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)
    evaluated: object = None
    screenshot_png: bytes = b""


async def _session(ws_url: str, url: str, expression: str, settle_s: float,
                   width: int, height: int) -> PageResult:
    from tornado.websocket import websocket_connect

    result = PageResult()
    conn = await websocket_connect(ws_url, max_message_size=256 * 1024 * 1024)
    next_id = 0
    pending: dict[int, asyncio.Future] = {}
    loaded = asyncio.get_running_loop().create_future()

    async def reader() -> None:
        while True:
            msg = await conn.read_message()
            if msg is None:
                return
            data = json.loads(msg)
            if "id" in data and data["id"] in pending:
                pending.pop(data["id"]).set_result(data)
                continue
            method, params = data.get("method"), data.get("params", {})
            if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
                args = params.get("args", [])
                result.console_errors.append(" ".join(str(a.get("value", a.get("description")))
                                                      for a in args))
            elif method == "Runtime.exceptionThrown":
                d = params.get("exceptionDetails", {})
                result.console_errors.append(d.get("exception", {}).get("description")
                                             or d.get("text", "exception"))
            elif method == "Log.entryAdded" and params["entry"].get("level") == "error":
                result.console_errors.append(params["entry"].get("text", ""))
            elif method == "Network.requestWillBeSent":
                result.requests.append(params["request"]["url"])
            elif method == "Page.loadEventFired" and not loaded.done():
                loaded.set_result(True)

    async def call(method: str, **params) -> dict:
        nonlocal next_id
        next_id += 1
        fut = asyncio.get_running_loop().create_future()
        pending[next_id] = fut
        await conn.write_message(json.dumps({"id": next_id, "method": method, "params": params}))
        reply = await asyncio.wait_for(fut, 60)
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    task = asyncio.ensure_future(reader())
    try:
        for domain in ("Runtime", "Log", "Network", "Page"):
            await call(f"{domain}.enable")
        await call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                   deviceScaleFactor=1, mobile=False)
        await call("Page.navigate", url=url)
        await asyncio.wait_for(loaded, 60)
        await asyncio.sleep(settle_s)  # WebGL and plotly finish drawing after the load event
        ev = await call("Runtime.evaluate", expression=expression, returnByValue=True)
        result.evaluated = ev.get("result", {}).get("value")
        shot = await call("Page.captureScreenshot", format="png", captureBeyondViewport=True)
        result.screenshot_png = base64.b64decode(shot["data"])
    finally:
        conn.close()
        task.cancel()
    return result


def open_page(url: str, profile_dir: Path, expression: str = "document.title",
              settle_s: float = 3.0, width: int = 1280, height: int = 1800,
              timeout_s: float = 90.0) -> PageResult:
    """Load ``url`` in a fresh headless Chromium (profile in ``profile_dir``) and inspect it."""
    binary = chromium_binary()
    if binary is None:
        raise FileNotFoundError("chromium is not installed")
    profile_dir.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile_dir}",
                             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        port_file = profile_dir / "DevToolsActivePort"
        deadline = time.monotonic() + 30
        while not (port_file.exists() and port_file.read_text().strip()):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"chromium did not open its DevTools port (rc={proc.poll()})")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            targets = json.load(r)
        ws_url = next(t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page")
        return asyncio.run(asyncio.wait_for(
            _session(ws_url, url, expression, settle_s, width, height), timeout_s))
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
