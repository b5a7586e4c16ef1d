"""Unit tests of the binary codec: sizes, limits, and every refusal."""

from __future__ import annotations

import dataclasses
import math
import struct
from typing import Any

import numpy as np
import pytest

from protocol import (
    MAX_DATAGRAM,
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
    codec,
    decode,
    encode,
    max_points,
)
from protocol.messages import FloatArray
from services.bench.codec import sample_future_path, sample_messages
from tests.protocol.vectors import VECTORS, assert_close, assert_same

LONG_ID = "v" * 32
PATH_KINDS = (Kind.FUTURE_PATH, Kind.AUTONOMOUS_PATH, Kind.COORDINATED_PATH)


def wide_points(n: int, t0: float = 10.0) -> FloatArray:
    """``n`` points whose deltas need 2 bytes in every column (worst case for size)."""
    k = np.arange(n, dtype=np.float64)
    sign = np.where(k % 2 == 0, 1.0, -1.0)
    return np.column_stack([150.0 * sign, -150.0 * sign, t0 + 0.3 * k])


def wide_speeds(n: int) -> FloatArray:
    return np.where(np.arange(n) % 2 == 0, 2.0, 20.0)


def path_message(
    kind: Kind, n: int, *, sender: str = LONG_ID, header: Header | None = None
) -> Message:
    """A worst-case path message of ``kind`` with ``n`` points and the longest ids."""
    h = header or Header(sender, 1, 10_000_000)
    pts = wide_points(n)
    if kind is Kind.COORDINATED_PATH:
        return CoordinatedPath(h, LONG_ID, Mode.C_FAST, pts, wide_speeds(n))
    cls = FuturePath if kind is Kind.FUTURE_PATH else AutonomousPath
    return cls(h, 1.0, 2.0, 10.0, 0.5, 4.5, 1.8, Mode.AUTO, pts)


def fp(**changes: Any) -> FuturePath:
    base = VECTORS["fp-basic"][0]
    assert isinstance(base, FuturePath)
    return dataclasses.replace(base, **changes)


def cp(**changes: Any) -> CoordinatedPath:
    base = VECTORS["cp-slow"][0]
    assert isinstance(base, CoordinatedPath)
    return dataclasses.replace(base, **changes)


def header(**changes: Any) -> Header:
    return dataclasses.replace(Header("car-a", 1, 12_345_000), **changes)


# ---------------------------------------------------------------- capacity and sizes


def test_max_points_per_kind() -> None:
    # room kept for a 79-byte signature trailer (protocol.auth, issue 13)
    assert max_points(Kind.FUTURE_PATH) == 216
    assert max_points(Kind.AUTONOMOUS_PATH) == 216
    assert max_points(Kind.COORDINATED_PATH) == 161
    assert max_points(Kind.MODE_COMMAND) == 0
    assert max_points(Kind.RSU_BEACON) == 0
    assert max_points(1) == 216
    with pytest.raises(ValueError, match="unknown message kind"):
        max_points(9)


def test_realistic_120_point_future_path_size() -> None:
    message = sample_future_path(120)
    assert message.points.shape == (120, 3)
    assert len(encode(message)) == 297


def test_worst_case_120_point_future_path_is_at_most_800_bytes() -> None:
    data = encode(path_message(Kind.FUTURE_PATH, 120))
    assert len(data) == 17 + 32 + 25 + 12 + 119 * 6 == 800
    back = decode(data)
    assert isinstance(back, FuturePath)
    assert back.points.shape == (120, 3)


def test_sizes_of_every_kind_at_120_points() -> None:
    sizes = {name: len(encode(m)) for name, m in sample_messages(120).items()}
    assert sizes == {
        "future_path": 297,
        "autonomous_path": 297,
        "coordinated_path": 403,
        "mode_command": 30,
        "rsu_beacon": 38,
    }


@pytest.mark.parametrize("kind", PATH_KINDS)
def test_max_points_fit_in_the_worst_case(kind: Kind) -> None:
    n = max_points(kind)
    message = path_message(kind, n)
    data = encode(message)
    room = MAX_DATAGRAM - 79  # a digest-form signature trailer must still fit
    assert room - 8 < len(data) <= room
    assert_close(message, decode(data))


