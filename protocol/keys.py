"""Zenoh key expressions of crosspath, built and parsed in one place.

Every key starts with a configurable prefix (default ``crosspath``; it may have
several segments, e.g. ``lab1/crosspath``, so several labs can share one
network). Ids (vehicles, RSUs, intersections, nodes) are 1..32 characters from
the safe set ``[A-Za-z0-9_-]``: they are single key segments, never contain a
wildcard or a separator, and are the same ids the wire codec accepts.

==========================================  ==========================================
key                                         stream
==========================================  ==========================================
``{prefix}/v2x/fp/{vehicle}``               ``Stream.FP`` future path broadcast, 10 Hz
``{prefix}/v2x/rsu/{rsu}/ap/{vehicle}``     ``Stream.AP`` autonomous path to the RSU
``{prefix}/v2x/rsu/{rsu}/cmd/{vehicle}``    ``Stream.CMD`` mode commands, coordinated paths
``{prefix}/v2x/rsu/{rsu}/beacon``           ``Stream.BEACON`` RSU presence, 1 Hz
``{prefix}/sim/{part}[/{part}...]``         ``Stream.SIM`` simulation plumbing
``{prefix}/stats/{node}``                   ``Stream.STATS`` counters, sizes, latencies
==========================================  ==========================================

Pure string functions: no Zenoh import; ``QOS`` says how each stream should be
published (the transports map it to Zenoh's options).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from types import MappingProxyType
from typing import Final

from protocol.messages import (
    AutonomousPath,
    CoordinatedPath,
    FuturePath,
    Kind,
    Message,
    ModeCommand,
    RsuBeacon,
)

DEFAULT_PREFIX: Final = "crosspath"
"""Key prefix used when none is configured."""

MAX_ID_LEN: Final = 32
"""Longest id in bytes (ids are ASCII)."""

ID_CHARS: Final = "A-Za-z0-9_-"
"""The safe character set of ids, as a regular-expression character class body."""

MAX_PREFIX_LEN: Final = 128
"""Longest accepted prefix in characters."""

_ID_RE: Final = re.compile(rf"[{ID_CHARS}]{{1,{MAX_ID_LEN}}}", re.ASCII)
_SEGMENT_RE: Final = re.compile(rf"[{ID_CHARS}]{{1,64}}", re.ASCII)
_GOOD_PREFIXES: set[str] = set()  # prefixes already validated (a process uses one or two)


class BadKey(ValueError):
    """A key expression, prefix or id that crosspath does not accept."""


class Stream(StrEnum):
    """Kind of traffic a key carries; the value is its short name in stats."""

    FP = "fp"
    AP = "ap"
    CMD = "cmd"
    BEACON = "beacon"
    SIM = "sim"
    STATS = "stats"


@dataclass(frozen=True, slots=True)
class Qos:
    """How a stream is published (DESIGN.md, key table).

    ``reliable``: reliable delivery (else best effort); ``express``: send at once,
    no batching; ``drop``: under congestion drop samples (else block the
    publisher). V2X streams are best effort and dropping (they are the radio);
    simulation plumbing and stats are reliable and blocking.
    """

    reliable: bool
    express: bool
    drop: bool


QOS: Final[Mapping[Stream, Qos]] = MappingProxyType(
    {
        Stream.FP: Qos(reliable=False, express=True, drop=True),
        Stream.AP: Qos(reliable=False, express=False, drop=True),
        Stream.CMD: Qos(reliable=False, express=False, drop=True),
        Stream.BEACON: Qos(reliable=False, express=False, drop=True),
        Stream.SIM: Qos(reliable=True, express=False, drop=False),
        Stream.STATS: Qos(reliable=True, express=False, drop=False),
    }
)
"""Publication QoS per stream."""

STREAM_OF_KIND: Final[Mapping[Kind, Stream]] = MappingProxyType(
    {
        Kind.FUTURE_PATH: Stream.FP,
        Kind.AUTONOMOUS_PATH: Stream.AP,
        Kind.COORDINATED_PATH: Stream.CMD,
        Kind.MODE_COMMAND: Stream.CMD,
        Kind.RSU_BEACON: Stream.BEACON,
    }
)
"""The stream each message kind travels on."""


@dataclass(frozen=True, slots=True)
class ParsedKey:
    """The parts of a concrete key expression.

    ``rsu`` is set for AP, CMD and BEACON keys; ``vehicle`` for FP, AP and CMD;
    ``node`` for STATS; ``parts`` holds the segments after ``sim`` for SIM keys.
    """

    stream: Stream
    rsu: str | None = None
    vehicle: str | None = None
    node: str | None = None
    parts: tuple[str, ...] = ()


def is_valid_id(value: object) -> bool:
    """Whether ``value`` is an id: a str of 1..32 characters from ``[A-Za-z0-9_-]``."""
    return isinstance(value, str) and _ID_RE.fullmatch(value) is not None


def validate_id(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a valid id, else raise ``BadKey`` naming ``what``."""
    if not is_valid_id(value):
        raise BadKey(f"invalid {what} {value!r}: need 1..{MAX_ID_LEN} characters from [{ID_CHARS}]")
    return value


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` if acceptable: '/'-separated id-like segments, no wildcards."""
    if isinstance(prefix, str) and prefix in _GOOD_PREFIXES:
        return prefix
    if not isinstance(prefix, str) or not 0 < len(prefix) <= MAX_PREFIX_LEN:
        raise BadKey(f"invalid key prefix {prefix!r}: need 1..{MAX_PREFIX_LEN} characters")
    for segment in prefix.split("/"):
        if _SEGMENT_RE.fullmatch(segment) is None:
            raise BadKey(
                f"invalid key prefix {prefix!r}: segment {segment!r} is not 1..64 "
                f"characters from [{ID_CHARS}] (no wildcards, no empty segments)"
            )
    if len(_GOOD_PREFIXES) < 64:
        _GOOD_PREFIXES.add(prefix)
    return prefix


# ---------------------------------------------------------------- concrete keys


def future_path(vehicle: str, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of ``vehicle``'s future path broadcast."""
    return f"{validate_prefix(prefix)}/v2x/fp/{validate_id(vehicle, 'vehicle id')}"


def autonomous_path(rsu: str, vehicle: str, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of ``vehicle``'s autonomous path sent to ``rsu``."""
    return (
        f"{validate_prefix(prefix)}/v2x/rsu/{validate_id(rsu, 'rsu id')}"
        f"/ap/{validate_id(vehicle, 'vehicle id')}"
    )


def rsu_command(rsu: str, vehicle: str, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of ``rsu``'s mode commands and coordinated paths for ``vehicle``."""
    return (
        f"{validate_prefix(prefix)}/v2x/rsu/{validate_id(rsu, 'rsu id')}"
        f"/cmd/{validate_id(vehicle, 'vehicle id')}"
    )


def rsu_beacon(rsu: str, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of ``rsu``'s presence beacon."""
    return f"{validate_prefix(prefix)}/v2x/rsu/{validate_id(rsu, 'rsu id')}/beacon"


def sim(*parts: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Key under the simulation plumbing, e.g. ``sim("truth", "car-a")``; at least one part."""
    if not parts:
        raise BadKey("a sim key needs at least one segment after 'sim'")
    checked = "/".join(validate_id(p, "sim key segment") for p in parts)
    return f"{validate_prefix(prefix)}/sim/{checked}"


def stats(node: str, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of ``node``'s published counters."""
    return f"{validate_prefix(prefix)}/stats/{validate_id(node, 'node id')}"


def message_key(message: Message, *, rsu: str | None = None, prefix: str = DEFAULT_PREFIX) -> str:
    """The key a message is published on.

    The sender is the vehicle for future and autonomous paths and the RSU for
    commands, coordinated paths and beacons; an autonomous path also needs the
    destination ``rsu``.
    """
    sender = message.header.sender
    if isinstance(message, FuturePath):
        return future_path(sender, prefix=prefix)
    if isinstance(message, AutonomousPath):
        if rsu is None:
            raise BadKey("an autonomous path key needs the destination rsu")
        return autonomous_path(rsu, sender, prefix=prefix)
    if isinstance(message, CoordinatedPath | ModeCommand):
        return rsu_command(sender, message.vehicle, prefix=prefix)
    if isinstance(message, RsuBeacon):
        return rsu_beacon(sender, prefix=prefix)
    raise BadKey(f"not a crosspath message: {type(message).__name__}")


# ---------------------------------------------------------------- subscriptions


def all_future_paths(*, prefix: str = DEFAULT_PREFIX) -> str:
    """Every car's future path."""
    return f"{validate_prefix(prefix)}/v2x/fp/*"


def all_autonomous_paths(rsu: str | None = None, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Autonomous paths of every car to ``rsu`` (to any RSU when None)."""
    r = "*" if rsu is None else validate_id(rsu, "rsu id")
    return f"{validate_prefix(prefix)}/v2x/rsu/{r}/ap/*"


def all_commands(vehicle: str | None = None, *, prefix: str = DEFAULT_PREFIX) -> str:
    """Commands from any RSU to ``vehicle`` (to every car when None)."""
    v = "*" if vehicle is None else validate_id(vehicle, "vehicle id")
    return f"{validate_prefix(prefix)}/v2x/rsu/*/cmd/{v}"


def all_beacons(*, prefix: str = DEFAULT_PREFIX) -> str:
    """Every RSU's beacon."""
    return f"{validate_prefix(prefix)}/v2x/rsu/*/beacon"


def all_v2x(*, prefix: str = DEFAULT_PREFIX) -> str:
    """All V2X traffic (monitors, traffic accounting)."""
    return f"{validate_prefix(prefix)}/v2x/**"


def all_sim(*, prefix: str = DEFAULT_PREFIX) -> str:
    """All simulation plumbing."""
    return f"{validate_prefix(prefix)}/sim/**"


def all_stats(*, prefix: str = DEFAULT_PREFIX) -> str:
    """Every node's stats."""
    return f"{validate_prefix(prefix)}/stats/*"


# ---------------------------------------------------------------- parsing


def _id_at(segments: list[str], index: int, what: str, key: str) -> str:
    value = segments[index]
    if not is_valid_id(value):
        raise BadKey(f"bad key {key!r}: invalid {what} {value!r}")
    return value


def parse(key: str, *, prefix: str = DEFAULT_PREFIX) -> ParsedKey:
    """Split a concrete key (no wildcards) into stream and ids; ``BadKey`` otherwise."""
    if not isinstance(key, str):
        raise BadKey(f"key must be a str, not {type(key).__name__}")
    head = validate_prefix(prefix) + "/"
    if not key.startswith(head):
        raise BadKey(f"bad key {key!r}: does not start with {head!r}")
    segments = key[len(head) :].split("/")
    n = len(segments)
    first = segments[0]
    if first == "v2x" and n >= 3:
        if segments[1] == "fp" and n == 3:
            return ParsedKey(Stream.FP, vehicle=_id_at(segments, 2, "vehicle id", key))
        if segments[1] == "rsu":
            if n == 4 and segments[3] == "beacon":
                return ParsedKey(Stream.BEACON, rsu=_id_at(segments, 2, "rsu id", key))
            if n == 5 and segments[3] in ("ap", "cmd"):
                stream = Stream.AP if segments[3] == "ap" else Stream.CMD
                return ParsedKey(
                    stream,
                    rsu=_id_at(segments, 2, "rsu id", key),
                    vehicle=_id_at(segments, 4, "vehicle id", key),
                )
    elif first == "sim" and n >= 2:
        parts = tuple(_id_at(segments, i, "sim key segment", key) for i in range(1, n))
        return ParsedKey(Stream.SIM, parts=parts)
    elif first == "stats" and n == 2:
        return ParsedKey(Stream.STATS, node=_id_at(segments, 1, "node id", key))
    raise BadKey(f"bad key {key!r}: not a crosspath key expression")


def matches(parsed: ParsedKey, message: Message) -> bool:
    """Whether ``message`` may travel on the key ``parsed`` (stream and ids agree).

    A receiver uses it to drop a message whose sender or target does not match
    the key it arrived on.
    """
    if STREAM_OF_KIND[message.kind] is not parsed.stream:
        return False
    sender = message.header.sender
    if isinstance(message, FuturePath | AutonomousPath):
        return parsed.vehicle == sender
    if isinstance(message, CoordinatedPath | ModeCommand):
        return parsed.rsu == sender and parsed.vehicle == message.vehicle
    return parsed.rsu == sender
