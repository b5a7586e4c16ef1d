"""Binary codec of crosspath's V2X messages (layout in ``protocol/SPEC.md``).

Plain ``struct`` fields, little-endian, at fixed offsets after each id; a vehicle
path declares the car's limits (``VehicleLimits``: top speed, acceleration, braking,
lateral acceleration) in five bytes, all zero when undeclared; path
points are fixed-point (1 cm, 1 ms) and delta coded in columns whose width (0,
1 or 2 bytes) the encoder picks per message, packed and unpacked in one go (in C,
else with numpy; never a per-point Python loop). No msgpack: every field has a known type, so
tags and map keys would only add bytes and time.

``decode`` is the trust boundary: whatever a peer sends, it returns a valid
message or raises ``DecodeError`` (a ``ValueError``), never anything else, and
it never allocates more than a few kilobytes (a datagram holds at most
``max_points`` points). Everything ``decode`` accepts, ``encode`` accepts too.

Speed (``crosspath bench codec``; issue 14's target is 25x stdlib JSON, 8 µs for
encode + decode of a 120-point path). An unsigned vehicle path from a known sender
is encoded and decoded with one ``struct`` call for header, sender, state and first
point (``_encode_vehicle_path_fast``, ``_decode_vehicle_path_fast``; anything unusual
goes the general way, which explains refusals), and its points with one call into
the C speed-ups (``protocol/_speedups.c``: ``vehicle_path`` quantises the state and
packs the points, ``unpack`` returns the read-only (N, 3) array, ``build`` sets a
decoded message's slots): about 7 µs. They are optional: built at install when a C
compiler is there, else (or after ``use_speedups(False)``) the numpy path runs, same
bytes, about 23 µs: a dozen numpy calls each way of 0.3-1 µs each, whatever the
size of a path (encoding works on the flat row-major array and checks delta widths
on the bytes of one int16 cast, ``_points_numpy``; decoding accumulates once over
the (N, 3) rows and scales them in one same-shape division, ``_vehicle_rows_numpy``).
Format 3 quantises every path time as a whole millisecond of the run, so neither
side shifts the t column by the header time. Ids and
delta-column layouts, once validated, are cached (at most ``_CACHE_MAX`` entries
each, cleared when full, so a peer cannot grow them), and ``decode`` builds the
message without running the dataclass ``__init__`` (``_constructor``): every field
is validated here and every array is fresh and read-only, which is all that
``__init__`` would ensure.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import re
import struct
from collections.abc import Callable
from typing import Any, Final, TypeVar

import numpy as np

from protocol.keys import ID_CHARS, MAX_ID_LEN, is_valid_id
from protocol.messages import (
    FORMAT_VERSION,
    MAX_DATAGRAM,
    AutonomousPath,
    Command,
    CoordinatedPath,
    Flags,
    FloatArray,
    FuturePath,
    Header,
    Kind,
    Message,
    Mode,
    ModeCommand,
    RsuBeacon,
    VehicleLimits,
    VehiclePath,
)

try:  # the C speed-ups (protocol/_speedups.c), built at install when there is a compiler
    from protocol import _speedups as _speedups_module
except ImportError:  # no compiler at install: the numpy path, same bytes
    _speedups_module = None  # type: ignore[assignment]

_C_POINTS: Any = _speedups_module
"""``protocol._speedups`` when built and in use, else None (``use_speedups``)."""


def speedups_available() -> bool:
    """Whether the codec's C speed-ups were built (``protocol/_speedups.c``)."""
    return _speedups_module is not None


def use_speedups(enabled: bool) -> bool:
    """Run the codec with its C speed-ups (when built) or on its numpy path; the previous
    setting. Both give the same bytes and messages: this exists to measure and test each."""
    global _C_POINTS
    previous = _C_POINTS is not None
    on = enabled and _speedups_module is not None
    _C_POINTS = _speedups_module if on else None
    _NEW.update(_NEW_BY_SPEEDUPS[on])
    return previous


MAGIC: Final = 0xCB
"""First byte of every crosspath datagram."""

MAX_SPEED_MPS: Final = 100.0
"""Largest speed accepted anywhere [m/s]; more is absurd for a road vehicle."""

MAX_COORD_M: Final = 10_000_000.0
"""Largest |x| or |y| accepted [m] (10,000 km: any local metric frame)."""

MAX_TIME_US: Final = 2**53
"""Largest |generation time| accepted [µs] (285 years; exact as a float)."""

MAX_LENGTH_M: Final = 50.0
"""Longest vehicle accepted [m]."""

MAX_WIDTH_M: Final = 10.0
"""Widest vehicle accepted [m]."""

MAX_ACCEL_MPS2: Final = 25.5
"""Largest acceleration, comfortable braking or lateral acceleration a car may declare
in its ``VehicleLimits`` [m/s²] (one byte of 0.1 m/s²; 2.6 g, beyond any tyre)."""

MAX_RADIUS_M: Final = 10_000.0
"""Largest RSU coverage radius accepted [m]."""

MAX_AUTH_LEN: Final = 256
"""Longest ``Header.auth`` (scheme byte + up to 255 bytes of data)."""

MAX_STEP_M: Final = 327.67
"""Largest change of x or y between consecutive path points [m] (int16 centimetres)."""

MAX_STEP_S: Final = 65.535
"""Largest time between consecutive path points [s] (uint16 milliseconds)."""

_KNOWN_FLAGS: Final = int(Flags.AUTH)
_I32_MIN: Final = -(2**31)
_I32_MAX: Final = 2**31 - 1
_MAX_COORD_CM: Final = round(MAX_COORD_M * 100)
_MAX_COORD_F: Final = float(_MAX_COORD_CM)
_MAX_SPEED_CM_S: Final = round(MAX_SPEED_MPS * 100)
_MAX_HEADING: Final = 31416  # 1e-4 rad, ceil(pi * 1e4)
_MAX_LENGTH_CM: Final = round(MAX_LENGTH_M * 100)
_MAX_WIDTH_CM: Final = round(MAX_WIDTH_M * 100)
_MAX_ACCEL_DM: Final = round(MAX_ACCEL_MPS2 * 10)  # 0.1 m/s² units
_NO_LIMITS: Final = (0, 0, 0, 0)  # limits not declared
_MAX_RADIUS_CM: Final = round(MAX_RADIUS_M * 100)

