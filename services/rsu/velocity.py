"""Velocity manager: the coordinated path of a car, from its latest autonomous path.

A coordinated path keeps the autonomous path's positions and changes only the
speeds (paper §III-B: "the vehicle decides the trajectory, the RSU determines
the speed"). It carries a target speed per point [m/s] and the pass times the
car will really achieve following them within its limits (accelerate at most
``accel_mps2``, brake at ``decel_comfort_mps2``), so that the RSU's table entry
for a coordinated car is honest. Times follow eq. (1) of the paper (constant
speed between consecutive points), the constant speed on a segment being the
mean of its end speeds (exact for constant acceleration).

A car that is told to stop holds its stop position until the horizon (``now +
T_free``), as a future path does: hold points every ``hold_step_s`` or closer,
so that any crossing point is less than one headway from one of them. The
positions of a stopping path are therefore the autonomous path's up to where the
car stops, then the stop point repeated.

Two policies (``Policy``):

``paper``
    ``C_SLOW``: target speed 0 at every point; the car brakes comfortably from
    its current speed; the path is the braking curve to the exact stop point,
    then the hold. ``C_FAST``: ``V_max`` at every point up to the zone exit plus
    one car length, then the autonomous path's own speeds (distance/time between
    its consecutive points); the car accelerates at ``accel_mps2``.
``slot`` (beyond the paper)
    ``C_FAST`` as in ``paper``. ``C_SLOW``: the earliest zone entry time ``t*``
    (the fastest entry plus 0, 1, 2... ``slot_step_s``, up to ``T_free``) whose
    retimed path has no conflict with the table, and the fastest profile that
    meets it: brake to a constant speed ``v_c`` (found by bisection) so as to
    reach the zone entry no earlier than ``t*``, then accelerate towards
    ``V_max``. If even ``slot_min_speed_mps`` is too fast, the car stops
    ``stop_gap_m`` (front bumper) before the zone and waits until it must
    start again to enter at ``t*``. If no such path exists (the car cannot stop
    before the zone any more, or no gap within ``T_free``) it falls back to the
    ``paper`` stop. A path that never reaches the zone, or a car already in
    it, also gets the ``paper`` stop. So does a path that ends at rest with the
    car's body in the zone (its own planner stops it there, behind a car still
    crossing, say): a retiming keeps the positions, so every slot of it would leave
    the car standing in the box ("don't block the box", :meth:`VelocityManager.rests_in_zone`).
    Without that rule ``four-way-flows-40`` (seed 0) locked up: three cars stood in
    the box, each waiting for the next, and 32 of 40 cars never got through; with it
    all 40 do. The same rule on ``C_FAST`` grants and releases (both policies) was
    tried and dropped: it held cars whose own path stopped in the box only for a
    moment (an emergency stop behind a car crossing in front), and ``four-way-flows``
    under ``paper`` (seed 0) went from 14.2 s of mean delay to 26.9 s, or stranded 14
    of 30 cars with the grant rule alone. The narrower rule kept (6 Dec,
    ``RsuCore._box_blocked``) holds such a path only while another car stands in the box.

The positions are the autonomous path's distinct positions: repeated points
(a held stop at its end) are merged, and the autonomous path is taken to stop
at its end in that case.

Each car is planned with its own limits, the ``VehicleLimits`` its path declares
(``protocol/SPEC.md`` 2.3): its ``v_max`` replaces ``V_max`` above, its ``accel``
and ``decel`` the accelerations, and its ``lat_accel`` caps every speed in a curve
at ``sqrt(lat_accel * r)``, ``r`` the radius of the path's own points
(:func:`services.rsu.paths.curve_caps`), braking at ``decel`` ahead of the curve.
A car that declares no limits is planned with the RSU's configuration (the
scenario's ``[params]``). The car's length and width are the ones in its path (the
slot search checks conflicts with the pair margin they give, see
``services.rsu.reservation``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from protocol.messages import Mode, VehicleLimits, VehiclePath
from services.model.types import Policy
from services.rsu import paths
from services.rsu.reservation import (
    ENDS_ROUNDING,
    LANE_SLACK_M,
    SAME_WAY_RAD,
    Entry,
    ReservationTable,
    follow_distance,
)

if TYPE_CHECKING:
    from services.rsu.config import RsuConfig

FloatArray = npt.NDArray[np.float64]

_SAME_POINT_M = 1e-6
_MAX_HOLDS = 20
HARD_STOP_FACTOR = 2.0
"""A stop short of the zone may brake up to this many times the comfortable deceleration
(4 m/s² by default, within the 5 m/s² emergency limit)."""
FIRM_STOP_FACTOR = 2.5
"""A car already told to stop short of the zone keeps that stop braking up to this many
times the comfortable deceleration (5 m/s² by default, the emergency limit): re-planned
every 0.1 s from a speed a little above its plan's (actuator lag, rounding), a stop at
exactly the hard limit would otherwise slide into the zone (found by the invariant's
property test)."""
REACTION_S = 0.4
"""A car told to stop keeps its speed this long before its brakes bite [s]: its actuator
lag (``vehicle_params.actuator_lag_s`` = 0.3 s) and up to one planning step (0.1 s)
before it takes the command. A stop is short of the zone only when it is with this much
travel at the current speed added.
Found by the demand experiment, slot, 600 veh/h, seed 4: a hard stop that fitted the
gap exactly carried the car's nose 1 m into the zone, where a crossing car hit it."""
_STOP_SLACK_M = 0.5  # a stop behind a car ahead keeps this more than the follow distance
_VC_GRID = 24
_VC_ROUNDS = 3
_COARSE_STEP_S = 0.5


