"""The reservation table: every car's latest future path, indexed in space and time.

Two paths conflict (paper §IV-C) when a point of each lies within the pair's
margin [m] of the other (Euclidean, car centres, ``<=``) and their pass times
differ by less than ``headway`` [s] (``<``), counting only points with
``now <= t <= now + horizon``.

Pair margin (ours; the paper's cars were all alike): the paper's ``d_margin``
(2.8 m) is meant for two standard 4.5 m x 1.8 m cars. A larger body reaches
further from its centre, so each car adds its *growth*, how much further its
body can reach from its centre than a standard car's can: half its diagonal
minus the standard car's (a circle bound, direction-free)::

    margin = d_margin + g(L1, W1) + g(L2, W2)
    g(L, W) = max(0, hypot(L', W') / 2 - hypot(4.5, 1.8) / 2),
    L' = min(L, MAX_BODY_LENGTH_M), W' = min(W, MAX_BODY_WIDTH_M)

(0 for a standard or smaller car, 3.71 m for a 12 m x 2.5 m bus, so a bus and
a car conflict within 6.51 m of centre distance). The growth is capped at the
largest plausible road vehicle (25 m x 3 m, 10.17 m): the wire allows 50 m x
10 m, and a hostile "car" declaring that must not make every neighbourhood
search huge; the RSU core counts such paths (``oversize``) and plans them with
the cap.

Index: a uniform grid over (x, y, t) with cells of ``d_margin`` x ``d_margin``
x ``headway`` (a hair larger, so that float rounding can never push a
conflicting pair two cells apart). Each cell key maps to the set of cars with
a point in it, a car with a growth ``g`` being entered in every cell within
``ceil(g / cell)`` cells in x and y of its points too; a query looks up the
neighbourhood of each of its own cells that its own reach (``d_margin`` plus
its growth plus any margin) spans, 3x3x3 for a standard car, which is then
guaranteed to contain every point it can conflict with, and checks only those
cars exactly, all pairs vectorised. A standard car's query stays 3x3x3 while a
bus is in the table. Cell coordinates wrap modulo 2**21 per axis when packed
into one integer key; a wrap only adds candidates (the exact check removes
them), it never loses a conflict.

Same-lane followers (ours, issue 12): ``d_margin`` is a crossing margin; two 4.5 m
cars one behind the other in a lane overlap long before their centres are 2.8 m
apart. So a pair of points also conflicts when:

* their paths head the same way there (within :data:`SAME_WAY_RAD`; a path that
  never moves has no heading and is in the way of any moving path; two that never
  move cannot run into each other),
* they are in one lane: less than half the two widths plus :data:`LANE_SLACK_M`
  apart sideways (two cars side by side in adjacent lanes are not),
* their centres are within the *follow distance* ``(L1 + L2) / 2 + follow_gap_m``
  (lengths capped as above; default gap 1.0 m: 5.5 m for two standard cars),
* and their times differ by less than ``follow_window_s`` (default 0.3 s: more than
  half the 0.5 s spacing of the points holding a stop, so no stop is missed).

That is "a follower is never less than a body length and a metre behind the car
ahead at the same moment"; the crossing rule still applies to the pair too. A query's
``margin_s`` widens the follow window, its ``margin_m`` does not widen the follow
distance: a car queued behind another (1.5 m gap, below) would never be clear by it. A car's
own planner keeps a 1.5 m gap to a car it senses ahead (``emergency_gap_m``), so a
standing queue is no conflict.

``naive_conflicts`` is the brute-force all-pairs reference (tests, benchmark).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol.codec import MAX_COORD_M, MAX_TIME_US
from services.model.scenario import DEFAULT_LENGTH_M, DEFAULT_WIDTH_M

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_AXIS_BITS = 21
_MASK = (1 << _AXIS_BITS) - 1
_CELL_SLACK = 1.0 + 1e-9
_REACH_SLACK = 1.0 + 1e-6  # on growths and margins: far more than float rounding

STANDARD_SHAPE = (DEFAULT_LENGTH_M, DEFAULT_WIDTH_M)
"""The car ``d_margin`` is meant for: length, width [m]."""
MAX_BODY_LENGTH_M = 25.0
"""Longest body the margin grows for [m]: the longest road vehicles allowed in Europe
(25.25 m combinations); a longer declared length is planned as this one."""
MAX_BODY_WIDTH_M = 3.0
"""Widest body the margin grows for [m] (legal road vehicles are at most 2.6 m)."""
_STANDARD_HALF_DIAGONAL = 0.5 * math.hypot(*STANDARD_SHAPE)
SAME_WAY_RAD = math.radians(35.0)
"""Two points whose paths head within this of each other there are in the same lane
(a follower and the car ahead, or a merge) [rad]."""
_SAME_WAY_COS = math.cos(SAME_WAY_RAD)
FOLLOW_GAP_M = 1.0
"""Default bumper-to-bumper gap a follower keeps to the car ahead at the same moment [m]."""
LANE_SLACK_M = 0.5
"""Same-way points more than half the two widths plus this apart sideways are in
adjacent lanes, not one behind the other [m]."""
FOLLOW_WINDOW_S = 0.3
"""Default time window of the follow rule [s] (see the module docstring)."""
_MAX_T_S = MAX_TIME_US / 1e6  # largest |t| [s]: the wire's bound on generation times
_OUT_OF_BOUNDS = (
    f"path points must be finite, |x| and |y| <= {MAX_COORD_M:g} m, |t| <= {_MAX_T_S:g} s"
)


def within_wire_bounds(points: FloatArray) -> bool:
    """True when the (N, 3) x, y, t ``points`` are finite and within what the wire can
    carry: |x|, |y| <= ``protocol.codec.MAX_COORD_M`` [m], |t| <= ``MAX_TIME_US`` [s]."""
    if not np.all(np.isfinite(points)):
        return False
    if not points.size:
        return True
    return bool(
        float(np.abs(points[:, :2]).max()) <= MAX_COORD_M
        and float(np.abs(points[:, 2]).max()) <= _MAX_T_S
    )


def _offsets(rxy: int, rt: int) -> IntArray:
    """Cell offsets of the (2 rxy + 1)^2 x (2 rt + 1) neighbourhood."""
    span_xy, span_t = range(-rxy, rxy + 1), range(-rt, rt + 1)
    return np.array(
        [(dx, dy, dt) for dx in span_xy for dy in span_xy for dt in span_t], dtype=np.int64
    )


_OFFSETS = {(1, 1): _offsets(1, 1)}


def body_growth(length: float, width: float) -> float:
    """How much further [m] a ``length`` x ``width`` [m] body can reach from its centre than
    a standard car's (:data:`STANDARD_SHAPE`): half-diagonal difference, >= 0, the body
    capped at :data:`MAX_BODY_LENGTH_M` x :data:`MAX_BODY_WIDTH_M`."""
    if not (math.isfinite(length) and math.isfinite(width) and length >= 0 and width >= 0):
        raise ValueError(f"vehicle shape must be finite and >= 0, got {length!r} x {width!r}")
    half = 0.5 * math.hypot(min(length, MAX_BODY_LENGTH_M), min(width, MAX_BODY_WIDTH_M))
    return max(0.0, half - _STANDARD_HALF_DIAGONAL)


def oversize(length: float, width: float) -> bool:
    """The body is beyond what the margin grows for (:func:`body_growth` caps it)."""
    return length > MAX_BODY_LENGTH_M or width > MAX_BODY_WIDTH_M


def _plane_offsets(r: int) -> IntArray:
    """(dx, dy) cell offsets of the (2 r + 1)^2 square."""
    span = range(-r, r + 1)
    return np.array([(dx, dy) for dx in span for dy in span], dtype=np.int64)


@dataclass(frozen=True, slots=True)
class Conflict:
    """A conflict between the queried path and another car's entry.

    ``time`` is when the conflict starts: the earliest, over conflicting point
    pairs, of the later of the two pass times [s] (so "a conflict within
    horizon H" is ``time <= now + H``). ``self_time`` / ``other_time`` are the
    earliest pass times among the conflicting points of each path [s];
    ``x``, ``y`` the queried path's first (lowest index) conflicting point [m].
    """

    vehicle: str
    time: float
    self_time: float
    other_time: float
    x: float
    y: float


@dataclass(slots=True, eq=False)
class Entry:
    """One car's reservation: its path, shape, and when it was last refreshed."""

    vehicle: str
    points: FloatArray
    length: float
    width: float
    updated: float
    keys: IntArray
    by_time: FloatArray  # the points sorted by pass time (stable), for the exact check
    growth: float = 0.0  # body_growth(length, width) [m]
    heading_by_time: FloatArray | None = None  # path_headings, in by_time's order

    def expires_at(self, expiry_s: float) -> float:
        return self.updated + expiry_s


def path_headings(points: FloatArray) -> FloatArray:
    """Unit direction (N, 2) of travel at each point: of the segment leaving it, else of the
    last segment of positive length before it (a held stop); NaN for a path that never
    moves (it counts as heading every way in the follow rule)."""
    n = points.shape[0]
    out = np.full((n, 2), np.nan, dtype=np.float64)
    if n < 2:
        return out
    seg = np.diff(points[:, :2], axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    moving = length > 1e-6
    if not moving.any():
        return out
    unit = np.full_like(seg, np.nan)
    unit[moving] = seg[moving] / length[moving, None]
    # segment i leaves point i; carry the last moving segment forward (held stops), and
    # the first one back (a path that starts with a hold)
    idx = np.where(moving, np.arange(n - 1), -1)
    idx = np.maximum.accumulate(idx)
    first = int(np.flatnonzero(moving)[0])
    idx[idx < 0] = first
    out[:-1] = unit[idx]
    out[-1] = out[-2]
    return out


MAX_POINT_GAP_S = 0.5
"""Points of a stored or queried path are at most this far apart in time [s]: a longer
segment (a future path holds a stop with two points, 10 s apart) gets points in between,
so a pair of cars is never missed between two of them (issue 12: a stopped car's future
path was invisible to the follow window and the headway after its first second)."""


def densify(points: FloatArray, max_dt: float = MAX_POINT_GAP_S) -> FloatArray:
    """``points`` with linearly interpolated points added wherever two consecutive ones
    are more than ``max_dt`` [s] apart (the same array when none is)."""
    n = points.shape[0]
    if n < 2:
        return points
    dt = np.diff(points[:, 2])
    long = dt > max_dt
    if not long.any():
        return points
    pieces = np.where(long, np.ceil(dt / max_dt).astype(np.int64), 1)
    idx = np.repeat(np.arange(n - 1), pieces)
    starts = np.cumsum(pieces) - pieces
    frac = (np.arange(idx.shape[0]) - starts[idx]) / pieces[idx]
    a, b = points[idx], points[idx + 1]
    body = a + (b - a) * frac[:, None]
    out: FloatArray = np.vstack([body, points[-1:]])
    return out


def follow_distance(l1: float, l2: float, gap: float) -> float:
    """Centre distance [m] two cars of lengths ``l1``, ``l2`` keep one behind the other."""
    return 0.5 * (min(l1, MAX_BODY_LENGTH_M) + min(l2, MAX_BODY_LENGTH_M)) + gap


def _pack(ix: IntArray, iy: IntArray, it: IntArray) -> IntArray:
    key: IntArray = ((ix & _MASK) << (2 * _AXIS_BITS)) | ((iy & _MASK) << _AXIS_BITS) | (it & _MASK)
    return key


def _pair_conflict(
    vehicle: str,
    q: FloatArray,
    o: FloatArray,
    d2: float,
    headway: float,
    follow: tuple[FloatArray, FloatArray, float, float, float] | None = None,
) -> Conflict | None:
    """Exact check of two windowed point sets; the one predicate both queries share.

    ``o`` must be sorted by time: only pairs less than one headway apart are
    enumerated (``searchsorted``, the bounds widened by far more than float
    rounding so that no pair is dropped), then tested with the exact predicate
    ``dx² + dy² <= d2 and |dt| < headway``; with ``follow`` (the headings of ``q`` and
    ``o``, the squared follow distance, the follow window and the lateral reach), also
    ``same way, |lateral| <= lat, dx² + dy² <= f2 and |dt| < window`` (module docstring).
    """
    n_q, n_o = q.shape[0], o.shape[0]
    if n_q == 0 or n_o == 0:
        return None
    qt = q[:, 2]
    ot = o[:, 2]
    reach = headway + 1e-12 * (np.abs(qt) + headway)
    lo = np.searchsorted(ot, qt - reach, side="left")
    hi = np.searchsorted(ot, qt + reach, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return None
    qi = np.repeat(np.arange(n_q), counts)
    starts = np.cumsum(counts) - counts
    oj = lo[qi] + (np.arange(total) - starts[qi])
    dx = q[qi, 0] - o[oj, 0]
    dy = q[qi, 1] - o[oj, 1]
    dist2 = dx * dx + dy * dy
    gap_t = np.abs(q[qi, 2] - o[oj, 2])
    hit = (dist2 <= d2) & (gap_t < headway)
    if follow is not None:
        hq, ho, f2, window, lat = follow
        uq, uo = hq[qi], ho[oj]
        cos = uq[:, 0] * uo[:, 0] + uq[:, 1] * uo[:, 1]
        # a path that never moves (no heading) is in the way of one that does
        q_still, o_still = np.isnan(uq[:, 0]), np.isnan(uo[:, 0])
        same_way = (cos >= _SAME_WAY_COS) | (q_still ^ o_still)
        # lateral offset across the lane (the query's heading, else the other's)
        ux = np.where(np.isnan(uq[:, 0]), uo[:, 0], uq[:, 0])
        uy = np.where(np.isnan(uq[:, 1]), uo[:, 1], uq[:, 1])
        side = np.abs(ux * dy - uy * dx)
        in_lane = side <= lat
        hit |= same_way & in_lane & (dist2 <= f2) & (gap_t < window)
    if not hit.any():
        return None
    qi = qi[hit]
    oj = oj[hit]
    tq = q[qi, 2]
    to = o[oj, 2]
    first = int(qi.min())
    return Conflict(
        vehicle=vehicle,
        time=float(np.maximum(tq, to).min()),
        self_time=float(tq.min()),
        other_time=float(to.min()),
        x=float(q[first, 0]),
        y=float(q[first, 1]),
    )


class ReservationTable:
    """Latest path per car, expiring ``expiry_s`` after its last refresh; space-time indexed."""

    def __init__(
        self,
        d_margin_m: float = 2.8,
        headway_s: float = 1.0,
        expiry_s: float = 0.5,
        follow_gap_m: float = FOLLOW_GAP_M,
        follow_window_s: float = FOLLOW_WINDOW_S,
    ):
        if not (math.isfinite(follow_gap_m) and follow_gap_m >= 0.0):
            raise ValueError(f"follow_gap_m must be finite and >= 0, got {follow_gap_m!r}")
        if not (math.isfinite(follow_window_s) and 0.0 <= follow_window_s <= headway_s):
            raise ValueError(f"follow_window_s must be in [0, headway_s], got {follow_window_s!r}")
        self.follow_gap_m = float(follow_gap_m)
        self.follow_window_s = float(follow_window_s)
        for name, value in (("d_margin_m", d_margin_m), ("headway_s", headway_s)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not (math.isfinite(expiry_s) and expiry_s > 0.0):
            raise ValueError(f"expiry_s must be a positive finite number, got {expiry_s!r}")
        self.d_margin_m = float(d_margin_m)
        self.headway_s = float(headway_s)
        self.expiry_s = float(expiry_s)
        self._d2 = self.d_margin_m * self.d_margin_m
        self._cell_xy = self.d_margin_m * _CELL_SLACK
        self._cell_t = self.headway_s * _CELL_SLACK
        self._entries: dict[str, Entry] = {}
        self._index: dict[int, set[str]] = {}

    # -- contents -------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, vehicle: object) -> bool:
        return vehicle in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def get(self, vehicle: str) -> Entry | None:
        return self._entries.get(vehicle)

    def is_live(self, vehicle: str, now: float) -> bool:
        entry = self._entries.get(vehicle)
        return entry is not None and now < entry.updated + self.expiry_s

    def next_expiry(self) -> float:
        """When the next entry expires [s]; ``inf`` for an empty table."""
        if not self._entries:
            return math.inf
        return min(e.updated for e in self._entries.values()) + self.expiry_s

    # -- updates --------------------------------------------------------------------------

    def _cells(self, points: FloatArray) -> tuple[IntArray, IntArray, IntArray]:
        ix = np.floor(points[:, 0] / self._cell_xy).astype(np.int64)
        iy = np.floor(points[:, 1] / self._cell_xy).astype(np.int64)
        it = np.floor(points[:, 2] / self._cell_t).astype(np.int64)
        return ix, iy, it

    def update(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        shape: tuple[float, float] = (4.5, 1.8),
    ) -> None:
        """Store ``points`` (N, 3) as the car's reservation, refreshed at ``now``.

        Raises ValueError (and changes nothing) for a wrong shape or non-finite
        or absurdly large values.
        """
        pts = np.array(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"a path is an (N, 3) array of x, y, t; got shape {pts.shape}")
        if not within_wire_bounds(pts):
            raise ValueError(_OUT_OF_BOUNDS)
        if not math.isfinite(now):
            raise ValueError("now must be finite")
        length, width = float(shape[0]), float(shape[1])
        growth = body_growth(length, width)
        pts.flags.writeable = False
        # indexed and checked densified (MAX_POINT_GAP_S); the entry keeps the path as sent
        dense = densify(pts) if bool(np.all(np.diff(pts[:, 2]) >= 0.0)) else pts
        ix, iy, it = self._cells(dense)
        k = self._cells_for(growth)
        if k and dense.shape[0]:
            # entered in every cell its grown body reaches too (see the module docstring)
            plane = _plane_offsets(k)
            keys: IntArray = np.unique(
                _pack(ix[:, None] + plane[None, :, 0], iy[:, None] + plane[None, :, 1], it[:, None])
            )
        else:
            keys = np.unique(_pack(ix, iy, it))
        self._unindex(vehicle)
        index = self._index
        for key in keys.tolist():
            cell = index.get(key)
            if cell is None:
                index[key] = {vehicle}
            else:
                cell.add(vehicle)
        order = np.argsort(dense[:, 2], kind="stable")
        by_time = dense[order] if dense.shape[0] else dense
        headings = path_headings(dense)[order] if dense.shape[0] else np.empty((0, 2))
        self._entries[vehicle] = Entry(
            vehicle, pts, length, width, float(now), keys, by_time, growth, headings
        )

    def touch(self, vehicle: str, now: float) -> bool:
        """Refresh a car's entry without changing its path (the car is alive)."""
        entry = self._entries.get(vehicle)
        if entry is None:
            return False
        entry.updated = max(entry.updated, float(now))
        return True

    def _unindex(self, vehicle: str) -> None:
        entry = self._entries.get(vehicle)
        if entry is None:
            return
        index = self._index
        for key in entry.keys.tolist():
            cell = index.get(key)
            if cell is not None:
                cell.discard(vehicle)
                if not cell:
                    del index[key]

    def remove(self, vehicle: str) -> bool:
        """Drop a car's entry; False if it had none."""
        if vehicle not in self._entries:
            return False
        self._unindex(vehicle)
        del self._entries[vehicle]
        return True

    def expire(self, now: float) -> list[str]:
        """Drop every entry not refreshed for ``expiry_s``; return their cars."""
        gone = [v for v, e in self._entries.items() if now >= e.updated + self.expiry_s]
        for vehicle in gone:
            self.remove(vehicle)
        return gone

    # -- queries --------------------------------------------------------------------------

    def _cells_for(self, reach: float) -> int:
        """Cells a ``reach`` [m] >= 0 beyond a cell's own spans (0 for none), with slack."""
        return math.ceil(reach * _REACH_SLACK / self._cell_xy) if reach > 0.0 else 0

    def _limits(self, margin_m: float, margin_s: float) -> tuple[float, float]:
        """The querying car's own reach [m] (``d_margin`` + its growth + ``margin_m``;
        each other car adds its growth) and the headway [s]."""
        if not (0.0 <= margin_m < math.inf and 0.0 <= margin_s < math.inf):
            raise ValueError("margins must be finite and >= 0")
        return self.d_margin_m + margin_m, self.headway_s + margin_s

    def growth_of(self, vehicle: str, shape: tuple[float, float] | None) -> float:
        """The querying car's growth [m]: of ``shape``, else of its own entry's shape, else 0."""
        if shape is not None:
            return body_growth(float(shape[0]), float(shape[1]))
        entry = self._entries.get(vehicle)
        return 0.0 if entry is None else entry.growth

    def _window(self, points: FloatArray, now: float, horizon_s: float) -> FloatArray:
        t = points[:, 2]
        windowed: FloatArray = points[(t >= now) & (t <= now + horizon_s)]
        return windowed

    def _window_sorted(
        self, entry: Entry, now: float, horizon_s: float
    ) -> tuple[FloatArray, FloatArray]:
        t = entry.by_time[:, 2]
        lo = int(np.searchsorted(t, now, side="left"))
        hi = int(np.searchsorted(t, now + horizon_s, side="right"))
        headings = entry.heading_by_time
        if headings is None:
            headings = np.full((entry.by_time.shape[0], 2), np.nan)
        return entry.by_time[lo:hi], headings[lo:hi]

    @staticmethod
    def _densified(
        points: FloatArray, now: float, horizon_s: float
    ) -> tuple[FloatArray, BoolArray, FloatArray]:
        """A query path densified (:func:`densify`, when its times run forward), the mask
        of its points within ``[now, now + horizon_s]``, and those points."""
        if points.shape[0] >= 2 and bool(np.all(np.diff(points[:, 2]) >= 0.0)):
            points = densify(points)
        t = points[:, 2]
        inside = (t >= now) & (t <= now + horizon_s)
        return points, inside, points[inside]

    def _follow_reach(self, length: float) -> float:
        """How far beyond ``d_margin`` the follow rule reaches for a car this long [m]
        (against the longest body in the table), for the neighbourhood search."""
        longest = max((e.length for e in self._entries.values()), default=length)
        return max(0.0, follow_distance(length, longest, self.follow_gap_m) - self.d_margin_m)

    def _query_shape(self, vehicle: str, shape: tuple[float, float] | None) -> tuple[float, float]:
        if shape is not None:
            return float(shape[0]), float(shape[1])
        entry = self._entries.get(vehicle)
        return STANDARD_SHAPE if entry is None else (entry.length, entry.width)

    @staticmethod
    def _lane_reach(w1: float, w2: float) -> float:
        """Lateral offset [m] within which two same-way cars are in one lane: half their
        widths plus :data:`LANE_SLACK_M` (less than a lane's width, 3.5 m for two cars)."""
        return 0.5 * (min(w1, MAX_BODY_WIDTH_M) + min(w2, MAX_BODY_WIDTH_M)) + LANE_SLACK_M

    def _others(
        self, vehicle: str, now: float, exclude: Collection[str], candidates: Collection[str]
    ) -> list[Entry]:
        out = []
        for other in candidates:
            if other == vehicle or other in exclude:
                continue
            entry = self._entries[other]
            if now < entry.updated + self.expiry_s:
                out.append(entry)
        out.sort(key=lambda e: e.vehicle)
        return out

    def candidates(
        self,
        points: FloatArray,
        margin_m: float = 0.0,
        margin_s: float = 0.0,
        growth_m: float = 0.0,
    ) -> set[str]:
        """Cars with a point in the cell neighbourhood of any of ``points``.

        The neighbourhood is 3x3x3 cells without margins or growth (``growth_m``,
        the querying car's :func:`body_growth`); wider when they make the reach
        exceed one cell.
        """
        if points.shape[0] == 0 or not self._index:
            return set()
        rxy = max(1, 1 + self._cells_for(margin_m + growth_m))
        rt = max(1, math.ceil((self.headway_s + margin_s) / self._cell_t))
        offsets = _OFFSETS.get((rxy, rt))
        if offsets is None:
            offsets = _OFFSETS.setdefault((rxy, rt), _offsets(rxy, rt))
        ix, iy, it = self._cells(points)
        _, first = np.unique(_pack(ix, iy, it), return_index=True)
        ix, iy, it = ix[first], iy[first], it[first]
        keys = _pack(
            ix[:, None] + offsets[None, :, 0],
            iy[:, None] + offsets[None, :, 1],
            it[:, None] + offsets[None, :, 2],
        )
        found: set[str] = set()
        get = self._index.get
        for key in np.unique(keys).tolist():
            cell = get(key)
            if cell:
                found |= cell
        return found

    def conflicts(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        horizon_s: float,
        exclude: Collection[str] = (),
        margin_m: float = 0.0,
        margin_s: float = 0.0,
        shape: tuple[float, float] | None = None,
    ) -> list[Conflict]:
        """Conflicts of ``vehicle``'s ``points`` with every other live entry, sorted by time.

        ``margin_m`` / ``margin_s`` (>= 0) widen ``d_margin`` / ``headway`` for this
        query only: a conflict "by a margin" (used for hysteresis). ``shape`` is the
        querying car's length, width [m] (default: its entry's, else a standard car's).
        """
        found = list(
            self._scan(vehicle, points, now, horizon_s, exclude, margin_m, margin_s, (), shape)
        )
        found.sort(key=lambda c: (c.time, c.vehicle))
        return found

    def first_conflict(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        horizon_s: float,
        exclude: Collection[str] = (),
        prefer: Sequence[str] = (),
        shape: tuple[float, float] | None = None,
        margin_m: float = 0.0,
        margin_s: float = 0.0,
    ) -> Conflict | None:
        """Any one conflict (checking the cars in ``prefer`` first), or None: cheaper than all."""
        scan = self._scan(
            vehicle, points, now, horizon_s, exclude, margin_m, margin_s, prefer, shape
        )
        return next(scan, None)

    def _scan(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        horizon_s: float,
        exclude: Collection[str],
        margin_m: float,
        margin_s: float,
        prefer: Sequence[str],
        shape: tuple[float, float] | None,
    ) -> Iterator[Conflict]:
        # densified first: a long segment may have no original point in the window
        full, inside, q = self._densified(_checked(points), now, horizon_s)
        if q.shape[0] == 0:
            return
        hq = path_headings(full)[inside]
        growth = self.growth_of(vehicle, shape)
        length, width = self._query_shape(vehicle, shape)
        reach, headway = self._limits(margin_m + growth, margin_s)
        extra = max(margin_m + growth, margin_m + self._follow_reach(length))
        found = self.candidates(q, extra, margin_s, 0.0)
        others = self._others(vehicle, now, exclude, found)
        if prefer:
            rank = {v: i for i, v in enumerate(prefer)}
            others.sort(key=lambda e: rank.get(e.vehicle, len(rank)))
        for entry in others:
            o, ho = self._window_sorted(entry, now, horizon_s)
            d = reach + entry.growth
            f = follow_distance(length, entry.length, self.follow_gap_m)
            lat = self._lane_reach(width, entry.width)
            follow = (hq, ho, f * f, self.follow_window_s + margin_s, lat)
            conflict = _pair_conflict(entry.vehicle, q, o, d * d, headway, follow)
            if conflict is not None:
                yield conflict

    def naive_conflicts(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        horizon_s: float,
        exclude: Collection[str] = (),
        margin_m: float = 0.0,
        margin_s: float = 0.0,
        shape: tuple[float, float] | None = None,
    ) -> list[Conflict]:
        """Same answer as ``conflicts`` by brute force: every point pair of every entry."""
        full, inside, q = self._densified(_checked(points), now, horizon_s)
        hq = path_headings(full)[inside]
        length, width = self._query_shape(vehicle, shape)
        reach, headway = self._limits(margin_m + self.growth_of(vehicle, shape), margin_s)
        found = []
        for entry in self._others(vehicle, now, exclude, list(self._entries)):
            o, ho = self._window_sorted(entry, now, horizon_s)
            d = reach + entry.growth
            f = follow_distance(length, entry.length, self.follow_gap_m)
            lat = self._lane_reach(width, entry.width)
            follow = (hq, ho, f * f, self.follow_window_s + margin_s, lat)
            conflict = _pair_conflict(entry.vehicle, q, o, d * d, headway, follow)
            if conflict is not None:
                found.append(conflict)
        found.sort(key=lambda c: (c.time, c.vehicle))
        return found


def _checked(points: npt.ArrayLike) -> FloatArray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"a path is an (N, 3) array of x, y, t; got shape {pts.shape}")
    if not within_wire_bounds(pts):
        raise ValueError(_OUT_OF_BOUNDS)
    return pts
