"""Plane geometry of the world model: polylines, convex polygons, occlusion, car footprints.

Units are metres and radians; a heading is measured counter-clockwise from +x (east),
so east is 0 and north is pi/2. Arc length ``s`` is measured along a polyline from its
first point, in metres.

**Reference point.** Every position in crosspath (ground truth, sensed cars, future
paths, ``s`` along a route) is the car's *geometric centre*: the centre of its
length x width rectangle. The front bumper is ``length / 2`` ahead of it.

Everything here is pure and vectorised with numpy: the sensors call
:func:`visible_mask` for hundreds of points every planning step of every car.
Polygons (buildings, conflict zones) are convex; either vertex order is accepted.
:meth:`Polyline.project_many` and :func:`any_rects_overlap` run in C when the optional
kernel ``services/model/_geometry.c`` was built (issue 14: the planners' projections of
other cars' future paths onto their routes, the RSU's body sweeps); numpy stays the
reference and the fallback, with the same answers to the bit; :func:`use_kernel` switches
it.
"""

from __future__ import annotations

import functools
import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

try:  # the projection and overlap kernels (services/model/_geometry.c), built with a compiler
    from services.model import _geometry as _geometry_module
except ImportError:  # pragma: no cover - without a C compiler
    _geometry_module = None  # type: ignore[assignment]

_KERNEL: Any = _geometry_module
"""``services.model._geometry`` when built and in use, else None (:func:`use_kernel`)."""

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]
BoolArray = npt.NDArray[np.bool_]

PointLike = tuple[float, float]

_EPS = 1e-9
"""Tolerance of the parametric clipping tests (dimensionless, per segment)."""

__all__ = [
    "BoolArray",
    "FloatArray",
    "PolygonSet",
    "Polyline",
    "convex_distance",
    "convex_overlap",
    "fillet_polyline",
    "footprint",
    "footprints",
    "is_convex",
    "min_point_distance",
    "polygon_area",
    "polygon_contains",
    "rect_distance",
    "rect_distances",
    "rects_overlap",
    "segment_blocked",
    "vertex_curvature",
    "visible_mask",
    "wrap_angle",
]

KINK_SPAN_M = 4.0
"""A polyline corner is driven as if its heading change were spread over at most this
arc length [m]: an unrounded 90° corner is then a ~2.5 m radius (a rounded one, see
``corner_radius_m``, has its true radius)."""


def use_kernel(enabled: bool) -> bool:
    """Project onto polylines and test bodies' overlap in C (when built) or in numpy; the
    previous setting. Both give the same answers: this exists to measure and test each."""
    global _KERNEL
    previous = _KERNEL is not None
    _KERNEL = _geometry_module if enabled else None
    return previous


def kernel_available() -> bool:
    """Whether ``services/model/_geometry.c`` was built."""
    return _geometry_module is not None


