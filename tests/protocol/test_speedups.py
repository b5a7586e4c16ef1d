"""The codec's C speed-ups (``protocol/_speedups.c``) against the numpy path they replace.

Each C function must give the very bytes, arrays and objects of the Python code beside it
(``codec._points_numpy`` / ``_points_checked``, ``_vehicle_rows_numpy``, Python's
``round``, ``codec._constructor``'s Python version), or decline with None so that the
Python path decides; and no input, however hostile, may make it read out of bounds or
raise anything but the ``TypeError`` of a wrong call. Without a C compiler the module is
not built and the codec runs on numpy: locally these tests then skip, on CI (``CI`` set)
they fail, since ``make test`` builds it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import AutonomousPath, FuturePath, Header, Kind, Mode, codec, decode, encode
from services.bench.codec import sample_messages
from tests.kernels import require_kernel
from tests.protocol.test_fast_points import (
    body_offset,
    datagrams,
    hostile_points,
    outcome,
    reference_read_points,
    spoil,
)
from tests.protocol.vectors import assert_same

require_kernel(codec.speedups_available(), "protocol._speedups")

from protocol import _speedups  # noqa: E402 - after the check above

FP = Kind.FUTURE_PATH


def test_the_codec_uses_the_c_module_by_default_and_can_leave_it() -> None:
    assert codec._C_POINTS is _speedups
    assert isinstance(codec._NEW[FuturePath], functools.partial)  # _speedups.build
    assert codec.use_speedups(False) is True
    try:
        assert codec._C_POINTS is None
        assert not isinstance(codec._NEW[FuturePath], functools.partial)
        assert codec.use_speedups(False) is False
    finally:
        codec.use_speedups(True)
    assert codec._C_POINTS is _speedups
    assert isinstance(codec._NEW[Header], functools.partial)


@settings(max_examples=300, deadline=None)
@given(hostile_points())
def test_c_pack_equals_the_numpy_and_checked_paths(case: tuple[Any, int]) -> None:
    pts, time_us = case
    checked = outcome(codec._points_checked, FP, pts, None, time_us)
    assert outcome(codec._points_numpy, FP, pts, None, time_us) == checked
    assert outcome(codec._points, FP, pts, None, time_us) == checked
    packed = _speedups.pack(pts, time_us // 1000, codec._MAX_COORD_F)
    if packed is not None:  # declined: the checked path decides (above)
        assert (len(pts), *packed) == checked


def test_c_pack_declines_arrays_it_does_not_read() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.1], [2.0, 2.0, 0.2]])
    assert _speedups.pack(pts, 0, codec._MAX_COORD_F) is not None
    cases: list[Any] = [
        pts.astype(np.float32),
        np.asfortranarray(pts),
        pts[::2],
        pts[:, :2],
        pts.reshape(-1),
        pts[:1],
        pts.astype(">f8"),
        pts.tolist(),
        b"\x00" * 72,
    ]
    for bad in cases:
        assert _speedups.pack(bad, 0, codec._MAX_COORD_F) is None
    assert _speedups.pack(np.zeros((1025, 3)), 0, codec._MAX_COORD_F) is None


EDGES = (-32769, -32768, -129, -128, 127, 128, 255, 256, 32767, 32768, 65535, 65536)
"""Steps [wire units] on each side of every width's bound (int8, uint8, int16, uint16)."""


def test_c_pack_at_every_width_edge() -> None:
    """A step of exactly a width's bound, and one past it, in x, y and t: the C code packs
    what the checked path packs, or declines and the checked path refuses (random floats
    almost never land on a bound; a one-unit slip in a C comparison would)."""
    scale = (100.0, 100.0, 1000.0)
    for col in range(3):
        for step in EDGES:
            if col == 2 and step < 0:
                continue  # time going back: refused whatever the width
            steps = np.zeros((4, 3))
            steps[:, 2] = 0.1
            steps[1, col] = step / scale[col]
            pts = np.cumsum(np.vstack([[5.0, -3.0, 12.0], steps]), axis=0)
            checked = outcome(codec._points_checked, FP, pts, None, 12_000_000)
            packed = _speedups.pack(pts, 12_000, codec._MAX_COORD_F)
            if packed is None:
                assert isinstance(checked[0], str), (col, step, checked)
            else:
                assert (len(pts), *packed) == checked, (col, step)


