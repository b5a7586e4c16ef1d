"""The live view's world: decoded messages folded into one JSON-able snapshot.

Pure (no asyncio, no sockets, no clock reads): the server (``services.view.server``)
feeds it what arrives (raw Zenoh datagrams, or the rows of a replayed trace) and
sends :meth:`ViewState.snapshot` to the browsers. Units: metres, seconds (run time),
metres per second.

What it keeps, per car: the latest position (ground truth when the car's truth
report arrives, else the position in its future path), its mode (the car's own
word: ``AUTO``, ``C_SLOW``, ``C_FAST``), its broadcast future path, the coordinated
path an RSU last sent it (dropped after :data:`CP_HOLD_S` without a repeat, or at
a ``TERMINATE`` command) and a speed sparkline (one sample per :data:`SPARK_DT_S`,
the last :data:`SPARK_SAMPLES`); per RSU, its beacon (centre, coverage radius).

Hostile input: every datagram is decoded with the protocol's own decoder
(``protocol.decode``) or the plumbing decoder, its key parsed with
``protocol.keys.parse`` and checked against the message (``keys.matches``); whatever
fails is counted in ``counters`` by reason and dropped. State is bounded whatever
arrives: at most ``max_cars`` cars and ``max_rsus`` RSUs (the one heard from least
recently is evicted, counted in ``evicted``), paths thinned to
:data:`MAX_DRAWN_POINTS`, a message whose time is more than :data:`MAX_TIME_JUMP_S`
ahead of the clock is refused (``implausible_time``) so one forged timestamp cannot
stop the clock, and a car not heard for :data:`FORGET_S` run seconds is forgotten.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from protocol import DecodeError, decode
from protocol import keys as pkeys
from protocol.messages import (
    Command,
    CoordinatedPath,
    FuturePath,
    ModeCommand,
    RsuBeacon,
    VehiclePath,
)
from services.edge.plumbing import (
    PlumbingError,
    StartRun,
    StopRun,
    decode_control,
    decode_truth,
)
from services.model.scenario import DEFAULT_LENGTH_M, DEFAULT_WIDTH_M, Scenario

__all__ = [
    "CP_HOLD_S",
    "FORGET_S",
    "MAX_DRAWN_POINTS",
    "MAX_TIME_JUMP_S",
    "MODES",
    "SPARK_DT_S",
    "SPARK_SAMPLES",
    "PlumbingOpener",
    "Replay",
    "TraceRow",
    "ViewState",
    "scenario_map",
]

MODES: Final = ("AUTO", "C_SLOW", "C_FAST")
"""Mode names the page has a colour for (anything else is drawn grey)."""

SPARK_DT_S: Final = 0.25
"""Run seconds between two sparkline samples of one car."""

SPARK_SAMPLES: Final = 240
"""Sparkline samples kept per car (60 run s at :data:`SPARK_DT_S`)."""

CP_HOLD_S: Final = 1.0
"""A coordinated path not repeated for this many run seconds is no longer drawn
(the RSU repeats its commands every ``command_repeat_s``, 0.1 s by default)."""

FORGET_S: Final = 10.0
"""A car (or RSU) not heard for this many run seconds is forgotten."""

STALE_S: Final = 1.0
"""A car not heard for this many run seconds is drawn faded."""

MAX_TIME_JUMP_S: Final = 600.0
"""A message more than this far ahead of the clock [run s] is refused."""

MAX_DRAWN_POINTS: Final = 60
"""Path points sent to the page per path (thinned evenly, the last one kept)."""

MAX_CARS: Final = 256
MAX_RSUS: Final = 64

COUNTERS: Final = (
    "received",
    "applied",
    "bad_key",
    "malformed",
    "mismatched",
    "implausible_time",
    "unauthenticated",
    "evicted",
    "ignored",
)


def _r(value: float, nd: int = 2) -> float:
    return round(float(value), nd)


def _thin(points: np.ndarray[Any, Any], cols: int = 2) -> list[list[float]]:
    """At most :data:`MAX_DRAWN_POINTS` rows of ``points[:, :cols]``, rounded to 1 cm."""
    n = int(points.shape[0])
    if n == 0:
        return []
    if n > MAX_DRAWN_POINTS:
        idx = np.unique(np.linspace(0, n - 1, MAX_DRAWN_POINTS).round().astype(int))
        points = points[idx]
    return [[_r(v) for v in row[:cols]] for row in points.tolist()]


def scenario_map(scenario: Scenario) -> dict[str, Any]:
    """The static map the page draws: lanes (centre line, width), buildings,
    intersections (centre, conflict zone, stop-line offset), RSUs (position,
    coverage), routes, and ``bounds`` [xmin, ymin, xmax, ymax] of it all and
    ``focus``, the box the page shows first: the conflict zones padded by 80 m
    (the whole map when there is no intersection)."""
    spec = scenario.spec
    lanes = [
        {"id": lane.id, "points": [[_r(x), _r(y)] for x, y in lane.points], "width": lane.width_m}
        for lane in spec.lanes
    ]
    routes = [
        {"id": rid, "points": [[_r(x), _r(y)] for x, y in scenario.route(rid).points.tolist()]}
        for rid in scenario.route_ids
    ]
    buildings = [
        {"id": b.id, "polygon": [[_r(x), _r(y)] for x, y in b.polygon]} for b in spec.buildings
    ]
    inters = [
        {
            "id": it.id,
            "center": [_r(it.center[0]), _r(it.center[1])],
            "zone": [[_r(x), _r(y)] for x, y in it.conflict_zone],
            "stop_line_offset": it.stop_line_offset_m,
        }
        for it in spec.intersections
    ]
    rsus = [
        {
            "id": r.id,
            "intersection": r.intersection,
            "x": _r(r.position[0]),
            "y": _r(r.position[1]),
            "r": r.coverage_m,
        }
        for r in spec.rsus
    ]
    lines = [[[float(x), float(y)] for x, y in lane.points] for lane in spec.lanes]
    lines += [scenario.route(rid).points.tolist() for rid in scenario.route_ids]
    xs = [p[0] for line in lines for p in line]
    ys = [p[1] for line in lines for p in line]
    if not xs:
        xs, ys = [-50.0, 50.0], [-50.0, 50.0]
    bounds = [min(xs), min(ys), max(xs), max(ys)]
    zx = [float(p[0]) for it in spec.intersections for p in it.conflict_zone]
    zy = [float(p[1]) for it in spec.intersections for p in it.conflict_zone]
    pad = 80.0
    focus = [min(zx) - pad, min(zy) - pad, max(zx) + pad, max(zy) + pad] if zx else bounds
    return {
        "name": scenario.name,
        "lanes": lanes,
        "routes": routes,
        "buildings": buildings,
        "intersections": inters,
        "rsus": rsus,
        "bounds": bounds,
        "focus": focus,
    }


PlumbingOpener = Callable[[bytes], tuple[bytes, str]]
"""Opens a signed plumbing payload (runs whose daemons sign, ``crosspath up`` by
default): (payload, the signer's subject); ``ValueError`` when it does not verify.
Truth must be signed by its car, a start or stop by the run's monitor."""


@dataclass(slots=True)
class _Car:
    id: str
    t: float = -math.inf  # run time of the latest position
    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0
    speed: float = 0.0
    length: float = DEFAULT_LENGTH_M
    width: float = DEFAULT_WIDTH_M
    mode: str = "AUTO"
    reason: str = ""
    has_truth: bool = False
    left: bool = False
    heard: float = -math.inf  # run time it was last heard of
    fp: list[list[float]] = field(default_factory=list)
    cp: list[list[float]] = field(default_factory=list)
    cp_t: float = -math.inf
    cp_mode: str = ""
    cp_rsu: str = ""
    spark: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=SPARK_SAMPLES))


