"""Reservation table: the indexed conflict query agrees with brute force, expiry, updates."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.rsu.reservation import (
    ENDS_ROUNDING,
    FOLLOW_GAP_M,
    FOLLOW_WINDOW_S,
    LANE_SLACK_M,
    MAX_BODY_LENGTH_M,
    MAX_BODY_WIDTH_M,
    SAME_WAY_RAD,
    STANDARD_SHAPE,
    Conflict,
    ReservationTable,
    body_growth,
    densify,
    follow_distance,
    oversize,
    path_headings,
)

D = 2.8
H = 1.0


def line(x0: float, y0: float, dx: float, dy: float, t0: float, n: int, dt: float) -> np.ndarray:
    k = np.arange(n, dtype=np.float64)
    return np.column_stack([x0 + dx * k, y0 + dy * k, t0 + dt * k])


def test_crossing_paths_conflict_and_report_where_and_when() -> None:
    table = ReservationTable(D, H, 0.5)
    # A eastbound along y = 0, at x = 0 at t = 5; B northbound along x = 0, 0.5 s later.
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    b = line(0.0, -55.0, 0.0, 1.0, 0.0, 111, 0.1)
    table.update("A", a, 0.0)
    found = table.conflicts("B", b, 0.0, 10.0)
    assert [c.vehicle for c in found] == ["A"]
    c = found[0]
    assert c == table.naive_conflicts("B", b, 0.0, 10.0)[0]
    # B's first point within 2.8 m of a point of A less than 1 s apart: (0, -2) at 5.3 s,
    # with A at x = -1, 0, 1 (4.9..5.1 s); A's earliest involved point: (-2, 0) at 4.8 s.
    assert (c.x, c.y) == pytest.approx((0.0, -2.0))
    assert c.self_time == pytest.approx(5.3)
    assert c.other_time == pytest.approx(4.8)
    assert c.time == pytest.approx(5.3)


def test_no_conflict_when_far_apart_in_time_or_space() -> None:
    table = ReservationTable(D, H, 0.5)
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    table.update("A", a, 0.0)
    later = line(0.0, -50.0, 0.0, 1.0, 1.5, 101, 0.1)  # through (0, 0) at 6.5 s, A at 5 s
    assert table.conflicts("B", later, 0.0, 10.0) == []
    aside = line(20.0, -50.0, 0.0, 1.0, 0.0, 101, 0.1)  # crosses A's line 2 s before A
    assert table.conflicts("C", aside, 0.0, 10.0) == []
    parallel = line(-50.0, 2.9, 1.0, 0.0, 0.0, 101, 0.1)  # side by side, 2.9 m apart
    assert table.conflicts("D", parallel, 0.0, 10.0) == []
    alongside = line(-50.0, 2.8, 1.0, 0.0, 0.0, 101, 0.1)  # exactly d_margin apart: conflicts
    assert [c.vehicle for c in table.conflicts("E", alongside, 0.0, 10.0)] == ["A"]


def test_window_limits_the_query_and_the_entries() -> None:
    table = ReservationTable(D, H, 0.5)
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)  # at (0, 0) at 5 s
    table.update("A", a, 0.0)
    b = line(0.0, -50.0, 0.0, 1.0, 0.0, 101, 0.1)  # at (0, 0) at 5 s too
    assert table.conflicts("B", b, 0.0, 4.0) == []
    assert [c.vehicle for c in table.conflicts("B", b, 0.0, 5.0)] == ["A"]
    assert table.conflicts("B", b, 0.0, 4.0) == table.naive_conflicts("B", b, 0.0, 4.0)


def test_own_entry_and_excluded_cars_are_skipped() -> None:
    table = ReservationTable(D, H, 0.5)
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    table.update("A", a, 0.0)
    table.update("B", a + np.array([0.0, 1.0, 0.2]), 0.0)
    assert [c.vehicle for c in table.conflicts("A", a, 0.0, 10.0)] == ["B"]
    assert table.conflicts("A", a, 0.0, 10.0, exclude=("B",)) == []
    assert [c.vehicle for c in table.conflicts("X", a, 0.0, 10.0)] == ["A", "B"]


def test_expiry_drops_silent_entries_and_touch_keeps_them() -> None:
    table = ReservationTable(D, H, 0.5)
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    table.update("A", a, 0.0)
    table.update("B", a, 0.0)
    assert table.next_expiry() == pytest.approx(0.5)
    assert table.touch("B", 0.3)
    assert not table.touch("nobody", 0.3)
    assert table.expire(0.49) == []
    # an entry past its expiry is no longer seen even before expire() runs
    assert [c.vehicle for c in table.conflicts("X", a, 0.6, 10.0)] == ["B"]
    assert table.expire(0.5) == ["A"]
    assert "A" not in table and "B" in table and len(table) == 1
    assert table.expire(0.8) == ["B"]
    assert len(table) == 0 and table.next_expiry() == math.inf


def test_update_replaces_and_remove_unindexes() -> None:
    table = ReservationTable(D, H, 0.5)
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    far = a + np.array([1000.0, 1000.0, 0.0])
    table.update("A", a, 0.0)
    table.update("A", far, 0.1)
    assert table.conflicts("X", a, 0.1, 10.0) == []
    assert [c.vehicle for c in table.conflicts("X", far, 0.1, 10.0)] == ["A"]
    assert table.remove("A") and not table.remove("A")
    assert table.conflicts("X", far, 0.1, 10.0) == []
    assert table.candidates(far) == set()


@pytest.mark.parametrize(
    "bad",
    [np.zeros((3, 2)), np.array([[0.0, 0.0, math.nan]]), np.array([[1e12, 0.0, 0.0]])],
)
def test_bad_paths_raise_and_change_nothing(bad: np.ndarray) -> None:
    table = ReservationTable(D, H, 0.5)
    a = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    table.update("A", a, 0.0)
    with pytest.raises(ValueError):
        table.update("A", bad, 0.1)
    with pytest.raises(ValueError):
        table.conflicts("B", bad, 0.1, 10.0)
    assert table.get("A") is not None and np.array_equal(table.get("A").points, a)  # type: ignore[union-attr]


def test_bad_parameters_raise() -> None:
    with pytest.raises(ValueError):
        ReservationTable(0.0, 1.0, 0.5)
    with pytest.raises(ValueError):
        ReservationTable(2.8, math.nan, 0.5)
    with pytest.raises(ValueError):
        ReservationTable(2.8, 1.0, -1.0)
    with pytest.raises(ValueError, match="at least"):  # below the wire's 1 ms
        ReservationTable(2.8, 1e-300, 0.5, follow_window_s=0.0)
    table = ReservationTable(2.8, 1e-3, 0.5, follow_window_s=0.0)  # the smallest
    a = np.array([[-10.0, 0.0, 0.0], [10.0, 0.0, 2.0]])
    b = np.array([[0.0, -10.0, 0.0], [0.0, 10.0, 2.0]])
    table.update("A", a, 0.0)
    assert table.conflicts("B", b, 0.0, 10.0) == table.naive_conflicts("B", b, 0.0, 10.0)


# Coordinates on a lattice of d_margin/2 and times on a lattice of headway/2 make pairs at
# exactly d_margin and exactly headway frequent: the edge cases of both predicates.
_coord = st.one_of(
    st.integers(-12, 12).map(lambda k: k * D / 2),
    st.floats(-20.0, 20.0, allow_nan=False),
)
_time = st.one_of(
    st.integers(0, 16).map(lambda k: k * H / 2),
    st.floats(0.0, 8.0, allow_nan=False),
)
_point = st.tuples(_coord, _coord, _time)
_path = st.lists(_point, min_size=0, max_size=12).map(
    lambda pts: np.array(pts, dtype=np.float64).reshape(-1, 3)
)


# Body sizes: mostly standard cars (growth 0), buses, and sizes up to the wire's bounds
# (beyond the growth cap), some exactly one or two cells of growth.
_shape = st.one_of(
    st.just(STANDARD_SHAPE),
    st.just((12.0, 2.5)),
    st.tuples(st.floats(0.01, 50.0), st.floats(0.01, 10.0)),
    st.tuples(st.sampled_from([4.5 + 2 * D, 4.5 + 4 * D, 25.0]), st.just(1.8)),
)


def _as_checked(points: np.ndarray) -> np.ndarray:
    """A path as the table checks it: densified when its times run forward."""
    if points.shape[0] >= 2 and np.all(np.diff(points[:, 2]) >= 0.0):
        return densify(points)
    return points


@settings(max_examples=300, deadline=None)
@given(
    others=st.lists(st.tuples(_path, _shape), min_size=0, max_size=6),
    query=_path,
    query_shape=_shape,
    now=st.sampled_from([0.0, 0.5, 1.0, 2.25]),
    horizon=st.sampled_from([1.0, 2.5, 5.0, 10.0]),
    margins=st.sampled_from([(0.0, 0.0), (0.6, 0.2), (D / 2, H / 2), (3.0, 1.5)]),
)
def test_indexed_query_equals_brute_force(
    others: list[tuple[np.ndarray, tuple[float, float]]],
    query: np.ndarray,
    query_shape: tuple[float, float],
    now: float,
    horizon: float,
    margins: tuple[float, float],
) -> None:
    table = ReservationTable(D, H, 0.5)
    for i, (pts, shape) in enumerate(others):
        table.update(f"v{i}", pts, now, shape)
    fast = table.conflicts("q", query, now, horizon, (), *margins, shape=query_shape)
    slow = table.naive_conflicts("q", query, now, horizon, (), *margins, shape=query_shape)
    assert fast == slow
    if margins != (0.0, 0.0):
        return
    first = table.first_conflict(
        "q", query, now, horizon, (), [f"v{len(others) - 1}"], shape=query_shape
    )
    assert (first is None) == (not fast)
    assert first is None or first in fast
    # and the brute force itself is right: recompute pair by pair, in plain Python
    # (the crossing rule, and the follow rule for same-way points in one lane)
    expected: dict[str, bool] = {}
    query = _as_checked(query)
    hq = path_headings(query).tolist()
    for i, (pts, shape) in enumerate(others):
        pts = _as_checked(pts)
        d = D + body_growth(*query_shape) + body_growth(*shape)
        f = follow_distance(query_shape[0], shape[0], FOLLOW_GAP_M)
        lane = 0.5 * (min(query_shape[1], 3.0) + min(shape[1], 3.0)) + LANE_SLACK_M
        ho = path_headings(pts).tolist()
        hit = False
        for (qx, qy, qt), (qux, quy) in zip(query.tolist(), hq, strict=True):
            if not now <= qt <= now + horizon:
                continue
            for (ox, oy, ot), (oux, ouy) in zip(pts.tolist(), ho, strict=True):
                if not now <= ot <= now + horizon:
                    continue
                dx, dy = qx - ox, qy - oy
                if dx * dx + dy * dy <= d * d and abs(qt - ot) < H:
                    hit = True
                q_still, o_still = math.isnan(qux), math.isnan(oux)
                if q_still and o_still:
                    continue
                same = q_still != o_still or qux * oux + quy * ouy >= math.cos(SAME_WAY_RAD)
                close = dx * dx + dy * dy <= f * f and abs(qt - ot) < FOLLOW_WINDOW_S
                # in one lane across either car's heading (a still path has none)
                in_lane = (not q_still and abs(qux * dy - quy * dx) <= lane) or (
                    not o_still and abs(oux * dy - ouy * dx) <= lane
                )
                if same and close and in_lane:
                    hit = True
        expected[f"v{i}"] = hit
    assert {c.vehicle for c in slow} == {v for v, hit in expected.items() if hit}
    for c in slow:
        assert isinstance(c, Conflict)
        assert now <= c.self_time <= c.time <= now + horizon
        assert now <= c.other_time <= c.time


@settings(max_examples=300, deadline=None)
@given(a=_path, a_shape=_shape, b=_path, b_shape=_shape, now=st.sampled_from([0.0, 1.0]))
def test_a_conflict_is_the_same_whichever_car_asks(
    a: np.ndarray,
    a_shape: tuple[float, float],
    b: np.ndarray,
    b_shape: tuple[float, float],
    now: float,
) -> None:
    """The table answers the RSU for one car and the invariant for every pair: A's path
    conflicts with B's exactly when B's conflicts with A's (the follow rule's lane was
    once measured across the asking car's heading only, and a turning car did not see a
    car it nearly touched that saw it, ``tests/rsu/test_invariant.py``)."""
    table = ReservationTable(D, H, 0.5)
    table.update("a", a, now, a_shape)
    table.update("b", b, now, b_shape)
    a_asks = table.conflicts("a", a, now, 10.0, shape=a_shape)
    b_asks = table.conflicts("b", b, now, 10.0, shape=b_shape)
    assert bool(a_asks) == bool(b_asks)
    if a_asks:
        assert a_asks[0].time == b_asks[0].time


@settings(max_examples=100, deadline=None)
@given(
    dx=st.floats(-3.5, 3.5),
    dy=st.floats(-3.5, 3.5),
    dt=st.floats(-1.5, 1.5),
    base=st.tuples(st.floats(-5000, 5000), st.floats(-5000, 5000), st.floats(0, 1000)),
)
def test_single_pair_near_the_margins(
    dx: float, dy: float, dt: float, base: tuple[float, float, float]
) -> None:
    """One point each, anywhere in the plane, near the d_margin / headway boundary."""
    x, y, t = base
    table = ReservationTable(D, H, 0.5)
    table.update("o", np.array([[x + dx, y + dy, t + dt]]), t - 2.0)
    q = np.array([[x, y, t]])
    fast = table.conflicts("q", q, t - 2.0, 5.0)
    slow = table.naive_conflicts("q", q, t - 2.0, 5.0)
    assert fast == slow
    ddx, ddy = x - (x + dx), y - (y + dy)
    expect = ddx * ddx + ddy * ddy <= D * D and abs(t - (t + dt)) < H
    assert bool(fast) == expect


def _passing(gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Two cars in opposing lanes whose centres pass ``gap`` [m] apart: A eastbound along
    y = 0, B westbound along y = ``gap``, both at x = 0 at 5 s."""
    a = line(-50.0, 0.0, 0.5, 0.0, 0.0, 201, 0.05)
    b = line(50.0, gap, -0.5, 0.0, 0.0, 201, 0.05)
    return a, b


