"""Traffic-efficiency and safety metrics of one run, from ground truth.

The harness calls :meth:`MetricsRecorder.record` every physics step (20 Hz) with the
ground truth of the cars present, and :meth:`MetricsRecorder.result` at the end.

Definitions (times in s on the run's time base, distances in m):

- **passing time** (paper §V): from the car's centre passing ``start_offset_m +
  passing_start_m`` to passing the centre of the *last* intersection on its route
  plus ``passing_end_after_center_m`` (a route through no intersection ends at
  ``goal - goal_tolerance_m``). Gate times are interpolated linearly in ``s``
  between steps. None if the car never passes both gates.
- **collisions**: distinct episodes of footprint overlap per pair of cars: a pair
  overlapping in consecutive steps is one collision. A step missing one of the two
  cars (its truth did not reach the monitor) measures nothing for that pair and
  neither starts nor ends its episode: safety metrics compare cars only at the
  same step, never against an older one (``services.sim.truth``).
- **min gap**: smallest distance between two footprints over all pairs and
  recorded steps; ``inf`` with fewer than two cars.
- **zone visits**: when a car's footprint starts and stops overlapping a conflict
  zone, refined between steps by bisection along its route.
- **PET** (post-encroachment time) in a conflict zone: for two cars whose paths
  conflict there, the time from one footprint leaving the zone to the other
  entering it; 0 when both occupy the zone at once. Paths conflict when they enter
  the zone at different points (more than 1 m apart) and their centre lines inside
  the zone come within ``d_margin_m``: crossing and merging count, a car following
  another through the same entry does not (that gap is a headway). ``inf`` if no
  such pair passes.
- **conflict-area PET**: the same pairs, measured where their paths meet, not over the
  whole zone (Allen et al.'s PET at the conflict point). The conflict area of a pair
  is, on each route, the stretch of its centre line inside the zone that comes within
  ``d_margin_m`` of the other's where that one heads another way (more than
  ``SAME_WAY_RAD``, 35 degrees, as the RSU's lane rule): a crossing, or a merge up to
  where the two paths have become one lane (beyond it the cars follow each other, which
  the gap measures). A car occupies its stretch from its front reaching the start to its
  rear passing the end (along its route: ``s +- length / 2``, interpolated linearly
  between steps). At a merge the zone PET is 0 whenever the follower enters the box
  before its leader has left it, metres apart (four-way-flows, paper, seed 0: 16 ms of
  joint occupancy, 7.4 m apart). A car is assumed to pass each conflict area once
  (routes do not loop through a zone).
- **first through**: the car entered the conflict zone of the first intersection on
  its route before every other car that entered that zone (ties: lower id).
- **stops**: times the speed drops below 0.1 m/s after having exceeded 1.0 m/s;
  a stop within ``goal_tolerance_m`` of the goal (the final stop) is not counted.
- **finished**: the car stood (speed < 0.1 m/s) within ``goal_tolerance_m`` of its
  goal at some step.
- **insertion delay** (the in-process harness, and the monitor's replay of the daemons'
  truth, ``services.sim.truth``, call :meth:`MetricsRecorder.inserted`): time from the
  car's arrival (its start time) to its insertion at its route's start (SUMO's depart
  delay); None for a car never inserted.
- **free-flow time**: the least time to drive from the car's start offset to its goal
  alone, from rest to rest, under its ``v_max``, ``accel``, ``decel_comfort`` and the
  curve speed caps (``kinematics.curve_speed_cap``); actuator lag ignored
  (:func:`free_flow_time_s`).
- **delay**: finished time minus arrival minus the free-flow time, i.e. travel time
  beyond free flow plus insertion wait; clipped at 0; None if not finished or never
  inserted.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import numpy as np
import numpy.typing as npt

from services.model.geometry import (
    FloatArray,
    Polyline,
    convex_overlap,
    footprint,
    footprints,
    min_point_distance,
    rect_distances,
)
from services.model.kinematics import Limits, TruthState, curve_speed_cap
from services.model.limits import STOP_ARM_ABOVE_MPS, STOP_COUNT_BELOW_MPS
from services.model.scenario import SAMPLE_STEP_M, Scenario
from services.rsu.reservation import SAME_WAY_RAD

__all__ = [
    "CollisionEvent",
    "MetricsRecorder",
    "RunMetrics",
    "VehicleMetrics",
    "ZoneVisit",
    "free_flow_time_s",
]

FREE_FLOW_STEP_M = 0.5
"""Grid step of the free-flow speed profile [m]."""

SAME_ENTRY_M = 1.0
"""Two paths entering a zone closer than this (m) share the entry (following, no PET)."""
_BISECT_ITERS = 30


@dataclass(frozen=True, slots=True)
class ZoneVisit:
    """One car's footprint occupying one conflict zone from ``entered_s`` to ``left_s``
    (None: still inside at the end)."""

    intersection: str
    entered_s: float
    left_s: float | None


@dataclass(frozen=True, slots=True)
class CollisionEvent:
    """Footprints of cars ``a`` and ``b`` (a < b) started to overlap at ``t``."""

    t: float
    a: str
    b: str


@dataclass(frozen=True, slots=True)
class VehicleMetrics:
    """Per-car results; see the module docstring for definitions."""

    passing_time_s: float | None
    first_through: bool
    stops: int
    max_speed_mps: float
    finished: bool
    finished_s: float | None
    entered_zone_s: float | None
    left_zone_s: float | None
    passing_start_s: float | None
    passing_end_s: float | None
    zone_visits: tuple[ZoneVisit, ...]
    mode_time_s: Mapping[str, float]
    reason_time_s: Mapping[str, float]
    mode_changes: tuple[tuple[float, str], ...]
    arrival_s: float | None = None
    inserted_s: float | None = None
    insertion_delay_s: float | None = None
    free_flow_s: float | None = None
    delay_s: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "passing_time_s": self.passing_time_s,
            "first_through": self.first_through,
            "stops": self.stops,
            "max_speed_mps": self.max_speed_mps,
            "finished": self.finished,
            "finished_s": self.finished_s,
            "entered_zone_s": self.entered_zone_s,
            "left_zone_s": self.left_zone_s,
            "mode_time_s": dict(self.mode_time_s),
            "reason_time_s": dict(self.reason_time_s),
        }


@dataclass(frozen=True, slots=True)
class RunMetrics:
    """Results of one run. ``min_gap_m``/``min_pet_s`` are ``inf`` when undefined."""

    collisions: int
    min_gap_m: float
    min_pet_s: float
    sim_s: float
    vehicles: Mapping[str, VehicleMetrics]
    collision_events: tuple[CollisionEvent, ...] = ()
    min_gap_t_s: float | None = None
    min_gap_pair: tuple[str, str] | None = None
    min_pet_pair: tuple[str, str] | None = None
    min_pet_intersection: str | None = None
    min_conflict_pet_s: float = math.inf
    min_conflict_pet_pair: tuple[str, str] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready keys of the run result (``inf`` becomes None: JSON has no inf)."""

        def fin(x: float) -> float | None:
            return x if math.isfinite(x) else None

        return {
            "collisions": self.collisions,
            "min_gap_m": fin(self.min_gap_m),
            "min_pet_s": fin(self.min_pet_s),
            "min_conflict_pet_s": fin(self.min_conflict_pet_s),
            "sim_s": self.sim_s,
            "vehicles": {vid: vm.as_dict() for vid, vm in self.vehicles.items()},
        }


