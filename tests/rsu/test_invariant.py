"""The RSU invariant (``services.rsu.core``, "The invariant") as hypothesis properties.

A test driver with the RSU core alone, at the 4-way intersection of
``scenarios/four-way-flows.toml`` (one lane per approach, straight and turning routes):
N cars start 60-130 m before the zone (so that every car can still stop comfortably),
in random lanes and at random speeds, followers at least a follow distance apart.
Every 0.1 s each car sends its future path (and, coordinated, its autonomous path);
a car in ``AUTO`` drives its own plan (V_max, stop at the stop line while it has not
been coordinated, as a blind corner makes it, and never closer than a follow distance
to the car ahead), a coordinated car follows its coordinated path exactly. No message
is lost. After every RSU step the invariant is checked; at the end every car is
through.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol.messages import (
    AutonomousPath,
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Mode,
    ModeCommand,
)
from services.model.geometry import Polyline
from services.model.scenario import load_scenario
from services.model.types import Policy
from services.rsu import core as rsu_core
from services.rsu.config import rsu_config
from services.rsu.core import RsuCore
from services.rsu.reservation import follow_distance
from services.vehicle.future_path import future_path_points
from services.vehicle.profile import (
    SpeedProfile,
    backward_pass,
    forward_pass,
    grid,
    pass_times,
    stop_cap,
)

SCENARIO = load_scenario(Path(__file__).parents[2] / "scenarios" / "four-way-flows.toml")
ROUTES = sorted(SCENARIO.route_ids)
P = SCENARIO.params
DT = 0.1
LENGTH, WIDTH = 4.5, 1.8
GAP = follow_distance(LENGTH, LENGTH, 1.0) + 0.5  # the driver's own car following [m]
_DV_S = 0.02  # a car's speed is its path's over the last this of the step [s]


@dataclass
class Car:
    vid: str
    route_id: str
    s: float
    v: float
    route: Polyline = field(init=False)
    s_in: float = field(init=False)
    s_out: float = field(init=False)
    s_line: float = field(init=False)
    mode: Mode = Mode.AUTO
    coord: np.ndarray | None = None  # coordinated path (x, y, t)
    coord_s: np.ndarray | None = None  # its arc lengths along the route
    changes: int = 0
    seq: int = 0

    def __post_init__(self) -> None:
        self.route = SCENARIO.route(self.route_id)
        (crossing,) = SCENARIO.crossings(self.route_id, LENGTH)
        self.s_in, self.s_out, self.s_line = crossing.s_in, crossing.s_out, crossing.s_stop

    @property
    def done(self) -> bool:
        return self.s - LENGTH / 2 > self.s_out + 5.0

    def xy(self) -> tuple[float, float]:
        return self.route.point_at(self.s)

    def own_profile(self, now: float, ahead: float | None, caution: bool) -> SpeedProfile:
        """V_max, capped by the stop line (``caution``) and the car ahead (arc length)."""
        end = min(self.route.length, self.s + 160.0)
        s = grid(self.s, end, 0.5)
        cap = np.full_like(s, P.v_max_mps)
        cap = np.minimum(cap, stop_cap(s, self.route.length - 1.0, P.decel_comfort_mps2))
        if caution and self.s < self.s_line - 0.5:
            cap = np.minimum(cap, stop_cap(s, self.s_line - 0.3, P.decel_comfort_mps2))
        if ahead is not None:
            cap = np.minimum(cap, stop_cap(s, ahead - GAP, 5.0))
        cap = backward_pass(cap, 0.5, P.decel_comfort_mps2)
        v = forward_pass(cap, self.v, 0.5, P.accel_mps2)
        return SpeedProfile(s, v, pass_times(s, v, now))

    def message(self, cls: type, now: float, profile: SpeedProfile) -> FuturePath:
        pts = future_path_points(profile, self.route, now, P.t_free_s, P.future_path_points)
        self.seq += 1
        x, y = self.xy()
        heading = self.route.heading_at(self.s)
        return cls(  # type: ignore[no-any-return]
            Header(self.vid, self.seq, round(now * 1e6)),
            x,
            y,
            self.v,
            heading,
            LENGTH,
            WIDTH,
            self.mode,
            pts,
        )


def _ahead(car: Car, cars: list[Car]) -> float | None:
    """Arc length (on ``car``'s route) of the nearest car ahead in its lane, or None."""
    best = None
    for other in cars:
        if other is car or other.done:
            continue
        ox, oy = other.xy()
        s, lat = car.route.project(ox, oy)
        if abs(lat) > 1.5 or s <= car.s:
            continue
        heading = car.route.heading_at(s)
        if math.cos(other.route.heading_at(other.s) - heading) < 0.8:
            continue
        best = s if best is None else min(best, s)
    return best


def _check_invariant(core: RsuCore, cars: dict[str, Car], now: float) -> None:
    cfg = core.config
    # 1. no two committed paths conflict within T_collision (same-lane followers count)
    for vehicle in core.table:
        entry = core.table.get(vehicle)
        assert entry is not None
        found = core.table.naive_conflicts(
            vehicle, entry.points, now, cfg.t_collision_s, shape=(entry.length, entry.width)
        )
        assert not found, f"t={now:.1f}: {vehicle} ({core.mode_of(vehicle).name}) vs {found}"
    # 4. bounded mode changes per crossing
    for car in cars.values():
        assert car.changes <= rsu_core.MAX_MODE_CHANGES + 2, (car.vid, car.changes)


def _drive(
    policy: Policy,
    starts: list[tuple[str, float, float]],
    seconds: float,
    cp_change_m: float | None = None,
) -> None:
    # cp_change_m: the coordinated path's change rule (services.model.send_rule); the cars
    # here follow the last coordinated path they were sent, as real ones do
    config = dataclasses.replace(rsu_config(SCENARIO, "rsu1", policy), cp_change_m=cp_change_m)
    core = RsuCore(config, listen_s=0.0)
    cars = {f"c{i}": Car(f"c{i}", r, s, v) for i, (r, s, v) in enumerate(starts)}
    steps = round(seconds / DT)
    for k in range(steps):
        now = round(k * DT, 6)
        live = [c for c in cars.values() if not c.done]
        if not live:
            break
        for car in live:
            ahead = _ahead(car, live)
            own = car.own_profile(now, ahead, caution=car.mode == Mode.AUTO)
            out = core.on_message(now, car.message(FuturePath, now, own))
            if car.mode != Mode.AUTO:
                free = car.own_profile(now, ahead, caution=False)
                out += core.on_message(now, car.message(AutonomousPath, now, free), config.rsu_id)
            for o in out:
                target = cars.get(o.vehicle) if o.vehicle is not None else None
                m = o.message
                if target is None:
                    continue
                if isinstance(m, ModeCommand):
                    new = Mode.AUTO if m.command == Command.TERMINATE else m.mode
                    if new != target.mode:
                        target.changes += 1
                    target.mode = new
                    if new == Mode.AUTO:
                        target.coord = target.coord_s = None
                elif isinstance(m, CoordinatedPath) and target.mode != Mode.AUTO:
                    # 3. a C_FAST path is sent only when it is clear of the table
                    target.coord = m.points
                    s_pts, _ = target.route.project_many(np.ascontiguousarray(m.points[:, :2]))
                    target.coord_s = np.maximum.accumulate(s_pts)
        core.tick(now)
        _check_invariant(core, cars, now)
        # motion
        for car in live:
            if car.mode != Mode.AUTO and car.coord is not None and car.coord_s is not None:
                t = car.coord[:, 2]
                s_new = float(np.interp(now + DT, t, car.coord_s))
                s_before = float(np.interp(now + DT - _DV_S, t, car.coord_s))
                car.v = max(0.0, (s_new - s_before) / _DV_S)  # its speed at the step's end
                car.s = max(car.s, s_new)
            else:
                own = car.own_profile(now, _ahead(car, live), caution=True)
                fin = np.isfinite(own.t)
                s_new = float(np.interp(now + DT, own.t[fin], own.s[fin]))
                car.v = max(0.0, float(np.interp(now + DT, own.t[fin], own.v[fin])))
                car.s = max(car.s, s_new)
        # 2. a car following its path never drives into the car ahead
        for car in live:
            ahead = _ahead(car, live)
            if ahead is not None:
                assert ahead - car.s >= LENGTH, f"t={now:.1f}: {car.vid} ran into the car ahead"
    # 5. nobody waits forever: every car is through at the end
    stuck = [c.vid for c in cars.values() if not c.done]
    assert not stuck, f"not through after {seconds} s: {stuck}"


def _starts(draw: st.DrawFn, n_max: int) -> list[tuple[str, float, float]]:
    n = draw(st.integers(2, n_max))
    placed: list[tuple[str, float, float]] = []
    for _ in range(n):
        route = draw(st.sampled_from(ROUTES))
        (crossing,) = SCENARIO.crossings(route, LENGTH)
        before = draw(st.floats(60.0, 130.0))
        s = crossing.s_in - LENGTH / 2 - before
        lane = route[0]  # the approach: routes from one side share its lane
        if any(r[0] == lane and abs(s2 - s) < GAP + 3.0 for r, s2, _ in placed):
            continue
        v = draw(st.floats(0.0, P.v_max_mps))
        placed.append((route, s, v))
    return placed


@st.composite
def situations(draw: st.DrawFn, n_max: int = 5) -> list[tuple[str, float, float]]:
    return _starts(draw, n_max)


@pytest.mark.parametrize("cp_change_m", [None, 0.5], ids=["cp-periodic", "cp-change"])
@pytest.mark.parametrize("policy", [Policy.PAPER, Policy.SLOT])
@settings(
    max_examples=4,
    deadline=None,
    derandomize=True,  # CI-stable; FOUND_BY_SEARCH below is what random search found
    suppress_health_check=[HealthCheck.too_slow],
)
@given(starts=situations())
def test_invariant_holds_for_random_n_car_situations(
    policy: Policy, cp_change_m: float | None, starts: list[tuple[str, float, float]]
) -> None:
    _drive(policy, starts, 45.0, cp_change_m)


# A situation random search found (issue 12): three cars of the east approach turning
# right, one stopped, and a left turn from the south into the west-bound lane. Under
# paper, a car held before the zone and the turning car crossing 0.8 m in front of its
# lane's line were one lane's follower and leader by the standing car's heading, not by
# the turning car's; the RSU asked the turning car and found no conflict. The follow
# rule now measures sideways across either car's heading (services.rsu.reservation).
FOUND_BY_SEARCH = [
    ("en", 55.964273891152104, 6.0),
    ("en", 46.25158189414503, 0.0),
    ("en", 84.25158189414503, 7.0),
    ("sw", 84.25, 3.0),
]


# Found by random search (4 Dec, 40 examples of up to 7 cars under paper): under paper, a
# straight car from the north (c0, C_FAST, 13.9 m/s, front 21 m from the zone) and a left
# turn from the south (c2, C_FAST, 5.6 m/s, 2.6 m from it) came to conflict within
# T_collision; neither could stop short braking hard, so c0, the later arriver, yielded,
# and its stop, with no limit from the zone once hard braking could not keep it out, was
# a comfortable one 48 m long, straight through c2's turn. Braking at the firm factor it
# stops 1.7 m before the zone (``VelocityManager.stop_limit``).
FOUND_BY_SEARCH_TURN = [
    ("ns", 48.25, 0.0),
    ("en", 84.25158189414503, 0.0),
    ("sw", 75.25, 0.0),
    ("sw", 84.25, 7.0),
]


@pytest.mark.parametrize("policy", [Policy.PAPER, Policy.SLOT])
@pytest.mark.parametrize(
    "starts", [FOUND_BY_SEARCH, FOUND_BY_SEARCH_TURN], ids=["follow-rule", "turn-stop"]
)
def test_invariant_holds_where_random_search_once_broke_it(
    policy: Policy, starts: list[tuple[str, float, float]]
) -> None:
    _drive(policy, starts, 45.0)