@pytest.mark.parametrize("kind", PATH_KINDS)
def test_one_point_more_than_max_points_is_refused(kind: Kind) -> None:
    with pytest.raises(EncodeError, match="at most"):
        encode(path_message(kind, max_points(kind) + 1))


@pytest.mark.parametrize("kind", PATH_KINDS)
def test_max_points_is_a_cap_even_for_small_deltas(kind: Kind) -> None:
    n = max_points(kind) + 1
    pts = np.column_stack([np.zeros(n), np.zeros(n), np.full(n, 10.0)])
    h = Header("a", 1, 10_000_000)
    message: Message
    if kind is Kind.COORDINATED_PATH:
        message = CoordinatedPath(h, "b", Mode.C_SLOW, pts, np.zeros(n))
    else:
        message = FuturePath(h, 0, 0, 0, 0, 4.5, 1.8, Mode.AUTO, pts)
    with pytest.raises(EncodeError, match="at most"):
        encode(message)


def test_trailer_can_push_a_full_path_over_the_datagram() -> None:
    h = Header(LONG_ID, 1, 10_000_000, Flags.AUTH, bytes(256))  # longer than a digest trailer
    with pytest.raises(EncodeError, match="1460-byte datagram"):
        encode(path_message(Kind.FUTURE_PATH, max_points(Kind.FUTURE_PATH), header=h))


def test_zero_and_one_point_paths_round_trip() -> None:
    for n in (0, 1):
        pts = np.array([[1.0, 2.0, 12.5]])[:n]
        m = fp(points=pts)
        data = encode(m)
        assert len(data) == 17 + 5 + 25 + 12 * n
        assert_same(m, decode(data))
        c = cp(points=pts, speeds=np.array([3.0])[:n])
        assert_same(c, decode(encode(c)))


def test_narrow_columns_are_chosen() -> None:
    # x changes by 1.15 m, y is constant, t by 100 ms: 2 bytes per point after the first
    m = sample_future_path(120)
    assert len(encode(m)) == 17 + 5 + 25 + 12 + 119 * 2


@pytest.mark.parametrize("n", [0, 1, 2, 120])
@pytest.mark.parametrize("kind", PATH_KINDS)
def test_decoded_messages_are_what_their_constructors_make(kind: Kind, n: int) -> None:
    # decode skips __init__ (codec._constructor): the result must still be a proper value,
    # with read-only float64 arrays that own their memory, as __post_init__ would leave them
    m = decode(encode(path_message(kind, n)))
    assert isinstance(m, FuturePath | AutonomousPath | CoordinatedPath)
    rebuilt = dataclasses.replace(m)  # runs __init__ and __post_init__
    assert_same(m, rebuilt)
    arrays = [m.points] + ([m.speeds] if isinstance(m, CoordinatedPath) else [])
    for arr in arrays:
        assert arr.dtype == np.float64
        assert arr.flags.c_contiguous
        assert not arr.flags.writeable
        assert arr.flags.owndata or arr.size == 0
    assert m.points.shape == (n, 3)
    assert dataclasses.replace(m.header) == m.header
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.header.seq = 2  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        m.points[..., 0] = 1.0


def test_codec_caches_stay_bounded_whatever_peers_send() -> None:
    # ids and delta layouts are cached (codec speed); distinct senders must not grow them
    for i in range(3 * codec._CACHE_MAX):
        sender = f"car-{i}"
        m = decode(encode(fp(header=header(sender=sender), points=wide_points(2 + i % 200))))
        assert m.header.sender == sender
    assert 0 < len(codec._ID_CACHE) <= codec._CACHE_MAX
    assert 0 < len(codec._ID_STRS) <= codec._CACHE_MAX
    assert 0 < len(codec._PLANS) <= codec._CACHE_MAX
    for i in range(3 * codec._CACHE_MAX):
        limits = VehicleLimits((100 + i) / 100, 1.5, 2.0, 2.0)  # distinct, exact on the wire
        m = decode(encode(fp(limits=limits)))
        assert isinstance(m, FuturePath) and m.limits == limits
    assert 0 < len(codec._LIMITS) <= codec._CACHE_MAX
    assert 0 < len(codec._LIMITS_WIRE) <= codec._CACHE_MAX
    with pytest.raises(EncodeError, match="invalid sender id"):
        encode(fp(header=header(sender="car 1")))


