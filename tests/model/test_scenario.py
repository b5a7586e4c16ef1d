"""Scenario files: the paper's scenario, the compiled view, and refusal of broken files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from protocol import FuturePath, Kind, decode, encode, max_points
from services.model.kinematics import Limits, TruthState
from services.model.scenario import (
    FUTURE_PATH_POINTS_MAX,
    Params,
    RsuParams,
    RsuParamsOverrides,
    Scenario,
    ScenarioError,
    UniformStart,
    VehicleParams,
    VehicleParamsOverrides,
    load_scenario,
    parse_scenario,
)

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"
CORRIDOR = Path(__file__).resolve().parents[1] / "data" / "corridor.toml"


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


@pytest.fixture(scope="module")
def corridor() -> Scenario:
    return load_scenario(CORRIDOR)


# --------------------------------------------------------------------------- the paper


def test_paper_params_are_the_design_numbers(paper: Scenario) -> None:
    p = paper.params
    assert p.v_max_mps == pytest.approx(50 / 3.6, abs=1e-4)
    assert (p.accel_mps2, p.decel_comfort_mps2, p.decel_emergency_mps2) == (1.5, 2.0, 5.0)
    assert p.actuator_lag_s == 0.3
    assert (p.physics_hz, p.planning_hz) == (20, 10)
    assert p.physics_dt_s == pytest.approx(0.05)
    assert p.planning_dt_s == pytest.approx(0.1)
    assert (p.sensor_range_m, p.headway_s, p.d_margin_m) == (80.0, 1.0, 2.8)
    assert (p.t_collision_s, p.t_free_s) == (5.0, 10.0)
    assert (p.reservation_expiry_s, p.coordinated_timeout_s) == (0.5, 0.3)
    assert (p.future_path_points, p.max_sim_s, p.goal_tolerance_m) == (120, 120.0, 1.0)
    # The file spells out the defaults: the model's defaults are the same numbers.
    assert Params().model_dump() == pytest.approx(p.model_dump(), abs=1e-4)


def test_paper_vehicles_and_routes(paper: Scenario) -> None:
    assert paper.name == "paper-blind-intersection"
    assert [v.id for v in paper.vehicles] == ["A", "B"]
    a, b = paper.vehicle("A"), paper.vehicle("B")
    assert a.start_time_s == 0.0
    assert isinstance(b.start_time_s, UniformStart)
    assert b.start_time_s.uniform == (0.0, 1.0)
    assert (a.length_m, a.width_m) == (4.5, 1.8)
    assert paper.goal_m("A") == pytest.approx(350.0)
    ra = paper.route(a.route)
    assert ra.point_at(0.0) == pytest.approx((-200.0, -1.75))
    assert ra.point_at(ra.length) == pytest.approx((150.0, -1.75))
    assert ra.heading_at(10.0) == pytest.approx(0.0)
    rb = paper.vehicle_route("B")
    assert rb.point_at(0.0) == pytest.approx((1.75, -200.0))
    assert rb.heading_at(10.0) == pytest.approx(math.pi / 2)
    assert paper.limits("A") == Limits(13.8889, 1.5, 2.0, 5.0, 0.3)


def test_paper_crossings(paper: Scenario) -> None:
    for vid in ("A", "B"):
        (c,) = paper.vehicle_crossings(vid)
        assert c.intersection == "X1"
        assert (c.s_in, c.s_out, c.center_s) == pytest.approx((196.5, 203.5, 200.0))
        # Front bumper on the stop line 8.5 m from the centre: centre 10.75 m before it.
        assert c.s_stop == pytest.approx(200.0 - 8.5 - 2.25)
    (c6,) = paper.crossings("east", length_m=6.0)
    assert c6.s_stop == pytest.approx(196.5 - 5.0 - 3.0)
    (lc,) = paper.lane_crossings("sb")
    assert (lc.s_in, lc.center_s) == pytest.approx((196.5, 200.0))


def test_paper_crossing_lanes(paper: Scenario) -> None:
    lanes = paper.crossing_lanes("east", "X1")
    assert sorted(a.lane for a in lanes) == ["nb", "sb"]
    for a in lanes:
        assert a.s_in == pytest.approx(196.5)
        assert a.polyline is paper.lane(a.lane)
        x, y = a.polyline.point_at(a.s_in)
        assert max(abs(x), abs(y)) == pytest.approx(3.5)
    assert sorted(a.lane for a in paper.crossing_lanes("north", "X1")) == ["eb", "wb"]


def test_paper_buildings_rsu_and_zone(paper: Scenario) -> None:
    polys = paper.building_polygons
    assert len(polys) == 4
    assert all(p.shape == (4, 2) and not p.flags.writeable for p in polys)
    assert len(paper.occluders) == 4
    xs = sorted({float(np.abs(p[:, 0]).min()) for p in polys})
    assert xs == [8.0]
    rsu = paper.rsu("rsu1")
    assert (rsu.intersection, rsu.coverage_m) == ("X1", 150.0)
    assert paper.zone_polygon("X1").tolist() == [[-3.5, -3.5], [3.5, -3.5], [3.5, 3.5], [-3.5, 3.5]]
    assert paper.intersection("X1").stop_line_offset_m == 5.0
    assert paper.metrics.passing_start_m == 10.0
    assert paper.metrics.passing_end_after_center_m == 100.0


def test_lane_of(paper: Scenario) -> None:
    lane = paper.lane_of(-50.0, -1.9, 0.1)
    assert lane is not None
    assert lane[0] == "eb"
    assert lane[1] == pytest.approx(150.0)
    assert paper.lane_of(-50.0, 1.75, math.pi) == ("wb", 250.0)
    assert paper.lane_of(-50.0, -1.75, math.pi) is None  # wrong way
    assert paper.lane_of(-50.0, -5.0, 0.0) is None  # 3.25 m off the lane
    # In the box, the heading decides between the crossing lanes.
    lane = paper.lane_of(1.0, -1.0, math.pi / 2)
    assert lane is not None and lane[0] == "nb"
    lane = paper.lane_of(1.0, -1.0, 0.0)
    assert lane is not None and lane[0] == "eb"
    assert paper.lane_of(-250.0, -1.75, 0.0) is None  # beyond the lane's start


def test_draw_start_times(paper: Scenario) -> None:
    d1 = paper.draw_start_times(1)
    assert d1 == paper.draw_start_times(1)
    assert d1["A"] == 0.0
    draws = [paper.draw_start_times(seed)["B"] for seed in range(200)]
    assert all(0.0 <= x <= 1.0 for x in draws)
    assert len(set(draws)) == 200
    assert 0.4 < float(np.mean(draws)) < 0.6
    with pytest.raises(ValueError):
        paper.draw_start_times(-1)


def test_draw_depends_only_on_seed_and_id(paper: Scenario) -> None:
    text = PAPER.read_text()
    extra = text.replace(
        "[[rsus]]",
        '[[vehicles]]\nid = "C"\nroute = "east"\nstart_time_s = { uniform = [5.0, 6.0] }\n\n'
        "[[rsus]]",
        1,
    )
    bigger = parse_scenario(extra)
    assert bigger.draw_start_times(9)["B"] == paper.draw_start_times(9)["B"]
    assert 5.0 <= bigger.draw_start_times(9)["C"] <= 6.0


# --------------------------------------------------------------------------- general maps


def test_corridor_crossings_sorted(corridor: Scenario) -> None:
    cs = corridor.crossings("through")
    assert [c.intersection for c in cs] == ["X1", "X2"]
    assert cs[1].s_stop == pytest.approx(296.5 - 3.0 - 2.25)
    follower = corridor.vehicle_crossings("follower")
    assert follower[0].s_stop == pytest.approx(196.5 - 5.0 - 2.5)
    assert corridor.goal_m("follower") == 450.0
    assert corridor.goal_m("lead") == pytest.approx(500.0)
    lim = corridor.limits("follower")
    assert (lim.v_max, lim.accel, lim.decel_comfort) == (10.0, 1.0, 2.0)
    assert corridor.limits("lead").v_max == 12.0


def test_crossing_lanes_of_turns(corridor: Scenario) -> None:
    def lanes(route: str, x: str) -> list[str]:
        return sorted(a.lane for a in corridor.crossing_lanes(route, x))

    assert lanes("through", "X1") == ["nb1", "sb1"]
    assert lanes("through", "X2") == ["nb2"]
    # A left turn also crosses the oncoming lane and merges into nb1.
    assert lanes("left", "X1") == ["nb1", "sb1", "wb"]
    # A right turn only merges with southbound traffic.
    assert lanes("right", "X1") == ["sb1"]
    assert lanes("left", "X2") == []  # never goes there
    with pytest.raises(KeyError):
        corridor.crossing_lanes("nope", "X1")


def test_turning_route_geometry(corridor: Scenario) -> None:
    left = corridor.route("left")
    end = left.point_at(left.length)
    assert end == pytest.approx((1.75, 200.0))
    (c,) = corridor.crossings("left")
    assert c.s_in == pytest.approx(196.5)
    assert c.s_in < c.center_s < c.s_out
    headings = left.headings_at(np.linspace(c.s_in, c.s_out, 50))
    assert headings[0] == pytest.approx(0.0, abs=0.2)
    assert headings[-1] == pytest.approx(math.pi / 2, abs=1e-6)


def test_start_time_uniform_draw_range(corridor: Scenario) -> None:
    for seed in range(20):
        t = corridor.draw_start_times(seed)
        assert 2.0 <= t["crosser"] <= 4.0
        assert t["lead"] == 0.0


# --------------------------------------------------------------------------- refusals

MINIMAL = """
[scenario]
name = "m"

