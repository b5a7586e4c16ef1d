"""Golden test vectors: messages and their exact datagrams (also listed in ``protocol/SPEC.md``).

Every value is exactly representable on the wire (whole centimetres, whole
milliseconds of the run's time base, whole cm/s), so decoding a vector gives the
message back exactly, not just within the resolution.
"""

from __future__ import annotations

import math

import numpy as np

from protocol import (
    AutonomousPath,
    Command,
    CoordinatedPath,
    Flags,
    FuturePath,
    Header,
    Message,
    Mode,
    ModeCommand,
    RsuBeacon,
    VehicleLimits,
    VehiclePath,
)
from protocol.messages import FloatArray


def _a(*rows: tuple[float, float, float] | float) -> FloatArray:
    return np.array(rows, dtype=np.float64)


VECTORS: dict[str, tuple[Message, str]] = {
    # a straight eastbound future path: x deltas fit int8, y constant, 100 ms apart; a car's
    # limits (50 km/h, 1.5 m/s², 2.0 m/s² braking, 2.0 m/s² lateral)
    "fp-basic": (
        FuturePath(
            Header("car-a", 1, 12_345_000),
            -20.5,
            -1.75,
            11.5,
            0.0,
            4.5,
            1.8,
            Mode.AUTO,
            _a(
                (-20.5, -1.75, 12.345),
                (-19.35, -1.75, 12.445),
                (-18.2, -1.75, 12.545),
                (-17.05, -1.75, 12.645),
            ),
            VehicleLimits(13.89, 1.5, 2.0, 2.0),
        ),
        (
            "cb03010001000000a85ebc0000000000056361722d61fef7ffff51ffffff7e04"
            "0000c201b4006d050f141400040011fef7ffff51ffffff000000007373736464"
            "64"
        ),
    ),
    # an autonomous path with 2-byte deltas and a header time that is not whole milliseconds
    # (point times are: T_0 counts from floor(time_us / 1000) = 100000 ms),
    # from a truck (8 m/s, 1.0 m/s², 1.5 m/s² braking, 1.2 m/s² lateral)
    "ap-wide": (
        AutonomousPath(
            Header("car-b", 4_000_000_000, 100_000_250),
            1.75,
            -30.0,
            13.89,
            1.5708,
            4.5,
            1.8,
            Mode.C_SLOW,
            _a((1.75, -30.0, 100.0), (2.0, -26.0, 100.3), (1.5, -22.0, 100.6)),
            VehicleLimits(8.0, 1.0, 1.5, 1.2),
        ),
        (
            "cb03020000286beefae1f50500000000056361722d62af00000048f4ffff6d05"
            "5c3dc201b40020030a0f0c01030029af00000048f4ffff0000000019ce900190"
            "012c012c01"
        ),
    ),
    # the RSU slows car-b down: one target speed per point
    "cp-slow": (
        CoordinatedPath(
            Header("rsu-1", 42, 100_050_000),
            "car-b",
            Mode.C_SLOW,
            _a((1.75, -30.0, 100.05), (1.75, -29.0, 100.15), (1.75, -28.1, 100.25)),
            _a(10.0, 9.0, 8.0),
        ),
        (
            "cb0303002a00000050a4f60500000000057273752d31056361722d6201030054"
            "af00000048f4ffff00000000e803645a64649c9c"
        ),
    ),
    "mc-initiate": (
        ModeCommand(Header("rsu-1", 43, 100_050_000), "car-a", Command.INITIATE, Mode.C_FAST),
        ("cb0304002b00000050a4f60500000000057273752d31056361722d610102"),
    ),
    "mc-terminate": (
        ModeCommand(Header("rsu-1", 44, 120_000_000), "car-b", Command.TERMINATE, Mode.AUTO),
        ("cb0304002c000000000e270700000000057273752d31056361722d620200"),
    ),
    "beacon": (
        RsuBeacon(Header("rsu-1", 7, 5_000_000), "x-0", 5.0, -5.0, 150.0),
        ("cb03050007000000404b4c0000000000057273752d3103782d30f40100000cfeffff983a0000"),
    ),
    # one point, negative header time, an authentication trailer (scheme 1, 4 bytes), and
    # no declared limits (five zero bytes)
    "fp-auth": (
        FuturePath(
            Header("car_c", 0, -1_500_000, Flags.AUTH, bytes.fromhex("01deadbeef")),
            0.0,
            0.0,
            0.0,
            -3.1415,
            12.0,
            2.55,
            Mode.C_FAST,
            _a((0.0, 0.0, -1.5)),
        ),
        (
            "cb03010100000000a01ce9ffffffffff056361725f6300000000000000000000"
            "4985b004ff000000000000020100000000000000000000000000000104deadbe"
            "ef"
        ),
    ),
}
"""Name -> (message, datagram as hex)."""


def assert_same(a: Message, b: Message) -> None:
    """``a`` and ``b`` are the same message, exactly (arrays included)."""
    assert_close(a, b, position=0.0, time=0.0, speed=0.0, angle=0.0, accel=0.0)


def assert_close(
    a: Message,
    b: Message,
    *,
    position: float = 0.005 + 1e-6,
    time: float = 0.0005 + 1e-6,
    speed: float = 0.005 + 1e-9,
    angle: float = 0.5e-4 + 1e-9,
    accel: float = 0.05 + 1e-9,
) -> None:
    """``b`` is ``a`` within the wire resolution (defaults: 0.5 cm, 0.5 ms, 0.5 cm/s, 0.5e-4 rad,
    0.05 m/s² for declared accelerations).

    Headings are compared modulo 2 pi; exact comparison (all tolerances 0)
    compares them as numbers.
    """
    assert type(a) is type(b)
    assert a.header == b.header
    if isinstance(a, VehiclePath):
        assert isinstance(b, VehiclePath)
        assert abs(a.x - b.x) <= position and abs(a.y - b.y) <= position
        assert abs(a.speed - b.speed) <= speed
        if angle == 0.0:
            assert a.heading == b.heading
        else:
            assert abs(math.remainder(a.heading - b.heading, math.tau)) <= angle
        assert abs(a.length - b.length) <= position
        assert abs(a.width - b.width) <= position
        assert a.mode is b.mode
        _assert_limits(a.limits, b.limits, speed, accel)
        _assert_points(a.points, b.points, position, time)
    elif isinstance(a, CoordinatedPath):
        assert isinstance(b, CoordinatedPath)
        assert (a.vehicle, a.mode) == (b.vehicle, b.mode)
        _assert_points(a.points, b.points, position, time)
        assert a.speeds.shape == b.speeds.shape
        assert np.all(np.abs(a.speeds - b.speeds) <= speed)
    elif isinstance(a, RsuBeacon):
        assert isinstance(b, RsuBeacon)
        assert a.intersection == b.intersection
        assert abs(a.x - b.x) <= position and abs(a.y - b.y) <= position
        assert abs(a.radius - b.radius) <= position
    else:
        assert a == b


def _assert_limits(
    a: VehicleLimits | None, b: VehicleLimits | None, speed: float, accel: float
) -> None:
    if a is None or b is None:
        assert a is b
        return
    assert abs(a.v_max - b.v_max) <= speed
    for name in ("accel", "decel", "lat_accel"):
        assert abs(getattr(a, name) - getattr(b, name)) <= accel, name


def _assert_points(a: FloatArray, b: FloatArray, position: float, time: float) -> None:
    assert a.shape == b.shape
    assert np.all(np.abs(a[:, :2] - b[:, :2]) <= position)
    assert np.all(np.abs(a[:, 2] - b[:, 2]) <= time)