@pytest.mark.parametrize("name", ["mode_command", "rsu_beacon"])
def test_decoded_small_messages_equal_their_rebuilt_selves(name: str) -> None:
    m = decode(encode(sample_messages()[name]))
    assert m == dataclasses.replace(m) == sample_messages()[name]
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.header = m.header  # type: ignore[misc]


def test_bytearray_and_memoryview_decode() -> None:
    data = bytes.fromhex(VECTORS["fp-basic"][1])
    assert_same(decode(data), decode(bytearray(data)))
    assert_same(decode(data), decode(memoryview(data)))


# ---------------------------------------------------------------- resolution


def test_heading_is_wrapped_into_plus_minus_pi() -> None:
    m = decode(encode(fp(heading=1.5 * math.pi)))
    assert isinstance(m, FuturePath)
    assert m.heading == pytest.approx(-0.5 * math.pi, abs=1e-4)
    m = decode(encode(fp(heading=-7.0)))
    assert isinstance(m, FuturePath)
    assert m.heading == pytest.approx(math.remainder(-7.0, math.tau), abs=1e-4)


def test_quantisation_does_not_accumulate_along_a_path() -> None:
    n = 200
    t = 5.0 + np.arange(n) * 0.0837
    pts = np.column_stack([np.arange(n) * 0.3333, np.arange(n) * -0.1234, t])
    m = fp(points=pts, header=header(time_us=4_999_999))
    assert_close(m, decode(encode(m)))


def test_header_time_need_not_be_whole_milliseconds() -> None:
    m = fp(header=header(time_us=12_345_678))
    back = decode(encode(m))
    assert back.header.time_us == 12_345_678
    assert_close(m, back)


def test_extreme_header_values_round_trip() -> None:
    for seq, time_us in [(0, -(2**53)), (2**32 - 1, 2**53)]:
        m = ModeCommand(Header("r", seq, time_us), "v", Command.INITIATE, Mode.C_SLOW)
        assert decode(encode(m)) == m


def test_auth_trailer_round_trips() -> None:
    for auth in (b"\x07", bytes(range(256))):
        m = RsuBeacon(Header("rsu-1", 1, 0, Flags.AUTH, auth), "x", 0.0, 0.0, 1.0)
        data = encode(m)
        assert data.endswith(auth[1:])
        assert decode(data) == m


# ---------------------------------------------------------------- encode refusals

BAD_IDS = ["", "v" * 33, "car a", "car/a", "car*", "café", "a\n", "$a", "a.b"]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_bad_ids_are_refused(bad: str) -> None:
    with pytest.raises(EncodeError, match="sender id"):
        encode(fp(header=header(sender=bad)))
    with pytest.raises(EncodeError, match="vehicle id"):
        encode(cp(vehicle=bad))
    with pytest.raises(EncodeError, match="vehicle id"):
        encode(ModeCommand(header(), bad, Command.INITIATE, Mode.C_SLOW))
    with pytest.raises(EncodeError, match="intersection id"):
        encode(RsuBeacon(header(), bad, 0.0, 0.0, 1.0))


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused(value: float) -> None:
    for field in ("x", "y", "speed", "heading", "length", "width"):
        with pytest.raises(EncodeError):
            encode(fp(**{field: value}))
    with pytest.raises(EncodeError):
        encode(RsuBeacon(header(), "x", 0.0, value, 1.0))
    with pytest.raises(EncodeError):
        encode(RsuBeacon(header(), "x", 0.0, 0.0, value))
    base = VECTORS["fp-basic"][0]
    assert isinstance(base, FuturePath)
    for row in (0, 2):
        for col in range(3):
            pts = base.points.copy()
            pts[row, col] = value
            with pytest.raises(EncodeError, match=r"NaN or infinity|backwards|changes"):
                encode(fp(points=pts))
    speeds = np.array([1.0, value, 2.0])
    with pytest.raises(EncodeError, match="speed"):
        encode(cp(speeds=speeds))


