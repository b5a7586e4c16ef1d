"""Property tests: round trips within the resolution, and hostile bytes never escape DecodeError."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from protocol import (
    FORMAT_VERSION,
    AutonomousPath,
    Command,
    CoordinatedPath,
    DecodeError,
    EncodeError,
    Flags,
    FuturePath,
    Header,
    Kind,
    Message,
    Mode,
    ModeCommand,
    RsuBeacon,
    VehicleLimits,
    decode,
    encode,
    max_points,
)
from protocol.messages import FloatArray
from services.bench.codec import sample_messages
from tests.protocol.vectors import VECTORS, assert_close

ids = st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True)
coords = st.floats(-1e7, 1e7)
path_times_us = st.integers(-(10**15), 10**15)

# per-column scale of the random steps between points: none, tiny, 1-byte, up to the int16 limit
STEP_XY = (0.0, 0.004, 1.27, 327.0)
STEP_T = (0.0, 0.0004, 0.255, 65.0)
STEP_V = (0.0, 0.004, 1.27, 100.0)


@st.composite
def headers(draw: st.DrawFn, time_us: st.SearchStrategy[int] | None = None) -> Header:
    auth = draw(st.one_of(st.just(b""), st.binary(min_size=1, max_size=256)))
    return Header(
        draw(ids),
        draw(st.integers(0, 2**32 - 1)),
        draw(time_us if time_us is not None else st.integers(-(2**53), 2**53)),
        Flags.AUTH if auth else 0,
        auth,
    )


@st.composite
def path_points(draw: st.DrawFn, kind: Kind, time_us: int) -> tuple[FloatArray, FloatArray]:
    """Points (N, 3) near the header time and speeds (N,), with deltas that fit the wire."""
    n = draw(st.integers(0, max_points(kind)))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    sx, sy = draw(st.sampled_from(STEP_XY)), draw(st.sampled_from(STEP_XY))
    st_, sv = draw(st.sampled_from(STEP_T)), draw(st.sampled_from(STEP_V))
    x0, y0 = draw(st.floats(-1e5, 1e5)), draw(st.floats(-1e5, 1e5))
    t0 = time_us / 1e6 + draw(st.floats(-1e6, 1e6))
    steps = rng.uniform(-1.0, 1.0, size=(max(n - 1, 0), 3)) * [sx, sy, st_]
    steps[:, 2] = np.abs(steps[:, 2])
    pts = np.empty((n, 3))
    if n:
        pts[0] = (x0, y0, t0)
        pts[1:] = steps
        pts = np.cumsum(pts, axis=0)
    speeds = np.clip(draw(st.floats(0, 100)) + np.cumsum(rng.uniform(-1, 1, n) * sv), 0, 100)
    return pts, speeds


accels = st.floats(0.06, 25.54)
"""Declared accelerations that round to 1..255 tenths of m/s²."""

limits = st.one_of(
    st.none(), st.builds(VehicleLimits, st.floats(0.01, 100.0), accels, accels, accels)
)


@st.composite
def vehicle_paths(draw: st.DrawFn) -> Message:
    h = draw(headers(path_times_us))
    future = draw(st.booleans())
    pts, _ = draw(path_points(Kind.FUTURE_PATH, h.time_us))
    return (FuturePath if future else AutonomousPath)(
        h,
        draw(coords),
        draw(coords),
        draw(st.floats(0, 100)),
        draw(st.floats(-100, 100)),
        draw(st.floats(0.01, 50)),
        draw(st.floats(0.01, 10)),
        draw(st.sampled_from(Mode)),
        pts,
        draw(limits),
    )


@st.composite
def coordinated_paths(draw: st.DrawFn) -> Message:
    h = draw(headers(path_times_us))
    pts, speeds = draw(path_points(Kind.COORDINATED_PATH, h.time_us))
    mode = draw(st.sampled_from([Mode.C_SLOW, Mode.C_FAST]))
    return CoordinatedPath(h, draw(ids), mode, pts, speeds)


@st.composite
def mode_commands(draw: st.DrawFn) -> Message:
    command, mode = draw(
        st.sampled_from(
            [
                (Command.INITIATE, Mode.C_SLOW),
                (Command.INITIATE, Mode.C_FAST),
                (Command.TERMINATE, Mode.AUTO),
            ]
        )
    )
    return ModeCommand(draw(headers()), draw(ids), command, mode)


@st.composite
def beacons(draw: st.DrawFn) -> Message:
    return RsuBeacon(
        draw(headers()), draw(ids), draw(coords), draw(coords), draw(st.floats(0.01, 10_000))
    )


messages = st.one_of(vehicle_paths(), coordinated_paths(), mode_commands(), beacons())


def encode_or_reject(message: Message) -> bytes:
    """Encode; a path with an auth trailer may legitimately not fit one datagram."""
    try:
        return encode(message)
    except EncodeError as exc:
        assume(not (message.header.auth and "datagram" in str(exc)))
        raise


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages)
def test_round_trip_within_resolution(message: Message) -> None:
    data = encode_or_reject(message)
    assert len(data) <= 1460
    back = decode(data)
    assert_close(message, back)
    # a decoded message is a fixed point of the codec
    assert encode(back) == data


def check_decode(data: bytes) -> Message | None:
    """``decode`` gives a message or DecodeError, nothing else; an accepted message re-encodes."""
    try:
        message = decode(data)
    except DecodeError:
        return None
    again = encode(message)  # whatever decode accepts, encode accepts
    assert_close(message, decode(again), position=1e-9, time=1e-9, speed=1e-12)
    return message


@settings(max_examples=2000, deadline=None)
@given(
    st.one_of(
        st.binary(max_size=1600),
        st.builds(
            lambda kind, flags, rest: bytes([0xCB, FORMAT_VERSION, kind, flags]) + rest,
            st.integers(0, 7),
            st.integers(0, 3),
            st.binary(max_size=1500),
        ),
    )
)
def test_arbitrary_bytes_give_a_message_or_decode_error(data: bytes) -> None:
    check_decode(data)


def valid_datagrams() -> list[bytes]:
    out = [bytes.fromhex(hex_) for _, hex_ in VECTORS.values()]
    out += [encode(m) for m in sample_messages(120).values()]
    out += [encode(m) for m in sample_messages(7).values()]
    return out


DATAGRAMS = valid_datagrams()


@settings(max_examples=1500, deadline=None)
@given(
    st.sampled_from(DATAGRAMS),
    st.lists(st.tuples(st.integers(0, 2000), st.integers(0, 255)), min_size=1, max_size=6),
    st.integers(-3, 3),
)
def test_mutated_datagrams_give_a_message_or_decode_error(
    data: bytes, edits: list[tuple[int, int]], resize: int
) -> None:
    buf = bytearray(data)
    for pos, value in edits:
        buf[pos % len(buf)] = value
    if resize < 0:
        del buf[resize:]
    else:
        buf += bytes(resize)
    check_decode(bytes(buf))


@pytest.mark.parametrize("index", range(len(DATAGRAMS)))
def test_every_truncation_is_rejected(index: int) -> None:
    data = DATAGRAMS[index]
    for end in range(len(data)):
        with pytest.raises(DecodeError):
            decode(data[:end])


@pytest.mark.parametrize("index", range(len(DATAGRAMS)))
def test_every_single_bit_flip_gives_a_message_or_decode_error(index: int) -> None:
    data = DATAGRAMS[index]
    accepted = 0
    for i in range(len(data) * 8):
        flipped = bytearray(data)
        flipped[i // 8] ^= 1 << (i % 8)
        if check_decode(bytes(flipped)) is not None:
            accepted += 1
    # most flips inside point data still decode (to a different path); header flips mostly do not
    assert accepted < len(data) * 8


def test_every_kind_is_exercised_by_the_corruption_tests() -> None:
    kinds: set[Any] = {decode(d).kind for d in DATAGRAMS}
    assert kinds == set(Kind)
