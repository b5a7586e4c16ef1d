"""``crosspath view``'s web server: one static page over HTTP, the world over a WebSocket.

Sources (one per server):

- **live**: a Zenoh peer (:class:`~services.edge.transport.ZenohTransport`) that
  subscribes to the run's V2X streams (``{prefix}/v2x/**``: future paths,
  coordinated paths and mode commands, RSU beacons) and to the monitor's plumbing
  (``{prefix}/sim/control`` for the run's start, ``{prefix}/sim/truth/*`` for
  ground truth). It takes part in nothing: it never publishes. When the run's
  daemons sign their plumbing (``crosspath up`` does, unless ``--insecure``), give
  the run's root public key (:func:`plumbing_opener`): truth is then shown only when
  signed by its car, and a start only when signed by the run's monitor; without it,
  signed plumbing is counted ``malformed`` and the cars are placed from their future
  paths (V2X) alone. Its subscription
  goes through a bounded :class:`~services.edge.transport.ReceivePolicy` inbox, so
  a flood cannot grow it.
- **replay**: the rows of a trace (:class:`~services.view.state.Replay`), played at
  ``rate`` run seconds per wall second, paused, scrubbed from the page.

Endpoints (GET only, loopback by default): ``/`` the page, ``/view.js`` its
script, ``/api/snapshot`` the world now (JSON, with ``replay`` and ``map``),
``/api/map`` the static map, ``/healthz``, and ``/ws``: the server sends
``{"type": "map", ...}`` on connect and whenever the map changes, then
``{"type": "frame", ...}`` (:meth:`ViewState.snapshot` plus ``replay``) every
``1 / frame_hz`` s, with the cars' sparklines :data:`SPARK_HZ` times a second; the
page may send ``{"cmd": "play" | "pause"}``,
``{"cmd": "seek", "t": run_s}`` and ``{"cmd": "rate", "rate": x}`` (replay
only). A command that does not parse is counted (``bad_commands``) and ignored.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any, Final

from websockets.asyncio.server import Server, ServerConnection, broadcast, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from protocol import keys as pkeys
from services.edge.plumbing import all_truths, control_key
from services.edge.settings import ZenohSettings
from services.edge.transport import ReceivePolicy, Subscription, ZenohTransport
from services.edge.trust import Refused, TrustStore, load_public_key
from services.model.scenario import Scenario, ScenarioError, load_scenario
from services.view.state import PlumbingOpener, Replay, ViewState, scenario_map

__all__ = ["MAX_RATE", "ViewServer", "plumbing_opener", "static_file"]

logger = logging.getLogger("crosspath.view")

MAX_RATE: Final = 100.0
"""Fastest replay rate [run s per wall s]."""

SPARK_HZ: Final = 2.0
"""Frames per second that carry the sparklines (the others leave them out: with many
cars they are most of a frame's bytes)."""

MAX_COMMAND_BYTES: Final = 4096
"""Largest message a page may send."""

_STATIC: Final = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/view.js": ("view.js", "text/javascript; charset=utf-8"),
}


def static_file(name: str) -> bytes:
    """A file of the page (package data ``services/view/static/``)."""
    return (resources.files("services.view") / "static" / name).read_bytes()


def plumbing_opener(root_public_key: Path) -> PlumbingOpener:
    """Opens the signed plumbing of a run whose authority's public key is
    ``root_public_key`` (``<run dir>/keys/root.pub`` of a ``crosspath up`` run): the
    view checks what the daemons check (a certificate from that root, its signature,
    no replay), without keys of its own. ``ValueError`` when the file is no such key."""
    store = TrustStore(load_public_key(root_public_key))

    def opener(blob: bytes) -> tuple[bytes, str]:
        try:
            payload, cert = store.verify_blob(blob, any_run=True)
        except Refused as exc:
            raise ValueError(str(exc)) from None
        return payload, cert.subject

    return opener


def _response(status: int, reason: str, body: bytes, content_type: str) -> Response:
    headers = Headers()
    headers["Content-Type"] = content_type
    headers["Content-Length"] = str(len(body))
    headers["Cache-Control"] = "no-store"
    headers["X-Content-Type-Options"] = "nosniff"
    return Response(status, reason, headers, body)