def test_the_margin_grows_with_the_cars_sizes() -> None:
    """Centres passing 3.5 m apart: no conflict for two standard cars (the paper's 2.8 m),
    a conflict when one of them is a 12 m x 2.5 m bus (the body reaches 3.7 m further)."""
    a, b = _passing(3.5)
    bus = (12.0, 2.5)
    for shape_a, shape_b, expect in [
        (STANDARD_SHAPE, STANDARD_SHAPE, []),
        (bus, STANDARD_SHAPE, ["A"]),
        (STANDARD_SHAPE, bus, ["A"]),
        ((3.0, 1.5), (3.0, 1.5), []),  # smaller than standard: the paper's margin, no less
    ]:
        table = ReservationTable(D, H, 0.5)
        table.update("A", a, 0.0, shape_a)
        found = table.conflicts("B", b, 0.0, 10.0, shape=shape_b)
        assert [c.vehicle for c in found] == expect, (shape_a, shape_b)
        assert found == table.naive_conflicts("B", b, 0.0, 10.0, shape=shape_b)
        # without a shape the query is its own entry's (here none: a standard car)
        table.update("B", b, 0.0, shape_b)
        assert [c.vehicle for c in table.conflicts("B", b, 0.0, 10.0)] == expect
    # the bus's pair margin: 2.8 + 3.71 m
    assert body_growth(*bus) == pytest.approx(
        0.5 * math.hypot(12.0, 2.5) - 0.5 * math.hypot(4.5, 1.8)
    )
    assert 3.70 < body_growth(*bus) < 3.72
    a, b = _passing(2.8 + body_growth(*bus) + 0.05)
    table = ReservationTable(D, H, 0.5)
    table.update("A", a, 0.0, bus)
    assert table.conflicts("B", b, 0.0, 10.0, shape=STANDARD_SHAPE) == []


