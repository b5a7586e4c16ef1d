"""The V2X message kinds of crosspath, as plain frozen values.

Units everywhere: metres, seconds, metres per second, radians. Times are on the
run's shared time base: seconds since the run's start epoch (the in-process
harness starts its virtual clock at 0; daemons share one epoch, see
``services/runtime``). On the wire, times are microseconds (header) and
milliseconds (path points); positions are centimetres (see ``SPEC.md``).

Path points are numpy arrays, made read-only on construction so that a message
really is a value: ``points`` has shape (N, 3) with columns x [m], y [m] and
pass time t [s]; ``CoordinatedPath.speeds`` has shape (N,) in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Final

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

FORMAT_VERSION = 3
"""Wire format version carried by every datagram (2: vehicle paths carry ``VehicleLimits``;
3: path times are whole milliseconds of the run's time base, ``SPEC.md`` 3)."""

MAX_DATAGRAM = 1460
"""Largest datagram crosspath ever produces, in bytes (one UDP payload on Ethernet)."""


class Kind(IntEnum):
    """Message kind tag (one byte on the wire)."""

    FUTURE_PATH = 1
    AUTONOMOUS_PATH = 2
    COORDINATED_PATH = 3
    MODE_COMMAND = 4
    RSU_BEACON = 5


class Mode(IntEnum):
    """Per-car mode kept by the RSU (paper §IV-C)."""

    AUTO = 0
    C_SLOW = 1
    C_FAST = 2


class Command(IntEnum):
    """What a mode command asks of the car."""

    INITIATE = 1
    TERMINATE = 2


class Flags(IntEnum):
    """Header flag bits."""

    AUTH = 0x01  # an authentication trailer follows the body


@dataclass(frozen=True, slots=True)
class Header:
    """Common header of every message.

    ``time_us`` is the generation time in microseconds on the run's time base.
    ``auth`` is the optional authentication trailer (opaque bytes; empty when
    absent); a later version of the codec fills it with a signature.
    """

    sender: str
    seq: int
    time_us: int
    flags: int = 0
    auth: bytes = b""

    @property
    def time_s(self) -> float:
        """Generation time in seconds."""
        return self.time_us / 1e6


_FLOAT64: Final = np.dtype(np.float64)


def _is_frozen(arr: FloatArray, ndim: int) -> bool:
    """Already a read-only float64 array of the right rank that owns its memory.

    Such an array (the decoder makes them; another message's ``points`` is one)
    is taken as is: copying it again would cost more than decoding it.
    """
    if arr.dtype is not _FLOAT64 or arr.ndim != ndim:
        return False
    flags = arr.flags
    return not flags.writeable and flags.owndata


def _frozen_points(
    points: FloatArray | list[list[float]] | list[tuple[float, float, float]],
) -> FloatArray:
    if type(points) is np.ndarray and _is_frozen(points, 2) and points.shape[1] == 3:
        return points
    arr = np.array(points, dtype=np.float64).reshape(-1, 3)
    arr.flags.writeable = False
    return arr


def _frozen_vector(values: FloatArray | list[float]) -> FloatArray:
    if type(values) is np.ndarray and _is_frozen(values, 1):
        return values
    arr = np.array(values, dtype=np.float64).reshape(-1)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, slots=True)
class VehicleLimits:
    """What a car can do, declared in its own paths so that an RSU plans it with them.

    ``v_max`` [m/s] top speed; ``accel`` [m/s²] the acceleration it plans with;
    ``decel`` [m/s², positive] its comfortable braking; ``lat_accel`` [m/s²] the
    lateral acceleration it accepts in a curve (speed cap ``sqrt(lat_accel * r)``).
    They travel in the path, not in a certificate: nothing vouches for them until
    messages are signed (a later version). On the wire ``v_max`` has 1 cm/s resolution,
    the accelerations 0.1 m/s² (``SPEC.md`` 2.3).
    """

    v_max: float
    accel: float
    decel: float
    lat_accel: float


@dataclass(frozen=True, slots=True, eq=False)
class VehiclePath:
    """A car's path with its current state (paper §III-A).

    Base of ``FuturePath`` (broadcast to all) and ``AutonomousPath`` (to the RSU
    while coordinated); both carry the same fields. ``limits`` None: the sender did
    not declare them, and a receiver assumes its own (the RSU: its scenario's).
    """

    header: Header
    x: float  # current position [m]
    y: float
    speed: float  # current speed [m/s]
    heading: float  # [rad], 0 = +x, counter-clockwise
    length: float  # vehicle shape [m]
    width: float
    mode: Mode  # the sender's current mode
    points: FloatArray = field(default_factory=lambda: _frozen_points([]))
    limits: VehicleLimits | None = None  # what the car can do, if it says

    def __post_init__(self) -> None:
        object.__setattr__(self, "points", _frozen_points(self.points))

    @property
    def kind(self) -> Kind:
        raise NotImplementedError


@dataclass(frozen=True, slots=True, eq=False)
class FuturePath(VehiclePath):
    """The trajectory turned into positions with pass times (paper eq. 1), broadcast 10 Hz."""

    @property
    def kind(self) -> Kind:
        return Kind.FUTURE_PATH


@dataclass(frozen=True, slots=True, eq=False)
class AutonomousPath(VehiclePath):
    """The path the car would drive alone, sent to its RSU 10 Hz while coordinated."""

    @property
    def kind(self) -> Kind:
        return Kind.AUTONOMOUS_PATH


@dataclass(frozen=True, slots=True, eq=False)
class CoordinatedPath:
    """The RSU's speed-modified autonomous path for one car; the car gives it priority.

    ``points`` are (x, y, t) as in a future path, ``speeds`` the target speed at
    each point [m/s].
    """

    header: Header
    vehicle: str  # the car this path is for
    mode: Mode  # C_SLOW or C_FAST
    points: FloatArray = field(default_factory=lambda: _frozen_points([]))
    speeds: FloatArray = field(default_factory=lambda: _frozen_vector([]))

    def __post_init__(self) -> None:
        object.__setattr__(self, "points", _frozen_points(self.points))
        object.__setattr__(self, "speeds", _frozen_vector(self.speeds))
        if self.speeds.shape[0] != self.points.shape[0]:
            raise ValueError(
                f"coordinated path: {self.speeds.shape[0]} speeds for {self.points.shape[0]} points"
            )

    @property
    def kind(self) -> Kind:
        return Kind.COORDINATED_PATH


@dataclass(frozen=True, slots=True)
class ModeCommand:
    """RSU → car: initiation of a coordinated mode, or termination back to AUTO."""

    header: Header
    vehicle: str
    command: Command
    mode: Mode  # target mode: C_SLOW or C_FAST for INITIATE, AUTO for TERMINATE

    @property
    def kind(self) -> Kind:
        return Kind.MODE_COMMAND


@dataclass(frozen=True, slots=True)
class RsuBeacon:
    """RSU presence, 1 Hz: which intersection it coordinates and where it reaches."""

    header: Header
    intersection: str
    x: float  # centre of coverage [m]
    y: float
    radius: float  # coverage radius [m]

    @property
    def kind(self) -> Kind:
        return Kind.RSU_BEACON


Message = FuturePath | AutonomousPath | CoordinatedPath | ModeCommand | RsuBeacon
"""Any V2X message."""
