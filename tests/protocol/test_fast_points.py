"""The codec's fast point paths give exactly what the straightforward ones give.

``codec._points`` (vehicle paths) must produce the same bytes as
``codec._points_checked`` or refuse with the same ``EncodeError``; ``codec._read_points``
must give bit-identical arrays to ``reference_read_points`` below, a verbatim copy of the
decoder before it was tuned for speed (issue 14), or the same ``DecodeError``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import (
    AutonomousPath,
    CoordinatedPath,
    DecodeError,
    EncodeError,
    FuturePath,
    Kind,
    codec,
    decode,
    encode,
)
from protocol.messages import FloatArray
from services.bench.codec import sample_messages
from tests.protocol.test_properties import path_points, path_times_us
from tests.protocol.vectors import assert_same


def reference_read_points(
    buf: bytes, off: int, kind: Kind, n: int, widths: int, ncols: int, time_us: int
) -> tuple[FloatArray, FloatArray | None, int]:
    """``codec._read_points`` as it was before issue 14 (the reference), with format 3 times."""
    if n > codec._MAX_POINTS[kind]:
        raise DecodeError("too many points")
    plan = codec._delta_plan(n, widths, ncols)
    if n == 0:
        return codec._NO_POINTS, (None if ncols == 3 else codec._NO_SPEEDS), off
    first_struct = codec._FIRST3 if ncols == 3 else codec._FIRST4
    first = first_struct.unpack_from(buf, off)
    off += first_struct.size
    for c in range(ncols):
        if not codec._COL_LO[c] <= first[c] <= codec._COL_HI[c]:
            raise DecodeError("first point out of range")
    rows = np.zeros((n, ncols))
    start = list(first)
    start[codec._T_COLUMN] += time_us // 1000
    rows[0] = start
    count = n - 1
    for c, dtype, size in plan:
        end = off + size
        if end > len(buf):
            raise DecodeError("truncated")
        rows[1:, c] = np.frombuffer(buf, dtype, count, off)
        off = end
    np.add.accumulate(rows, 0, None, rows)
    speeds = None
    if ncols == 4:
        cm_s = rows[:, 3]
        if np.minimum.reduce(cm_s) < 0 or np.maximum.reduce(cm_s) > codec._MAX_SPEED_CM_S:
            raise DecodeError("path speeds out of range")
        speeds = cm_s / 100.0
        points = rows[:, :3] / codec._SCALE_ROW
    else:
        points = np.divide(rows, codec._SCALE_ROW, rows)
    return points, speeds, off


def outcome(fn: Any, *args: Any) -> Any:
    try:
        return fn(*args)
    except (EncodeError, DecodeError) as exc:
        return type(exc).__name__, str(exc)


@st.composite
def hostile_points(draw: st.DrawFn) -> tuple[FloatArray, int]:
    """Realistic paths, some spoiled: NaN/inf, a huge jump, time going back, big time steps."""
    time_us = draw(path_times_us)
    pts, _ = draw(path_points(Kind.FUTURE_PATH, time_us))
    pts = pts.copy()
    if len(pts) >= 2 and draw(st.booleans()):
        i = draw(st.integers(0, len(pts) - 1))
        col = draw(st.integers(0, 2))
        pts[i, col] = draw(
            st.sampled_from([np.nan, np.inf, -np.inf, 1e12, -1e12])
            | st.floats(-1e4, 1e4, allow_nan=False)
        )
    return pts, time_us


@settings(max_examples=150, deadline=None)
@given(hostile_points())
def test_fast_encode_equals_checked_encode(case: tuple[FloatArray, int]) -> None:
    pts, time_us = case
    fast = outcome(codec._points, Kind.FUTURE_PATH, pts, None, time_us)
    checked = outcome(codec._points_checked, Kind.FUTURE_PATH, pts, None, time_us)
    assert fast == checked


def test_fast_encode_takes_every_width_layout() -> None:
    """x, y and t steps of 0, 1 and 2 bytes in every combination, t up to 65.535 s."""
    seen = set()
    for sx in (0.0, 0.5, 1.27, 1.28, 300.0):
        for sy in (0.0, -0.3, -1.28, -1.29, -300.0):
            for st_ in (0.0, 0.084, 0.127, 0.128, 0.255, 0.256, 65.5):
                steps = np.tile([sx, sy, st_], (30, 1))
                steps[::2, :2] *= -1 if sx != 300.0 else 1
                pts = np.cumsum(np.vstack([[5.0, -3.0, 12.0], steps]), axis=0)
                fast = codec._points(Kind.FUTURE_PATH, pts, None, 12_000_500)
                assert fast == codec._points_checked(Kind.FUTURE_PATH, pts, None, 12_000_500)
                seen.add(fast[1])
    assert len(seen) >= 20


def spoil(data: bytes, edits: list[tuple[int, int]], start: int = 0) -> bytes:
    """``data`` with each (offset, byte) of ``edits`` at or after ``start`` written in."""
    buf = bytearray(data)
    for at, value in edits:
        if start <= at < len(buf):
            buf[at] = value
    return bytes(buf)


def datagrams() -> list[bytes]:
    out = [encode(m) for m in sample_messages(120).values()]
    out += [encode(m) for m in sample_messages(2).values()]
    return [d for d in out if d[2] in (Kind.FUTURE_PATH, Kind.COORDINATED_PATH)]


def body_offset(data: bytes) -> tuple[int, int, int, int, int]:
    """(offset of the first point, n, widths, ncols, time_us) of a vehicle or coordinated path."""
    head = codec._HEAD.unpack_from(data, 0)
    off = codec._HEAD.size + head[6]
    if data[2] == Kind.COORDINATED_PATH:
        off += 1 + data[off]
        _, n, widths = codec._CP_STATE.unpack_from(data, off)
        return off + codec._CP_STATE.size, n, widths, 4, head[5]
    fields = codec._STATE.unpack_from(data, off)
    return off + codec._STATE.size, fields[-2], fields[-1], 3, head[5]


@settings(max_examples=250, deadline=None)
@given(
    st.sampled_from(datagrams()),
    st.lists(st.tuples(st.integers(0, 800), st.integers(0, 255)), max_size=6),
    st.integers(-(2**40), 2**40),
)
def test_fast_decode_equals_reference(data: bytes, edits: list[tuple[int, int]], dt: int) -> None:
    off, n, widths, ncols, time_us = body_offset(data)
    kind = Kind(data[2])
    args = (spoil(data, edits, off), off, kind, n, widths, ncols, time_us + dt)  # points only
    fast = outcome(codec._read_points, *args)
    ref = outcome(reference_read_points, *args)
    if isinstance(ref, tuple) and isinstance(ref[0], str):
        assert fast == ref or isinstance(fast[0], str)
        return
    assert not isinstance(fast[0], str)
    assert fast[0].tobytes() == ref[0].tobytes() and fast[0].shape == ref[0].shape
    assert fast[0].flags.c_contiguous and not fast[0].flags.writeable
    assert (fast[1] is None) == (ref[1] is None)
    if ref[1] is not None:
        assert fast[1].tobytes() == ref[1].tobytes()
    assert fast[2] == ref[2]


def test_decoded_message_equals_reference_for_real_paths() -> None:
    for data in datagrams():
        off, n, widths, ncols, time_us = body_offset(data)
        ref = reference_read_points(data, off, Kind(data[2]), n, widths, ncols, time_us)
        m = decode(data)
        assert isinstance(m, FuturePath | CoordinatedPath)
        assert m.points.tobytes() == ref[0].tobytes()


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(datagrams()),
    st.lists(st.tuples(st.integers(0, 800), st.integers(0, 255)), max_size=4),
)
def test_fast_message_paths_equal_the_general_ones(
    data: bytes, edits: list[tuple[int, int]]
) -> None:
    """``decode``'s and ``encode``'s one-struct vehicle path shortcuts change nothing."""
    raw = spoil(data, edits)
    fast = outcome(codec._decode_vehicle_path_fast, raw)
    general = outcome(codec._decode, raw)
    if fast is None or (isinstance(fast, tuple) and isinstance(general, tuple)):
        return  # not taken, or refused by both
    assert isinstance(fast, FuturePath | AutonomousPath) and type(fast) is type(general)
    assert_same(general, fast)
    assert fast.points.flags.owndata and not fast.points.flags.writeable
    again = codec._encode_vehicle_path_fast(fast.kind, fast)
    assert again is None or again == b"".join(codec._encode_vehicle_path(fast.kind, fast))
    assert encode(fast) == encode(general)