class ViewServer:
    """Serves one :class:`ViewState` (live or replayed) to any number of pages.

    ``replay`` None: live (call :meth:`attach_zenoh`, or feed ``state.on_datagram``
    yourself). ``scenario``: the map; live without one, the map of the scenario
    named in the run's start message is loaded when it is a packaged name or a path.
    """

    def __init__(
        self,
        state: ViewState,
        *,
        replay: Replay | None = None,
        scenario: Scenario | None = None,
        frame_hz: float = 10.0,
        rate: float = 1.0,
        source: str = "live",
        scenario_loader: Callable[[str], Scenario] = load_scenario,
    ) -> None:
        if not (math.isfinite(frame_hz) and 0 < frame_hz <= 60):
            raise ValueError(f"frame_hz must be in (0, 60], got {frame_hz!r}")
        if not (math.isfinite(rate) and 0 < rate <= MAX_RATE):
            raise ValueError(f"rate must be in (0, {MAX_RATE}], got {rate!r}")
        self.state = state
        self.replay = replay
        self.frame_hz = frame_hz
        self.rate = rate
        self.playing = replay is not None
        self.source = source
        self.bad_commands = 0
        self._scenario_loader = scenario_loader
        self._map_fixed = scenario is not None
        self._map_tried: str | None = None
        if scenario is not None:
            state.set_map(scenario_map(scenario))
        self._clients: set[ServerConnection] = set()
        self._server: Server | None = None
        self._frames: asyncio.Task[None] | None = None
        self._transport: ZenohTransport | None = None
        self._subs: list[Subscription] = []
        if replay is not None:
            replay.seek(replay.t_start)

    # -- sources

    async def attach_zenoh(self, settings: ZenohSettings) -> None:
        """Open a Zenoh peer with ``settings`` and subscribe to the run's streams."""
        transport = ZenohTransport(settings)
        await transport.open_async()
        self._transport = transport
        prefix = self.state.prefix
        policy = ReceivePolicy(depth=4, rate_hz=0.0, max_lanes=2048)
        state = self.state

        def handler(key: str, payload: bytes) -> None:
            state.on_datagram(key, payload)

        for keyexpr in (
            pkeys.all_v2x(prefix=prefix),
            control_key(prefix=prefix),
            all_truths(prefix=prefix),
        ):
            self._subs.append(transport.subscribe(keyexpr, handler, policy))

    def _maybe_load_map(self) -> None:
        """Live: the map of the scenario the run's start names, once per name."""
        name = self.state.run.get("scenario")
        if self._map_fixed or not isinstance(name, str) or name == self._map_tried:
            return
        self._map_tried = name
        try:
            scenario = self._scenario_loader(name)
        except (ScenarioError, OSError, ValueError) as exc:
            logger.warning("no map for scenario %r: %s", name, exc)
            return
        self.state.set_map(scenario_map(scenario))

    # -- frames

    def replay_info(self) -> dict[str, Any] | None:
        replay = self.replay
        if replay is None:
            return None
        return {
            "playing": self.playing,
            "t": round(replay.at, 3),
            "t_start": round(replay.t_start, 3),
            "t_end": round(replay.t_end, 3),
            "rate": self.rate,
        }

    def frame(self, *, sparklines: bool = True) -> dict[str, Any]:
        """The frame every page gets now (see :meth:`ViewState.snapshot`)."""
        snap = self.state.snapshot(sparklines=sparklines)
        snap["type"] = "frame"
        snap["source"] = self.source
        snap["replay"] = self.replay_info()
        snap["clients"] = len(self._clients)
        snap["counters"]["bad_commands"] = self.bad_commands
        return snap

    def map_message(self) -> dict[str, Any]:
        return {"type": "map", "version": self.state.map_version, "map": self.state.map}

    async def _frame_loop(self) -> None:
        period = 1.0 / self.frame_hz
        loop = asyncio.get_running_loop()
        last = loop.time()
        sent_map = self.state.map_version
        every = max(1, round(self.frame_hz / SPARK_HZ))
        count = 0
        while True:
            await asyncio.sleep(period)
            now = loop.time()
            if self.replay is not None and self.playing:
                replay = self.replay
                replay.seek(replay.at + (now - last) * self.rate)
                if replay.at >= replay.t_end:
                    self.playing = False
            last = now
            self._maybe_load_map()
            if not self._clients:
                continue
            if self.state.map_version != sent_map:
                sent_map = self.state.map_version
                broadcast(self._clients, json.dumps(self.map_message()))
            count += 1
            frame = self.frame(sparklines=count % every == 0)
            broadcast(self._clients, json.dumps(frame, allow_nan=False))

    @staticmethod
    def _frame_loop_ended(task: asyncio.Task[None]) -> None:
        """A bug of ours in the frame loop: say so at once (the pages would freeze)."""
        if not task.cancelled() and task.exception() is not None:
            logger.error("the frame loop failed", exc_info=task.exception())

    # -- control from the page

    def command(self, text: str | bytes) -> bool:
        """Apply one page command (see the module docstring); False when refused."""
        try:
            data = json.loads(text)
            if not isinstance(data, dict):
                raise ValueError("not an object")
            cmd = data.get("cmd")
            replay = self.replay
            if replay is None:
                raise ValueError("live: nothing to control")
            if cmd == "play":
                if replay.at >= replay.t_end:
                    replay.seek(replay.t_start)
                self.playing = True
            elif cmd == "pause":
                self.playing = False
            elif cmd == "seek":
                t = data.get("t")
                if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
                    raise ValueError("seek needs a finite t")
                replay.seek(float(t))
            elif cmd == "rate":
                rate = data.get("rate")
                if (
                    isinstance(rate, bool)
                    or not isinstance(rate, int | float)
                    or not (math.isfinite(rate) and 0 < rate <= MAX_RATE)
                ):
                    raise ValueError(f"rate must be in (0, {MAX_RATE}]")
                self.rate = float(rate)
            else:
                raise ValueError(f"unknown command {cmd!r}")
        except (ValueError, TypeError) as exc:  # json.JSONDecodeError is a ValueError
            self.bad_commands += 1
            logger.debug("refused a page command: %s", exc)
            return False
        return True

    # -- HTTP and WebSocket

    def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            return None  # the WebSocket handshake goes on
        if path in _STATIC:
            name, ctype = _STATIC[path]
            return _response(200, "OK", static_file(name), ctype)
        if path == "/api/snapshot":
            body = dict(self.frame(), map=self.state.map)
            return _response(200, "OK", json.dumps(body).encode(), "application/json")
        if path == "/api/map":
            return _response(200, "OK", json.dumps(self.state.map).encode(), "application/json")
        if path == "/healthz":
            return _response(200, "OK", b"ok\n", "text/plain; charset=utf-8")
        return _response(404, "Not Found", b"not found\n", "text/plain; charset=utf-8")

    async def _ws(self, connection: ServerConnection) -> None:
        self._clients.add(connection)
        try:
            await connection.send(json.dumps(self.map_message()))
            await connection.send(json.dumps(self.frame(), allow_nan=False))
            async for message in connection:
                self.command(message)
        except ConnectionClosed:
            pass
        finally:
            self._clients.discard(connection)

    async def start(self, host: str = "127.0.0.1", port: int = 8765) -> tuple[str, int]:
        """Listen on ``host``:``port`` (0: any free port); the address actually bound."""
        self._server = await serve(
            self._ws,
            host,
            port,
            process_request=self._http,
            max_size=MAX_COMMAND_BYTES,
            compression=None,
            server_header=None,
        )
        self._frames = asyncio.get_running_loop().create_task(self._frame_loop())
        self._frames.add_done_callback(self._frame_loop_ended)
        sock = next(iter(self._server.sockets))
        bound = sock.getsockname()
        return str(bound[0]), int(bound[1])

    async def stop(self) -> None:
        """Close the pages, the listener and the Zenoh peer."""
        if self._frames is not None:
            self._frames.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._frames
            self._frames = None
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        if self._transport is not None:
            self._transport.close()
            self._transport = None