def wrap_angle(a: float) -> float:
    """Angle folded into [-pi, pi), radians."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _as_points(points: Sequence[PointLike] | FloatArray, what: str, min_n: int) -> FloatArray:
    """A fresh (N, 2) float64 copy of ``points``, validated: finite, at least ``min_n`` rows."""
    try:
        arr = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: not a list of [x, y] pairs ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{what}: expected a list of [x, y] pairs, got shape {arr.shape}")
    if arr.shape[0] < min_n:
        raise ValueError(f"{what}: needs at least {min_n} points, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what}: coordinates must be finite")
    return arr


def _readonly(a: FloatArray) -> FloatArray:
    a.flags.writeable = False
    return a


# --------------------------------------------------------------------------- polylines


class Polyline:
    """A piecewise-linear curve with arc-length parametrisation.

    ``points`` (N, 2), ``cumlen`` (N,) arc length at each vertex and ``length`` are
    read-only. Queries clamp ``s`` to [0, length]. The heading of a vertex is the
    heading of the segment that *leaves* it (the last segment for the end point).
    """

    __slots__ = (
        "_cum_list",
        "_dir",
        "_head_list",
        "_heading",
        "_pt_list",
        "_seglen",
        "_unit",
        "_unit_list",
        "cumlen",
        "length",
        "points",
    )

    points: FloatArray
    cumlen: FloatArray
    length: float

    def __init__(self, points: Sequence[PointLike] | FloatArray) -> None:
        pts = _as_points(points, "polyline", 2)
        d = np.diff(pts, axis=0)
        seglen = np.hypot(d[:, 0], d[:, 1])
        short = np.flatnonzero(seglen <= 1e-9)
        if short.size:
            raise ValueError(f"polyline: zero-length segment after point {int(short[0])}")
        self.points = _readonly(pts)
        self.cumlen = _readonly(np.concatenate(([0.0], np.cumsum(seglen))))
        self.length = float(self.cumlen[-1])
        self._dir = _readonly(d)
        self._seglen = _readonly(seglen)
        self._unit = _readonly(d / seglen[:, None])
        self._heading = _readonly(np.arctan2(d[:, 1], d[:, 0]))
        # Plain-Python copies for the scalar queries the per-step code makes.
        self._cum_list: list[float] = self.cumlen.tolist()
        self._pt_list: list[list[float]] = pts.tolist()
        self._unit_list: list[list[float]] = self._unit.tolist()
        self._head_list: list[float] = self._heading.tolist()

    def __repr__(self) -> str:
        return f"Polyline(n={len(self.points)}, length={self.length:.3f})"

    def __len__(self) -> int:
        return len(self.points)

    def _locate(self, s: npt.ArrayLike) -> tuple[IntArray, FloatArray]:
        """Segment index and distance into that segment for each ``s`` (clamped)."""
        sa = np.asarray(s, dtype=np.float64)
        if np.any(np.isnan(sa)):
            raise ValueError("polyline: arc length is NaN")
        sa = np.minimum(np.maximum(sa, 0.0), self.length)
        idx = np.searchsorted(self.cumlen, sa, side="right") - 1
        idx = np.minimum(np.maximum(idx, 0), len(self._seglen) - 1)
        return idx, sa - self.cumlen[idx]

    def points_at(self, s: npt.ArrayLike) -> FloatArray:
        """Positions at arc lengths ``s`` (shape (...,) -> (..., 2)), metres."""
        idx, ds = self._locate(s)
        out: FloatArray = self.points[idx] + self._unit[idx] * ds[..., None]
        return out

    def _locate1(self, s: float) -> tuple[int, float]:
        """Scalar :meth:`_locate` without numpy overhead."""
        s = float(s)
        if s != s:
            raise ValueError("polyline: arc length is NaN")
        s = min(max(s, 0.0), self.length)
        i = min(bisect_right(self._cum_list, s) - 1, len(self._head_list) - 1)
        return i, s - self._cum_list[i]

    def point_at(self, s: float) -> tuple[float, float]:
        """Position at arc length ``s``, metres."""
        i, ds = self._locate1(s)
        p, u = self._pt_list[i], self._unit_list[i]
        return p[0] + u[0] * ds, p[1] + u[1] * ds

    def headings_at(self, s: npt.ArrayLike) -> FloatArray:
        """Headings (radians) at arc lengths ``s``: the direction of the segment there."""
        idx, _ = self._locate(s)
        out: FloatArray = self._heading[idx]
        return out

    def heading_at(self, s: float) -> float:
        """Heading (radians) at arc length ``s``."""
        return self._head_list[self._locate1(s)[0]]

    def project_many(self, xy: Sequence[PointLike] | FloatArray) -> tuple[FloatArray, FloatArray]:
        """Closest-point projection of each row of ``xy`` (M, 2).

        Returns ``(s, lateral)``: arc length of the closest point on the polyline and
        the signed distance to it, positive to the left of the driving direction. For
        points beyond either end, ``lateral`` is the distance to the end point (so it
        grows with the overshoot), signed by the side of the end segment's line.
        """
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        a = self.points[:-1]
        if _KERNEL is not None:  # the same numbers, to the bit (services/model/_geometry.c)
            fast: tuple[FloatArray, FloatArray] | None = _KERNEL.project_many(
                a, self._unit, self._seglen, self.cumlen, p
            )
            if fast is not None:
                return fast
        rel = p[:, None, :] - a[None, :, :]  # (M, S, 2)
        t = np.einsum("msk,sk->ms", rel, self._unit)  # metres along each segment
        t = np.minimum(np.maximum(t, 0.0), self._seglen[None, :])
        diff = rel - t[..., None] * self._unit[None, :, :]
        dist2 = np.einsum("msk,msk->ms", diff, diff)
        i = np.argmin(dist2, axis=1)
        rows = np.arange(len(p))
        s = self.cumlen[i] + t[rows, i]
        u = self._unit[i]
        r = rel[rows, i]
        cross = u[:, 0] * r[:, 1] - u[:, 1] * r[:, 0]
        lateral = np.where(cross >= 0.0, 1.0, -1.0) * np.sqrt(dist2[rows, i])
        return s, lateral

    def project(self, x: float, y: float) -> tuple[float, float]:
        """``(s, lateral)`` of one point; see :meth:`project_many`."""
        s, lat = self.project_many(np.array([[x, y]], dtype=np.float64))
        return float(s[0]), float(lat[0])

    def intervals_in_polygon(
        self, poly: Sequence[PointLike] | FloatArray
    ) -> list[tuple[float, float]]:
        """All arc-length intervals where the polyline lies in the closed convex ``poly``.

        Touching the boundary in a single point does not count as entering. Adjacent
        pieces are merged, so a curve that crosses the polygon once yields one interval.
        """
        verts, normals = _prepare_convex(poly)
        a = self.points[:-1]
        num = np.einsum("sek,ek->se", a[:, None, :] - verts[None, :, :], normals)
        den = self._dir @ normals.T  # (S, E)
        t0, t1 = _clip_params(num, den, strict=False)
        keep = np.flatnonzero(t1 - t0 > _EPS)
        out: list[tuple[float, float]] = []
        for i in keep:
            lo = float(self.cumlen[i] + t0[i] * self._seglen[i])
            hi = float(self.cumlen[i] + t1[i] * self._seglen[i])
            if out and lo - out[-1][1] <= 1e-7:
                out[-1] = (out[-1][0], hi)
            else:
                out.append((lo, hi))
        return out

    def interval_in_polygon(
        self, poly: Sequence[PointLike] | FloatArray
    ) -> tuple[float, float] | None:
        """``(s_in, s_out)``: first entry into and last exit from a convex polygon, or None."""
        iv = self.intervals_in_polygon(poly)
        if not iv:
            return None
        return iv[0][0], iv[-1][1]

    def sample(self, s0: float, s1: float, step: float) -> FloatArray:
        """Evenly spaced points (K, 2) from ``s0`` to ``s1`` inclusive, at most ``step`` apart."""
        if not (math.isfinite(step) and step > 0.0):
            raise ValueError("polyline: sample step must be finite and > 0")
        n = max(2, math.ceil(abs(s1 - s0) / step) + 1)
        return self.points_at(np.linspace(s0, s1, n))

    def slice(self, s0: float, s1: float) -> Polyline:
        """The piece between arc lengths ``s0 < s1`` (clamped) as a new polyline."""
        s0 = max(0.0, min(s0, self.length))
        s1 = max(0.0, min(s1, self.length))
        if s1 - s0 <= 1e-9:
            raise ValueError("polyline: empty slice")
        inner = self.cumlen[(self.cumlen > s0 + 1e-9) & (self.cumlen < s1 - 1e-9)]
        return Polyline(self.points_at(np.concatenate(([s0], inner, [s1]))))


def vertex_curvature(line: Polyline) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Curvature of a polyline at its vertices: ``(s, kappa, before, after)``, all (N,).

    ``kappa`` [1/m] is the vertex's heading change divided by the shorter of its
    adjacent segments (at most ``KINK_SPAN_M``): for a circular arc sampled by equal
    chords (``fillet_polyline``) that is exactly 1/r inside the arc. ``before`` and
    ``after`` [m] are how far the curvature holds on either side of the vertex (that
    same span, so every chord of an arc is covered by its end vertices). End points
    have zero curvature. Cached per polyline (they are immutable).
    """
    return _vertex_curvature(line)