def test_nan_error_names_the_problem() -> None:
    base = VECTORS["fp-basic"][0]
    assert isinstance(base, FuturePath)
    pts = base.points.copy()
    pts[2, 0] = math.nan
    with pytest.raises(EncodeError, match="x contains NaN or infinity"):
        encode(fp(points=pts))


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"speed": -0.1}, "speed"),
        ({"speed": 100.1}, "speed"),
        ({"length": 0.0}, "length"),
        ({"length": 50.01}, "length"),
        ({"width": -1.8}, "width"),
        ({"width": 10.01}, "width"),
        ({"x": 1.1e7}, "x"),
        ({"y": -1.1e7}, "y"),
        ({"mode": 7}, "Mode|mode"),
    ],
)
def test_absurd_state_is_refused(changes: dict[str, Any], match: str) -> None:
    with pytest.raises(EncodeError, match=match):
        encode(fp(**changes))


@pytest.mark.parametrize(
    ("rows", "match"),
    [
        ([(0, 0, 1.0), (1, 0, 0.9)], "backwards"),
        ([(0, 0, 1.0), (327.68, 0, 1.1)], "x changes by 327.68 m"),
        ([(0, 0, 1.0), (0, -400, 1.1)], "y changes"),
        ([(0, 0, 1.0), (0, 0, 66.6)], "65.535 s"),
        ([(0, 0, 2.2e6)], "2\\*\\*31 ms"),
        ([(1.1e7, 0, 1.0)], "beyond"),
    ],
)
def test_bad_points_are_refused(rows: list[tuple[float, float, float]], match: str) -> None:
    with pytest.raises(EncodeError, match=match):
        encode(fp(points=np.array(rows, dtype=np.float64), header=header(time_us=0)))


CAR = VehicleLimits(13.89, 1.5, 2.0, 2.0)


@pytest.mark.parametrize(
    ("limits", "match"),
    [
        (dataclasses.replace(CAR, v_max=0.004), "v_max"),
        (dataclasses.replace(CAR, v_max=100.01), "v_max"),
        (dataclasses.replace(CAR, v_max=-8.0), "v_max"),
        (dataclasses.replace(CAR, accel=0.04), "accel"),
        (dataclasses.replace(CAR, accel=25.56), "accel"),
        (dataclasses.replace(CAR, decel=-2.0), "decel"),
        (dataclasses.replace(CAR, lat_accel=0.0), "lat_accel"),
        (dataclasses.replace(CAR, lat_accel=math.nan), "lat_accel"),
        (dataclasses.replace(CAR, v_max=math.inf), "v_max"),
        ((13.89, 1.5, 2.0, 2.0), "VehicleLimits"),
    ],
)
def test_absurd_limits_are_refused(limits: Any, match: str) -> None:
    with pytest.raises(EncodeError, match=match):
        encode(fp(limits=limits))


def test_limits_round_trip_within_their_resolution() -> None:
    for limits in (
        VehicleLimits(8.0, 1.0, 1.5, 1.2),
        VehicleLimits(0.01, 0.06, 0.1, 25.5),
        VehicleLimits(100.0, 25.54, 1.55, 2.049),
        None,
    ):
        back = decode(encode(fp(limits=limits)))
        assert isinstance(back, FuturePath)
        if limits is None:
            assert back.limits is None
            continue
        assert back.limits is not None
        assert abs(back.limits.v_max - limits.v_max) <= 0.005 + 1e-9
        for name in ("accel", "decel", "lat_accel"):
            assert abs(getattr(back.limits, name) - getattr(limits, name)) <= 0.05 + 1e-9
        assert encode(back) == encode(fp(limits=limits))
    # the same limits and path give the same bytes whichever kind carries them
    ap = AutonomousPath(*[getattr(fp(), f.name) for f in dataclasses.fields(FuturePath)])
    assert encode(ap)[3:] == encode(fp())[3:]


def test_largest_deltas_are_accepted() -> None:
    rows = [(0, 0, 0.0), (327.67, -327.68, 65.535), (0, -0.01, 65.535)]
    m = fp(points=np.array(rows, dtype=np.float64), header=header(time_us=0))
    assert_close(m, decode(encode(m)))


