"""Scenario files: the map, the cars and the run parameters, validated before anything runs.

A scenario is a TOML file (format in ``scenarios/README.md``) parsed into pydantic
models (:class:`ScenarioFile`), then compiled into a :class:`Scenario`: polylines for
lanes and routes, conflict-zone crossings per route, the crossing lanes the
blind-corner caution must watch, and packed building polygons for occlusion.

Every problem is reported as one :class:`ScenarioError` naming the field path
(``vehicles[1].route``) and the reason; unknown keys are refused. So is anything the
wire format cannot carry (``protocol.codec``: ids, coordinates, speeds, sizes, points
per message, the step between consecutive path points) or the RSU core would refuse
(cross-field nonsense such as ``t_collision_s > t_free_s``): a scenario that loads
never fails later with an ``EncodeError``.

Demand comes as ``[[vehicles]]`` (one car each) and ``[[flows]]`` (a stream of cars on a
route, SUMO-style): :meth:`Scenario.for_seed` draws a flow's arrivals from the run's seed
and returns the scenario with every flow car as a vehicle ``<flow id>-<n>`` (n from 0)
whose ``start_time_s`` is its arrival; every consumer then sees plain vehicles.

The RSU's tuning knobs (``[rsu_params]``, per RSU ``[rsus.params]``) and the car's
(``[vehicle_params]``) are part of the scenario, so every harness (``crosspath sim``,
the daemons, the experiments) runs the same experiment from the same file.

Conventions (see ``geometry``): metres, seconds, radians; every position is a car's
geometric centre; a route's ``s`` is the arc length of the centre along the route.
"""

from __future__ import annotations

