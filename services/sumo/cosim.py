"""Co-simulation (``crosspath sumo NET.net.xml ROUTES.rou.xml``): SUMO is the world,
crosspath drives the connected cars.

SUMO runs the network, the demand (its ``.rou.xml``: vehicles, flows, trips), the
physics, the insertion of every car and all the cars that are not connected. A car
SUMO inserts is *connected* with probability ``connected_share`` (drawn per car from
the run's seed and its SUMO id); a connected car gets crosspath's vehicle agent
(``services.vehicle``, the same pure core as the harness and the daemons): it senses
every car within range (``services.sim.sensors.perceive``, on SUMO's positions),
plans, broadcasts its future path, obeys the RSU of each junction in ``rsu`` mode, and
drives its SUMO vehicle by commanding its speed each SUMO step: the agent's
acceleration command goes through crosspath's body model (actuator lag, limits:
``services.model.kinematics.step``) and the resulting speed is set with
``traci.vehicle.setSpeed``, with every SUMO check off for that car (speed mode 32:
no safe speed, no right of way, no acceleration limits of SUMO's own; lane-change
mode 0). Its position is SUMO's. The V2X channel, the RSU cores and their
configuration are those of the in-process harness (``services.sim.membus``,
``services.rsu``); the RSUs and their conflict zones come from SUMO's junction
shapes (``services.sumo.from_sumo``: one RSU per junction with internal lanes).
Modes: ``rsu`` (future paths and RSUs), ``fp-only``, ``standalone`` (connected cars
drive on their own sensors, without V2X).

Decisions where the issue is silent:

- Step: SUMO runs at crosspath's physics rate (``1 / physics_hz``, 0.05 s) with the
  ballistic update (crosspath's body integrates the same way); planning, V2X and the
  RSUs at ``planning_hz`` (10 Hz). Collisions: ``--collision.action warn``, checked on
  lanes and junctions with ``--collision.mingap-factor 0`` (only bodies that touch;
  SUMO's default counts any gap under ``minGap`` as a collision); teleporting off.
- A connected car's route is its SUMO route's lanes from the lane it was inserted on,
  each next lane the first connection to the route's next edge; a car that would need
  a lane change to follow its route is left to SUMO (not connected, logged). The
  agent plans on that polyline extended straight beyond the route's end by its
  braking distance plus 10 m, so that it leaves the network at speed (SUMO removes it
  there) instead of stopping at the end.
- A connected car's limits are its SUMO vType's (``accel``, ``decel`` as the comfort
  deceleration, ``emergencyDecel``, ``maxSpeed`` capped by the network's fastest lane),
  with the scenario defaults for the actuator lag and lateral acceleration.
- Ids: a SUMO id that is not a crosspath id (``[A-Za-z0-9_-]{1,32}``, e.g. ``flow.3``)
  becomes one as in ``from_sumo`` (``flow_3``); the result is keyed by crosspath id and
  ``sumo.vehicles[id].sumo_id`` gives SUMO's.
- Result (``services.model.results.RunResult``, ``harness`` ``in-process``): the
  safety metrics (``collisions``, ``min_gap_m``, ``min_pet_s``) and per-car ``stops``,
  ``max_speed_mps``, ``passing_time_s``, ``first_through`` come from crosspath's
  metrics (``services.sim.metrics``) replayed over SUMO's positions of every car; a
  car ``finished`` when SUMO reports it arrived; ``insertion_delay_s`` is SUMO's depart
  delay; ``delay_s`` is its travel time from its intended departure to its arrival
  minus its free-flow time (from its departure position and speed to the route's end,
  accelerating at ``accel``, within ``v_max`` and the curve caps, not stopping at the
  end), so travel time beyond free flow plus the insertion wait; the ``sumo`` section
  has SUMO's own ``timeLoss`` and ``departDelay`` per car (SUMO counts the start from
  rest as lost time, crosspath's delay does not), SUMO's own collision count and the
  share connected.
- The run ends when SUMO has no vehicle left to run, or at ``max_sim_s``.

Two radios, one loop: :class:`Cosimulation` runs the SUMO loop, the agents, the physics
and the result, and its radio and pacing are a few hooks (``_open_radio``, ``_pace``,
``_deliver``, ``_transmit``, ``_tick_rsus``, ``_close_radio``, ``_channel_params``,
``_result_sections``). Here they are the in-process ones: the seeded ``MemoryChannel``
and the ``RsuCore`` of each junction in this process, as fast as SUMO goes (``harness``
``in-process``). With ``CosimOptions.daemons`` (``crosspath sumo --daemons``),
``services.sumo.daemons.DaemonsCosimulation`` overrides only those hooks: every RSU is
a ``crosspath rsu`` daemon process, V2X travels over Zenoh, SUMO steps on the run clock
at ``speed`` (``harness`` ``daemons``; that module says how the cars of the run are
listed and how the daemons are started and stopped). ``services.sumo.run.cosimulate``
picks the one the options ask for.
"""