def test_bad_coordinated_paths_are_refused() -> None:
    with pytest.raises(EncodeError, match="not AUTO"):
        encode(cp(mode=Mode.AUTO))
    with pytest.raises(EncodeError, match="speed"):
        encode(cp(speeds=np.array([1.0, -0.5, 1.0])))
    with pytest.raises(EncodeError, match="speed"):
        encode(cp(speeds=np.array([1.0, 100.5, 1.0])))


@pytest.mark.parametrize(
    ("command", "mode"),
    [
        (Command.INITIATE, Mode.AUTO),
        (Command.TERMINATE, Mode.C_SLOW),
        (Command.TERMINATE, Mode.C_FAST),
    ],
)
def test_nonsense_mode_commands_are_refused(command: Command, mode: Mode) -> None:
    with pytest.raises(EncodeError):
        encode(ModeCommand(header(), "car-a", command, mode))


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"seq": -1}, "32 bits"),
        ({"seq": 2**32}, "32 bits"),
        ({"time_us": 2**53 + 1}, "2\\*\\*53"),
        ({"flags": 0x02}, "flag"),
        ({"flags": Flags.AUTH}, "auth"),
        ({"auth": b"sig"}, "auth"),
        ({"flags": Flags.AUTH, "auth": bytes(257)}, "at most 256"),
        ({"seq": 1.5}, "cannot encode"),
    ],
)
def test_bad_headers_are_refused(changes: dict[str, Any], match: str) -> None:
    with pytest.raises(EncodeError, match=match):
        encode(ModeCommand(header(**changes), "car-a", Command.INITIATE, Mode.C_SLOW))


def test_radius_limits() -> None:
    for radius in (0.0, -1.0, 10_000.01):
        with pytest.raises(EncodeError, match="radius"):
            encode(RsuBeacon(header(), "x", 0.0, 0.0, radius))


def test_not_a_message_is_refused() -> None:
    with pytest.raises(EncodeError, match="not a crosspath message"):
        encode(header())  # type: ignore[arg-type]


def test_encode_errors_are_value_errors() -> None:
    assert issubclass(EncodeError, ValueError)
    assert issubclass(DecodeError, ValueError)


# ---------------------------------------------------------------- decode refusals


def patched(name: str, offset: int, new: bytes) -> bytes:
    data = bytearray.fromhex(VECTORS[name][1])
    data[offset : offset + len(new)] = new
    return bytes(data)