import math
import re
import tomllib
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
from pydantic import (
    AfterValidator,
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

from protocol import Kind, max_points
from protocol.codec import (
    MAX_ACCEL_MPS2,
    MAX_COORD_M,
    MAX_LENGTH_M,
    MAX_RADIUS_M,
    MAX_SPEED_MPS,
    MAX_STEP_M,
    MAX_STEP_S,
    MAX_WIDTH_M,
)
from protocol.keys import ID_CHARS, MAX_ID_LEN
from services.model.catalog import resolve_scenario
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
from services.model.limits import SPEED_CAP_FACTOR

__all__ = [
    "DEFAULT_LENGTH_M",
    "DEFAULT_WIDTH_M",
    "LANE_MATCH_HEADING_RAD",
    "LANE_MATCH_LATERAL_M",
    "MAX_FLOW_VEHICLES",
    "ApproachLane",
    "BuildingSpec",
    "Crossing",
    "DynamicsOverrides",
    "FlowSpec",
    "IntersectionSpec",
    "LaneSpec",
    "MetricsSpec",
    "Params",
    "RouteSpec",
    "RsuParams",
    "RsuParamsOverrides",
    "RsuSpec",
    "Scenario",
    "ScenarioError",
    "ScenarioFile",
    "ScenarioInfo",
    "UniformStart",
    "VehicleParams",
    "VehicleParamsOverrides",
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

ID_PATTERN = rf"^[{ID_CHARS}]{{1,{MAX_ID_LEN}}}$"
"""Ids are the wire's and the key expressions' (``protocol.keys``): 1..32 of [A-Za-z0-9_-]."""

WIRE_SPEED_MAX_MPS = MAX_SPEED_MPS / SPEED_CAP_FACTOR
"""Largest ``v_max_mps``: the physics lets a car reach ``v_max * SPEED_CAP_FACTOR``, and
that speed must still fit the wire's ``MAX_SPEED_MPS`` [m/s]."""

MIN_SIZE_M = 0.01
"""Smallest car length or width and RSU coverage: the wire's resolution, 1 cm [m]."""

MAX_FLOW_VEHICLES = 5000
"""Most cars one flow may be expected to make (``vehicles_per_hour`` x its duration):
a larger flow is refused. A Poisson draw is cut at :data:`FLOW_VEHICLES_CAP` cars."""

FLOW_VEHICLES_CAP = 9999
"""Hard cap on the cars one flow draws (4 digits of ``n`` in ``<flow id>-<n>``)."""

FLOW_ID_MAX_LEN = MAX_ID_LEN - 1 - len(str(FLOW_VEHICLES_CAP - 1))
"""A flow id leaves room for ``-<n>``: its cars' ids must still be valid ids (27 chars)."""

FUTURE_PATH_POINTS_MAX = min(max_points(Kind.FUTURE_PATH), max_points(Kind.AUTONOMOUS_PATH))
"""Most points a car can put in one future (or autonomous) path datagram."""

PATH_THINNING = 2.0
"""A coordinated path may skip every other point of the car's path when the RSU thins it
to fit a datagram (``services.rsu.core``), so the per-point step of a future path must
fit the wire's ``MAX_STEP_M`` / ``MAX_STEP_S`` this many times over."""


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


def _on_the_wire(v: float) -> float:
    if abs(v) > MAX_COORD_M:
        raise ValueError(f"{v} m is beyond the wire format's ±{MAX_COORD_M:g} m")
    return v


F = Annotated[float, Strict(), AfterValidator(_on_the_wire)]
PosF = Annotated[float, Strict(), Field(gt=0.0)]
NonNegF = Annotated[float, Strict(), Field(ge=0.0)]
PosInt = Annotated[int, Strict(), Field(gt=0)]
Point = tuple[F, F]
Points = Annotated[list[Point], Field(min_length=2)]
PolygonPoints = Annotated[list[Point], Field(min_length=3)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _check_wire_speed(v: float | None) -> float | None:
    if v is not None and v > WIRE_SPEED_MAX_MPS:
        raise ValueError(
            f"{v} m/s: a car may reach {SPEED_CAP_FACTOR} x v_max, and the wire carries at "
            f"most {MAX_SPEED_MPS:g} m/s (so v_max_mps <= {WIRE_SPEED_MAX_MPS:.2f})"
        )
    return v


def _check_wire_accel(v: float | None) -> float | None:
    """A car declares its accelerations in its paths in 0.1 m/s² bytes (SPEC.md 2.3)."""
    if v is not None and not 0.1 <= v <= MAX_ACCEL_MPS2:
        raise ValueError(
            f"{v} m/s²: a car's paths carry its accelerations as 0.1..{MAX_ACCEL_MPS2:g} m/s²"
        )
    return v


def _wire_size(what: str, most: float) -> Callable[[float], float]:
    """A validator: sizes the wire carries in whole centimetres, from 1 cm to ``most`` m."""

    def check(v: float) -> float:
        if not MIN_SIZE_M <= v <= most:
            raise ValueError(f"{v} m: the wire carries {what} of {MIN_SIZE_M}..{most:g} m")
        return v

    return check


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
    lat_accel_mps2: PosF = 2.0
    """Lateral acceleration a car allows itself in curves: speed <= sqrt(a_lat * r) [m/s²]."""
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

    _wire_speed = field_validator("v_max_mps")(_check_wire_speed)
    _wire_accel = field_validator("accel_mps2", "decel_comfort_mps2", "lat_accel_mps2")(
        _check_wire_accel
    )

    @field_validator("future_path_points")
    @classmethod
    def _fits_a_datagram(cls, v: int) -> int:
        if v > FUTURE_PATH_POINTS_MAX:
            raise ValueError(
                f"{v} points do not fit one datagram: a future path carries at most "
                f"{FUTURE_PATH_POINTS_MAX} (protocol.max_points)"
            )
        return v

    @field_validator("t_free_s")
    @classmethod
    def _horizon(cls, v: float) -> float:
        if v > MAX_STEP_S:
            raise ValueError(
                f"{v} s: a standing car's future path holds its last point t_free_s after "
                f"the first, and the wire carries at most {MAX_STEP_S} s between points"
            )
        return v

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
    priority_lanes: list[Id] = []
    """Lanes of a priority road through this intersection: a car on another lane gives
    way to a car on one of these that it knows only from its sensors (no future path:
    a driver crosspath does not coordinate, who follows the road's priority, e.g. SUMO's
    unconnected cars). Empty (the paper's blind intersection): no priority road, and
    crosspath's own right of way holds for sensed cars too."""

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
    lat_accel_mps2: PosF | None = None

    _wire_speed = field_validator("v_max_mps")(_check_wire_speed)
    _wire_accel = field_validator("accel_mps2", "decel_comfort_mps2", "lat_accel_mps2")(
        _check_wire_accel
    )


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


class VehicleParams(_Model):
    """``[vehicle_params]``: the car's planner and controller knobs (``services.vehicle``);
    defaults are the ones the results in the README were made with."""

    stop_margin_m: NonNegF = 0.3
    """Planned stops aim this far before the stop line, for the actuator lag [m]."""
    caution_sample_m: PosF = 2.0
    """Spacing of the points sampled along crossing lanes to judge visibility [m]."""
    creep_mps: PosF = 1.5
    """Under caution, past the stop line the car creeps this fast at most, to see [m/s]."""
    creep_margin_m: NonNegF = 0.5
    """Creeping stops this far before the conflict zone [m]."""
    emergency_gap_m: NonNegF = 1.5
    """Gap kept to a sensed car on the path when braking for it [m]."""
    control_lookahead_s: NonNegF = 0.3
    """The controller tracks the planned speed this far ahead (about the actuator lag) [s]."""
    control_time_constant_s: PosF = 0.4
    """Speed error to acceleration command gain is 1 / this [s]."""
    fp_stale_s: PosF = 0.5
    """Received future paths older than this are forgotten [s] (under ``fp_rule =
    "change"`` plus ``fp_refresh_s``: see :meth:`Scenario.fp_hold_s`)."""
    fp_rule: Literal["periodic", "change"] = "periodic"
    """When a car sends its future path (``services.model.send_rule``): "periodic" every
    planning tick (the paper's 10 Hz), "change" only when it deviates from the last one
    sent by more than ``fp_change_m``, on a mode change, and at least every
    ``fp_refresh_s``. Scenario-wide (not a per-car override): every receiver's expiry
    follows it."""
    fp_change_m: PosF = 0.5
    """``fp_rule = "change"``: largest deviation [m] between the new path and the last one
    sent, compared at the same times, that is not sent."""
    fp_refresh_s: PosF = 1.0
    """``fp_rule = "change"``: a path is sent at least this often [s]."""
    ap_rule: Literal["periodic", "change"] = "periodic"
    """The same for the autonomous path to the RSU (while coordinated): "change" sends
    it on a deviation over ``fp_change_m``, a mode change, and at least every
    ``ap_refresh_s``. The RSU answers each with a coordinated path, so under "change"
    the car's ``coordinated_timeout_s`` grows by ``ap_refresh_s``."""
    ap_refresh_s: PosF = 0.2
    """``ap_rule = "change"``: the autonomous path is sent at least this often [s]."""
    cp_rule: Literal["periodic", "change"] = "periodic"
    """The same for the RSU's coordinated path to a car: "periodic" answers every
    autonomous path with one, "change" only when it deviates from the last one sent to
    that car by more than ``fp_change_m``, on a mode change, and at least every
    ``cp_refresh_s``; the car's ``coordinated_timeout_s`` grows by ``cp_refresh_s``."""
    cp_refresh_s: PosF = 0.5
    """``cp_rule = "change"``: the RSU sends a car a coordinated path at least this often
    (when it answers an autonomous path) [s]."""


class VehicleParamsOverrides(_Model):
    """``[vehicles.params]``: one car's own knobs; a key left out keeps ``[vehicle_params]``."""

    stop_margin_m: NonNegF | None = None
    caution_sample_m: PosF | None = None
    creep_mps: PosF | None = None
    creep_margin_m: NonNegF | None = None
    emergency_gap_m: NonNegF | None = None
    control_lookahead_s: NonNegF | None = None
    control_time_constant_s: PosF | None = None
    fp_stale_s: PosF | None = None


class VehicleSpec(_Model):
    """``[[vehicles]]``: one car. ``goal_m`` None means the route's end."""

    id: Id
    route: Id
    start_time_s: StartTime = 0.0
    start_offset_m: NonNegF = 0.0
    goal_m: PosF | None = None
    length_m: Annotated[PosF, AfterValidator(_wire_size("car lengths", MAX_LENGTH_M))] = (
        DEFAULT_LENGTH_M
    )
    width_m: Annotated[PosF, AfterValidator(_wire_size("car widths", MAX_WIDTH_M))] = (
        DEFAULT_WIDTH_M
    )
    dynamics: DynamicsOverrides | None = None
    params: VehicleParamsOverrides | None = None


class FlowSpec(_Model):
    """``[[flows]]``: a stream of cars on one route from ``begin_s`` to ``end_s`` [run s];
    ``arrivals`` "poisson" (exponential gaps) or "uniform" (one every 3600 /
    ``vehicles_per_hour`` s from ``begin_s``). Its cars are ``<id>-<n>``."""

    id: Annotated[Id, StringConstraints(max_length=FLOW_ID_MAX_LEN)]
    route: Id
    vehicles_per_hour: PosF
    begin_s: NonNegF = 0.0
    end_s: PosF
    arrivals: Literal["poisson", "uniform"] = "poisson"
    length_m: Annotated[PosF, AfterValidator(_wire_size("car lengths", MAX_LENGTH_M))] = (
        DEFAULT_LENGTH_M
    )
    width_m: Annotated[PosF, AfterValidator(_wire_size("car widths", MAX_WIDTH_M))] = (
        DEFAULT_WIDTH_M
    )
    dynamics: DynamicsOverrides | None = None

    @model_validator(mode="after")
    def _window(self) -> FlowSpec:
        if self.end_s <= self.begin_s:
            raise ValueError(f"end_s ({self.end_s} s) must be after begin_s ({self.begin_s} s)")
        return self

    @property
    def expected_vehicles(self) -> float:
        """Cars the flow makes on average: rate x duration."""
        return self.vehicles_per_hour * (self.end_s - self.begin_s) / 3600.0


class RsuParams(_Model):
    """``[rsu_params]``: the RSU core's knobs beyond the paper's ``[params]`` (defaults are
    the ones the results in the README were made with; ``services.rsu.velocity`` and
    ``services.rsu.modes`` say what each does)."""

    command_repeat_s: PosF = 0.1
    """A mode command is repeated this often until the car's future path shows it [s]."""
    beacon_period_s: PosF = 1.0
    """The RSU beacon's period [s]."""
    stop_gap_m: NonNegF = 2.0
    """``slot``: front bumper to zone edge when a car must stop and wait [m]."""
    slot_step_s: PosF = 0.1
    """``slot``: granularity of the entry-time search [s]."""
    slot_min_speed_mps: PosF = 2.0
    """``slot``: below this a car stops and waits rather than crawl [m/s]; < ``v_max_mps``."""
    hold_step_s: PosF = 0.5
    """Spacing of the points holding a stop [s]; < 2 ``headway_s``, so that no crossing
    point can fall between two of them unseen."""
    release_margin_m: NonNegF = 0.6
    """Hysteresis: "free" and releases need this much more room than a conflict [m]..."""
    release_margin_s: NonNegF = 0.2
    """... and this much more headway [s]."""


class RsuParamsOverrides(_Model):
    """``[rsus.params]``: one RSU's own knobs; a key left out keeps ``[rsu_params]``."""

    command_repeat_s: PosF | None = None
    beacon_period_s: PosF | None = None
    stop_gap_m: NonNegF | None = None
    slot_step_s: PosF | None = None
    slot_min_speed_mps: PosF | None = None
    hold_step_s: PosF | None = None
    release_margin_m: NonNegF | None = None
    release_margin_s: NonNegF | None = None


class RsuSpec(_Model):
    """``[[rsus]]``: a roadside unit serving one intersection."""

    id: Id
    intersection: Id
    position: Point
    coverage_m: Annotated[PosF, AfterValidator(_wire_size("coverage radii", MAX_RADIUS_M))] = 150.0
    params: RsuParamsOverrides | None = None


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
    vehicles: list[VehicleSpec] = []
    flows: list[FlowSpec] = []
    rsus: list[RsuSpec] = []
    rsu_params: RsuParams = RsuParams()
    vehicle_params: VehicleParams = VehicleParams()
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
        elif e["type"] == "string_too_long" and e["loc"][:1] == ("flows",):
            msg = (
                f"{e['input']!r} is too long for a flow id: at most {FLOW_ID_MAX_LEN} "
                "characters, so that its cars' ids <id>-<n> stay valid ids"
            )
        elif e["type"] == "string_pattern_mismatch":
            msg = f"{e['input']!r} is not a valid id: use 1 to {MAX_ID_LEN} of A-Z a-z 0-9 _ -"
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
        self._rsu_params: dict[str, RsuParams] = {}
        self._vehicle_params: dict[str, VehicleParams] = {}
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
            ("flows", sp.flows),
            ("rsus", sp.rsus),
        ):
            self._unique(kind, [it.id for it in items])
        if not sp.vehicles and not sp.flows:
            raise self._err("vehicles", "a scenario needs at least one [[vehicles]] or [[flows]]")
        if sp.params.t_collision_s > sp.params.t_free_s:
            raise self._err(
                "params.t_collision_s",
                f"{sp.params.t_collision_s} s must not exceed t_free_s ({sp.params.t_free_s} s): "
                "the RSU looks for conflicts within the horizon the paths cover",
            )
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
        for i, it in enumerate(sp.intersections):
            for k, lane_id in enumerate(it.priority_lanes):
                if lane_id not in self._lanes:
                    known = ", ".join(sorted(self._lanes)) or "none"
                    raise self._err(
                        f"intersections[{i}].priority_lanes[{k}]",
                        f"unknown lane {lane_id!r} (known: {known})",
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
                limits = limits_from_params(sp.params, v.dynamics)
            except ValueError as exc:
                raise self._err(f"vehicles[{i}].dynamics", str(exc)) from None
            own = v.dynamics is not None and v.dynamics.v_max_mps is not None
            self._check_path_step(
                f"vehicles[{i}].dynamics.v_max_mps" if own else None, f"car {v.id!r}", limits
            )
            rv = v.model_copy(update={"goal_m": min(goal, line.length)})
            resolved.append(rv)
            self._vehicles[v.id] = rv
            self._vehicle_params[v.id] = _merged(sp.vehicle_params, v.params)
        self.vehicles: tuple[VehicleSpec, ...] = tuple(resolved)
        self._check_flows()
        self._check_fp_rule()
        self._pack_lanes()

        for i, r in enumerate(sp.rsus):
            if r.intersection not in self._intersections:
                known = ", ".join(sorted(self._intersections)) or "none"
                raise self._err(
                    f"rsus[{i}].intersection",
                    f"unknown intersection {r.intersection!r} (known: {known})",
                )
            self._rsus[r.id] = r
            self._rsu_params[r.id] = self._check_rsu_params(
                _merged(sp.rsu_params, r.params), f"rsus[{i}]", r.params
            )

    def _check_fp_rule(self) -> None:
        """Under ``fp_rule = "change"`` a held path must still cover the time it is used
        for: ``fp_refresh_s`` plus the longest expiry must fit the horizon ``t_free_s``,
        and the refresh must be at least one planning period."""
        vp, p = self.spec.vehicle_params, self.spec.params
        if vp.ap_rule == "change" and vp.ap_refresh_s < 1.0 / p.planning_hz - 1e-9:
            raise self._err(
                "vehicle_params.ap_refresh_s",
                f"{vp.ap_refresh_s} s is shorter than one planning period "
                f"({1.0 / p.planning_hz:g} s)",
            )
        if vp.cp_rule == "change":
            if vp.cp_refresh_s < 1.0 / p.planning_hz - 1e-9:
                raise self._err(
                    "vehicle_params.cp_refresh_s",
                    f"{vp.cp_refresh_s} s is shorter than one planning period "
                    f"({1.0 / p.planning_hz:g} s)",
                )
            # the car follows a coordinated path up to its (grown) timeout after it came
            held = (
                vp.cp_refresh_s
                + p.coordinated_timeout_s
                + (vp.ap_refresh_s if vp.ap_rule == "change" else 0.0)
            )
            if held > p.t_free_s:
                raise self._err(
                    "vehicle_params.cp_refresh_s",
                    f"{vp.cp_refresh_s} s plus the car's coordinated timeout exceeds the "
                    f"path horizon t_free_s = {p.t_free_s} s: a held coordinated path "
                    "would run out before the car gives it up",
                )
        if vp.fp_rule == "periodic":
            return
        base = max(
            p.reservation_expiry_s,
            vp.fp_stale_s,
            *(v.fp_stale_s for v in self._vehicle_params.values()),
        )
        if vp.fp_refresh_s + base > p.t_free_s:
            raise self._err(
                "vehicle_params.fp_refresh_s",
                f"{vp.fp_refresh_s} s plus the expiry {base} s exceeds the path horizon "
                f"t_free_s = {p.t_free_s} s: a held path would run out before it expires",
            )
        if vp.fp_refresh_s < 1.0 / p.planning_hz - 1e-9:
            raise self._err(
                "vehicle_params.fp_refresh_s",
                f"{vp.fp_refresh_s} s is shorter than one planning period "
                f"({1.0 / p.planning_hz:g} s)",
            )

    def _check_flows(self) -> None:
        """Each flow's route exists, its demand is bounded, its limits are valid and fit
        the wire, and no other car or RSU id looks like one of its cars' ids."""
        sp = self.spec
        others = [v.id for v in sp.vehicles] + [r.id for r in sp.rsus]
        for i, f in enumerate(sp.flows):
            if f.route not in self._routes:
                known = ", ".join(sorted(self._routes))
                raise self._err(f"flows[{i}].route", f"unknown route {f.route!r} (known: {known})")
            if f.expected_vehicles > MAX_FLOW_VEHICLES:
                raise self._err(
                    f"flows[{i}].vehicles_per_hour",
                    f"{f.expected_vehicles:.0f} cars expected over {f.end_s - f.begin_s:g} s; "
                    f"a flow makes at most {MAX_FLOW_VEHICLES}",
                )
            try:
                limits = limits_from_params(sp.params, f.dynamics)
            except ValueError as exc:
                raise self._err(f"flows[{i}].dynamics", str(exc)) from None
            own = f.dynamics is not None and f.dynamics.v_max_mps is not None
            self._check_path_step(
                f"flows[{i}].dynamics.v_max_mps" if own else None, f"flow {f.id!r}", limits
            )
            pattern = re.compile(rf"{re.escape(f.id)}-[0-9]+")
            clash = [x for x in others if pattern.fullmatch(x)]
            if clash:
                raise self._err(
                    f"flows[{i}].id",
                    f"its cars are named {f.id}-<n>, and {clash[0]!r} is already a vehicle or RSU",
                )

    def _flow_arrivals(self, f: FlowSpec, seed: int) -> list[float]:
        """Arrival times [run s] of one flow's cars in ``[begin_s, end_s)``."""
        if f.arrivals == "uniform":
            period = 3600.0 / f.vehicles_per_hour
            n = min(math.ceil((f.end_s - f.begin_s) / period - 1e-9), FLOW_VEHICLES_CAP)
            return [f.begin_s + k * period for k in range(n)]
        rng = np.random.default_rng([seed, zlib.crc32(f"flow:{f.id}".encode())])
        mean_gap = 3600.0 / f.vehicles_per_hour
        out: list[float] = []
        t = f.begin_s + float(rng.exponential(mean_gap))
        while t < f.end_s and len(out) < FLOW_VEHICLES_CAP:
            out.append(t)
            t += float(rng.exponential(mean_gap))
        return out

    def draw_arrivals(self, seed: int) -> dict[str, list[float]]:
        """Per flow, its cars' arrival times [run s] for one trial, increasing. Poisson
        gaps come from numpy ``default_rng([seed, crc32("flow:" + id)])``: a flow's
        arrivals depend only on the seed and its own id; uniform arrivals on neither."""
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be an int >= 0, got {seed!r}")
        return {f.id: self._flow_arrivals(f, seed) for f in self.spec.flows}

    def require_no_flows(self, harness: str) -> None:
        """Refuse ``[[flows]]`` where ``harness`` needs every car named before it starts: a
        daemon loads the plain file ``crosspath up`` expands for the run's seed
        (``services.supervise.expand``), the network lab does not expand flows yet."""
        if self.spec.flows:
            raise ScenarioError(
                "flows",
                f"{harness} runs only [[vehicles]]; run flows with crosspath up (it expands "
                "them for the run's seed into <run dir>/scenario.toml) or in-process "
                "(crosspath sim, services.api.simulate)",
                self.source,
            )

    def for_seed(self, seed: int) -> Scenario:
        """The scenario one trial runs: every flow's cars drawn (:meth:`draw_arrivals`) and
        appended as vehicles ``<flow id>-<n>`` after the ``[[vehicles]]``, each starting
        at its arrival at the route's start; no flows left. Itself without flows."""
        if not self.spec.flows:
            return self
        cars = list(self.spec.vehicles)
        flows = {f.id: f for f in self.spec.flows}
        for fid, times in self.draw_arrivals(seed).items():
            f = flows[fid]
            cars.extend(
                VehicleSpec(
                    id=f"{fid}-{n}",
                    route=f.route,
                    start_time_s=t,
                    length_m=f.length_m,
                    width_m=f.width_m,
                    dynamics=f.dynamics,
                )
                for n, t in enumerate(times)
            )
        if not cars:
            raise self._err("flows", f"seed {seed} draws no car from any flow, and no [[vehicles]]")
        return Scenario(self.spec.model_copy(update={"vehicles": cars, "flows": []}), self.source)

    def _point_step_m(self, limits: Limits) -> float:
        """Distance between consecutive future-path points of a car at its speed cap [m]."""
        p = self.spec.params
        return limits.v_max * SPEED_CAP_FACTOR * p.t_free_s / (p.future_path_points - 1)

    def _check_path_step(self, own_path: str | None, who: str, limits: Limits) -> None:
        """A car's future path, and a coordinated path thinned from it, must fit the wire's
        largest step between consecutive points. ``own_path`` names the car's own
        ``v_max_mps`` when it sets one (else the scenario's knob is blamed)."""
        p = self.spec.params
        step = self._point_step_m(limits)
        if step * PATH_THINNING <= MAX_STEP_M:
            return
        raise self._err(
            own_path or "params.future_path_points",
            f"{who} at {limits.v_max * SPEED_CAP_FACTOR:.1f} m/s puts its future-path "
            f"points {step:.1f} m apart ({p.t_free_s} s over {p.future_path_points - 1} "
            f"steps); thinned by the RSU that is {step * PATH_THINNING:.1f} m, and the wire "
            f"carries at most {MAX_STEP_M} m between points: raise future_path_points or "
            "lower t_free_s or v_max_mps",
        )

    def _check_rsu_params(
        self, rp: RsuParams, where: str, overrides: RsuParamsOverrides | None
    ) -> RsuParams:
        """Refuse RSU knobs the core cannot work with, naming the field that set them
        (``rsus[i].params.x`` when the RSU overrides it, else ``rsu_params.x``)."""
        p = self.spec.params

        def path(name: str) -> str:
            if overrides is not None and getattr(overrides, name) is not None:
                return f"{where}.params.{name}"
            return f"rsu_params.{name}"

        if rp.slot_min_speed_mps >= p.v_max_mps:
            raise self._err(
                path("slot_min_speed_mps"),
                f"{rp.slot_min_speed_mps} m/s must be below params.v_max_mps "
                f"({p.v_max_mps:.2f} m/s)",
            )
        if p.headway_s > 0.0 and rp.hold_step_s >= 2.0 * p.headway_s:
            raise self._err(
                path("hold_step_s"),
                f"{rp.hold_step_s} s must be below 2 x params.headway_s ({2.0 * p.headway_s} s): "
                "a crossing point could fall between two hold points unseen",
            )
        steps = [self._point_step_m(self.limits(v.id)) for v in self.vehicles] + [
            self._point_step_m(limits_from_params(p, f.dynamics)) for f in self.spec.flows
        ]
        crawl_s = max(steps, default=0.0) * PATH_THINNING / rp.slot_min_speed_mps
        if crawl_s > MAX_STEP_S:
            raise self._err(
                path("slot_min_speed_mps"),
                f"a car crawling at {rp.slot_min_speed_mps} m/s takes {crawl_s:.1f} s between "
                f"coordinated-path points; the wire carries at most {MAX_STEP_S} s",
            )
        return rp

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

    def rsu_params(self, rsu_id: str) -> RsuParams:
        """The RSU's knobs: ``[rsu_params]`` with its own ``params`` overrides. KeyError if
        unknown."""
        return self._rsu_params[rsu_id]

    def fp_hold_s(self, base_s: float) -> float:
        """How long a receiver keeps a car's future path after hearing it [s]: ``base_s``
        (the RSU's ``reservation_expiry_s``, a car's ``fp_stale_s``) under the periodic
        rule; under ``fp_rule = "change"`` a quiet car sends only every ``fp_refresh_s``,
        so ``fp_refresh_s + base_s`` (the same loss margin after the longest silence).
        One owner for both sides (``services.rsu.config.rsu_config``,
        ``services.vehicle.agent``), so that no path expires between two sends."""
        vp = self.spec.vehicle_params
        return base_s if vp.fp_rule == "periodic" else vp.fp_refresh_s + base_s

    def vehicle_params(self, vehicle_id: str) -> VehicleParams:
        """The car's planner and controller knobs: ``[vehicle_params]`` with its own
        ``params`` overrides. KeyError if unknown."""
        return self._vehicle_params[vehicle_id]

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
    """Load and validate a scenario file, or a packaged scenario by name
    (:func:`~services.model.catalog.resolve_scenario`); raises :class:`ScenarioError`."""
    p = Path(path)
    try:
        p = resolve_scenario(p)
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError("", f"cannot read scenario file: {exc}", str(p)) from None
    return parse_scenario(text, str(p))


_M = TypeVar("_M", bound=BaseModel)


def _merged(base: _M, overrides: BaseModel | None) -> _M:
    """``base`` with every field ``overrides`` sets (not None) replaced (both validated)."""
    if overrides is None:
        return base
    update = {k: v for k, v in overrides.model_dump().items() if v is not None}
    return base.model_copy(update=update)


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
        lat_accel=pick("lat_accel_mps2"),
    )