@functools.lru_cache(maxsize=256)
def _vertex_curvature(line: Polyline) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    n = len(line.points)
    seg = np.asarray(line._seglen, dtype=np.float64)
    head = np.asarray(line._heading, dtype=np.float64)
    kappa = np.zeros(n, dtype=np.float64)
    before = np.zeros(n, dtype=np.float64)
    after = np.zeros(n, dtype=np.float64)
    if n > 2:
        turn = np.abs((np.diff(head) + math.pi) % (2.0 * math.pi) - math.pi)
        span = np.minimum(np.minimum(seg[:-1], seg[1:]), KINK_SPAN_M)
        kappa[1:-1] = turn / span
        before[1:-1] = span
        after[1:-1] = span
    return (
        _readonly(line.cumlen.copy()),
        _readonly(kappa),
        _readonly(before),
        _readonly(after),
    )


def fillet_polyline(
    points: Sequence[PointLike] | FloatArray, radius_m: float, step_m: float = 0.5
) -> FloatArray:
    """Round every interior corner of a polyline with a circular arc of ``radius_m``.

    Used for turning routes and lanes written as a few corner points. The arc is
    sampled with chords of at most ``step_m``. Raises ValueError when a corner's arc
    does not fit between its neighbours or the polyline turns back on itself.
    """
    pts = _as_points(points, "polyline", 2)
    if not (math.isfinite(radius_m) and radius_m >= 0.0):
        raise ValueError("corner radius must be finite and >= 0")
    if radius_m == 0.0 or len(pts) == 2:
        return pts
    if not (math.isfinite(step_m) and step_m > 0.0):
        raise ValueError("arc step must be finite and > 0")
    d = np.diff(pts, axis=0)
    seglen = np.hypot(d[:, 0], d[:, 1])
    if np.any(seglen <= 1e-9):
        raise ValueError("polyline: zero-length segment")
    u = d / seglen[:, None]
    tangent = np.zeros(len(pts))
    turn = np.zeros(len(pts))
    for i in range(1, len(pts) - 1):
        c = float(np.clip(u[i - 1] @ u[i], -1.0, 1.0))
        theta = math.acos(c)
        if theta > math.pi - 1e-6:
            raise ValueError(f"polyline turns back on itself at point {i}")
        turn[i] = theta
        tangent[i] = radius_m * math.tan(theta / 2.0)
    for k in range(len(seglen)):
        if tangent[k] + tangent[k + 1] > seglen[k] + 1e-9:
            raise ValueError(
                f"corner radius {radius_m} m does not fit on the segment after point {k}"
            )
    out: list[FloatArray] = [pts[0]]
    for i in range(1, len(pts) - 1):
        if turn[i] < 1e-9:
            out.append(pts[i])
            continue
        u1, u2 = u[i - 1], u[i]
        p1 = pts[i] - u1 * tangent[i]
        left = (u1[0] * u2[1] - u1[1] * u2[0]) > 0.0
        n1 = np.array([-u1[1], u1[0]]) if left else np.array([u1[1], -u1[0]])
        centre = p1 + n1 * radius_m
        a0 = math.atan2(p1[1] - centre[1], p1[0] - centre[0])
        sweep = turn[i] if left else -turn[i]
        k = max(1, math.ceil(radius_m * turn[i] / step_m))
        for j in range(k + 1):
            ang = a0 + sweep * j / k
            out.append(centre + radius_m * np.array([math.cos(ang), math.sin(ang)]))
    out.append(pts[-1])
    arr = np.array(out, dtype=np.float64)
    # Drop points that coincide (arc ends meeting a vertex or each other).
    keep = np.ones(len(arr), dtype=bool)
    keep[1:] = np.hypot(*np.diff(arr, axis=0).T) > 1e-6
    return arr[keep]