@dataclass(frozen=True, slots=True)
class TraceRow:
    """One car at one step of a replayed trace (``sim --trace`` / ``up --trace`` CSV
    or a monitor step log). ``heading`` None: derived from the motion."""

    t: float
    vehicle: str
    x: float
    y: float
    speed: float
    mode: str = ""
    reason: str = ""
    heading: float | None = None
    length: float | None = None
    width: float | None = None


class ViewState:
    """The folded world (see the module docstring). ``prefix`` is the key prefix of
    the run's Zenoh streams."""

    def __init__(
        self,
        *,
        prefix: str = pkeys.DEFAULT_PREFIX,
        max_cars: int = MAX_CARS,
        max_rsus: int = MAX_RSUS,
        opener: PlumbingOpener | None = None,
    ) -> None:
        if max_cars < 1 or max_rsus < 1:
            raise ValueError("max_cars and max_rsus must be >= 1")
        self.prefix = pkeys.validate_prefix(prefix)
        self.opener = opener
        self.max_cars = max_cars
        self.max_rsus = max_rsus
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self.t: float | None = None
        self.run: dict[str, Any] = {}
        self.ended = False
        self.map: dict[str, Any] | None = None
        self.map_version = 0
        self._cars: OrderedDict[str, _Car] = OrderedDict()
        self._rsus: OrderedDict[str, dict[str, Any]] = OrderedDict()

    # -- housekeeping

    def set_map(self, data: dict[str, Any] | None) -> None:
        """Replace the static map (:func:`scenario_map`); the page redraws it."""
        self.map = data
        self.map_version += 1
        if data is not None:
            for r in data.get("rsus", []):
                self._rsus.setdefault(r["id"], dict(r, t=None))

    def reset(self) -> None:
        """Forget the cars, RSU beacons and the clock (a new run); the counters stay."""
        self._cars.clear()
        self._rsus.clear()
        self.t = None
        self.ended = False
        if self.map is not None:
            for r in self.map.get("rsus", []):
                self._rsus[r["id"]] = dict(r, t=None)

    def _count(self, name: str) -> bool:
        self.counters[name] += 1
        return False

    def _time_ok(self, t: float) -> bool:
        if not math.isfinite(t):
            return False
        return self.t is None or t <= self.t + MAX_TIME_JUMP_S

    def _tick(self, t: float) -> None:
        if self.t is None or t > self.t:
            self.t = t
        now = self.t
        while self._cars:  # forget cars not heard for long (oldest first)
            first = next(iter(self._cars.values()))
            if now - first.heard <= FORGET_S:
                break
            self._cars.popitem(last=False)

    def _car(self, vid: str, t: float) -> _Car:
        car = self._cars.get(vid)
        if car is None:
            if len(self._cars) >= self.max_cars:
                self._cars.popitem(last=False)
                self.counters["evicted"] += 1
            car = self._cars[vid] = _Car(vid)
        else:
            self._cars.move_to_end(vid)
        car.heard = max(car.heard, t)
        return car

    def _position(
        self,
        car: _Car,
        t: float,
        x: float,
        y: float,
        heading: float | None,
        speed: float,
    ) -> None:
        if t < car.t:
            return  # older than what we have (reordered datagram)
        if heading is None:
            dx, dy = x - car.x, y - car.y
            if car.t > -math.inf and math.hypot(dx, dy) > 0.05:
                heading = math.atan2(dy, dx)
            else:
                heading = car.heading
        car.t, car.x, car.y, car.heading, car.speed = t, x, y, heading, speed
        if not car.spark or t - car.spark[-1][0] >= SPARK_DT_S - 1e-9:
            car.spark.append((t, speed))

    # -- input

    def on_datagram(self, key: str, payload: bytes) -> bool:
        """One datagram from the run's Zenoh streams; True when it changed the state.
        Anything that does not decode or does not match its key is counted and dropped."""
        self.counters["received"] += 1
        try:
            parsed = pkeys.parse(key, prefix=self.prefix)
        except pkeys.BadKey:
            return self._count("bad_key")
        if parsed.stream is pkeys.Stream.SIM:
            return self._on_sim(parsed, payload)
        if parsed.stream is pkeys.Stream.STATS:
            return self._count("ignored")
        try:
            message = decode(payload)
        except DecodeError:
            return self._count("malformed")
        if not pkeys.matches(parsed, message):
            return self._count("mismatched")
        t = message.header.time_s
        if not self._time_ok(t):
            return self._count("implausible_time")
        if isinstance(message, FuturePath):
            self._on_future_path(message)
        elif isinstance(message, CoordinatedPath):
            self._on_coordinated(message)
        elif isinstance(message, ModeCommand):
            self._on_command(message)
        elif isinstance(message, RsuBeacon):
            self._on_beacon(message)
        else:  # autonomous paths: the RSU's business, the future path is drawn already
            return self._count("ignored")
        self.counters["applied"] += 1
        return True

    def _on_sim(self, parsed: pkeys.ParsedKey, payload: bytes) -> bool:
        parts = parsed.parts
        is_control = parts == ("control",)
        if not is_control and (len(parts) != 2 or parts[0] != "truth"):
            return self._count("ignored")
        signer: str | None = None
        if self.opener is not None:
            try:
                payload, signer = self.opener(payload)
            except ValueError:
                return self._count("unauthenticated")
        try:
            if is_control:
                return self._on_control(decode_control(payload), signer)
            report = decode_truth(payload)
        except PlumbingError:
            return self._count("malformed")
        if report.vehicle != parts[1]:
            return self._count("mismatched")
        if signer not in (None, report.vehicle):
            return self._count("unauthenticated")
        if self.run.get("run_id") not in (None, report.run_id):
            return self._count("ignored")  # a report of another run
        if report.presence == "waiting":
            return self._count("ignored")  # not in the world yet
        st = report.state
        if not self._time_ok(st.t):
            return self._count("implausible_time")
        row = TraceRow(
            st.t,
            st.id,
            st.x,
            st.y,
            st.speed,
            report.mode,
            report.reason,
            st.heading,
            st.length,
            st.width,
        )
        self.on_truth(row, left=report.presence == "left")
        self.counters["applied"] += 1
        return True

    def _on_control(self, control: StartRun | StopRun, signer: str | None) -> bool:
        if isinstance(control, StartRun):
            if signer not in (None, control.monitor):
                return self._count("unauthenticated")
            self._on_start(control)
        else:
            if signer not in (None, self.run.get("monitor")):
                return self._count("unauthenticated")
            self.ended = True
        self.counters["applied"] += 1
        return True

    def _on_start(self, start: StartRun) -> None:
        if self.run.get("run_id") == start.run_id:
            return  # the monitor repeats its start
        self.reset()
        self.run = {
            "run_id": start.run_id,
            "scenario": start.scenario,
            "mode": str(start.mode),
            "policy": str(start.policy),
            "seed": start.seed,
            "speed": start.speed,
            "vehicles": list(start.vehicles),
            "rsus": list(start.rsus),
            "monitor": start.monitor,
        }

    def on_truth(self, row: TraceRow, *, left: bool = False) -> None:
        """A car's ground truth (a truth report, or a row of a replayed trace)."""
        self._tick(row.t)
        car = self._car(row.vehicle, row.t)
        car.has_truth = True
        car.left = left
        self._position(car, row.t, row.x, row.y, row.heading, row.speed)
        if row.length is not None and row.width is not None:
            car.length, car.width = row.length, row.width
        if row.mode:
            car.mode = row.mode
        car.reason = row.reason

    def _on_future_path(self, fp: FuturePath) -> None:
        t = fp.header.time_s
        self._tick(t)
        car = self._car(fp.header.sender, t)
        self._vehicle_path(car, fp, t)

    def _vehicle_path(self, car: _Car, path: VehiclePath, t: float) -> None:
        car.fp = _thin(path.points)
        car.mode = path.mode.name
        car.length, car.width = path.length, path.width
        if not car.has_truth:
            self._position(car, t, path.x, path.y, path.heading, path.speed)

    def _on_coordinated(self, cp: CoordinatedPath) -> None:
        t = cp.header.time_s
        self._tick(t)
        car = self._car(cp.vehicle, t)
        car.cp = _thin(cp.points)
        car.cp_t = t
        car.cp_mode = cp.mode.name
        car.cp_rsu = cp.header.sender

    def _on_command(self, cmd: ModeCommand) -> None:
        t = cmd.header.time_s
        self._tick(t)
        car = self._car(cmd.vehicle, t)
        if cmd.command is Command.TERMINATE:
            car.cp = []
            car.cp_t = -math.inf

    def _on_beacon(self, beacon: RsuBeacon) -> None:
        t = beacon.header.time_s
        self._tick(t)
        rid = beacon.header.sender
        if rid not in self._rsus and len(self._rsus) >= self.max_rsus:
            self._rsus.popitem(last=False)
            self.counters["evicted"] += 1
        self._rsus[rid] = {
            "id": rid,
            "intersection": beacon.intersection,
            "x": _r(beacon.x),
            "y": _r(beacon.y),
            "r": _r(beacon.radius),
            "t": t,
        }
        self._rsus.move_to_end(rid)

    # -- output

    def snapshot(self, *, sparklines: bool = True) -> dict[str, Any]:
        """The world now, as plain JSON-able data (no map: see :attr:`map`);
        ``sparklines`` False leaves each car's ``spark`` out (the bulk of a frame)."""
        now = self.t if self.t is not None else 0.0
        cars = []
        for car in sorted(self._cars.values(), key=lambda c: c.id):
            if car.t == -math.inf:
                continue  # heard of (a command for it) but never seen
            cp_live = bool(car.cp) and now - car.cp_t <= CP_HOLD_S
            cars.append(
                {
                    "id": car.id,
                    "x": _r(car.x),
                    "y": _r(car.y),
                    "h": _r(car.heading, 3),
                    "v": _r(car.speed),
                    "len": car.length,
                    "wid": car.width,
                    "mode": car.mode,
                    "reason": car.reason,
                    "stale": now - car.heard > STALE_S,
                    "left": car.left,
                    "fp": car.fp,
                    "cp": car.cp if cp_live else [],
                    "cp_mode": car.cp_mode if cp_live else "",
                    "cp_rsu": car.cp_rsu if cp_live else "",
                }
            )
            if sparklines:
                cars[-1]["spark"] = [[_r(t, 2), _r(v)] for t, v in car.spark]
        return {
            "t": None if self.t is None else _r(self.t, 3),
            "run": dict(self.run),
            "ended": self.ended,
            "cars": cars,
            "rsus": [dict(r) for r in self._rsus.values()],
            "counters": dict(self.counters),
            "map_version": self.map_version,
        }