# header: magic, version, kind, flags, seq, time_us, sender length (then the sender id)
_HEAD: Final = struct.Struct("<BBBBIqB")
# future/autonomous path state: x, y, speed, heading, length, width, then the limits
# v_max [cm/s], accel, decel, lat_accel [0.1 m/s²], then mode, n, widths
_STATE: Final = struct.Struct("<iiHhHHHBBBBHB")
# coordinated path after its vehicle id: mode, n, widths
_CP_STATE: Final = struct.Struct("<BHB")
_FIRST3: Final = struct.Struct("<iii")  # first point: x [cm], y [cm], t [ms after header time]
_FIRST4: Final = struct.Struct("<iiiH")  # ... and speed [cm/s]
_COMMAND: Final = struct.Struct("<BB")  # command, mode
_BEACON: Final = struct.Struct("<iiI")  # x [cm], y [cm], radius [cm]
_U8: Final = struct.Struct("<B")
_TRAILER: Final = struct.Struct("<BB")  # scheme, length

_ID_BYTES_RE: Final = re.compile(rf"[{ID_CHARS}]{{1,{MAX_ID_LEN}}}".encode("ascii"))

# delta columns: x, y, t, speed. Width code c in 0..2 means c bytes per delta.
_T_COLUMN: Final = 2
_DTYPES_SIGNED: Final[dict[int, np.dtype[Any]]] = {1: np.dtype("<i1"), 2: np.dtype("<i2")}
_DTYPES_UNSIGNED: Final[dict[int, np.dtype[Any]]] = {1: np.dtype("<u1"), 2: np.dtype("<u2")}
_SCALE3: Final = np.array([[100.0], [100.0], [1000.0]])  # m, m, s <-> cm, cm, ms
_SCALE_ROW: Final = _SCALE3.reshape(3)
_COLUMN_NAMES: Final = ("x", "y", "t", "speed")
# bounds in wire units (cm, ms after header time, cm/s) of the first point (all speeds)
_COL_LO: Final = (-_MAX_COORD_CM, -_MAX_COORD_CM, _I32_MIN, 0)
_COL_HI: Final = (_MAX_COORD_CM, _MAX_COORD_CM, _I32_MAX, _MAX_SPEED_CM_S)

_HEADER_MAX: Final = _HEAD.size + MAX_ID_LEN
_VP_FIXED: Final = _STATE.size + _FIRST3.size
_CP_FIXED: Final = 1 + MAX_ID_LEN + _CP_STATE.size + _FIRST4.size


class EncodeError(ValueError):
    """A message that cannot go on the wire (bad id, NaN, out of range, too big)."""


class DecodeError(ValueError):
    """A datagram that is not a valid crosspath message; the only error ``decode`` raises."""


_SIGNED_TRAILER: Final = 79
"""Room kept for a digest-form scheme-1 trailer (``protocol.auth.DIGEST_TRAILER_LEN``):
a signed worst-case message still fits one datagram (SPEC.md 3, Capacity)."""


def _fit(fixed: int, row: int) -> int:
    return (MAX_DATAGRAM - _HEADER_MAX - fixed - _SIGNED_TRAILER) // row + 1


_MAX_POINTS: Final[dict[Kind, int]] = {
    Kind.FUTURE_PATH: _fit(_VP_FIXED, 6),
    Kind.AUTONOMOUS_PATH: _fit(_VP_FIXED, 6),
    Kind.COORDINATED_PATH: _fit(_CP_FIXED, 8),
    Kind.MODE_COMMAND: 0,
    Kind.RSU_BEACON: 0,
}


def max_points(kind: Kind | int) -> int:
    """Most path points a message of ``kind`` may carry (0 for kinds without points).

    Every message with at most this many points fits one ``MAX_DATAGRAM``
    datagram whatever its values, assuming the longest ids (32 bytes), 2-byte
    deltas in every column and a digest-form scheme-1 signature trailer (79 bytes).
    Messages with more points are refused by both ``encode`` and ``decode``;
    a longer trailer can still push a full message over the limit (``EncodeError``).
    """
    try:
        return _MAX_POINTS[Kind(kind)]
    except ValueError:
        raise ValueError(f"unknown message kind {kind!r}") from None


_CACHE_MAX: Final = 1024
"""Entries of each codec cache (ids, delta layouts); a full cache is emptied."""

_K = TypeVar("_K")
_V = TypeVar("_V")


def _remember(cache: dict[_K, _V], key: _K, value: _V) -> _V:
    """Store ``value`` under ``key``, emptying ``cache`` first when full: whatever peers
    send, no cache holds more than ``_CACHE_MAX`` entries."""
    if len(cache) >= _CACHE_MAX:
        cache.clear()
    cache[key] = value
    return value


# ---------------------------------------------------------------- encoding


_ID_CACHE: Final[dict[str, bytes]] = {}
"""Ids already validated and encoded; a car encodes the same few ids at 10 Hz."""


def _id_bytes(value: str, what: str) -> bytes:
    if type(value) is str:
        known = _ID_CACHE.get(value)
        if known is not None:
            return known
    if not is_valid_id(value):
        raise EncodeError(
            f"invalid {what} {value!r}: need 1..{MAX_ID_LEN} characters from [{ID_CHARS}]"
        )
    data = value.encode("ascii")
    return _remember(_ID_CACHE, value, data) if type(value) is str else data


def _fixed(value: float, scale: float, lo: int, hi: int, what: str, unit: str) -> int:
    """``value`` in wire units (``value * scale`` rounded half to even), range checked."""
    v = float(value)
    if not math.isfinite(v):
        raise EncodeError(f"{what} is {v}: NaN and infinities cannot be encoded")
    q = round(v * scale)
    if not lo <= q <= hi:
        raise EncodeError(f"{what} {v} {unit} is outside [{lo / scale}, {hi / scale}] {unit}")
    return q


def _header(kind: Kind, header: Header) -> tuple[bytes, bytes]:
    """The header bytes and the trailer bytes (empty without ``Flags.AUTH``)."""
    sender = _id_bytes(header.sender, "sender id")
    seq = operator.index(header.seq)
    if not 0 <= seq <= 0xFFFF_FFFF:
        raise EncodeError(f"sequence number {seq} does not fit 32 bits unsigned")
    time_us = operator.index(header.time_us)
    if not -MAX_TIME_US <= time_us <= MAX_TIME_US:
        raise EncodeError(f"generation time {time_us} µs is beyond ±2**53 µs")
    flags = operator.index(header.flags)
    if flags & ~_KNOWN_FLAGS or flags < 0:
        raise EncodeError(f"unknown header flag bits {flags:#x}")
    auth = header.auth if type(header.auth) is bytes else bytes(header.auth)
    if bool(flags & Flags.AUTH) != bool(auth):
        raise EncodeError("header.auth must be non-empty exactly when flags has Flags.AUTH")
    trailer = b""
    if auth:
        if len(auth) > MAX_AUTH_LEN:
            raise EncodeError(f"auth trailer of {len(auth)} bytes; at most {MAX_AUTH_LEN}")
        trailer = _TRAILER.pack(auth[0], len(auth) - 1) + auth[1:]
    head = _HEAD.pack(MAGIC, FORMAT_VERSION, kind, flags, seq, time_us, len(sender))
    return head + sender, trailer


