"""``crosspath scenario from-sumo``: a SUMO network becomes a scenario that runs."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import pytest

from services.api import simulate
from services.cli.main import main
from services.model.geometry import polygon_contains
from services.model.scenario import Scenario, load_scenario
from services.sumo.from_sumo import SumoNetError, _hull, _Ids, scenario_from_net, write_scenario
from services.sumo.netgen import Control


def test_hull_of_a_rounded_cross_is_convex_and_keeps_the_arm_ends() -> None:
    plus = [
        (-3.5, 5.5), (3.5, 5.5), (4.0, 4.0), (5.5, 3.5), (5.5, -3.5), (4.0, -4.0),
        (3.5, -5.5), (-3.5, -5.5), (-4.0, -4.0), (-5.5, -3.5), (-5.5, 3.5), (-4.0, 4.0),
    ]  # fmt: skip
    hull = _hull(plus)
    assert len(hull) == 8  # the four concave corner points are inside
    for i in range(len(hull)):
        (ax, ay), (bx, by), (cx, cy) = hull[i], hull[(i + 1) % 8], hull[(i + 2) % 8]
        assert (bx - ax) * (cy - by) - (by - ay) * (cx - bx) > 0  # counter-clockwise, convex


def test_sumo_ids_become_valid_unique_ids() -> None:
    ids = _Ids()
    assert ids(":c_0_0") == "c_0_0"
    assert ids("a#b.c") == "a_b_c"
    assert ids("a#b.c") == "a_b_c-2"
    assert len(ids("x" * 80)) <= 32


def test_four_way_round_trip(short_nets: dict[Control, Path], tmp_path: Path) -> None:
    net = short_nets[Control.PRIORITY]
    sc = scenario_from_net(net, stagger_s=3.0)
    back = load_scenario(write_scenario(sc, tmp_path / "fw.toml"))
    assert back.spec == sc.spec
    assert len(back.route_ids) == 12  # 4 approaches x (straight, left, right)
    assert "w_in-e_out" in back.route_ids and "w_in-n_out" in back.route_ids
    assert len(back.lane_ids) == 4  # each straight pair chained through the junction
    (it,) = back.intersections
    assert it.center == (0.0, 0.0)
    # the zone is SUMO's junction shape's hull: the arms end 5.5 m from the centre
    assert max(abs(x) for x, _ in it.conflict_zone) == pytest.approx(5.5)
    for rid in back.route_ids:
        (crossing,) = back.crossings(rid)
        assert crossing.s_in == pytest.approx(40.0 - 5.5, abs=0.01)
        start = back.route(rid).points_at([0.0])[0]
        assert math.hypot(*start) == pytest.approx(math.hypot(40.0, 1.75), abs=0.01)
    assert [r.intersection for r in back.rsus] == [it.id]
    assert len(back.vehicles) == 12
    starts = [v.start_time_s for v in back.vehicles]
    assert all(isinstance(t, float) for t in starts)
    assert sorted(t for t in starts if isinstance(t, float)) == [3.0 * i for i in range(12)]
    # netgen's priority road runs east-west (edge priority 2 against 1): its lanes, both ways
    assert it.priority_lanes == ["e_in_0", "w_in_0"]


@pytest.mark.parametrize("control", [Control.ALLWAY_STOP, Control.UNREGULATED])
def test_no_priority_road_where_the_junction_has_none(
    short_nets: dict[Control, Path], control: Control
) -> None:
    (it,) = scenario_from_net(short_nets[control]).intersections
    assert it.priority_lanes == []


def test_flows_instead_of_cars(short_nets: dict[Control, Path]) -> None:
    sc = scenario_from_net(short_nets[Control.PRIORITY], vehicles_per_hour=100.0, flow_end_s=60.0)
    assert len(sc.spec.flows) == 12 and not sc.vehicles
    assert {f.vehicles_per_hour for f in sc.spec.flows} == {100.0}


@pytest.mark.slow  # 12 cars for about a minute of run time in-process
def test_converted_network_runs_in_crosspath_sim(
    short_nets: dict[Control, Path], tmp_path: Path
) -> None:
    out = tmp_path / "fw.toml"
    assert main(["scenario", "from-sumo", str(short_nets[Control.PRIORITY]), "-o", str(out),
                 "--stagger", "3"]) == 0  # fmt: skip
    result = simulate(out, mode="standalone", seed=0)
    assert result.collisions == 0
    assert result.all_finished
    assert len(result.vehicles) == 12


def _start(sc: Scenario, route_id: str) -> tuple[float, float]:
    x, y = sc.route(route_id).points_at([0.0])[0]
    return round(float(x), 3), round(float(y), 3)


def test_corridor_routes_run_through_several_junctions(
    corridors: dict[int, Path], tmp_path: Path
) -> None:
    sc = scenario_from_net(corridors[3])
    back = load_scenario(write_scenario(sc, tmp_path / "c3.toml"))
    assert back.spec == sc.spec
    # one intersection per junction, at the junction, each with its own RSU there
    assert [it.id for it in back.intersections] == ["j0", "j1", "j2"]
    assert [it.center for it in back.intersections] == [(0.0, 0.0), (40.0, 0.0), (80.0, 0.0)]
    assert [(r.id, r.intersection) for r in back.rsus] == [(f"rsu-j{k}", f"j{k}") for k in range(3)]
    assert all(r.position == back.intersection(r.intersection).center for r in back.rsus)
    # 8 entries (w, e, n0..n2, s0..s2), each to the 7 exits but its own arm; ids unique
    rids = back.route_ids
    assert len(rids) == len(set(rids)) == 8 * 7
    assert len({_start(back, r) for r in rids}) == 8
    assert sorted(v.route for v in back.vehicles) == sorted(rids)
    through = Counter[int]()
    for rid in rids:
        crossings = back.crossings(rid)
        line = back.route(rid)
        # each zone the route's crossings name contains the route between s_in and s_out
        for c in crossings:
            assert 0.0 < c.s_in < c.s_out < line.length
            ((x, y),) = line.points_at([0.5 * (c.s_in + c.s_out)])
            assert polygon_contains(back.intersection(c.intersection).conflict_zone, x, y)
        # the junctions it passes are consecutive ones of the corridor, each once, in order
        ks = [int(c.intersection.removeprefix("j")) for c in crossings]
        step = 1 if ks[-1] >= ks[0] else -1
        assert ks == list(range(ks[0], ks[-1] + step, step))
        through[len(ks)] += 1
    assert through == {1: 14, 2: 24, 3: 18}
    assert [c.intersection for c in back.crossings("w_j0-j2_e")] == ["j0", "j1", "j2"]
    assert [c.intersection for c in back.crossings("e_j2-j0_w")] == ["j2", "j1", "j0"]


def test_corridor_runs_in_crosspath_sim_with_an_rsu_per_junction(
    corridors: dict[int, Path], tmp_path: Path
) -> None:
    out = tmp_path / "c2.toml"
    assert main(["scenario", "from-sumo", str(corridors[2]), "-o", str(out),
                 "--stagger", "2", "--max-routes", "4"]) == 0  # fmt: skip
    sc = load_scenario(out)
    assert len(sc.route_ids) == len(sc.vehicles) == 4
    # with a cap, each entry's routes through the most junctions come first: both here
    assert all([c.intersection for c in sc.crossings(r)] in (["j0", "j1"], ["j1", "j0"])
               for r in sc.route_ids)  # fmt: skip
    result = simulate(out, mode="rsu", seed=0)
    assert result.collisions == 0
    assert result.all_finished and len(result.vehicles) == 4
    assert all(v.finished for v in result.vehicles.values())
    assert result.provenance is not None
    assert result.provenance.policy_params.keys() == {"rsu-j0", "rsu-j1"}


def test_max_routes_caps_the_routes_and_keeps_every_entry(corridors: dict[int, Path]) -> None:
    net = corridors[2]
    for bad in (0, -1, True, False):
        with pytest.raises(ValueError, match="max_routes"):
            scenario_from_net(net, max_routes=bad)
    full = scenario_from_net(net)
    assert len(full.route_ids) == 6 * 5  # 6 entries, each to the 5 exits but its own arm
    entries = {_start(full, r) for r in full.route_ids}
    assert len(entries) == 6
    assert scenario_from_net(net, max_routes=30).spec == full.spec
    for cap in (1, 6, 7, 13):
        sc = scenario_from_net(net, max_routes=cap)
        assert len(sc.route_ids) == len(sc.vehicles) == cap
        assert set(sc.route_ids) <= set(full.route_ids)
        starts = [_start(sc, r) for r in sc.route_ids]
        # round robin over the entries: every entry once before any twice
        per_entry = Counter(starts)
        assert len(per_entry) == min(cap, 6)
        assert max(per_entry.values()) - min(per_entry.values()) <= 1
        assert set(per_entry) <= entries


def test_not_a_network_is_one_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.net.xml"
    bad.write_text("<routes/>")
    with pytest.raises(SumoNetError, match="not a SUMO network"):
        scenario_from_net(bad)
    assert main(["scenario", "from-sumo", str(bad), "-o", str(tmp_path / "x.toml")]) == 2
    assert "not a SUMO network" in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()
