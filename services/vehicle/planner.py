"""The autonomous planner: the Autoware stand-in (DESIGN.md, "The vehicle").

Pure: ``plan(now, ego, sensed, future_paths, coordination)`` returns a speed
profile along the car's route and the reason its speed is capped. Rules, in
the order DESIGN.md gives them:

1. cruise at V_max, stop at the goal, and in curves keep the lateral
   acceleration within ``lat_accel_mps2``: speed ≤ sqrt(a_lat · r) along the
   route (``services.model.kinematics.curve_speed_cap``), braking for the
   curve at the comfortable deceleration;
2. blind-corner caution: approaching an intersection whose crossing lanes are
   hidden, keep a speed from which the car can stop at the stop line braking
   comfortably, until the visible stretch of every crossing lane is long
   enough that an unseen car at V_max could not reach the conflict zone
   before this car has cleared it (lifted in ``C_FAST``);
3. yield: for every known other car whose path conflicts with this car's in
   space (its future path comes within ``d_margin_m`` of this route inside the
   zone, or, known only from the sensors, its lane is one of the route's
   ``crossing_lanes``: opposing straight traffic and turns that do not cross
   never count; nor does traffic from this car's own approach, which is
   followed, not crossed) and in time (conflict-zone occupancy intervals
   within the 1.0 s headway), the car without right of way plans a stop at
   the stop line until the interval has passed. **Right of way** at a blind,
   unsignalled intersection: (a) a car that can no longer stop before the zone
   (emergency braking) goes first; (b) then the earlier arrival at the stop
   line (``line_arrival``: on at the current speed, then braking comfortably to
   a stop at the line, from the distance along the lane and the speed, which
   both cars see alike; as a run time, so a future path a period old gives the
   sender's own verdict), when the two differ by more than ``TIE_S`` = 0.3 s;
   (c) then right before left (the car coming from the other's right goes
   first); (d) the lower id only as the last tie-break (opposing or
   same-direction ties). The verdict is taken when the two first conflict and
   kept, both ways, until the other has cleared the zone or no longer
   conflicts (commitment): estimates shift as both slow for the corner, and a
   swapped order makes a car stop twice or both go. Only a committed car
   overrides it, and a kept yield to a car that has stopped short of the zone
   is re-judged, so two cars never wait for each other. Against a moving
   oncoming car known only from the sensors, a car turning across its lane
   gives way whatever the order: the oncoming car's route does not cross the
   turner's lane, so it never counts the turner (``_decide``);
4. emergency braking for any sensed car on the path, in every mode;
5. a priority road (``priority_lanes`` of an intersection, e.g. from a SUMO
   priority junction): between two cars that conflict there and neither of
   which is committed, the one on the priority road goes first, before rule 3's
   arrival order (drivers that crosspath does not coordinate, such as SUMO's
   unconnected cars, keep that order, and a car cannot tell them from a
   crosspath car whose radio it does not hear). In a coordinated mode, where
   rule 3 is lifted, a car coming from a minor road still gives way to each car
   on the priority road known only from its sensors, unless it is committed: no
   RSU can order that one. (Found in the SUMO co-simulation with a share of the
   cars connected: a connected car on the minor road took the way by rule 3, or
   by its RSU, from an unconnected car on the priority road whose SUMO driver
   did not give it.)

Our interpretation where DESIGN.md is silent (also in the README):

- Occupancy intervals [t_in, t_out] cover the car's footprint in the zone
  (centre within the zone grown by half a car length).
- Against a car known from its future path, this car's own interval comes
  from its plan without yield stops, and the other's from its future path:
  both cars compare the same two plans. A future path that stops short of the
  zone (the other car is waiting or creeping) counts as its *earliest
  possible* arrival (driving off at the limits from its current speed), and
  then so does this car's own.
- Against a car known only from the sensors, both sides use the earliest
  possible occupancy along their lanes for the time conflict, rather than
  DESIGN.md's constant-velocity prediction: constant velocity calls a slow,
  accelerating car far off, and the two cars, each predicting the other at
  constant velocity and itself by its plan, then both believe they are first.
- Right of way, though, goes by ``line_arrival``, not by the earliest possible
  arrival: as both cars brake for the blind corner the earliest arrivals
  compress a 0.3-1 s start gap into a tie, and right before left then let the
  later car go first (issue 17). ``line_arrival`` keeps two cars on the same
  profile their start gap apart all the way in.
- A yield can only be planned while the car can still stop before the stop
  line with emergency deceleration; past that point it is committed.
- The autonomous path sent to the RSU follows a car ahead in this lane by that
  car's future path where it is known (``Coordination.follow``, ``_follow_cap``):
  at each place no faster than the leader went one follow distance further on, and
  stopped that far (and a grid step) behind where the leader's path rests in this
  lane. Braking for the leader as if it might stop hard now, as the plan the car
  drives does (rule 4), made a follower's path rest a stopping distance behind its
  leader, so the RSU saw a turn behind a straight car only 1-2 m from the box, when
  neither of two opposing left turners could stay out any more (issue 12).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from protocol.messages import FuturePath
from services.model.geometry import IntArray, Polyline, footprint, visible_mask, wrap_angle
from services.model.kinematics import Limits, TruthState, curve_speed_cap
from services.model.scenario import SAME_APPROACH_RAD, Crossing, Scenario, VehicleParams
from services.vehicle.profile import (
    FloatArray,
    SpeedProfile,
    backward_pass,
    earliest_arrival,
    forward_pass,
    grid,
    pass_times,
    stop_cap,
)

DS = 0.5
"""Arc-length step of the speed profile [m]."""

LOOKAHEAD_M = 220.0
"""How far ahead the planner looks [m] (≥ 10 s at V_max, plus stopping room)."""

TIE_S = 0.3
"""Stop-line arrival times closer than this are a tie, decided by right before left,
then by id [s]."""

ARRIVED_M = 0.0
"""A car whose front is within this of its stop line has arrived (arrival time 0) [m].
Zero: a car waiting just before its line must not tie with one that is already
through it (with 1 m, the two arrivals compressed into a tie as both slowed and the
order flipped half-way)."""

ARRIVAL_FLOOR_MPS = 1.0
"""A slower or stopped car's stop-line arrival is estimated as if it crept on at this
speed (``line_arrival``) [m/s]."""

APPROACH_PROBE_M = 2.0
"""The lane a route comes in on is the one it is on this far before the zone [m]."""

COMMIT_MARGIN_M = 0.3
"""A car that cannot stop this far before the conflict zone braking at the emergency
limit is committed: it goes first [m]."""

FOLLOW_REST_MPS = 0.25
"""A future path slower than this over its last stretch rests there (``_follow_cap``) [m/s]."""

SIDE_MARGIN_M = 0.3
"""A sensed car this close beside the car's swept body counts as on its path: brake for
it [m]; a standing one at least ``PASS_MARGIN_M`` off is passed at the creep speed."""

PASS_MARGIN_M = 0.05
"""A *standing* car within ``SIDE_MARGIN_M`` of the swept body but at least this far
from it is passed at the creep speed, not stopped for [m]. Without it two cars lock for
good: in a jammed 4-way (demand 600 veh/h, rsu/paper, seed 0) one car stood with its
nose 0.1 m beside a crossing car's lane, and the crossing car, standing in its way,
would not pass it by the 0.3 m margin (issue 12; the RSU's half of that lock is
``RsuCore._past_standing``)."""

# Stop margin, creep speed, caution sampling, emergency gap: the scenario's
# [vehicle_params] (services.model.scenario.VehicleParams), in ``AutonomousPlanner.params``.


class Reason(StrEnum):
    """Why the planned speed is what it is (recorded every planning step)."""

    CRUISE = "cruise"
    GOAL = "goal"
    CURVE = "curve"
    CAUTION = "caution"
    YIELD = "yield"
    EMERGENCY = "emergency"
    COORDINATED = "coordinated"
    WAITING = "waiting"  # not started yet


_PRIORITY = (
    Reason.CRUISE,
    Reason.GOAL,
    Reason.CURVE,
    Reason.COORDINATED,
    Reason.CAUTION,
    Reason.YIELD,
    Reason.EMERGENCY,
)
"""When several constraints bind equally, the reason reported is the most specific."""


@dataclass(frozen=True, slots=True)
class Interval:
    """Conflict-zone occupancy of one car [s, run time]."""

    t_in: float
    t_out: float

    def overlaps(self, other: Interval, headway: float) -> bool:
        return self.t_in < other.t_out + headway and other.t_in < self.t_out + headway


@dataclass(frozen=True, slots=True)
class Plan:
    """One planning step's result."""

    profile: SpeedProfile
    reason: Reason
    detail: str = ""  # e.g. the id yielded to
    unyielded: SpeedProfile | None = None  # plan without yield stops (for the autonomous path)
    yielding_to: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Coordination:
    """What the coordinated mode imposes on the planner this step."""

    lift_caution: bool = False
    target_s: FloatArray | None = None  # coordinated target speeds by route arc length
    target_v: FloatArray | None = None
    skip_yield: bool = False
    follow: Mapping[str, FuturePath] | None = None
    """Future paths by vehicle id: a car ahead in this lane whose path is here is
    followed by that path instead of braked for as if it might stop hard now
    (``_follow_cap``). For the autonomous path sent to the RSU, which then sees where a
    follower goes behind its leader through the intersection, not only where it could
    stop (issue 12, the opposing-left-turner lock); the plan the car drives keeps the
    sensed caps."""


