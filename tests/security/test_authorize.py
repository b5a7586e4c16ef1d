"""A car obeys only an RSU certified for the intersection it approaches, inside its coverage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from protocol import Command, CoordinatedPath, Header, Mode, ModeCommand, RsuBeacon
from protocol.auth import Certificate, Coverage, Role, issue_certificate, public_bytes
from services.model.scenario import Scenario, load_scenario
from services.vehicle.authorize import approaching, refusal

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"
ROOT = Ed25519PrivateKey.generate()


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


def rsu_cert(rsu: str, intersections: tuple[str, ...], cover: Coverage) -> Certificate:
    key = Ed25519PrivateKey.generate()
    return issue_certificate(
        ROOT,
        rsu,
        Role.RSU,
        public_bytes(key),
        0,
        2**32 - 1,
        intersections=intersections,
        coverage=cover,
    )


def initiate(rsu: str = "rsu1") -> ModeCommand:
    return ModeCommand(Header(rsu, 1, 0), "A", Command.INITIATE, Mode.C_FAST)


def test_only_the_rsu_of_the_approached_intersection_inside_coverage(paper: Scenario) -> None:
    car = paper.vehicles[0].id
    crossings = paper.vehicle_crossings(car)
    here = paper.vehicle_route(car).point_at(crossings[0].s_in - 30.0)
    x, y = float(here[0]), float(here[1])
    s = crossings[0].s_in - 30.0
    target = approaching(crossings, s)
    assert target == crossings[0].intersection
    spec = paper.rsus[0]
    good = rsu_cert(spec.id, (target,), Coverage(spec.position[0], spec.position[1], 150.0))
    cp = CoordinatedPath(Header(spec.id, 2, 0), "A", Mode.C_FAST, np.zeros((0, 3)), np.zeros(0))
    assert refusal(initiate(spec.id), good, crossings, s, x, y) is None
    assert refusal(cp, good, crossings, s, x, y) is None
    other = rsu_cert(spec.id, ("elsewhere",), Coverage(spec.position[0], spec.position[1], 150.0))
    assert refusal(initiate(), other, crossings, s, x, y) == "cmd_wrong_intersection"
    small = rsu_cert(spec.id, (target,), Coverage(x + 100.0, y, 10.0))
    assert refusal(initiate(), small, crossings, s, x, y) == "cmd_out_of_coverage"
    assert refusal(initiate(), None, crossings, s, x, y) == "cmd_unauthorised"
    past = crossings[-1].s_out + 1.0  # just left: its RSU still holds it until released
    assert refusal(initiate(), good, crossings, past, x, y) is None
    assert refusal(initiate(), other, crossings, past, x, y) == "cmd_wrong_intersection"
    terminate = ModeCommand(Header("rsu1", 3, 0), "A", Command.TERMINATE, Mode.AUTO)
    assert refusal(terminate, small, crossings, past, x, y) is None
    beacon = RsuBeacon(Header("evil", 1, 0), "x", 0.0, 0.0, 10.0)
    assert refusal(beacon, None, crossings, s, x, y) is None