def test_c_unpack_declines_a_body_cut_anywhere() -> None:
    """A genuine path's points cut one byte short, or any shorter, are never read: the
    bounds check is exact (random bytes almost never sit one byte short of the end)."""
    for data in datagrams():
        off, n, widths, ncols, time_us = body_offset(data)
        if ncols != 3:
            continue
        layout = (off, n, widths, time_us // 1000, codec._MAX_COORD_F)
        whole = _speedups.unpack(data, *layout)
        assert whole is not None
        end = whole[1]
        for cut in range(off, end):
            assert _speedups.unpack(data[:cut], *layout) is None, (cut, end)
        exact = _speedups.unpack(data[:end], *layout)  # nothing after the points: read whole
        assert exact is not None and exact[1] == end


quantities = (
    st.floats(allow_nan=True, allow_infinity=True)
    | st.integers(-(10**6), 10**6).map(lambda k: k / 200)  # halves of a wire unit: ties
    | st.integers(-(2**70), 2**70)
)


@settings(max_examples=300, deadline=None)
@given(st.lists(quantities, min_size=6, max_size=6))
def test_c_state_is_pythons_round(values: list[float]) -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1]])
    try:
        done = _speedups.vehicle_path(pts, 0, codec._MAX_COORD_F, *values)
    except OverflowError:
        pytest.fail("vehicle_path raised for a number it should decline")
    scales = (100.0, 100.0, 100.0, 1e4, 100.0, 100.0)
    expected: list[int | None] = []
    for v, scale in zip(values, scales, strict=True):
        try:
            expected.append(round(float(v) * scale))
        except (OverflowError, ValueError):
            expected.append(None)
    if done is None:  # declined: a value Python cannot round, or one beyond 2**62
        assert any(e is None or abs(e) >= 4.6e18 for e in expected)
        return
    assert list(done[:6]) == expected
    assert done[6:] == _speedups.pack(pts, 0, codec._MAX_COORD_F)


