"""The reservation table's C query (``services/rsu/_scan.c``) against the numpy path it
replaces and the brute force.

The kernel must give the very conflicts of ``ReservationTable``'s numpy path (and so of
``naive_conflicts``), to the bit, or decline with None so that the numpy path answers; no
argument, however wrong, may make it read out of bounds. Without a C compiler it is not
built and the table runs on numpy: locally these tests then skip, on CI (``CI`` set) they
fail, since ``make test`` builds it.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.rsu import reservation
from services.rsu.reservation import STANDARD_SHAPE, ReservationTable
from tests.kernels import both_ways, require_kernel
from tests.rsu.test_reservation import D, H, _path, _shape

require_kernel(reservation.scan_available(), "services.rsu._scan")

from services.rsu import _scan  # noqa: E402 - after the check above


@pytest.fixture(autouse=True)
def _kernel_on() -> Iterator[None]:
    previous = reservation.use_scan(True)
    yield
    reservation.use_scan(previous)


def _both(table: ReservationTable, *args: Any, **kwargs: Any) -> tuple[list[Any], list[Any]]:
    """The table's answer with the kernel, then on its numpy path."""
    fast, slow = both_ways(reservation.use_scan, table.conflicts, *args, **kwargs)
    return fast, slow


def test_the_kernel_is_in_use_and_can_be_switched_off() -> None:
    assert reservation._SCAN is _scan
    assert reservation.use_scan(False) is True
    assert reservation._SCAN is None
    assert reservation.use_scan(True) is False
    assert reservation._SCAN is _scan


@settings(max_examples=300, deadline=None)
@given(
    others=st.lists(st.tuples(_path, _shape), min_size=0, max_size=8),
    query=_path,
    query_shape=_shape,
    now=st.sampled_from([0.0, 0.5, 1.0, 2.25]),
    horizon=st.sampled_from([1.0, 2.5, 5.0, 10.0]),
    margins=st.sampled_from([(0.0, 0.0), (0.6, 0.2), (D / 2, H / 2), (3.0, 1.5)]),
    removed=st.sets(st.integers(0, 7), max_size=3),
    excluded=st.sets(st.integers(0, 7), max_size=2),
)
def test_the_kernel_equals_the_numpy_path_and_the_brute_force(
    others: list[tuple[np.ndarray, tuple[float, float]]],
    query: np.ndarray,
    query_shape: tuple[float, float],
    now: float,
    horizon: float,
    margins: tuple[float, float],
    removed: set[int],
    excluded: set[int],
) -> None:
    """Random paths on lattices of half the margin and half the headway (pairs exactly at
    either bound), out of time order, holding stops, of any size; cars removed (dead
    block rows) and excluded."""
    table = ReservationTable(D, H, 0.5)
    for i, (pts, shape) in enumerate(others):
        table.update(f"v{i}", pts, now, shape)
    for i in removed:
        table.remove(f"v{i}")
    exclude = [f"v{i}" for i in excluded]
    args = ("q", query, now, horizon, exclude, *margins)
    fast, slow = _both(table, *args, shape=query_shape)
    assert fast == slow
    assert fast == table.naive_conflicts(*args, shape=query_shape)


def test_a_jam_gives_the_same_conflicts_on_both_paths() -> None:
    """The bench's jam at one intersection, 120 cars, some holding a stop (stored
    headings), every car queried: both paths agree, conflict for conflict."""
    from services.bench.rsu import _intersection_car

    rng = np.random.default_rng(11)
    table = ReservationTable(D, H, 0.5)
    paths = {}
    for k in range(120):
        pts = _intersection_car(rng, f"c{k}", 0.0, 1).points
        if k % 5 == 0:
            pts = np.vstack([pts[:50], [[pts[49, 0], pts[49, 1], 10.0]]])
        paths[f"c{k}"] = pts
        table.update(f"c{k}", pts, 0.0, (12.0, 2.5) if k % 13 == 0 else STANDARD_SHAPE)
    total = 0
    for v, pts in paths.items():
        fast, slow = _both(table, v, pts, 0.1, 10.0)
        assert fast == slow, v
        total += len(fast)
    assert total > 200  # a jam: plenty to compare