[[intersections]]
id = "X1"
center = [0.0, 0.0]
conflict_zone = [[-3.5, -3.5], [3.5, -3.5], [3.5, 3.5], [-3.5, 3.5]]

[[buildings]]
id = "b1"
polygon = [[8.0, 8.0], [20.0, 8.0], [20.0, 20.0], [8.0, 20.0]]

[[routes]]
id = "r1"
points = [[-100.0, -1.75], [100.0, -1.75]]

[[vehicles]]
id = "A"
route = "r1"

[[vehicles]]
id = "B"
route = "r1"
start_offset_m = 20.0

[[rsus]]
id = "rsu1"
intersection = "X1"
position = [-8.0, 8.0]
"""


def test_minimal_file_uses_defaults() -> None:
    sc = parse_scenario(MINIMAL)
    assert sc.params == Params()
    assert sc.vehicle("B").start_offset_m == 20.0
    assert sc.rsu("rsu1").coverage_m == 150.0
    assert sc.metrics.passing_start_m == 10.0


def _refused(text: str) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        parse_scenario(text, "test.toml")
    return info.value


@pytest.mark.parametrize(
    ("old", "new", "path", "reason"),
    [
        # unknown keys, at the top and deep inside
        (
            '[scenario]\nname = "m"',
            '[scenario]\nname = "m"\ncolour = "red"',
            "scenario.colour",
            "unknown key",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nspeed = 3.0\nstart_offset_m',
            "vehicles[1].speed",
            "unknown key",
        ),
        ("[[rsus]]", "[bogus]\nx = 1\n\n[[rsus]]", "bogus", "unknown key"),
        # a vehicle on a route that does not exist
        (
            'route = "r1"\nstart_offset_m',
            'route = "r9"\nstart_offset_m',
            "vehicles[1].route",
            "unknown route 'r9'",
        ),
        # a priority road on a lane that does not exist
        (
            "[[buildings]]",
            'priority_lanes = ["r1"]\n\n[[buildings]]',
            "intersections[0].priority_lanes[0]",
            "unknown lane 'r1'",
        ),
        # polygons
        (
            "polygon = [[8.0, 8.0], [20.0, 8.0], [20.0, 20.0], [8.0, 20.0]]",
            "polygon = [[8.0, 8.0], [20.0, 20.0], [20.0, 8.0], [8.0, 20.0]]",
            "buildings[0].polygon",
            "convex",
        ),
        (
            "polygon = [[8.0, 8.0], [20.0, 8.0], [20.0, 20.0], [8.0, 20.0]]",
            "polygon = [[8.0, 8.0], [20.0, 8.0]]",
            "buildings[0].polygon",
            "at least 3",
        ),
        (
            "conflict_zone = [[-3.5, -3.5], [3.5, -3.5], [3.5, 3.5], [-3.5, 3.5]]",
            "conflict_zone = [[-3.5, -3.5], [3.5, -3.5], [0.0, 0.0], [3.5, 3.5], [-3.5, 3.5]]",
            "intersections[0].conflict_zone",
            "convex",
        ),
        ("center = [0.0, 0.0]", "center = [10.0, 0.0]", "intersections[0].center", "conflict_zone"),
        # ids
        ('id = "A"', 'id = "A car"', "vehicles[0].id", "not a valid id"),
        ('id = "A"', 'id = "' + "x" * 33 + '"', "vehicles[0].id", "not a valid id"),
        ('id = "B"', 'id = "A"', "vehicles[1].id", "duplicate id 'A'"),
        ('id = "rsu1"', 'id = "A"', "rsus[0].id", "also a vehicle"),
        # start time ranges
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nstart_time_s = { uniform = [2.0, 1.0] }\nstart_offset_m',
            "vehicles[1].start_time_s.uniform",
            "exceeds",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nstart_time_s = "soon"\nstart_offset_m',
            "vehicles[1].start_time_s",
            "uniform = [lo, hi]",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nstart_time_s = { normal = 1 }\nstart_offset_m',
            "vehicles[1].start_time_s.uniform",
            "required",
        ),
        # sizes, speeds, types
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nlength_m = 0.0\nstart_offset_m',
            "vehicles[1].length_m",
            "greater than 0",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nwidth_m = "2"\nstart_offset_m',
            "vehicles[1].width_m",
            "number",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\ndynamics = { v_max_mps = -3.0 }\nstart_offset_m',
            "vehicles[1].dynamics.v_max_mps",
            "greater than 0",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\ndynamics = { decel_emergency_mps2 = 1.0 }\nstart_offset_m',
            "vehicles[1].dynamics",
            "decel_emergency",
        ),
        (
            '[scenario]\nname = "m"',
            '[scenario]\nname = "m"\n[params]\nv_max_mps = nan',
            "params.v_max_mps",
            "finite",
        ),
        (
            '[scenario]\nname = "m"',
            '[scenario]\nname = "m"\n[params]\nphysics_hz = 20.0',
            "params.physics_hz",
            "integer",
        ),
        (
            '[scenario]\nname = "m"',
            '[scenario]\nname = "m"\n[params]\nphysics_hz = 25',
            "params",
            "multiple of planning_hz",
        ),
        (
            '[scenario]\nname = "m"',
            '[scenario]\nname = "m"\n[params]\ndecel_comfort_mps2 = 6.0',
            "params",
            "decel_emergency",
        ),
        # route geometry and goals
        (
            "start_offset_m = 20.0",
            "start_offset_m = 250.0",
            "vehicles[1].start_offset_m",
            "route's end",
        ),
        (
            "start_offset_m = 20.0",
            "start_offset_m = 20.0\ngoal_m = 300.0",
            "vehicles[1].goal_m",
            "beyond",
        ),
        (
            "start_offset_m = 20.0",
            "start_offset_m = 20.0\ngoal_m = 10.0",
            "vehicles[1].goal_m",
            "after start_offset_m",
        ),
        (
            "points = [[-100.0, -1.75], [100.0, -1.75]]",
            "points = [[-100.0, -1.75]]",
            "routes[0].points",
            "at least 2",
        ),
        (
            "points = [[-100.0, -1.75], [100.0, -1.75]]",
            "points = [[-100.0, -1.75], [-100.0, -1.75], [100.0, -1.75]]",
            "routes[0].points",
            "zero-length",
        ),
        (
            "points = [[-100.0, -1.75], [100.0, -1.75]]",
            "points = [[-100.0, 12.0], [100.0, 12.0]]",
            "routes[0]",
            "building",
        ),
        (
            "points = [[-100.0, -1.75], [100.0, -1.75]]",
            "points = [[-100.0, -1.75], [100.0, -1.75], [100.0, 1.75], [-100.0, 1.75]]",
            "routes[0]",
            "more than once",
        ),
        # cross references
        (
            'intersection = "X1"',
            'intersection = "X7"',
            "rsus[0].intersection",
            "unknown intersection 'X7'",
        ),
        # required sections
        ('[scenario]\nname = "m"', "", "scenario", "required"),
    ],
)
def test_broken_files_are_refused_with_path(old: str, new: str, path: str, reason: str) -> None:
    assert old in MINIMAL
    err = _refused(MINIMAL.replace(old, new, 1))
    assert err.path == path, str(err)
    assert reason in err.reason, str(err)
    assert str(err).startswith(f"test.toml: {path}: ")


def test_toml_syntax_and_unreadable_file(tmp_path: Path) -> None:
    err = _refused("[scenario\nname = 1")
    assert err.path == ""
    assert "TOML" in err.reason
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text(MINIMAL.replace('route = "r1"\nstart_offset_m', 'route = "zz"\nstart_offset_m'))
    with pytest.raises(ScenarioError, match=r"bad\.toml: vehicles\[1\]\.route: unknown route"):
        load_scenario(bad)


def test_scenario_error_is_a_value_error() -> None:
    assert issubclass(ScenarioError, ValueError)
    err = _refused(MINIMAL.replace('id = "A"', 'id = ""', 1))
    assert err.path == "vehicles[0].id"
    assert err.source == "test.toml"


def test_readme_example_parses() -> None:
    text = (ROOT / "scenarios" / "README.md").read_text()
    block = text.split("```toml\n", 1)[1].split("```", 1)[0]
    sc = parse_scenario(block, "README.md")
    assert sc.name == "tiny"
    assert sc.limits("A").v_max == 8.0
    (c,) = sc.vehicle_crossings("A")
    assert c.intersection == "X1"
    assert 0.0 <= sc.draw_start_times(3)["A"] <= 2.0


# --------------------------------------------------------------------------- what the wire carries


def _with_params(extra: str) -> str:
    """MINIMAL with ``extra`` TOML lines appended to a fresh ``[params]`` table."""
    return MINIMAL.replace('[scenario]\nname = "m"', f'[scenario]\nname = "m"\n[params]\n{extra}')


def test_future_path_points_beyond_the_codec_are_refused_at_load() -> None:
    """``future_path_points = 300`` used to load and then crash ``crosspath sim`` with an
    EncodeError; the loader now names the field and the codec's limit."""
    cap = min(max_points(Kind.FUTURE_PATH), max_points(Kind.AUTONOMOUS_PATH))
    assert cap == FUTURE_PATH_POINTS_MAX
    err = _refused(_with_params("future_path_points = 300"))
    assert err.path == "params.future_path_points", str(err)
    assert f"at most {cap}" in err.reason and "datagram" in err.reason
    assert parse_scenario(_with_params(f"future_path_points = {cap}")).params.future_path_points