# --------------------------------------------------------------------------- polygons


def polygon_area(poly: Sequence[PointLike] | FloatArray) -> float:
    """Signed area (m²): positive when the vertices run counter-clockwise."""
    p = np.asarray(poly, dtype=np.float64)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def is_convex(poly: Sequence[PointLike] | FloatArray) -> bool:
    """True for a simple convex polygon with >= 3 vertices and non-zero area.

    Collinear vertices are allowed; repeated vertices and self-crossing are not.
    """
    try:
        p = _as_points(poly, "polygon", 3)
    except ValueError:
        return False
    e = np.roll(p, -1, axis=0) - p
    if np.any(np.hypot(e[:, 0], e[:, 1]) <= 1e-9):
        return False
    en = np.roll(e, -1, axis=0)
    cross = e[:, 0] * en[:, 1] - e[:, 1] * en[:, 0]
    scale = float(np.max(np.abs(p))) + 1.0
    tol = 1e-9 * scale * scale
    if not (np.all(cross >= -tol) or np.all(cross <= tol)):
        return False
    if abs(polygon_area(p)) <= tol:
        return False
    # Same-sign turns can still wind twice (a pentagram): the turning must total 2*pi.
    ang = np.arctan2(cross, np.einsum("ij,ij->i", e, en))
    return abs(abs(float(ang.sum())) - 2.0 * math.pi) < 1e-6


