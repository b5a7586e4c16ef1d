"""Issue 12: "don't block the box". Under ``slot`` a car whose own path stops in the zone
gets no slot (a retiming of that path) but the paper's stop, short of the zone where it
can (``VelocityManager.rests_in_zone``, ``paths.body_in_zone``).

Found in ``four-way-flows-40`` under ``slot``: slot plans on autonomous paths that stopped
in the box (behind a turner still crossing) put three cars in the zone at once, each
waiting for the next; 32 of 40 cars never got through.

Crafted paths at the 4-way box of ``test_issue12_causes`` (centre at the origin, 7 m
square), car A eastbound on y = -1.75.
"""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from protocol.messages import AutonomousPath, Mode
from services.model.types import Policy
from services.rsu import paths
from services.rsu.reservation import ReservationTable
from services.rsu.velocity import VelocityManager
from tests.rsu.test_issue12_causes import CROSS, EAST, NORTH, VMAX, ZONE, config, message, straight

LENGTH, WIDTH = 4.5, 1.8
HALF_BOX = 3.5


def stopping(x0: float, v: float, x_stop: float, t0: float) -> np.ndarray:
    """An eastbound path from ``x0`` at ``v`` braking evenly to a stop at ``x_stop``, then
    held to the 10 s horizon (120 points, the last ones repeated as a future path's)."""
    dist = x_stop - x0
    if v > 0.0 and 2.0 * dist / v > 9.5:
        raise ValueError("the car would not stop within the horizon")
    t = t0 + np.linspace(0.0, 10.0, 120)
    if v <= 0.0 or dist <= 0.0:
        s = np.zeros_like(t)
    else:
        b = v * v / (2.0 * dist)
        tau = np.minimum(t - t0, v / b)
        s = np.minimum(v * tau - 0.5 * b * tau * tau, dist)
    return np.column_stack([x0 + s, np.full_like(t, -1.75), t])


def overlaps_box(x: float, y: float, length: float, width: float) -> bool:
    """The axis-aligned body at (x, y) overlaps the 7 m box by more than the touch slack."""
    t = paths.BODY_TOUCH_M
    x_lo, x_hi = x - 0.5 * length + t, x + 0.5 * length - t
    y_lo, y_hi = y - 0.5 * width + t, y + 0.5 * width - t
    return x_hi >= -HALF_BOX and x_lo <= HALF_BOX and y_hi >= -HALF_BOX and y_lo <= HALF_BOX


# -- the geometry -----------------------------------------------------------------------------


def test_ends_at_rest() -> None:
    assert paths.ends_at_rest(np.array([[0.0, 0.0, 0.0]]))
    assert paths.ends_at_rest(stopping(-30.0, 8.0, -10.0, 0.0))
    assert not paths.ends_at_rest(straight((-40.0, -1.75), EAST, 8.0, 0.0))
    # a stop a few cm past the last point, long after it (a future path's 0.1 m rule)
    creep = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 1.0], [5.04, 0.0, 9.0]])
    assert paths.ends_at_rest(creep)


@settings(max_examples=300, deadline=None)
@given(
    x=st.floats(-15.0, 15.0),
    y=st.floats(-6.0, 6.0),
    length=st.floats(2.0, 12.0),
    width=st.floats(1.2, 2.6),
)
def test_body_in_zone_is_the_body_overlapping_the_box(
    x: float, y: float, length: float, width: float
) -> None:
    t = paths.BODY_TOUCH_M
    for edge in (
        x + 0.5 * length - t + HALF_BOX,
        x - 0.5 * length + t - HALF_BOX,
        y + 0.5 * width - t + HALF_BOX,
        y - 0.5 * width + t - HALF_BOX,
    ):
        assume(abs(edge) > 1e-6)
    held = np.array([[x - 10.0, y, 0.0], [x, y, 2.0], [x, y, 10.0]])
    assert paths.body_in_zone(held, ZONE, length, width, EAST) == overlaps_box(x, y, length, width)
    alone = np.array([[x, y, 0.0]])  # a path that never moves: the heading given
    assert paths.body_in_zone(alone, ZONE, length, width, EAST) == overlaps_box(x, y, length, width)


# -- the slot policy ------------------------------------------------------------------------


def front_gap(x: float) -> float:
    """Distance [m] from an eastbound car's front at centre ``x`` to the box."""
    return -HALF_BOX - (x + 0.5 * LENGTH)


def slot_plan(a: np.ndarray, v: float, table: ReservationTable) -> tuple[str, float]:
    """Kind and farthest x [m] of A's C_SLOW plan under ``slot`` on its own path ``a``."""
    vm = VelocityManager(config(Policy.SLOT))
    path = message(AutonomousPath, "A", a, v, EAST, Mode.C_SLOW)
    plan = vm.plan("A", path, Mode.C_SLOW, float(a[0, 2]), table)
    return plan.kind, float(plan.points[:, 0].max())


def test_a_slot_plan_never_enters_a_box_the_path_stops_in() -> None:
    """Retiming keeps the path's positions: no slot of a path that stops in the box."""
    kind, end_x = slot_plan(stopping(-30.0, 8.0, -1.0, 0.0), 8.0, ReservationTable())
    assert kind == "slot_fallback"
    assert front_gap(end_x) >= 0.0


def test_a_path_that_stops_past_the_box_still_gets_its_slot() -> None:
    """The control: stopping with its rear past the box, A gets a slot through it."""
    kind, end_x = slot_plan(stopping(-30.0, 8.0, HALF_BOX + 3.5, 0.0), 8.0, ReservationTable())
    assert kind == "slot"
    assert end_x > HALF_BOX


@settings(max_examples=150, deadline=None)
@given(
    v=st.floats(2.0, VMAX),
    stop=st.floats(-HALF_BOX - 0.5 * LENGTH + 0.2, HALF_BOX + 0.5 * LENGTH - 0.2),
    u=st.floats(0.0, 1.0),
    b_at=st.one_of(st.none(), st.floats(0.0, 10.0)),
)
def test_no_slot_plan_leaves_a_car_standing_in_the_box(
    v: float, stop: float, u: float, b_at: float | None
) -> None:
    """Property: whatever A's own path that stops around the box, and whenever a crossing
    car B (if any) passes through the box, A's slot-policy C_SLOW plan does not end at
    rest with A's body in the box while A can still stop before it (comfortable
    braking plus the stop gap)."""
    cfg = config(Policy.SLOT)
    braking = v * v / (2.0 * cfg.decel_comfort_mps2)
    nearest = -HALF_BOX - 0.5 * LENGTH - (braking + cfg.stop_gap_m + 0.5)  # still free to stop
    farthest = stop - 4.7 * v  # its own path stops within the horizon (9.4 s, < 9.5 s)
    assume(farthest < nearest)
    x0 = farthest + u * (nearest - farthest)
    table = ReservationTable(cfg.d_margin_m, cfg.headway_s, cfg.expiry_s)
    if b_at is not None:  # B northbound at V_max, at the crossing point at b_at
        start = (CROSS[0], CROSS[1] - b_at * VMAX)
        table.update("B", straight(start, NORTH, VMAX, 0.0), 0.0)
    vm = VelocityManager(cfg)
    path = message(AutonomousPath, "A", stopping(x0, v, stop, 0.0), v, EAST, Mode.C_SLOW)
    plan = vm.plan("A", path, Mode.C_SLOW, 0.0, table)
    standing = paths.ends_at_rest(plan.points) and paths.body_in_zone(
        plan.points, ZONE, LENGTH, WIDTH, EAST
    )
    assert not standing, (plan.kind, float(plan.points[:, 0].max()))
