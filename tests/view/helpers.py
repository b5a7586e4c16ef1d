"""Datagrams a run would put on the wire, and headless Chromium, for the view's tests."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import re
import shutil
import tempfile
import urllib.request
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any, Final

import numpy as np
import pytest
from websockets.asyncio.client import ClientConnection, connect

from protocol import encode
from protocol import keys as pkeys
from protocol.messages import (
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Mode,
    ModeCommand,
    RsuBeacon,
)
from services.edge.plumbing import (
    StartRun,
    TruthReport,
    control_key,
    encode_control,
    encode_truth,
    truth_key,
)
from services.model.kinematics import TruthState
from services.model.types import Policy, RunMode

RUN_ID = "view-test"


def fp(car: str, t: float, x: float, y: float, *, mode: Mode = Mode.AUTO) -> tuple[str, bytes]:
    """A future path of ``car`` at run time ``t``, heading east at 10 m/s."""
    points = np.array([[x + 1.0 * i, y, t + 0.1 * i] for i in range(30)])
    msg = FuturePath(
        Header(car, int(t * 10), int(t * 1e6)), x, y, 10.0, 0.0, 4.5, 1.8, mode, points
    )
    return pkeys.message_key(msg), encode(msg)


def cp(rsu: str, car: str, t: float, x: float, y: float) -> tuple[str, bytes]:
    points = np.array([[x + 0.5 * i, y, t + 0.1 * i] for i in range(20)])
    msg = CoordinatedPath(
        Header(rsu, int(t * 10), int(t * 1e6)), car, Mode.C_SLOW, points, np.full(20, 5.0)
    )
    return pkeys.message_key(msg), encode(msg)


def terminate(rsu: str, car: str, t: float) -> tuple[str, bytes]:
    msg = ModeCommand(Header(rsu, 99, int(t * 1e6)), car, Command.TERMINATE, Mode.AUTO)
    return pkeys.message_key(msg), encode(msg)


def beacon(rsu: str, t: float) -> tuple[str, bytes]:
    msg = RsuBeacon(Header(rsu, 1, int(t * 1e6)), "X1", 0.0, 0.0, 150.0)
    return pkeys.message_key(msg), encode(msg)


def truth(
    car: str, step: int, t: float, x: float, y: float, mode: str = "AUTO"
) -> tuple[str, bytes]:
    state = TruthState(car, t, x, y, 0.0, 8.0, 0.0, x + 200.0, 4.5, 1.8)
    report = TruthReport(RUN_ID, step, state, mode, "cruise")
    return truth_key(car), encode_truth(report)


def start(scenario: str = "paper-blind-intersection") -> tuple[str, bytes]:
    msg = StartRun(
        run_id=RUN_ID,
        scenario=scenario,
        mode=RunMode.RSU,
        policy=Policy.PAPER,
        seed=1,
        start_times={"A": 0.0, "B": 0.5},
        epoch_unix=1.0e9,
        speed=1.0,
        max_sim_s=60.0,
        monitor="monitor",
        vehicles=("A", "B"),
        rsus=("rsu1",),
    )
    return control_key(), encode_control(msg)


# ---------------------------------------------------------------- headless Chromium


def chromium() -> str:
    """The Chromium binary; skips when missing, but fails on CI (make test installs it)."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing (deploy/lab/install-sysdeps.sh installs it)")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    return path


def _flags(profile: str) -> list[str]:
    return [
        "--headless",
        "--no-sandbox",  # CI runs as root
        "--disable-gpu",
        "--hide-scrollbars",
        "--no-first-run",
        "--disable-extensions",
        f"--user-data-dir={profile}",
        "--window-size=1400,860",
    ]


_STATE_JS: Final = """(() => {
  const el = document.getElementById("state");
  if (!el || !document.body) return null;
  return JSON.stringify({
    cars: JSON.parse(el.dataset.cars),
    moved: JSON.parse(el.dataset.moved),
    t: el.dataset.t,
    frames: Number(document.body.dataset.frames),
  });
})()"""


class Page:
    """One page of headless Chromium, driven over the DevTools protocol."""

    def __init__(self, ws: ClientConnection) -> None:
        self._ws = ws
        self._id = 0

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        ident = self._id
        await self._ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            msg = json.loads(await asyncio.wait_for(self._ws.recv(), 60))
            if msg.get("id") == ident:
                if "error" in msg:
                    raise AssertionError(f"{method}: {msg['error']}")
                result: dict[str, Any] = msg["result"]
                return result

    async def evaluate(self, expression: str) -> Any:
        out = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in out:
            raise AssertionError(f"the page threw: {out['exceptionDetails']}")
        return out["result"].get("value")

    async def state(self) -> dict[str, Any]:
        """What the page exposes in ``#state``: ``cars`` (id, x, y, mode), ``moved``
        (metres per car since the page first saw it), ``t``, ``frames`` drawn."""
        try:
            text = await self.evaluate(_STATE_JS)
        except AssertionError as exc:
            if "execution context" in str(exc):
                return {}  # navigating: no document yet
            raise
        if text is None:
            return {}  # not loaded yet
        data: dict[str, Any] = json.loads(text)
        return data

    async def wait_state(
        self, pred: Callable[[dict[str, Any]], bool], timeout: float = 60.0
    ) -> dict[str, Any]:
        """Poll :meth:`state` until ``pred`` holds; the last state either way."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        state: dict[str, Any] = {}
        while loop.time() < deadline:
            with contextlib.suppress(json.JSONDecodeError, TypeError):
                state = await self.state()
                if state and pred(state):
                    break
            await asyncio.sleep(0.2)
        return state

    async def screenshot(self, path: Path) -> None:
        out = await self.call("Page.captureScreenshot", format="png")
        path.write_bytes(base64.b64decode(out["data"]))


@contextlib.asynccontextmanager
async def browser(url: str) -> AsyncIterator[Page]:
    """Headless Chromium showing ``url``, for as long as the block runs (the event loop
    keeps running: the view server is on it)."""
    with tempfile.TemporaryDirectory(prefix="crosspath-chromium-") as profile:
        proc = await asyncio.create_subprocess_exec(
            chromium(),
            *_flags(profile),
            "--remote-debugging-port=0",
            url,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        assert proc.stderr is not None
        lines: list[str] = []
        try:
            devtools = None
            while devtools is None:
                raw = await asyncio.wait_for(proc.stderr.readline(), 60)
                if not raw:
                    raise AssertionError(f"chromium exited: {lines[-5:]}")
                line = raw.decode("utf-8", "replace")
                lines.append(line)
                found = re.search(r"DevTools listening on ws://([^/]+)/", line)
                devtools = found.group(1) if found else None
            drain = asyncio.get_running_loop().create_task(proc.stderr.read())
            page_ws = None
            for _ in range(300):
                targets = await asyncio.to_thread(_json_list, devtools)
                pages = [t for t in targets if t.get("type") == "page"]
                if pages:
                    page_ws = pages[0]["webSocketDebuggerUrl"]
                    break
                await asyncio.sleep(0.1)
            if page_ws is None:
                raise AssertionError("chromium opened no page")
            async with connect(page_ws, max_size=None) as ws:
                yield Page(ws)
            drain.cancel()
        finally:
            if proc.returncode is None:
                proc.terminate()
                try:
                    await asyncio.wait_for(proc.wait(), 10)
                except TimeoutError:
                    proc.kill()
                    await proc.wait()


def _json_list(host: str) -> list[dict[str, Any]]:
    with urllib.request.urlopen(f"http://{host}/json/list", timeout=5) as resp:
        data: list[dict[str, Any]] = json.loads(resp.read())
        return data