def test_growth_is_capped_and_shapes_are_checked() -> None:
    assert body_growth(*STANDARD_SHAPE) == 0.0
    assert body_growth(1.0, 1.0) == 0.0
    cap = body_growth(MAX_BODY_LENGTH_M, MAX_BODY_WIDTH_M)
    assert 10.0 < cap < 10.3
    assert body_growth(50.0, 10.0) == cap  # the wire's largest: no larger neighbourhood
    assert oversize(50.0, 1.8) and oversize(4.5, 3.5) and not oversize(25.0, 3.0)
    table = ReservationTable(D, H, 0.5)
    for bad in [(math.nan, 1.8), (4.5, math.inf), (-1.0, 1.8)]:
        with pytest.raises(ValueError):
            table.update("A", line(0.0, 0.0, 1.0, 0.0, 0.0, 3, 0.1), 0.0, bad)
    assert "A" not in table
    # a hostile 50 m x 10 m "car" reaches no further than a 25 m x 3 m one
    pts = line(-50.0, 0.0, 1.0, 0.0, 0.0, 101, 0.1)
    table.update("big", pts, 0.0, (50.0, 10.0))
    table.update("cap", pts, 0.0, (MAX_BODY_LENGTH_M, MAX_BODY_WIDTH_M))
    big, capped = table.get("big"), table.get("cap")
    assert big is not None and capped is not None
    assert big.growth == capped.growth == cap
    reach = D + cap
    near = line(-50.0, reach - 0.01, 1.0, 0.0, 0.0, 101, 0.1)
    far = line(-50.0, reach + 0.01, 1.0, 0.0, 0.0, 101, 0.1)
    lane = {"big", "cap"}
    assert {c.vehicle for c in table.conflicts("X", near, 0.0, 10.0, shape=(1.0, 1.0))} == lane
    assert table.conflicts("X", far, 0.0, 10.0, shape=(1.0, 1.0)) == []


