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

Index (issue 14; a jam at one intersection makes nearly every car a candidate, so
the exact check is batched over all of them): each stored path, densified and sorted
by time, is cut into *blocks*, its points within one time cell of ``_BLOCK_CELLS``
headways (a hair longer, so float rounding cannot push a pair further apart in
cells), each with its bounding box in float32 rounded outwards; the blocks of all
cars sit in a few packed numpy arrays (about 0.2 KB per car; the path itself is the
message's own read-only array, not a copy). A query pairs its own blocks with the
live blocks within the time band by box distance, then each of its points with those
boxes, then each point with the block's points less than the band apart in time
(bisection), and checks those pairs exactly in one vectorised pass over all cars.
Two searches: the crossing rule (pair margin, headway) and the follow rule (follow
distance, follow window), each with its own radius and band. Every bound carries
slack far above float rounding: the search only ever adds pairs, the exact predicate
(the one of ``_pair_conflict``) decides, so the answer equals the brute force's.

The query in C (issue 14, profile-driven): at 200 cars at one intersection that numpy
search and check paid most of their time in the fancy indexing of 6 000-25 000 candidate
point pairs. ``services/rsu/_scan.c`` walks the same blocks, boxes and bounds in one pass
and checks each pair with the same arithmetic (no fused multiply-add), building no pair
list; it is built at install when there is a C compiler and used when built
(:func:`use_scan` switches it, :func:`scan_available` says whether it was built). The
numpy path stays the reference and the fallback: both give the same conflicts to the bit
(``tests/rsu/test_scan.py``).

Same-lane followers (ours, issue 12): ``d_margin`` is a crossing margin; two 4.5 m
cars one behind the other in a lane overlap long before their centres are 2.8 m
apart. So a pair of points also conflicts when:

* their paths head the same way there (within :data:`SAME_WAY_RAD`; a path that
  never moves has no heading and is in the way of any moving path; two that never
  move cannot run into each other),
* they are in one lane: less than half the two widths plus :data:`LANE_SLACK_M`
  apart sideways across either car's heading (two cars side by side in adjacent lanes
  are not; either, so that the rule does not depend on which car asks),
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
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol.codec import MAX_COORD_M, MAX_TIME_US
from services.model.scenario import DEFAULT_LENGTH_M, DEFAULT_WIDTH_M
from services.rsu import paths

try:  # the query in C (services/rsu/_scan.c), built at install when there is a compiler
    from services.rsu import _scan as _scan_module
except ImportError:  # pragma: no cover - without a C compiler
    _scan_module = None  # type: ignore[assignment]

_SCAN: Any = _scan_module
"""``services.rsu._scan`` when built and in use, else None (``use_scan``)."""

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_CELL_SLACK = 1.0 + 1e-9
_REACH_SLACK = 1.0 + 1e-6  # on growths and margins: far more than float rounding
_BLOCK_CELLS = 2
"""A stored path's points are grouped in blocks of this many headways (time cells)."""

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
MIN_HEADWAY_S = 1e-3
"""Smallest headway a table takes [s]: the wire's time resolution (path times are whole
milliseconds), and it keeps every time cell index far inside int64 (a headway of 1e-300
made the search's cell arithmetic overflow)."""
ENDS_ROUNDING = 2.0**-24
"""Relative rounding of :meth:`ReservationTable.path_ends` (float32: half an ulp)."""
_MAX_T_S = MAX_TIME_US / 1e6  # largest |t| [s]: the wire's bound on generation times
_OUT_OF_BOUNDS = (
    f"path points must be finite, |x| and |y| <= {MAX_COORD_M:g} m, |t| <= {_MAX_T_S:g} s"
)


def within_wire_bounds(points: FloatArray) -> bool:
    """True when the (N, 3) x, y, t ``points`` are finite and within what the wire can
    carry: |x|, |y| <= ``protocol.codec.MAX_COORD_M`` [m], |t| <= ``MAX_TIME_US`` [s]. In
    C when the kernel is built and in use (:func:`services.rsu.paths.use_kernel`)."""
    kernel = paths.kernel()
    if kernel is not None:
        fast: bool | None = kernel.within_bounds(points, MAX_COORD_M, _MAX_T_S)
        if fast is not None:
            return fast
    if not np.all(np.isfinite(points)):
        return False
    if not points.size:
        return True
    return bool(
        float(np.abs(points[:, :2]).max()) <= MAX_COORD_M
        and float(np.abs(points[:, 2]).max()) <= _MAX_T_S
    )


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
    """One car's reservation: its path (as sent), shape, and when it was last refreshed
    (a snapshot the table makes on request; the table keeps it in packed arrays)."""

    vehicle: str
    points: FloatArray
    length: float
    width: float
    updated: float
    growth: float = 0.0  # body_growth(length, width) [m]

    def expires_at(self, expiry_s: float) -> float:
        return self.updated + expiry_s