def _prepare_convex(poly: Sequence[PointLike] | FloatArray) -> tuple[FloatArray, FloatArray]:
    """Counter-clockwise vertices (E, 2) and inward edge normals (E, 2) of a convex polygon."""
    p = _as_points(poly, "polygon", 3)
    area = polygon_area(p)
    if abs(area) <= 1e-12:
        raise ValueError("polygon: zero area")
    if area < 0.0:
        p = p[::-1].copy()
    e = np.roll(p, -1, axis=0) - p
    normals = np.stack((-e[:, 1], e[:, 0]), axis=1)
    return p, normals


def _clip_params(
    num: FloatArray, den: FloatArray, *, strict: bool
) -> tuple[FloatArray, FloatArray]:
    """Cyrus-Beck clipping of ``a + t*d, t in [0, 1]`` by half-planes ``num + t*den >= 0``.

    ``num``/``den`` are (..., E) over the polygon's edges; returns ``t0, t1`` (...) of the
    inside part (empty when ``t1 <= t0``). ``strict`` clips by the open interior.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = -num / den
    par_out = (den == 0.0) & ((num <= 0.0) if strict else (num < 0.0))
    lower = np.where(den > 0.0, ratio, -np.inf)
    lower = np.where(par_out, np.inf, lower)
    upper = np.where(den < 0.0, ratio, np.inf)
    t0 = np.maximum(lower.max(axis=-1), 0.0)
    t1 = np.minimum(upper.min(axis=-1), 1.0)
    return t0, t1


def polygon_contains(poly: Sequence[PointLike] | FloatArray, x: float, y: float) -> bool:
    """True when (x, y) lies in the closed convex polygon."""
    verts, normals = _prepare_convex(poly)
    side = np.einsum("ek,ek->e", np.array([x, y]) - verts, normals)
    scale = float(np.max(np.abs(verts))) + 1.0
    return bool(np.all(side >= -1e-12 * scale * scale))


@dataclass(frozen=True, slots=True)
class PolygonSet:
    """Convex polygons packed for fast occlusion tests.

    ``vertices`` and inward ``normals`` are (E, 2) over all polygons' edges, each
    polygon's edges contiguous and counter-clockwise; ``starts`` (K,) indexes each
    polygon's first edge. Build it once (the scenario does) and pass it wherever a
    sequence of polygons is accepted.
    """

    vertices: FloatArray
    normals: FloatArray
    starts: IntArray

    @classmethod
    def from_polygons(cls, polygons: Sequence[Sequence[PointLike] | FloatArray]) -> PolygonSet:
        verts: list[FloatArray] = []
        norms: list[FloatArray] = []
        starts: list[int] = []
        n = 0
        for poly in polygons:
            v, nn = _prepare_convex(poly)
            starts.append(n)
            verts.append(v)
            norms.append(nn)
            n += len(v)
        if not starts:
            empty = np.zeros((0, 2), dtype=np.float64)
            return cls(_readonly(empty), _readonly(empty.copy()), np.zeros(0, dtype=np.intp))
        st = np.array(starts, dtype=np.intp)
        st.flags.writeable = False
        return cls(_readonly(np.concatenate(verts)), _readonly(np.concatenate(norms)), st)

    def __len__(self) -> int:
        return len(self.starts)


Polygons = Sequence[FloatArray] | PolygonSet


_PACKED: dict[tuple[int, ...], tuple[tuple[FloatArray, ...], PolygonSet]] = {}
_PACKED_MAX = 32


def _as_set(polygons: Polygons) -> PolygonSet:
    """Pack polygons; read-only arrays (the scenario's buildings) are packed once and
    remembered, keyed by identity (the entry keeps the arrays alive)."""
    if isinstance(polygons, PolygonSet):
        return polygons
    polys = tuple(polygons)
    cacheable = all(isinstance(p, np.ndarray) and not p.flags.writeable for p in polys)
    if not cacheable:
        return PolygonSet.from_polygons(polys)
    key = tuple(id(p) for p in polys)
    hit = _PACKED.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], polys, strict=True)):
        return hit[1]
    packed = PolygonSet.from_polygons(polys)
    if len(_PACKED) >= _PACKED_MAX:
        _PACKED.pop(next(iter(_PACKED)))
    _PACKED[key] = (polys, packed)
    return packed


def visible_mask(
    p: PointLike, targets: Sequence[PointLike] | FloatArray, polygons: Polygons
) -> BoolArray:
    """Line of sight from ``p`` to each target (M, 2): True when the segment p->target
    crosses the interior of no polygon.

    Grazing a polygon's edge or vertex does not block. Vectorised over targets and
    over all polygon edges at once; pass a :class:`PolygonSet` to skip re-packing.
    """
    tg = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    ps = _as_set(polygons)
    if len(ps) == 0 or len(tg) == 0:
        return np.ones(len(tg), dtype=np.bool_)
    origin = np.array(p, dtype=np.float64)
    num = (origin[None, :] - ps.vertices) * ps.normals
    num_e = num[:, 0] + num[:, 1]  # (E,)
    den = (tg - origin) @ ps.normals.T  # (M, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = -num_e[None, :] / den
    par_out = (den == 0.0) & (num_e[None, :] <= 0.0)
    lower = np.where(den > 0.0, ratio, -np.inf)
    lower = np.where(par_out, np.inf, lower)
    upper = np.where(den < 0.0, ratio, np.inf)
    t0 = np.maximum(np.maximum.reduceat(lower, ps.starts, axis=1), 0.0)
    t1 = np.minimum(np.minimum.reduceat(upper, ps.starts, axis=1), 1.0)
    blocked = np.any(t1 - t0 > _EPS, axis=1)
    out: BoolArray = ~blocked
    return out


def segment_blocked(p: PointLike, q: PointLike, polygons: Polygons) -> bool:
    """True when the segment p->q crosses the interior of any polygon (occlusion)."""
    return not bool(visible_mask(p, np.array([q], dtype=np.float64), polygons)[0])


# --------------------------------------------------------------------------- footprints


def footprint(x: float, y: float, heading: float, length: float, width: float) -> FloatArray:
    """Corners (4, 2) of a car's rectangle centred on (x, y), counter-clockwise:
    front-left, rear-left, rear-right, front-right. (x, y) is the geometric centre."""
    c, s = math.cos(heading), math.sin(heading)
    hl, hw = 0.5 * length, 0.5 * width
    fx, fy = c * hl, s * hl
    lx, ly = -s * hw, c * hw
    return np.array(
        [
            [x + fx + lx, y + fy + ly],
            [x - fx + lx, y - fy + ly],
            [x - fx - lx, y - fy - ly],
            [x + fx - lx, y + fy - ly],
        ],
        dtype=np.float64,
    )


def footprints(
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    heading: npt.ArrayLike,
    length: npt.ArrayLike,
    width: npt.ArrayLike,
) -> FloatArray:
    """Vectorised :func:`footprint`: arrays (M,) -> corners (M, 4, 2)."""
    xa = np.asarray(x, dtype=np.float64).reshape(-1)
    ya = np.asarray(y, dtype=np.float64).reshape(-1)
    h = np.asarray(heading, dtype=np.float64).reshape(-1)
    hl = 0.5 * np.broadcast_to(np.asarray(length, dtype=np.float64), xa.shape)
    hw = 0.5 * np.broadcast_to(np.asarray(width, dtype=np.float64), xa.shape)
    c, s = np.cos(h), np.sin(h)
    f = np.stack((c * hl, s * hl), axis=1)[:, None, :]
    left = np.stack((-s * hw, c * hw), axis=1)[:, None, :]
    sign_f = np.array([1.0, -1.0, -1.0, 1.0])[None, :, None]
    sign_l = np.array([1.0, 1.0, -1.0, -1.0])[None, :, None]
    centre = np.stack((xa, ya), axis=1)[:, None, :]
    out: FloatArray = centre + sign_f * f + sign_l * left
    return out


def min_point_distance(a: FloatArray, b: FloatArray) -> float:
    """Smallest distance (m) between any point of ``a`` (M, 2) and any of ``b`` (K, 2)."""
    diff = a[:, None, :] - b[None, :, :]
    return float(np.sqrt(np.min(np.einsum("mkc,mkc->mk", diff, diff))))


def _edge_axes(p: FloatArray) -> FloatArray:
    e = np.roll(p, -1, axis=0) - p
    return np.stack((-e[:, 1], e[:, 0]), axis=1)


def convex_overlap(a: FloatArray, b: FloatArray) -> bool:
    """Separating-axis test for two convex polygons (touching counts as overlap)."""
    axes = np.concatenate((_edge_axes(a), _edge_axes(b)))
    pa = a @ axes.T
    pb = b @ axes.T
    lo = np.maximum(pa.min(axis=0), pb.min(axis=0))
    hi = np.minimum(pa.max(axis=0), pb.max(axis=0))
    return bool(np.all(lo <= hi))


def _point_segment_dist(pts: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distances (M, S) from points (M, 2) to segments a->b (S, 2)."""
    d = b - a
    dd = np.einsum("sk,sk->s", d, d)
    rel = pts[:, None, :] - a[None, :, :]
    t = np.minimum(np.maximum(np.einsum("msk,sk->ms", rel, d) / dd[None, :], 0.0), 1.0)
    diff = rel - t[..., None] * d[None, :, :]
    out: FloatArray = np.sqrt(np.einsum("msk,msk->ms", diff, diff))
    return out


def convex_distance(a: FloatArray, b: FloatArray) -> float:
    """Minimum distance (m) between two convex polygons; 0 when they overlap."""
    if convex_overlap(a, b):
        return 0.0
    a2 = np.roll(a, -1, axis=0)
    b2 = np.roll(b, -1, axis=0)
    return float(min(_point_segment_dist(a, b, b2).min(), _point_segment_dist(b, a, a2).min()))


_NEXT4 = np.array([1, 2, 3, 0], dtype=np.intp)


def _quads_separated(a: FloatArray, b: FloatArray) -> BoolArray:
    """Separating-axis test over pairs of convex quads (P, 4, 2) -> (P,) True if apart."""
    ea = a[:, _NEXT4] - a
    eb = b[:, _NEXT4] - b
    e = np.concatenate((ea, eb), axis=1)  # (P, 8, 2)
    axes = np.stack((-e[..., 1], e[..., 0]), axis=-1)
    pa = np.einsum("pik,pjk->pij", a, axes)  # (P, 4, 8)
    pb = np.einsum("pik,pjk->pij", b, axes)
    lo = np.maximum(pa.min(axis=1), pb.min(axis=1))
    hi = np.minimum(pa.max(axis=1), pb.max(axis=1))
    out: BoolArray = np.any(lo > hi, axis=1)
    return out


def _quad_vertex_edge_dist(p: FloatArray, q: FloatArray) -> FloatArray:
    """Per pair, the smallest distance from a vertex of ``p`` to an edge of ``q`` (P,)."""
    a = q
    d = q[:, _NEXT4] - q  # (P, 4, 2) edges
    dd = np.einsum("pek,pek->pe", d, d)
    rel = p[:, :, None, :] - a[:, None, :, :]  # (P, 4 vertices, 4 edges, 2)
    t = np.minimum(np.maximum(np.einsum("pvek,pek->pve", rel, d) / dd[:, None, :], 0.0), 1.0)
    diff = rel - t[..., None] * d[:, None, :, :]
    out: FloatArray = np.sqrt(np.einsum("pvek,pvek->pve", diff, diff).min(axis=(1, 2)))
    return out


def rect_distances(a: FloatArray, b: FloatArray) -> FloatArray:
    """Vectorised :func:`rect_distance` over pairs of footprints (P, 4, 2) -> (P,), m."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4, 2)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4, 2)
    if len(a) == 0:
        return np.zeros(0, dtype=np.float64)
    dist = np.minimum(_quad_vertex_edge_dist(a, b), _quad_vertex_edge_dist(b, a))
    out: FloatArray = np.where(_quads_separated(a, b), dist, 0.0)
    return out


def rects_overlap(a: FloatArray, b: FloatArray) -> bool:
    """Do two car footprints (4, 2) overlap? Separating axis theorem (touching overlaps)."""
    return not bool(_quads_separated(a[None], b[None])[0])


def any_rects_overlap(a: FloatArray, b: FloatArray) -> bool:
    """Does any footprint of ``a`` (M, 4, 2) overlap any of ``b`` (K, 4, 2)? All M x K
    pairs by the separating axis theorem, vectorised (touching overlaps)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4, 2)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4, 2)
    if len(a) == 0 or len(b) == 0:
        return False
    if _KERNEL is not None:  # pair by pair, the first overlap answers; the same tests
        fast: bool | None = _KERNEL.any_quads_overlap(a, b)
        if fast is not None:
            return fast
    m, k = len(a), len(b)
    pa = np.repeat(a, k, axis=0)
    pb = np.tile(b, (m, 1, 1))
    return not bool(np.all(_quads_separated(pa, pb)))


def rect_distance(a: FloatArray, b: FloatArray) -> float:
    """Minimum distance (m) between two footprints (4, 2); 0 when they overlap."""
    return float(rect_distances(a[None], b[None])[0])