def test_jam_with_churn_equals_brute_force() -> None:
    """A jam at one intersection (the bench's paths), some cars holding a stop, cars
    updated and removed in between (block rows reused and compacted): the batched query
    finds exactly what the brute force finds, for every car of the table."""
    from services.bench.rsu import _intersection_car

    rng = np.random.default_rng(7)
    table = ReservationTable(D, H, 0.5)
    paths = {}
    for k in range(40):
        pts = _intersection_car(rng, f"c{k}", 0.0, 1).points
        if k % 7 == 0:  # stopped at its 40th point and holding there: an irregular path
            pts = np.vstack([pts[:40], [[pts[39, 0], pts[39, 1], 10.0]]])
        paths[f"c{k}"] = pts
        table.update(f"c{k}", pts, 0.0, (12.0, 2.5) if k % 11 == 0 else STANDARD_SHAPE)
    for k in range(0, 40, 3):  # churn: replace some, drop others
        if k % 2:
            table.remove(f"c{k}")
            del paths[f"c{k}"]
        else:
            paths[f"c{k}"] = _intersection_car(rng, f"c{k}", 0.0, 2).points
            table.update(f"c{k}", paths[f"c{k}"], 0.1)
    for v, pts in paths.items():  # every car again: most rows dead, then compacted
        table.update(v, pts, 0.1)
    assert table._dead < table._rows
    assert len(table) == len(paths)
    total = 0
    for v, pts in list(paths.items())[::2]:
        for margins in [(0.0, 0.0), (0.6, 0.2)]:
            fast = table.conflicts(v, pts, 0.1, 10.0, (), *margins)
            assert fast == table.naive_conflicts(v, pts, 0.1, 10.0, (), *margins), v
            total += len(fast)
    assert total > 40  # a jam: plenty of conflicts to compare