from __future__ import annotations

import itertools
import logging
import math
import tempfile
import time
import xml.etree.ElementTree as ET
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from protocol import DecodeError, decode, encode
from protocol import keys as keyexpr
from protocol.keys import Stream
from protocol.messages import Message
from services.model.geometry import Polyline
from services.model.kinematics import BodyState, Limits, TruthState, curve_speed_cap, step
from services.model.results import (
    ChannelParams,
    Origin,
    RunResult,
    RunSummary,
    SumoSection,
    SumoVehicle,
    VehicleResult,
)
from services.model.scenario import Scenario, ScenarioFile
from services.model.types import Policy, RunMode, parse_mode, parse_policy
from services.rsu.config import rsu_config
from services.rsu.core import Outgoing as RsuOutgoing
from services.rsu.core import RsuCore
from services.sim.membus import ChannelModel, MemoryChannel
from services.sim.metrics import FREE_FLOW_STEP_M, MetricsRecorder
from services.sim.results import provenance, run_result
from services.sim.sensors import perceive
from services.sumo.baseline import SUMO_RUN_ARGS, sumo_api
from services.sumo.from_sumo import SumoNetwork, _Ids, _join, read_net, scenario_from_net
from services.sumo.netgen import sumo_binary
from services.vehicle.agent import AgentSpec, VehicleAgent
from services.vehicle.agent import Outgoing as CarOutgoing

__all__ = ["CosimOptions", "Cosimulation"]

log = logging.getLogger("crosspath.sumo.cosim")

SPEED_MODE_CROSSPATH = 32
"""SUMO speed mode of a connected car: every SUMO check off (bit 5 set: not even the
right of way inside a junction); its speed is exactly the one crosspath commands."""
RUNOUT_EXTRA_M = 10.0
NOT_CONNECTED = "SUMO"
"""Mode label of a car SUMO drives."""
MAX_SPEED = 1000.0
"""Largest run speed of the daemons mode (run seconds per wall second, as ``crosspath up``)."""


@dataclass(frozen=True, slots=True)
class CosimOptions:
    """One co-simulation. ``mode``/``policy`` take the enums or their names;
    ``connected_share`` a fraction 0..1; ``max_sim_s`` [s] > 0; ``rsus``: one RSU per
    junction (rsu mode); ``sumo_args`` extra options for SUMO. ``daemons``: the RSUs as
    daemons over Zenoh (``services.sumo.daemons``), at ``speed`` run seconds per wall
    second (0 < speed <= 1000), run time 0 ``start_delay_s`` [wall s, 0..60] after the
    start, logs and keys in ``run_dir`` (default ``results/sumo/<time>-<id>``), V2X
    unsigned when ``insecure``; ``channel`` must then inject no loss (the network is
    real). ``speed``, ``run_dir``, ``insecure``, ``start_delay_s`` only apply to the
    daemons mode."""

    mode: RunMode = RunMode.RSU
    policy: Policy = Policy.PAPER
    seed: int = 0
    connected_share: float = 1.0
    channel: ChannelModel = field(default_factory=ChannelModel)
    max_sim_s: float = 3600.0
    rsus: bool = True
    sumo_args: tuple[str, ...] = ()
    daemons: bool = False
    speed: float = 1.0
    run_dir: Path | None = None
    insecure: bool = False
    start_delay_s: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", parse_mode(self.mode))
        object.__setattr__(self, "policy", parse_policy(self.policy))
        object.__setattr__(self, "sumo_args", tuple(self.sumo_args))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an int >= 0, got {self.seed!r}")
        share = self.connected_share
        if isinstance(share, bool) or not isinstance(share, int | float) or not 0 <= share <= 1:
            raise ValueError(f"connected_share must be a fraction 0..1, got {share!r}")
        m = self.max_sim_s
        if (
            isinstance(m, bool)
            or not isinstance(m, int | float)
            or not (math.isfinite(m) and m > 0)
        ):
            raise ValueError(f"max_sim_s must be a finite number > 0, got {m!r}")
        if not isinstance(self.channel, ChannelModel):
            raise TypeError(f"channel must be a ChannelModel, got {self.channel!r}")
        sp = self.speed
        if isinstance(sp, bool) or not isinstance(sp, int | float) or not 0 < sp <= MAX_SPEED:
            raise ValueError(f"speed must be a number in (0, {MAX_SPEED:g}], got {sp!r}")
        d = self.start_delay_s
        if isinstance(d, bool) or not isinstance(d, int | float) or not 0 <= d <= 60:
            raise ValueError(f"start_delay_s must be a number within 0..60 [s], got {d!r}")
        if self.run_dir is not None:
            object.__setattr__(self, "run_dir", Path(self.run_dir))
        if self.daemons and self.channel.loss > 0:
            raise ValueError(
                "loss is injected by the in-process channel only; the daemons run over a "
                "real network (use the network lab to inject loss)"
            )


