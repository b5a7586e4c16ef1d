"""A route's projection and the bodies' overlap test in C (``services/model/_geometry.c``)
against the numpy code they replace (``Polyline.project_many``, ``any_rects_overlap``).

The kernel must give numpy's numbers to the bit, or decline with None so that numpy
answers. Without a C compiler it is not built: locally these tests then skip, on CI
(``CI`` set) they fail, since ``make test`` builds it.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from services.model import geometry
from services.model.geometry import Polyline, any_rects_overlap, footprints
from tests.kernels import both_ways, require_kernel

require_kernel(geometry.kernel_available(), "services.model._geometry")

from services.model import _geometry  # noqa: E402 - after the check above


@pytest.fixture(autouse=True)
def _kernel_on() -> Iterator[None]:
    previous = geometry.use_kernel(True)
    yield
    geometry.use_kernel(previous)


def _both(line: Polyline, xy: Any) -> tuple[Any, Any]:
    return both_ways(geometry.use_kernel, line.project_many, xy)


def _same(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> bool:
    return all(
        x.dtype == y.dtype
        and x.shape == y.shape
        and np.array_equal(x, y)
        and np.array_equal(np.signbit(x), np.signbit(y))
        for x, y in zip(a, b, strict=True)
    )


@st.composite
def _routes(draw: st.DrawFn) -> Polyline:
    """2-60 vertices, steps of 0.5-40 m in any direction (zig-zags, hairpins, turns)."""
    n = draw(st.integers(2, 60))
    angles = draw(hnp.arrays(np.float64, (n - 1,), elements=st.floats(-np.pi, np.pi)))
    lengths = draw(hnp.arrays(np.float64, (n - 1,), elements=st.floats(0.5, 40.0)))
    steps = np.column_stack([lengths * np.cos(angles), lengths * np.sin(angles)])
    origin = draw(st.sampled_from([0.0, -150.0, 2500.25]))
    return Polyline(origin + np.vstack([[0.0, 0.0], np.cumsum(steps, axis=0)]))


@settings(max_examples=300, deadline=None)
@given(
    _routes(),
    hnp.arrays(
        np.float64, st.tuples(st.integers(0, 12), st.just(2)), elements=st.floats(-300.0, 300.0)
    ),
)
def test_projection_equals_numpy(line: Polyline, offsets: np.ndarray) -> None:
    """Points anywhere near, on the vertices, and beyond either end."""
    pts = np.vstack([line.points[0] + offsets, line.points, line.points[[0, -1]] * 1.001])
    fast, slow = _both(line, pts)
    assert _same(fast, slow)
    s, lateral = fast
    assert np.all((s >= 0.0) & (s <= line.length))
    on_route = np.abs(lateral[offsets.shape[0] :][: line.points.shape[0]])
    assert np.all(on_route <= 1e-9)  # a vertex projects onto the route itself


def test_a_point_left_of_a_straight_road_is_positive_on_both() -> None:
    line = Polyline(np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]]))
    fast, slow = _both(line, [[12.0, 3.0], [5.0, -2.0], [25.0, 0.0]])
    assert _same(fast, slow)
    assert fast[0].tolist() == [12.0, 5.0, 20.0]
    assert fast[1].tolist() == [3.0, -2.0, 5.0]


def test_the_kernel_declines_what_it_does_not_expect() -> None:
    line = Polyline(np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 5.0]]))
    a, u, ln, cum = line.points[:-1], line._unit, line._seglen, line.cumlen
    p = np.array([[1.0, 1.0]])
    assert _geometry.project_many(a, u, ln, cum, p) is not None
    spoilt: list[tuple[Any, ...]] = [
        (a.astype(np.float32), u, ln, cum, p),
        (a, u[:1], ln, cum, p),  # fewer units than segments
        (a, u, ln[:1], cum, p),  # short lengths
        (a, u, ln, cum[:-1], p),  # short arc lengths
        (a, u, ln, cum, p.ravel()),  # one dimension
        (a, u, ln, cum, np.array([[np.nan, 0.0]])),  # non-finite: numpy answers
        (a[:0], u[:0], ln[:0], cum[:1], p),  # no segment
        (a, u, ln.astype(">f8"), cum, p),  # byte order
        (a.tolist(), u, ln, cum, p),  # not an array
    ]
    for args in spoilt:
        assert _geometry.project_many(*args) is None
    with pytest.raises(TypeError):
        _geometry.project_many(a, u, ln, cum)  # type: ignore[call-arg]
    fast, slow = _both(line, np.array([[np.nan, 1.0]]))
    assert np.isnan(fast[0][0]) and np.isnan(slow[0][0])  # numpy's answer, both ways


def test_the_kernel_can_be_switched_off() -> None:
    assert geometry._KERNEL is _geometry
    assert geometry.use_kernel(False) is True
    assert geometry._KERNEL is None
    assert geometry.use_kernel(True) is False


def _overlap_both(a: np.ndarray, b: np.ndarray) -> tuple[bool, bool]:
    fast, slow = both_ways(geometry.use_kernel, any_rects_overlap, a, b)
    return fast, slow


_bodies = hnp.arrays(
    np.float64,
    st.tuples(st.integers(0, 6), st.just(5)),
    elements=st.floats(-12.0, 12.0, allow_nan=False),
)


@settings(max_examples=400, deadline=None)
@given(_bodies, _bodies, st.sampled_from([0.0, 0.5, 1.0]))
def test_body_overlap_equals_numpy(a: np.ndarray, b: np.ndarray, snap: float) -> None:
    """Cars of any pose and size 1-12 m, often touching: on a lattice (``snap`` > 0)
    corners and edges meet exactly, the borderline the separating axis test must call as
    numpy does (touching overlaps)."""
    if snap:
        a, b = np.round(a / snap) * snap, np.round(b / snap) * snap
        a[:, 2], b[:, 2] = np.round(a[:, 2]) * (np.pi / 2), np.round(b[:, 2]) * (np.pi / 2)
    fa = footprints(a[:, 0], a[:, 1], a[:, 2], 1.0 + np.abs(a[:, 3]), 1.0 + np.abs(a[:, 4]))
    fb = footprints(b[:, 0], b[:, 1], b[:, 2], 1.0 + np.abs(b[:, 3]), 1.0 + np.abs(b[:, 4]))
    fast, slow = _overlap_both(fa, fb)
    assert fast is slow


def test_touching_bodies_overlap_and_apart_ones_do_not_on_both() -> None:
    one = footprints([0.0], [0.0], [0.0], [4.0], [2.0])
    touching = footprints([4.0], [0.0], [0.0], [4.0], [2.0])  # front to back, 0 m apart
    apart = footprints([4.0 + 1e-9], [0.0], [0.0], [4.0], [2.0])
    diagonal = footprints([3.0], [3.0], [np.pi / 4], [4.0], [2.0])
    assert _overlap_both(one, touching) == (True, True)
    assert _overlap_both(one, apart) == (False, False)
    many = np.concatenate([apart, apart, touching])  # the last pair answers
    assert _overlap_both(one, many) == (True, True)
    assert _overlap_both(one, diagonal) == _overlap_both(diagonal, one)


def test_the_overlap_kernel_declines_what_it_does_not_expect() -> None:
    one = footprints([0.0], [0.0], [0.0], [4.0], [2.0])
    spoilt: list[Any] = [
        one.astype(np.float32),
        one.reshape(1, 8),
        one[:, :3],
        one.astype(">f8"),
        [1],
    ]
    for bad in spoilt:
        assert _geometry.any_quads_overlap(bad, one) is None
        assert _geometry.any_quads_overlap(one, bad) is None
    nan = one.copy()
    nan[0, 0, 0] = np.nan
    assert _geometry.any_quads_overlap(nan, one) is None  # numpy answers
    assert _overlap_both(nan, one)[0] is _overlap_both(nan, one)[1]
