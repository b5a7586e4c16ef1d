"""The car's autonomy stack as one pure object: planner + future path + coordinated mode.

``VehicleAgent`` is sans-IO: the harness (in-process simulation or the vehicle
daemon) passes ``now`` and inputs in and sends what comes out:

- ``on_message(now, message, rsu)``: a received future path of another car, a
  mode command or coordinated path from an RSU, or an RSU beacon;
- ``tick(now, ego, sensed)`` at the planning rate (10 Hz): plans, and returns
  the messages to send (the future path broadcast and, while coordinated, the
  autonomous path to the RSU; each every tick or, by the scenario's ``fp_rule`` /
  ``ap_rule``, on change: ``services.model.send_rule``) and the next deadline;
- ``command(body)`` at the physics rate (20 Hz): the acceleration command that
  tracks the last planned speed profile (the controller).

Several RSUs: the car is coordinated by at most one RSU at a time, its owner (the RSU
of the next intersection on its route, while the car is in its coverage); every other
RSU's commands and paths are ignored until the owner lets the car go, and the car hands
itself over as it leaves the owner's zone. The rule is in
``services.vehicle.coordination`` ("Several RSUs").
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from protocol.keys import Stream
from protocol.messages import (
    AutonomousPath,
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Message,
    Mode,
    ModeCommand,
    RsuBeacon,
    VehicleLimits,
)
from services.model.kinematics import BodyState, Limits, TruthState
from services.model.scenario import Scenario, VehicleParams
from services.model.send_rule import ChangeRule, change_rule
from services.vehicle.coordination import (
    RsuReach,
    VehicleEvent,
    Where,
    next_mode,
    owner_lapsed,
    owner_refusal,
    owner_zone_exit,
)
from services.vehicle.future_path import future_path_points
from services.vehicle.planner import AutonomousPlanner, Coordination, Plan, Reason
from services.vehicle.profile import FloatArray, SpeedProfile

log = logging.getLogger("crosspath.vehicle")

# The controller's look-ahead and time constant and the future-path staleness are the
# scenario's [vehicle_params] (services.model.scenario.VehicleParams), in ``AgentSpec.params``.

STOP_MARGIN_M = 0.1
"""A final stop ends this far short of the profile's rest point [m] (the lag's error)."""

STOP_ROOM_M = 0.01
"""Closer than this to the end of a final stop [m], the car brakes at once to rest."""

FINAL_STOP_M = 1.5
"""A car this close to where its profile comes to rest [m] (plus the controller's
look-ahead) brakes at the constant deceleration that ends there."""


@dataclass(frozen=True, slots=True)
class AgentSpec:
    """One car as its agent sees itself: resolved goal and limits (the scenario file's
    ``[[vehicles]]`` entry is ``services.model.scenario.VehicleSpec``)."""

    vehicle_id: str
    route_id: str
    goal_s: float
    length: float
    width: float
    limits: Limits
    params: VehicleParams = field(default_factory=VehicleParams)


@dataclass(frozen=True, slots=True)
class Outgoing:
    """A message the car sends: the future path broadcast, or an autonomous path to an
    RSU (the RSU core's counterpart is ``services.rsu.core.Outgoing``)."""

    stream: Stream
    message: FuturePath | AutonomousPath
    rsu: str | None = None


@dataclass(frozen=True, slots=True)
class TickResult:
    plan: Plan
    outbound: list[Outgoing]
    mode: Mode
    next_deadline: float


@dataclass(slots=True)
class _Coordinated:
    mode: Mode = Mode.AUTO
    rsu: str | None = None
    """The owner: the RSU coordinating the car (None exactly in AUTO)."""
    exit_s: float = np.inf
    """Arc length [m] at which the car leaves the owner's zone (the handover)."""
    since: float = 0.0
    last_path_at: float = -np.inf
    target_s: FloatArray | None = None
    target_v: FloatArray | None = None
    hold_s: float = np.inf
    """Arc length [m] of a stop inside the coordinated path (a slot's stop-and-go), else inf."""
    hold_until: float = -np.inf
    """Run time [s] at which the path leaves that stop: targets beyond it count only then."""


def interior_hold(s: FloatArray, points: FloatArray) -> tuple[float, float]:
    """The first stop of a coordinated path that the path leaves again: its arc length
    ``s`` [m] and the time [s] of its last held point; ``(inf, -inf)`` when the path holds
    only at its end (or never). A path's points are followed by arc length; a slot's
    stop-and-go waits in time, which arc length alone does not show (issue 12: cars crept
    through the wait at 0.2 m/s, into the box)."""
    n = points.shape[0]
    if n < 3:
        return np.inf, -np.inf
    same = np.all(np.abs(np.diff(points[:, :2], axis=0)) <= 1e-6, axis=1)
    moved = np.flatnonzero(~same)
    for i in np.flatnonzero(same):
        later = moved[moved > i]
        if later.size:
            return float(s[i]), float(points[int(later[0]), 2])
    return np.inf, -np.inf


@dataclass(slots=True)
class VehicleAgent:
    """Planner, future-path sender and coordinated mode of one car."""

    spec: AgentSpec
    scenario: Scenario
    v2x: bool = True
    planner: AutonomousPlanner = field(init=False)
    coordination: _Coordinated = field(init=False)
    future_paths: dict[str, tuple[FuturePath, float]] = field(init=False)
    rsus: dict[str, tuple[RsuBeacon, float]] = field(init=False)
    last_plan: Plan | None = field(init=False, default=None)
    seq: int = field(init=False, default=0)
    counters: dict[str, int] = field(init=False)
    fp_rule: ChangeRule | None = field(init=False, default=None)
    """When the future path is sent (``services.model.send_rule``); None: every tick."""
    fp_hold_s: float = field(init=False, default=0.0)
    """How long a received future path is kept [s] (``Scenario.fp_hold_s``)."""
    ap_rule: ChangeRule | None = field(init=False, default=None)
    """When the autonomous path is sent while coordinated; None: every tick."""
    cp_timeout_s: float = field(init=False, default=0.0)
    """Back to AUTO after this long without a coordinated path [s]."""
    where: Where | None = field(init=False, default=None)
    """The car's place at its last planning step (None before the first)."""
    reach: dict[str, RsuReach] = field(init=False)
    """The scenario's RSUs: the intersection each serves and its coverage disc."""
    rsu_newest_us: dict[str, int] = field(init=False)
    """Per RSU, the generation time [µs] of the newest command or coordinated path taken
    from it: an older one arriving later (reordered by the network, or withheld and
    released by an attacker, which the replay window cannot tell from a first delivery)
    is ignored, so a stale C_SLOW never undoes a newer release. Written only for RSUs
    whose message passed the owner rule and whose reach is known (a few per route)."""
    _rest_of: tuple[SpeedProfile | None, float | None] = field(init=False, default=(None, None))
    """The last plan's profile and where it comes to rest (:meth:`_rest_s`), computed once
    per plan (10 Hz) for the controller (20 Hz)."""

    def __post_init__(self) -> None:
        p = self.scenario.params
        self.planner = AutonomousPlanner(
            vehicle_id=self.spec.vehicle_id,
            scenario=self.scenario,
            route_id=self.spec.route_id,
            goal_s=self.spec.goal_s,
            length=self.spec.length,
            width=self.spec.width,
            limits=self.spec.limits,
            headway_s=p.headway_s,
            sensor_range_m=p.sensor_range_m,
            params=self.spec.params,
        )
        self.coordination = _Coordinated()
        self.future_paths = {}
        self.rsus = {}
        self.counters = {}
        self.reach = {}
        self.rsu_newest_us = {}
        for r in self.scenario.rsus:
            cx, cy = self.scenario.intersection(r.intersection).center
            self.reach[r.id] = RsuReach(r.intersection, float(cx), float(cy), r.coverage_m)
        self.fp_rule = change_rule(self.spec.params)
        self.fp_hold_s = self.scenario.fp_hold_s(self.spec.params.fp_stale_s)
        self.ap_rule = change_rule(self.spec.params, stream="ap")
        # the RSU answers every autonomous path with a coordinated path: when the former is
        # sent only on change, the latter may come that much later; and when the RSU sends
        # its coordinated path only on change (cp_rule), up to cp_refresh_s later still
        vp = self.spec.params
        self.cp_timeout_s = (
            p.coordinated_timeout_s
            + (0.0 if self.ap_rule is None else vp.ap_refresh_s)
            + (0.0 if vp.cp_rule == "periodic" else vp.cp_refresh_s)
        )

    @property
    def mode(self) -> Mode:
        return self.coordination.mode

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    # ------------------------------------------------------------------ input
    def on_message(self, now: float, message: Message, rsu: str | None = None) -> None:
        """Take one received, decoded message. Never raises on odd but valid input."""
        if not self.v2x:
            return
        me = self.spec.vehicle_id
        if isinstance(message, FuturePath):
            if message.header.sender != me:
                prev = self.future_paths.get(message.header.sender)
                if (
                    prev is None
                    or message.header.seq > prev[0].header.seq
                    or (message.header.time_us > prev[0].header.time_us)
                ):
                    self.future_paths[message.header.sender] = (message, now)
            return
        if isinstance(message, RsuBeacon):
            self.rsus[message.header.sender] = (message, now)
            return
        if isinstance(message, ModeCommand):
            if message.vehicle != me:
                self._count("cmd_not_mine")
                return
            why = self._refusal(rsu or message.header.sender, message.command)
            if why is None and self._out_of_order(rsu or message.header.sender, message):
                why = "out_of_order"
            if why is not None:
                self._count(f"cmd_{why}")
                return
            if message.command is Command.TERMINATE:
                event = VehicleEvent.TERMINATE
            elif message.mode is Mode.C_SLOW:
                event = VehicleEvent.INITIATE_SLOW
            else:
                event = VehicleEvent.INITIATE_FAST
            self._apply(now, event, rsu or message.header.sender)
            return
        if isinstance(message, CoordinatedPath):
            if message.vehicle != me:
                self._count("cp_not_mine")
                return
            c = self.coordination
            if c.mode is Mode.AUTO:
                self._count("cp_ignored")
                return
            why = self._refusal(rsu or message.header.sender, None)
            if why is None and self._out_of_order(rsu or message.header.sender, message):
                why = "out_of_order"
            if why is not None:
                self._count(f"cp_{why}")
                return
            if message.mode is not c.mode and message.mode in (Mode.C_SLOW, Mode.C_FAST):
                # the path implies its mode: a lost initiation is recovered from it
                self._apply(
                    now,
                    VehicleEvent.INITIATE_SLOW
                    if message.mode is Mode.C_SLOW
                    else VehicleEvent.INITIATE_FAST,
                    rsu or message.header.sender,
                )
            self._follow(now, message)
            return
        self._count("ignored")

    def _reach(self, rsu: str) -> RsuReach | None:
        """The RSU's intersection and coverage: the scenario's, else its last beacon's."""
        known = self.reach.get(rsu)
        if known is not None:
            return known
        heard = self.rsus.get(rsu)
        if heard is None:
            return None
        b = heard[0]
        return RsuReach(b.intersection, b.x, b.y, b.radius)

    def _out_of_order(self, rsu: str, message: Message) -> bool:
        """Whether ``message`` is older than what this RSU last told the car (see
        ``rsu_newest_us``); else it becomes the newest. One step's command and path
        share a time, so equal times are in order."""
        time_us = message.header.time_us
        newest = self.rsu_newest_us.get(rsu)
        if newest is not None and time_us < newest:
            return True
        if newest is not None or self._reach(rsu) is not None:  # known RSUs only: bounded
            self.rsu_newest_us[rsu] = time_us
        return False

    def _refusal(self, sender: str, command: Command | None) -> str | None:
        """Why the car must not obey this RSU's command (``command``) or coordinated path
        (None): ``services.vehicle.coordination.owner_refusal``."""
        return owner_refusal(
            sender,
            self.coordination.rsu,
            self._reach(sender),
            self.planner.crossings,
            self.where,
            terminate=command is Command.TERMINATE,
        )

    def _apply(self, now: float, event: VehicleEvent, rsu: str | None) -> None:
        c = self.coordination
        new = next_mode(c.mode, event)
        if new is not c.mode:
            log.info("%s: %s -> %s (%s)", self.spec.vehicle_id, c.mode.name, new.name, event.value)
            self._count(f"mode_{new.name.lower()}")
            if c.mode is Mode.AUTO:
                c.since = now
                c.last_path_at = now  # the timeout counts from the initiation
                c.target_s = c.target_v = None
                c.hold_s, c.hold_until = np.inf, -np.inf
                # the new owner (owner_refusal let only the next intersection's RSU here)
                c.rsu = rsu
                reach = None if rsu is None else self._reach(rsu)
                s = self.where.s if self.where is not None else 0.0
                c.exit_s = (
                    np.inf
                    if reach is None
                    else owner_zone_exit(self.planner.crossings, reach.intersection, s)
                )
            c.mode = new
            if new is Mode.AUTO:
                c.rsu = None
                c.exit_s = np.inf
                c.target_s = c.target_v = None
                c.hold_s, c.hold_until = np.inf, -np.inf

    def _follow(self, now: float, path: CoordinatedPath) -> None:
        c = self.coordination
        pts = path.points
        if pts.shape[0] == 0:
            return
        s, _lat = self.planner.route.project_many(np.ascontiguousarray(pts[:, 0:2]))
        order = np.argsort(s, kind="stable")
        c.target_s = np.asarray(s[order], dtype=np.float64)
        c.target_v = np.asarray(path.speeds[order], dtype=np.float64)
        c.hold_s, c.hold_until = interior_hold(s, pts)
        c.last_path_at = now
        self._count("cp_followed")

    # ------------------------------------------------------------------ planning step
    def tick(self, now: float, ego: TruthState, sensed: list[TruthState]) -> TickResult:
        """One planning step (10 Hz)."""
        p = self.scenario.params
        c = self.coordination
        self.where = Where(ego.s, ego.x, ego.y)
        if c.mode is not Mode.AUTO and c.rsu is not None:
            reach = self._reach(c.rsu)
            lapsed = "owner_unknown" if reach is None else owner_lapsed(reach, c.exit_s, self.where)
            if lapsed is not None:
                log.info("%s: handed over by %s (%s)", self.spec.vehicle_id, c.rsu, lapsed)
                self._count(lapsed)
                self._apply(now, VehicleEvent.HANDOVER, None)
        if c.mode is not Mode.AUTO and now - c.last_path_at > self.cp_timeout_s:
            log.info(
                "%s: no coordinated path for %.2f s, back to AUTO",
                self.spec.vehicle_id,
                now - c.last_path_at,
            )
            self._count("coordinated_timeout")
            self._apply(now, VehicleEvent.TIMEOUT, None)
        fps = {vid: fp for vid, (fp, rx) in self.future_paths.items() if now - rx <= self.fp_hold_s}
        for vid in [v for v in self.future_paths if v not in fps]:
            del self.future_paths[vid]
        autonomous = self.planner.plan(now, ego, sensed, fps)
        if c.mode is Mode.AUTO:
            plan = autonomous
        else:
            # the autonomous path for the RSU: this car's own plan to its goal, without the
            # blind-corner caution and the yield stops that the RSU's coordination replaces
            # (its positions must run through the intersection for a coordinated path to be
            # built on them), following the car ahead by that car's future path where it is
            # known (issue 12: braked for as if it might stop hard now, a follower's turn
            # reached the RSU only when it could no longer stay out of the box)
            autonomous = self.planner.plan(
                now, ego, sensed, {}, Coordination(lift_caution=True, skip_yield=True, follow=fps)
            )
            target_v = c.target_v
            if target_v is not None and c.target_s is not None and now < c.hold_until:
                # a slot's wait: nothing past its stop until the path leaves it
                target_v = np.where(c.target_s > c.hold_s + 1e-6, 0.0, target_v)
            coordination = Coordination(
                lift_caution=c.mode is Mode.C_FAST,
                target_s=c.target_s,
                target_v=target_v,
                skip_yield=c.target_v is not None,
            )
            plan = self.planner.plan(now, ego, sensed, fps, coordination)
            if plan.reason in (Reason.CRUISE,) and c.target_v is not None:
                plan = Plan(
                    plan.profile, Reason.COORDINATED, c.mode.name, plan.unyielded, plan.yielding_to
                )
        self.last_plan = plan
        out: list[Outgoing] = []
        if self.v2x:
            points = self._path_points(now, plan)
            why = None if self.fp_rule is None else self.fp_rule.why(now, points, c.mode)
            if self.fp_rule is None or why is not None:
                out.append(
                    Outgoing(Stream.FP, self._path_message(FuturePath, now, ego, plan, points))
                )
            if why is not None:
                self._count(f"fp_{why}")
            elif self.fp_rule is not None:
                self._count("fp_skipped")
            if c.mode is not Mode.AUTO and c.rsu is not None:
                ap_points = self._path_points(now, autonomous)
                if self.ap_rule is None or self.ap_rule.why(now, ap_points, c.mode) is not None:
                    message = self._path_message(AutonomousPath, now, ego, autonomous, ap_points)
                    out.append(Outgoing(Stream.AP, message, c.rsu))
                else:
                    self._count("ap_skipped")
        return TickResult(plan, out, c.mode, now + 1.0 / p.planning_hz)

    def _path_message(
        self,
        cls: type[FuturePath] | type[AutonomousPath],
        now: float,
        ego: TruthState,
        plan: Plan,
        points: FloatArray | None = None,
    ) -> FuturePath | AutonomousPath:
        pts = self._path_points(now, plan) if points is None else points
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        return cls(
            header=Header(sender=self.spec.vehicle_id, seq=self.seq, time_us=round(now * 1e6)),
            x=ego.x,
            y=ego.y,
            speed=ego.speed,
            heading=ego.heading,
            length=self.spec.length,
            width=self.spec.width,
            mode=self.coordination.mode,
            points=pts,
            limits=self._declared_limits(),
        )

    def _path_points(self, now: float, plan: Plan) -> FloatArray:
        """The plan's path points (x, y, t) over the horizon (paper eq. 1)."""
        p = self.scenario.params
        return future_path_points(
            plan.profile, self.planner.route, now, p.t_free_s, p.future_path_points
        )

    def _declared_limits(self) -> VehicleLimits:
        """The limits every path of this car declares, so that an RSU plans it with them
        (``protocol/SPEC.md`` 2.3); unsigned until messages are signed. Rounded down to
        the wire's resolution (1 cm/s, 0.1 m/s²): an RSU never plans the car beyond
        what it can do (the scenario keeps accelerations >= 0.1 m/s²)."""
        lim = self.spec.limits

        def down(value: float, unit: float) -> float:
            return max(unit, math.floor(value / unit + 1e-9) * unit)

        return VehicleLimits(
            down(lim.v_max, 0.01),
            down(lim.accel, 0.1),
            down(lim.decel_comfort, 0.1),
            down(lim.lat_accel, 0.1),
        )

    # ------------------------------------------------------------------ control
    def command(self, body: BodyState) -> float:
        """Acceleration command [m/s²] tracking the last plan (20 Hz).

        The final stop (:meth:`_final_stop`): tracking the speed a look-ahead ahead
        creeps over the last metre of a stop (a lone car's stop at its goal from 13.9 m/s
        took 8.6 s against 6.9 s at the comfortable deceleration), so within 1.5 m plus
        the look-ahead of the profile's rest point the car brakes at the constant
        deceleration that ends there. A lone car's delay in rsu mode went from 1.97 to
        0.92 s. Tried first on 3 Dec and set aside until two faults it exposed were fixed:
        an fp-only mutual yield (``AutonomousPlanner._arrival``) and two committed cars
        both told to stop by the RSU (``RsuCore._stops_short``, and the car keeping the
        RSU's stop, ``AutonomousPlanner._stop_at``)."""
        plan = self.last_plan
        if plan is None:
            return -self.spec.limits.decel_comfort
        prof = plan.profile
        look = body.s + max(body.v, 0.5) * self.spec.params.control_lookahead_s
        v_ref = prof.speed_at(look)
        if prof.speed_at(body.s) <= 1e-3 and v_ref <= 1e-3:
            return -self.spec.limits.decel_emergency if body.v > 0.0 else 0.0
        # feedforward: the profile's own acceleration at the look-ahead point, a = d(v²)/ds / 2
        step = 0.5
        v_next = prof.speed_at(look + step)
        a_ff = (v_next * v_next - v_ref * v_ref) / (2.0 * step)
        cmd = a_ff + (v_ref - body.v) / self.spec.params.control_time_constant_s
        if self._rest_of[0] is not prof:
            self._rest_of = (prof, self._rest_s(prof))
        stop = self._rest_of[1]
        if stop is not None:
            final = self._final_stop(body, stop)
            if final is not None:
                cmd = final
        return min(cmd, self._top_speed_room(body))

    def _rest_s(self, prof: SpeedProfile) -> float | None:
        """Where the profile comes to rest after moving [m]: between its last moving grid
        point and the first standing one, where a comfortable stop from the former ends;
        None if it never moves or never stops."""
        v_all = prof.v
        moving = np.flatnonzero(v_all > 1e-9)
        if moving.size == 0:
            return None
        standing = np.flatnonzero(v_all[moving[0] :] <= 1e-9)
        if standing.size == 0:
            return None
        k = int(moving[0] + standing[0])
        v = float(v_all[k - 1])
        room = v * v / (2.0 * self.spec.limits.decel_comfort)
        return float(min(prof.s[k - 1] + room, prof.s[k]))

    def _final_stop(self, body: BodyState, stop: float) -> float | None:
        """On the profile's last braking ramp to rest at ``stop`` [m]: the constant
        deceleration [m/s², < 0] that ends at rest :data:`STOP_MARGIN_M` short of it, from
        where the actuator lag takes the car; None elsewhere (the tracking command).

        Tracking the speed a look-ahead ahead brakes a little early all along a ramp
        (that is its lag compensation) but turns into a creep in its last metre, where
        the ramp's √ shape drops to 0 within the look-ahead: a stop from 13.9 m/s took
        8.6 s instead of 6.9 s. Only within :data:`FINAL_STOP_M` plus the look-ahead of
        the rest point, and where the stop needs at least half the comfortable
        deceleration (a car far short of its stop point still drives up to it)."""
        lim = self.spec.limits
        dc = lim.decel_comfort
        reach = FINAL_STOP_M + max(body.v, 0.5) * self.spec.params.control_lookahead_s
        if not body.s < stop <= body.s + reach:
            return None
        lag = lim.actuator_lag_s
        v = max(body.v + body.a * lag, 0.0)
        room = stop - STOP_MARGIN_M - body.s - lag * (body.v + 0.5 * body.a * lag)
        if room <= STOP_ROOM_M:  # at its end: stop; standing, tracking takes it the rest
            return -lim.decel_emergency if body.v > 0.0 else None
        need = v * v / (2.0 * room)
        if need < 0.5 * dc:
            return None
        return -min(need, lim.decel_emergency)

    def _top_speed_room(self, body: BodyState) -> float:
        """Largest command [m/s²] that keeps the car at or below V_max despite the lag.

        Through the first-order actuator lag (time constant tau) the speed the car
        settles at if the command drops to zero is w = v + a·tau, and w' equals the
        command exactly; the speed never passes w while a > 0. Keeping w ≤ V_max over
        the next physics step (the command is held for dt) keeps v ≤ V_max: without
        this the car overshot to 14.03 m/s against 13.89 (issue 17).
        """
        lim = self.spec.limits
        settle = body.v + body.a * lim.actuator_lag_s
        return (lim.v_max - settle) / self.scenario.params.physics_dt_s


def vehicle_agent(scenario: Scenario, vehicle_id: str, v2x: bool) -> VehicleAgent:
    """The pure autonomy stack of one car (shared with the vehicle daemon)."""
    spec = scenario.vehicle(vehicle_id)
    return VehicleAgent(
        spec=AgentSpec(
            vehicle_id=spec.id,
            route_id=spec.route,
            goal_s=scenario.goal_m(vehicle_id),
            length=spec.length_m,
            width=spec.width_m,
            limits=scenario.limits(vehicle_id),
            params=scenario.vehicle_params(vehicle_id),
        ),
        scenario=scenario,
        v2x=v2x,
    )