_SIGN: Final = bytes(0xFF if b & 0x80 else 0 for b in range(256))
"""``bytes.translate`` table: each byte to the byte that sign-extends it (0x00 or 0xFF)."""

_ZEROS: Final = bytes(max(_fit(_VP_FIXED, 6), _fit(_CP_FIXED, 8)))
_I2: Final = np.dtype("<i2")
_FAST_SQ_LIMIT: Final = 32767.0**2
"""Sum of squared deltas [wire units²] under which every delta fits an int16 exactly."""

_TILES: Final[dict[int, FloatArray]] = {}
"""Points -> the wire scale repeated per point (x, y, t of every row), read-only."""


def _tiled_scale(n: int) -> FloatArray:
    """``_SCALE_ROW`` repeated ``n`` times: one 1-D multiply or divide scales a whole path."""
    tile = _TILES.get(n)
    if tile is None:
        tile = _remember(_TILES, n, _read_only(np.tile(_SCALE_ROW, n)))
    return tile


_ROWS_SCALE: Final[dict[int, FloatArray]] = {}
"""Points -> the wire scale as an (N, 3) array, read-only."""


def _scale_rows(n: int) -> FloatArray:
    """``_SCALE_ROW`` in each of ``n`` rows: one same-shape divide scales a whole path."""
    rows = _ROWS_SCALE.get(n)
    if rows is None:
        rows = _remember(_ROWS_SCALE, n, _read_only(np.tile(_SCALE_ROW, (n, 1))))
    return rows


