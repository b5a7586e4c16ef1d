"""The path projections in C (``services/rsu/_scan.c``) against the numpy code they
replace (``services/rsu/paths.py``, ``reservation.path_headings``).

Each kernel function must give the numpy function's numbers to the bit, or decline with
None so that numpy answers; no argument, however wrong, may make it read out of bounds.
Without a C compiler the kernel is not built: locally these tests then skip, on CI (``CI``
set) they fail, since ``make test`` builds it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from services.rsu import paths, reservation
from tests.kernels import both_ways, require_kernel

require_kernel(reservation.scan_available(), "services.rsu._scan")

from services.rsu import _scan  # noqa: E402 - after the check above


@pytest.fixture(autouse=True)
def _kernel_on() -> Iterator[None]:
    previous = paths.use_kernel(True)
    yield
    paths.use_kernel(previous)


def _both(fn: Callable[..., Any], *args: Any) -> tuple[Any, Any]:
    """``fn(*args)`` with the kernel, then on numpy."""
    return both_ways(paths.use_kernel, fn, *args)


def _same(a: Any, b: Any) -> bool:
    """Equal to the bit (NaN where NaN), same dtype and shape; tuples element by element."""
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return (
            isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and np.array_equal(a, b, equal_nan=True)
            and np.array_equal(np.signbit(a), np.signbit(b))
        )
    return bool(a == b)


@st.composite
def _polylines(draw: st.DrawFn) -> np.ndarray:
    """Paths as the RSU sees them: 1-130 points (x, y, t), steps of up to a few metres on
    a 1 cm lattice (the wire's), with held stops (repeated points), straight runs and
    turns; sometimes far from the origin."""
    n = draw(st.integers(1, 130))
    steps = draw(
        hnp.arrays(np.float64, (n, 2), elements=st.integers(-300, 300).map(lambda v: v / 100))
    )
    hold = draw(hnp.arrays(np.bool_, (n,)))
    steps[hold] = 0.0
    if draw(st.booleans()):
        steps[:, 1] = 0.0  # along an axis
    origin = draw(st.sampled_from([0.0, 1234.56, -9876.5]))
    xy = origin + np.cumsum(steps, axis=0)
    t = np.cumsum(np.full(n, 0.1))
    return np.column_stack([xy, t])


_coord = st.floats(-400.0, 400.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(_polylines(), st.lists(st.tuples(_coord, _coord), min_size=1, max_size=4))
def test_projections_equal_numpy(xy: np.ndarray, where: list[tuple[float, float]]) -> None:
    q = xy[0, :2] + np.array(where, dtype=np.float64)
    fast, slow = _both(paths.project_many, xy, q)
    assert _same(fast, slow)
    for x, y in q.tolist():
        for reach in (0.0, 1.5, 20.0):
            fast, slow = _both(paths.farther_than, xy, x, y, reach)
            assert fast is slow
    assert _same(*_both(paths.segment_lengths, xy))


@settings(max_examples=300, deadline=None)
@given(_polylines())
def test_headings_and_curvature_equal_numpy(xy: np.ndarray) -> None:
    s = paths.arc_length(xy)
    assert _same(*_both(reservation.path_headings, xy))
    assert _same(*_both(paths.path_curvature, xy, s))
    fast, slow = _both(paths.curve_caps, xy, s, 2.0, 13.9)
    assert _same(fast, slow)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(3, 8),
    st.floats(2.0, 30.0),
    st.floats(0.0, 6.3),
    st.booleans(),
    hnp.arrays(np.float64, (12, 2), elements=st.floats(-40.0, 40.0)),
)
def test_zone_membership_equals_numpy(
    k: int, radius: float, turn: float, clockwise: bool, offsets: np.ndarray
) -> None:
    """Regular polygons either way round; points inside, outside and on the edges (the
    vertices and the edges' midpoints)."""
    a = turn + np.arange(k) * (2 * np.pi / k) * (-1 if clockwise else 1)
    polygon = np.column_stack([radius * np.cos(a), radius * np.sin(a)])
    zone = paths.ConvexZone.of(polygon)
    mid = 0.5 * (zone.vertices + np.roll(zone.vertices, -1, axis=0))
    pts = np.vstack([offsets, zone.vertices, mid, [[np.nan, 0.0]]])
    fast, slow = _both(zone.contains, pts)
    assert _same(fast, slow)
    assert fast[12 : 12 + 2 * k].all()  # the edges belong to the zone
    assert not fast[-1]


@settings(max_examples=100, deadline=None)
@given(_polylines(), st.sampled_from(["reversed", "every-other", "fortran", "x-y-only"]))
def test_views_of_any_layout_give_the_same_numbers(xy: np.ndarray, layout: str) -> None:
    """Strided, reversed and column-major arrays are read where they lie, not copied."""
    view = {
        "reversed": xy[::-1],
        "every-other": xy[::2],
        "fortran": np.asfortranarray(xy),
        "x-y-only": xy[:, :2],
    }[layout]
    q = view[:3, :2] + 0.5
    assert _same(*_both(paths.project_many, view, q))
    assert _same(*_both(paths.segment_lengths, view))
    assert _same(*_both(reservation.path_headings, view))
    fast, slow = _both(paths.farther_than, view, 3.0, -2.0, 1.0)
    assert fast is slow


_wire_values = st.one_of(
    st.floats(-2e6, 2e6),  # within and beyond the wire's bounds
    st.sampled_from([0.0, -0.0, 1e300, -1e300]),
    st.floats(allow_nan=True, allow_infinity=True),
)


@settings(max_examples=300, deadline=None)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(0, 20), st.just(3)), elements=_wire_values),
    st.sampled_from(["c", "fortran", "reversed"]),
)
def test_the_wire_bounds_check_equals_numpy(points: np.ndarray, layout: str) -> None:
    """Finite, |x|, |y| <= MAX_COORD_M and |t| <= the wire's time bound, values anywhere."""
    view = {"c": points, "fortran": np.asfortranarray(points), "reversed": points[::-1]}[layout]
    fast, slow = _both(reservation.within_wire_bounds, view)
    assert fast is slow


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(0.0, 1.2), min_size=0, max_size=40),
    st.sampled_from([0.5, 0.1, 1.0]),
)
def test_densify_equals_numpy(steps: list[float], max_dt: float) -> None:
    """Times 0-1.2 s apart, so that some gaps are over the limit and some exactly on it."""
    t = np.cumsum(np.array([0.0, *steps]))
    points = np.column_stack([np.arange(t.shape[0]) * 0.7, -0.3 * t, t])
    fast, slow = _both(reservation.densify, points, max_dt)
    assert _same(fast, slow)
    assert (fast is points) is (slow is points)  # the same array when no gap is long