def test_the_most_points_the_loader_accepts_encode() -> None:
    """The largest accepted future path is sent without an EncodeError."""
    from services.vehicle.agent import vehicle_agent

    cap = FUTURE_PATH_POINTS_MAX
    sc = parse_scenario(_with_params(f"future_path_points = {cap}"))
    agent = vehicle_agent(sc, "A", v2x=True)
    route = sc.vehicle_route("A")
    x, y = route.point_at(5.0)  # slow and far from the goal: every point is kept
    ego = TruthState("A", 0.0, x, y, route.heading_at(5.0), 5.0, 0.0, 5.0, 4.5, 1.8)
    (out,) = agent.tick(0.0, ego, []).outbound
    assert out.message.points.shape[0] == cap
    back = decode(encode(out.message))
    assert isinstance(back, FuturePath) and back.points.shape == (cap, 3)


@pytest.mark.parametrize(
    ("old", "new", "path", "reason"),
    [
        # speeds: v_max x SPEED_CAP_FACTOR must fit the wire's MAX_SPEED_MPS
        ('name = "m"', 'name = "m"\n[params]\nv_max_mps = 99.0', "params.v_max_mps", "m/s"),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\ndynamics = { v_max_mps = 99.0 }\nstart_offset_m',
            "vehicles[1].dynamics.v_max_mps",
            "the wire carries at most 100 m/s",
        ),
        # sizes
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nlength_m = 60.0\nstart_offset_m',
            "vehicles[1].length_m",
            "0.01..50 m",
        ),
        (
            'route = "r1"\nstart_offset_m',
            'route = "r1"\nwidth_m = 0.001\nstart_offset_m',
            "vehicles[1].width_m",
            "0.01..10 m",
        ),
        (
            "position = [-8.0, 8.0]",
            "position = [-8.0, 8.0]\ncoverage_m = 2e4",
            "rsus[0].coverage_m",
            "10000",
        ),
        # coordinates
        ("center = [0.0, 0.0]", "center = [2e7, 0.0]", "intersections[0].center[0]", "±1e+07 m"),
        (
            "points = [[-100.0, -1.75], [100.0, -1.75]]",
            "points = [[-100.0, -1.75], [1e8, -1.75]]",
            "routes[0].points[1][0]",
            "beyond the wire format",
        ),
        # time between path points: a standing car's future path spans t_free_s in one step
        ('name = "m"', 'name = "m"\n[params]\nt_free_s = 70.0', "params.t_free_s", "65.535 s"),
        # distance between path points, also after the RSU thins a coordinated path
        (
            'name = "m"',
            'name = "m"\n[params]\nv_max_mps = 90.0\nfuture_path_points = 3',
            "params.future_path_points",
            "at most 327.67 m between points",
        ),
        (
            'route = "r1"\nstart_offset_m = 20.0',
            'route = "r1"\nstart_offset_m = 20.0\ndynamics = { v_max_mps = 90.0 }\n'
            "[params]\nfuture_path_points = 3",
            "vehicles[1].dynamics.v_max_mps",
            "327.67 m",
        ),
    ],
)
def test_what_the_codec_cannot_carry_is_refused(old: str, new: str, path: str, reason: str) -> None:
    assert old in MINIMAL
    err = _refused(MINIMAL.replace(old, new, 1))
    assert err.path == path, str(err)
    assert reason in err.reason, str(err)


