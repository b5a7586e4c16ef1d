"""``rsu_config``: every RSU knob comes from the scenario file and reaches ``RsuConfig``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol import Kind, max_points
from services.model.scenario import Params, RsuParams, parse_scenario
from services.model.types import Policy
from services.rsu.config import RsuConfig, rsu_config
from services.rsu.core import RsuCore

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"

# a valid value for each knob, different from its default (slot_min below v_max, hold_step
# below 2 x headway)
NEW_VALUES = {
    "command_repeat_s": 0.25,
    "beacon_period_s": 2.5,
    "stop_gap_m": 3.5,
    "slot_step_s": 0.05,
    "slot_min_speed_mps": 3.0,
    "hold_step_s": 0.3,
    "release_margin_m": 0.9,
    "release_margin_s": 0.4,
}


def test_every_knob_is_listed() -> None:
    assert set(NEW_VALUES) == set(RsuParams.model_fields)
    for name, value in NEW_VALUES.items():
        assert value != RsuParams.model_fields[name].default, name


def test_defaults_are_the_scenario_models() -> None:
    """RsuConfig's defaults come from the scenario models: one owner for each number."""
    zone = np.array([(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0)])
    cfg = RsuConfig("rsu1", "X1", (0.0, 0.0), zone)
    for name, value in RsuParams().model_dump().items():
        assert getattr(cfg, name) == value, name
    p = Params()
    assert (cfg.t_collision_s, cfg.t_free_s, cfg.expiry_s) == (
        p.t_collision_s,
        p.t_free_s,
        p.reservation_expiry_s,
    )
    assert (cfg.d_margin_m, cfg.headway_s, cfg.v_max_mps) == (
        p.d_margin_m,
        p.headway_s,
        p.v_max_mps,
    )


@pytest.mark.parametrize(("name", "value"), sorted(NEW_VALUES.items()))
def test_each_knob_reaches_the_core_from_rsu_params(name: str, value: float) -> None:
    text = PAPER.read_text() + f"\n[rsu_params]\n{name} = {value}\n"
    sc = parse_scenario(text, "paper+knob.toml")
    for rsu in sc.rsus:
        cfg = rsu_config(sc, rsu.id, Policy.SLOT)
        assert getattr(cfg, name) == value
        assert getattr(RsuCore(cfg).config, name) == value


def test_all_knobs_at_once_and_a_per_rsu_override() -> None:
    table = "".join(f"{k} = {v}\n" for k, v in NEW_VALUES.items())
    text = PAPER.read_text() + f"\n[rsu_params]\n{table}"
    sc = parse_scenario(text)
    (rsu,) = sc.rsus
    cfg = rsu_config(sc, rsu.id, Policy.PAPER)
    assert {k: getattr(cfg, k) for k in NEW_VALUES} == NEW_VALUES
    assert cfg.max_points == max_points(Kind.COORDINATED_PATH)
    # the RSU's own table wins over [rsu_params] for the keys it sets
    own = PAPER.read_text().replace(
        "coverage_m = 150.0", "coverage_m = 150.0\nparams = { hold_step_s = 0.2 }"
    )
    assert own != PAPER.read_text()
    sc = parse_scenario(own + f"\n[rsu_params]\n{table}")
    cfg = rsu_config(sc, rsu.id, Policy.PAPER)
    assert cfg.hold_step_s == 0.2 and cfg.stop_gap_m == NEW_VALUES["stop_gap_m"]


def test_paper_values_reach_the_core() -> None:
    sc = parse_scenario(PAPER.read_text())
    (rsu,) = sc.rsus
    cfg = rsu_config(sc, rsu.id, Policy.PAPER)
    p = sc.params
    assert (cfg.t_collision_s, cfg.t_free_s, cfg.expiry_s, cfg.headway_s) == (
        p.t_collision_s,
        p.t_free_s,
        p.reservation_expiry_s,
        p.headway_s,
    )
    assert cfg.coverage_m == rsu.coverage_m and cfg.policy is Policy.PAPER
