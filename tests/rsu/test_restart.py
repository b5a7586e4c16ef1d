"""An RSU killed and restarted during the paper run (in-process harness, ``RsuOutage``).

Issue 16: a restarted RSU re-ordered cars already committed (min PET 0.04 s in the
lab). The restarted core listens first and keeps every committed car's order: at
every kill moment and restart delay the run keeps the headway and has no collision.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from services.model.scenario import load_scenario
from services.model.types import RunMode
from services.sim.harness import RsuOutage, SimOptions, Simulation

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"
HEADWAY_S = 1.0  # the scenario's headway_s
MAX_SIM_S = 45.0  # both cars are through by about 38 s


def run(seed: int, crash_s: float, restart_s: float | None) -> Simulation:
    sc = load_scenario(PAPER)
    assert sc.params.headway_s == HEADWAY_S
    outage = RsuOutage("rsu1", crash_s, restart_s)
    sim = Simulation(sc, SimOptions(seed=seed, max_sim_s=MAX_SIM_S, rsu_outages=(outage,)))
    result = sim.run()
    assert result.collisions == 0
    assert result.min_pet_s is not None and result.min_pet_s >= HEADWAY_S, result.min_pet_s
    return sim


@pytest.mark.parametrize("delay_s", [1.0, 4.0, 9.0])
@pytest.mark.parametrize("crash_s", [6.0, 9.0, 12.0, 14.0, 16.0])
def test_a_restarted_rsu_keeps_the_headway(crash_s: float, delay_s: float) -> None:
    sim = run(1, crash_s, crash_s + delay_s)
    core = sim.rsus["rsu1"]  # the restarted one
    assert core.counters["beacons"] > 0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_lab_moment_restart_while_both_cars_creep_to_the_corner(seed: int) -> None:
    """Kill at 12 s; the lab's restart at 19 s joins the run about 2 s later (start-up):
    both cars, back in AUTO, creep towards the blind corner. Before the fix: PET 0.0-0.7 s."""
    for restart_s in (20.0, 21.0, 21.5):
        sim = run(seed, 12.0, restart_s)
        core = sim.rsus["rsu1"]
        assert core.counters["fp_listened"] > 0  # it listened before commanding
        assert core.counters["initiations"] > 0  # and then coordinated


def test_outages_are_validated() -> None:
    with pytest.raises(ValueError, match="restart_s"):
        RsuOutage("rsu1", 5.0, 4.0)
    with pytest.raises(ValueError, match="crash_s"):
        RsuOutage("rsu1", -1.0)
    sc = load_scenario(PAPER)
    with pytest.raises(ValueError, match="no RSU"):
        Simulation(sc, SimOptions(rsu_outages=(RsuOutage("rsu9", 1.0),)))
    with pytest.raises(ValueError, match="no RSU"):
        Simulation(sc, SimOptions(mode=RunMode.FP_ONLY, rsu_outages=(RsuOutage("rsu1", 1.0),)))


def test_a_crashed_rsu_without_restart_is_gone_for_good() -> None:
    sim = run(1, 12.0, None)
    assert "rsu1" not in sim.rsus