_EMPTY: FloatArray = np.empty((0, 3), dtype=np.float64)
_EMPTY.flags.writeable = False


def scan_available() -> bool:
    """Whether the query's C kernel was built (``services/rsu/_scan.c``)."""
    return _scan_module is not None


def use_scan(enabled: bool) -> bool:
    """Answer queries with the C kernel (when built) or on the numpy path; the previous
    setting. Both give the same conflicts: this exists to measure and test each."""
    global _SCAN
    previous = _SCAN is not None
    _SCAN = _scan_module if enabled else None
    return previous


def path_headings(points: FloatArray) -> FloatArray:
    """Unit direction (N, 2) of travel at each point: of the segment leaving it, else of the
    last segment of positive length before it (a held stop); NaN for a path that never
    moves (it counts as heading every way in the follow rule). In C when the kernel is
    built and in use (:func:`services.rsu.paths.use_kernel`)."""
    kernel = paths.kernel()
    if kernel is not None:
        fast: FloatArray | None = kernel.path_headings(points)
        if fast is not None:
            return fast
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
    kernel = paths.kernel()
    if kernel is not None and kernel.gap_over(points, max_dt) is False:
        return points  # the common case, without numpy's overhead (issue 14)
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


def _in_lane(
    hq: FloatArray, ho: FloatArray, dx: FloatArray, dy: FloatArray, lat: float | FloatArray
) -> BoolArray:
    """Pairs of points (headings ``hq``, ``ho`` (K, 2), NaN for a path that never moves;
    offsets ``dx``, ``dy`` (K,)) in one lane: less than ``lat`` [m] apart sideways across
    either car's heading. Either, so that the rule is the same whichever car asks: across
    the query's heading alone, a car standing before the zone saw a turning car cross
    0.8 m in front of its lane's line as in its lane, and the turning car did not see the
    standing one (``tests/rsu/test_invariant.py``, ``FOUND_BY_SEARCH``)."""
    side_q = np.abs(hq[:, 0] * dy - hq[:, 1] * dx)
    side_o = np.abs(ho[:, 0] * dy - ho[:, 1] * dx)
    out: BoolArray = (side_q <= lat) | (side_o <= lat)  # NaN (no heading) compares False
    return out


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
        in_lane = _in_lane(uq, uo, dx, dy, lat)
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


def _frozen(points: npt.ArrayLike) -> FloatArray:
    """``points`` as a read-only float64 array: the caller's own when it already is one
    (a message's: ``protocol.messages`` freezes them; shared, not copied), else a frozen
    copy. A read-only array is taken to be immutable."""
    if type(points) is np.ndarray and points.dtype == np.float64 and not points.flags.writeable:
        return points
    pts = np.array(points, dtype=np.float64)
    pts.flags.writeable = False
    return pts


def _outward32(lo: FloatArray, hi: FloatArray) -> tuple[npt.NDArray[np.float32], ...]:
    """``lo`` / ``hi`` bounds as float32, rounded outwards (never inside the float64 box)."""
    lo32 = lo.astype(np.float32)
    hi32 = hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return lo32, hi32


def _expand(counts: IntArray) -> tuple[IntArray, IntArray]:
    """For ``counts`` (K,) >= 0: (which of the K each of the ``sum(counts)`` items belongs to,
    its rank within it)."""
    total = int(counts.sum())
    owner = np.repeat(np.arange(counts.shape[0]), counts)
    starts = np.cumsum(counts) - counts
    rank: IntArray = np.arange(total) - starts[owner]
    return owner, rank