@dataclass(slots=True)
class _Car:
    """One SUMO vehicle as crosspath sees it."""

    cid: str
    sumo_id: str
    lanes: list[str] | None
    route: Polyline
    offsets: dict[str, tuple[float, float]]
    """SUMO lane -> (arc length of its start on ``route`` [m], shape length / lane length)."""
    length: float
    width: float
    arrival_s: float
    inserted_s: float
    depart_s_front: float
    depart_speed: float
    limits: Limits
    agent: VehicleAgent | None = None
    accel: float = 0.0
    arrived_s: float | None = None


def _draw_connected(seed: int, sumo_id: str, share: float) -> bool:
    if share >= 1.0:
        return True
    if share <= 0.0:
        return False
    rng = np.random.default_rng([seed, zlib.crc32(f"connected:{sumo_id}".encode())])
    return bool(rng.random() < share)


def _free_time_to_exit(route: Polyline, s0: float, v0: float, limits: Limits) -> float:
    """Least time [s] from ``s0`` at ``v0`` to the end of ``route``, alone, accelerating
    at ``accel`` within ``v_max`` and the curve caps, not stopping at the end."""
    end = route.length
    if not end > s0:
        return 0.0
    n = max(math.ceil((end - s0) / FREE_FLOW_STEP_M), 2)
    s = np.linspace(s0, end, n + 1)
    ds = (end - s0) / n
    v = np.array(curve_speed_cap(route, s, limits.lat_accel, limits.v_max, pad_m=ds))
    v[0] = min(v[0], max(v0, 0.0))
    for k in range(1, n + 1):
        v[k] = min(v[k], math.sqrt(v[k - 1] ** 2 + 2.0 * limits.accel * ds))
    for k in range(n - 1, 0, -1):
        v[k] = min(v[k], math.sqrt(v[k + 1] ** 2 + 2.0 * limits.decel_comfort * ds))
    mean = np.maximum(0.5 * (v[:-1] + v[1:]), 1e-6)
    return float(np.sum(ds / mean))