def _points(
    kind: Kind, points: FloatArray, speeds: FloatArray | None, time_us: int
) -> tuple[int, int, bytes]:
    """Point count, widths byte and the packed points (first row + delta columns).

    Vehicle paths go to the C packer (``protocol/_speedups.c``) when it was built, else
    to ``_points_numpy``; whatever either declines goes to ``_points_checked``."""
    n = points.shape[0]
    if _C_POINTS is None or speeds is not None or not 2 <= n <= _MAX_POINTS[kind]:
        return _points_numpy(kind, points, speeds, time_us)
    packed: tuple[int, bytes] | None = _C_POINTS.pack(points, time_us // 1000, _MAX_COORD_F)
    if packed is None:
        return _points_numpy(kind, points, speeds, time_us)
    return n, packed[0], packed[1]


def _points_numpy(
    kind: Kind, points: FloatArray, speeds: FloatArray | None, time_us: int
) -> tuple[int, int, bytes]:
    """``_points`` without the C packer: the numpy fast path of vehicle paths
    (``_points_checked`` does the rest and explains every refusal). Five numpy calls on
    the row-major path (scale, round, deltas, one dot product that bounds every delta,
    one int16 cast), then bytes slicing: the low and high bytes of the int16 deltas,
    split into columns, are the wire's 1-byte columns, and a delta fits one byte iff its
    high byte sign-extends its low byte (``bytes.translate``), instead of a min/max
    reduction and a cast per column. Same bytes as ``_points_checked``
    (``tests/protocol/test_fast_points.py``).
    """
    n = points.shape[0]
    if speeds is not None or not 2 <= n <= _MAX_POINTS[kind] or points.shape != (n, 3):
        return _points_checked(kind, points, speeds, time_us)
    q = np.multiply(points.reshape(-1), _tiled_scale(n))  # x, y [cm], t [ms] per row
    np.rint(q, q)
    x0, y0, t0 = q[:3].tolist()
    t0 -= time_us // 1000  # exact: whole numbers below 2**53
    deltas = np.subtract(q[3:], q[:-3])
    if not (
        -_MAX_COORD_CM <= x0 <= _MAX_COORD_CM
        and -_MAX_COORD_CM <= y0 <= _MAX_COORD_CM
        and _I32_MIN <= t0 <= _I32_MAX
        and np.dot(deltas, deltas) <= _FAST_SQ_LIMIT  # NaN fails too
    ):
        return _points_checked(kind, points, speeds, time_us)
    small = deltas.astype(_I2)  # rows of x, y, t; exact, every |delta| <= 32767
    raw = small.tobytes()
    low, high = raw[0::2], raw[1::2]
    zero = _ZEROS[: n - 1]
    parts = [_FIRST3.pack(int(x0), int(y0), int(t0))]
    widths = 0
    if high == low.translate(_SIGN):  # every delta fits one signed byte
        cx, cy, ct = low[0::3], low[1::3], low[2::3]
        if cx != zero:
            parts.append(cx)
            widths = 0x01
        if cy != zero:
            parts.append(cy)
            widths |= 0x04
        if ct != zero:
            if ct.translate(_SIGN) != zero:
                return _points_checked(kind, points, speeds, time_us)  # time goes back
            parts.append(ct)
            widths |= 0x10
        return n, widths, b"".join(parts)
    for c in range(3):
        c0, c1 = low[c::3], high[c::3]
        if c == _T_COLUMN:  # unsigned: 0..32767 here
            if c1.translate(_SIGN) != zero:
                return _points_checked(kind, points, speeds, time_us)  # time goes back
            code = 2 if c1 != zero else 1 if c0 != zero else 0
        elif c1 == c0.translate(_SIGN):
            code = 1 if c0 != zero else 0
        else:
            code = 2
        if code == 1:
            parts.append(c0)
        elif code == 2:
            parts.append(small[c::3].tobytes())
        widths |= code << (2 * c)
    return n, widths, b"".join(parts)


def _points_checked(
    kind: Kind, points: FloatArray, speeds: FloatArray | None, time_us: int
) -> tuple[int, int, bytes]:
    """Point count, widths byte and the packed points, every case (``_points`` is faster)."""
    n = int(points.shape[0])
    cap = _MAX_POINTS[kind]
    if n > cap:
        raise EncodeError(f"{n} points: a {kind.name.lower()} carries at most {cap} (one datagram)")
    if n == 0:
        return 0, 0, b""
    if points.shape != (n, 3):
        raise EncodeError(f"points must have shape (N, 3), not {points.shape}")
    ncols = 3 if speeds is None else 4
    # column-major wire units: x [cm], y [cm], t [ms after the header time], speed [cm/s]
    cols = np.empty((ncols, n))
    np.multiply(points.T, _SCALE3, cols[:3])  # t: whole ms of the run's time base
    if speeds is not None:
        np.multiply(speeds, 100.0, cols[3])
    np.rint(cols, cols)
    first: list[float] = cols[:, 0].tolist()
    first[_T_COLUMN] -= time_us // 1000  # the first time goes after the header's ms
    for c in range(ncols):
        # NaN fails both comparisons, infinities one
        if not _COL_LO[c] <= first[c] <= _COL_HI[c]:
            _raise_bad_column(points, speeds, c)
    if speeds is not None:
        lo, hi = float(np.minimum.reduce(cols[3])), float(np.maximum.reduce(cols[3]))
        if not (lo >= 0 and hi <= _MAX_SPEED_CM_S):
            _raise_bad_column(points, speeds, 3)
    parts = [(_FIRST3 if ncols == 3 else _FIRST4).pack(*map(int, first))]
    widths = 0
    if n > 1:
        deltas = np.subtract(cols[:, 1:], cols[:, :-1])  # exact: integers far below 2**53
        dlo: list[float] = np.minimum.reduce(deltas, 1).tolist()
        dhi: list[float] = np.maximum.reduce(deltas, 1).tolist()
        for c in range(ncols):
            code = _width_code(points, speeds, c, dlo[c], dhi[c])
            if code:
                dtypes = _DTYPES_UNSIGNED if c == _T_COLUMN else _DTYPES_SIGNED
                parts.append(deltas[c].astype(dtypes[code]).tobytes())
                widths |= code << (2 * c)
    return n, widths, b"".join(parts)


def _width_code(
    points: FloatArray, speeds: FloatArray | None, column: int, lo: float, hi: float
) -> int:
    """The narrowest width code for deltas in [lo, hi] of ``column``."""
    if lo == 0 and hi == 0:
        return 0
    if not (math.isfinite(lo) and math.isfinite(hi)):
        _raise_bad_column(points, speeds, column)
    if column == _T_COLUMN:
        if lo < 0:
            raise EncodeError("point times go backwards: times must be non-decreasing")
        if hi <= 0xFF:
            return 1
        if hi <= 0xFFFF:
            return 2
        raise EncodeError(
            f"{hi / 1000:.3f} s between consecutive points: at most 65.535 s (uint16 ms)"
        )
    if lo >= -128 and hi <= 127:
        return 1
    if lo >= -32768 and hi <= 32767:
        return 2
    unit = "m/s" if column == 3 else "m"
    raise EncodeError(
        f"{_COLUMN_NAMES[column]} changes by {max(-lo, hi) / 100:.2f} {unit} between "
        f"consecutive points: at most 327.67 {unit} (int16 centi-units)"
    )


def _raise_bad_column(points: FloatArray, speeds: FloatArray | None, column: int) -> None:
    values = points[:, column] if column < 3 else speeds
    if values is not None and not np.isfinite(values).all():
        raise EncodeError(f"path {_COLUMN_NAMES[column]} contains NaN or infinity")
    if column == _T_COLUMN:
        raise EncodeError("the first point's time is more than 2**31 ms away from the header time")
    if column == 3:
        raise EncodeError(f"path speeds must lie in [0, {MAX_SPEED_MPS}] m/s")
    raise EncodeError(f"the first point's {_COLUMN_NAMES[column]} is beyond ±{MAX_COORD_M} m")


def _encode_vehicle_path(kind: Kind, m: VehiclePath) -> list[bytes]:
    head, trailer = _header(kind, m.header)
    n, widths, packed = _points(kind, m.points, None, m.header.time_us)
    mode = _mode(m.mode)
    heading = float(m.heading)
    if math.isfinite(heading) and abs(heading) > _MAX_HEADING / 1e4:
        heading = math.remainder(heading, math.tau)  # into [-pi, pi]
    state = _STATE.pack(*_vehicle_state(m, heading), *_limits_wire(m.limits), mode, n, widths)
    return [head, state, packed, trailer]


_LIMITS_WIRE: Final[dict[VehicleLimits, tuple[int, int, int, int]]] = {}
"""Limits already validated and quantised; a car declares the same ones at 10 Hz."""


def _limits_wire(limits: VehicleLimits | None) -> tuple[int, int, int, int]:
    """v_max [cm/s], accel, decel, lat_accel [0.1 m/s²] of ``limits``; zeros for None."""
    if limits is None:
        return _NO_LIMITS
    if type(limits) is not VehicleLimits:
        raise EncodeError(f"limits must be VehicleLimits or None, not {type(limits).__name__}")
    known = _LIMITS_WIRE.get(limits)
    if known is not None:
        return known
    wire = (
        _fixed(limits.v_max, 100.0, 1, _MAX_SPEED_CM_S, "limits.v_max", "m/s"),
        _fixed(limits.accel, 10.0, 1, _MAX_ACCEL_DM, "limits.accel", "m/s²"),
        _fixed(limits.decel, 10.0, 1, _MAX_ACCEL_DM, "limits.decel", "m/s²"),
        _fixed(limits.lat_accel, 10.0, 1, _MAX_ACCEL_DM, "limits.lat_accel", "m/s²"),
    )
    return _remember(_LIMITS_WIRE, limits, wire)


def _state_in_range(x: int, y: int, speed: int, h: int, length: int, width: int) -> bool:
    """A vehicle state in wire units (cm, cm/s, 1e-4 rad) fits its fields."""
    return (
        -_MAX_COORD_CM <= x <= _MAX_COORD_CM
        and -_MAX_COORD_CM <= y <= _MAX_COORD_CM
        and 0 <= speed <= _MAX_SPEED_CM_S
        and -_MAX_HEADING <= h <= _MAX_HEADING
        and 1 <= length <= _MAX_LENGTH_CM
        and 1 <= width <= _MAX_WIDTH_CM
    )


def _vehicle_state(m: VehiclePath, heading: float) -> tuple[int, ...]:
    """x, y, speed, heading, length, width of ``m`` in wire units, range checked."""
    try:  # fast path: one expression; any failure is explained by ``_fixed`` below
        x, y = round(float(m.x) * 100.0), round(float(m.y) * 100.0)
        speed, h = round(float(m.speed) * 100.0), round(heading * 1e4)
        length, width = round(float(m.length) * 100.0), round(float(m.width) * 100.0)
        if _state_in_range(x, y, speed, h, length, width):
            return x, y, speed, h, length, width
    except (ValueError, OverflowError):
        pass
    return (
        _fixed(m.x, 100.0, -_MAX_COORD_CM, _MAX_COORD_CM, "x", "m"),
        _fixed(m.y, 100.0, -_MAX_COORD_CM, _MAX_COORD_CM, "y", "m"),
        _fixed(m.speed, 100.0, 0, _MAX_SPEED_CM_S, "speed", "m/s"),
        _fixed(heading, 1e4, -_MAX_HEADING, _MAX_HEADING, "heading", "rad"),
        _fixed(m.length, 100.0, 1, _MAX_LENGTH_CM, "length", "m"),
        _fixed(m.width, 100.0, 1, _MAX_WIDTH_CM, "width", "m"),
    )


def _encode_future_path(m: Any) -> list[bytes]:
    return _encode_vehicle_path(Kind.FUTURE_PATH, m)


def _encode_autonomous_path(m: Any) -> list[bytes]:
    return _encode_vehicle_path(Kind.AUTONOMOUS_PATH, m)


def _encode_coordinated_path(m: CoordinatedPath) -> list[bytes]:
    head, trailer = _header(Kind.COORDINATED_PATH, m.header)
    vehicle = _id_bytes(m.vehicle, "vehicle id")
    mode = _mode(m.mode)
    if mode is Mode.AUTO:
        raise EncodeError("a coordinated path has mode C_SLOW or C_FAST, not AUTO")
    if m.speeds.shape != (m.points.shape[0],):
        raise EncodeError("a coordinated path needs one speed per point")
    n, widths, packed = _points(Kind.COORDINATED_PATH, m.points, m.speeds, m.header.time_us)
    state = _U8.pack(len(vehicle)) + vehicle + _CP_STATE.pack(mode, n, widths)
    return [head, state, packed, trailer]


def _encode_mode_command(m: ModeCommand) -> list[bytes]:
    head, trailer = _header(Kind.MODE_COMMAND, m.header)
    vehicle = _id_bytes(m.vehicle, "vehicle id")
    command = Command(m.command)
    mode = _mode(m.mode)
    _check_command(command, mode, EncodeError)
    body = _U8.pack(len(vehicle)) + vehicle + _COMMAND.pack(command, mode)
    return [head, body, trailer]


def _encode_rsu_beacon(m: RsuBeacon) -> list[bytes]:
    head, trailer = _header(Kind.RSU_BEACON, m.header)
    intersection = _id_bytes(m.intersection, "intersection id")
    body = _BEACON.pack(
        _fixed(m.x, 100.0, -_MAX_COORD_CM, _MAX_COORD_CM, "x", "m"),
        _fixed(m.y, 100.0, -_MAX_COORD_CM, _MAX_COORD_CM, "y", "m"),
        _fixed(m.radius, 100.0, 1, _MAX_RADIUS_CM, "radius", "m"),
    )
    return [head, _U8.pack(len(intersection)) + intersection + body, trailer]


def _mode(value: Mode | int) -> Mode:
    mode = _MODES.get(value)
    if mode is None:
        raise EncodeError(f"invalid mode {value!r}")
    return mode


def _check_command(command: Command, mode: Mode, error: type[ValueError]) -> None:
    if command is Command.INITIATE and mode is Mode.AUTO:
        raise error("an INITIATE command targets C_SLOW or C_FAST, not AUTO")
    if command is Command.TERMINATE and mode is not Mode.AUTO:
        raise error(f"a TERMINATE command returns to AUTO, not {mode.name}")


_ENCODERS: Final[dict[type, Callable[[Any], list[bytes]]]] = {
    FuturePath: _encode_future_path,
    AutonomousPath: _encode_autonomous_path,
    CoordinatedPath: _encode_coordinated_path,
    ModeCommand: _encode_mode_command,
    RsuBeacon: _encode_rsu_beacon,
}


_VP_PREFIX: Final[dict[int, struct.Struct]] = {
    size: struct.Struct(f"<BBBBIqB{size}siiHhHHHBBBBHB") for size in range(1, MAX_ID_LEN + 1)
}
"""Sender id length -> header, sender id and vehicle path state in one ``struct``."""

_VP_KINDS: Final[dict[type, Kind]] = {
    FuturePath: Kind.FUTURE_PATH,
    AutonomousPath: Kind.AUTONOMOUS_PATH,
}


def _encode_vehicle_path_fast(kind: Kind, m: VehiclePath) -> bytes | None:
    """The datagram of an unsigned vehicle path with a known sender id, in one ``struct``
    call besides its points; None for anything unusual, which ``_encode_vehicle_path``
    then encodes or refuses with its own explanation. Same bytes as that function."""
    h = m.header
    sender = _ID_CACHE.get(h.sender) if type(h.sender) is str else None
    seq, time_us = h.seq, h.time_us
    mode = _MODES.get(m.mode)
    if (
        sender is None
        or mode is None
        or h.flags != 0
        or h.auth
        or type(seq) is not int
        or type(time_us) is not int
        or not 0 <= seq <= 0xFFFF_FFFF
        or not -MAX_TIME_US <= time_us <= MAX_TIME_US
    ):
        return None
    limits = m.limits
    wire = _NO_LIMITS if limits is None else _LIMITS_WIRE.get(limits)
    if wire is None:
        return None
    points = m.points
    done: tuple[int, int, int, int, int, int, int, bytes] | None = (
        None
        if _C_POINTS is None or not 2 <= len(points) <= _MAX_POINTS[kind]
        else _C_POINTS.vehicle_path(
            points, time_us // 1000, _MAX_COORD_F, m.x, m.y, m.speed, m.heading, m.length, m.width
        )
    )
    if done is not None:
        x, y, speed, heading, length, width, widths, packed = done
        n = len(points)
    else:
        try:
            x, y = round(float(m.x) * 100.0), round(float(m.y) * 100.0)
            speed, heading = round(float(m.speed) * 100.0), round(float(m.heading) * 1e4)
            length, width = round(float(m.length) * 100.0), round(float(m.width) * 100.0)
        except (ValueError, OverflowError, TypeError):
            return None
        n, widths, packed = _points(kind, points, None, time_us)
    if not _state_in_range(x, y, speed, heading, length, width):
        return None
    lv, la, ld, ll = wire
    head = _VP_PREFIX[len(sender)].pack(
        MAGIC, FORMAT_VERSION, kind, 0, seq, time_us, len(sender), sender,
        x, y, speed, heading, length, width, lv, la, ld, ll, mode, n, widths,
    )  # fmt: skip
    return head + packed  # at most 49 + 25 + 12 + 215 * 6 bytes: always fits


def encode(message: Message) -> bytes:
    """The datagram of ``message``; ``EncodeError`` if it is invalid or exceeds ``MAX_DATAGRAM``."""
    kind = _VP_KINDS.get(type(message))
    if kind is not None:
        try:
            fast = _encode_vehicle_path_fast(kind, message)  # type: ignore[arg-type]
        except EncodeError:
            raise
        except (TypeError, ValueError, AttributeError, OverflowError, struct.error) as exc:
            raise EncodeError(f"cannot encode {type(message).__name__}: {exc}") from exc
        if fast is not None:
            return fast
    encoder = _ENCODERS.get(type(message))
    if encoder is None:
        for cls, candidate in _ENCODERS.items():
            if isinstance(message, cls):
                encoder = candidate
                break
        else:
            raise EncodeError(f"not a crosspath message: {type(message).__name__}")
    try:
        data = b"".join(encoder(message))
    except EncodeError:
        raise
    except (TypeError, ValueError, AttributeError, OverflowError, struct.error) as exc:
        raise EncodeError(f"cannot encode {type(message).__name__}: {exc}") from exc
    if len(data) > MAX_DATAGRAM:
        raise EncodeError(
            f"{type(message).__name__} from {message.header.sender!r} needs {len(data)} bytes, "
            f"more than one {MAX_DATAGRAM}-byte datagram"
        )
    return data


# ---------------------------------------------------------------- decoding

_KINDS: Final = {int(k): k for k in Kind}
_MODES: Final = {int(m): m for m in Mode}
_COMMANDS: Final = {int(c): c for c in Command}


_ID_STRS: Final[dict[bytes, str]] = {}
"""Ids already checked on receipt; a daemon hears the same few senders at 10 Hz."""


def _read_id(buf: bytes, off: int, length: int, what: str) -> str:
    end = off + length
    if not 1 <= length <= MAX_ID_LEN or end > len(buf):
        raise DecodeError(f"{what}: bad length {length} at offset {off}")
    raw = buf[off:end]
    known = _ID_STRS.get(raw)
    if known is not None:
        return known
    if _ID_BYTES_RE.fullmatch(raw) is None:
        raise DecodeError(f"{what}: bytes outside [{ID_CHARS}]")
    return _remember(_ID_STRS, raw, raw.decode("ascii"))


_Plan = tuple[tuple[int, np.dtype[Any], int], ...]
_PLANS: Final[dict[tuple[int, int, int], _Plan]] = {}
"""(points, widths byte, columns) -> the delta columns on the wire: (column, dtype, bytes)."""


_PLAN_BYTES: Final[dict[_Plan, int]] = {}
"""Delta plan -> the bytes its columns take (filled as plans are made)."""


def _delta_plan(n: int, widths: int, ncols: int) -> _Plan:
    """Which columns carry deltas, as what, and how many bytes each; validates ``widths``."""
    plan = _PLANS.get((n, widths, ncols))
    if plan is not None:
        return plan
    if widths >> (2 * ncols):
        raise DecodeError(f"widths byte {widths:#04x} has bits set beyond the columns")
    if n <= 1 and widths:
        raise DecodeError("widths byte must be 0 for paths of fewer than 2 points")
    columns: list[tuple[int, np.dtype[Any], int]] = []
    for c in range(ncols):
        code = (widths >> (2 * c)) & 3
        if code == 3:
            raise DecodeError(f"reserved width code 3 for column {_COLUMN_NAMES[c]}")
        if code:
            dtypes = _DTYPES_UNSIGNED if c == _T_COLUMN else _DTYPES_SIGNED
            columns.append((c, dtypes[code], (n - 1) * code))
    plan = tuple(columns)
    if len(_PLAN_BYTES) >= _CACHE_MAX:
        _PLAN_BYTES.clear()
    _PLAN_BYTES[plan] = sum(size for _, _, size in plan)
    return _remember(_PLANS, (n, widths, ncols), plan)


def _read_only(arr: FloatArray) -> FloatArray:
    arr.setflags(write=False)
    return arr


_NO_POINTS: Final = _read_only(np.empty((0, 3)))
_NO_SPEEDS: Final = _read_only(np.empty(0))


def _read_points(
    buf: bytes, off: int, kind: Kind, n: int, widths: int, ncols: int, time_us: int
) -> tuple[FloatArray, FloatArray | None, int]:
    """Points (N, 3) in metres and seconds, speeds [m/s] if ``ncols`` is 4, next offset."""
    if n > _MAX_POINTS[kind]:
        raise DecodeError(f"{n} points: more than the {_MAX_POINTS[kind]} that fit a datagram")
    plan = _delta_plan(n, widths, ncols)
    if n == 0:
        return _NO_POINTS, (None if ncols == 3 else _NO_SPEEDS), off
    first_struct = _FIRST3 if ncols == 3 else _FIRST4
    first = first_struct.unpack_from(buf, off)
    off += first_struct.size
    for c in range(ncols):
        if not _COL_LO[c] <= first[c] <= _COL_HI[c]:
            raise DecodeError(f"first point: {_COLUMN_NAMES[c]} out of range")
    # row-major float64 holding whole numbers (sums stay exact below 2**53): x [cm],
    # y [cm], t [ms of the run's time base], speed [cm/s]
    count = n - 1
    full = len(plan) == ncols or not count  # else a column of width 0 keeps zero deltas
    rows = np.empty((n, ncols)) if full else np.zeros((n, ncols))
    if ncols == 3:
        rows[0] = (first[0], first[1], first[2] + time_us // 1000)
    else:
        rows[0] = (first[0], first[1], first[2] + time_us // 1000, first[3])
    for c, dtype, size in plan:
        end = off + size
        if end > len(buf):
            raise DecodeError(f"truncated: column {_COLUMN_NAMES[c]} needs {end} bytes")
        rows[1:, c] = np.frombuffer(buf, dtype, count, off)
        off = end
    np.add.accumulate(rows, 0, None, rows)
    if ncols == 3:
        flat = rows.reshape(-1)
        np.divide(flat, _tiled_scale(n), flat)  # 1-D: a (N, 3) / (3,) broadcast is slower
        return _read_only(rows), None, off
    cm_s = rows[:, 3]
    if np.minimum.reduce(cm_s) < 0 or np.maximum.reduce(cm_s) > _MAX_SPEED_CM_S:
        raise DecodeError("path speeds out of range")
    # fresh and read-only: the message takes them without a copy
    return _read_only(rows[:, :3] / _SCALE_ROW), _read_only(cm_s / 100.0), off


def _enum(table: dict[int, Any], value: int, what: str) -> Any:
    member = table.get(value)
    if member is None:
        raise DecodeError(f"invalid {what} {value}")
    return member


def _read_trailer(buf: bytes, off: int, flags: int) -> bytes:
    size = len(buf)
    if not flags & Flags.AUTH:
        if off != size:
            raise DecodeError(f"{size - off} trailing bytes after the body")
        return b""
    if off + _TRAILER.size > size:
        raise DecodeError("truncated authentication trailer")
    scheme, length = _TRAILER.unpack_from(buf, off)
    start = off + _TRAILER.size
    if start + length != size:
        raise DecodeError(
            f"authentication trailer says {length} bytes, datagram has {size - start}"
        )
    return bytes((scheme,)) + buf[start:]


def _decode(data: bytes | bytearray | memoryview) -> Message:
    if isinstance(data, bytes):
        buf = data
    elif isinstance(data, bytearray | memoryview):
        buf = bytes(data)
    else:
        raise DecodeError(f"expected bytes, not {type(data).__name__}")
    size = len(buf)
    if size > MAX_DATAGRAM:
        raise DecodeError(f"{size} bytes: longer than one {MAX_DATAGRAM}-byte datagram")
    if size < _HEAD.size:
        raise DecodeError(f"truncated: {size} bytes, a header alone needs {_HEAD.size}+")
    magic, version, kind_value, flags, seq, time_us, sender_len = _HEAD.unpack_from(buf, 0)
    if magic != MAGIC:
        raise DecodeError(f"bad magic {magic:#04x}: not a crosspath datagram")
    if version != FORMAT_VERSION:
        raise DecodeError(f"unsupported format version {version} (this is {FORMAT_VERSION})")
    kind = _KINDS.get(kind_value)
    if kind is None:
        raise DecodeError(f"invalid message kind {kind_value}")
    if flags & ~_KNOWN_FLAGS:
        raise DecodeError(f"unknown header flag bits {flags:#04x}")
    if not -MAX_TIME_US <= time_us <= MAX_TIME_US:
        raise DecodeError(f"absurd generation time {time_us} µs")
    off = _HEAD.size
    sender = _read_id(buf, off, sender_len, "sender id")
    cls, args, off = _BODY_READERS[kind](buf, off + sender_len, kind, time_us)
    header = _NEW[Header](sender, seq, time_us, flags, _read_trailer(buf, off, flags))
    message: Message = _NEW[cls](header, *args)
    return message


_Body = tuple[type[Message], tuple[Any, ...], int]

_T = TypeVar("_T")


def _constructor(cls: type[_T], speedups: bool) -> Callable[..., _T]:
    """A function making a ``cls`` from all its fields in order, without ``__init__``.

    Only for what the decoder has validated, with fresh read-only arrays. It is
    generated from the dataclass's fields as ``dataclasses`` generates ``__init__``,
    but sets each slot through its descriptor and skips ``__post_init__``: 0.8 µs
    instead of 2 µs for a future path. With ``speedups`` the C module sets the same
    slots through the same descriptors (``_speedups.build``): 0.3 µs.
    """
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    if not all(name.isidentifier() for name in names):
        raise TypeError(f"{cls.__name__}: unexpected field names {names}")
    if speedups and _speedups_module is not None:
        spec = (cls, tuple(getattr(cls, name) for name in names))
        return functools.partial(_speedups_module.build, spec)
    scope: dict[str, Any] = {"_new": object.__new__, "_cls": cls}
    scope.update({f"_set_{name}": getattr(cls, name).__set__ for name in names})
    lines = [f"def new({', '.join(names)}):", "    obj = _new(_cls)"]
    lines += [f"    _set_{name}(obj, {name})" for name in names]
    lines.append("    return obj")
    exec("\n".join(lines), scope)  # the source is made of the dataclass's own field names
    new: Callable[..., _T] = scope["new"]
    return new


_BUILT: Final = (Header, FuturePath, AutonomousPath, CoordinatedPath, ModeCommand, RsuBeacon)
_NEW_BY_SPEEDUPS: Final[dict[bool, dict[type, Callable[..., Any]]]] = {
    on: {cls: _constructor(cls, on) for cls in _BUILT} for on in (True, False)
}
_NEW: Final[dict[type, Callable[..., Any]]] = dict(_NEW_BY_SPEEDUPS[_speedups_module is not None])
"""Class -> its constructor for decoded values (``use_speedups`` switches them)."""


_LIMITS: Final[dict[tuple[int, int, int, int], VehicleLimits]] = {}
"""Declared limits already checked on receipt, by their wire values."""


def _read_limits(raw: tuple[int, int, int, int]) -> VehicleLimits | None:
    """The limits of wire values ``raw``; None when all are 0 (not declared)."""
    known = _LIMITS.get(raw)
    if known is not None:
        return known
    if raw == _NO_LIMITS:
        return None
    v_max, accel, decel, lat_accel = raw
    if not (1 <= v_max <= _MAX_SPEED_CM_S and accel and decel and lat_accel):
        raise DecodeError(
            f"absurd vehicle limits: v_max {v_max / 100} m/s, accel {accel / 10}, "
            f"decel {decel / 10}, lat_accel {lat_accel / 10} m/s² (all 0, or none)"
        )
    limits = VehicleLimits(v_max / 100, accel / 10, decel / 10, lat_accel / 10)
    return _remember(_LIMITS, raw, limits)


def _read_vehicle_path(buf: bytes, off: int, kind: Kind, time_us: int) -> _Body:
    x, y, speed, heading, length, width, lv, la, ld, ll, mode_v, n, widths = _STATE.unpack_from(
        buf, off
    )
    mode = _MODES.get(mode_v)
    if mode is None:
        raise DecodeError(f"invalid mode {mode_v}")
    if not (-_MAX_COORD_CM <= x <= _MAX_COORD_CM and -_MAX_COORD_CM <= y <= _MAX_COORD_CM):
        raise DecodeError("absurd position")
    if speed > _MAX_SPEED_CM_S:
        raise DecodeError(f"absurd speed {speed / 100} m/s")
    if not -_MAX_HEADING <= heading <= _MAX_HEADING:
        raise DecodeError(f"heading {heading / 1e4} rad beyond ±pi")
    if not (1 <= length <= _MAX_LENGTH_CM and 1 <= width <= _MAX_WIDTH_CM):
        raise DecodeError(f"absurd vehicle shape {length / 100} m x {width / 100} m")
    limits = _read_limits((lv, la, ld, ll))
    points, _, off = _read_points(buf, off + _STATE.size, kind, n, widths, 3, time_us)
    cls = FuturePath if kind is Kind.FUTURE_PATH else AutonomousPath
    args = (
        x / 100,
        y / 100,
        speed / 100,
        heading / 1e4,
        length / 100,
        width / 100,
        mode,
        points,
        limits,
    )
    return cls, args, off


def _read_coordinated_path(buf: bytes, off: int, kind: Kind, time_us: int) -> _Body:
    vehicle = _read_id(buf, off + 1, buf[off], "vehicle id")
    off += 1 + len(vehicle)
    mode_v, n, widths = _CP_STATE.unpack_from(buf, off)
    mode: Mode = _enum(_MODES, mode_v, "mode")
    if mode is Mode.AUTO:
        raise DecodeError("a coordinated path with mode AUTO")
    points, speeds, off = _read_points(buf, off + _CP_STATE.size, kind, n, widths, 4, time_us)
    return CoordinatedPath, (vehicle, mode, points, speeds), off


def _read_mode_command(buf: bytes, off: int, kind: Kind, time_us: int) -> _Body:
    vehicle = _read_id(buf, off + 1, buf[off], "vehicle id")
    off += 1 + len(vehicle)
    command_v, mode_v = _COMMAND.unpack_from(buf, off)
    command: Command = _enum(_COMMANDS, command_v, "command")
    mode: Mode = _enum(_MODES, mode_v, "mode")
    _check_command(command, mode, DecodeError)
    return ModeCommand, (vehicle, command, mode), off + _COMMAND.size


def _read_rsu_beacon(buf: bytes, off: int, kind: Kind, time_us: int) -> _Body:
    intersection = _read_id(buf, off + 1, buf[off], "intersection id")
    off += 1 + len(intersection)
    x, y, radius = _BEACON.unpack_from(buf, off)
    if not (-_MAX_COORD_CM <= x <= _MAX_COORD_CM and -_MAX_COORD_CM <= y <= _MAX_COORD_CM):
        raise DecodeError("absurd position")
    if not 1 <= radius <= _MAX_RADIUS_CM:
        raise DecodeError(f"absurd coverage radius {radius / 100} m")
    return RsuBeacon, (intersection, x / 100, y / 100, radius / 100), off + _BEACON.size


_BODY_READERS: Final[dict[Kind, Callable[[bytes, int, Kind, int], _Body]]] = {
    Kind.FUTURE_PATH: _read_vehicle_path,
    Kind.AUTONOMOUS_PATH: _read_vehicle_path,
    Kind.COORDINATED_PATH: _read_coordinated_path,
    Kind.MODE_COMMAND: _read_mode_command,
    Kind.RSU_BEACON: _read_rsu_beacon,
}


_VP_FAST_HEADS: Final = frozenset(
    bytes((MAGIC, FORMAT_VERSION, kind, flags))
    for kind in (Kind.FUTURE_PATH, Kind.AUTONOMOUS_PATH)
    for flags in (0, int(Flags.AUTH))
)
_VP_CLASSES: Final = {Kind.FUTURE_PATH: FuturePath, Kind.AUTONOMOUS_PATH: AutonomousPath}
_MAX_VP_POINTS: Final = _MAX_POINTS[Kind.FUTURE_PATH]
_COLUMN_KEYS: Final = tuple((slice(1, None), c) for c in range(4))
"""``rows[key]``: the delta rows of column c."""


def _vehicle_rows_numpy(
    buf: bytes, off: int, n: int, widths: int, time_us: int
) -> tuple[FloatArray, int] | None:
    """The (N, 3) points at ``off`` (read-only) and the offset after them, for a known
    delta layout and a first point in range; None for anything else. Without the C
    packer: one accumulate over the rows and one same-shape division."""
    plan = _PLANS.get((n, widths, 3))
    need = None if plan is None else _PLAN_BYTES.get(plan)
    if plan is None or need is None or off + _FIRST3.size + need > len(buf):
        return None
    x0, y0, t0 = _FIRST3.unpack_from(buf, off)
    if not (-_MAX_COORD_CM <= x0 <= _MAX_COORD_CM and -_MAX_COORD_CM <= y0 <= _MAX_COORD_CM):
        return None
    off += _FIRST3.size
    rows = np.empty((n, 3)) if len(plan) == 3 else np.zeros((n, 3))
    rows[0] = (x0, y0, t0 + time_us // 1000)
    count = n - 1
    for c, dtype, nbytes in plan:
        rows[_COLUMN_KEYS[c]] = np.frombuffer(buf, dtype, count, off)
        off += nbytes
    np.add.accumulate(rows, 0, None, rows)
    np.divide(rows, _scale_rows(n), rows)
    rows.setflags(write=False)
    return rows, off


def _decode_vehicle_path_fast(buf: bytes) -> Message | None:
    """A vehicle path of at least 2 points from a known sender with known limits and
    delta layout, with one ``struct`` call for everything before its points; None for
    anything else, which ``_decode`` then decodes or refuses with its explanation.
    Exactly the message ``_decode`` gives (``tests/protocol/test_fast_points.py``)."""
    size = len(buf)
    layout = _VP_PREFIX.get(buf[16]) if 17 <= size <= MAX_DATAGRAM else None
    if layout is None or size < layout.size + _FIRST3.size or buf[:4] not in _VP_FAST_HEADS:
        return None
    (_, _, kind, flags, seq, time_us, _, raw_sender, x, y, speed, heading, length, width,
     lv, la, ld, ll, mode, n, widths) = layout.unpack_from(buf, 0)  # fmt: skip
    sender = _ID_STRS.get(raw_sender)
    limits = None if lv == la == ld == ll == 0 else _LIMITS.get((lv, la, ld, ll))
    if (
        sender is None
        or (limits is None and lv | la | ld | ll)
        or not (
            2 <= n <= _MAX_VP_POINTS
            and mode <= 2
            and -MAX_TIME_US <= time_us <= MAX_TIME_US
            and -_MAX_COORD_CM <= x <= _MAX_COORD_CM
            and -_MAX_COORD_CM <= y <= _MAX_COORD_CM
            and speed <= _MAX_SPEED_CM_S
            and -_MAX_HEADING <= heading <= _MAX_HEADING
            and 1 <= length <= _MAX_LENGTH_CM
            and 1 <= width <= _MAX_WIDTH_CM
        )
    ):
        return None
    if _C_POINTS is not None:
        unpacked: tuple[FloatArray, int] | None = _C_POINTS.unpack(
            buf, layout.size, n, widths, time_us // 1000, _MAX_COORD_F
        )
        if unpacked is None:
            return None
        rows, off = unpacked  # a fresh read-only array
        auth = _read_trailer(buf, off, flags)
    else:
        read = _vehicle_rows_numpy(buf, layout.size, n, widths, time_us)
        if read is None:
            return None
        rows, off = read
        auth = _read_trailer(buf, off, flags)
    message: Message = _NEW[_VP_CLASSES[kind]](
        _NEW[Header](sender, seq, time_us, flags, auth),
        x / 100,
        y / 100,
        speed / 100,
        heading / 1e4,
        length / 100,
        width / 100,
        _MODES[mode],
        rows,
        limits,
    )
    return message


def decode(data: bytes | bytearray | memoryview) -> Message:
    """The message in one datagram; ``DecodeError`` (and nothing else) for anything malformed."""
    try:
        if type(data) is bytes:
            fast = _decode_vehicle_path_fast(data)
            if fast is not None:
                return fast
        return _decode(data)
    except DecodeError:
        raise
    except (
        struct.error,
        ValueError,
        TypeError,
        IndexError,
        OverflowError,
        KeyError,
        AttributeError,
    ) as exc:
        raise DecodeError(f"malformed datagram: {exc}") from exc