class ReservationTable:
    """Latest path per car, expiring ``expiry_s`` after its last refresh; space-time indexed.

    Storage (issue 14: about 0.3 KB per car besides the path itself): per car a slot in
    a few numpy columns (refresh time, length, width, growth, point count), its path
    (the caller's array when it is a read-only float64 one, e.g. a message's: shared,
    not copied), and its *blocks* (module docstring) in packed arrays shared by all
    cars. Queries: the module docstring. Headings of stored points are derived from the
    path when needed (stored only for paths with a stop, or out of time order).
    """

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
        if headway_s < MIN_HEADWAY_S:
            raise ValueError(f"headway_s must be at least {MIN_HEADWAY_S} s, got {headway_s!r}")
        if not (math.isfinite(expiry_s) and expiry_s > 0.0):
            raise ValueError(f"expiry_s must be a positive finite number, got {expiry_s!r}")
        self.d_margin_m = float(d_margin_m)
        self.headway_s = float(headway_s)
        self.expiry_s = float(expiry_s)
        self._d2 = self.d_margin_m * self.d_margin_m
        self._cell_xy = self.d_margin_m * _CELL_SLACK
        self._cell_t = self.headway_s * _CELL_SLACK
        self._block_t = self._cell_t * _BLOCK_CELLS
        # per car: a slot
        self._slot: dict[str, int] = {}
        self._names: list[str] = []
        self._free: list[int] = []
        self._orig: list[FloatArray] = []  # the path as sent
        self._dense: list[FloatArray] = []  # densified, sorted by pass time (stable)
        self._head: list[FloatArray | None] = []  # headings in _dense's order, when irregular
        self._entry: list[Entry | None] = []  # made on request (get)
        cap = 16
        self._used = np.zeros(cap, dtype=np.bool_)
        self._updated = np.full(cap, -np.inf)
        self._length = np.zeros(cap)
        self._width = np.zeros(cap)
        self._growth = np.zeros(cap)
        self._row0 = np.zeros(cap, dtype=np.int32)  # its blocks: rows row0 .. row0 + nrow
        self._nrow = np.zeros(cap, dtype=np.int32)
        self._npts = np.zeros(cap, dtype=np.int32)  # points in _dense
        self._has_head = np.zeros(cap, dtype=np.bool_)  # _head[s] is stored (not None)
        # first x, y and last x, y of the path as sent [m], as float32 (``path_ends``)
        self._ends = np.zeros((cap, 4), dtype=np.float32)
        # blocks of every car, packed (rows of a removed car: slot -1 until compacted)
        bcap = 64
        self._rows = 0
        self._dead = 0
        self._b_slot = np.full(bcap, -1, dtype=np.int32)
        self._b_k = np.zeros(bcap, dtype=np.int64)  # time cell
        self._b_start = np.zeros(bcap, dtype=np.int32)  # its first point (in _dense order)
        self._b_box = np.zeros((bcap, 4), dtype=np.float32)  # x0, x1, y0, y1 [m]

    # -- contents -------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._slot)

    def __contains__(self, vehicle: object) -> bool:
        return vehicle in self._slot

    def __iter__(self) -> Iterator[str]:
        return iter(self._slot)

    def get(self, vehicle: str) -> Entry | None:
        """The car's entry (the same object until its next update; ``touch`` refreshes it)."""
        s = self._slot.get(vehicle)
        if s is None:
            return None
        entry = self._entry[s]
        if entry is None:
            entry = Entry(
                vehicle,
                self._orig[s],
                float(self._length[s]),
                float(self._width[s]),
                float(self._updated[s]),
                float(self._growth[s]),
            )
            self._entry[s] = entry
        return entry

    def is_live(self, vehicle: str, now: float) -> bool:
        s = self._slot.get(vehicle)
        return s is not None and now < float(self._updated[s]) + self.expiry_s

    def next_expiry(self) -> float:
        """When the next entry expires [s]; ``inf`` for an empty table."""
        if not self._slot:
            return math.inf
        return float(self._updated[self._used].min()) + self.expiry_s

    # -- updates --------------------------------------------------------------------------

    def _cells(self, points: FloatArray) -> tuple[IntArray, IntArray, IntArray]:
        ix = np.floor(points[:, 0] / self._cell_xy).astype(np.int64)
        iy = np.floor(points[:, 1] / self._cell_xy).astype(np.int64)
        it = np.floor(points[:, 2] / self._cell_t).astype(np.int64)
        return ix, iy, it

    def _new_slot(self) -> int:
        if self._free:
            return self._free.pop()
        s = len(self._names)
        cap = self._used.shape[0]
        if s >= cap:
            grow = max(cap // 2, 16)
            self._used = np.concatenate([self._used, np.zeros(grow, dtype=np.bool_)])
            self._updated = np.concatenate([self._updated, np.full(grow, -np.inf)])
            self._length = np.concatenate([self._length, np.zeros(grow)])
            self._width = np.concatenate([self._width, np.zeros(grow)])
            self._growth = np.concatenate([self._growth, np.zeros(grow)])
            self._row0 = np.concatenate([self._row0, np.zeros(grow, dtype=np.int32)])
            self._nrow = np.concatenate([self._nrow, np.zeros(grow, dtype=np.int32)])
            self._npts = np.concatenate([self._npts, np.zeros(grow, dtype=np.int32)])
            self._has_head = np.concatenate([self._has_head, np.zeros(grow, dtype=np.bool_)])
            self._ends = np.concatenate([self._ends, np.zeros((grow, 4), dtype=np.float32)])
        self._names.append("")
        self._orig.append(_EMPTY)
        self._dense.append(_EMPTY)
        self._head.append(None)
        self._entry.append(None)
        return s

    def _drop_rows(self, s: int) -> None:
        n = int(self._nrow[s])
        if n:
            r0 = int(self._row0[s])
            self._b_slot[r0 : r0 + n] = -1
            self._dead += n
            self._nrow[s] = 0

    def _add_rows(self, s: int, dense: FloatArray) -> None:
        n_pts = dense.shape[0]
        if n_pts == 0:
            return
        k = np.floor(dense[:, 2] / self._block_t).astype(np.int64)
        starts = np.concatenate(([0], np.flatnonzero(np.diff(k)) + 1))
        n = starts.shape[0]
        if self._dead > 64 and self._dead > self._rows - self._dead:
            self._compact()
        if self._rows + n > self._b_slot.shape[0]:
            grow = max(self._b_slot.shape[0] // 4, n, 64)
            self._b_slot = np.concatenate([self._b_slot, np.full(grow, -1, dtype=np.int32)])
            self._b_k = np.concatenate([self._b_k, np.zeros(grow, dtype=np.int64)])
            self._b_start = np.concatenate([self._b_start, np.zeros(grow, dtype=np.int32)])
            self._b_box = np.concatenate([self._b_box, np.zeros((grow, 4), dtype=np.float32)])
        r0 = self._rows
        rows = slice(r0, r0 + n)
        self._b_slot[rows] = s
        self._b_k[rows] = k[starts]
        self._b_start[rows] = starts
        x0, x1 = _outward32(
            np.minimum.reduceat(dense[:, 0], starts), np.maximum.reduceat(dense[:, 0], starts)
        )
        y0, y1 = _outward32(
            np.minimum.reduceat(dense[:, 1], starts), np.maximum.reduceat(dense[:, 1], starts)
        )
        box = self._b_box[rows]
        box[:, 0], box[:, 1], box[:, 2], box[:, 3] = x0, x1, y0, y1
        self._row0[s] = r0
        self._nrow[s] = n
        self._rows += n

    def _stops(self, rows: IntArray) -> IntArray:
        """End (exclusive, in its car's points) of each block row: the next row's start
        when that is the same car's, else the car's point count."""
        slot = self._b_slot[rows]
        nxt = np.minimum(rows + 1, self._b_slot.shape[0] - 1)
        same = (rows + 1 < self._rows) & (self._b_slot[nxt] == slot)
        out: IntArray = np.where(same, self._b_start[nxt], self._npts[slot])
        return out

    def _compact(self) -> None:
        """Drop the rows of removed cars (each car's rows stay together, in order)."""
        keep = np.flatnonzero(self._b_slot[: self._rows] >= 0)
        n = keep.shape[0]
        for arr in (self._b_slot, self._b_k, self._b_start, self._b_box):
            arr[:n] = arr[keep]
        self._b_slot[n:] = -1
        self._rows = n
        self._dead = 0
        if n:
            slots, first = np.unique(self._b_slot[:n], return_index=True)
            self._row0[slots] = first

    def update(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        shape: tuple[float, float] = (4.5, 1.8),
    ) -> None:
        """Store ``points`` (N, 3) as the car's reservation, refreshed at ``now``.

        Raises ValueError (and changes nothing) for a wrong shape or non-finite
        or absurdly large values. A frozen float64 array (a decoded message's) is kept
        as is, not copied: it must not change afterwards (numpy refuses writes to it).
        """
        pts = _frozen(points)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"a path is an (N, 3) array of x, y, t; got shape {pts.shape}")
        if not within_wire_bounds(pts):
            raise ValueError(_OUT_OF_BOUNDS)
        if not math.isfinite(now):
            raise ValueError("now must be finite")
        length, width = float(shape[0]), float(shape[1])
        growth = body_growth(length, width)
        # indexed and checked densified (MAX_POINT_GAP_S); the entry keeps the path as sent
        in_order = bool(np.all(np.diff(pts[:, 2]) >= 0.0))
        dense = densify(pts) if in_order else pts
        head: FloatArray | None = None
        if in_order:
            n = dense.shape[0]
            if n >= 2:
                seg = np.diff(dense[:, :2], axis=0)
                regular = bool(np.all(np.hypot(seg[:, 0], seg[:, 1]) > 1e-6))
            else:
                regular = False
            if not regular:  # a held stop, or too short to head anywhere: stored
                head = path_headings(dense)
        else:
            order = np.argsort(dense[:, 2], kind="stable")
            head = path_headings(dense)[order]
            dense = dense[order]
        s = self._slot.get(vehicle)
        if s is None:
            s = self._new_slot()
            self._slot[vehicle] = s
        else:
            self._drop_rows(s)
        self._names[s] = vehicle
        self._orig[s] = pts
        self._dense[s] = dense
        self._head[s] = head
        self._has_head[s] = head is not None
        self._entry[s] = None
        self._used[s] = True
        self._updated[s] = float(now)
        self._length[s] = length
        self._width[s] = width
        self._growth[s] = growth
        self._npts[s] = dense.shape[0]
        if pts.shape[0]:
            self._ends[s, :2], self._ends[s, 2:] = pts[0, :2], pts[-1, :2]
        self._add_rows(s, dense)

    def touch(self, vehicle: str, now: float) -> bool:
        """Refresh a car's entry without changing its path (the car is alive)."""
        s = self._slot.get(vehicle)
        if s is None:
            return False
        self._updated[s] = max(float(self._updated[s]), float(now))
        entry = self._entry[s]
        if entry is not None:
            entry.updated = float(self._updated[s])
        return True

    def remove(self, vehicle: str) -> bool:
        """Drop a car's entry; False if it had none."""
        s = self._slot.pop(vehicle, None)
        if s is None:
            return False
        self._drop_rows(s)
        self._used[s] = False
        self._updated[s] = -np.inf
        self._orig[s] = self._dense[s] = _EMPTY
        self._head[s] = self._entry[s] = None
        self._has_head[s] = False
        self._names[s] = ""
        self._free.append(s)
        return True

    def expire(self, now: float) -> list[str]:
        """Drop every entry not refreshed for ``expiry_s``; return their cars."""
        old = self._used & (now >= self._updated + self.expiry_s)
        if not old.any():
            return []
        gone = [v for v, s in self._slot.items() if old[s]]
        for vehicle in gone:
            self.remove(vehicle)
        return gone

    # -- queries --------------------------------------------------------------------------

    def path_ends(
        self, vehicle: str, now: float, exclude: Collection[str] = ()
    ) -> tuple[list[str], FloatArray, FloatArray]:
        """Every live entry with a point, but ``vehicle``'s and those of ``exclude``: its
        car, the first and last points of its path (K, 4: x0, y0, x1, y1) [m] and its
        width [m], as arrays: the lane searches test them all at once (issue 14: a loop
        over the table was a third of an update at 200 cars). The points are kept as
        float32 (memory, issue 14): each coordinate within :data:`ENDS_ROUNDING` of its
        magnitude of the true one (1e-44 m near 0), which a prefilter must allow for."""
        cap = self._used.shape[0]
        slots = np.flatnonzero(self._live(vehicle, now, exclude)[:cap] & (self._npts > 0))
        names = self._names
        ends: FloatArray = self._ends[slots].astype(np.float64)
        return [names[s] for s in slots.tolist()], ends, self._width[slots]

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
        s = self._slot.get(vehicle)
        return 0.0 if s is None else float(self._growth[s])

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

    def _query_shape(self, vehicle: str, shape: tuple[float, float] | None) -> tuple[float, float]:
        if shape is not None:
            return float(shape[0]), float(shape[1])
        s = self._slot.get(vehicle)
        return STANDARD_SHAPE if s is None else (float(self._length[s]), float(self._width[s]))

    @staticmethod
    def _lane_reach(w1: float, w2: float) -> float:
        """Lateral offset [m] within which two same-way cars are in one lane: half their
        widths plus :data:`LANE_SLACK_M` (less than a lane's width, 3.5 m for two cars)."""
        return 0.5 * (min(w1, MAX_BODY_WIDTH_M) + min(w2, MAX_BODY_WIDTH_M)) + LANE_SLACK_M

    def _live(self, vehicle: str, now: float, exclude: Collection[str]) -> BoolArray:
        """Per slot, plus a last False for slot -1: a live entry of another, not excluded car."""
        cap = self._used.shape[0]
        live = np.zeros(cap + 1, dtype=np.bool_)
        live[:cap] = now < self._updated + self.expiry_s
        for v in (vehicle, *exclude):
            s = self._slot.get(v)
            if s is not None:
                live[s] = False
        return live

    def _near(
        self, q: FloatArray, live: BoolArray, rules: Sequence[tuple[FloatArray, float]]
    ) -> list[tuple[IntArray, IntArray]]:
        """Per rule (radius per slot [m], band [s]): pairs (index into ``q``, block row) of
        a query point and a live block that may hold a point less than the band from it
        in time and within the radius in space (a superset: the bounds carry slack far
        above float rounding). Blocks are first paired with the query's own blocks (its
        points by time cell) by box distance, for all rules at once, then with its points."""
        none = np.empty(0, dtype=np.int64)
        empty = [(none, none) for _ in rules]
        rows = self._rows
        if rows == 0 or q.shape[0] == 0:
            return empty
        sel = np.flatnonzero(live[self._b_slot[:rows]])
        if sel.shape[0] == 0:
            return empty
        cell = self._block_t
        radius_all = np.maximum.reduce([r for r, _ in rules])
        rt = max(1, math.ceil(max(band for _, band in rules) / cell))
        qk_all = np.floor(q[:, 2] / cell).astype(np.int64)
        qorder = np.argsort(qk_all, kind="stable")
        qk = qk_all[qorder]
        qstart = np.concatenate(([0], np.flatnonzero(np.diff(qk)) + 1))
        qstop = np.append(qstart[1:], qk.shape[0])
        uk = qk[qstart]
        qx, qy, qt = q[qorder, 0], q[qorder, 1], q[qorder, 2]
        qx0, qx1 = np.minimum.reduceat(qx, qstart), np.maximum.reduceat(qx, qstart)
        qy0, qy1 = np.minimum.reduceat(qy, qstart), np.maximum.reduceat(qy, qstart)
        # block pairs within rt time cells, by box distance
        bk = self._b_k[sel]
        lo = np.searchsorted(uk, bk - rt, side="left")
        hi = np.searchsorted(uk, bk + rt, side="right")
        which, rank = _expand(hi - lo)
        if which.shape[0] == 0:
            return empty
        rows_b = sel[which]
        jq = lo[which] + rank
        box = self._b_box[rows_b].astype(np.float64)
        r = radius_all[self._b_slot[rows_b]]
        gx = np.maximum(np.maximum(box[:, 0] - qx1[jq], qx0[jq] - box[:, 1]), 0.0)
        gy = np.maximum(np.maximum(box[:, 2] - qy1[jq], qy0[jq] - box[:, 3]), 0.0)
        ok = gx * gx + gy * gy <= r * r
        rows_b, jq, box = rows_b[ok], jq[ok], box[ok]
        if rows_b.shape[0] == 0:
            return empty
        # each point of the query block against the block's box and time cell
        which, rank = _expand(qstop[jq] - qstart[jq])
        pos = qstart[jq][which] + rank
        rows_b, box = rows_b[which], box[which]
        px, py, pt = qx[pos], qy[pos], qt[pos]
        gx = np.maximum(np.maximum(box[:, 0] - px, px - box[:, 1]), 0.0)
        gy = np.maximum(np.maximum(box[:, 2] - py, py - box[:, 3]), 0.0)
        g2 = gx * gx + gy * gy
        t0 = self._b_k[rows_b] * cell
        gt = np.maximum(np.maximum(t0 - pt, pt - (t0 + cell)), 0.0)
        slack = 1e-9 * (np.abs(pt) + cell)
        slot = self._b_slot[rows_b]
        out = []
        for radius, band in rules:
            r = radius[slot]
            ok = (g2 <= r * r) & (gt < band * _REACH_SLACK + slack)
            out.append((qorder[pos[ok]], rows_b[ok]))
        return out

    def candidates(
        self,
        points: FloatArray,
        margin_m: float = 0.0,
        margin_s: float = 0.0,
        growth_m: float = 0.0,
    ) -> set[str]:
        """Cars (live or not) with a block near enough to any of ``points`` to hold a
        point within ``d_margin`` (plus the margins and both growths) and the headway."""
        reach, headway = self._limits(margin_m + growth_m, margin_s)
        live = np.zeros(self._used.shape[0] + 1, dtype=np.bool_)
        live[:-1] = self._used
        radius = (reach + self._growth) * _REACH_SLACK + 1e-9
        ((_, rows),) = self._near(np.asarray(points, dtype=np.float64), live, [(radius, headway)])
        return {self._names[s] for s in np.unique(self._b_slot[rows]).tolist()}

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
        found = self._batch(vehicle, points, now, horizon_s, exclude, margin_m, margin_s, shape)
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
        """One conflict, or None: with the first car of ``prefer`` that has one, else with
        the first car by id."""
        found = self._batch(vehicle, points, now, horizon_s, exclude, margin_m, margin_s, shape)
        if not found:
            return None
        rank = {v: i for i, v in enumerate(prefer)}
        return min(found, key=lambda c: (rank.get(c.vehicle, len(rank)), c.vehicle))

    def _batch(
        self,
        vehicle: str,
        points: npt.ArrayLike,
        now: float,
        horizon_s: float,
        exclude: Collection[str],
        margin_m: float,
        margin_s: float,
        shape: tuple[float, float] | None,
    ) -> list[Conflict]:
        """Every conflict, all cars at once (class docstring), in no particular order."""
        # densified first: a long segment may have no original point in the window
        full, inside, q = self._densified(_checked(points), now, horizon_s)
        if q.shape[0] == 0 or self._rows == 0:
            return []
        growth = self.growth_of(vehicle, shape)
        length, width = self._query_shape(vehicle, shape)
        reach, headway = self._limits(margin_m + growth, margin_s)
        window = self.follow_window_s + margin_s
        # per slot: crossing margin, follow distance, lane reach (the pair's, as in the
        # per-pair check) and the larger of the first two as the search radius
        d_slot = reach + self._growth
        f_slot = (
            0.5 * (min(length, MAX_BODY_LENGTH_M) + np.minimum(self._length, MAX_BODY_LENGTH_M))
            + self.follow_gap_m
        )
        lat_slot = (
            0.5 * (min(width, MAX_BODY_WIDTH_M) + np.minimum(self._width, MAX_BODY_WIDTH_M))
            + LANE_SLACK_M
        )
        live = self._live(vehicle, now, exclude)
        # two searches: the crossing rule (d, headway) and the follow rule (f, window);
        # a pair that meets both may come twice, which changes no minimum below
        rules = [(d_slot * _REACH_SLACK + 1e-9, headway), (f_slot * _REACH_SLACK + 1e-9, window)]
        if _SCAN is not None:
            found = self._scan(
                _SCAN,
                (full, inside, q),
                (now, now + horizon_s),
                live,
                rules,
                (np.ascontiguousarray(d_slot), f_slot, lat_slot),
            )
            if found is not None:
                return found
        pairs = [
            (rule, qi, rows)
            for rule, (qi, rows) in enumerate(self._near(q, live, rules))
            if qi.shape[0]
        ]
        if not pairs:
            return []
        # the stored points of those blocks, packed: one array for every car involved
        mark = np.zeros(self._used.shape[0], dtype=np.bool_)
        for _, _, rows in pairs:
            mark[self._b_slot[rows]] = True
        slots = np.flatnonzero(mark)
        dense = self._dense
        arrays = [dense[s] for s in slots.tolist()]
        sizes = np.array([a.shape[0] for a in arrays], dtype=np.int64)
        offset = np.zeros(self._used.shape[0], dtype=np.int64)
        offset[slots] = np.cumsum(sizes) - sizes
        size = np.zeros(self._used.shape[0], dtype=np.int64)
        size[slots] = sizes
        packed = np.concatenate(arrays) if len(arrays) > 1 else arrays[0]
        # pass times made one ascending sequence (each car's shifted past the one before
        # by more than its span and the bands), to find within each block the points
        # less than a band from a query point by bisection; slack as in _pair_conflict
        pt = packed[:, 2]
        t_lo, t_hi = float(pt.min()), float(pt.max())
        span = (t_hi - t_lo) + 2.0 * headway + 1.0
        shift = np.zeros(self._used.shape[0])
        shift[slots] = np.arange(slots.shape[0]) * span - t_lo
        seq = pt + np.repeat(shift[slots], sizes)
        end = now + horizon_s
        found_q, found_o, found_owner = [], [], []
        for rule, qi, rows in pairs:
            slot_of_row = self._b_slot[rows].astype(np.int64)
            first = self._b_start[rows].astype(np.int64) + offset[slot_of_row]
            last = self._stops(rows) + offset[slot_of_row]
            band = headway if rule == 0 else window
            at = q[qi, 2] + shift[slot_of_row]
            reach = band + 1e-9 * (np.abs(at) + span)
            lo = np.maximum(np.searchsorted(seq, at - reach, side="left"), first)
            hi = np.minimum(np.searchsorted(seq, at + reach, side="right"), last)
            which, rank = _expand(np.maximum(hi - lo, 0))
            qi = qi[which]
            owner = slot_of_row[which]
            oj = lo[which] + rank
            o = packed[oj]
            qq = q[qi]
            dx = qq[:, 0] - o[:, 0]
            dy = qq[:, 1] - o[:, 1]
            dist2 = dx * dx + dy * dy
            ot = o[:, 2]
            gap_t = np.abs(qq[:, 2] - ot)
            inw = (ot >= now) & (ot <= end)
            # the exact predicate, as in _pair_conflict
            if rule == 0:
                d = d_slot[owner]
                hit = (dist2 <= d * d) & (gap_t < headway) & inw
            else:
                f = f_slot[owner]
                maybe = np.flatnonzero((dist2 <= f * f) & (gap_t < window) & inw)
                hq = path_headings(full)[inside][qi[maybe]]
                ho = self._headings(packed, oj[maybe], owner[maybe], offset, size)
                mdx, mdy = dx[maybe], dy[maybe]
                cos = hq[:, 0] * ho[:, 0] + hq[:, 1] * ho[:, 1]
                q_still, o_still = np.isnan(hq[:, 0]), np.isnan(ho[:, 0])
                same_way = (cos >= _SAME_WAY_COS) | (q_still ^ o_still)
                hit = np.zeros(qi.shape[0], dtype=np.bool_)
                hit[maybe] = same_way & _in_lane(hq, ho, mdx, mdy, lat_slot[owner[maybe]])
            found_q.append(qi[hit])
            found_o.append(oj[hit])
            found_owner.append(owner[hit])
        qi = np.concatenate(found_q)
        if qi.shape[0] == 0:
            return []
        owner = np.concatenate(found_owner)
        qt = q[qi, 2]
        ot = packed[np.concatenate(found_o), 2]
        order = np.argsort(owner, kind="stable")
        qi, owner, qt, ot = qi[order], owner[order], qt[order], ot[order]
        cut = np.concatenate(([0], np.flatnonzero(np.diff(owner)) + 1))
        time = np.minimum.reduceat(np.maximum(qt, ot), cut)
        self_time = np.minimum.reduceat(qt, cut)
        other_time = np.minimum.reduceat(ot, cut)
        first = np.minimum.reduceat(qi, cut)
        names = self._names
        return [
            Conflict(names[s], tm, st, ot_, float(q[i, 0]), float(q[i, 1]))
            for s, tm, st, ot_, i in zip(
                owner[cut].tolist(),
                time.tolist(),
                self_time.tolist(),
                other_time.tolist(),
                first.tolist(),
                strict=True,
            )
        ]

    def _scan(
        self,
        kernel: Any,
        query: tuple[FloatArray, BoolArray, FloatArray],
        window_s: tuple[float, float],
        live: BoolArray,
        rules: Sequence[tuple[FloatArray, float]],
        exact: tuple[FloatArray, FloatArray, FloatArray],
    ) -> list[Conflict] | None:
        """``_batch``'s answer from the C kernel (the same conflicts, in slot order), or
        None when the kernel refuses its arguments (the numpy path then answers).
        ``query``: the densified path, its window mask and the points in the window;
        ``window_s``: the window [s]; ``exact``: per slot the crossing margin, the follow
        distance and the lane reach [m]."""
        full, inside, q = query
        (rad_d, headway), (rad_f, window) = rules
        d_slot, f_slot, lat_slot = exact
        cap = self._used.shape[0]
        out_time = np.full(cap, np.inf)
        out_self = np.full(cap, np.inf)
        out_other = np.full(cap, np.inf)
        out_first = np.full(cap, -1, dtype=np.int64)
        params = (headway, window, *window_s, self._block_t, _SAME_WAY_COS, _REACH_SLACK)
        n = kernel.scan(
            np.ascontiguousarray(q),
            np.ascontiguousarray(path_headings(full)[inside]),
            self._dense,
            self._head,
            live,
            self._b_slot,
            self._b_k,
            self._b_start,
            self._b_box,
            self._rows,
            self._npts,
            d_slot,
            f_slot,
            lat_slot,
            rad_d,
            rad_f,
            params,
            out_time,
            out_self,
            out_other,
            out_first,
        )
        if n is None:
            return None
        hit = np.flatnonzero(out_first >= 0)
        first = out_first[hit]
        names = self._names
        return [
            Conflict(names[s], tm, st, ot, x, y)
            for s, tm, st, ot, x, y in zip(
                hit.tolist(),
                out_time[hit].tolist(),
                out_self[hit].tolist(),
                out_other[hit].tolist(),
                q[first, 0].tolist(),
                q[first, 1].tolist(),
                strict=True,
            )
        ]

    def _headings(
        self, packed: FloatArray, oj: IntArray, owner: IntArray, offset: IntArray, size: IntArray
    ) -> FloatArray:
        """Headings (K, 2) of the packed stored points ``oj`` (of slots ``owner``): as
        :func:`path_headings` gives them (the segment leaving the point, the last one's
        for the last point), stored for the irregular paths."""
        local = oj - offset[owner]
        out: FloatArray = np.full((oj.shape[0], 2), np.nan)
        if packed.shape[0] >= 2:
            # (a path of fewer than two points is irregular: its NaN headings are stored)
            seg = offset[owner] + np.minimum(local, size[owner] - 2)
            seg = np.clip(seg, 0, packed.shape[0] - 2)
            step = packed[seg + 1, :2] - packed[seg, :2]
            length = np.hypot(step[:, 0], step[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                out = step / length[:, None]
        head = self._head
        for s in np.unique(owner[self._has_head[owner]]).tolist():
            stored = head[s]
            if stored is not None:
                mine = owner == s
                out[mine] = stored[local[mine]]
        return out

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
        """Same answer as ``conflicts`` by brute force: every point pair of every entry
        (vectorised per entry, one :func:`_pair_conflict` call each; an entry's headings
        are derived from its path on the way, :func:`path_headings`)."""
        full, inside, q = self._densified(_checked(points), now, horizon_s)
        hq = path_headings(full)[inside]
        length, width = self._query_shape(vehicle, shape)
        reach, headway = self._limits(margin_m + self.growth_of(vehicle, shape), margin_s)
        live = self._live(vehicle, now, exclude)
        found = []
        for other in sorted(v for v, s in self._slot.items() if live[s]):
            s = self._slot[other]
            dense = self._dense[s]
            head = self._head[s]
            heads = path_headings(dense) if head is None else head
            t = dense[:, 2]
            lo = int(np.searchsorted(t, now, side="left"))
            hi = int(np.searchsorted(t, now + horizon_s, side="right"))
            o, ho = dense[lo:hi], heads[lo:hi]
            d = reach + float(self._growth[s])
            f = follow_distance(length, float(self._length[s]), self.follow_gap_m)
            lat = self._lane_reach(width, float(self._width[s]))
            follow = (hq, ho, f * f, self.follow_window_s + margin_s, lat)
            conflict = _pair_conflict(other, q, o, d * d, headway, follow)
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