# --------------------------------------------------------------------------- RSU and vehicle knobs


def test_cross_field_nonsense_is_refused_with_the_field_path() -> None:
    err = _refused(_with_params("t_collision_s = 12.0"))
    assert err.path == "params.t_collision_s" and "t_free_s (10.0 s)" in err.reason
    err = _refused(_with_params("t_free_s = 4.0"))
    assert err.path == "params.t_collision_s" and "t_free_s (4.0 s)" in err.reason
    # slot_min_speed_mps must stay below v_max, from the shared table or the RSU's own
    text = MINIMAL + "\n[rsu_params]\nslot_min_speed_mps = 14.0\n"
    err = _refused(text)
    assert err.path == "rsu_params.slot_min_speed_mps" and "v_max_mps" in err.reason
    text = MINIMAL + "params = { slot_min_speed_mps = 20.0 }\n"
    err = _refused(text)
    assert err.path == "rsus[0].params.slot_min_speed_mps", str(err)
    # hold points every 2 headways or more could let a crossing point through unseen
    err = _refused(MINIMAL + "params = { hold_step_s = 2.0 }\n")
    assert err.path == "rsus[0].params.hold_step_s" and "headway" in err.reason
    # a crawl so slow that consecutive coordinated points are more than 65.535 s apart
    err = _refused(MINIMAL + "\n[rsu_params]\nslot_min_speed_mps = 0.01\n")
    assert err.path == "rsu_params.slot_min_speed_mps" and "65.535 s" in err.reason


