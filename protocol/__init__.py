"""crosspath wire protocol: message kinds, binary codec, key expressions.

Imports neither Zenoh nor asyncio. Public API::

    encode(message) -> bytes          # never more than MAX_DATAGRAM bytes, else EncodeError
    decode(data: bytes) -> Message    # raises DecodeError (a ValueError) for anything hostile
    max_points(kind) -> int           # how many path points fit one datagram
"""

from protocol.codec import DecodeError, EncodeError, decode, encode, max_points
from protocol.messages import (
    FORMAT_VERSION,
    MAX_DATAGRAM,
    AutonomousPath,
    Command,
    CoordinatedPath,
    Flags,
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

__all__ = [
    "FORMAT_VERSION",
    "MAX_DATAGRAM",
    "AutonomousPath",
    "Command",
    "CoordinatedPath",
    "DecodeError",
    "EncodeError",
    "Flags",
    "FuturePath",
    "Header",
    "Kind",
    "Message",
    "Mode",
    "ModeCommand",
    "RsuBeacon",
    "VehicleLimits",
    "VehiclePath",
    "decode",
    "encode",
    "max_points",
]
