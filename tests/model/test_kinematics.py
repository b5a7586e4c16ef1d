"""Longitudinal kinematics: exact actuator lag, no reversing, hard speed cap."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.model.kinematics import BodyState, Limits, TruthState, step
from services.model.scenario import DynamicsOverrides, Params, limits_from_params

LIM = Limits(v_max=13.8889, accel=1.5, decel_comfort=2.0, decel_emergency=5.0, actuator_lag_s=0.3)
DT = 0.05


def run(state: BodyState, a_cmd: float, seconds: float, dt: float = DT) -> BodyState:
    for _ in range(round(seconds / dt)):
        state = step(state, a_cmd, dt, LIM)
    return state


def test_lag_is_exact_and_step_size_independent() -> None:
    s0 = BodyState(s=3.0, v=5.0, a=0.5)
    coarse = step(s0, -3.0, 0.05, LIM)
    fine = run(s0, -3.0, 0.05, dt=0.005)
    assert coarse.s == pytest.approx(fine.s, abs=1e-9)
    assert coarse.v == pytest.approx(fine.v, abs=1e-9)
    assert coarse.a == pytest.approx(fine.a, abs=1e-9)


def test_acceleration_from_rest_by_hand() -> None:
    out = step(BodyState(0.0, 0.0, 0.0), 1.5, 1.0, LIM)
    e = math.exp(-1.0 / 0.3)
    assert out.a == pytest.approx(1.5 * (1.0 - e))
    assert out.v == pytest.approx(1.5 * 1.0 - 1.5 * 0.3 * (1.0 - e))
    assert out.s == pytest.approx(0.5 * 1.5 - 1.5 * 0.3 * (1.0 - 0.3 * (1.0 - e)))
    later = run(BodyState(0.0, 0.0, 0.0), 1.5, 8.0)
    assert later.a == pytest.approx(1.5, abs=1e-6)
    assert later.v == pytest.approx(1.5 * (8.0 - 0.3), abs=1e-6)  # the lag delays by tau


def test_command_is_clipped() -> None:
    assert run(BodyState(0.0, 0.0, 0.0), 10.0, 5.0).a == pytest.approx(1.5, abs=1e-6)
    hard = run(BodyState(0.0, 14.0, 0.0), -100.0, 1.0)
    assert hard.a == pytest.approx(-5.0, abs=0.2)


def test_braking_stops_and_holds_without_reversing() -> None:
    state = BodyState(0.0, 10.0, 0.0)
    for _ in range(100):
        state = step(state, -5.0, DT, LIM)
        assert state.v >= 0.0
    assert state.v == 0.0
    assert state.a == 0.0
    # Stopping distance: v²/2d plus at most v*tau for the lag.
    assert 10.0 <= state.s <= 10.0 + 10.0 * 0.3
    held = run(state, -2.0, 3.0)
    assert held == BodyState(state.s, 0.0, 0.0)


def test_stop_within_a_step_then_pull_away() -> None:
    # Braking hard at low speed, but the command already asks to accelerate again.
    out = step(BodyState(0.0, 0.1, -4.0), 1.0, 0.05, LIM)
    assert out.v >= 0.0
    assert out.s >= 0.0
    # Standing with a negative acceleration left over: the brakes hold, no dip.
    out = step(BodyState(5.0, 0.0, -3.0), 1.0, 0.05, LIM)
    assert out.s >= 5.0
    assert out.v >= 0.0
    assert out.a > 0.0


def test_speed_hard_cap() -> None:
    slow = Limits(v_max=5.0, accel=1.5, decel_comfort=2.0, decel_emergency=5.0, actuator_lag_s=0.3)
    state = BodyState(0.0, 0.0, 0.0)
    for _ in range(400):
        prev = state
        state = step(state, 1.5, DT, slow)
        assert state.v <= 5.0 * 1.05 + 1e-12
        assert state.s >= prev.s
    assert state.v == pytest.approx(5.25)
    assert state.a <= 0.0


def test_zero_lag() -> None:
    nolag = Limits(13.9, 1.5, 2.0, 5.0, 0.0)
    out = step(BodyState(0.0, 2.0, 0.0), 1.0, 0.5, nolag)
    assert (out.s, out.v, out.a) == pytest.approx((1.125, 2.5, 1.0))


@pytest.mark.parametrize(
    ("a_cmd", "dt"), [(math.nan, 0.05), (math.inf, 0.05), (1.0, 0.0), (1.0, -0.1), (1.0, math.nan)]
)
def test_step_rejects_bad_input(a_cmd: float, dt: float) -> None:
    with pytest.raises(ValueError):
        step(BodyState(0.0, 1.0, 0.0), a_cmd, dt, LIM)


def test_limits_validation_and_from_params() -> None:
    with pytest.raises(ValueError):
        Limits(0.0, 1.5, 2.0, 5.0, 0.3)
    with pytest.raises(ValueError):
        Limits(10.0, 1.5, 2.0, 1.0, 0.3)  # emergency below comfortable
    with pytest.raises(ValueError):
        Limits(10.0, 1.5, 2.0, 5.0, -0.1)
    p = Params()
    assert limits_from_params(p) == Limits(p.v_max_mps, 1.5, 2.0, 5.0, 0.3)
    over = DynamicsOverrides(v_max_mps=8.0, actuator_lag_s=0.1)
    assert limits_from_params(p, over) == Limits(8.0, 1.5, 2.0, 5.0, 0.1)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0.0, 15.0),
    st.floats(-5.0, 1.5),
    st.lists(st.floats(-20.0, 20.0), min_size=1, max_size=80),
)
def test_invariants_under_any_commands(v0: float, a0: float, cmds: list[float]) -> None:
    state = BodyState(0.0, v0, a0)
    for c in cmds:
        nxt = step(state, c, DT, LIM)
        assert nxt.v >= 0.0
        assert nxt.s >= state.s - 1e-12
        assert nxt.v <= max(v0, LIM.v_max * 1.05) + 1e-9
        assert -5.0 - 1e-9 <= nxt.a <= max(1.5, a0) + 1e-9
        state = nxt


def test_truth_state_footprint() -> None:
    t = TruthState("A", 0.0, 10.0, -1.75, 0.0, 5.0, 0.0, 210.0, 4.5, 1.8)
    fp = t.footprint()
    assert fp.shape == (4, 2)
    assert float(fp[:, 0].max()) == pytest.approx(12.25)
    assert float(fp[:, 1].min()) == pytest.approx(-2.65)
