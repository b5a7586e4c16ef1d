"""Geometry: polylines, convex polygons, occlusion, footprints."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.model.geometry import (
    PolygonSet,
    Polyline,
    any_rects_overlap,
    convex_distance,
    convex_overlap,
    fillet_polyline,
    footprint,
    footprints,
    is_convex,
    min_point_distance,
    polygon_area,
    polygon_contains,
    rect_distance,
    rect_distances,
    rects_overlap,
    segment_blocked,
    visible_mask,
    wrap_angle,
)

SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
L_SHAPE = Polyline([(0.0, 0.0), (10.0, 0.0), (10.0, 5.0)])


# --------------------------------------------------------------------------- polyline


def test_polyline_lengths_and_points() -> None:
    pl = L_SHAPE
    assert pl.length == pytest.approx(15.0)
    assert pl.cumlen.tolist() == [0.0, 10.0, 15.0]
    assert pl.point_at(4.0) == pytest.approx((4.0, 0.0))
    assert pl.point_at(12.5) == pytest.approx((10.0, 2.5))
    assert pl.point_at(-3.0) == pytest.approx((0.0, 0.0))  # clamped
    assert pl.point_at(99.0) == pytest.approx((10.0, 5.0))
    pts = pl.points_at(np.array([0.0, 10.0, 15.0, 20.0]))
    assert pts.shape == (4, 2)
    assert np.allclose(pts, [[0, 0], [10, 0], [10, 5], [10, 5]])


def test_polyline_headings() -> None:
    pl = L_SHAPE
    assert pl.heading_at(5.0) == pytest.approx(0.0)
    assert pl.heading_at(10.0) == pytest.approx(math.pi / 2)  # the leaving segment
    assert pl.heading_at(15.0) == pytest.approx(math.pi / 2)
    h = pl.headings_at(np.array([0.0, 9.9, 10.1]))
    assert h.tolist() == pytest.approx([0.0, 0.0, math.pi / 2])


def test_polyline_is_read_only() -> None:
    with pytest.raises(ValueError):
        L_SHAPE.points[0, 0] = 5.0
    with pytest.raises(ValueError):
        L_SHAPE.cumlen[0] = 1.0


@pytest.mark.parametrize(
    "points",
    [
        [(0.0, 0.0)],
        [(0.0, 0.0), (0.0, 0.0)],
        [(0.0, 0.0), (1.0, 0.0), (1.0, 0.0)],
        [(0.0, 0.0), (math.nan, 1.0)],
        [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0)],
    ],
)
def test_polyline_rejects_bad_points(points: list[tuple[float, ...]]) -> None:
    with pytest.raises(ValueError):
        Polyline(points)  # type: ignore[arg-type]


def test_polyline_rejects_nan_arc_length() -> None:
    with pytest.raises(ValueError):
        L_SHAPE.point_at(math.nan)


def test_project_signed_lateral() -> None:
    pl = Polyline([(0.0, 0.0), (10.0, 0.0)])
    assert pl.project(3.0, 2.0) == pytest.approx((3.0, 2.0))  # left positive
    assert pl.project(3.0, -1.5) == pytest.approx((3.0, -1.5))
    s, lat = pl.project(13.0, 4.0)  # beyond the end: distance to the end point
    assert s == pytest.approx(10.0)
    assert lat == pytest.approx(5.0)


def test_project_on_corner_and_many() -> None:
    pl = L_SHAPE
    assert pl.project(8.0, 3.0) == pytest.approx((13.0, 2.0))  # left of the north leg
    assert pl.project(12.0, 3.0) == pytest.approx((13.0, -2.0))
    xy = np.array([[8.0, 3.0], [12.0, 3.0], [5.0, -1.0]])
    s, lat = pl.project_many(xy)
    assert s.tolist() == pytest.approx([13.0, 13.0, 5.0])
    assert lat.tolist() == pytest.approx([2.0, -2.0, -1.0])


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 15.0), st.floats(-0.9, 0.9))
def test_project_inverts_point_at(s: float, off: float) -> None:
    pl = L_SHAPE
    if abs(s - 10.0) < 1.0:  # near the corner, the closest point may be on the other leg
        return
    x, y = pl.point_at(s)
    h = pl.heading_at(s)
    sp, lat = pl.project(x - off * math.sin(h), y + off * math.cos(h))
    assert sp == pytest.approx(s, abs=1e-9)
    assert lat == pytest.approx(off, abs=1e-9)


def test_interval_in_polygon() -> None:
    pl = Polyline([(-10.0, 0.5), (10.0, 0.5)])
    assert pl.interval_in_polygon(SQUARE) == pytest.approx((9.0, 11.0))
    assert pl.interval_in_polygon(SQUARE[::-1]) == pytest.approx((9.0, 11.0))  # clockwise
    assert Polyline([(-10.0, 5.0), (10.0, 5.0)]).interval_in_polygon(SQUARE) is None
    # The polygon is closed: running along an edge is inside ...
    diamond = np.array([[-1.0, 1.0], [0.0, 0.0], [1.0, 1.0], [0.0, 2.0]])
    assert Polyline([(-2.0, 0.0), (0.0, 2.0)]).interval_in_polygon(diamond) == pytest.approx(
        (math.sqrt(2), 2.0 * math.sqrt(2))
    )
    # ... but touching a single corner is not entering.
    assert Polyline([(-2.0, 0.0), (0.0, 2.0)]).interval_in_polygon(SQUARE) is None


def test_interval_over_several_segments_and_twice() -> None:
    pl = Polyline([(-5.0, 0.0), (0.0, 0.0), (0.0, 5.0)])
    iv = pl.interval_in_polygon(SQUARE)
    assert iv == pytest.approx((4.0, 6.0))
    assert len(pl.intervals_in_polygon(SQUARE)) == 1
    u_turn = Polyline([(-5.0, 0.5), (5.0, 0.5), (5.0, -0.5), (-5.0, -0.5)])
    ivs = u_turn.intervals_in_polygon(SQUARE)
    assert len(ivs) == 2
    assert ivs[0] == pytest.approx((4.0, 6.0))
    assert ivs[1] == pytest.approx((15.0, 17.0))
    assert u_turn.interval_in_polygon(SQUARE) == pytest.approx((4.0, 17.0))


def test_sample_and_slice() -> None:
    pts = L_SHAPE.sample(8.0, 12.0, 0.5)
    assert len(pts) == 9
    assert pts[0].tolist() == pytest.approx([8.0, 0.0])
    assert pts[-1].tolist() == pytest.approx([10.0, 2.0])
    piece = L_SHAPE.slice(8.0, 12.0)
    assert piece.length == pytest.approx(4.0)
    assert np.allclose(piece.points, [[8, 0], [10, 0], [10, 2]])


def test_fillet_polyline_left_turn() -> None:
    r = 3.0
    pts = fillet_polyline([(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)], r, step_m=0.1)
    pl = Polyline(pts)
    # Two straights shortened by r each, plus a quarter circle.
    assert pl.length == pytest.approx(20.0 - 2 * r + math.pi * r / 2, abs=0.01)
    arc = pts[1:-1]
    d = np.hypot(arc[:, 0] - 7.0, arc[:, 1] - 3.0)
    assert np.allclose(d, r)
    h = pl.headings_at(np.linspace(0.0, pl.length, 400))
    assert np.max(np.abs(np.diff(h))) < 0.05  # no heading jump


def test_fillet_polyline_right_turn_and_errors() -> None:
    pts = fillet_polyline([(0.0, 0.0), (10.0, 0.0), (10.0, -10.0)], 2.0)
    arc = pts[1:-1]
    assert np.allclose(np.hypot(arc[:, 0] - 8.0, arc[:, 1] + 2.0), 2.0)
    assert fillet_polyline([(0.0, 0.0), (1.0, 0.0)], 5.0).shape == (2, 2)
    with pytest.raises(ValueError, match="does not fit"):
        fillet_polyline([(0.0, 0.0), (2.0, 0.0), (2.0, 10.0)], 5.0)
    with pytest.raises(ValueError, match="turns back"):
        fillet_polyline([(0.0, 0.0), (2.0, 0.0), (0.0, 0.0)], 0.5)


# --------------------------------------------------------------------------- polygons


def test_convexity_and_area() -> None:
    assert is_convex(SQUARE)
    assert is_convex(SQUARE[::-1])
    assert is_convex([(0.0, 0.0), (1.0, 0.0), (2.0, 0.0), (2.0, 2.0), (0.0, 2.0)])  # collinear
    assert not is_convex([(0.0, 0.0), (2.0, 2.0), (2.0, 0.0), (0.0, 2.0)])  # bow tie
    assert not is_convex([(0.0, 0.0), (2.0, 0.0), (1.0, 0.5), (2.0, 2.0), (0.0, 2.0)])
    assert not is_convex([(0.0, 0.0), (1.0, 0.0)])
    assert not is_convex([(0.0, 0.0), (1.0, 0.0), (2.0, 0.0)])  # no area
    assert not is_convex([(0.0, 0.0), (1.0, 0.0), (1.0, 0.0), (0.0, 1.0)])  # repeated vertex
    star = [
        (math.cos(a), math.sin(a)) for a in np.arange(5) * 4 * math.pi / 5
    ]  # pentagram: same-sign turns, winds twice
    assert not is_convex(star)
    assert polygon_area(SQUARE) == pytest.approx(4.0)
    assert polygon_area(SQUARE[::-1]) == pytest.approx(-4.0)
    assert polygon_contains(SQUARE, 1.0, 0.0)
    assert not polygon_contains(SQUARE, 1.01, 0.0)


def test_segment_blocked_cases() -> None:
    polys = [SQUARE]
    assert segment_blocked((-5.0, 0.0), (5.0, 0.0), polys)  # straight through
    assert segment_blocked((-5.0, 0.0), (0.0, 0.0), polys)  # ends inside
    assert not segment_blocked((-5.0, 1.0), (5.0, 1.0), polys)  # along an edge
    assert not segment_blocked((-2.0, 0.0), (0.0, 2.0), polys)  # through the vertex (-1, 1)
    assert not segment_blocked((-5.0, 3.0), (5.0, 3.0), polys)  # misses
    assert not segment_blocked((-5.0, 0.0), (-1.0, 0.0), polys)  # stops on the face
    assert not segment_blocked((-5.0, 0.0), (5.0, 0.0), [])


def test_visible_mask_matches_segment_blocked_and_set() -> None:
    rng = np.random.default_rng(7)
    polys = [
        SQUARE + np.array([3.0, 0.0]),
        SQUARE * 2.0 + np.array([-4.0, 4.0]),
        np.array([[0, -6], [2, -4], [-1, -3]]),
    ]
    packed = PolygonSet.from_polygons(polys)
    targets = rng.uniform(-10.0, 10.0, size=(300, 2))
    p = (0.3, -0.2)
    m1 = visible_mask(p, targets, polys)
    m2 = visible_mask(p, targets, packed)
    assert m1.shape == (300,)
    assert np.array_equal(m1, m2)
    one_by_one = np.array([not segment_blocked(p, (float(x), float(y)), polys) for x, y in targets])
    assert np.array_equal(m1, one_by_one)
    assert 0 < int(m1.sum()) < 300  # both outcomes occur


def _depth(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Signed depth of points inside a CCW convex polygon (min over edges)."""
    e = np.roll(poly, -1, axis=0) - poly
    n = np.stack((-e[:, 1], e[:, 0]), axis=1)
    n = n / np.hypot(n[:, 0], n[:, 1])[:, None]
    d = np.einsum("mek,ek->me", pts[:, None, :] - poly[None, :, :], n)
    out: np.ndarray = d.min(axis=1)
    return out


