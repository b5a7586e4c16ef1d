"""Geometry and timing helpers on paths, for the RSU (pure, vectorised with numpy).

A path is an (N, 3) float array of car-centre positions x, y [m] with pass
times t [s, run time base], as in ``protocol.messages``. A conflict zone is a
convex polygon (K, 2) [m], either orientation.

Eq. (1) of the paper gives the pass time of point n from the speed on the
segment that ends at it::

    t_n = t_{n-1} + |p_n - p_{n-1}| / v_n,   t_0 = current time

``retime`` applies it, ``segment_speeds`` inverts it. Zone helpers test points
only (no segment clipping): paths have points at most a few metres apart,
much less than the width of an intersection box.

:func:`segment_lengths`, :func:`farther_than`, :func:`project_many`,
:func:`path_curvature` and :meth:`ConvexZone.contains` (and ``reservation``'s
``path_headings``, ``within_wire_bounds`` and ``densify``'s gap test) run in C when the optional
kernel ``services/rsu/_scan.c`` was built (issue 14: numpy's overhead per call on
120-point paths made them a quarter of an RSU update in a jam); the numpy code stays the
reference and the fallback, and both give the same numbers to the bit
(``tests/rsu/test_paths_kernel.py``). :func:`use_kernel` switches it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from services.model.geometry import convex_overlap, footprint

try:  # the projections in C (services/rsu/_scan.c), built at install when there is a compiler
    from services.rsu import _scan as _kernel_module
except ImportError:  # pragma: no cover - without a C compiler
    _kernel_module = None  # type: ignore[assignment]

_KERNEL: Any = _kernel_module
"""``services.rsu._scan`` when built and in use, else None (:func:`use_kernel`)."""

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

_EPS = 1e-9  # services/rsu/_scan.c: SEG_EPS


def use_kernel(enabled: bool) -> bool:
    """Run the projections in C (when built) or in numpy; the previous setting. Both give
    the same numbers: this exists to measure and test each."""
    global _KERNEL
    previous = _KERNEL is not None
    _KERNEL = _kernel_module if enabled else None
    return previous


def kernel() -> Any:
    """``services.rsu._scan`` when built and in use (:func:`use_kernel`), else None."""
    return _KERNEL


APPROACH_END_M = 30.0
"""A future path ending this close to the conflict zone [m] (beyond its circumradius)
counts as approaching even if it does not enter it: a cautious car stops at the stop
line (8.5 m from the centre in the paper's scenario) or where it can see the crossing
road."""


CURVE_BASE_M = 2.0
"""A received path's curvature is measured on points at least this far either side of
each point [m]. Its points are quantised to 1 cm on the wire: over 0.1 m that alone
fakes a 1 m radius, over 2 m a radius of about 280 m at worst (a cap of 24 m/s at
2 m/s²). Three points of a circle give its radius exactly, however far apart."""


def path_curvature(xy: FloatArray, s: FloatArray) -> FloatArray:
    """Curvature [1/m] at each point (M, 2) of a path with arc lengths ``s`` (M,) [m].

    At each point, the circle through it and the nearest points at least
    :data:`CURVE_BASE_M` before and after it (0 where there are none); then the
    largest of these within ``2 CURVE_BASE_M`` of the point, so that a point where a
    curve begins or ends (its circle half on the straight) takes the curve's own
    curvature. Not the vehicle's ``curve_speed_cap``: that one reads a route's exact
    polyline, this one noisy samples of it.
    """
    if _KERNEL is not None:
        fast: FloatArray | None = _KERNEL.path_curvature(xy, s, CURVE_BASE_M)
        if fast is not None:
            return fast
    n = xy.shape[0]
    kappa = np.zeros(n, dtype=np.float64)
    if n < 3:
        return kappa
    before = np.searchsorted(s, s - CURVE_BASE_M, side="right") - 1
    after = np.searchsorted(s, s + CURVE_BASE_M, side="left")
    ok = np.flatnonzero((before >= 0) & (after < n))
    if ok.size:
        p, a, b = xy[ok], xy[before[ok]], xy[after[ok]]
        u, w = p - a, b - a
        cross2 = np.abs(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0])  # twice the triangle's area
        sides = np.hypot(u[:, 0], u[:, 1]) * np.hypot(*(b - p).T) * np.hypot(w[:, 0], w[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa[ok] = np.where(sides > 0.0, 2.0 * cross2 / sides, 0.0)
    near = np.abs(s[:, None] - s[None, :]) <= 2.0 * CURVE_BASE_M
    spread: FloatArray = np.where(near, kappa[None, :], 0.0).max(axis=1)
    return spread


def curve_caps(xy: FloatArray, s: FloatArray, lat_accel: float, v_max: float) -> FloatArray:
    """Speed cap [m/s] at each point (M, 2) of a path, arc lengths ``s`` (M,) [m]:
    ``min(v_max, sqrt(lat_accel * r))`` with the path's own radius ``r``
    (:func:`path_curvature`)."""
    kappa = path_curvature(xy, s)
    with np.errstate(divide="ignore"):
        caps: FloatArray = np.minimum(v_max, np.sqrt(lat_accel / kappa))
    return caps


def as_path(points: npt.ArrayLike) -> FloatArray:
    """Points as a float (N, 3) array; raises ValueError on a wrong shape."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"a path is an (N, 3) array of x, y, t; got shape {arr.shape}")
    return arr


def convex_polygon(polygon: npt.ArrayLike) -> FloatArray:
    """Validate a convex polygon (K >= 3 vertices, non-degenerate); return a read-only copy."""
    arr = np.array(polygon, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 3:
        raise ValueError(f"a conflict zone is a (K>=3, 2) polygon; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("conflict zone vertices must be finite")
    edges = np.roll(arr, -1, axis=0) - arr
    nxt = np.roll(edges, -1, axis=0)
    cross = edges[:, 0] * nxt[:, 1] - edges[:, 1] * nxt[:, 0]
    if not (np.all(cross >= -_EPS) or np.all(cross <= _EPS)):
        raise ValueError("conflict zone polygon must be convex")
    if abs(polygon_area(arr)) < _EPS:
        raise ValueError("conflict zone polygon has no area")
    arr.flags.writeable = False
    return arr


def polygon_area(polygon: FloatArray) -> float:
    """Signed area [m²] (positive when counter-clockwise)."""
    x, y = polygon[:, 0], polygon[:, 1]
    return float(0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))


def polygon_centroid(polygon: FloatArray) -> tuple[float, float]:
    """Area centroid of a simple polygon [m]: the intersection centre of a conflict zone."""
    x, y = polygon[:, 0], polygon[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * float(cross.sum())
    if abs(area) < _EPS:
        return float(x.mean()), float(y.mean())
    cx = float(((x + xn) * cross).sum()) / (6.0 * area)
    cy = float(((y + yn) * cross).sum()) / (6.0 * area)
    return cx, cy


@dataclass(frozen=True, slots=True, eq=False)
class ConvexZone:
    """A validated convex conflict zone with its edges precomputed (counter-clockwise)."""

    vertices: FloatArray  # (K, 2) [m], counter-clockwise
    edges: FloatArray  # (K, 2): vertex k+1 - vertex k
    centroid: tuple[float, float]
    tol: float
    radius: float  # [m] farthest vertex from the centroid
    sides: tuple[tuple[float, float, float, float], ...]  # (vx, vy, ex, ey) per edge

    @classmethod
    def of(cls, polygon: ConvexZone | npt.ArrayLike) -> ConvexZone:
        """Validate ``polygon`` (either orientation); raise ValueError if it is no convex zone."""
        if isinstance(polygon, ConvexZone):
            return polygon
        arr = np.array(convex_polygon(polygon))
        if polygon_area(arr) < 0:
            arr = arr[::-1].copy()
        edges = np.roll(arr, -1, axis=0) - arr
        arr.flags.writeable = False
        edges.flags.writeable = False
        tol = _EPS * max(1.0, float(np.abs(arr).max()))
        cx, cy = polygon_centroid(arr)
        radius = float(np.hypot(arr[:, 0] - cx, arr[:, 1] - cy).max())
        sides = tuple(
            (vx, vy, ex, ey)
            for (vx, vy), (ex, ey) in zip(arr.tolist(), edges.tolist(), strict=True)
        )
        return cls(arr, edges, (cx, cy), tol, radius, sides)

    def contains(self, xy: npt.ArrayLike) -> BoolArray:
        """Which points (M, 2+) lie inside or on the edge (vectorised; in C when built)."""
        if _KERNEL is not None:
            fast: BoolArray | None = _KERNEL.convex_contains(
                xy, self.vertices, self.edges, self.tol
            )
            if fast is not None:
                return fast
        pts = np.asarray(xy, dtype=np.float64)
        if pts.ndim == 1:
            pts = pts.reshape(1, -1)
        v, e = self.vertices, self.edges
        cross = e[None, :, 0] * (pts[:, 1:2] - v[None, :, 1]) - e[None, :, 1] * (
            pts[:, 0:1] - v[None, :, 0]
        )
        result: BoolArray = np.all(cross >= -self.tol, axis=1)
        return result

    def contains_point(self, x: float, y: float) -> bool:
        """One point inside or on the edge (plain floats: cheaper than numpy for one point)."""
        tol = self.tol
        for vx, vy, ex, ey in self.sides:  # noqa: SIM110 - a NaN side test stays "inside"
            if ex * (y - vy) - ey * (x - vx) < -tol:
                return False
        return True


def inside_convex(xy: npt.ArrayLike, polygon: ConvexZone | npt.ArrayLike) -> BoolArray:
    """Which points (M, 2+) lie inside or on the edge of a convex polygon (K, 2)."""
    return ConvexZone.of(polygon).contains(xy)


def segment_lengths(points: FloatArray) -> FloatArray:
    """Length of the segment ending at each point [m]; 0 for the first."""
    if _KERNEL is not None:
        fast: FloatArray | None = _KERNEL.segment_lengths(points)
        if fast is not None:
            return fast
    d = np.zeros(points.shape[0], dtype=np.float64)
    if points.shape[0] > 1:
        d[1:] = np.hypot(np.diff(points[:, 0]), np.diff(points[:, 1]))
    return d


def arc_length(points: FloatArray) -> FloatArray:
    """Distance along the path from its first point to each point [m]."""
    return np.cumsum(segment_lengths(points))


def segment_speeds(points: FloatArray, v0: float) -> FloatArray:
    """Eq. (1) inverted: the constant speed on the segment ending at each point [m/s].

    ``v0`` (the car's current speed) is used for the first point. A zero-length
    segment (a held stop) has speed 0; a segment with no time to cover a
    positive length has speed ``inf``.
    """
    n = points.shape[0]
    v = np.empty(n, dtype=np.float64)
    if n == 0:
        return v
    v[0] = v0
    if n > 1:
        d = segment_lengths(points)[1:]
        dt = np.diff(points[:, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(d <= 0.0, 0.0, np.where(dt > 0.0, d / np.where(dt > 0.0, dt, 1.0), np.inf))
        v[1:] = s
    return v


def retime(points: FloatArray, speeds: FloatArray, t0: float) -> FloatArray:
    """Eq. (1): new pass times from the constant speed on each segment (ending at each point).

    Returns a new (N, 3) array with the same positions. A segment of positive
    length at speed <= 0 is never covered: it and every later point get
    ``inf``. Zero-length segments take no time.
    """
    n = points.shape[0]
    out = np.array(points, dtype=np.float64, copy=True)
    if n == 0:
        return out
    d = segment_lengths(points)
    dt = np.zeros(n, dtype=np.float64)
    if n > 1:
        seg_v = np.asarray(speeds, dtype=np.float64)[1:]
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(d[1:] <= 0.0, 0.0, np.where(seg_v > 0.0, d[1:] / seg_v, np.inf))
        dt[1:] = step
    out[:, 2] = t0 + np.cumsum(dt)
    return out


def bounds(xy: FloatArray) -> tuple[float, float, float, float]:
    """x0, x1, y0, y1 [m] of the points ``xy`` (M >= 1, 2+ columns)."""
    x, y = xy[:, 0], xy[:, 1]
    return float(x.min()), float(x.max()), float(y.min()), float(y.max())


def beyond(
    box: tuple[float, float, float, float],
    x: FloatArray | float,
    y: FloatArray | float,
    reach: FloatArray | float,
) -> BoolArray:
    """Per point, (x, y) is farther than ``reach`` [m] from the box (:func:`bounds`), so
    from any point of a polyline inside it: :func:`project` would find it farther too (a
    cheap test before it; the slack is far above float rounding). Issue 14: the
    projections were the RSU's cost."""
    dx = np.maximum(np.maximum(box[0] - x, np.subtract(x, box[1])), 0.0)
    dy = np.maximum(np.maximum(box[2] - y, np.subtract(y, box[3])), 0.0)
    out: BoolArray = dx * dx + dy * dy > np.square(np.add(reach, 1e-6))
    return out


def farther_than(xy: FloatArray, x: float, y: float, reach: float) -> bool:
    """(x, y) is farther than ``reach`` [m] from the polyline ``xy`` (M >= 1, 2+
    columns), as :func:`project` measures it: its nearest vertex, less half the longest
    segment (a foot on a segment is within half its length of one of its ends), is. A
    cheap test before projecting (issue 14)."""
    if _KERNEL is not None:
        fast: bool | None = _KERNEL.farther_than(xy, x, y, reach)
        if fast is not None:
            return fast
    d = np.hypot(xy[:, 0] - x, xy[:, 1] - y)
    half = 0.5 * float(segment_lengths(xy).max())
    return float(d.min()) - half > reach + 1e-6


def project(xy: FloatArray, x: float, y: float) -> tuple[float, float, int]:
    """Where the point (x, y) [m] projects on the polyline ``xy`` (M >= 2, 2+ columns):
    (arc length [m], distance from the line [m], index of the segment's first point).
    Repeated points are skipped; ``(0, distance to the first point, 0)`` for a polyline
    that never moves. One point of :func:`project_many`."""
    s, dist, index = project_many(xy, np.array([[x, y]], dtype=np.float64))
    return float(s[0]), float(dist[0]), int(index[0])


def project_many(
    xy: FloatArray, points: FloatArray
) -> tuple[FloatArray, FloatArray, npt.NDArray[np.int64]]:
    """:func:`project` of every row of ``points`` (K, 2+) at once: arc lengths [m],
    distances [m] and segment indices, each (K,). One (K, M) pass instead of K calls
    (issue 14: the RSU projected a leader's path point by point)."""
    if _KERNEL is not None:
        fast: tuple[FloatArray, FloatArray, npt.NDArray[np.int64]] | None = _KERNEL.project_many(
            xy, points
        )
        if fast is not None:
            return fast
    pts = np.asarray(xy, dtype=np.float64)[:, :2]
    q = np.asarray(points, dtype=np.float64)[:, :2]
    k = q.shape[0]
    seg = np.diff(pts, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    ok = seg_len > _EPS
    if pts.shape[0] < 2 or not ok.any():
        dist0 = np.hypot(q[:, 0] - float(pts[0, 0]), q[:, 1] - float(pts[0, 1]))
        return np.zeros(k), dist0, np.zeros(k, dtype=np.int64)
    unit = np.where(ok[:, None], seg / np.where(ok, seg_len, 1.0)[:, None], 0.0)
    rel = q[:, None, :] - pts[None, :-1, :]  # (K, M-1, 2)
    along = np.clip(np.einsum("kij,ij->ki", rel, unit), 0.0, seg_len)
    foot = pts[None, :-1, :] + unit[None, :, :] * along[:, :, None]
    dist = np.hypot(foot[:, :, 0] - q[:, 0:1], foot[:, :, 1] - q[:, 1:2])
    dist[:, ~ok] = np.inf
    index = np.argmin(dist, axis=1)
    rows = np.arange(k)
    start = np.concatenate(([0.0], np.cumsum(seg_len)))
    return start[index] + along[rows, index], dist[rows, index], index.astype(np.int64)


def heading_of(xy: FloatArray, index: int) -> float | None:
    """Heading [rad] of the polyline's segment ``index`` (or the nearest one that moves
    before or after it); None for a polyline that never moves."""
    pts = np.asarray(xy, dtype=np.float64)[:, :2]
    last = pts.shape[0] - 2  # the last segment
    if last >= 0:
        # the segment at ``index`` (the first or last one beyond the ends) is its own
        # nearest when it moves: no pass over the whole polyline (issue 14)
        j = min(max(index, 0), last)
        dx = float(pts[j + 1, 0] - pts[j, 0])
        dy = float(pts[j + 1, 1] - pts[j, 1])
        if float(np.hypot(dx, dy)) > _EPS:
            return math.atan2(dy, dx)
    seg = np.diff(pts, axis=0)
    moving = np.flatnonzero(np.hypot(seg[:, 0], seg[:, 1]) > _EPS)
    if moving.size == 0:
        return None
    j = int(moving[np.argmin(np.abs(moving - index))])
    return math.atan2(float(seg[j, 1]), float(seg[j, 0]))


def headings_at(xy: FloatArray, index: npt.NDArray[np.int64]) -> FloatArray:
    """:func:`heading_of` for every segment index in ``index`` at once [rad]; NaN for a
    polyline that never moves (issue 14: one call per car ahead was a tenth of a stop)."""
    pts = np.asarray(xy, dtype=np.float64)[:, :2]
    seg = np.diff(pts, axis=0)
    moving = np.flatnonzero(np.hypot(seg[:, 0], seg[:, 1]) > _EPS)
    if moving.size == 0:
        return np.full(index.shape[0], np.nan)
    # the nearest moving segment, the earlier one on a tie (as heading_of's argmin)
    pos = np.searchsorted(moving, index)
    lo = moving[np.maximum(pos - 1, 0)]
    hi = moving[np.minimum(pos, moving.size - 1)]
    j = np.where(np.abs(index - lo) <= np.abs(hi - index), lo, hi)
    # math.atan2, as heading_of: numpy's arctan2 differs from it in the last bit at times
    rise, run = seg[j, 1].tolist(), seg[j, 0].tolist()
    return np.array([math.atan2(a, b) for a, b in zip(rise, run, strict=True)], dtype=np.float64)


def zone_span(points: FloatArray, polygon: ConvexZone | npt.ArrayLike) -> tuple[int, int] | None:
    """(first index inside the zone, first index after leaving it again) or None.

    The exit index is N when the path ends inside the zone.
    """
    if points.shape[0] == 0:
        return None
    inside = ConvexZone.of(polygon).contains(points[:, :2])
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return None
    first = int(idx[0])
    after = np.flatnonzero(~inside[first:])
    exit_index = first + int(after[0]) if after.size else points.shape[0]
    return first, exit_index


AT_REST_MPS = 0.25
"""A path whose last segment is slower than this [m/s] ends at rest (issue 12, cause 1)."""

BODY_TOUCH_M = 0.05
"""A body whose edge only touches the zone, within this [m], does not block it."""


STANDING_M = 0.1
"""A path whose points all lie within this of its first [m] stands still (a future
path drops points closer than 0.1 m)."""


def stands(points: FloatArray) -> bool:
    """The path (N, 3) never moves: every point within ``STANDING_M`` of the first."""
    if points.shape[0] < 2:
        return True
    d = points[:, :2] - points[0, :2]
    return float(np.max(np.einsum("nc,nc->n", d, d))) <= STANDING_M * STANDING_M


def ends_at_rest(points: FloatArray) -> bool:
    """The path (N, 3) ends standing still: one point, a repeated last point (a held
    stop), or a last segment of a few cm over a long time (a future path drops points
    closer than 0.1 m, so its stop point may sit just past the last one)."""
    if points.shape[0] < 2:
        return True
    d = math.hypot(float(points[-1, 0] - points[-2, 0]), float(points[-1, 1] - points[-2, 1]))
    dt = float(points[-1, 2] - points[-2, 2])
    return d <= 1e-6 or (dt > 0.0 and d < AT_REST_MPS * dt)


def body_in_zone(
    xy: FloatArray,
    polygon: ConvexZone | npt.ArrayLike,
    length: float,
    width: float,
    heading: float,
) -> bool:
    """The body of a car of ``length`` x ``width`` [m] at the polyline's last point (M, 2+),
    along its last moving segment (else ``heading`` [rad]), overlaps the zone by more
    than ``BODY_TOUCH_M``: a path that ends at rest there (:func:`ends_at_rest`) leaves
    the car standing in the box, blocking every crossing through it."""
    x, y = float(xy[-1, 0]), float(xy[-1, 1])
    last = heading_of(xy, xy.shape[0] - 2)
    h = heading if last is None else last
    return pose_in_zone(x, y, h, length, width, polygon, BODY_TOUCH_M)


def pose_in_zone(
    x: float,
    y: float,
    heading: float,
    length: float,
    width: float,
    polygon: ConvexZone | npt.ArrayLike,
    shrink: float = 0.0,
) -> bool:
    """The body of a car of ``length`` x ``width`` [m] at (x, y) heading ``heading`` [rad]
    overlaps the zone by more than ``shrink`` [m] (each side pulled in by that much)."""
    zone = ConvexZone.of(polygon)
    cx, cy = zone.centroid
    if math.hypot(x - cx, y - cy) > zone.radius + 0.5 * math.hypot(length, width):
        return False  # far from the box: the cheap test first
    body = footprint(x, y, heading, max(length - 2.0 * shrink, 0.0), max(width - 2.0 * shrink, 0.0))
    return convex_overlap(body, np.asarray(zone.vertices))


def zone_entry_time(points: FloatArray, polygon: ConvexZone | npt.ArrayLike) -> float:
    """Pass time of the first point inside the zone [s]; ``inf`` if the path never enters."""
    span = zone_span(points, polygon)
    if span is None:
        return math.inf
    return float(points[span[0], 2])


def is_leaving(
    x: float,
    y: float,
    heading: float,
    polygon: ConvexZone | npt.ArrayLike,
    centre: tuple[float, float] | None = None,
) -> bool:
    """The car has passed the conflict zone: outside it and heading away from its centre.

    ``centre`` defaults to the zone's centroid.
    """
    zone = ConvexZone.of(polygon)
    if zone.contains_point(x, y):
        return False
    cx, cy = zone.centroid if centre is None else centre
    return math.cos(heading) * (x - cx) + math.sin(heading) * (y - cy) > 0.0


def is_approaching(
    x: float,
    y: float,
    points: FloatArray,
    polygon: ConvexZone | npt.ArrayLike,
    rsu_centre: tuple[float, float],
    coverage_m: float,
    now: float,
    horizon_s: float,
) -> bool:
    """In coverage, not yet in the zone, and heading for it.

    Heading for it: the path enters the zone within ``horizon_s`` of ``now``,
    or it ends closer to the zone than the car is now and within
    :data:`APPROACH_END_M` of it. The second case is a car whose own plan stops
    short of the zone (blind-corner caution: it will not enter until it sees
    the crossing road, which the RSU sees for it). The distance bound keeps a
    car merely driving in the zone's general direction, on another road or
    hundreds of metres away, out of coordination.
    """
    if math.hypot(x - rsu_centre[0], y - rsu_centre[1]) > coverage_m:
        return False
    zone = ConvexZone.of(polygon)
    if zone.contains_point(x, y):
        return False
    if zone_entry_time(points, zone) <= now + horizon_s:
        return True
    if points.shape[0] == 0:
        return False
    cx, cy = zone.centroid
    here = math.hypot(x - cx, y - cy)
    there = math.hypot(float(points[-1, 0]) - cx, float(points[-1, 1]) - cy)
    return there < here - 0.5 and there <= zone.radius + APPROACH_END_M


def zone_entry_s(
    xy: FloatArray, s: FloatArray, polygon: ConvexZone | npt.ArrayLike, extend_m: float = 0.0
) -> float | None:
    """Arc length [m] at which the polyline ``xy`` (M, 2+), arc lengths ``s`` (M,), first
    touches the zone, the polyline continued straight beyond its end by ``extend_m`` [m]
    (a body's front reaches past the centre's last point); refined on the crossing segment
    by bisection. None when it never does (or never moves when it starts outside)."""
    zone = ConvexZone.of(polygon)
    pts = np.asarray(xy, dtype=np.float64)[:, :2]
    arc = np.asarray(s, dtype=np.float64)
    if pts.shape[0] == 0:
        return None
    if extend_m > 0.0 and pts.shape[0] >= 2:
        heading = heading_of(pts, pts.shape[0] - 2)
        if heading is not None:
            tip = pts[-1] + extend_m * np.array([math.cos(heading), math.sin(heading)])
            pts = np.vstack([pts, tip])
            arc = np.append(arc, arc[-1] + extend_m)
    inside = zone.contains(pts)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return None
    i = int(idx[0])
    if i == 0:
        return float(arc[0])
    ax, ay = float(pts[i - 1, 0]), float(pts[i - 1, 1])
    dx, dy = float(pts[i, 0]) - ax, float(pts[i, 1]) - ay
    lo, hi = 0.0, 1.0  # lo outside, hi inside (convex: one crossing on the segment)
    for _ in range(30):  # in floats: the same arithmetic as numpy's, without its overhead
        mid = 0.5 * (lo + hi)
        if zone.contains_point(ax + mid * dx, ay + mid * dy):
            hi = mid
        else:
            lo = mid
    return float(arc[i - 1] + hi * (arc[i] - arc[i - 1]))
