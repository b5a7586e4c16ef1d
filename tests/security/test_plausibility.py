"""The RSU's plausibility check (services.rsu.plausibility): real paths pass, forged ones
are refused with the right reason."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from protocol import FuturePath, Header, Message, Mode, VehiclePath
from services.model.scenario import Scenario, load_scenario
from services.model.types import RunMode
from services.rsu.plausibility import ZONE_STAND_S, Bounds, Seen, check_path
from services.sim.harness import SimOptions, Simulation

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


@pytest.fixture(scope="module")
def genuine(paper: Scenario) -> list[VehiclePath]:
    """Every vehicle path the cars sent in an rsu-mode run of the paper scenario."""
    sent: list[VehiclePath] = []
    original = Simulation._send

    def spy(self: Simulation, now: float, key: str, message: Message, rx: list[str]) -> None:
        if isinstance(message, VehiclePath):
            sent.append(message)
        original(self, now, key, message, rx)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Simulation, "_send", spy)
        Simulation(paper, SimOptions(mode=RunMode.RSU, seed=0)).run()
    assert len(sent) > 100
    return sent


def test_genuine_paths_are_plausible(paper: Scenario, genuine: list[VehiclePath]) -> None:
    bounds = Bounds.from_scenario(paper)
    seen: dict[tuple[str, int], Seen] = {}
    refused = []
    for m in genuine:
        lane = (m.header.sender, int(m.kind))
        why, seen[lane] = check_path(m, seen.get(lane), bounds)
        if why is not None:
            refused.append((m.header.sender, m.header.time_s, why))
    assert refused == []


def _a_path(genuine: list[VehiclePath]) -> FuturePath:
    fps = [m for m in genuine if isinstance(m, FuturePath) and m.speed > 5.0]
    return fps[len(fps) // 2]


def test_forged_paths_are_refused(paper: Scenario, genuine: list[VehiclePath]) -> None:
    bounds = Bounds.from_scenario(paper)
    m = _a_path(genuine)
    assert check_path(m, None, bounds)[0] is None
    fast = dataclasses.replace(m, speed=bounds.v_max + 1)
    assert check_path(fast, None, bounds)[0] == "implausible_speed"
    pts = m.points.copy()
    pts[:, 0] = pts[0, 0] + (pts[:, 2] - pts[0, 2]) * (bounds.v_max + 5)
    pts[:, 1] = pts[0, 1]
    assert check_path(dataclasses.replace(m, points=pts), None, bounds)[0] == (
        "implausible_path_speed"
    )
    jerky = m.points.copy()
    half = len(jerky) // 2
    jerky[half:, 0] = jerky[half - 1, 0]  # stops dead from cruising speed
    jerky[half:, 1] = jerky[half - 1, 1]
    assert check_path(dataclasses.replace(m, points=jerky), None, bounds)[0] == (
        "implausible_path_accel"
    )
    far = m.points.copy()
    far[:, 0] += 50.0
    assert check_path(dataclasses.replace(m, points=far), None, bounds)[0] == (
        "implausible_path_start"
    )
    before = Seen(m.x - 100.0, m.y, m.header.time_s - 0.1)
    assert check_path(m, before, bounds)[0] == "implausible_jump"


def test_a_car_parked_in_the_zone_claiming_to_approach_is_refused(paper: Scenario) -> None:
    bounds = Bounds.from_scenario(paper)
    it = paper.intersections[0]
    cx, cy = it.center
    pts = np.array([[cx, cy, 0.0], [cx + 5, cy, 1.0], [cx + 15, cy, 2.0]])
    seen = None
    reasons = []
    for k in range(int(ZONE_STAND_S * 10) + 5):
        t = k / 10
        p = pts.copy()
        p[:, 2] += t
        m = FuturePath(
            Header("ghost", k, round(t * 1e6)), cx, cy, 0.0, 0.0, 4.5, 1.8, Mode.C_FAST, p
        )
        why, seen = check_path(m, seen, bounds)
        reasons.append(why)
    assert reasons[0] is None
    assert reasons[-1] == "implausible_zone_stop"
