"""Sensors: range, occlusion by buildings, and the paper's first-sight distance."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from services.model.geometry import segment_blocked
from services.model.kinematics import TruthState
from services.model.scenario import Scenario, load_scenario
from services.sim.sensors import perceive, sight_points

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"
WALL = [np.array([[-1.0, -10.0], [1.0, -10.0], [1.0, 10.0], [-1.0, 10.0]])]


def car(vid: str, x: float, y: float, heading: float = 0.0) -> TruthState:
    return TruthState(vid, 0.0, x, y, heading, 0.0, 0.0, 0.0, 4.5, 1.8)


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


def test_range_is_centre_distance() -> None:
    ego = car("E", 0.0, 0.0)
    near, far = car("N", 79.9, 0.0), car("F", 80.1, 0.0)
    assert perceive(ego, [near, far], [], 80.0) == [near]
    assert perceive(ego, [near, far], [], 100.0) == [near, far]
    assert perceive(ego, [near], [], 0.0) == []


def test_buildings_occlude() -> None:
    ego = car("E", -10.0, 0.0)
    hidden = car("H", 10.0, 0.0)
    beside = car("S", 10.0, 30.0)
    assert perceive(ego, [hidden, beside], WALL, 80.0) == [beside]


def test_a_visible_corner_is_enough() -> None:
    box = [np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])]
    ego = car("E", -10.0, 0.0)
    # The centre is hidden behind the box; the front corners peek out above it.
    peek = car("P", 10.0, 0.0, heading=math.pi / 2)
    assert segment_blocked((ego.x, ego.y), (peek.x, peek.y), box)
    assert perceive(ego, [peek], box, 80.0) == [peek]
    small = TruthState("Q", 0.0, 10.0, 0.0, math.pi / 2, 0.0, 0.0, 0.0, 1.0, 1.0)
    assert perceive(ego, [small], box, 80.0) == []


def test_skips_ego_and_keeps_order() -> None:
    ego = car("E", 0.0, 0.0)
    others = [car("C", 5.0, 0.0), ego, car("A", -5.0, 0.0), car("B", 0.0, 5.0)]
    assert [o.id for o in perceive(ego, others, [], 80.0)] == ["C", "A", "B"]
    assert perceive(ego, [], [], 80.0) == []
    with pytest.raises(ValueError):
        perceive(ego, others, [], -1.0)


def test_sight_points_shape() -> None:
    pts = sight_points([car("A", 0.0, 0.0), car("B", 10.0, 0.0, math.pi / 2)])
    assert pts.shape == (10, 2)
    assert pts[0].tolist() == [0.0, 0.0]
    assert pts[5].tolist() == [10.0, 0.0]
    assert sight_points([]).shape == (0, 2)


def _approach(d: float) -> tuple[TruthState, TruthState]:
    """A eastbound and B northbound, both ``d`` metres from the centre."""
    return car("A", -d, -1.75, 0.0), car("B", 1.75, -d, math.pi / 2)


def _first_sight(paper: Scenario, who: int) -> float:
    lo, hi = 5.0, 40.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        a, b = _approach(mid)
        ego, other = (a, b) if who == 0 else (b, a)
        if perceive(ego, [other], paper.building_polygons, paper.params.sensor_range_m):
            lo = mid
        else:
            hi = mid
    return lo


def test_paper_cars_first_see_each_other_about_16m_out(paper: Scenario) -> None:
    """DESIGN.md: the two approaching cars first see each other roughly 16 m from the
    centre. Centre to centre the sight line clears the building corner (-8, -8) at
    d = (16 + sqrt(243.75)) / 2 = 15.81 m; a footprint corner is seen a little earlier."""
    occ = paper.occluders
    for d in (5.0, 10.0, 14.0, 15.0):
        a, b = _approach(d)
        assert perceive(a, [b], occ, 80.0) == [b]
        assert perceive(b, [a], occ, 80.0) == [a]
    for d in (18.0, 20.0, 40.0, 79.0):
        a, b = _approach(d)
        assert perceive(a, [b], occ, 80.0) == []
        assert perceive(b, [a], occ, 80.0) == []
    centre_line = (16.0 + math.sqrt(243.75)) / 2.0
    a, b = _approach(centre_line - 0.01)
    assert not segment_blocked((a.x, a.y), (b.x, b.y), occ)
    a, b = _approach(centre_line + 0.01)
    assert segment_blocked((a.x, a.y), (b.x, b.y), occ)
    a_sees_b = _first_sight(paper, 0)
    b_sees_a = _first_sight(paper, 1)
    assert a_sees_b == pytest.approx(17.36, abs=0.01)
    assert b_sees_a == pytest.approx(17.55, abs=0.01)