def test_rsu_params_defaults_and_overrides() -> None:
    sc = parse_scenario(MINIMAL)
    assert sc.spec.rsu_params == RsuParams() and sc.rsu_params("rsu1") == RsuParams()
    sc = parse_scenario(
        MINIMAL
        + "params = { hold_step_s = 0.25 }\n\n[rsu_params]\nhold_step_s = 0.4\nstop_gap_m = 3.0\n"
    )
    knobs = sc.rsu_params("rsu1")
    assert (knobs.hold_step_s, knobs.stop_gap_m) == (0.25, 3.0)  # the RSU's own key wins
    assert sc.spec.rsu_params.hold_step_s == 0.4
    with pytest.raises(KeyError):
        sc.rsu_params("nope")


def test_override_tables_have_the_fields_of_their_table() -> None:
    assert set(RsuParamsOverrides.model_fields) == set(RsuParams.model_fields)
    # the future-path rule is scenario-wide: every receiver's expiry follows it
    scenario_wide = {
        "fp_rule",
        "fp_change_m",
        "fp_refresh_s",
        "ap_rule",
        "ap_refresh_s",
        "cp_rule",
        "cp_refresh_s",
    }
    assert (
        set(VehicleParamsOverrides.model_fields) == set(VehicleParams.model_fields) - scenario_wide
    )
    assert RsuParamsOverrides().model_dump() == dict.fromkeys(RsuParams.model_fields)


