"""The page in headless Chromium: the cars appear and move, replayed and live.

The page writes what it drew into ``#state`` (each car's position and how far it
moved since the page first saw it); ``chromium --dump-dom`` reads it back. Chromium
missing: skipped here, a failure on CI (``deploy/lab/install-sysdeps.sh`` installs it).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sys
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from services.api import simulate
from services.edge.settings import ZenohSettings
from services.edge.transport import RELIABLE_QOS, V2X_QOS, ZenohTransport
from services.model.scenario import load_scenario
from services.view.server import ViewServer
from services.view.state import Replay, ViewState
from services.view.traces import load_trace
from tests.view.helpers import browser, chromium, cp, fp, start, truth
from tests.view.test_server import endpoints, get

REPO = Path(__file__).resolve().parents[2]


def both_moved(metres: float) -> Callable[[dict[str, Any]], bool]:
    """Both cars of the paper's scenario are on the page and moved ``metres`` on it."""

    def check(state: dict[str, Any]) -> bool:
        moved = state["moved"]
        return set(moved) >= {"A", "B"} and all(m > metres for m in moved.values())

    return check


@pytest.fixture(autouse=True)
def _needs_chromium() -> None:
    chromium()


async def test_replay_of_a_sim_trace_shows_the_cars_moving(tmp_path: Path) -> None:
    """A `sim --trace` replayed: paused at the start until the page shows the cars, then
    the page's play button moves them, and its slider scrubs back."""
    trace = tmp_path / "trace.csv"
    simulate("paper-blind-intersection", mode="rsu", seed=1, trace=trace)  # `sim --trace`
    loaded = load_trace(trace)
    state = ViewState()
    replay = Replay(loaded.rows, state)
    server = ViewServer(
        state,
        replay=replay,
        scenario=load_scenario("paper-blind-intersection"),
        rate=8.0,
        source="replay",
    )
    server.playing = False
    host, port = await server.start("127.0.0.1", 0)
    shot = tmp_path / "view.png"
    try:
        async with browser(f"http://{host}:{port}/") as page:
            first = await page.wait_state(lambda s: len(s["cars"]) >= 1)
            await page.evaluate('document.getElementById("btn-play").click()')
            seen = await page.wait_state(both_moved(5.0))
            await page.screenshot(shot)
            await page.evaluate('document.getElementById("btn-play").click()')  # pause
            await page.evaluate(
                'const s = document.getElementById("scrub"); s.value = "1.0";'
                's.dispatchEvent(new Event("input"))'
            )
            back = await page.wait_state(lambda s: s["t"] == "1")
    finally:
        await server.stop()
    assert [c["id"] for c in first["cars"]] == ["A"] and first["t"] == "0"  # B starts later
    cars = {c["id"]: c for c in seen["cars"]}
    assert cars["A"]["y"] == pytest.approx(-1.75) and cars["B"]["x"] == pytest.approx(1.75)
    assert seen["moved"]["A"] > 5.0 and seen["moved"]["B"] > 5.0, seen
    assert float(seen["t"]) > 0.5 and seen["frames"] >= 3
    assert back["t"] == "1" and not server.playing and replay.at == 1.0  # paused, scrubbed
    assert shot.read_bytes()[:4] == b"\x89PNG" and shot.stat().st_size > 20_000  # not blank


