"""Speed-profile passes and eq. (1) of the paper, against hand computations."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.vehicle.profile import (
    backward_pass,
    earliest_arrival,
    forward_pass,
    grid,
    pass_times,
    stop_cap,
    track_envelope,
)


def test_eq1_constant_speed_by_hand() -> None:
    s = np.array([0.0, 1.0, 2.0, 4.0])
    v = np.array([2.0, 2.0, 2.0, 2.0])
    t = pass_times(s, v, t0=10.0)
    assert np.allclose(t, [10.0, 10.5, 11.0, 12.0])


def test_eq1_mean_speed_per_step_and_stop_is_never_passed() -> None:
    s = np.array([0.0, 1.0, 2.0, 3.0])
    v = np.array([2.0, 1.0, 0.0, 0.0])
    t = pass_times(s, v, t0=0.0)
    # step 1 at mean 1.5 m/s, step 2 at mean 0.5 m/s, step 3 never
    assert math.isclose(t[1], 1.0 / 1.5)
    assert math.isclose(t[2], 1.0 / 1.5 + 2.0)
    assert math.isinf(t[3])


def test_stop_cap_is_braking_curve() -> None:
    s = np.array([0.0, 5.0, 10.0, 12.0])
    cap = stop_cap(s, 10.0, 2.0)
    assert np.allclose(cap, [math.sqrt(40.0), math.sqrt(20.0), 0.0, 0.0])


@settings(max_examples=60, deadline=None)
@given(
    caps=st.lists(st.floats(0.0, 20.0), min_size=2, max_size=80),
    v0=st.floats(0.0, 20.0),
)
def test_passes_respect_limits(caps: list[float], v0: float) -> None:
    ds, acc, dec = 0.5, 1.5, 2.0
    cap = np.array(caps)
    v = forward_pass(backward_pass(cap, ds, dec), v0, ds, acc)
    assert np.all(v <= cap + 1e-9)
    dv2 = np.diff(v * v)
    assert np.all(dv2 <= 2 * acc * ds + 1e-6)
    assert np.all(dv2 >= -2 * dec * ds - 1e-6)
    assert v[0] <= v0 + 1e-9


def test_forward_pass_from_rest_reaches_cruise() -> None:
    s = grid(0.0, 200.0, 0.5)
    v = forward_pass(np.full_like(s, 13.9), 0.0, 0.5, 1.5)
    # v² = 2 a s until the cap
    i = int(np.searchsorted(s, 20.0))
    assert math.isclose(v[i], math.sqrt(2 * 1.5 * s[i]), rel_tol=1e-9)
    assert math.isclose(v[-1], 13.9)


def test_track_envelope_brakes_smoothly() -> None:
    target = np.zeros(100)
    v = track_envelope(target, 10.0, 0.5, 1.5, 2.0)
    # reaches zero after v0²/(2a) = 25 m = 50 steps
    assert v[48] > 0.0
    assert v[50] == 0.0


def test_earliest_arrival() -> None:
    assert earliest_arrival(0.0, 5.0, 1.5, 13.9) == 0.0
    # from rest, 12 m at 1.5 m/s²: sqrt(2·12/1.5) = 4 s
    assert math.isclose(earliest_arrival(12.0, 0.0, 1.5, 13.9), 4.0)
    # already at v_max: constant speed
    assert math.isclose(earliest_arrival(139.0, 13.9, 1.5, 13.9), 10.0)