def test_vehicle_params_defaults_and_overrides() -> None:
    sc = parse_scenario(MINIMAL)
    assert sc.vehicle_params("A") == VehicleParams() == sc.spec.vehicle_params
    text = MINIMAL.replace(
        'id = "B"\nroute = "r1"', 'id = "B"\nroute = "r1"\nparams = { creep_mps = 0.5 }'
    )
    sc = parse_scenario(text + "\n[vehicle_params]\ncreep_mps = 1.0\nfp_stale_s = 0.8\n")
    assert (sc.vehicle_params("A").creep_mps, sc.vehicle_params("B").creep_mps) == (1.0, 0.5)
    assert sc.vehicle_params("B").fp_stale_s == 0.8
    err = _refused(text.replace("creep_mps = 0.5", "creep_mps = 0.0"))
    assert err.path == "vehicles[1].params.creep_mps"
    err = _refused(MINIMAL + "\n[vehicle_params]\nwarp = 1\n")
    assert err.path == "vehicle_params.warp" and err.reason == "unknown key"


# ------------------------------------------------------------------ flows (issue 12)

FLOW = """
[[flows]]
id = "f"
route = "r1"
vehicles_per_hour = 600.0
end_s = 60.0
"""


def _with_flow(flow: str = FLOW, base: str = MINIMAL) -> str:
    return base + flow