@dataclass(slots=True)
class _Track:
    """Mutable per-car bookkeeping of the recorder."""

    id: str
    route: Polyline
    length: float
    width: float
    goal: float
    gate0: float
    gate1: float
    first_x: str | None
    zones: list[str]
    last: TruthState | None = None
    last_t: float | None = None
    t_gate0: float | None = None
    t_gate1: float | None = None
    armed: bool = False
    stops: int = 0
    max_speed: float = 0.0
    finished_s: float | None = None
    inside: dict[str, bool] = field(default_factory=dict)
    visits: list[list[Any]] = field(default_factory=list)  # [intersection, t_in, t_out|None]
    mode: str | None = None
    reason: str | None = None
    mode_time: dict[str, float] = field(default_factory=dict)
    reason_time: dict[str, float] = field(default_factory=dict)
    mode_changes: list[tuple[float, str]] = field(default_factory=list)
    arrival_s: float | None = None
    inserted_s: float | None = None
    arc_window: tuple[float, float] | None = None  # route stretch around its zones [m]
    arc_t: list[float] = field(default_factory=list)  # times [s] of arc_s, in order
    arc_s: list[float] = field(default_factory=list)  # route positions [m] in arc_window


class MetricsRecorder:
    """Accumulates run metrics step by step; pure (no clock, no I/O)."""

    def __init__(self, scenario: Scenario) -> None:
        self._sc = scenario
        p = scenario.params
        m = scenario.metrics
        self._tol = p.goal_tolerance_m
        self._tracks: dict[str, _Track] = {}
        for v in scenario.vehicles:
            route = scenario.route(v.route)
            cr = scenario.vehicle_crossings(v.id)
            goal = scenario.goal_m(v.id)
            gate1 = cr[-1].center_s + m.passing_end_after_center_m if cr else goal - self._tol
            self._tracks[v.id] = _Track(
                id=v.id,
                route=route,
                length=v.length_m,
                width=v.width_m,
                goal=goal,
                gate0=v.start_offset_m + m.passing_start_m,
                gate1=gate1,
                first_x=cr[0].intersection if cr else None,
                zones=[c.intersection for c in cr],
                # the conflict areas lie in its zones; a body length of room either side
                arc_window=(
                    (min(c.s_in for c in cr) - v.length_m, max(c.s_out for c in cr) + v.length_m)
                    if cr
                    else None
                ),
            )
        self._zone_poly: dict[str, FloatArray] = {}
        self._zone_reach: dict[str, tuple[float, float, float]] = {}
        for it in scenario.intersections:
            poly = scenario.zone_polygon(it.id)
            c = poly.mean(axis=0)
            r = float(np.max(np.hypot(*(poly - c).T)))
            self._zone_poly[it.id] = poly
            self._zone_reach[it.id] = (float(c[0]), float(c[1]), r)
        self._conflict_cache: dict[tuple[str, str, str], bool] = {}
        self._area_cache: dict[tuple[str, str, str], tuple[float, float] | None] = {}
        self._t: float | None = None
        self._t0: float | None = None
        self._collisions: list[CollisionEvent] = []
        self._overlap: set[tuple[str, str]] = set()
        self._min_gap = math.inf
        self._min_gap_t: float | None = None
        self._min_gap_pair: tuple[str, str] | None = None
        # close pairs whose exact footprint distance is not computed yet (see _update_pairs)
        self._pending: list[_PendingStep] = []
        self._pending_pairs = 0
        self._pending_bound = math.inf

    # -- recording ------------------------------------------------------------------

    def inserted(self, vehicle_id: str, arrival_s: float, t: float) -> None:
        """Car ``vehicle_id``, arrived at ``arrival_s``, entered the world at ``t`` [s]."""
        tr = self._tracks.get(vehicle_id)
        if tr is None:
            raise ValueError(f"inserted: unknown vehicle {vehicle_id!r}")
        if not (math.isfinite(arrival_s) and math.isfinite(t) and t >= arrival_s - 1e-9):
            raise ValueError(f"inserted: bad times arrival {arrival_s!r}, insertion {t!r}")
        tr.arrival_s = arrival_s
        tr.inserted_s = t

    def record(
        self,
        t: float,
        states: Sequence[TruthState],
        modes: Mapping[str, str] | None = None,
        reasons: Mapping[str, str] | None = None,
    ) -> None:
        """Take one step's ground truth at time ``t`` (s, strictly increasing).

        ``modes``/``reasons`` optionally label each car (e.g. ``"C_SLOW"``, ``"yield"``);
        the recorder sums the time spent under each label.
        """
        if not math.isfinite(t):
            raise ValueError(f"record: t must be finite, got {t!r}")
        if self._t is not None and t <= self._t:
            raise ValueError(f"record: time must increase ({t} after {self._t})")
        ids = [st.id for st in states]
        if len(set(ids)) != len(ids):
            raise ValueError("record: a vehicle appears twice in one step")
        for vid in ids:
            if vid not in self._tracks:
                raise ValueError(f"record: unknown vehicle {vid!r}")
        if self._t0 is None:
            self._t0 = t
        self._t = t
        for st in states:
            tr = self._tracks[st.id]
            self._update_vehicle(
                tr,
                t,
                st,
                None if modes is None else modes.get(st.id),
                None if reasons is None else reasons.get(st.id),
            )
        self._update_pairs(t, states)

    def _update_vehicle(
        self, tr: _Track, t: float, st: TruthState, mode: str | None, reason: str | None
    ) -> None:
        prev = tr.last
        prev_t = tr.last_t
        if prev_t is not None:
            dt = t - prev_t
            if tr.mode is not None:
                tr.mode_time[tr.mode] = tr.mode_time.get(tr.mode, 0.0) + dt
            if tr.reason is not None:
                tr.reason_time[tr.reason] = tr.reason_time.get(tr.reason, 0.0) + dt
        if mode is not None and mode != tr.mode:
            tr.mode_changes.append((t, mode))
        tr.mode = mode
        tr.reason = reason

        if tr.t_gate0 is None:
            tr.t_gate0 = _gate_time(prev, prev_t, st, t, tr.gate0)
        if tr.t_gate1 is None:
            tr.t_gate1 = _gate_time(prev, prev_t, st, t, tr.gate1)

        tr.max_speed = max(tr.max_speed, st.speed)
        at_goal = st.s >= tr.goal - self._tol
        if st.speed > STOP_ARM_ABOVE_MPS:
            tr.armed = True
        elif st.speed < STOP_COUNT_BELOW_MPS:
            if tr.armed and not at_goal:
                tr.stops += 1
            tr.armed = False
            if tr.finished_s is None and abs(st.s - tr.goal) <= self._tol:
                tr.finished_s = t

        window = tr.arc_window
        if window is not None:
            back = st.s if prev is None else prev.s
            # this step's move touches the window
            if max(back, st.s) >= window[0] and min(back, st.s) <= window[1]:
                if (
                    prev is not None
                    and prev_t is not None
                    and (not tr.arc_t or tr.arc_t[-1] != prev_t)
                ):
                    tr.arc_t.append(prev_t)
                    tr.arc_s.append(prev.s)
                tr.arc_t.append(t)
                tr.arc_s.append(st.s)

        for xid in tr.zones:
            now_in = self._in_zone(xid, st)
            was_in = tr.inside.get(xid, False)
            if now_in == was_in:
                continue
            tz = self._refine(tr, xid, prev, prev_t, st, t, now_in)
            if now_in:
                tr.visits.append([xid, tz, None])
            else:
                for v in reversed(tr.visits):
                    if v[0] == xid and v[2] is None:
                        v[2] = tz
                        break
            tr.inside[xid] = now_in
        tr.last = st
        tr.last_t = t

    def _in_zone(self, xid: str, st: TruthState) -> bool:
        cx, cy, r = self._zone_reach[xid]
        half_diag = 0.5 * math.hypot(st.length, st.width)
        if math.hypot(st.x - cx, st.y - cy) > r + half_diag:
            return False
        return convex_overlap(st.footprint(), self._zone_poly[xid])

    def _inside_at(self, tr: _Track, xid: str, s: float) -> bool:
        x, y = tr.route.point_at(s)
        fp = footprint(x, y, tr.route.heading_at(s), tr.length, tr.width)
        return convex_overlap(fp, self._zone_poly[xid])

    def _refine(
        self,
        tr: _Track,
        xid: str,
        prev: TruthState | None,
        prev_t: float | None,
        st: TruthState,
        t: float,
        now_in: bool,
    ) -> float:
        """Time between two steps at which the zone state flipped (bisection along s)."""
        if prev is None or prev_t is None or not st.s > prev.s:
            return t
        if self._inside_at(tr, xid, prev.s) == now_in or self._inside_at(tr, xid, st.s) != now_in:
            return t  # the truth is not on the route geometry: keep the step time
        lo, hi = prev.s, st.s
        for _ in range(_BISECT_ITERS):
            mid = 0.5 * (lo + hi)
            if self._inside_at(tr, xid, mid) == now_in:
                hi = mid
            else:
                lo = mid
        return prev_t + (t - prev_t) * (hi - prev.s) / (st.s - prev.s)

    def _update_pairs(self, t: float, states: Sequence[TruthState]) -> None:
        """Queue the pairs of this step that may be closer than the minimum gap so far.

        A cheap lower bound (centre distance minus both circumradii) selects the
        pairs; their footprints and exact distances are computed in batches of up to
        :data:`PAIR_BATCH` pairs (one vectorised call instead of one per step,
        the harness's largest cost otherwise), in step order, so the collision
        events and the minimum gap are exactly those of a step-by-step check.
        """
        # x [m], y [m], heading [rad], length [m], width [m] per car
        poses = np.array(
            [(s.x, s.y, s.heading, s.length, s.width) for s in states], dtype=np.float64
        ).reshape(-1, 5)
        rad = 0.5 * np.hypot(poses[:, 3], poses[:, 4])
        ii, jj = _pairs(len(states))  # none for fewer than two cars
        centre = np.hypot(*(poses[ii, :2] - poses[jj, :2]).T)
        lb = centre - rad[ii] - rad[jj]
        # the gap is at most the centre distance: a pending pair bounds the minimum too
        bound = min(self._min_gap, self._pending_bound)
        cand = np.flatnonzero((lb <= 0.0) | (lb < bound))
        ids = [s.id for s in states]
        present = frozenset(ids)
        if cand.size == 0:
            # no pair present is close: that ends their overlaps (not an absent car's)
            self._flush_pairs()
            self._overlap = {p for p in self._overlap if not present.issuperset(p)}
            return
        ci, cj = ii[cand], jj[cand]
        names = [
            (ids[i], ids[j]) if ids[i] <= ids[j] else (ids[j], ids[i])
            for i, j in zip(ci.tolist(), cj.tolist(), strict=True)
        ]
        self._pending.append(_PendingStep(t, names, poses[ci], poses[cj], present))
        self._pending_pairs += len(names)
        self._pending_bound = min(self._pending_bound, float(centre[cand].min()))
        if self._pending_pairs >= PAIR_BATCH:
            self._flush_pairs()

    def _flush_pairs(self) -> None:
        """Exact distances of every queued pair, applied step by step in order."""
        if not self._pending:
            return
        steps, self._pending = self._pending, []
        self._pending_pairs = 0
        self._pending_bound = math.inf
        a = np.concatenate([st.a for st in steps]).T
        b = np.concatenate([st.b for st in steps]).T
        dists = rect_distances(footprints(*a), footprints(*b)).tolist()
        k = 0
        for st in steps:
            # a pair with a car absent at this step keeps its state (nothing measured)
            now_overlap = {p for p in self._overlap if not st.present.issuperset(p)}
            for pair in st.pairs:
                d = dists[k]
                k += 1
                if d < self._min_gap:
                    self._min_gap = d
                    self._min_gap_t = st.t
                    self._min_gap_pair = pair
                if d == 0.0:
                    now_overlap.add(pair)
                    if pair not in self._overlap:
                        self._collisions.append(CollisionEvent(st.t, *pair))
            self._overlap = now_overlap

    # -- results ------------------------------------------------------------------

    def _conflicting(self, ra: str, rb: str, xid: str) -> bool:
        key = (min(ra, rb), max(ra, rb), xid)
        hit = self._conflict_cache.get(key)
        if hit is not None:
            return hit
        zone = self._zone_poly[xid]
        pa, pb = self._sc.route(ra), self._sc.route(rb)
        ia, ib = pa.interval_in_polygon(zone), pb.interval_in_polygon(zone)
        res = False
        if ia is not None and ib is not None:
            ea, eb = pa.point_at(ia[0]), pb.point_at(ib[0])
            if math.hypot(ea[0] - eb[0], ea[1] - eb[1]) > SAME_ENTRY_M:
                sa = pa.sample(ia[0], ia[1], SAMPLE_STEP_M)
                sb = pb.sample(ib[0], ib[1], SAMPLE_STEP_M)
                res = min_point_distance(sa, sb) < self._sc.params.d_margin_m
        self._conflict_cache[key] = res
        return res

    def _conflict_area(self, ra: str, rb: str, xid: str) -> tuple[float, float] | None:
        """The stretch ``(s0, s1)`` of route ``ra``'s centre line inside zone ``xid`` that
        comes within ``d_margin_m`` of route ``rb``'s there, at a point of ``rb`` heading
        another way (by more than ``SAME_WAY_RAD``); None if none does."""
        key = (ra, rb, xid)
        if key in self._area_cache:
            return self._area_cache[key]
        zone = self._zone_poly[xid]
        pa, pb = self._sc.route(ra), self._sc.route(rb)
        ia, ib = pa.interval_in_polygon(zone), pb.interval_in_polygon(zone)
        area: tuple[float, float] | None = None
        if ia is not None and ib is not None:
            n = max(2, math.ceil((ia[1] - ia[0]) / SAMPLE_STEP_M) + 1)
            s = np.linspace(ia[0], ia[1], n)
            nb = max(2, math.ceil((ib[1] - ib[0]) / SAMPLE_STEP_M) + 1)
            sb_s = np.linspace(ib[0], ib[1], nb)
            sa, sb = pa.points_at(s), pb.points_at(sb_s)
            d = np.hypot(sa[:, None, 0] - sb[None, :, 0], sa[:, None, 1] - sb[None, :, 1])
            turn = pa.headings_at(s)[:, None] - pb.headings_at(sb_s)[None, :]
            across = np.abs(np.arctan2(np.sin(turn), np.cos(turn))) > SAME_WAY_RAD
            near = np.flatnonzero(((d < self._sc.params.d_margin_m) & across).any(axis=1))
            if near.size:
                area = (float(s[near[0]]), float(s[near[-1]]))
        self._area_cache[key] = area
        return area

    def _occupancy(self, tr: _Track, area: tuple[float, float]) -> tuple[float, float] | None:
        """When ``tr``'s body was on ``area`` of its route: front at its start to rear past
        its end [s]; the end ``inf`` if the rear never passed; None if it never got there."""
        enter = _first_reach(tr.arc_t, tr.arc_s, area[0] - 0.5 * tr.length)
        if enter is None:
            return None
        leave = _first_reach(tr.arc_t, tr.arc_s, area[1] + 0.5 * tr.length)
        return enter, math.inf if leave is None else leave

    def _conflict_pet(self, a: str, b: str, xid: str) -> float:
        """Conflict-area PET of cars ``a`` and ``b`` at ``xid`` [s]; ``inf`` if one of them
        never reached its side of the area."""
        ta, tb = self._tracks[a], self._tracks[b]
        ra, rb = self._sc.vehicle(a).route, self._sc.vehicle(b).route
        area_a, area_b = self._conflict_area(ra, rb, xid), self._conflict_area(rb, ra, xid)
        if area_a is None or area_b is None:
            return math.inf
        oa, ob = self._occupancy(ta, area_a), self._occupancy(tb, area_b)
        if oa is None or ob is None:
            return math.inf
        return max(0.0, ob[0] - oa[1], oa[0] - ob[1])

    def result(self) -> RunMetrics:
        """The metrics so far (may be called at any time; recording may continue)."""
        self._flush_pairs()
        visits: dict[str, dict[str, list[tuple[float, float]]]] = {}
        for tr in self._tracks.values():
            for xid, tin, tout in tr.visits:
                out = math.inf if tout is None else float(tout)
                visits.setdefault(xid, {}).setdefault(tr.id, []).append((float(tin), out))

        min_pet = math.inf
        pet_pair: tuple[str, str] | None = None
        pet_x: str | None = None
        min_area_pet = math.inf
        area_pair: tuple[str, str] | None = None
        for xid, per_car in visits.items():
            for a, b in combinations(sorted(per_car), 2):
                ra = self._sc.vehicle(a).route
                rb = self._sc.vehicle(b).route
                if not self._conflicting(ra, rb, xid):
                    continue
                area_pet = self._conflict_pet(a, b, xid)
                if area_pet < min_area_pet:
                    min_area_pet, area_pair = area_pet, (a, b)
                for ain, aout in per_car[a]:
                    for bin_, bout in per_car[b]:
                        pet = max(0.0, bin_ - aout, ain - bout)
                        if pet < min_pet:
                            min_pet, pet_pair, pet_x = pet, (a, b), xid

        first_entry: dict[str, tuple[float, str]] = {}
        for xid, per_car in visits.items():
            first_entry[xid] = min((min(v[0] for v in vs), vid) for vid, vs in per_car.items())

        vehicles: dict[str, VehicleMetrics] = {}
        for vid, tr in self._tracks.items():
            first = tr.first_x
            own = [v for v in tr.visits if v[0] == first] if first is not None else []
            first_through = bool(
                own and first is not None and first_entry.get(first, (0.0, ""))[1] == vid
            )
            passing = (
                tr.t_gate1 - tr.t_gate0
                if tr.t_gate0 is not None and tr.t_gate1 is not None
                else None
            )
            ins_delay = free = delay = None
            if tr.arrival_s is not None and tr.inserted_s is not None:
                ins_delay = max(tr.inserted_s - tr.arrival_s, 0.0)
                v = self._sc.vehicle(vid)
                free = free_flow_time_s(tr.route, v.start_offset_m, tr.goal, self._sc.limits(vid))
                if tr.finished_s is not None:
                    delay = max(tr.finished_s - tr.arrival_s - free, 0.0)
            vehicles[vid] = VehicleMetrics(
                passing_time_s=passing,
                first_through=first_through,
                stops=tr.stops,
                max_speed_mps=tr.max_speed,
                finished=tr.finished_s is not None,
                finished_s=tr.finished_s,
                entered_zone_s=float(own[0][1]) if own else None,
                left_zone_s=None if not own or own[0][2] is None else float(own[0][2]),
                passing_start_s=tr.t_gate0,
                passing_end_s=tr.t_gate1,
                zone_visits=tuple(
                    ZoneVisit(x, float(a), None if b is None else float(b)) for x, a, b in tr.visits
                ),
                mode_time_s=dict(tr.mode_time),
                reason_time_s=dict(tr.reason_time),
                mode_changes=tuple(tr.mode_changes),
                arrival_s=tr.arrival_s,
                inserted_s=tr.inserted_s,
                insertion_delay_s=ins_delay,
                free_flow_s=free,
                delay_s=delay,
            )
        return RunMetrics(
            collisions=len(self._collisions),
            min_gap_m=self._min_gap,
            min_pet_s=min_pet,
            min_conflict_pet_s=min_area_pet,
            min_conflict_pet_pair=area_pair,
            sim_s=0.0 if self._t is None else self._t,
            vehicles=vehicles,
            collision_events=tuple(self._collisions),
            min_gap_t_s=self._min_gap_t,
            min_gap_pair=self._min_gap_pair,
            min_pet_pair=pet_pair,
            min_pet_intersection=pet_x,
        )


