"""Scenario files: the map, the cars and the run parameters, validated before anything runs.

A scenario is a TOML file (format in ``scenarios/README.md``) parsed into pydantic
models (:class:`ScenarioFile`), then compiled into a :class:`Scenario`: polylines for
lanes and routes, conflict-zone crossings per route, the crossing lanes the
blind-corner caution must watch, and packed building polygons for occlusion.

Every problem is reported as one :class:`ScenarioError` naming the field path
(``vehicles[1].route``) and the reason; unknown keys are refused.

Conventions (see ``geometry``): metres, seconds, radians; every position is a car's
geometric centre; a route's ``s`` is the arc length of the centre along the route.
"""

from __future__ import annotations

import math
import tomllib
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Strict,
    StringConstraints,
    Tag,
    ValidationError,
    field_validator,
    model_validator,
)

from services.model.geometry import (
    FloatArray,
    PolygonSet,
    Polyline,
    fillet_polyline,
    is_convex,
    min_point_distance,
    polygon_contains,
    visible_mask,
    wrap_angle,
)
from services.model.kinematics import Limits

__all__ = [
    "DEFAULT_LENGTH_M",
    "DEFAULT_WIDTH_M",
    "LANE_MATCH_HEADING_RAD",
    "LANE_MATCH_LATERAL_M",
    "ApproachLane",
    "BuildingSpec",
    "Crossing",
    "DynamicsOverrides",
    "IntersectionSpec",
    "LaneSpec",
    "MetricsSpec",
    "Params",
    "RouteSpec",
    "RsuSpec",
    "Scenario",
    "ScenarioError",
    "ScenarioFile",
    "ScenarioInfo",
    "UniformStart",
    "VehicleModel",
    "VehicleSpec",
    "limits_from_params",
    "load_scenario",
    "parse_scenario",
]

DEFAULT_LENGTH_M = 4.5
"""Car length when a vehicle does not give one (m)."""
DEFAULT_WIDTH_M = 1.8
"""Car width when a vehicle does not give one (m)."""

LANE_MATCH_LATERAL_M = 2.5
"""``lane_of``: a sensed car belongs to a lane only within this lateral offset (m)."""
LANE_MATCH_HEADING_RAD = math.radians(45.0)
"""``lane_of``: ... and only if its heading matches the lane's within this angle."""

SAME_APPROACH_RAD = math.radians(45.0)
"""``crossing_lanes``: a lane entering the zone within this angle of the route's own
entry heading comes from the same approach (it is followed, not crossed)."""

SAMPLE_STEP_M = 0.25
"""Sampling step for comparing two paths inside a conflict zone (m)."""

ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"


class ScenarioError(ValueError):
    """A scenario file is unusable. ``path`` is the field path (``vehicles[1].route``,
    empty for the whole file), ``reason`` what is wrong, ``source`` the file."""

    def __init__(self, path: str, reason: str, source: str = "<string>") -> None:
        self.path = path
        self.reason = reason
        self.source = source
        where = f"{source}: {path}" if path else source
        super().__init__(f"{where}: {reason}")


# --------------------------------------------------------------------------- file models