# offsets in the vectors (all senders are 5 bytes, so bodies start at 22):
# fp-basic: x 22, y 26, speed 30, heading 32, length 34, width 36, v_max 38, accel 40,
#           decel 41, lat_accel 42, mode 43, N 44, widths 46, first point 47;
# cp-slow: vehicle 22, mode 28, first speed 44;
# mode commands: command 28, mode 29; beacon: intersection 22, radius 34
FP = bytes.fromhex(VECTORS["fp-basic"][1])


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"", "truncated"),
        (FP[:16], "truncated"),
        (FP[:-1], "truncated|malformed"),
        (FP + b"\x00", "trailing"),
        (FP + bytes(MAX_DATAGRAM), "longer than"),
        (patched("fp-basic", 0, b"\xca"), "magic"),
        (patched("fp-basic", 1, b"\x02"), "version"),  # version 2 counted T differently
        (patched("fp-basic", 1, b"\x04"), "version"),
        (patched("fp-basic", 2, b"\x00"), "kind"),
        (patched("fp-basic", 2, b"\x06"), "kind"),
        (patched("fp-basic", 3, b"\x02"), "flag"),
        (patched("fp-basic", 3, b"\x01"), "trailer"),
        (patched("fp-basic", 8, struct.pack("<q", 2**53 + 1)), "absurd generation time"),
        (patched("fp-basic", 16, b"\x00"), "sender id"),
        (patched("fp-basic", 16, b"\x21"), "sender id"),
        (patched("fp-basic", 17, b"car a"), "sender id"),
        (patched("fp-basic", 17, b"car\xffa"), "sender id"),
        (patched("fp-basic", 22, struct.pack("<i", 10**9 + 1)), "position"),
        (patched("fp-basic", 30, struct.pack("<H", 10001)), "speed"),
        (patched("fp-basic", 32, struct.pack("<h", 31417)), "heading"),
        (patched("fp-basic", 34, struct.pack("<H", 0)), "shape"),
        (patched("fp-basic", 36, struct.pack("<H", 1001)), "shape"),
        (patched("fp-basic", 38, struct.pack("<H", 10001)), "limits"),
        (patched("fp-basic", 38, struct.pack("<H", 0)), "limits"),
        (patched("fp-basic", 40, b"\x00"), "limits"),
        (patched("fp-basic", 41, b"\x00"), "limits"),
        (patched("fp-basic", 42, b"\x00"), "limits"),
        (patched("fp-auth", 38, b"\x01"), "limits"),
        (patched("fp-auth", 42, b"\x01"), "limits"),
        (patched("fp-basic", 43, b"\x03"), "mode"),
        (patched("fp-basic", 44, struct.pack("<H", 231)), "231 points"),
        (patched("fp-basic", 44, struct.pack("<H", 0xFFFF)), "points"),
        (patched("fp-basic", 44, struct.pack("<H", 5)), "truncated"),
        (patched("fp-basic", 44, struct.pack("<H", 3)), "trailing"),
        (patched("fp-basic", 46, b"\x13"), "reserved width code 3"),
        (patched("fp-basic", 46, b"\x51"), "beyond the columns"),
        (patched("fp-basic", 46, b"\x12"), "truncated"),
        (patched("fp-basic", 47, struct.pack("<i", -(10**9) - 1)), "first point"),
        (patched("cp-slow", 28, b"\x00"), "AUTO"),
        (patched("cp-slow", 28, b"\x03"), "mode"),
        (patched("cp-slow", 44, struct.pack("<H", 10001)), "first point"),
        (patched("cp-slow", 44, struct.pack("<H", 100)), "speeds out of range"),
        (patched("cp-slow", 22, b"\x21"), "vehicle id"),
        (patched("mc-initiate", 28, b"\x03"), "command"),
        (patched("mc-initiate", 29, b"\x00"), "not AUTO"),
        (patched("mc-terminate", 29, b"\x01"), "returns to AUTO"),
        (patched("beacon", 34, struct.pack("<I", 0)), "radius"),
        (patched("beacon", 34, struct.pack("<I", 10**6 + 1)), "radius"),
        (patched("beacon", 22, b"\x00"), "intersection id"),
    ],
)
def test_malformed_datagrams_are_rejected(data: bytes, match: str) -> None:
    with pytest.raises(DecodeError, match=match):
        decode(data)


def test_widths_must_be_zero_for_short_paths() -> None:
    one = fp(points=np.array([[1.0, 2.0, 12.5]]))
    data = bytearray(encode(one))
    data[46] = 0x01
    with pytest.raises(DecodeError, match="fewer than 2 points"):
        decode(bytes(data))


def test_trailer_length_must_reach_the_end() -> None:
    data = bytes.fromhex(VECTORS["fp-auth"][1])
    with pytest.raises(DecodeError, match="trailer"):
        decode(data[:-1])
    with pytest.raises(DecodeError, match="trailer"):
        decode(data + b"\x00")


@pytest.mark.parametrize("value", [None, "cb01", 3, [0xCB, 1], 1.5])
def test_non_bytes_are_rejected(value: Any) -> None:
    with pytest.raises(DecodeError, match="expected bytes"):
        decode(value)


def test_wider_columns_than_needed_are_accepted() -> None:
    # fp-basic re-encoded with a 2-byte x column: same message, 3 bytes longer
    data = bytearray(FP[:46])
    data.append(0x12)  # x width 2, y 0, t 1
    data += FP[47:59]  # first point
    data += struct.pack("<3h", 115, 115, 115)
    data += bytes([100, 100, 100])
    assert_same(VECTORS["fp-basic"][0], decode(bytes(data)))


def test_every_decoded_vector_re_encodes_to_itself() -> None:
    for message, hex_ in VECTORS.values():
        assert encode(decode(bytes.fromhex(hex_))) == bytes.fromhex(hex_)
        assert_same(message, decode(encode(message)))