@settings(max_examples=80, deadline=None)
@given(
    st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
    st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
)
def test_visible_mask_against_sampling_oracle(
    p: tuple[float, float], q: tuple[float, float]
) -> None:
    poly = np.array([[-3.0, -2.0], [4.0, -1.0], [3.0, 5.0], [-2.0, 3.0]])
    ts = np.linspace(0.0, 1.0, 4001)[:, None]
    pts = np.array(p) + ts * (np.array(q) - np.array(p))
    depth = float(_depth(poly, pts).max())
    blocked = segment_blocked(p, q, [poly])
    if depth > 0.05:
        assert blocked
    elif depth < -0.05:
        assert not blocked


def test_visible_mask_empty_inputs() -> None:
    assert visible_mask((0.0, 0.0), np.zeros((0, 2)), [SQUARE]).shape == (0,)
    assert visible_mask((5.0, 5.0), np.array([[6.0, 6.0]]), []).tolist() == [True]


def test_read_only_polygons_are_packed_once() -> None:
    a = SQUARE.copy()
    a.flags.writeable = False
    targets = np.array([[5.0, 0.0], [0.0, 5.0]])
    first = visible_mask((-5.0, 0.0), targets, [a])
    again = visible_mask((-5.0, 0.0), targets, [a])
    assert first.tolist() == again.tolist() == [False, True]