def _first_reach(times: Sequence[float], arcs: Sequence[float], target: float) -> float | None:
    """First time [s] the route position reaches ``target`` [m], interpolated linearly
    between samples; the first sample's time if it is already there; None if never."""
    for i, s in enumerate(arcs):
        if s >= target:
            if i == 0:
                return times[0]
            s0, t0 = arcs[i - 1], times[i - 1]  # s0 < target <= s
            return t0 + (times[i] - t0) * (target - s0) / (s - s0)
    return None


def _gate_time(
    prev: TruthState | None, prev_t: float | None, st: TruthState, t: float, gate: float
) -> float | None:
    """When the car's centre passed arc length ``gate`` during the last step, or None."""
    if st.s < gate:
        return None
    if prev is None or prev_t is None or prev.s >= gate or not st.s > prev.s:
        return t
    return prev_t + (t - prev_t) * (gate - prev.s) / (st.s - prev.s)


PAIR_BATCH = 256
"""Close pairs queued before their exact distances are computed in one call."""


@dataclass(frozen=True, slots=True)
class _PendingStep:
    """One step's close pairs: (id, id) sorted, and the two cars' poses (P, 5):
    x [m], y [m], heading [rad], length [m], width [m]; ``present`` every car of the step."""

    t: float
    pairs: list[tuple[str, str]]
    a: FloatArray
    b: FloatArray
    present: frozenset[str]