@dataclass(frozen=True, slots=True, eq=False)
class SpeedPlan:
    """Body of a coordinated path: points (M, 3) x, y, t and target speeds (M,) [m/s].

    ``kind`` says how it was made (``stop``, ``fast``, ``slot``, ``slot_stop``,
    ``slot_fallback``); ``entry_time`` is the planned zone entry [s] (``inf``
    when the car does not reach the zone on this path).
    """

    points: FloatArray
    speeds: FloatArray
    kind: str
    entry_time: float = math.inf
    short: bool = False
    """A stop whose body stays out of the zone: its front ``stop_gap_m`` before it, or
    closer when the brakes no longer allow the whole gap."""
    reserved: FloatArray | None = None
    """Points (M, 3) to reserve instead of ``points``: where the car will be, when that is
    further on than where it is told to stop (a stop that cannot stay out of the zone,
    ``REACTION_S``; found by the demand experiment, slot, 400 veh/h, seed 3: a stop
    reserved 0.7 m short of the zone ended in it, and a crossing car, planned through
    the empty zone, hit it)."""


@dataclass(frozen=True, slots=True, eq=False)
class _Track:
    """An autonomous path reduced to distinct positions, with arc lengths and own speeds,
    and the car's limits (its own, or the RSU's defaults)."""

    xy: FloatArray  # (M, 2)
    s: FloatArray  # (M,) arc length [m]
    d: FloatArray  # (M,) segment length ending at each point [m]
    v_ap: FloatArray  # (M,) the autonomous path's own speed on each segment [m/s]
    t0: float
    v0: float
    t_end: float  # latest time the plan must cover [s]
    limits: VehicleLimits
    length: float  # [m]
    width: float  # [m]
    v_cap: FloatArray  # (M,) v_max, lowered in curves to sqrt(lat_accel * r) [m/s]

    @property
    def v_max(self) -> float:
        return self.limits.v_max

    @property
    def accel(self) -> float:
        return self.limits.accel

    @property
    def decel(self) -> float:
        return self.limits.decel


def _track(path: VehiclePath, limits: VehicleLimits, now: float, t_free: float) -> _Track:
    v_max = limits.v_max
    pts = np.asarray(path.points, dtype=np.float64)
    if pts.shape[0] == 0:
        pts = np.array([[path.x, path.y, path.header.time_s]], dtype=np.float64)
    d_all = paths.segment_lengths(pts)
    keep = d_all > _SAME_POINT_M
    keep[0] = True
    ends_stopped = paths.ends_at_rest(pts)
    kept = pts[keep]
    d = paths.segment_lengths(kept)
    s = np.cumsum(d)
    xy = kept[:, :2].copy()
    v_cap = paths.curve_caps(xy, s, limits.lat_accel, v_max)
    v_ap = np.minimum(np.maximum(paths.segment_speeds(kept, float(path.speed)), 0.0), v_cap)
    if ends_stopped:
        v_ap[-1] = 0.0
    t0 = float(pts[0, 2])
    t_end = max(float(pts[-1, 2]), now + t_free, t0 + t_free)
    return _Track(
        xy=xy,
        s=s,
        d=d,
        v_ap=v_ap,
        t0=t0,
        v0=max(0.0, float(path.speed)),
        t_end=t_end,
        limits=limits,
        length=float(path.length),
        width=float(path.width),
        v_cap=v_cap,
    )


def _accel_limited(w: FloatArray, s: FloatArray, accel: float) -> FloatArray:
    """Squared speeds ``w`` (along the last axis, at arc lengths ``s``) lowered where the
    car cannot reach them accelerating at ``accel`` from the points before:
    ``min over j <= i of w[j] + 2 accel (s_i - s_j)``, vectorised."""
    ramp = 2.0 * accel * s
    out: FloatArray = np.minimum.accumulate(w - ramp, axis=-1) + ramp
    return out


def _segment_times(d: FloatArray, v: FloatArray) -> FloatArray:
    """Time spent on each segment (ending at each point) at the mean of its end speeds."""
    dt = np.zeros(d.shape[0], dtype=np.float64)
    if d.shape[0] > 1:
        mean = 0.5 * (v[:-1] + v[1:])
        with np.errstate(divide="ignore", invalid="ignore"):
            dt[1:] = np.where(d[1:] <= 0.0, 0.0, np.where(mean > 0.0, d[1:] / mean, np.inf))
    return dt