def test_the_table_falls_back_to_numpy_when_the_kernel_declines(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    class Declines:
        calls = 0

        def scan(self, *args: Any) -> None:
            Declines.calls += 1

    table = ReservationTable(D, H, 0.5)
    a = np.array([[-10.0, 0.0, 0.0], [10.0, 0.0, 2.0]])
    b = np.array([[0.0, -10.0, 0.0], [0.0, 10.0, 2.0]])
    table.update("A", a, 0.0)
    expected = table.naive_conflicts("B", b, 0.0, 10.0)
    assert len(expected) == 1
    monkeypatch.setattr(reservation, "_SCAN", Declines())
    assert table.conflicts("B", b, 0.0, 10.0) == expected
    assert Declines.calls == 1


def _arguments(table: ReservationTable, q: np.ndarray) -> list[Any]:
    cap = table._used.shape[0]
    live = np.ones(cap + 1, dtype=np.bool_)
    live[-1] = False
    per_slot = np.full(cap, 3.0)
    return [
        q,
        np.zeros((q.shape[0], 2)),
        table._dense,
        table._head,
        live,
        table._b_slot,
        table._b_k,
        table._b_start,
        table._b_box,
        table._rows,
        table._npts,
        per_slot,
        per_slot,
        per_slot,
        per_slot,
        per_slot,
        (1.0, 0.3, 0.0, 10.0, table._block_t, 0.8, 1.000001),
        np.full(cap, np.inf),
        np.full(cap, np.inf),
        np.full(cap, np.inf),
        np.full(cap, -1, dtype=np.int64),
    ]


def test_the_kernel_declines_arguments_it_does_not_expect() -> None:
    """Wrong dtypes, shapes, lengths, read-only outputs and block starts past a path's
    end: None (the numpy path answers), never a read out of bounds."""
    table = ReservationTable(D, H, 0.5)
    table.update("A", np.array([[-10.0, 0.0, 0.0], [10.0, 0.0, 2.0]]), 0.0)
    q = np.array([[0.0, -10.0, 0.0], [0.0, 0.0, 1.0], [0.0, 10.0, 2.0]])
    good = _arguments(table, q)
    assert _scan.scan(*good) == 1
    cap = table._used.shape[0]
    slots = len(table._dense)  # the kernel's columns are indexed by slot
    read_only = np.full(cap, np.inf)
    read_only.flags.writeable = False
    bad_start = table._b_start.copy()
    bad_start[0] = 1000
    negative_start = table._b_start.copy()
    negative_start[0] = -1
    spoilt: list[tuple[int, Any]] = [
        (0, q.astype(np.float32)),  # query of another dtype
        (0, q[:, :2].copy()),  # two columns
        (1, np.zeros((2, 2))),  # headings of another length
        (2, [np.zeros((2, 2))] * len(table._dense)),  # a stored path of two columns
        (3, table._head[:-1]),  # lists of different lengths
        (4, np.ones(slots, dtype=np.bool_)),  # live mask too short (slots + 1)
        (5, table._b_slot.astype(np.int64)),
        (7, bad_start),
        (7, negative_start),
        (8, table._b_box.astype(np.float64)),
        (9, table._b_slot.shape[0] + 1),  # more rows than the columns hold
        (11, np.full(slots - 1, 3.0)),  # a per-slot column too short
        (17, read_only),
        (20, np.full(cap, -1, dtype=np.int32)),
    ]
    for index, value in spoilt:
        args = list(good)
        args[index] = value
        assert _scan.scan(*args) is None, index
    with pytest.raises(TypeError):
        _scan.scan(*good[:-1])  # one argument short
    with pytest.raises(TypeError):
        _scan.scan(*good[:2], tuple(good[2]), *good[3:])  # type: ignore[call-arg]  # a tuple