# --------------------------------------------------------------------------- footprints


def test_footprint_corners() -> None:
    fp = footprint(10.0, 5.0, 0.0, 4.0, 2.0)
    assert np.allclose(fp, [[12, 6], [8, 6], [8, 4], [12, 4]])
    fp = footprint(0.0, 0.0, math.pi / 2, 4.0, 2.0)
    assert np.allclose(fp, [[-1, 2], [-1, -2], [1, -2], [1, 2]])
    assert polygon_area(fp) == pytest.approx(8.0)  # counter-clockwise
    many = footprints([10.0, 0.0], [5.0, 0.0], [0.0, math.pi / 2], 4.0, 2.0)
    assert many.shape == (2, 4, 2)
    assert np.allclose(many[1], fp)


def test_rect_overlap_and_distance() -> None:
    a = footprint(0.0, 0.0, 0.0, 4.0, 2.0)
    b = footprint(5.0, 0.0, 0.0, 4.0, 2.0)  # 1 m gap, nose to tail
    assert not rects_overlap(a, b)
    assert rect_distance(a, b) == pytest.approx(1.0)
    c = footprint(3.0, 0.5, 0.3, 4.0, 2.0)
    assert rects_overlap(a, c)
    assert rect_distance(a, c) == 0.0
    d = footprint(4.0, 0.0, 0.0, 4.0, 2.0)  # touching
    assert rects_overlap(a, d)
    assert rect_distance(a, d) == 0.0
    e = footprint(5.0, 4.0, 0.0, 4.0, 2.0)  # diagonal: corner (2, 1) to corner (3, 3)
    assert rect_distance(a, e) == pytest.approx(math.sqrt(5.0))
    f = footprint(0.0, 2.0 + math.sqrt(2.0), math.pi / 4, 2.0, 2.0)  # rotated square, corner down
    assert rect_distance(a, f) == pytest.approx(1.0)
    assert rect_distance(f, a) == pytest.approx(1.0)