def _near_lane(
    vehicle: str,
    tr: _Track,
    now: float,
    table: ReservationTable,
    exclude: Collection[str],
    *,
    both_ends: bool,
) -> list[tuple[Entry, float]]:
    """The live entries (but this car's and ``exclude``) whose path starts (and, with
    ``both_ends``, ends) near enough to this car's path to be in its lane, each with
    that lane reach [m] (half both widths plus ``LANE_SLACK_M``), in the table's order:
    candidates for the exact projections of the lane searches."""
    if tr.xy.shape[0] < 2:
        return []
    names, ends, widths = table.path_ends(vehicle, now, exclude)
    if not names:
        return []
    box = paths.bounds(tr.xy)
    lane = 0.5 * (tr.width + widths) + LANE_SLACK_M
    # widened by the ends' rounding (sqrt(2) x ENDS_ROUNDING x the larger coordinate, at most)
    slack = 2.0 * ENDS_ROUNDING * np.abs(ends)
    far = paths.beyond(box, ends[:, 0], ends[:, 1], lane + slack[:, 0] + slack[:, 1])
    if both_ends:
        far |= paths.beyond(box, ends[:, 2], ends[:, 3], lane + slack[:, 2] + slack[:, 3])
    out: list[tuple[Entry, float]] = []
    for k in np.flatnonzero(~far).tolist():
        entry = table.get(names[k])
        if entry is not None:
            out.append((entry, float(lane[k])))
    return out


def _holds(x: float, y: float, t_from: float, t_until: float, step: float) -> FloatArray:
    """Points holding (x, y) after ``t_from`` up to ``t_until``, at most ``step`` apart."""
    span = t_until - t_from
    if span <= 0.0:
        return np.empty((0, 3), dtype=np.float64)
    count = min(_MAX_HOLDS, max(1, math.ceil(span / step)))
    t = t_from + span * np.arange(1, count + 1, dtype=np.float64) / count
    return np.column_stack([np.full(count, x), np.full(count, y), t])


def _finish(
    xy: FloatArray,
    d: FloatArray,
    v: FloatArray,
    targets: FloatArray,
    t_start: float,
    t_end: float,
    hold_step: float,
) -> tuple[FloatArray, FloatArray]:
    """Points and target speeds for a profile ``v`` (speed the car has at each point).

    Points after the first one the car cannot reach are dropped; a car that ends
    at rest holds its last point until ``t_end``.
    """
    dt = _segment_times(d, v)
    t = t_start + np.cumsum(dt)
    reach = np.isfinite(t)
    m = int(np.argmin(reach)) if not reach.all() else t.shape[0]
    pts = np.column_stack([xy[:m], t[:m]])
    tg = targets[:m]
    if m < t.shape[0] or v[m - 1] <= 0.0:
        hold = _holds(float(pts[-1, 0]), float(pts[-1, 1]), float(pts[-1, 2]), t_end, hold_step)
        pts = np.vstack([pts, hold])
        tg = np.concatenate([tg, np.zeros(hold.shape[0])])
    return pts, tg


def _envelope(d: FloatArray, cap: FloatArray, decel: float) -> FloatArray:
    """Squared speed limit at each point from the caps there and ahead, braking at ``decel``.

    ``env[i] = min over j >= i of cap[j]^2 + 2 decel (s_j - s_i)``: a reverse
    cumulative minimum, vectorised.
    """
    s = np.cumsum(d)
    key = cap * cap + 2.0 * decel * s
    env: FloatArray = np.minimum.accumulate(key[::-1])[::-1] - 2.0 * decel * s
    return np.maximum(env, 0.0)


def _kinematic(d: FloatArray, cap: FloatArray, v0: float, accel: float, decel: float) -> FloatArray:
    """Speed at each point: as fast as ``cap`` allows, within the accel/decel limits.

    The car brakes at ``decel`` ahead of a lower cap; starting above the caps, it
    brakes at ``decel`` until it is under them (it cannot do better comfortably).
    """
    n = d.shape[0]
    v = np.empty(n, dtype=np.float64)
    if n == 0:
        return v
    env = _envelope(d, cap, decel).tolist()
    dl = d.tolist()
    cur = v0 * v0
    v[0] = v0
    for i in range(1, n):
        hi = cur + 2.0 * accel * dl[i]
        lo = cur - 2.0 * decel * dl[i]
        cur = max(lo, min(env[i], hi), 0.0)
        v[i] = math.sqrt(cur)
    return v