Id = Annotated[str, Strict(), StringConstraints(pattern=ID_PATTERN)]
F = Annotated[float, Strict()]
PosF = Annotated[float, Strict(), Field(gt=0.0)]
NonNegF = Annotated[float, Strict(), Field(ge=0.0)]
PosInt = Annotated[int, Strict(), Field(gt=0)]
Point = tuple[F, F]
Points = Annotated[list[Point], Field(min_length=2)]
PolygonPoints = Annotated[list[Point], Field(min_length=3)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _check_convex(v: list[tuple[float, float]]) -> list[tuple[float, float]]:
    if not is_convex(v):
        raise ValueError("polygon must be convex, simple, with non-zero area")
    return v


class ScenarioInfo(_Model):
    """``[scenario]``: what this is."""

    name: Annotated[str, Strict(), StringConstraints(min_length=1, max_length=100)]
    description: Annotated[str, Strict()] = ""


class Params(_Model):
    """``[params]``: run parameters shared by every actor (DESIGN.md defaults)."""

    v_max_mps: PosF = 50.0 / 3.6
    accel_mps2: PosF = 1.5
    decel_comfort_mps2: PosF = 2.0
    decel_emergency_mps2: PosF = 5.0
    actuator_lag_s: NonNegF = 0.3
    physics_hz: PosInt = 20
    planning_hz: PosInt = 10
    sensor_range_m: PosF = 80.0
    headway_s: NonNegF = 1.0
    d_margin_m: PosF = 2.8
    t_collision_s: PosF = 5.0
    t_free_s: PosF = 10.0
    reservation_expiry_s: PosF = 0.5
    coordinated_timeout_s: PosF = 0.3
    future_path_points: Annotated[int, Strict(), Field(ge=2)] = 120
    max_sim_s: PosF = 120.0
    goal_tolerance_m: PosF = 1.0

    @model_validator(mode="after")
    def _consistent(self) -> Params:
        if self.decel_emergency_mps2 < self.decel_comfort_mps2:
            raise ValueError("decel_emergency_mps2 must be >= decel_comfort_mps2")
        if self.physics_hz % self.planning_hz:
            raise ValueError("physics_hz must be a whole multiple of planning_hz")
        return self

    @property
    def physics_dt_s(self) -> float:
        """Physics step (s)."""
        return 1.0 / self.physics_hz

    @property
    def planning_dt_s(self) -> float:
        """Planning and V2X period (s)."""
        return 1.0 / self.planning_hz


class LaneSpec(_Model):
    """``[[lanes]]``: one lane of a road; driving direction is the point order."""

    id: Id
    points: Points
    width_m: PosF = 3.5
    corner_radius_m: NonNegF = 0.0


class IntersectionSpec(_Model):
    """``[[intersections]]``: a conflict zone and where its stop lines are."""

    id: Id
    center: Point
    conflict_zone: PolygonPoints
    stop_line_offset_m: NonNegF = 5.0

    _convex = field_validator("conflict_zone")(_check_convex)


class BuildingSpec(_Model):
    """``[[buildings]]``: a convex occluder (sight lines cannot cross it)."""

    id: Id
    polygon: PolygonPoints

    _convex = field_validator("polygon")(_check_convex)


class RouteSpec(_Model):
    """``[[routes]]``: the path a car follows, as corner points (optionally rounded)."""

    id: Id
    points: Points
    corner_radius_m: NonNegF = 0.0


class UniformStart(_Model):
    """A start time drawn per trial: ``{uniform = [lo, hi]}`` seconds."""

    uniform: tuple[NonNegF, NonNegF]

    @field_validator("uniform")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError(f"range lower bound {v[0]} exceeds upper bound {v[1]}")
        return v


class DynamicsOverrides(_Model):
    """A vehicle's own limits; a field left out keeps the ``[params]`` value."""

    v_max_mps: PosF | None = None
    accel_mps2: PosF | None = None
    decel_comfort_mps2: PosF | None = None
    decel_emergency_mps2: PosF | None = None
    actuator_lag_s: NonNegF | None = None


def _start_kind(v: Any) -> str | None:
    if isinstance(v, Mapping | UniformStart):
        return "__range"
    if isinstance(v, int | float) and not isinstance(v, bool):
        return "__fixed"
    return None


StartTime = Annotated[
    Annotated[NonNegF, Tag("__fixed")] | Annotated[UniformStart, Tag("__range")],
    Discriminator(
        _start_kind,
        custom_error_type="start_time",
        custom_error_message="must be seconds >= 0 or a table {uniform = [lo, hi]}",
    ),
]


class VehicleSpec(_Model):
    """``[[vehicles]]``: one car. ``goal_m`` None means the route's end."""

    id: Id
    route: Id
    start_time_s: StartTime = 0.0
    start_offset_m: NonNegF = 0.0
    goal_m: PosF | None = None
    length_m: PosF = DEFAULT_LENGTH_M
    width_m: PosF = DEFAULT_WIDTH_M
    dynamics: DynamicsOverrides | None = None


VehicleModel = VehicleSpec
"""Alias of :class:`VehicleSpec`."""


class RsuSpec(_Model):
    """``[[rsus]]``: a roadside unit serving one intersection."""

    id: Id
    intersection: Id
    position: Point
    coverage_m: PosF = 150.0


class MetricsSpec(_Model):
    """``[metrics]``: where the passing-time measurement starts and ends (m)."""

    passing_start_m: NonNegF = 10.0
    passing_end_after_center_m: NonNegF = 100.0


class ScenarioFile(_Model):
    """The whole validated document."""

    scenario: ScenarioInfo
    params: Params = Params()
    lanes: list[LaneSpec] = []
    intersections: list[IntersectionSpec] = []
    buildings: list[BuildingSpec] = []
    routes: Annotated[list[RouteSpec], Field(min_length=1)]
    vehicles: Annotated[list[VehicleSpec], Field(min_length=1)]
    rsus: list[RsuSpec] = []
    metrics: MetricsSpec = MetricsSpec()


# --------------------------------------------------------------------------- compiled view


@dataclass(frozen=True, slots=True)
class Crossing:
    """Where a route (or lane) passes one intersection's conflict zone, arc lengths in m.

    ``s_in``/``s_out``: the centre line enters/leaves the zone. ``s_stop``: the
    *centre* position at which the car's FRONT bumper is on the stop line, i.e.
    ``s_in - stop_line_offset_m - length / 2`` (may be negative when the route starts
    inside the approach). ``center_s``: closest point to the intersection centre.
    """

    intersection: str
    s_in: float
    s_out: float
    s_stop: float
    center_s: float


@dataclass(frozen=True, slots=True)
class ApproachLane:
    """A lane whose traffic crosses (or merges with) a route in a conflict zone.

    ``s_in`` is the lane's arc length at its zone entry: the caution rule samples the
    lane upstream of it to see how much of the crossing road is visible.
    """

    lane: str
    polyline: Polyline
    s_in: float


def _fmt_loc(loc: Sequence[int | str]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part.startswith("__"):
            continue  # union tag, not a field
        else:
            out += f".{part}" if out else part
    return out


def _wrap_validation(err: ValidationError, source: str) -> ScenarioError:
    items = []
    for e in err.errors():
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        elif e["type"] == "string_pattern_mismatch":
            msg = f"{e['input']!r} is not a valid id: use 1 to 32 of A-Z a-z 0-9 _ -"
        elif msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        items.append((_fmt_loc(e["loc"]), msg))
    path, reason = items[0]
    if len(items) > 1:
        reason += "; also " + "; ".join(f"{p or '<file>'}: {r}" for p, r in items[1:])
    return ScenarioError(path, reason, source)


class Scenario:
    """A validated, compiled scenario: the ready-to-use map for the harness, the
    planners and the metrics. Immutable after construction; queries are cached."""

    def __init__(self, spec: ScenarioFile, source: str = "<string>") -> None:
        self.spec = spec
        self.source = source
        self._lanes: dict[str, Polyline] = {}
        self._routes: dict[str, Polyline] = {}
        self._vehicles: dict[str, VehicleSpec] = {}
        self._intersections: dict[str, IntersectionSpec] = {}
        self._rsus: dict[str, RsuSpec] = {}
        self._zones: dict[str, FloatArray] = {}
        self._crossings: dict[tuple[str, str, float], list[Crossing]] = {}
        self._approach: dict[tuple[str, str], list[ApproachLane]] = {}
        self._compile()

    # -- construction -------------------------------------------------------------

    def _err(self, path: str, reason: str) -> ScenarioError:
        return ScenarioError(path, reason, self.source)

    def _unique(self, kind: str, ids: Sequence[str]) -> None:
        seen: dict[str, int] = {}
        for i, ident in enumerate(ids):
            if ident in seen:
                raise self._err(
                    f"{kind}[{i}].id", f"duplicate id {ident!r} (also {kind}[{seen[ident]}])"
                )
            seen[ident] = i

    def _compile(self) -> None:
        sp = self.spec
        for kind, items in (
            ("lanes", sp.lanes),
            ("intersections", sp.intersections),
            ("buildings", sp.buildings),
            ("routes", sp.routes),
            ("vehicles", sp.vehicles),
            ("rsus", sp.rsus),
        ):
            self._unique(kind, [it.id for it in items])
        vids = {v.id for v in sp.vehicles}
        for i, r in enumerate(sp.rsus):
            if r.id in vids:
                raise self._err(f"rsus[{i}].id", f"id {r.id!r} is also a vehicle id")

        self.occluders = PolygonSet.from_polygons(
            [np.array(b.polygon, dtype=np.float64) for b in sp.buildings]
        )
        self._building_arrays = [self._ro(b.polygon) for b in sp.buildings]

        for i, it in enumerate(sp.intersections):
            if not polygon_contains(it.conflict_zone, *it.center):
                raise self._err(f"intersections[{i}].center", "must lie in the conflict_zone")
            self._intersections[it.id] = it
            self._zones[it.id] = self._ro(it.conflict_zone)

        for i, lane in enumerate(sp.lanes):
            self._lanes[lane.id] = self._build_line(
                f"lanes[{i}]", lane.points, lane.corner_radius_m
            )
        for i, rs in enumerate(sp.routes):
            self._routes[rs.id] = self._build_line(f"routes[{i}]", rs.points, rs.corner_radius_m)

        resolved: list[VehicleSpec] = []
        for i, v in enumerate(sp.vehicles):
            if v.route not in self._routes:
                known = ", ".join(sorted(self._routes))
                raise self._err(
                    f"vehicles[{i}].route", f"unknown route {v.route!r} (known: {known})"
                )
            line = self._routes[v.route]
            if v.start_offset_m >= line.length:
                raise self._err(
                    f"vehicles[{i}].start_offset_m",
                    f"{v.start_offset_m} m is not before the route's end ({line.length:.3f} m)",
                )
            goal = line.length if v.goal_m is None else v.goal_m
            if goal > line.length + 1e-6:
                raise self._err(
                    f"vehicles[{i}].goal_m",
                    f"{goal} m is beyond the route's end ({line.length:.3f} m)",
                )
            if goal <= v.start_offset_m:
                raise self._err(f"vehicles[{i}].goal_m", "must be after start_offset_m")
            try:
                limits_from_params(sp.params, v.dynamics)
            except ValueError as exc:
                raise self._err(f"vehicles[{i}].dynamics", str(exc)) from None
            rv = v.model_copy(update={"goal_m": min(goal, line.length)})
            resolved.append(rv)
            self._vehicles[v.id] = rv
        self.vehicles: tuple[VehicleSpec, ...] = tuple(resolved)
        self._pack_lanes()

        for i, r in enumerate(sp.rsus):
            if r.intersection not in self._intersections:
                known = ", ".join(sorted(self._intersections)) or "none"
                raise self._err(
                    f"rsus[{i}].intersection",
                    f"unknown intersection {r.intersection!r} (known: {known})",
                )
            self._rsus[r.id] = r

    def _build_line(
        self, where: str, points: Sequence[tuple[float, float]], radius: float
    ) -> Polyline:
        """A lane or route: corners rounded; it must cross each zone at most once and
        run through no building."""
        try:
            line = Polyline(fillet_polyline(points, radius))
        except ValueError as exc:
            raise self._err(f"{where}.points", str(exc)) from None
        for it in self.spec.intersections:
            if len(line.intervals_in_polygon(self._zones[it.id])) > 1:
                raise self._err(where, f"enters intersection {it.id!r} more than once")
        if len(self.occluders):
            for k in range(len(line.points) - 1):
                p = (float(line.points[k, 0]), float(line.points[k, 1]))
                ok = visible_mask(p, line.points[k + 1 : k + 2], self.occluders)
                if not bool(ok[0]):
                    raise self._err(where, f"segment after point {k} runs through a building")
        return line

    @staticmethod
    def _ro(points: Sequence[tuple[float, float]]) -> FloatArray:
        a = np.array(points, dtype=np.float64)
        a.flags.writeable = False
        return a

    # -- plain lookups ------------------------------------------------------------

    @property
    def name(self) -> str:
        return self.spec.scenario.name

    @property
    def description(self) -> str:
        return self.spec.scenario.description

    @property
    def params(self) -> Params:
        return self.spec.params

    @property
    def metrics(self) -> MetricsSpec:
        return self.spec.metrics

    @property
    def intersections(self) -> tuple[IntersectionSpec, ...]:
        return tuple(self.spec.intersections)

    @property
    def rsus(self) -> tuple[RsuSpec, ...]:
        return tuple(self.spec.rsus)

    @property
    def lane_ids(self) -> tuple[str, ...]:
        return tuple(self._lanes)

    @property
    def route_ids(self) -> tuple[str, ...]:
        return tuple(self._routes)

    @property
    def building_polygons(self) -> list[FloatArray]:
        """Building polygons (read-only (K, 2) arrays), for ``sensors.perceive``.
        ``occluders`` holds the same polygons packed for fast visibility tests."""
        return list(self._building_arrays)

    def vehicle(self, vehicle_id: str) -> VehicleSpec:
        """The vehicle's spec with ``goal_m`` resolved (never None). KeyError if unknown."""
        return self._vehicles[vehicle_id]

    def intersection(self, intersection_id: str) -> IntersectionSpec:
        return self._intersections[intersection_id]

    def rsu(self, rsu_id: str) -> RsuSpec:
        return self._rsus[rsu_id]

    def zone_polygon(self, intersection_id: str) -> FloatArray:
        """The intersection's conflict zone, read-only (K, 2)."""
        return self._zones[intersection_id]

    def route(self, route_id: str) -> Polyline:
        """The route's polyline (corners rounded if asked). KeyError if unknown."""
        return self._routes[route_id]

    def lane(self, lane_id: str) -> Polyline:
        return self._lanes[lane_id]

    def vehicle_route(self, vehicle_id: str) -> Polyline:
        return self._routes[self._vehicles[vehicle_id].route]

    def goal_m(self, vehicle_id: str) -> float:
        """Arc length of the vehicle's goal along its route (m)."""
        g = self._vehicles[vehicle_id].goal_m
        return self.vehicle_route(vehicle_id).length if g is None else g

    def limits(self, vehicle_id: str) -> Limits:
        """Dynamic limits of one vehicle: ``[params]`` with its overrides."""
        return limits_from_params(self.params, self._vehicles[vehicle_id].dynamics)

    # -- crossings ----------------------------------------------------------------

    def _line_crossings(
        self, kind: str, ident: str, line: Polyline, length_m: float
    ) -> list[Crossing]:
        if not (math.isfinite(length_m) and length_m > 0.0):
            raise ValueError(f"length_m must be finite and > 0, got {length_m!r}")
        key = (kind, ident, length_m)
        hit = self._crossings.get(key)
        if hit is not None:
            return list(hit)
        out: list[Crossing] = []
        for it in self.spec.intersections:
            iv = line.interval_in_polygon(self._zones[it.id])
            if iv is None:
                continue
            s_in, s_out = iv
            cs, _ = line.slice(s_in, s_out).project(*it.center)
            out.append(
                Crossing(
                    intersection=it.id,
                    s_in=s_in,
                    s_out=s_out,
                    s_stop=s_in - it.stop_line_offset_m - 0.5 * length_m,
                    center_s=s_in + cs,
                )
            )
        out.sort(key=lambda c: (c.s_in, c.intersection))
        self._crossings[key] = out
        return list(out)

    def crossings(self, route_id: str, length_m: float = DEFAULT_LENGTH_M) -> list[Crossing]:
        """Conflict zones along a route, sorted by ``s_in``. ``s_stop`` depends on the car's
        length: pass it (or use :meth:`vehicle_crossings`)."""
        return self._line_crossings("route", route_id, self._routes[route_id], length_m)

    def vehicle_crossings(self, vehicle_id: str) -> list[Crossing]:
        """:meth:`crossings` of the vehicle's route with its own length."""
        v = self._vehicles[vehicle_id]
        return self.crossings(v.route, v.length_m)

    def lane_crossings(self, lane_id: str, length_m: float = DEFAULT_LENGTH_M) -> list[Crossing]:
        """Conflict zones along a lane, sorted by ``s_in``."""
        return self._line_crossings("lane", lane_id, self._lanes[lane_id], length_m)

    def crossing_lanes(self, route_id: str, intersection_id: str) -> list[ApproachLane]:
        """Lanes whose traffic conflicts with this route in this intersection's zone.

        A lane counts when (1) it enters the zone from another approach: its entry
        heading differs from the route's by more than 45°, so parallel traffic in the
        same direction (the route's own lane) is excluded, and (2) its centre line inside
        the zone comes within ``d_margin_m`` of the route's: crossing traffic and
        merging traffic count; opposing traffic counts only when the route turns
        across it (a left turn). Empty when the route does not cross the zone.
        """
        key = (route_id, intersection_id)
        hit = self._approach.get(key)
        if hit is not None:
            return list(hit)
        route = self._routes[route_id]
        zone = self._zones[intersection_id]
        out: list[ApproachLane] = []
        riv = route.interval_in_polygon(zone)
        if riv is not None:
            r_pts = route.sample(riv[0], riv[1], SAMPLE_STEP_M)
            r_head = route.heading_at(riv[0])
            for lane_id, lane in self._lanes.items():
                liv = lane.interval_in_polygon(zone)
                if liv is None:
                    continue
                if abs(wrap_angle(lane.heading_at(liv[0]) - r_head)) <= SAME_APPROACH_RAD:
                    continue
                l_pts = lane.sample(liv[0], liv[1], SAMPLE_STEP_M)
                if min_point_distance(r_pts, l_pts) < self.params.d_margin_m:
                    out.append(ApproachLane(lane=lane_id, polyline=lane, s_in=liv[0]))
        self._approach[key] = out
        return list(out)

    def _pack_lanes(self) -> None:
        """All lane segments in flat arrays, so ``lane_of`` is one numpy pass."""
        ids = list(self._lanes)
        lines = [self._lanes[i] for i in ids]
        if not lines:
            self._seg_a = np.zeros((0, 2))
            self._seg_u = np.zeros((0, 2))
            self._seg_len = np.zeros(0)
            self._seg_s0 = np.zeros(0)
            self._seg_head = np.zeros(0)
            self._seg_lane = np.zeros(0, dtype=np.intp)
            self._lane_ids: list[str] = []
            return
        self._lane_ids = ids
        self._seg_a = np.concatenate([ln.points[:-1] for ln in lines])
        d = np.concatenate([np.diff(ln.points, axis=0) for ln in lines])
        self._seg_len = np.hypot(d[:, 0], d[:, 1])
        self._seg_u = d / self._seg_len[:, None]
        self._seg_s0 = np.concatenate([ln.cumlen[:-1] for ln in lines])
        self._seg_head = np.arctan2(d[:, 1], d[:, 0])
        self._seg_lane = np.concatenate(
            [np.full(len(ln.points) - 1, k, dtype=np.intp) for k, ln in enumerate(lines)]
        )

    def lane_of(self, x: float, y: float, heading: float) -> tuple[str, float] | None:
        """Lane id and arc length of a sensed car at (x, y) with ``heading``: the closest
        lane within 2.5 m whose direction there matches within 45°, or None. (Compared
        per lane segment, so at a lane's corner the segment that agrees with the car's
        heading is the one matched.)"""
        if not self._lane_ids:
            return None
        rel = np.array([x, y]) - self._seg_a
        t = np.minimum(np.maximum(np.einsum("sk,sk->s", rel, self._seg_u), 0.0), self._seg_len)
        diff = rel - t[:, None] * self._seg_u
        dist = np.hypot(diff[:, 0], diff[:, 1])
        dh = np.abs((heading - self._seg_head + math.pi) % (2.0 * math.pi) - math.pi)
        ok = (dist <= LANE_MATCH_LATERAL_M) & (dh <= LANE_MATCH_HEADING_RAD)
        if not ok.any():
            return None
        k = int(np.argmin(np.where(ok, dist, np.inf)))
        return self._lane_ids[int(self._seg_lane[k])], float(self._seg_s0[k] + t[k])

    # -- per-trial draws ----------------------------------------------------------

    def draw_start_times(self, seed: int) -> dict[str, float]:
        """Start time (s) of every vehicle for one trial. Fixed times pass through; each
        ``{uniform = [lo, hi]}`` is drawn from numpy ``default_rng([seed, crc32(id)])``,
        so a vehicle's draw depends only on the seed and its own id."""
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be an int >= 0, got {seed!r}")
        out: dict[str, float] = {}
        for v in self.vehicles:
            st = v.start_time_s
            if isinstance(st, UniformStart):
                lo, hi = st.uniform
                rng = np.random.default_rng([seed, zlib.crc32(v.id.encode())])
                out[v.id] = float(rng.uniform(lo, hi)) if hi > lo else float(lo)
            else:
                out[v.id] = float(st)
        return out


def parse_scenario(text: str, source: str = "<string>") -> Scenario:
    """Parse and validate TOML text; raises :class:`ScenarioError`."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError("", f"TOML syntax error: {exc}", source) from None
    try:
        spec = ScenarioFile.model_validate(raw)
    except ValidationError as exc:
        raise _wrap_validation(exc, source) from None
    return Scenario(spec, source)


def load_scenario(path: str | Path) -> Scenario:
    """Load and validate a scenario file; raises :class:`ScenarioError`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError("", f"cannot read scenario file: {exc}", str(p)) from None
    return parse_scenario(text, str(p))


def limits_from_params(params: Params, overrides: DynamicsOverrides | None = None) -> Limits:
    """The scenario's limits, with a vehicle's own overrides (fields left None keep
    the scenario value)."""

    def pick(name: str) -> float:
        if overrides is not None:
            val = getattr(overrides, name)
            if val is not None:
                return float(val)
        return float(getattr(params, name))

    return Limits(
        v_max=pick("v_max_mps"),
        accel=pick("accel_mps2"),
        decel_comfort=pick("decel_comfort_mps2"),
        decel_emergency=pick("decel_emergency_mps2"),
        actuator_lag_s=pick("actuator_lag_s"),
    )
