"""``[vehicle_params]``: every planner and controller knob comes from the scenario file."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.model.kinematics import BodyState, TruthState
from services.model.scenario import VehicleParams, parse_scenario
from services.vehicle.agent import vehicle_agent

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"

NEW_VALUES = {
    "stop_margin_m": 0.7,
    "caution_sample_m": 1.0,
    "creep_mps": 1.0,
    "creep_margin_m": 0.8,
    "emergency_gap_m": 2.5,
    "control_lookahead_s": 0.5,
    "control_time_constant_s": 0.6,
    "fp_stale_s": 0.9,
    "fp_rule": "change",
    "fp_change_m": 1.0,
    "fp_refresh_s": 2.0,
    "ap_rule": "change",
    "ap_refresh_s": 0.5,
    "cp_rule": "change",
    "cp_refresh_s": 0.7,
}


def test_every_knob_is_listed() -> None:
    assert set(NEW_VALUES) == set(VehicleParams.model_fields)
    for name, value in NEW_VALUES.items():
        assert value != VehicleParams.model_fields[name].default, name


@pytest.mark.parametrize(("name", "value"), sorted(NEW_VALUES.items()))
def test_each_knob_reaches_the_agent_and_its_planner(name: str, value: float | str) -> None:
    sc = parse_scenario(PAPER.read_text() + f"\n[vehicle_params]\n{name} = {value!r}\n")
    for v in sc.vehicles:
        agent = vehicle_agent(sc, v.id, v2x=True)
        assert getattr(agent.spec.params, name) == value
        assert getattr(agent.planner.params, name) == value


def test_a_car_overrides_one_knob_for_itself() -> None:
    text = PAPER.read_text().replace('id = "B"', 'id = "B"\nparams = { creep_mps = 0.5 }', 1)
    assert text != PAPER.read_text()
    sc = parse_scenario(text + "\n[vehicle_params]\ncreep_mps = 1.0\n")
    assert vehicle_agent(sc, "A", v2x=False).planner.params.creep_mps == 1.0
    assert vehicle_agent(sc, "B", v2x=False).planner.params.creep_mps == 0.5


def test_the_controller_reads_its_knobs() -> None:
    """A stiffer controller (smaller time constant) commands more for the same error."""
    commands = []
    for tau in (0.4, 0.2):
        sc = parse_scenario(
            PAPER.read_text() + f"\n[vehicle_params]\ncontrol_time_constant_s = {tau}\n"
        )
        agent = vehicle_agent(sc, "A", v2x=False)
        route = sc.vehicle_route("A")
        x, y = route.point_at(20.0)
        agent.tick(
            0.0, TruthState("A", 0.0, x, y, route.heading_at(20.0), 5.0, 0.0, 20.0, 4.5, 1.8), []
        )
        commands.append(agent.command(BodyState(20.0, 5.0, 0.0)))
    assert commands[1] > commands[0] > 0.0