def test_a_quarter_circle_gives_its_curvature_on_both() -> None:
    """A 12 m radius turn sampled every 0.5 m: the curvature is 1/12 inside the turn."""
    a = np.linspace(0.0, np.pi / 2, 40)
    xy = np.column_stack([12.0 * np.cos(a), 12.0 * np.sin(a), a])
    s = paths.arc_length(xy)
    fast, slow = _both(paths.path_curvature, xy, s)
    assert _same(fast, slow)
    assert np.allclose(fast[5:-5], 1.0 / 12.0, rtol=1e-3)


def test_the_kernel_can_be_switched_off() -> None:
    assert paths.kernel() is _scan
    assert paths.use_kernel(False) is True
    assert paths.kernel() is None
    assert paths.use_kernel(True) is False
    assert paths.kernel() is _scan


def test_the_kernel_declines_what_it_does_not_expect() -> None:
    good = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [2.0, 1.0, 0.2]])
    q = np.array([[0.5, 0.5]])
    nan = good.copy()
    nan[1, 0] = np.nan
    spoilt: list[Any] = [
        good.astype(np.float32),  # dtype
        good[:, :1].copy(),  # one column
        good.ravel(),  # one dimension
        good.astype(">f8"),  # byte order
        [[0.0, 0.0], [1.0, 0.0]],  # not an array
    ]
    for bad in spoilt:
        assert _scan.segment_lengths(bad) is None
        assert _scan.project_many(bad, q) is None
        assert _scan.project_many(good, bad) is None
        assert _scan.farther_than(bad, 0.0, 0.0, 1.0) is None
        assert _scan.path_headings(bad) is None
        assert _scan.path_curvature(bad, np.zeros(3), 2.0) is None
        assert _scan.convex_contains(bad, good[:, :2].copy(), good[:, :2].copy(), 0.0) is None
        assert _scan.convex_contains(q, bad, good[:, :2].copy(), 0.0) is None
        assert _scan.within_bounds(bad, 1.0, 1.0) is None
        assert _scan.gap_over(bad, 0.5) is None
    empty = np.empty((0, 3))
    assert _scan.project_many(empty, q) is None
    assert _scan.farther_than(empty, 0.0, 0.0, 1.0) is None
    assert _scan.project_many(nan, q) is None  # non-finite: numpy answers
    assert _scan.farther_than(good, np.inf, 0.0, 1.0) is None
    s = paths.arc_length(good)
    assert _scan.path_curvature(good, s[:2].copy(), 2.0) is None  # short arc lengths
    assert _scan.path_curvature(good, s[::-1].copy(), 2.0) is None  # not sorted
    assert _scan.path_curvature(good, s.astype(np.float32), 2.0) is None
    assert _scan.convex_contains(q, good[:, :2].copy(), good[:2, :2].copy(), 0.0) is None
    with pytest.raises(TypeError):
        _scan.project_many(good)  # type: ignore[call-arg]
    # the functions still answer through numpy
    assert _same(*_both(paths.project_many, nan, q))
    assert _same(*_both(paths.segment_lengths, nan))