@dataclass(slots=True)
class _Constraint:
    reason: Reason
    cap: FloatArray
    detail: str = ""


@dataclass(slots=True)
class AutonomousPlanner:
    """Speed planning along one route. Keeps only the previous step's yield decisions."""

    vehicle_id: str
    scenario: Scenario
    route_id: str
    goal_s: float
    length: float
    width: float
    limits: Limits
    headway_s: float
    sensor_range_m: float
    params: VehicleParams = field(default_factory=VehicleParams)
    route: Polyline = field(init=False)
    crossings: list[Crossing] = field(init=False)
    _zones: dict[str, _ZoneBox] = field(init=False)
    _crossing_lanes: dict[str, frozenset[str]] = field(init=False)
    _stop_offset: dict[str, float] = field(init=False)
    _priority: dict[str, frozenset[str]] = field(init=False)
    _approach: dict[str, str | None] = field(init=False)
    _order: dict[tuple[str, str], bool] = field(init=False, default_factory=dict)
    _next_order: dict[tuple[str, str], bool] = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.route = self.scenario.route(self.route_id)
        self.crossings = self.scenario.crossings(self.route_id, self.length)
        self._zones = {
            i.id: _ZoneBox.of(self.scenario.zone_polygon(i.id)) for i in self.scenario.intersections
        }
        self._stop_offset = {i.id: i.stop_line_offset_m for i in self.scenario.intersections}
        # the lanes whose traffic crosses or merges with this route, per intersection: only
        # these are watched round a blind corner or yielded to when known from the sensors
        self._crossing_lanes = {
            c.intersection: frozenset(
                a.lane for a in self.scenario.crossing_lanes(self.route_id, c.intersection)
            )
            for c in self.crossings
        }
        # the priority roads at the intersections this route crosses (rule 5), and the
        # lane it comes in on to each
        self._priority = {}
        self._approach = {}
        for c in self.crossings:
            major = frozenset(self.scenario.intersection(c.intersection).priority_lanes)
            if major:
                self._priority[c.intersection] = major
            self._approach[c.intersection] = self._approach_lane(c)

    # ------------------------------------------------------------------ planning
    def plan(
        self,
        now: float,
        ego: TruthState,
        sensed: Sequence[TruthState],
        future_paths: Mapping[str, FuturePath],
        coordination: Coordination | None = None,
    ) -> Plan:
        """Plan the speed profile from the ego state (``ego.s`` on this route)."""
        coordination = coordination or Coordination()
        lim = self.limits
        s0 = ego.s
        v0 = ego.speed
        s = grid(s0, min(self.goal_s, s0 + LOOKAHEAD_M) + DS, DS)
        base = np.full_like(s, lim.v_max)
        constraints: list[_Constraint] = [_Constraint(Reason.CRUISE, base)]
        constraints.append(_Constraint(Reason.GOAL, stop_cap(s, self.goal_s, lim.decel_comfort)))
        # held from a little before the curve: the speed follows the plan through the
        # actuator lag, so the cap starts the distance covered in one lag earlier
        curve = curve_speed_cap(self.route, s, lim.lat_accel, lim.v_max, pad_m=DS)
        if float(curve.min()) < lim.v_max:
            lead = float(curve.min()) * (lim.actuator_lag_s + self.params.control_lookahead_s)
            curve = curve_speed_cap(self.route, s, lim.lat_accel, lim.v_max, pad_m=DS + lead)
        if float(curve.min()) < lim.v_max:
            # braking for a curve is planned at the comfortable deceleration
            constraints.append(
                _Constraint(Reason.CURVE, backward_pass(curve, DS, lim.decel_comfort))
            )
        if coordination.target_v is not None and coordination.target_s is not None:
            # the coordinated speeds are reached early (as caps) but never by braking harder
            # than comfortably from the current speed (the paper's smooth C_SLOW deceleration)
            target = np.interp(s, coordination.target_s, coordination.target_v)
            early = backward_pass(target, DS, lim.decel_comfort)
            smooth = np.sqrt(np.maximum(v0 * v0 - 2.0 * lim.decel_comfort * (s - s0), 0.0))
            constraints.append(_Constraint(Reason.COORDINATED, np.maximum(early, smooth)))
            if coordination.target_v[-1] <= 0.0:
                # ... except where the coordinated path ends at rest: the RSU reserved that
                # stop (short of the zone, behind the car ahead) and may brake the car
                # harder than comfortably to keep it there
                end = float(coordination.target_s[-1])
                constraints.append(_Constraint(Reason.COORDINATED, self._stop_at(s, s0, v0, end)))
        for crossing in self._crossings_ahead(s0):
            if not coordination.lift_caution and not self._clear_view(now, ego, crossing):
                cap = self._stop_line_cap(s, s0, v0, crossing)
                if cap is not None:
                    # creep past the line towards the zone, to see round the corner
                    edge = crossing.s_in - self.length / 2.0 - self.params.creep_margin_m
                    creep = np.minimum(self.params.creep_mps, stop_cap(s, edge, lim.decel_comfort))
                    constraints.append(
                        _Constraint(Reason.CAUTION, np.maximum(cap, creep), crossing.intersection)
                    )
        emergency = self._emergency_caps(s, ego, sensed, coordination.follow)
        constraints.extend(emergency)

        unyielded = self._combine(now, s, v0, constraints)
        yield_to: list[str] = []
        self._next_order = {}
        for crossing in self._crossings_ahead(s0):
            if coordination.skip_yield:
                # coordinated: the RSU orders the cars it knows; not the priority road's
                others = self._priority_targets(now, ego, crossing, sensed, future_paths)
            else:
                others = self._yield_targets(
                    now, ego, crossing, unyielded.profile, sensed, future_paths
                )
            if others:
                cap = self._stop_line_cap(s, s0, v0, crossing, soonest=True)
                if cap is not None:
                    constraints.append(_Constraint(Reason.YIELD, cap, ",".join(others)))
                    yield_to.extend(others)
        if not coordination.skip_yield:
            self._order = self._next_order
        if not yield_to:
            return Plan(
                unyielded.profile, unyielded.reason, unyielded.detail, unyielded.profile, ()
            )
        final = self._combine(now, s, v0, constraints)
        return Plan(final.profile, final.reason, final.detail, unyielded.profile, tuple(yield_to))

    def _combine(
        self, now: float, s: FloatArray, v0: float, constraints: list[_Constraint]
    ) -> Plan:
        lim = self.limits
        shaped = [backward_pass(c.cap, DS, lim.decel_emergency) for c in constraints]
        cap = np.minimum.reduce(shaped)
        v = forward_pass(cap, v0, DS, lim.accel)
        # the binding constraint: the lowest cap around where the car will be in ~1 s
        look = min(int((max(v0, 1.0) * 1.0) / DS), s.shape[0] - 1)
        values = [float(c[look]) for c in shaped]
        low = min(values)
        k = max(
            (i for i, val in enumerate(values) if val <= low + 1e-6),
            key=lambda i: _PRIORITY.index(constraints[i].reason),
        )
        reason = constraints[k].reason
        if reason is Reason.CRUISE or values[k] >= lim.v_max - 1e-6:
            reason, detail = Reason.CRUISE, ""
        else:
            detail = constraints[k].detail
        profile = SpeedProfile(s=s, v=v, t=pass_times(s, v, now))
        return Plan(profile, reason, detail)

    # ------------------------------------------------------------------ rules
    def _crossings_ahead(self, s0: float) -> Iterable[Crossing]:
        """Crossings whose zone the car's rear has not yet left."""
        for c in self.crossings:
            if s0 - self.length / 2.0 < c.s_out:
                yield c

    def _stop_line_cap(
        self, s: FloatArray, s0: float, v0: float, crossing: Crossing, soonest: bool = False
    ) -> FloatArray | None:
        """Cap for stopping at the stop line, or None if the car is committed.

        Braking comfortably when it can, harder when it must; if even emergency
        braking cannot stop it at the line, it stops short of the conflict zone
        instead; if it cannot do that either, it is committed and goes on. With
        ``soonest`` (a yield), a car that can no longer stop at the line (it crept on to
        see round the corner, or is crawling right at it) stops as soon as it comfortably
        can, short of the zone, rather than rolling on to the zone's edge: it would only
        start again from there, slower.
        """
        lim = self.limits
        line = crossing.s_stop - self.params.stop_margin_m
        edge = crossing.s_in - self.length / 2.0 - 0.3
        here = s0 + v0 * v0 / (2.0 * lim.decel_comfort)
        stops = (line, here, edge) if soonest and here <= edge else (line, edge)
        for s_stop in stops:
            room = s_stop - s0
            if room < -0.3:
                continue  # already past this point
            if v0 * v0 / (2.0 * max(room, 1e-3)) > lim.decel_emergency:
                continue
            return self._stop_at(s, s0, v0, s_stop)
        return None

    def _stop_at(self, s: FloatArray, s0: float, v0: float, s_stop: float) -> FloatArray:
        """Cap for stopping at ``s_stop`` [m]: comfortably when that reaches it, harder
        when it must (10 % to spare, as at a stop line), at most the emergency
        deceleration (a stop that even that misses is as close as the car can make it)."""
        lim = self.limits
        room = s_stop - s0
        needed = v0 * v0 / (2.0 * max(room, 1e-3))
        decel = (
            lim.decel_comfort
            if needed <= lim.decel_comfort
            else min(needed * 1.1, lim.decel_emergency)
        )
        return stop_cap(s, max(s_stop, s0), decel)

    def _clear_view(self, now: float, ego: TruthState, crossing: Crossing) -> bool:
        """Blind-corner rule: can every crossing lane be seen far enough upstream?"""
        if ego.s > crossing.s_stop + 0.5:
            return True  # past the stop line: caution no longer helps
        lim = self.limits
        if crossing.s_in - ego.s > self.sensor_range_m:
            return False  # the crossing road is beyond the sensors' reach
        # time for this car to clear the zone (rear out), driving off at the limit from now
        to_clear = crossing.s_out + self.length / 2.0 - ego.s
        t_clear = earliest_arrival(to_clear, ego.speed, lim.accel, lim.v_max)
        needed = lim.v_max * t_clear
        buildings = self.scenario.building_polygons
        for lane in self.scenario.crossing_lanes(self.route_id, crossing.intersection):
            # points along the lane upstream of its zone entry, out to the needed distance
            step = self.params.caution_sample_m
            d = np.arange(0.0, needed + step, step)
            s_lane = lane.s_in - d
            inside = s_lane >= 0.0
            if not np.any(inside):
                continue
            pts = lane.polyline.points_at(s_lane[inside])
            dist = np.hypot(pts[:, 0] - ego.x, pts[:, 1] - ego.y)
            ok = (dist <= self.sensor_range_m) & visible_mask((ego.x, ego.y), pts, buildings)
            if not bool(np.all(ok)):
                return False
        return True

    def _emergency_caps(
        self,
        s: FloatArray,
        ego: TruthState,
        sensed: Sequence[TruthState],
        follow: Mapping[str, FuturePath] | None = None,
    ) -> list[_Constraint]:
        """Brake (up to the emergency limit) for any sensed car whose footprint is on the
        path; a car ahead going this way whose future path is in ``follow`` is followed
        by that path instead (``_follow_cap``)."""
        out: list[_Constraint] = []
        lim = self.limits
        half_w = self.width / 2.0 + SIDE_MARGIN_M
        pass_w = self.width / 2.0 + PASS_MARGIN_M
        if not sensed:
            return out
        # every sensed car's corners projected at once (issue 14: one call per car was a
        # tenth of a planning step in traffic); rows are independent, so the same numbers
        corners = np.concatenate(
            [footprint(o.x, o.y, o.heading, o.length, o.width) for o in sensed]
        )
        cs_all, lat_all = self.route.project_many(corners)
        for k, other in enumerate(sensed):
            cs, lat = cs_all[4 * k : 4 * k + 4], lat_all[4 * k : 4 * k + 4]
            on_path = (np.abs(lat) <= half_w) & (cs > ego.s)
            in_way = bool(np.any(on_path))
            if not in_way:
                # also a car crossing the path: corners on both sides of the route line
                ahead = (cs > ego.s) & (cs < ego.s + 60.0)
                if not (bool(np.any(ahead & (lat > 0))) and bool(np.any(ahead & (lat < 0)))):
                    continue
                s_obs = float(np.min(cs[ahead]))
            else:
                s_obs = float(np.min(cs[on_path]))
            # a car moving the same way keeps going: allow its stopping distance
            rel = float(np.cos(other.heading - self.route.heading_at(s_obs)))
            fp = None if follow is None or rel <= 0.7 else follow.get(other.id)
            if fp is not None and in_way:
                by_path = self._follow_cap(s, ego, fp, other.length)
                if by_path is not None:
                    out.append(_Constraint(Reason.EMERGENCY, by_path, other.id))
                    continue
            extra = other.speed**2 / (2.0 * lim.decel_emergency) if rel > 0.7 else 0.0
            s_stop = s_obs + extra - self.length / 2.0 - self.params.emergency_gap_m
            if s_stop - ego.s > 60.0:
                continue
            cap = stop_cap(s, max(s_stop, ego.s), lim.decel_emergency)
            # a standing car beside the swept body, not in it: pass it at the creep speed
            standing = other.speed <= self.params.creep_mps / 2.0
            if in_way and standing and not bool(np.any(on_path & (np.abs(lat) <= pass_w))):
                cap = np.maximum(cap, min(self.params.creep_mps, lim.v_max))
            out.append(_Constraint(Reason.EMERGENCY, cap, other.id))
        return out

    def _follow_cap(
        self, s: FloatArray, ego: TruthState, fp: FuturePath, other_length: float
    ) -> FloatArray | None:
        """Speed cap [m/s] on ``s`` for following the car ahead by its future path
        ``fp``: at each place this car goes no faster than that car went one follow
        distance further on (half the two lengths plus ``emergency_gap_m``), and stops that
        far behind where its path rests while still in this lane. A queue discharges so,
        each car pulling away from where the one ahead did. Only the stretch of ``fp``
        that runs along this route (within half this car's width plus ``SIDE_MARGIN_M``,
        from its first point on) counts: where it turns off, this car's own way is free.
        None when fewer than two points of it lie ahead in this lane."""
        pts = fp.points
        if pts.shape[0] < 2:
            return None
        cs, lat = self.route.project_many(pts[:, :2])
        on = (np.abs(lat) <= self.width / 2.0 + SIDE_MARGIN_M) & (cs > ego.s)
        off = np.flatnonzero(~on)
        k = int(off[0]) if off.size else int(pts.shape[0])
        if k < 2:
            return None
        s_l = cs[:k]
        ds_l, dt_l = np.diff(s_l), np.diff(pts[:k, 2])
        if bool(np.any(ds_l < -0.05)):
            return None  # not a path along this route
        d = (self.length + other_length) / 2.0 + self.params.emergency_gap_m
        slow = ds_l < FOLLOW_REST_MPS * np.maximum(dt_l, 0.0)
        rest: float | None = None
        if k == pts.shape[0] and bool(slow[-1]):
            # it rests at the start of its path's trailing slow run
            moving = np.flatnonzero(~slow)
            first = int(moving[-1]) + 1 if moving.size else 0
            rest = float(s_l[first])
            s_l, ds_l, dt_l = s_l[: first + 1], ds_l[:first], dt_l[:first]
        cap = np.full_like(s, np.inf)
        step = ds_l > 1e-6
        if bool(np.any(step)):
            v_l = np.minimum(ds_l[step] / np.maximum(dt_l[step], 1e-6), self.limits.v_max)
            mid = (0.5 * (s_l[1:] + s_l[:-1]))[step]
            # from one grid step short of where it is now: between two grid points the
            # profile's speed is interpolated, and it must not outrun the leader's start
            q = s + d
            inside = (q >= s_l[0] - DS) & (q <= s_l[-1])
            if bool(np.any(inside)):
                cap[inside] = np.interp(q[inside], mid, v_l)
        if rest is not None:
            # a grid step short: the profile reaches a stop up to a step past its cap's
            cap = np.minimum(cap, stop_cap(s, rest - d - DS, self.limits.decel_emergency))
        return np.minimum(cap, self.limits.v_max)

    # ------------------------------------------------------------------ yield
    def _own_interval(
        self, now: float, ego: TruthState, crossing: Crossing, profile: SpeedProfile
    ) -> Interval | None:
        """This car's occupancy by its plan without yield stops; None if it stops short."""
        half = self.length / 2.0
        if crossing.s_in - half > profile.s[-1]:
            return None
        finite = np.isfinite(profile.t)
        s_fin = profile.s[finite]
        if s_fin[-1] < crossing.s_in - half:
            return None
        t_in = float(np.interp(crossing.s_in - half, s_fin, profile.t[finite]))
        if s_fin[-1] < crossing.s_out + half:
            return Interval(t_in, np.inf)
        return Interval(t_in, float(np.interp(crossing.s_out + half, s_fin, profile.t[finite])))

    def _earliest_interval(
        self, now: float, s: float, v: float, crossing: Crossing, length: float
    ) -> Interval:
        """Occupancy if the car drove off at the limits from (s, v): the earliest possible."""
        lim = self.limits
        half = length / 2.0
        t_in = now + earliest_arrival(crossing.s_in - half - s, v, lim.accel, lim.v_max)
        t_out = now + earliest_arrival(crossing.s_out + half - s, v, lim.accel, lim.v_max)
        return Interval(t_in, t_out)

    def _yield_targets(
        self,
        now: float,
        ego: TruthState,
        crossing: Crossing,
        unyielded: SpeedProfile,
        sensed: Sequence[TruthState],
        future_paths: Mapping[str, FuturePath],
    ) -> list[str]:
        """The cars this one must let through ``crossing`` first (see ``_goes_first``)."""
        if ego.s - self.length / 2.0 > crossing.s_in:
            return []  # already in the zone: go on
        planned = self._own_interval(now, ego, crossing, unyielded)
        earliest = self._earliest_interval(now, ego.s, ego.speed, crossing, self.length)
        zone = self._zones[crossing.intersection]
        mine = self._own_arrival(now, ego, crossing)
        still = ego.speed <= self.params.creep_mps / 2.0
        out: list[str] = []
        seen: set[str] = set()
        for fp_id, fp in future_paths.items():
            if fp_id == self.vehicle_id:
                continue
            seen.add(fp_id)
            where = _InZone.of(fp, zone)
            theirs = self._fp_interval(now, fp, zone, crossing, where)
            if theirs is None:
                continue
            arrival = self._fp_arrival(now, fp, zone, crossing, where)
            if arrival is None:
                continue  # its path does not cross ours here
            if self._order.get((crossing.intersection, fp_id), False) and theirs.planned:
                # its right of way is settled: go only once its plan leaves room even for
                # this car's earliest arrival (its own plan, slowed by caution, and the
                # yield it causes would alternate with the release, step by step)
                own_iv, other_iv = earliest, theirs.interval
            elif planned is not None and theirs.planned:
                own_iv, other_iv = planned, theirs.interval
            else:
                # one of the two stops short of the zone: both sides judge by earliest arrival
                own_iv, other_iv = earliest, self._fp_earliest(now, fp, zone, crossing)
            overlap = own_iv.overlaps(other_iv, self.headway_s)
            moving = fp.speed > self.params.creep_mps / 2.0
            if self._decide(crossing, fp_id, overlap, arrival, mine, moving, still):
                out.append(fp_id)
        for other in sensed:
            if other.id in seen:
                continue
            found = self._sensed_conflict(now, other, crossing)
            if found is None:
                continue
            sensed_iv, arrival = found
            overlap = earliest.overlaps(sensed_iv, self.headway_s)
            moving = other.speed > self.params.creep_mps / 2.0
            if self._decide(crossing, other.id, overlap, arrival, mine, moving, still, True):
                out.append(other.id)
        return out

    def _approach_lane(self, crossing: Crossing) -> str | None:
        """The lane this route comes in on to ``crossing`` (just before its zone)."""
        s = max(crossing.s_in - APPROACH_PROBE_M, 0.0)
        x, y = self.route.point_at(s)
        found = self.scenario.lane_of(x, y, self.route.heading_at(s))
        return None if found is None else found[0]

    def _major(self, crossing: Crossing, lane: str | None) -> bool:
        """``lane`` is a priority road at ``crossing`` (rule 5)."""
        major = self._priority.get(crossing.intersection)
        return major is not None and lane is not None and lane in major

    def _priority_targets(
        self,
        now: float,
        ego: TruthState,
        crossing: Crossing,
        sensed: Sequence[TruthState],
        future_paths: Mapping[str, FuturePath],
    ) -> list[str]:
        """Rule 5 in a coordinated mode: the cars known only from the sensors, on a
        priority road this car comes to from a minor one, whose earliest zone occupancy
        comes within the headway of this car's earliest: they go first, unless this car
        is committed. No RSU can order such a driver, who keeps the road's priority."""
        if crossing.intersection not in self._priority or self._major(
            crossing, self._approach.get(crossing.intersection)
        ):
            return []
        if ego.s - self.length / 2.0 > crossing.s_in:
            return []  # already in the zone: go on
        mine = self._own_arrival(now, ego, crossing)
        if mine.committed:
            return []
        earliest = self._earliest_interval(now, ego.s, ego.speed, crossing, self.length)
        out: list[str] = []
        for other in sensed:
            if other.id in future_paths:
                continue
            found = self._sensed_conflict(now, other, crossing)
            if found is None or not self._major(crossing, found[1].lane):
                continue
            if earliest.overlaps(found[0], self.headway_s):
                out.append(other.id)
        return out

    def _decide(
        self,
        crossing: Crossing,
        other_id: str,
        overlap: bool,
        other: _Arrival,
        mine: _Arrival,
        moving: bool,
        still: bool = False,
        sensed_only: bool = False,
    ) -> bool:
        """Yield to this car? The verdict is taken when the two first conflict and then
        kept (commitment), both ways, while the other stays a conflict here: estimated
        arrivals shift as both slow for the blind corner, and a car that swapped the
        order half-way would stop twice, or go together with the other. Both cars take
        it from the same facts (``_goes_first``), so they agree. Exceptions: a committed
        car goes first (and the verdict follows); while the car that holds the right of
        way stands still short of the zone (``moving`` false for the other car's, ``still``
        true for this car's own speed), the verdict is re-judged, so two cars never wait
        for each other. Both cars re-judge on the same fact (the holder's speed, which
        both see) and then judge the same standing facts, so they agree: a car that kept
        its right of way while it stood (waiting for a third car) and the car that
        re-judged its yield meanwhile went together into the zone (issue 12,
        ``test_standalone_crossing_between_two_opposite_cars``).

        Against an oncoming car known only from the sensors (``sensed_only``: its lane is
        the opposing one, which this route turns across), the other goes first while it
        moves: its own route does not cross this car's lane, so it cannot see
        the conflict and will not give way (the left turn gives way to oncoming traffic;
        found in the SUMO co-simulation with every car in ``standalone``, where the
        turning car took the way by the tie-break and the oncoming car drove on). While
        the oncoming car stands still, the usual order decides, so that two oncoming cars
        turning across each other's lane do not wait for each other for ever, nor a turner
        for a car that waits for a third."""
        key = (crossing.intersection, other_id)
        kept = self._order.get(key)
        if kept is None and not overlap:
            return False  # no conflict yet: no verdict
        other_major, my_major = self._major(crossing, other.lane), self._major(crossing, mine.lane)
        if other.committed != mine.committed:
            first = other.committed
        elif other_major != my_major:
            first = other_major  # rule 5: the priority road first
        elif sensed_only and moving and _oncoming(other, mine):
            first = True
        elif kept is None or (kept and not moving) or (not kept and still):
            first = self._goes_first(other, mine, other_id)
        else:
            first = kept
        self._next_order[key] = first
        return overlap and first

    def _goes_first(self, other: _Arrival, mine: _Arrival, other_id: str) -> bool:
        """Does the other car have right of way over this one? Both cars decide from the
        same facts, so they agree: a committed car first, then the earlier stop-line
        arrival (beyond ``TIE_S``), then right before left, then the lower id."""
        if other.committed != mine.committed:
            return other.committed
        if other.t_line > mine.t_line + TIE_S:
            return False
        if mine.t_line > other.t_line + TIE_S:
            return True
        rel = wrap_angle(other.heading - mine.heading)
        if math.pi / 4.0 < rel < 3.0 * math.pi / 4.0:
            return True  # it comes from this car's right
        if -3.0 * math.pi / 4.0 < rel < -math.pi / 4.0:
            return False  # it comes from the left: this car has the right of way
        return other_id < self.vehicle_id

    def _arrival(
        self,
        stamp: float,
        d_zone: float,
        speed: float,
        offset: float,
        heading: float,
        lane: str | None = None,
        age: float = 0.0,
    ) -> _Arrival:
        """Arrival of a car whose centre was ``d_zone`` [m] before entering the (grown) zone
        at run time ``stamp`` [s] (now for this car and sensed ones, the send time of a
        future path, ``age`` [s] ago): an absolute time, so that a path received a period
        late gives the same verdict as the sender's own fresh state (``line_arrival`` runs
        down at 1 s/s along the blind-corner plan). A car slower than
        ``ARRIVAL_FLOOR_MPS`` is counted as creeping at the floor, whose estimate runs
        down only at ``speed / floor`` s/s: its path's estimate is moved on by the rest
        over ``age``. Without that, two cars standing at their lines judged each other
        with estimates a period apart and each gave way to the other for ever (the
        demand experiment, fp-only, found with a controller that stops more exactly).
        A car at or past its line has arrived: its estimate, 0 from its own now, does not
        run down at all, so its path's is moved on by the whole ``age`` (else a car at
        its line, 0.0625 s old, was first by 0.31 s to the other car and tied at 0.25 s
        for itself, and each gave way to the other; found by the property test)."""
        lim = self.limits
        d_line = d_zone - offset - ARRIVED_M
        t_line = stamp + line_arrival(d_line, speed, self.scenario.params.decel_comfort_mps2)
        if age > 0.0 and d_line <= 0.0:
            t_line += age
        elif age > 0.0 and speed < ARRIVAL_FLOOR_MPS:
            t_line += age * (1.0 - max(speed, 0.0) / ARRIVAL_FLOOR_MPS)
        committed = speed * speed / (2.0 * lim.decel_emergency) > d_zone - COMMIT_MARGIN_M
        return _Arrival(t_line, committed and speed > 0.0, heading, lane)

    def _own_arrival(self, now: float, ego: TruthState, crossing: Crossing) -> _Arrival:
        d_zone = crossing.s_in - self.length / 2.0 - ego.s
        heading = self.route.heading_at(crossing.s_in)
        offset = self._stop_offset[crossing.intersection]
        return self._arrival(
            now, d_zone, ego.speed, offset, heading, self._approach.get(crossing.intersection)
        )

    def _fp_arrival(
        self, now: float, fp: FuturePath, zone: _ZoneBox, crossing: Crossing, where: _InZone
    ) -> _Arrival | None:
        """Arrival of a car known from its future path, or None when its path does not come
        within ``d_margin_m`` of this route in the zone (opposing traffic, a turn that does
        not cross) or it comes from this car's own approach (followed, not crossed)."""
        pts = fp.points
        here_inside = where.here
        offset = self._stop_offset[crossing.intersection]
        margin = self.scenario.params.d_margin_m
        idx = where.idx
        if idx.shape[0]:
            _s, lat = self.route.project_many(np.ascontiguousarray(pts[idx, 0:2]))
            close = bool(np.any(np.abs(lat) < margin))
            exits = idx[-1] < pts.shape[0] - 1
            if not close and exits and not here_inside:
                return None  # passes through the zone without coming near this route
            # (a car still in the zone keeps counting until it has left it, even when the
            # rest of its path is clear of this route: the zone is free only then)
            first = int(idx[0])
            if first > 0:
                dx, dy = pts[first, 0] - pts[first - 1, 0], pts[first, 1] - pts[first - 1, 1]
                heading = math.atan2(dy, dx) if dx * dx + dy * dy > 1e-6 else fp.heading
            else:
                heading = fp.heading
            if not close and not self._lane_crosses(fp.x, fp.y, fp.heading, crossing):
                return None
            if here_inside:
                d_zone = 0.0
            else:
                xy = np.vstack(([fp.x, fp.y], pts[: first + 1, 0:2]))
                d_zone = float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))
        else:
            if not self._lane_crosses(fp.x, fp.y, fp.heading, crossing):
                return None
            heading = fp.heading
            d_zone = max(float(np.hypot(fp.x - zone.cx, fp.y - zone.cy)) - zone.radius, 0.0)
        own = self.route.heading_at(crossing.s_in)
        if abs(wrap_angle(heading - own)) <= SAME_APPROACH_RAD:
            return None  # the same approach: car following, not right of way
        stamp = fp.header.time_us * 1e-6
        age = max(now - stamp, 0.0)
        on_lane = self._on_lane(
            stamp, fp.x, fp.y, fp.heading, fp.speed, fp.length, crossing, age=age
        )
        if on_lane is not None:
            return on_lane[2]  # measured along its lane: the numbers its sender computes
        return self._arrival(stamp, d_zone, fp.speed, offset, heading, age=age)

    def _lane_crosses(self, x: float, y: float, heading: float, crossing: Crossing) -> bool:
        """Does the lane a car at (x, y) with ``heading`` drives in cross this route here?
        A car on no known lane is assumed to."""
        found = self.scenario.lane_of(x, y, heading)
        if found is None:
            return True
        return found[0] in self._crossing_lanes.get(crossing.intersection, frozenset())

    def _fp_interval(
        self, now: float, fp: FuturePath, zone: _ZoneBox, crossing: Crossing, where: _InZone
    ) -> _Known | None:
        """Occupancy of the zone by a car known from its future path."""
        pts = fp.points
        if pts.shape[0] == 0:
            return None
        here_inside = where.here
        idx = where.idx
        if idx.shape[0]:
            t_in = now if here_inside else float(pts[idx[0], 2])
            t_out = np.inf if idx[-1] == pts.shape[0] - 1 else float(pts[idx[-1], 2])
            return _Known(Interval(t_in, t_out), planned=True)
        if here_inside:
            return _Known(Interval(now, now + 1.0), planned=True)
        # not entering within its horizon: waiting before the zone, far away, or gone
        cx, cy = zone.cx, zone.cy
        d_now = float(np.hypot(fp.x - cx, fp.y - cy))
        d_end = float(np.hypot(pts[-1, 0] - cx, pts[-1, 1] - cy))
        if d_end > d_now + 0.5:
            return None  # moving away: gone
        if d_now > 40.0:
            return None  # far away and not arriving within its horizon
        return _Known(self._fp_earliest(now, fp, zone, crossing), planned=False)

    def _fp_earliest(
        self, now: float, fp: FuturePath, zone: _ZoneBox, crossing: Crossing
    ) -> Interval:
        """Earliest occupancy of a car known from its future path, from its current state."""
        radius = zone.radius
        d_now = float(np.hypot(fp.x - zone.cx, fp.y - zone.cy))
        dist = max(d_now - radius, 0.0)
        virtual = Crossing(crossing.intersection, dist, dist + 2.0 * radius, 0.0, 0.0)
        return self._earliest_interval(now, 0.0, fp.speed, virtual, fp.length)

    def _sensed_conflict(
        self, now: float, other: TruthState, crossing: Crossing
    ) -> tuple[Interval, _Arrival] | None:
        """Occupancy of the zone by a sensed car along its lane (the earliest it can be
        there) and its arrival, or None when its lane does not cross this route here.

        Constant velocity would call a slow car far off; a car that can still
        accelerate may arrive much sooner, and both cars must reach the same
        verdict from the same facts, so both sides use the earliest arrival.
        """
        found = self._on_lane(
            now, other.x, other.y, other.heading, other.speed, other.length, crossing
        )
        if found is None:
            return None
        c, s_other, arrival = found
        iv = self._earliest_interval(now, s_other, other.speed, c, other.length)
        return iv, arrival

    def _on_lane(
        self,
        stamp: float,
        x: float,
        y: float,
        heading: float,
        speed: float,
        length: float,
        crossing: Crossing,
        age: float = 0.0,
    ) -> tuple[Crossing, float, _Arrival] | None:
        """A car at (x, y) on a lane that crosses this route at ``crossing``, and not yet
        through it: that lane's crossing, the car's arc length on the lane [m] and its
        arrival (state taken at ``stamp``); else None. Measured along the lane exactly
        as this car measures itself along its route, so both compute the same numbers."""
        found = self.scenario.lane_of(x, y, heading)
        if found is None:
            return None
        lane_id, s_other = found
        if lane_id not in self._crossing_lanes.get(crossing.intersection, frozenset()):
            return None  # opposing, parallel or non-crossing traffic never conflicts here
        lane_cross = [
            c
            for c in self.scenario.lane_crossings(lane_id, length)
            if c.intersection == crossing.intersection
        ]
        if not lane_cross:
            return None
        c = lane_cross[0]
        if s_other - length / 2.0 > c.s_out:
            return None  # already through
        lane = self.scenario.lane(lane_id)
        d_zone = c.s_in - length / 2.0 - s_other
        offset = self._stop_offset[crossing.intersection]
        heading = lane.heading_at(c.s_in)
        arrival = self._arrival(stamp, d_zone, speed, offset, heading, lane_id, age)
        return c, s_other, arrival