class Replay:
    """Replays trace rows through a :class:`ViewState` at any run time, forwards or
    backwards (scrubbing back folds again from the start: the sparklines need the
    history). Rows need not be sorted."""

    def __init__(self, rows: Iterable[TraceRow], state: ViewState) -> None:
        self.rows = _with_headings(sorted(rows, key=lambda r: (r.t, r.vehicle)))
        if not self.rows:
            raise ValueError("the trace has no rows")
        self.state = state
        self.t_start = self.rows[0].t
        self.t_end = self.rows[-1].t
        self._next = 0
        self._at = -math.inf

    def seek(self, t: float) -> None:
        """Fold every row up to run time ``t`` (clamped to the trace)."""
        if not math.isfinite(t):
            raise ValueError(f"seek time must be finite, got {t!r}")
        t = min(max(t, self.t_start), self.t_end)
        if t < self._at:
            self.state.reset()
            self._next = 0
        rows = self.rows
        while self._next < len(rows) and rows[self._next].t <= t + 1e-9:
            self.state.on_truth(rows[self._next])
            self._next += 1
        self._at = t
        self.state.t = t
        self.state.ended = self._next >= len(rows)

    @property
    def at(self) -> float:
        """Run time folded up to."""
        return self._at if math.isfinite(self._at) else self.t_start