@settings(max_examples=150, deadline=None)
@given(
    paths_=st.lists(
        st.tuples(st.floats(-9.9e6, 9.9e6), st.floats(-9.9e6, 9.9e6), st.integers(0, 4)),
        min_size=0,
        max_size=8,
    ),
    removed=st.sets(st.integers(0, 7), max_size=3),
    excluded=st.sets(st.integers(0, 7), max_size=2),
    stale=st.sets(st.integers(0, 7), max_size=2),
)
def test_path_ends_are_the_live_entries_first_and_last_points(
    paths_: list[tuple[float, float, int]], removed: set[int], excluded: set[int], stale: set[int]
) -> None:
    """``path_ends`` (the lane searches' prefilter) gives every live entry with a point but
    the asking car's and the excluded ones, each path's first and last points within the
    float32 rounding it documents, and its width; nothing removed, expired or empty."""
    table = ReservationTable(D, H, 0.5)
    sent: dict[str, np.ndarray] = {}
    for i, (x, y, n) in enumerate(paths_):
        pts = line(x, y, 0.7, -0.3, 0.0, n, 0.1)
        vehicle = f"v{i}"
        table.update(vehicle, pts, -1.0 if i in stale else 0.0, (4.5, 1.0 + 0.1 * i))
        sent[vehicle] = pts
    for i in removed:
        table.remove(f"v{i}")
    names, ends, widths = table.path_ends("v0", 0.2, [f"v{i}" for i in excluded])
    expected = {
        v
        for v, pts in sent.items()
        if pts.shape[0] and v != "v0" and int(v[1:]) not in removed | excluded | stale
    }
    assert sorted(names) == sorted(expected)

    for name, end, width in zip(names, ends.tolist(), widths.tolist(), strict=True):
        pts = sent[name]
        want = [pts[0, 0], pts[0, 1], pts[-1, 0], pts[-1, 1]]
        for got, exact in zip(end, want, strict=True):
            # relative, and float32's subnormal spacing near 0 (the prefilter's 1e-6 m covers it)
            assert abs(got - exact) <= ENDS_ROUNDING * abs(exact) + 1e-44
        assert width == pytest.approx(1.0 + 0.1 * int(name[1:]))