def _oncoming(other: _Arrival, mine: _Arrival) -> bool:
    """The two cars enter the zone from opposite approaches (within 45° of opposite)."""
    return abs(wrap_angle(other.heading - mine.heading)) > 3.0 * math.pi / 4.0


@dataclass(frozen=True, slots=True)
class _Arrival:
    """When a car reaches its stop line (``line_arrival`` from its state, added to the
    time of that state; the time of the state once past the line) [s, run time], whether
    it is committed, its heading entering the zone [rad], and the lane it comes in on
    (None when not known: a future path off the lanes)."""

    t_line: float
    committed: bool
    heading: float
    lane: str | None = None


@dataclass(frozen=True, slots=True)
class _Known:
    """Another car's occupancy, and whether it comes from its plan (else: earliest arrival)."""

    interval: Interval
    planned: bool


def line_arrival(d_line: float, speed: float, decel: float) -> float:
    """Stop-line arrival [s from now] of a car ``d_line`` [m] before its line at ``speed``
    [m/s], on the plan a careful car follows at a blind corner: on at its current speed,
    then braking at ``decel`` [m/s²] (the scenario's comfortable deceleration, the same
    for every car) to a stop at the line: ``d / max(v, ARRIVAL_FLOOR_MPS) + v / (2 decel)``.

    Both cars compute it from facts both see alike (distance along the lane, speed). Two
    cars that drive the same speed profile ``δ`` apart get estimates ``δ`` apart all the
    way in (exact while cruising and while braking at ``decel``), where the earliest
    possible arrival compressed the gap into a tie as both slowed for the corner (issue
    17). 0 once at or past the line; a stopped car counts as creeping at the floor.
    """
    if d_line <= 0.0:
        return 0.0
    v = max(speed, 0.0)
    return d_line / max(v, ARRIVAL_FLOOR_MPS) + v / (2.0 * decel)