def _with_headings(rows: list[TraceRow]) -> list[TraceRow]:
    """Rows (sorted by time) with a heading each: where given, else towards the car's
    next position at least 5 cm away (its last known heading at the end; 0, east, for
    a car that never moves)."""
    by_car: dict[str, list[int]] = {}
    for i, row in enumerate(rows):
        by_car.setdefault(row.vehicle, []).append(i)
    out = list(rows)
    for idx in by_car.values():
        heading = 0.0
        ahead: list[float | None] = [None] * len(idx)
        nxt: TraceRow | None = None
        for j in range(len(idx) - 1, -1, -1):  # from the end: the next distinct position
            row = rows[idx[j]]
            if nxt is not None and math.hypot(nxt.x - row.x, nxt.y - row.y) > 0.05:
                ahead[j] = math.atan2(nxt.y - row.y, nxt.x - row.x)
                nxt = row
            elif nxt is None:
                nxt = row
            else:
                ahead[j] = ahead[j + 1]
        for j, i in enumerate(idx):
            row = rows[i]
            if row.heading is not None:
                heading = row.heading
                continue
            found = ahead[j]
            if found is not None:
                heading = found
            out[i] = dataclasses.replace(row, heading=heading)
    return out


def rows_from_trace_csv(records: Iterable[Mapping[str, str]]) -> list[TraceRow]:
    """Rows of a ``sim --trace`` / ``up --trace`` CSV (``csv.DictReader`` records);
    ``ValueError`` naming the line when one does not read."""
    out: list[TraceRow] = []
    for i, rec in enumerate(records, start=2):
        try:
            row = TraceRow(
                float(rec["t"]),
                str(rec["vehicle"]),
                float(rec["x"]),
                float(rec["y"]),
                float(rec["speed"]),
                str(rec.get("mode") or ""),
                str(rec.get("reason") or ""),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"line {i}: not a trace row ({exc})") from None
        if not all(math.isfinite(v) for v in (row.t, row.x, row.y, row.speed)):
            raise ValueError(f"line {i}: a number is not finite")
        out.append(row)
    return out
