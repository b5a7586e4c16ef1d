"""``crosspath scenario from-sumo``: a SUMO network becomes a scenario that runs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from services.api import simulate
from services.cli.main import main
from services.model.scenario import load_scenario
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


def test_not_a_network_is_one_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.net.xml"
    bad.write_text("<routes/>")
    with pytest.raises(SumoNetError, match="not a SUMO network"):
        scenario_from_net(bad)
    assert main(["scenario", "from-sumo", str(bad), "-o", str(tmp_path / "x.toml")]) == 2
    assert "not a SUMO network" in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()