def test_flow_cars_are_named_and_appended_after_the_vehicles() -> None:
    sc = parse_scenario(_with_flow())
    assert [v.id for v in sc.vehicles] == ["A", "B"]  # unseeded: flows not drawn
    trial = sc.for_seed(3)
    arrivals = sc.draw_arrivals(3)["f"]
    ids = [v.id for v in trial.vehicles]
    assert ids[:2] == ["A", "B"]
    assert ids[2:] == [f"f-{n}" for n in range(len(arrivals))]
    assert len(arrivals) > 0
    starts = trial.draw_start_times(3)
    assert [starts[f"f-{n}"] for n in range(len(arrivals))] == arrivals
    assert all(0.0 <= t < 60.0 for t in arrivals)
    assert arrivals == sorted(arrivals)
    car = trial.vehicle("f-0")
    assert car.route == "r1" and car.start_offset_m == 0.0 and car.goal_m == pytest.approx(200.0)
    assert trial.spec.flows == []
    assert parse_scenario(MINIMAL).for_seed(3).vehicles == parse_scenario(MINIMAL).vehicles


def test_flow_without_vehicles_and_with_its_own_dynamics() -> None:
    base = MINIMAL.split("[[vehicles]]", 1)[0] + MINIMAL.split("start_offset_m = 20.0\n", 1)[1]
    flow = FLOW + "length_m = 5.0\nwidth_m = 2.0\ndynamics = { v_max_mps = 10.0 }\n"
    sc = parse_scenario(_with_flow(flow, base))
    assert sc.vehicles == ()
    trial = sc.for_seed(0)
    assert trial.vehicles and all(v.id.startswith("f-") for v in trial.vehicles)
    assert trial.vehicle("f-0").length_m == 5.0
    assert trial.limits("f-0").v_max == 10.0


