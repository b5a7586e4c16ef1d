"""SUMO runs and their delay, measured as crosspath's (``services.sumo.baseline``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.sumo.baseline import free_time_loss, run_sumo
from services.sumo.netgen import Control
from tests.sumo.conftest import require_sumo

# two crossing streams and turns, light enough that every control clears them
DEPARTURES = {
    "we": [0.0, 6.0, 12.0],
    "sn": [1.0, 7.0, 13.0],
    "ns": [2.0],
    "ew": [3.0, 9.0],
    "wn": [4.0],
    "es": [10.0],
}
N_CARS = sum(len(v) for v in DEPARTURES.values())


@pytest.fixture(scope="module")
def free(tmp_path_factory: pytest.TempPathFactory) -> dict[str, float]:
    require_sumo()
    return free_time_loss(tmp_path_factory.mktemp("free"))


def test_free_flow_time_loss_is_the_start_from_rest(free: dict[str, float]) -> None:
    # straight: accelerating from rest to 13.89 m/s at 1.5 m/s² loses v / (2 a) = 4.63 s
    for route in ("we", "ew", "sn", "ns"):
        assert free[route] == pytest.approx(13.8889 / (2 * 1.5), abs=0.3)
    # turns slow down in the junction: they lose more than going straight
    assert all(free[r] > free["we"] + 0.5 for r in ("wn", "ws", "es", "en"))


@pytest.mark.parametrize("control", [Control.PRIORITY, Control.ALLWAY_STOP, Control.TRAFFIC_LIGHT])
def test_every_control_clears_light_demand_without_collision(
    tmp_path: Path, free: dict[str, float], control: Control
) -> None:
    run = run_sumo(tmp_path, control, DEPARTURES, 300.0, free, tag="light")
    assert (run.loaded, run.inserted, run.finished) == (N_CARS, N_CARS, N_CARS)
    assert run.all_finished and run.collisions == 0
    assert set(run.delays_s) == {f"{r}-{n}" for r, ts in DEPARTURES.items() for n in range(len(ts))}
    assert all(d >= 0.0 for d in run.delays_s.values())
    assert run.sim_s < 300.0  # stopped when the last car arrived
    doc = run.to_json()
    assert doc["mean_delay_s"] == pytest.approx(run.mean_delay_s)


def test_all_way_stop_costs_every_car_a_stop(tmp_path: Path, free: dict[str, float]) -> None:
    alone = {"we": [0.0]}
    prio = run_sumo(tmp_path / "p", Control.PRIORITY, alone, 120.0, free)
    stop = run_sumo(tmp_path / "s", Control.ALLWAY_STOP, alone, 120.0, free)
    # alone on the major road: free flow; at an all-way stop: a full stop and start
    assert prio.delays_s["we-0"] == pytest.approx(0.0, abs=0.3)
    assert stop.delays_s["we-0"] > 3.0


def test_bad_horizon_is_refused(tmp_path: Path, free: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="max_sim_s"):
        run_sumo(tmp_path, Control.PRIORITY, DEPARTURES, 0.0, free)