@dataclass(slots=True)
class Cosimulation:
    """One co-simulation of ``net`` and ``routes``; ``run()`` returns the run result."""

    net_path: Path
    routes_path: Path
    options: CosimOptions = field(default_factory=CosimOptions)
    origin: Origin = field(default_factory=Origin)
    net: SumoNetwork = field(init=False)
    base: Scenario = field(init=False)
    cars: dict[str, _Car] = field(init=False, default_factory=dict)
    present: dict[str, None] = field(init=False, default_factory=dict)
    rsus: dict[str, RsuCore] = field(init=False, default_factory=dict)
    channel: MemoryChannel = field(init=False)
    counters: dict[str, int] = field(init=False, default_factory=dict)
    steps: list[tuple[float, list[TruthState], dict[str, str], dict[str, str]]] = field(
        init=False, default_factory=list
    )
    sumo_pairs: set[tuple[str, str]] = field(init=False, default_factory=set)
    _ids: _Ids = field(init=False)
    _by_sumo: dict[str, str] = field(init=False, default_factory=dict)
    _route_scenarios: dict[tuple[str, ...], tuple[str, Scenario]] = field(
        init=False, default_factory=dict
    )
    _lane_len: dict[str, float] = field(init=False, default_factory=dict)
    _api: ModuleType | None = field(init=False, default=None)
    _now: float = field(init=False, default=0.0)
    """Run time of SUMO's latest step [s]."""

    def __post_init__(self) -> None:
        for p in (self.net_path, self.routes_path):
            if not Path(p).is_file():
                raise ValueError(f"{p}: no such file")
        self.net = read_net(self.net_path)
        # the map: lanes, junction zones, RSUs and params of from_sumo (one route suffices)
        self.base = scenario_from_net(
            self.net_path, max_routes=1, rsus=self.options.rsus, name=None
        )
        o = self.options
        self.rsus = (
            {r.id: RsuCore(rsu_config(self.base, r.id, o.policy)) for r in self.base.rsus}
            if o.mode is RunMode.RSU
            else {}
        )
        self._ids = _Ids()
        self._ids.used.update(r.id for r in self.base.rsus)
        self.channel = MemoryChannel(o.channel, seed=o.seed * 7919 + 17)

    # ------------------------------------------------------------------ helpers
    @property
    def api(self) -> ModuleType:
        if self._api is None:
            raise RuntimeError("SUMO is not running")
        return self._api

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def _lane_length(self, lane: str) -> float:
        got = self._lane_len.get(lane)
        if got is None:
            got = self._lane_len[lane] = float(self.api.lane.getLength(lane))
        return got

    def _lane_path(self, first_lane: str, edges: Sequence[str]) -> list[str] | None:
        """SUMO lanes from ``first_lane`` along ``edges`` (first connection to each next
        edge, internal lanes included); None when a lane change would be needed."""
        net = self.net
        if net.lane_edge.get(first_lane) != edges[0]:
            return None
        lanes = [first_lane]
        cur = first_lane
        for nxt in edges[1:]:
            conn = next(
                (
                    c
                    for c in net.connections
                    if c.from_lane == cur and net.lane_edge.get(c.to_lane) == nxt
                ),
                None,
            )
            if conn is None:
                return None
            lanes += [*net.via_chain(conn.via), conn.to_lane]
            cur = conn.to_lane
        return lanes

    def _route_of(
        self, lanes: list[str]
    ) -> tuple[Polyline, dict[str, tuple[float, float]], list[tuple[float, float]]]:
        offsets: dict[str, tuple[float, float]] = {}
        acc = 0.0
        for lid in lanes:
            shape = self.net.lanes[lid]
            shape_len = sum(math.dist(a, b) for a, b in itertools.pairwise(shape))
            lane_len = self._lane_length(lid)
            offsets[lid] = (acc, shape_len / lane_len if lane_len > 0 else 1.0)
            acc += shape_len
        pts = _join([self.net.lanes[lid] for lid in lanes])
        return Polyline(np.array(pts, dtype=np.float64)), offsets, pts

    def _agent_scenario(
        self, lanes: list[str], pts: list[tuple[float, float]], limits: Limits
    ) -> tuple[str, Scenario]:
        """The map plus this lane path (extended by the run-out) as route ``r``."""
        key = tuple(lanes)
        hit = self._route_scenarios.get(key)
        if hit is not None:
            return hit
        (x0, y0), (x1, y1) = pts[-2], pts[-1]
        d = math.hypot(x1 - x0, y1 - y0)
        runout = limits.v_max**2 / (2.0 * limits.decel_comfort) + RUNOUT_EXTRA_M
        ext = (x1 + (x1 - x0) / d * runout, y1 + (y1 - y0) / d * runout)
        doc = self.base.spec.model_dump()
        doc.update(
            routes=[{"id": "r", "points": [list(q) for q in [*pts, ext]]}],
            vehicles=[{"id": "v", "route": "r"}],
            flows=[],
        )
        sc = Scenario(ScenarioFile.model_validate(doc), self.base.source)
        self._route_scenarios[key] = ("r", sc)
        return "r", sc

    def _limits(self, sid: str) -> Limits:
        p = self.base.params
        api = self.api
        decel = float(api.vehicle.getDecel(sid))
        return Limits(
            v_max=min(float(api.vehicle.getMaxSpeed(sid)), p.v_max_mps),
            accel=float(api.vehicle.getAccel(sid)),
            decel_comfort=decel,
            decel_emergency=max(float(api.vehicle.getEmergencyDecel(sid)), decel),
            actuator_lag_s=p.actuator_lag_s,
            lat_accel=p.lat_accel_mps2,
        )

    # ------------------------------------------------------------------ SUMO side
    def _depart(self, sid: str, now: float) -> None:
        api = self.api
        o = self.options
        cid = self._car_id(sid)
        self._by_sumo[sid] = cid
        lane = str(api.vehicle.getLaneID(sid))
        edges = [str(e) for e in api.vehicle.getRoute(sid)]
        length = float(api.vehicle.getLength(sid))
        width = float(api.vehicle.getWidth(sid))
        limits = self._limits(sid)
        lanes = self._lane_path(lane, edges)
        connected = _draw_connected(o.seed, sid, o.connected_share) and self._may_connect(cid)
        if lanes is None:
            # a lane change needed (or an odd lane): SUMO drives it; its route for the
            # metrics is the lane it is on
            if connected:
                log.warning("%s: its route needs a lane change, SUMO drives it", sid)
                self._count("lane_change_needed")
            connected = False
            lanes = [lane]
        route, offsets, pts = self._route_of(lanes)
        lane_pos = float(api.vehicle.getLanePosition(sid))
        s_front = offsets[lane][0] + lane_pos * offsets[lane][1]
        car = _Car(
            cid=cid,
            sumo_id=sid,
            lanes=lanes,
            route=route,
            offsets=offsets,
            length=length,
            width=width,
            arrival_s=max(0.0, now - float(api.vehicle.getDepartDelay(sid))),
            inserted_s=now,
            depart_s_front=s_front,
            depart_speed=float(api.vehicle.getSpeed(sid)),
            limits=limits,
        )
        if connected and len(pts) >= 2:
            rid, sc = self._agent_scenario(lanes, pts, limits)
            spec = AgentSpec(
                vehicle_id=cid,
                route_id=rid,
                goal_s=sc.route(rid).length,
                length=length,
                width=width,
                limits=limits,
                params=sc.spec.vehicle_params,
            )
            car.agent = VehicleAgent(spec, sc, v2x=o.mode is not RunMode.STANDALONE)
            api.vehicle.setSpeedMode(sid, SPEED_MODE_CROSSPATH)
            api.vehicle.setLaneChangeMode(sid, 0)
        self.cars[cid] = car
        self.present[cid] = None

    def _truth(self, car: _Car, now: float) -> TruthState:
        api = self.api
        sid = car.sumo_id
        fx, fy = api.vehicle.getPosition(sid)
        heading = math.radians(90.0 - float(api.vehicle.getAngle(sid)))
        half = 0.5 * car.length
        x, y = float(fx) - math.cos(heading) * half, float(fy) - math.sin(heading) * half
        lane = str(api.vehicle.getLaneID(sid))
        off = car.offsets.get(lane)
        if off is not None:
            s = off[0] + float(api.vehicle.getLanePosition(sid)) * off[1] - half
        else:
            s = car.route.project(x, y)[0]
        speed = float(api.vehicle.getSpeed(sid))
        accel = car.accel if car.agent is not None else float(api.vehicle.getAcceleration(sid))
        return TruthState(
            id=car.cid,
            t=now,
            x=x,
            y=y,
            heading=heading,
            speed=speed,
            accel=accel,
            s=s,
            length=car.length,
            width=car.width,
        )

    def _open_sumo(self, label: str, *extra: str) -> ModuleType:
        """Start SUMO on the network and demand at the physics step with ``extra``
        options (then the seed and ``sumo_args``); its API module."""
        api = sumo_api()
        cmd = [
            str(sumo_binary("sumo")),
            "-n",
            str(self.net_path),
            "-r",
            str(self.routes_path),
            "--step-length",
            f"{self.base.params.physics_dt_s:g}",
            *extra,
            "--seed",
            str(self.options.seed),
            *self.options.sumo_args,
        ]
        if api.__name__ == "traci":
            api.start(cmd, label=f"{label}-{id(self)}")
        else:
            api.start(cmd)
        return api

    def _start(self, tripinfo: Path) -> None:
        self._api = self._open_sumo(
            "cosim",
            "--step-method.ballistic",
            "true",
            "--tripinfo-output",
            str(tripinfo),
            *SUMO_RUN_ARGS,
            "--collision.mingap-factor",
            "0",
        )

    # ------------------------------------------------------------------ radio and pacing
    # The hooks below are the in-process radio (the MemoryChannel and the RsuCores of
    # this process) and its pacing (none: as fast as SUMO goes). The daemons mode
    # (``services.sumo.daemons``) overrides exactly these; the loop, the physics and
    # the result are shared.
    harness = "in-process"

    def _car_id(self, sumo_id: str) -> str:
        """The crosspath id of a SUMO vehicle departing now."""
        return self._ids(sumo_id)

    def _may_connect(self, cid: str) -> bool:
        """Whether car ``cid`` (drawn connected) may get an agent."""
        return True

    def _open_radio(self) -> None:
        """Before SUMO starts."""

    def _close_radio(self) -> None:
        """After SUMO closed (also after an error)."""

    def _pace(self, now: float) -> None:
        """Wait until run time ``now`` [s] has come (after SUMO's step to ``now``)."""

    def _channel_params(self) -> ChannelParams:
        ch = self.options.channel
        return ChannelParams(
            kind="memory", loss=ch.loss, latency_s=ch.latency_s, jitter_s=ch.jitter_s
        )

    def _result_sections(self, sim_s: float) -> dict[str, Any]:
        """The optional fields of the run result this radio fills in."""
        return {"loss": self.options.channel.loss}

    def _send(self, now: float, key: str, message: Message, receivers: list[str]) -> None:
        self.channel.send(now, key, encode(message), receivers)

    def _listeners(self) -> list[str]:
        return [c for c in self.present if self.cars[c].agent is not None]

    def _send_rsu(self, now: float, rsu_id: str, og: RsuOutgoing) -> None:
        if og.vehicle is None:
            self._send(now, keyexpr.rsu_beacon(rsu_id), og.message, self._listeners())
        elif og.vehicle in self.present and self.cars[og.vehicle].agent is not None:
            self._send(now, keyexpr.rsu_command(rsu_id, og.vehicle), og.message, [og.vehicle])

    def _deliver(self, now: float) -> None:
        # a delivery is (at, order, receiver, key, payload) (services.sim.membus)
        for _at, _order, receiver, key, payload in self.channel.due(now):
            try:
                message, parsed = decode(payload), keyexpr.parse(key)
            except (DecodeError, ValueError):
                self._count("malformed")
                continue
            if receiver in self.rsus:
                for og in self.rsus[receiver].on_message(now, message, parsed.rsu):
                    self._send_rsu(now, receiver, og)
                continue
            car = self.cars.get(receiver)
            if car is not None and car.agent is not None and receiver in self.present:
                car.agent.on_message(now, message, parsed.rsu)

    def _transmit(self, now: float, cid: str, out: CarOutgoing) -> None:
        """Send one of car ``cid``'s outbound messages."""
        if out.stream is Stream.FP:
            receivers = [c for c in self._listeners() if c != cid] + list(self.rsus)
            self._send(now, keyexpr.future_path(cid), out.message, receivers)
        elif out.stream is Stream.AP and out.rsu in self.rsus:
            self._send(now, keyexpr.autonomous_path(out.rsu, cid), out.message, [out.rsu])

    def _tick_rsus(self, now: float) -> None:
        """The RSUs' planning step (after the cars')."""
        for rid, rsu in self.rsus.items():
            for og in rsu.tick(now):
                self._send_rsu(now, rid, og)

    # ------------------------------------------------------------------ loop
    def run(self) -> RunResult:
        """Run SUMO to the end with crosspath driving the connected cars; the result."""
        p = self.base.params
        dt = p.physics_dt_s
        plan_every = max(round(p.physics_hz / p.planning_hz), 1)
        wall0 = time.perf_counter()
        reasons: dict[str, str] = {}
        now = 0.0
        with tempfile.TemporaryDirectory(prefix="crosspath-cosim-") as tmp:
            tripinfo = Path(tmp) / "tripinfo.xml"
            try:
                self._open_radio()
                self._start(tripinfo)
                api = self.api
                try:
                    self._loop(api, dt, plan_every, reasons)
                finally:
                    now = self._now
                    api.close()
                    self._api = None
            finally:
                self._close_radio()
            trips = _tripinfo(tripinfo)
        return self._result(now, time.perf_counter() - wall0, trips)

    def _loop(self, api: ModuleType, dt: float, plan_every: int, reasons: dict[str, str]) -> None:
        """SUMO steps until no vehicle is left or ``max_sim_s``."""
        o = self.options
        k = 0
        while True:
            api.simulationStep()
            now = float(api.simulation.getTime())
            self._now = now
            self._pace(now)
            for sid in api.simulation.getArrivedIDList():
                cid = self._by_sumo.get(str(sid))
                if cid is not None:
                    self.cars[cid].arrived_s = now
                    self.present.pop(cid, None)
            for sid in api.simulation.getDepartedIDList():
                self._depart(str(sid), now)
            for c in api.simulation.getCollisions():
                a, b = str(c.collider), str(c.victim)
                self.sumo_pairs.add((min(a, b), max(a, b)))
            truths = {cid: self._truth(self.cars[cid], now) for cid in self.present}
            self._deliver(now)
            if k % plan_every == 0:
                self._plan(now, truths, reasons)
            modes = {
                cid: (NOT_CONNECTED if (agent := self.cars[cid].agent) is None else agent.mode.name)
                for cid in truths
            }
            self.steps.append(
                (
                    now,
                    list(truths.values()),
                    modes,
                    {c: reasons.get(c, NOT_CONNECTED) for c in truths},
                )
            )
            if now >= o.max_sim_s - 1e-9 or api.simulation.getMinExpectedNumber() <= 0:
                break
            self._drive(truths, dt)
            k += 1

    def _plan(self, now: float, truths: dict[str, TruthState], reasons: dict[str, str]) -> None:
        params = self.base.params
        values = list(truths.values())
        for cid, ego in truths.items():
            agent = self.cars[cid].agent
            if agent is None:
                continue
            others = [t for t in values if t.id != cid]
            sensed = perceive(ego, others, self.base.occluders, params.sensor_range_m)
            result = agent.tick(now, ego, sensed)
            reasons[cid] = result.plan.reason.value
            for out in result.outbound:
                self._transmit(now, cid, out)
        self._tick_rsus(now)

    def _drive(self, truths: dict[str, TruthState], dt: float) -> None:
        """Command each connected car's speed for the next SUMO step."""
        for cid, t in truths.items():
            car = self.cars[cid]
            if car.agent is None:
                continue
            body = BodyState(s=t.s, v=t.speed, a=car.accel)
            nxt = step(body, car.agent.command(body), dt, car.limits)
            car.accel = nxt.a
            self.api.vehicle.setSpeed(car.sumo_id, max(nxt.v, 0.0))

    # ------------------------------------------------------------------ result
    def _metrics_scenario(self) -> Scenario:
        """The map with every car's route and the car, for the metrics replay."""
        routes: list[dict[str, Any]] = []
        rid_of: dict[tuple[str, ...], str] = {}
        vehicles: list[dict[str, Any]] = []
        for cid, car in self.cars.items():
            key = tuple(car.lanes or ())
            if key not in rid_of:
                rid_of[key] = f"r{len(rid_of)}"
                routes.append({"id": rid_of[key], "points": [list(p) for p in car.route.points]})
            start = min(max(car.depart_s_front - 0.5 * car.length, 0.0), car.route.length * 0.5)
            vehicles.append(
                {
                    "id": cid,
                    "route": rid_of[key],
                    "start_time_s": car.arrival_s,
                    "start_offset_m": round(start, 6),
                    "length_m": car.length,
                    "width_m": car.width,
                }
            )
        if not vehicles:
            return self.base
        doc = self.base.spec.model_dump()
        doc.update(routes=routes, vehicles=vehicles, flows=[])
        return Scenario(ScenarioFile.model_validate(doc), self.base.source)

    def _result(
        self, sim_s: float, wall_s: float, trips: dict[str, tuple[float, float]]
    ) -> RunResult:
        o = self.options
        sc = self._metrics_scenario()
        rec = MetricsRecorder(sc)
        for car in self.cars.values():
            rec.inserted(car.cid, car.arrival_s, car.inserted_s)
        for t, states, modes, reasons in self.steps:
            rec.record(t, states, modes, reasons)
        metrics = rec.result()
        vehicles: dict[str, VehicleResult] = {}
        sumo_cars: dict[str, SumoVehicle] = {}
        delays: list[float] = []
        for cid, car in sorted(self.cars.items()):
            vm = metrics.vehicles[cid]
            delay = None
            if car.arrived_s is not None:
                s0 = car.depart_s_front
                free = _free_time_to_exit(car.route, s0, car.depart_speed, car.limits)
                delay = max(0.0, car.arrived_s - car.arrival_s - free)
                delays.append(delay)
            vehicles[cid] = VehicleResult(
                passing_time_s=_fin(vm.passing_time_s),
                first_through=bool(vm.first_through),
                stops=int(vm.stops),
                max_speed_mps=_fin(vm.max_speed_mps),
                finished=car.arrived_s is not None,
                delay_s=_fin(delay),
                insertion_delay_s=_fin(car.inserted_s - car.arrival_s),
            )
            trip = trips.get(car.sumo_id)
            sumo_cars[cid] = SumoVehicle(
                sumo_id=car.sumo_id,
                connected=car.agent is not None,
                time_loss_s=None if trip is None else _fin(max(trip[0], 0.0)),
                depart_delay_s=None if trip is None else _fin(max(trip[1], 0.0)),
            )
        losses = [v.time_loss_s for v in sumo_cars.values() if v.time_loss_s is not None]
        finished = sum(1 for v in vehicles.values() if v.finished)
        summary = RunSummary(
            vehicles_inserted=len(vehicles),
            vehicles_finished=finished,
            all_finished=bool(vehicles) and finished == len(vehicles) and not self.present,
            mean_delay_s=_fin(float(np.mean(delays))) if delays else None,
            p95_delay_s=_fin(float(np.percentile(delays, 95.0))) if delays else None,
            throughput_vph=_fin(finished * 3600.0 / sim_s) if sim_s > 0 else None,
            stops_per_vehicle=(
                _fin(sum(v.stops for v in vehicles.values()) / len(vehicles)) if vehicles else None
            ),
        )
        channel = self._channel_params()
        sumo = SumoSection(
            net=str(self.net_path),
            routes=str(self.routes_path),
            step_s=self.base.params.physics_dt_s,
            connected_share=float(o.connected_share),
            connected=sum(1 for c in self.cars.values() if c.agent is not None),
            collisions=len(self.sumo_pairs),
            mean_time_loss_s=_fin(float(np.mean(losses))) if losses else None,
            vehicles=sumo_cars,
        )
        result = run_result(
            metrics,
            mode=o.mode,
            policy=o.policy if o.mode is RunMode.RSU else None,
            seed=o.seed,
            sim_s=sim_s,
            wall_s=wall_s,
            scenario=self.base.name,
            start_times={cid: c.arrival_s for cid, c in self.cars.items()},
            harness=self.harness,
            provenance=provenance(self.base, self.origin, channel, o.mode, o.policy),
            summary=summary,
            sumo=sumo,
            **self._result_sections(sim_s),
        )
        return result.updated(
            vehicles=vehicles,
            all_finished=summary.all_finished,
        )


def _fin(x: float | None) -> float | None:
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), 4)


def _tripinfo(path: Path) -> dict[str, tuple[float, float]]:
    """SUMO id -> (timeLoss, departDelay) [s] of the arrived vehicles."""
    if not path.is_file():
        return {}
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError:
        return {}
    return {
        el.get("id", ""): (float(el.get("timeLoss", "nan")), float(el.get("departDelay", "nan")))
        for el in root.iter("tripinfo")
    }