def test_c_state_declines_what_is_not_a_number() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1]])
    args = [1.0, 2.0, 3.0, 0.5, 4.5, 1.8]
    assert _speedups.vehicle_path(pts, 0, codec._MAX_COORD_F, *args) is not None
    for bad in ("1.0", None, [1.0], 10**400):
        spoiled = [bad, *args[1:]]
        assert _speedups.vehicle_path(pts, 0, codec._MAX_COORD_F, *spoiled) is None  # type: ignore[arg-type]


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(datagrams()),
    st.lists(st.tuples(st.integers(0, 800), st.integers(0, 255)), max_size=6),
    st.integers(-(2**40), 2**40),
)
def test_c_unpack_equals_the_reference(data: bytes, edits: list[tuple[int, int]], dt: int) -> None:
    off, n, widths, ncols, time_us = body_offset(data)
    if ncols != 3:
        return  # coordinated paths (speeds) stay on numpy
    raw = spoil(data, edits, off)
    time_us += dt
    got = _speedups.unpack(raw, off, n, widths, time_us // 1000, codec._MAX_COORD_F)
    ref = outcome(reference_read_points, raw, off, Kind(data[2]), n, widths, 3, time_us)
    if got is None:
        return  # declined: the general decoder explains (test_fast_points)
    rows, end = got
    assert not isinstance(ref[0], str), ref
    assert rows.tobytes() == ref[0].tobytes() and rows.shape == ref[0].shape == (n, 3)
    assert rows.flags.owndata and rows.flags.c_contiguous and not rows.flags.writeable
    assert end == ref[2]


@settings(max_examples=500, deadline=None)
@given(
    st.binary(max_size=1500),
    st.integers(-5, 1600),
    st.integers(-5, 1100),
    st.integers(0, 255),
    st.integers(-(2**53) // 1000, 2**53 // 1000),
)
def test_c_unpack_of_any_bytes_stays_in_bounds(
    buf: bytes, off: int, n: int, widths: int, t_base_ms: int
) -> None:
    got = _speedups.unpack(buf, off, n, widths, t_base_ms, codec._MAX_COORD_F)
    if got is None:
        return
    rows, end = got
    codes = [(widths >> (2 * c)) & 3 for c in range(3)]
    assert 3 not in codes and widths < 64 and 2 <= n <= 1024
    assert end == off + 12 + (n - 1) * sum(codes) <= len(buf)
    assert rows.shape == (n, 3) and np.isfinite(rows).all()


@settings(max_examples=150, deadline=None)
@given(
    st.sampled_from(datagrams()),
    st.lists(st.tuples(st.integers(0, 800), st.integers(0, 255)), max_size=4),
)
def test_numpy_and_c_decoders_give_the_same_message(
    data: bytes, edits: list[tuple[int, int]]
) -> None:
    raw = spoil(data, edits)
    codec._decode(data)  # fill the id and layout caches both fast paths look up
    c_path = outcome(codec._decode_vehicle_path_fast, raw)
    previous = codec.use_speedups(False)
    try:
        numpy_path = outcome(codec._decode_vehicle_path_fast, raw)
    finally:
        codec.use_speedups(previous)
    general = outcome(codec._decode, raw)
    for got in (numpy_path, c_path):  # each: declined, or what the general decoder gives
        if isinstance(got, FuturePath | AutonomousPath):
            assert type(got) is type(general)
            assert_same(general, got)
        else:
            assert got is None or got == general
    if numpy_path is not None and c_path is not None:
        assert type(numpy_path) is type(c_path)


def test_c_and_numpy_paths_round_trip_every_sample_alike() -> None:
    for points in (2, 120, 161):
        for m in sample_messages(points).values():
            data = encode(m)
            via_c = decode(data)
            previous = codec.use_speedups(False)
            try:
                assert encode(m) == data
                via_numpy = decode(data)
            finally:
                codec.use_speedups(previous)
            assert_same(via_c, via_numpy)


def test_c_build_makes_what_the_constructor_makes() -> None:
    m = sample_messages(120)["future_path"]
    assert isinstance(m, FuturePath)
    names = [f.name for f in dataclasses.fields(FuturePath)]
    spec = (FuturePath, tuple(getattr(FuturePath, name) for name in names))
    built = _speedups.build(spec, *(getattr(m, name) for name in names))
    assert type(built) is FuturePath
    assert_same(m, built)
    assert_same(built, dataclasses.replace(built))
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.x = 1.0  # type: ignore[misc]


def test_c_build_refuses_a_wrong_call() -> None:
    names = [f.name for f in dataclasses.fields(Header)]
    spec = (Header, tuple(getattr(Header, name) for name in names))
    assert _speedups.build(spec, "car-a", 1, 2, 0, b"") == Header("car-a", 1, 2)
    with pytest.raises(TypeError):
        _speedups.build(spec, "car-a", 1, 2)  # a value short
    with pytest.raises(TypeError):
        _speedups.build((Header, ("not a descriptor",) * 5), "car-a", 1, 2, 0, b"")
    with pytest.raises(TypeError):
        _speedups.build((Header,), "car-a")  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        _speedups.build(("not a class", spec[1]), "car-a", 1, 2, 0, b"")  # type: ignore[arg-type]
    with pytest.raises(TypeError):  # a slot descriptor of another class
        _speedups.build((FuturePath, spec[1] + (None,) * 5), *range(10))


def test_a_huge_time_base_is_exact() -> None:
    """Times near the wire's ±2**53 µs limit keep every millisecond in both paths."""
    t_us = 2**53 - 10**6
    pts = np.column_stack([np.arange(5.0), np.zeros(5), t_us // 1000 / 1000 + np.arange(5) * 0.1])
    m = FuturePath(Header("car-a", 1, t_us), 0.0, 0.0, 1.0, 0.0, 4.5, 1.8, Mode.AUTO, pts)
    data = encode(m)
    back = decode(data)
    assert isinstance(back, FuturePath)
    assert back.points.tobytes() == codec._decode(data).points.tobytes()  # type: ignore[union-attr]
    assert math.isclose(back.points[-1, 2], pts[-1, 2], rel_tol=0, abs_tol=1e-3)