@functools.lru_cache(maxsize=64)
def _pairs(n: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Index pairs (i < j) of ``n`` cars; cached, the set of cars rarely changes."""
    ii, jj = np.triu_indices(n, k=1)
    ii.flags.writeable = False
    jj.flags.writeable = False
    return ii, jj


@functools.lru_cache(maxsize=256)
def free_flow_time_s(route: Polyline, s0: float, goal: float, limits: Limits) -> float:
    """Least time [s] from rest at ``s0`` to rest at ``goal`` [m] along ``route``, alone:
    speed within ``v_max`` and the curve caps, accelerating at ``accel``, braking at
    ``decel_comfort`` (forward and backward passes on a :data:`FREE_FLOW_STEP_M` grid)."""
    if not goal > s0:
        raise ValueError(f"free_flow_time_s: goal {goal!r} must be beyond s0 {s0!r}")
    n = max(math.ceil((goal - s0) / FREE_FLOW_STEP_M), 2)
    s = np.linspace(s0, goal, n + 1)
    ds = (goal - s0) / n
    cap = curve_speed_cap(route, s, limits.lat_accel, limits.v_max, pad_m=ds)
    v = np.minimum(cap, np.inf)
    v[0] = v[-1] = 0.0
    for k in range(1, n + 1):
        v[k] = min(v[k], math.sqrt(v[k - 1] ** 2 + 2.0 * limits.accel * ds))
    for k in range(n - 1, -1, -1):
        v[k] = min(v[k], math.sqrt(v[k + 1] ** 2 + 2.0 * limits.decel_comfort * ds))
    mean = 0.5 * (v[:-1] + v[1:])
    return float(np.sum(ds / mean))