class VelocityManager:
    """Computes coordinated paths for one RSU's configuration (pure)."""

    def __init__(self, config: RsuConfig) -> None:
        self.config = config
        self.policy = Policy(config.policy)
        self.zone = paths.ConvexZone.of(config.conflict_zone)
        # the last track's front reach: one plan asks for it up to three times (issue 14)
        self._reach_of: tuple[_Track, float | None] | None = None
        # a car that declares no limits is planned with the scenario's [params]
        self.default_limits = VehicleLimits(
            config.v_max_mps, config.accel_mps2, config.decel_comfort_mps2, config.lat_accel_mps2
        )

    # -- public ---------------------------------------------------------------------------

    def plan(
        self,
        vehicle: str,
        path: VehiclePath,
        mode: Mode,
        now: float,
        table: ReservationTable,
        exclude: Collection[str] = (),
        *,
        firm: bool = False,
        reaction_s: float = REACTION_S,
        admissible: Callable[[FloatArray], bool] | None = None,
    ) -> SpeedPlan:
        """Coordinated path body for ``vehicle`` in ``mode`` from its autonomous ``path``,
        with the limits the path declares (else the configuration's). ``firm``: the car
        was last told to stop short of the zone (``SpeedPlan.short``), and keeps that
        stop braking up to ``FIRM_STOP_FACTOR``. ``reaction_s`` [s]: how long the car still
        drives on before its brakes bite if told to stop (``stop_limit``): ``REACTION_S``
        for a stop that is news to it, less for one it was told ``REACTION_S`` ago.
        ``admissible``: a further test a slot path (points (M, 3)) must pass besides the
        table's, e.g. the RSU's crossing order of committed cars."""
        cfg = self.config
        track = _track(path, self.limits_of(path), now, cfg.t_free_s)
        if mode == Mode.C_FAST:
            return self.behind_leaders(vehicle, track, self._fast(track), now, table, exclude)
        if mode == Mode.C_SLOW:
            kind = "stop"
            if self.policy == Policy.SLOT:
                slot = self._slot(vehicle, track, now, table, exclude, admissible)
                if slot is not None:
                    return slot
                kind = "slot_fallback"
            return self._paper_stop(vehicle, track, now, table, exclude, firm, reaction_s, kind)
        raise ValueError(f"no coordinated path for mode {mode!r}")

    def stop(
        self,
        vehicle: str,
        path: VehiclePath,
        now: float,
        table: ReservationTable,
        *,
        reaction_s: float = REACTION_S,
    ) -> SpeedPlan:
        """The paper's ``C_SLOW`` stop for ``vehicle`` on its autonomous ``path``, under
        either policy: what telling it to yield now would leave it doing (the RSU weighs
        that before choosing which of two committed cars yields)."""
        track = _track(path, self.limits_of(path), now, self.config.t_free_s)
        return self._paper_stop(vehicle, track, now, table, (), False, reaction_s, "stop")

    def _paper_stop(
        self,
        vehicle: str,
        track: _Track,
        now: float,
        table: ReservationTable,
        exclude: Collection[str],
        firm: bool,
        reaction_s: float,
        kind: str,
    ) -> SpeedPlan:
        """The paper's stop on ``track``, within :meth:`stop_limit`, reserved where the car
        will stand after ``reaction_s``."""
        factor = FIRM_STOP_FACTOR if firm else HARD_STOP_FACTOR
        lag = track.v0 * max(reaction_s, 0.0)
        lane = self.lane_limit(vehicle, track, now, table, exclude)  # the same for both
        limit = self.stop_limit(vehicle, track, now, table, exclude, factor, lag, lane=lane)
        stop = self._stop(track, kind, limit, lag)
        if lag > 0.0 and not stop.short:
            # told to stop as short as it can, it still drives on ``lag`` before its
            # brakes bite: reserve where it will stand, not where it is told to
            late = self.stop_limit(vehicle, track, now, table, exclude, factor, lag, lag, lane=lane)
            if late > limit + _SAME_POINT_M:
                reserved = self._stop(track, kind, late, lag).points
                return replace(stop, reserved=reserved)
        return stop

    def front_reach(self, tr: _Track) -> float | None:
        """Arc length [m] where the car's centre stands when its front reaches the zone
        (its path continued straight past its end: a path that stops just before the zone
        may still hold the body's front in it); None when its front never reaches the zone
        or is already in it."""
        memo = self._reach_of
        if memo is not None and memo[0] is tr:  # a track is frozen, the zone fixed
            return memo[1]
        half = 0.5 * tr.length
        s_zone = paths.zone_entry_s(tr.xy, tr.s, self.zone, half)
        reach = None if s_zone is None else s_zone - half
        if reach is not None and not reach > 0.0:
            reach = None
        self._reach_of = (tr, reach)
        return reach

    def rests_in_zone(self, tr: _Track) -> bool:
        """The autonomous path ends at rest with the car's body in the zone (its own
        planner stops it there, e.g. behind a car still in the box): no retiming of it
        may enter the zone ("don't block the box", ``paths.body_in_zone``)."""
        if tr.xy.shape[0] < 2 or tr.v_ap[-1] > 0.0:
            return False
        return paths.body_in_zone(tr.xy, self.zone, tr.length, tr.width, 0.0)

    def limits_of(self, path: VehiclePath) -> VehicleLimits:
        """The limits to plan ``path``'s car with: its declared ones, else the RSU's."""
        if path.limits is not None:
            return path.limits
        return self.default_limits

    # -- paper ----------------------------------------------------------------------------

    def _leaders(
        self,
        vehicle: str,
        tr: _Track,
        now: float,
        table: ReservationTable,
        exclude: Collection[str],
    ) -> list[tuple[FloatArray, FloatArray, float]]:
        """The cars ahead in this car's lane: per car, the times (K,) [s] and arc lengths
        (K,) [m, along this car's path, non-decreasing] of its points while in the lane,
        and whether it is still in the lane at its path's end (1.0) or leaves it (0.0)."""
        out: list[tuple[FloatArray, FloatArray, float]] = []
        if tr.xy.shape[0] < 2:
            return out
        for entry, lane in _near_lane(vehicle, tr, now, table, exclude, both_ends=False):
            p0 = entry.points[0]
            first = paths.project(tr.xy, float(p0[0]), float(p0[1]))
            if first[1] > lane or first[0] <= 0.0:
                continue
            pts = entry.points
            s_all, off, _ = paths.project_many(tr.xy, pts)
            on = off <= lane
            stay = int(np.argmin(on)) if not on.all() else pts.shape[0]
            s_l = np.maximum.accumulate(s_all[:stay])
            out.append((pts[:stay, 2].copy(), s_l, 1.0 if stay == pts.shape[0] else 0.0))
        return out

    def behind_leaders(
        self,
        vehicle: str,
        tr: _Track,
        plan: SpeedPlan,
        now: float,
        table: ReservationTable,
        exclude: Collection[str] = (),
    ) -> SpeedPlan:
        """``plan`` retimed so that the car passes every point of its path a headway (plus
        the release margin) after each car ahead in its lane has passed ``d_margin``
        further on, and the follow window after it has passed a follow distance on: a
        ``C_FAST`` car follows the car ahead instead of catching it (issue 12). Where a
        car ahead ends its path in the lane, this car holds a follow distance behind."""
        leaders = self._leaders(vehicle, tr, now, table, exclude)
        if not leaders:
            return plan
        cfg = self.config
        pts = plan.points
        s_me = paths.arc_length(pts)
        t_new = pts[:, 2].copy()
        for t_l, s_l, stays in leaders:
            if t_l.shape[0] == 0:
                continue
            end = float(s_l[-1])
            f = follow_distance(tr.length, tr.length, table.follow_gap_m) + cfg.release_margin_m
            rules = (
                (cfg.d_margin_m + cfg.release_margin_m, cfg.headway_s + cfg.release_margin_s),
                (f, table.follow_window_s + cfg.release_margin_s),
            )
            for dist, gap_t in rules:
                target = s_me + dist
                when = np.interp(target, s_l, t_l, left=-math.inf, right=math.inf)
                if stays == 0.0:
                    when = np.where(target > end, float(t_l[-1]), when)
                when = np.where(target < float(s_l[0]), -math.inf, when)
                t_new = np.maximum(t_new, when + gap_t)
        t_new = np.maximum.accumulate(t_new)
        if np.array_equal(t_new, pts[:, 2]):
            return plan
        ok = np.isfinite(t_new)
        m = int(np.argmin(ok)) if not ok.all() else t_new.shape[0]
        if m == 0:
            return plan
        out = np.column_stack([pts[:m, :2], t_new[:m]])
        speeds = np.minimum(plan.speeds[:m], paths.segment_speeds(out, tr.v0))
        if m < pts.shape[0]:
            hold = _holds(
                float(out[-1, 0]), float(out[-1, 1]), float(out[-1, 2]), tr.t_end, cfg.hold_step_s
            )
            out = np.vstack([out, hold])
            speeds = np.concatenate([speeds[:-1], [0.0], np.zeros(hold.shape[0])])
        entry = paths.zone_entry_time(out, self.zone)
        return SpeedPlan(out, speeds, plan.kind, entry)

    def stop_limit(
        self,
        vehicle: str,
        tr: _Track,
        now: float,
        table: ReservationTable,
        exclude: Collection[str] = (),
        factor: float = HARD_STOP_FACTOR,
        lag: float = 0.0,
        overrun: float = 0.0,
        *,
        lane: float | None = None,
    ) -> float:
        """How far along its path [m] a stopping car may go (issue 12, cause 5): short
        of the zone (its front ``stop_gap_m`` before it, or as far before it as the brakes
        allow, :meth:`front_reach`) when braking
        at up to ``factor`` times its comfortable deceleration does it (a comfortable
        stop in the zone blocks the crossing it was stopped for), and where braking at
        ``FIRM_STOP_FACTOR`` stops it when even that cannot (out of the zone if the brakes
        allow, else into it as little as they can); to its
        autonomous path's own end when that ends at rest (its planner stops there, e.g.
        behind a car it senses), and to a follow distance behind where every car ahead
        of it in its lane (in the table) ends its path; ``inf`` for no limit. ``lag`` [m]:
        how far the car drives on before it brakes (``REACTION_S`` at its speed, for a stop
        that is news to it): a stop short of the zone is one with that travel added.
        ``overrun`` [m]: how much further a stop that cannot stay out of the zone goes
        (``lag`` for where the car will stand, :meth:`plan`). ``lane``: the
        :meth:`lane_limit` of these arguments when the caller has it already."""
        limit = float(tr.s[-1]) if tr.v_ap[-1] <= 0.0 else math.inf
        reach = self.front_reach(tr)
        if reach is not None:
            hard = tr.v0 * tr.v0 / (2.0 * factor * tr.decel)
            if hard <= reach - lag:
                # short of the zone, braking up to factor x comfortably: the whole stop gap
                # short when that fits, else as short as the brakes allow (no cliff: a car
                # 3 cm past the gap's reach was stopped comfortably in the middle of the
                # crossing; demand experiment, paper, 400 veh/h, seed 0, final stop on)
                # (the plan's stop point ``lag`` short of the reach: the car drives on
                # that far before braking)
                limit = min(limit, max(reach - max(self.config.stop_gap_m, lag), hard))
            else:
                # not even so: as short as the emergency brakes allow, not a comfortable
                # stop through the crossing it yields to (random search of the invariant,
                # paper: a C_FAST car 21 m from the zone at 13.9 m/s, told to yield to a
                # turning car that could not stop, got a comfortable stop 48 m long through
                # the turner's path; braking at 5 m/s^2 it stops 1.7 m before the zone)
                firm = tr.v0 * tr.v0 / (2.0 * FIRM_STOP_FACTOR * tr.decel)
                limit = min(limit, firm + overrun)
        if lane is None:
            lane = self.lane_limit(vehicle, tr, now, table, exclude)
        return min(limit, lane)

    def lane_limit(
        self,
        vehicle: str,
        tr: _Track,
        now: float,
        table: ReservationTable,
        exclude: Collection[str] = (),
    ) -> float:
        """:meth:`stop_limit`'s part that depends on the cars ahead only [m along the
        path]: a follow distance behind where every car ahead of it in its lane (in the
        table) ends its path; ``inf`` for none (issue 14: asked once per paper stop)."""
        limit = math.inf
        if tr.xy.shape[0] < 2:
            return limit
        near = _near_lane(vehicle, tr, now, table, exclude, both_ends=True)
        if not near:
            return limit
        # first and last points of every car near the lane projected at once (issue 14)
        ends = np.array([[e.points[0, :2], e.points[-1, :2]] for e, _ in near]).reshape(-1, 2)
        s_end, off_end, i_end = paths.project_many(tr.xy, ends)
        mine_all = paths.headings_at(tr.xy, i_end[1::2])
        for k, (entry, lane) in enumerate(near):
            first = (float(s_end[2 * k]), float(off_end[2 * k]))
            last = (float(s_end[2 * k + 1]), float(off_end[2 * k + 1]))
            if first[1] > lane or last[1] > lane or first[0] <= 0.0:
                continue  # not in this lane, or not ahead
            theirs = paths.heading_of(entry.points, entry.points.shape[0] - 1)
            mine = float(mine_all[k])
            crossing = theirs is not None and not math.isnan(mine)
            if crossing and math.cos(theirs - mine) < math.cos(SAME_WAY_RAD):  # type: ignore[operator]
                continue  # it ends crossing or leaving this lane
            gap = follow_distance(tr.length, entry.length, table.follow_gap_m) + _STOP_SLACK_M
            limit = min(limit, last[0] - gap)
        return limit

    def _stop(
        self, tr: _Track, kind: str = "stop", limit: float = math.inf, lag: float = 0.0
    ) -> SpeedPlan:
        """Brake comfortably from the current speed to the exact stop point, then hold;
        harder when the stop must come sooner, at ``limit`` [m along the path] (a car
        ahead, or the autonomous path's own stop)."""
        cfg = self.config
        b = tr.decel
        v0 = tr.v0
        s_stop = v0 * v0 / (2.0 * b)
        if s_stop > limit:
            s_stop = max(limit, 0.0)
            b = v0 * v0 / (2.0 * s_stop) if s_stop > 1e-3 else math.inf
        if math.isinf(b):
            v = np.zeros_like(tr.s)  # stop where it is: nothing left to brake on
            v[0] = v0
        else:
            v = np.sqrt(np.maximum(v0 * v0 - 2.0 * b * tr.s, 0.0))
        k = max(1, int(np.searchsorted(tr.s, s_stop, side="right")))  # points 0..k-1 reached
        xy, d, vk = tr.xy[:k], tr.d[:k], v[:k]
        if k < tr.s.shape[0] and s_stop > tr.s[k - 1] + 1e-3:
            frac = (s_stop - tr.s[k - 1]) / tr.d[k]
            xy = np.vstack([xy, tr.xy[k - 1] + frac * (tr.xy[k] - tr.xy[k - 1])])
            d = np.append(d, s_stop - tr.s[k - 1])
            vk = np.append(vk, 0.0)
        t = tr.t0 + np.cumsum(_segment_times(d, vk))
        pts = np.column_stack([xy, t])
        hold = _holds(float(xy[-1, 0]), float(xy[-1, 1]), float(t[-1]), tr.t_end, cfg.hold_step_s)
        pts = np.vstack([pts, hold])
        reach = self.front_reach(tr)
        short = reach is not None and s_stop + lag <= reach + 1e-6
        return SpeedPlan(pts, np.zeros(pts.shape[0]), kind, short=short)

    def _fast_caps(self, tr: _Track) -> tuple[FloatArray, int | None]:
        """The car's ``v_max`` (lower in curves) up to the zone exit plus one car length,
        then the path's own speeds."""
        cap = tr.v_cap.copy()
        span = paths.zone_span(tr.xy, self.zone)
        if span is not None and span[1] < tr.s.shape[0]:
            after = tr.s > tr.s[span[1]] + tr.length
            cap[after] = tr.v_ap[after]
        if tr.v_ap[-1] <= 0.0:
            cap[-1] = 0.0
        return cap, (None if span is None else span[0])

    def _fast(self, tr: _Track) -> SpeedPlan:
        cfg = self.config
        cap, entry = self._fast_caps(tr)
        v = _kinematic(tr.d, cap, tr.v0, tr.accel, tr.decel)
        pts, speeds = _finish(tr.xy, tr.d, v, cap, tr.t0, tr.t_end, cfg.hold_step_s)
        reached = entry is not None and entry < pts.shape[0]
        entry_time = float(pts[entry, 2]) if reached and entry is not None else math.inf
        return SpeedPlan(pts, speeds, "fast", entry_time)

    # -- slot -----------------------------------------------------------------------------

    def _slot(
        self,
        vehicle: str,
        tr: _Track,
        now: float,
        table: ReservationTable,
        exclude: Collection[str],
        admissible: Callable[[FloatArray], bool] | None = None,
    ) -> SpeedPlan | None:
        """The slot plan, or None when there is none (the caller then stops the car)."""
        cfg = self.config
        cap, entry = self._fast_caps(tr)
        if entry is None or entry == 0 or self.rests_in_zone(tr):
            # retiming keeps the path's positions: a path that stops in the box has no slot
            return None
        env = _envelope(tr.d, cap, tr.decel)
        fastest = self._cruise(tr, entry, env, tr.v_max)
        t_fast = tr.t0 + float(np.sum(_segment_times(tr.d[: entry + 1], fastest[: entry + 1])))
        step = cfg.slot_step_s
        coarse = max(1, round(_COARSE_STEP_S / step))  # fine steps per coarse step
        count = math.floor(cfg.t_free_s / step + 1e-9)
        culprit: list[str] = []
        impossible = False

        def attempt(i: int) -> SpeedPlan | None:
            """The plan entering ``i`` steps late if it is conflict-free, else None."""
            nonlocal impossible
            plan = self._meet(tr, entry, env, cap, t_fast + i * step)
            if plan is None:
                impossible = True  # it can no longer wait that long: nor any longer
                return None
            # with the release margins as clearance (issue 12, cause 6): a slot at the
            # exact edge of a conflict is lost again at the next re-plan
            hit = table.first_conflict(
                vehicle,
                plan.points,
                now,
                cfg.t_free_s,
                exclude,
                culprit,
                (tr.length, tr.width),
                cfg.release_margin_m,
                cfg.release_margin_s,
            )
            if hit is None:
                return plan if admissible is None or admissible(plan.points) else None
            culprit[:] = [hit.vehicle]
            return None

        # Coarse to fine: a gap a yielding car fits in is wider than the coarse step.
        failed = -1
        for i in range(0, count + 1, coarse):
            found = attempt(i)
            if found is None and not impossible:
                failed = i
                continue
            impossible = False
            for j in range(failed + 1, i):  # the fine steps since the last failure
                earlier = attempt(j)
                if earlier is not None or impossible:
                    return earlier
            if found is not None:
                return found
            break
        return None

    def _cruise(self, tr: _Track, entry: int, env: FloatArray, v_c: float) -> FloatArray:
        """Speeds: reach ``v_c`` (braking or accelerating), hold it to the zone entry, then go;
        never above the squared-speed envelope ``env`` (curves, the caps after the zone)."""
        s = tr.s
        v0 = tr.v0
        if v_c <= v0:
            w = np.maximum(np.maximum(v0 * v0 - 2.0 * tr.decel * s, 0.0), v_c * v_c)
        else:
            w = np.minimum(v0 * v0 + 2.0 * tr.accel * s, v_c * v_c)
        w = np.where(np.arange(s.shape[0]) <= entry, np.minimum(w, env), env)
        w = _accel_limited(w, s, tr.accel)
        return np.sqrt(np.maximum(w, 0.0))

    def _entry_times(self, tr: _Track, entry: int, env: FloatArray, v_cs: FloatArray) -> FloatArray:
        """Time to the zone entry for each cruise speed in ``v_cs`` (vectorised; the
        profiles of :meth:`_cruise` up to the entry)."""
        s1 = tr.s[: entry + 1]
        s = s1[None, :]
        d = tr.d[: entry + 1][None, :]
        v0 = tr.v0
        vc = v_cs[:, None]
        dec = np.maximum(np.maximum(v0 * v0 - 2.0 * tr.decel * s, 0.0), vc * vc)
        acc = np.minimum(v0 * v0 + 2.0 * tr.accel * s, vc * vc)
        w = np.minimum(np.where(vc <= v0, dec, acc), env[None, : entry + 1])
        v = np.sqrt(np.maximum(_accel_limited(w, s1, tr.accel), 0.0))
        mean = 0.5 * (v[:, :-1] + v[:, 1:])
        with np.errstate(divide="ignore", invalid="ignore"):
            dt = np.where(d[:, 1:] <= 0.0, 0.0, d[:, 1:] / mean)
        times: FloatArray = dt.sum(axis=1)
        return times

    def _meet(
        self,
        tr: _Track,
        entry: int,
        env: FloatArray,
        cap: FloatArray,
        target: float,
    ) -> SpeedPlan | None:
        """Fastest profile entering the zone no earlier than ``target``; None if impossible."""
        cfg = self.config
        need = target - tr.t0
        hi = tr.v_max
        lo = min(cfg.slot_min_speed_mps, hi)  # a car slower than that still has a slot
        t_lo, t_hi = self._entry_times(tr, entry, env, np.array([lo, hi]))
        if t_hi >= need - 1e-9:
            v = self._cruise(tr, entry, env, hi)
            return self._plan_from(tr, v, cap, entry, tr.t0, "slot")
        if t_lo >= need:
            for _ in range(_VC_ROUNDS):
                grid = np.linspace(lo, hi, _VC_GRID)
                times = self._entry_times(tr, entry, env, grid)
                ok = np.flatnonzero(times >= need)  # times decrease with the speed
                best = int(ok[-1])
                lo = float(grid[best])
                hi = float(grid[min(best + 1, grid.shape[0] - 1)])
            v = self._cruise(tr, entry, env, lo)
            return self._plan_from(tr, v, cap, entry, tr.t0, "slot")
        return self._stop_and_go(tr, entry, env, cap, target)

    def _plan_from(
        self, tr: _Track, v: FloatArray, targets: FloatArray, entry: int, t0: float, kind: str
    ) -> SpeedPlan:
        cfg = self.config
        # target speeds: the profile to the zone entry, the caps after; never above the
        # curve caps (the car's current speed may be, at the first point)
        speeds = np.minimum(np.where(np.arange(v.shape[0]) <= entry, v, targets), tr.v_cap)
        pts, sp = _finish(tr.xy, tr.d, v, speeds, t0, tr.t_end, cfg.hold_step_s)
        entry_time = float(pts[entry, 2]) if entry < pts.shape[0] else math.inf
        return SpeedPlan(pts, sp, kind, entry_time)

    def _stop_and_go(
        self,
        tr: _Track,
        entry: int,
        env: FloatArray,
        cap: FloatArray,
        target: float,
    ) -> SpeedPlan | None:
        """Stop ``stop_gap_m`` before the zone, wait, start so as to enter at ``target``.

        None when the car can no longer stop comfortably before the zone.
        """
        cfg = self.config
        a, b = tr.accel, tr.decel
        s = tr.s
        k = int(np.searchsorted(s, s[entry] - (tr.length / 2.0 + cfg.stop_gap_m), side="right")) - 1
        if k < 0 or tr.v0 * tr.v0 > 2.0 * b * s[k] + 1e-6:
            return None
        idx = np.arange(s.shape[0])
        w_before = np.minimum(tr.v0 * tr.v0 + 2.0 * a * s, 2.0 * b * np.maximum(s[k] - s, 0.0))
        w_after = 2.0 * a * np.maximum(s - s[k], 0.0)
        w = np.minimum(np.where(idx <= k, w_before, w_after), env)
        w[0] = tr.v0 * tr.v0
        v = np.sqrt(np.maximum(_accel_limited(w, s, a), 0.0))
        v[0] = tr.v0
        v[k] = 0.0
        dt = _segment_times(tr.d, v)
        if not np.all(np.isfinite(dt)):
            return None
        t_before = tr.t0 + np.cumsum(dt[: k + 1])
        t_stop = float(t_before[-1])
        t_go = max(t_stop, target - float(dt[k + 1 : entry + 1].sum()))
        hold = _holds(float(tr.xy[k, 0]), float(tr.xy[k, 1]), t_stop, t_go, cfg.hold_step_s)
        t_after = t_go + np.cumsum(dt[k + 1 :])
        targets = np.minimum(np.where(idx <= entry, v, cap), tr.v_cap)
        pts = np.vstack(
            [
                np.column_stack([tr.xy[: k + 1], t_before]),
                hold,
                np.column_stack([tr.xy[k + 1 :], t_after]),
            ]
        )
        speeds = np.concatenate([targets[: k + 1], np.zeros(hold.shape[0]), targets[k + 1 :]])
        if k + 1 < s.shape[0] and v[-1] <= 0.0:
            tail = _holds(
                float(pts[-1, 0]), float(pts[-1, 1]), float(pts[-1, 2]), tr.t_end, cfg.hold_step_s
            )
            pts = np.vstack([pts, tail])
            speeds = np.concatenate([speeds, np.zeros(tail.shape[0])])
        entry_time = t_go + float(dt[k + 1 : entry + 1].sum())
        return SpeedPlan(pts, speeds, "slot_stop", entry_time)
