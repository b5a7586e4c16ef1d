"""The view's web server with plain clients: HTTP endpoints, the WebSocket, page commands,
and a live run's datagrams over real Zenoh."""

from __future__ import annotations

import asyncio
import json
import socket
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from websockets.asyncio.client import connect

from protocol import keys as pkeys
from services.edge.settings import ZenohSettings
from services.edge.transport import RELIABLE_QOS, V2X_QOS, ZenohTransport
from services.model.scenario import load_scenario
from services.view.server import ViewServer
from services.view.state import Replay, TraceRow, ViewState
from tests.view.helpers import fp, start, truth


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            return resp.status, resp.headers["Content-Type"], resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read()


async def aget(url: str) -> tuple[int, str, bytes]:
    return await asyncio.to_thread(get, url)


def rows() -> list[TraceRow]:
    return [TraceRow(0.05 * k, "A", -100.0 + 0.5 * k, -1.75, 10.0, "AUTO") for k in range(400)]


@pytest.fixture
async def replay_server() -> AsyncIterator[tuple[ViewServer, str]]:
    state = ViewState()
    server = ViewServer(
        state,
        replay=Replay(rows(), state),
        scenario=load_scenario("paper-blind-intersection"),
        frame_hz=20.0,
        source="replay",
    )
    host, port = await server.start("127.0.0.1", 0)
    yield server, f"{host}:{port}"
    await server.stop()


async def test_http_endpoints(replay_server: tuple[ViewServer, str]) -> None:
    _, addr = replay_server
    status, ctype, body = await aget(f"http://{addr}/")
    assert status == 200 and ctype.startswith("text/html") and b'<canvas id="map"' in body
    status, ctype, body = await aget(f"http://{addr}/view.js")
    assert status == 200 and "javascript" in ctype and b"new WebSocket" in body
    status, ctype, body = await aget(f"http://{addr}/api/snapshot")
    snap = json.loads(body)
    assert status == 200 and ctype == "application/json"
    assert snap["source"] == "replay" and snap["map"]["name"] == "paper-blind-intersection"
    assert [c["id"] for c in snap["cars"]] == ["A"] and snap["replay"]["t_end"] == pytest.approx(
        19.95
    )
    status, _, body = await aget(f"http://{addr}/api/map")
    assert status == 200 and len(json.loads(body)["lanes"]) == 4
    assert (await aget(f"http://{addr}/healthz"))[0] == 200
    assert (await aget(f"http://{addr}/../etc/passwd"))[0] == 404
    assert (await aget(f"http://{addr}/static/../../server.py"))[0] == 404


async def recv(ws: Any, kind: str) -> dict[str, Any]:
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
        if msg["type"] == kind:
            return msg  # type: ignore[no-any-return]


async def frame_where(ws: Any, pred: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
    """The first frame (from now on, queued ones included) for which ``pred`` holds."""
    frame: dict[str, Any] = {}
    for _ in range(100):
        frame = await recv(ws, "frame")
        if pred(frame):
            return frame
    raise AssertionError(f"no such frame; the last was {frame}")


async def test_websocket_frames_and_replay_control(replay_server: tuple[ViewServer, str]) -> None:
    server, addr = replay_server
    async with connect(f"ws://{addr}/ws") as ws:
        first = json.loads(await ws.recv())
        assert first["type"] == "map" and len(first["map"]["buildings"]) == 4
        frame = await recv(ws, "frame")
        assert frame["replay"]["playing"] is True
        await ws.send(json.dumps({"cmd": "pause"}))
        await ws.send(json.dumps({"cmd": "seek", "t": 10.0}))
        frame = await frame_where(ws, lambda f: f["t"] == 10.0)
        assert frame["replay"] == {
            "playing": False,
            "t": 10.0,
            "t_start": 0.0,
            "t_end": pytest.approx(19.95),
            "rate": 1.0,
        }
        assert frame["cars"][0]["x"] == pytest.approx(0.0)  # -100 + 0.5 * 200
        await ws.send(json.dumps({"cmd": "seek", "t": 2.0}))  # scrub back
        frame = await frame_where(ws, lambda f: f["t"] == 2.0)
        assert frame["cars"][0]["x"] == pytest.approx(-80.0)
        await ws.send(json.dumps({"cmd": "rate", "rate": 50}))
        await ws.send(json.dumps({"cmd": "play"}))
        frame = await frame_where(ws, lambda f: f["t"] > 8.0)
        assert frame["replay"]["rate"] == 50.0
        for bad in (
            "{",
            "[]",
            '{"cmd": "seek", "t": "soon"}',
            '{"cmd": "rate", "rate": 1e9}',
            '{"cmd": "seek", "t": NaN}',
            '{"cmd": "explode"}',
        ):
            await ws.send(bad)
        frame = await frame_where(ws, lambda f: f["counters"]["bad_commands"] == 6)
        assert frame["replay"]["rate"] == 50.0  # the bad rate was refused
    assert server.bad_commands == 6


async def test_an_oversized_page_message_closes_only_that_page(
    replay_server: tuple[ViewServer, str],
) -> None:
    _, addr = replay_server
    async with connect(f"ws://{addr}/ws") as ws:
        await ws.recv()
        await ws.send("x" * 100_000)
        with pytest.raises(Exception, match=r"1009|too big"):
            for _ in range(50):
                await asyncio.wait_for(ws.recv(), 5)
    status, _, _ = await aget(f"http://{addr}/healthz")
    assert status == 200


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def endpoints() -> list[str]:
    return [
        f"udp/127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
        f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}",
    ]


async def test_live_over_zenoh_map_from_the_start_message() -> None:
    """A run's actor publishes on Zenoh; the view (a peer connected to it) folds it,
    loads the map named in the start message and drops garbage."""
    eps = endpoints()
    actor = ZenohTransport(ZenohSettings(listen=eps))
    await actor.open_async()
    state = ViewState()
    server = ViewServer(state)
    try:
        await server.attach_zenoh(ZenohSettings(connect=eps))
        _, port = await server.start("127.0.0.1", 0)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 10
        k = 0
        while loop.time() < deadline:
            t = 0.05 * k
            actor.publish(*start(), RELIABLE_QOS)
            actor.publish(*truth("A", k, t, -60.0 + t * 8, -1.75), RELIABLE_QOS)
            actor.publish(*fp("B", t, 1.75, -60.0 + t * 8), V2X_QOS)
            actor.publish(pkeys.future_path("C"), b"\x02\x01garbage", V2X_QOS)
            k += 1
            await asyncio.sleep(0.05)
            snap = state.snapshot()
            if (
                len(snap["cars"]) == 2
                and state.map is not None
                and state.counters["malformed"] > 0
                and k > 10
            ):
                break
        _, _, body = await aget(f"http://127.0.0.1:{port}/api/snapshot")
        snap = json.loads(body)
    finally:
        await server.stop()
        actor.close()
    assert snap["map"]["name"] == "paper-blind-intersection"
    assert snap["run"]["run_id"] == "view-test" and snap["source"] == "live"
    assert {c["id"]: c["mode"] for c in snap["cars"]} == {"A": "AUTO", "B": "AUTO"}
    assert snap["cars"][0]["x"] > -60.0  # moved
    assert snap["counters"]["malformed"] > 0 and snap["counters"]["applied"] > 10