@dataclass(frozen=True, slots=True)
class _ZoneBox:
    """An intersection's zone as the yield rules use it, computed once (issue 14: these
    reductions over the polygon, per future path per tick, were a tenth of a traffic
    run): its axis-aligned bounds, centre [m] and the radius of the circle a square of
    its corner distance holds [m]."""

    x0: float
    y0: float
    x1: float
    y1: float
    cx: float
    cy: float
    radius: float

    @classmethod
    def of(cls, zone: FloatArray) -> _ZoneBox:
        cx, cy = float(zone[:, 0].mean()), float(zone[:, 1].mean())
        return cls(
            float(zone[:, 0].min()),
            float(zone[:, 1].min()),
            float(zone[:, 0].max()),
            float(zone[:, 1].max()),
            cx,
            cy,
            float(np.min(np.hypot(zone[:, 0] - cx, zone[:, 1] - cy)) / np.sqrt(2.0)),
        )


@dataclass(frozen=True, slots=True)
class _InZone:
    """Where a future path is in a zone's box grown by half the car's length: the indices
    of its points inside (ascending) and whether the car is inside now."""

    idx: IntArray
    here: bool

    @classmethod
    def of(cls, fp: FuturePath, zone: _ZoneBox) -> _InZone:
        m = fp.length / 2.0
        x0, y0, x1, y1 = zone.x0 - m, zone.y0 - m, zone.x1 + m, zone.y1 + m
        x, y = fp.points[:, 0], fp.points[:, 1]
        idx = np.flatnonzero((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))
        return cls(idx, x0 <= fp.x <= x1 and y0 <= fp.y <= y1)
