"""The RSU's conflict margin grows with the cars' sizes: a bus in a full run, and the core's
own checks (oversize bodies counted, the commitment test with the car's own braking)."""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.messages import FuturePath, Header, Mode, VehicleLimits
from services.api import simulate
from services.model.catalog import resolve_scenario
from services.model.scenario import load_scenario
from services.rsu.core import RsuCore
from services.rsu.reservation import body_growth
from tests.rsu.test_core import EAST, VMAX, config, line

BUS = (12.0, 2.5)


def bus_scenario(tmp_path: Path) -> Path:
    """The paper's scenario with car B a 12 m x 2.5 m bus, written to ``tmp_path``."""
    text = resolve_scenario("paper-blind-intersection").read_text(encoding="utf-8")
    block = 'id = "B"\n'
    start = text.index(block)
    shape = "length_m = 4.5\nwidth_m = 1.8\n"
    at = text.index(shape, start)
    assert text.count(block) == 1 and at - start < 200, "the scenario's car B changed shape"
    text = text[:at] + f"length_m = {BUS[0]}\nwidth_m = {BUS[1]}\n" + text[at + len(shape) :]
    path = tmp_path / "bus.toml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("policy", ["paper", "slot"])
def test_a_bus_crosses_safely_under_the_rsu(tmp_path: Path, policy: str) -> None:
    sc = load_scenario(bus_scenario(tmp_path))
    b = next(v for v in sc.vehicles if v.id == "B")
    assert (b.length_m, b.width_m) == BUS
    for seed in (0, 1):
        result = simulate(sc, mode="rsu", policy=policy, seed=seed)
        assert result.all_finished
        assert result.collisions == 0
        assert result.min_pet_s is not None and result.min_pet_s >= 1.0, (seed, result.min_pet_s)


def _path(length: float, limits: VehicleLimits | None, x: float) -> FuturePath:
    """Car A eastbound on y = -1.75 at ``x`` [m] at full speed, towards the zone."""
    pts = line((x, -1.75), EAST, VMAX, 0.0)
    header = Header("A", 1, 0)
    return FuturePath(header, x, -1.75, VMAX, EAST, length, 1.8, Mode.AUTO, pts, limits)


def test_an_oversize_body_is_counted_and_still_coordinated() -> None:
    core = RsuCore(config(), listen_s=0.0)
    out = core.on_message(0.0, _path(40.0, None, -80.0))
    assert out, "the car is coordinated all the same"
    assert core.counters["oversize"] == 1 and core.counters["invalid"] == 0
    entry = core.table.get("A")
    assert entry is not None and entry.growth == body_growth(25.0, 1.8)


def test_commitment_uses_the_car_s_own_braking() -> None:
    """Front 70 m from the zone at 13.9 m/s: a car braking at 2 m/s² (48 m) can still stop,
    one that declares 1 m/s² (96 m) cannot: the RSU must count it committed."""
    x = -3.5 - 70.0 - 2.25
    verdicts = []
    for limits in (None, VehicleLimits(VMAX, 2.0, 1.0, 2.0)):
        core = RsuCore(config(), listen_s=0.0)
        path = _path(4.5, limits, x)
        core.on_message(0.0, path)
        car = core._cars["A"]
        verdicts.append(core._committed(car, path.points))
    assert core.config.decel_comfort_mps2 == 2.0
    assert verdicts == [False, True]