def test_same_seed_same_arrivals_different_seed_different() -> None:
    sc = parse_scenario(_with_flow())
    assert sc.draw_arrivals(7) == sc.draw_arrivals(7)
    assert sc.draw_arrivals(7) != sc.draw_arrivals(8)
    assert [v.id for v in sc.for_seed(7).vehicles] == [v.id for v in sc.for_seed(7).vehicles]


def test_poisson_counts_vary_around_the_rate_uniform_counts_are_exact() -> None:
    poisson = parse_scenario(_with_flow())  # 600 veh/h over 60 s: 10 expected
    counts = [len(poisson.draw_arrivals(seed)["f"]) for seed in range(200)]
    assert len(set(counts)) > 3
    assert 9.0 < float(np.mean(counts)) < 11.0
    uniform = parse_scenario(_with_flow(FLOW + 'arrivals = "uniform"\nbegin_s = 5.0\n'))
    times = uniform.draw_arrivals(0)["f"]
    assert times == uniform.draw_arrivals(1)["f"]
    assert len(times) == 10  # 60 - 5 = 55 s at one car per 6 s: 5, 11, ..., 59
    assert times[0] == 5.0 and np.allclose(np.diff(times), 6.0)


def test_seed_is_checked() -> None:
    sc = parse_scenario(_with_flow())
    with pytest.raises(ValueError, match="seed"):
        sc.draw_arrivals(-1)


@pytest.mark.parametrize(
    ("old", "new", "path", "reason"),
    [
        ("vehicles_per_hour = 600.0", "vehicles_per_hour = 0.0", "flows[0].vehicles_per_hour", ""),
        ("end_s = 60.0", "", "flows[0].end_s", "required"),
        ("end_s = 60.0", "end_s = 60.0\nbegin_s = 60.0", "flows[0]", "after begin_s"),
        ("end_s = 60.0", 'end_s = 60.0\narrivals = "burst"', "flows[0].arrivals", ""),
        ('route = "r1"', 'route = "zz"', "flows[0].route", "unknown route"),
        ('id = "f"', 'id = "' + "f" * 28 + '"', "flows[0].id", "too long for a flow id"),
        ('id = "f"', 'id = "A"\n', "flows[0].id", ""),  # fine id: refused below for clash
        ("end_s = 60.0", "end_s = 60.0\ncolour = 1", "flows[0].colour", "unknown key"),
        (
            "vehicles_per_hour = 600.0",
            "vehicles_per_hour = 600000.0",
            "flows[0].vehicles_per_hour",
            "at most 5000",
        ),
        (
            "end_s = 60.0",
            "end_s = 60.0\ndynamics = { v_max_mps = 99.0 }",
            "flows[0].dynamics.v_max_mps",
            "the wire carries",
        ),
    ],
)
def test_broken_flows_are_refused_with_path(old: str, new: str, path: str, reason: str) -> None:
    text = _with_flow(FLOW.replace(old, new, 1))
    if path == "flows[0].id" and not reason:
        text = text.replace('id = "A"\nroute = "r1"', 'id = "A-1"\nroute = "r1"', 1)
        reason = "'A-1' is already a vehicle"
    err = _refused(text)
    assert err.path == path, str(err)
    assert reason in err.reason, str(err)


def test_a_flow_id_of_27_characters_is_accepted() -> None:
    sc = parse_scenario(_with_flow(FLOW.replace('id = "f"', 'id = "' + "f" * 27 + '"')))
    assert max(len(v.id) for v in sc.for_seed(0).vehicles) <= 32


def test_a_scenario_needs_vehicles_or_flows() -> None:
    base = MINIMAL.split("[[vehicles]]", 1)[0] + MINIMAL.split("start_offset_m = 20.0\n", 1)[1]
    err = _refused(base)
    assert err.path == "vehicles" and "[[flows]]" in err.reason


def test_packaged_four_way_flows_loads() -> None:
    sc = load_scenario(ROOT / "scenarios" / "four-way-flows.toml")
    assert len(sc.route_ids) == 12 and len(sc.spec.flows) == 12 and len(sc.rsus) == 1
    trial = sc.for_seed(0)
    assert len(trial.vehicles) > 12
    for rid in sc.route_ids:
        assert len(sc.crossings(rid)) == 1