def test_rect_sat_needs_both_axis_sets() -> None:
    a = footprint(0.0, 0.0, 0.0, 2.0, 2.0)
    b = footprint(1.9, 1.9, math.pi / 4, 2.0, 2.0)  # separated only along b's axis
    assert not rects_overlap(a, b)
    assert rect_distance(a, b) > 0.0


def test_helpers() -> None:
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    assert wrap_angle(-0.5) == pytest.approx(-0.5)
    assert min_point_distance(np.array([[0.0, 0.0], [5.0, 5.0]]), np.array([[3.0, 4.0]])) == (
        pytest.approx(math.sqrt(5.0))
    )


def test_rect_distances_batch_matches_general_convex() -> None:
    rng = np.random.default_rng(3)
    n = 400
    a = footprints(rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(-4, 4, n), 4.5, 1.8)
    b = footprints(rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(-4, 4, n), 4.5, 1.8)
    batch = rect_distances(a, b)
    one = np.array([convex_distance(a[k], b[k]) for k in range(n)])
    assert np.allclose(batch, one)
    assert np.array_equal(batch == 0.0, np.array([convex_overlap(a[k], b[k]) for k in range(n)]))
    assert 0 < int((batch == 0.0).sum()) < n
    assert rect_distances(np.zeros((0, 4, 2)), np.zeros((0, 4, 2))).shape == (0,)


_coord = st.floats(-10.0, 10.0, allow_nan=False)
_body = st.tuples(
    _coord, _coord, st.floats(-math.pi, math.pi), st.floats(0.5, 6.0), st.floats(0.5, 3.0)
)


@settings(max_examples=60, deadline=None)
@given(a=st.lists(_body, max_size=5), b=st.lists(_body, max_size=5))
def test_any_rects_overlap_is_the_pairwise_test_over_all_pairs(
    a: list[tuple[float, float, float, float, float]],
    b: list[tuple[float, float, float, float, float]],
) -> None:
    fa = [footprint(*body) for body in a]
    fb = [footprint(*body) for body in b]
    expected = any(rects_overlap(p, q) for p in fa for q in fb)
    got = any_rects_overlap(np.array(fa).reshape(-1, 4, 2), np.array(fb).reshape(-1, 4, 2))
    assert got == expected