async def test_live_page_follows_what_is_published_on_zenoh() -> None:
    """An actor publishes truth, future paths and coordinated paths on Zenoh while the
    page is open; the page shows both cars moving, B in the mode the RSU gave it."""
    eps = endpoints()
    actor = ZenohTransport(ZenohSettings(listen=eps))
    await actor.open_async()
    state = ViewState()
    server = ViewServer(state)
    stop = asyncio.Event()

    async def publish() -> None:
        k = 0
        while not stop.is_set():
            t = 0.05 * k
            actor.publish(*start(), RELIABLE_QOS)
            actor.publish(*truth("A", k, t, -60.0 + 8 * t, -1.75), RELIABLE_QOS)
            actor.publish(*truth("B", k, t, 1.75, -60.0 + 5 * t, mode="C_SLOW"), RELIABLE_QOS)
            actor.publish(*fp("A", t, -60.0 + 8 * t, -1.75), V2X_QOS)
            actor.publish(*cp("rsu1", "B", t, 1.75, -60.0 + 5 * t), V2X_QOS)
            k += 1
            await asyncio.sleep(0.05)

    try:
        await server.attach_zenoh(ZenohSettings(connect=eps))
        host, port = await server.start("127.0.0.1", 0)
        task = asyncio.get_running_loop().create_task(publish())
        try:
            async with browser(f"http://{host}:{port}/") as page:
                seen = await page.wait_state(both_moved(1.0))
        finally:
            stop.set()
            await task
    finally:
        await server.stop()
        actor.close()
    cars = {c["id"]: c for c in seen["cars"]}
    assert set(cars) == {"A", "B"}, seen
    assert cars["B"]["mode"] == "C_SLOW"
    assert seen["moved"]["A"] > 0.5 and seen["moved"]["B"] > 0.5, seen


@contextlib.asynccontextmanager
async def process(
    *argv: str, output: bool = True, log: Path | None = None
) -> AsyncIterator[asyncio.subprocess.Process]:
    """``argv`` in its own session, interrupted (then killed) at the end; its stdout
    readable when ``output``, else written to ``log`` (for a failure's message) or
    discarded."""
    sink: Any = asyncio.subprocess.PIPE if output else asyncio.subprocess.DEVNULL
    if not output and log is not None:
        sink = log.open("wb")
    proc = await asyncio.create_subprocess_exec(
        *argv,
        cwd=REPO,
        stdout=sink,
        stderr=asyncio.subprocess.STDOUT,
        start_new_session=True,
    )
    if not isinstance(sink, int):
        sink.close()  # the child has its own descriptor
    try:
        yield proc
    finally:
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGINT)
            try:
                await asyncio.wait_for(proc.wait(), 15)
            except TimeoutError:
                os.killpg(proc.pid, signal.SIGKILL)
                await proc.wait()


@pytest.mark.daemons
@pytest.mark.slow  # 15 to 25 s: four daemons, a run at twice real time and a browser
@pytest.mark.timeout(240)  # generous: a loaded machine slows the browser down
async def test_view_of_real_daemons_via_run_dir(tmp_path: Path) -> None:
    """``crosspath up`` on the paper scenario and ``crosspath view --run-dir`` beside it:
    the page shows the cars of the real run moving."""
    run_dir = tmp_path / "run"
    port = endpoints()[1].rsplit(":", 1)[1]
    cli = [sys.executable, "-m", "services.cli.main"]
    async with (
        process(
            *cli,
            "up",
            "paper-blind-intersection",
            "--mode",
            "rsu",
            "--speed",
            "2",
            "--run-dir",
            str(run_dir),
            output=False,
            log=tmp_path / "up.log",
        ) as up,
        process(*cli, "view", "--run-dir", str(run_dir), "--port", port) as view,
    ):
        assert view.stdout is not None
        line = await asyncio.wait_for(view.stdout.readline(), 90)
        assert b"live at http://" in line, line
        async with browser(f"http://127.0.0.1:{port}/") as page:
            seen = await page.wait_state(both_moved(1.0))
        _, _, body = await asyncio.to_thread(get, f"http://127.0.0.1:{port}/api/snapshot")
        assert up.returncode is None or up.returncode == 0, (tmp_path / "up.log").read_text()[
            -2000:
        ]
    snap = json.loads(body)
    # the run's signed truth verified with the run's root key; nothing refused
    assert snap["run"]["mode"] == "rsu" and snap["map"]["name"] == "paper-blind-intersection"
    counters = snap["counters"]
    assert counters["malformed"] == counters["unauthenticated"] == counters["mismatched"] == 0
    # verified truth updates flowed: how many by the time the page saw both cars move
    # depends on the machine's load (exactly 50 once on a loaded CI run, > 50 before)
    assert counters["applied"] >= 20
    assert set(seen["moved"]) == {"A", "B"}, seen
    assert all(m > 1.0 for m in seen["moved"].values()), seen
