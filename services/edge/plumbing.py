"""Simulation plumbing between the daemons: run control, ground truth, statistics.

These messages are not V2X: they stand for the wired link between the
simulator and the actors in the paper's setup, travel reliably (TCP) under
``{prefix}/sim/...`` and ``{prefix}/stats/...`` (``protocol.keys``) and are
never subject to fault injection. Each is a msgpack map with a ``v`` (format
version) and a ``type`` field; decoding validates every field and raises
:class:`PlumbingError` (a ``ValueError``) with a clear reason, nothing else.

==========================================  ===========================================
key                                         message
==========================================  ===========================================
``{prefix}/sim/control``                    :class:`StartRun` / :class:`StopRun`
                                            (the monitor, to everyone)
``{prefix}/sim/truth/{vehicle}``            :class:`TruthReport` (each car, 20 Hz)
``{prefix}/sim/alive/{node}``               liveliness token of each daemon (no payload)
``{prefix}/stats/{node}``                   :class:`StatsReport` (each daemon, periodic
                                            and final)
==========================================  ===========================================

Run control: the monitor publishes one :class:`StartRun` per run (repeated
until every actor acknowledged it by a stats report carrying the run id; a
daemon ignores a start whose run id it has already seen), and one
:class:`StopRun` at the end. Run time 0 is ``epoch_unix`` (Unix seconds) and
run time advances ``speed`` times as fast as wall time
(``services.edge.clock.RunClock``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

import msgpack

from protocol import keys
from protocol.auth import Role
from protocol.codec import MAX_COORD_M, MAX_LENGTH_M, MAX_SPEED_MPS, MAX_WIDTH_M
from services.edge.trust import Credentials, Refused, Signer, TrustStore
from services.model.kinematics import TruthState
from services.model.types import Policy, RunMode

__all__ = [
    "MAX_PLUMBING_BYTES",
    "MAX_STATS_BYTES",
    "PLUMBING_VERSION",
    "PRESENCE",
    "TRUTH_BOUNDS",
    "Control",
    "PlumbingAuth",
    "PlumbingError",
    "StartRun",
    "StatsReport",
    "StopRun",
    "TruthReport",
    "alive_key",
    "all_alive",
    "all_truths",
    "control_key",
    "decode_control",
    "decode_stats",
    "decode_truth",
    "encode_control",
    "encode_stats",
    "encode_truth",
    "node_of_alive_key",
    "truth_key",
]

PLUMBING_VERSION: Final = 1
"""Format version of every plumbing message (field ``v``)."""

MAX_PLUMBING_BYTES: Final = 256 * 1024
"""Larger plumbing payloads are refused before decoding (a stats report of a busy
node is a few kilobytes)."""

MAX_SPEED: Final = 1000.0
"""Largest accepted time scale (as ``config.TimeSettings``)."""

MAX_STATS_BYTES: Final = 128 * 1024
"""A stats report is at most this long, encoded: larger ones are refused by the decoder
and are a bug when we make one (every section of a report is bounded: streams, receive
policies and the RSU's table log are)."""

MAX_RUN_TIME_S: Final = 1e9
"""Largest run time a truth report may carry [s] (about 30 years)."""

MAX_HEADING_RAD: Final = 100.0
"""Largest heading magnitude a truth report may carry [rad]; the physics keeps it near
[-pi, pi], the bound only keeps trigonometry and squares finite."""

MAX_ACCEL_MPS2: Final = 100.0
"""Largest acceleration magnitude a truth report may carry [m/s^2] (ten g)."""

TRUTH_BOUNDS: Final[Mapping[str, tuple[float, float]]] = MappingProxyType(
    {
        "t": (-MAX_RUN_TIME_S, MAX_RUN_TIME_S),
        "x": (-MAX_COORD_M, MAX_COORD_M),
        "y": (-MAX_COORD_M, MAX_COORD_M),
        "heading": (-MAX_HEADING_RAD, MAX_HEADING_RAD),
        "speed": (-MAX_SPEED_MPS, MAX_SPEED_MPS),
        "accel": (-MAX_ACCEL_MPS2, MAX_ACCEL_MPS2),
        "s": (-MAX_COORD_M, MAX_COORD_M),
        "length": (0.0, MAX_LENGTH_M),
        "width": (0.0, MAX_WIDTH_M),
    }
)
"""Per ground-truth field, the closed range a report may carry (positions as the V2X wire
format's, ``protocol.codec``): a car fed ``x = 1e300`` crashed on an OverflowError."""


class PlumbingError(ValueError):
    """A plumbing payload that is not a valid message of the expected type."""


# --------------------------------------------------------------------------- keys


def control_key(*, prefix: str = keys.DEFAULT_PREFIX) -> str:
    """Run start and stop messages."""
    return keys.sim("control", prefix=prefix)


def truth_key(vehicle: str, *, prefix: str = keys.DEFAULT_PREFIX) -> str:
    """Ground truth of one car."""
    return keys.sim("truth", vehicle, prefix=prefix)


def all_truths(*, prefix: str = keys.DEFAULT_PREFIX) -> str:
    """Ground truth of every car."""
    return f"{keys.validate_prefix(prefix)}/sim/truth/*"


def alive_key(node: str, *, prefix: str = keys.DEFAULT_PREFIX) -> str:
    """Liveliness token of one daemon."""
    return keys.sim("alive", node, prefix=prefix)


def all_alive(*, prefix: str = keys.DEFAULT_PREFIX) -> str:
    """Liveliness tokens of every daemon."""
    return f"{keys.validate_prefix(prefix)}/sim/alive/*"


def node_of_alive_key(key: str, *, prefix: str = keys.DEFAULT_PREFIX) -> str:
    """The node id of a liveliness token key; ``keys.BadKey`` if it is not one."""
    parsed = keys.parse(key, prefix=prefix)
    if len(parsed.parts) != 2 or parsed.parts[0] != "alive":
        raise keys.BadKey(f"bad key {key!r}: not a liveliness token key")
    return parsed.parts[1]


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class StartRun:
    """The monitor starts a run: everything an actor needs beyond the scenario file.

    ``start_times`` [s, run time] per car (``Scenario.draw_start_times(seed)``);
    ``epoch_unix`` the wall-clock instant of run time 0 (Unix s); ``speed`` run
    seconds per wall second; ``max_sim_s`` when the run ends at the latest [s];
    ``monitor`` the monitor's node id (actors end the run when its liveliness
    token disappears); ``vehicles``/``rsus`` the actors taking part.
    """

    run_id: str
    scenario: str
    mode: RunMode
    policy: Policy
    seed: int
    start_times: Mapping[str, float]
    epoch_unix: float
    speed: float
    max_sim_s: float
    monitor: str
    vehicles: tuple[str, ...]
    rsus: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _check_id(self.run_id, "run_id")
        _check_id(self.monitor, "monitor")
        if not isinstance(self.scenario, str) or not 0 < len(self.scenario) <= 100:
            raise PlumbingError("scenario: need a name of 1..100 characters")
        try:
            object.__setattr__(self, "mode", RunMode(self.mode))
        except ValueError:
            raise PlumbingError(f"mode: unknown run mode {self.mode!r}") from None
        try:
            object.__setattr__(self, "policy", Policy(self.policy))
        except ValueError:
            raise PlumbingError(f"policy: unknown policy {self.policy!r}") from None
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise PlumbingError(f"seed: need an int >= 0, got {self.seed!r}")
        _check_number(self.epoch_unix, "epoch_unix", lo=0.0)
        _check_number(self.speed, "speed", lo=0.0, lo_open=True, hi=MAX_SPEED)
        _check_number(self.max_sim_s, "max_sim_s", lo=0.0, lo_open=True)
        vehicles = _id_tuple(self.vehicles, "vehicles")
        if not vehicles:
            raise PlumbingError("vehicles: need at least one vehicle")
        rsus = _id_tuple(self.rsus, "rsus")
        object.__setattr__(self, "vehicles", vehicles)
        object.__setattr__(self, "rsus", rsus)
        if not isinstance(self.start_times, Mapping):
            raise PlumbingError("start_times: need a table vehicle -> seconds")
        times: dict[str, float] = {}
        for vid, value in self.start_times.items():
            _check_id(vid, "start_times key")
            _check_number(value, f"start_times.{vid}", lo=0.0)
            times[vid] = float(value)
        missing = [v for v in vehicles if v not in times]
        if missing:
            raise PlumbingError(f"start_times: no start time for {', '.join(missing)}")
        object.__setattr__(self, "start_times", MappingProxyType(times))

    def to_wire(self) -> dict[str, Any]:
        return {
            "type": "start",
            "run_id": self.run_id,
            "scenario": self.scenario,
            "mode": str(self.mode),
            "policy": str(self.policy),
            "seed": self.seed,
            "start_times": dict(self.start_times),
            "epoch_unix": self.epoch_unix,
            "speed": self.speed,
            "max_sim_s": self.max_sim_s,
            "monitor": self.monitor,
            "vehicles": list(self.vehicles),
            "rsus": list(self.rsus),
        }


@dataclass(frozen=True, slots=True)
class StopRun:
    """The monitor ends run ``run_id`` at run time ``sim_s`` [s]; ``reason`` is for logs."""

    run_id: str
    reason: str = "finished"
    sim_s: float = 0.0

    def __post_init__(self) -> None:
        _check_id(self.run_id, "run_id")
        if not isinstance(self.reason, str) or len(self.reason) > 500:
            raise PlumbingError("reason: need a text of at most 500 characters")
        _check_number(self.sim_s, "sim_s")

    def to_wire(self) -> dict[str, Any]:
        return {"type": "stop", "run_id": self.run_id, "reason": self.reason, "sim_s": self.sim_s}


Control = StartRun | StopRun
"""A run-control message."""


@dataclass(frozen=True, slots=True)
class TruthReport:
    """One car's ground truth at physics step ``step`` (run time ``state.t`` [s]).

    ``mode`` is the car's coordination mode name (``AUTO``, ``C_SLOW``,
    ``C_FAST``) and ``reason`` its planner's reason, both as of its last planning
    step; the monitor records them, the other cars' simulated sensors use
    ``state``.
    """

    run_id: str
    step: int
    state: TruthState
    mode: str = "AUTO"
    reason: str = ""
    presence: str = "in"
    """:data:`PRESENCE`: ``in`` (in the world), ``waiting`` (arrived, not yet inserted: no
    truth, ``state`` is its entry), ``left`` (at its goal: its last report, then none)."""

    def __post_init__(self) -> None:
        _check_id(self.run_id, "run_id")
        _check_id(self.state.id, "vehicle")
        if isinstance(self.step, bool) or not isinstance(self.step, int) or self.step < 0:
            raise PlumbingError(f"step: need an int >= 0, got {self.step!r}")
        for name, (lo, hi) in TRUTH_BOUNDS.items():
            _check_number(getattr(self.state, name), name, lo=lo, hi=hi)
        for name in ("mode", "reason"):
            value = getattr(self, name)
            if not isinstance(value, str) or len(value) > 64:
                raise PlumbingError(f"{name}: need a text of at most 64 characters")
        if self.presence not in PRESENCE:
            raise PlumbingError(f"presence: need one of {', '.join(PRESENCE)}")

    @property
    def vehicle(self) -> str:
        return self.state.id


@dataclass(frozen=True, slots=True)
class StatsReport:
    """A node's cumulative traffic counters (``services.edge.stats.NodeStats.snapshot``).

    ``run_id`` None: counted while no run was active. ``final``: the last report
    of that run (the node stopped sending).
    """

    node: str
    run_id: str | None
    final: bool
    snapshot: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _check_id(self.node, "node")
        if self.run_id is not None:
            _check_id(self.run_id, "run_id")
        if not isinstance(self.final, bool):
            raise PlumbingError("final: need a bool")
        if not isinstance(self.snapshot, Mapping) or not isinstance(
            self.snapshot.get("streams"), Mapping
        ):
            raise PlumbingError("snapshot: need a table with a 'streams' table")


# --------------------------------------------------------------------------- codecs


def _pack(body: dict[str, Any]) -> bytes:
    data: bytes = msgpack.packb({"v": PLUMBING_VERSION, **body}, use_bin_type=True)
    return data


def _unpack(data: bytes, what: str) -> dict[str, Any]:
    if not isinstance(data, bytes | bytearray | memoryview):
        raise PlumbingError(f"{what}: payload must be bytes")
    if len(data) > MAX_PLUMBING_BYTES:
        raise PlumbingError(f"{what}: payload of {len(data)} B exceeds {MAX_PLUMBING_BYTES} B")
    try:
        body = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise PlumbingError(f"{what}: not msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(body, dict):
        raise PlumbingError(f"{what}: expected a map, got {type(body).__name__}")
    if body.get("v") != PLUMBING_VERSION:
        raise PlumbingError(f"{what}: unsupported format version {body.get('v')!r}")
    return body


def _field(body: Mapping[str, Any], name: str, what: str) -> Any:
    if name not in body:
        raise PlumbingError(f"{what}: missing field {name!r}")
    return body[name]


def encode_control(message: Control) -> bytes:
    """A start or stop message as bytes."""
    return _pack(message.to_wire())


def decode_control(data: bytes) -> Control:
    """Parse a control message; :class:`PlumbingError` on anything invalid."""
    body = _unpack(data, "control")
    kind = body.get("type")
    try:
        if kind == "start":
            return StartRun(
                run_id=_field(body, "run_id", "start"),
                scenario=_field(body, "scenario", "start"),
                mode=_field(body, "mode", "start"),
                policy=_field(body, "policy", "start"),
                seed=_field(body, "seed", "start"),
                start_times=_field(body, "start_times", "start"),
                epoch_unix=_field(body, "epoch_unix", "start"),
                speed=_field(body, "speed", "start"),
                max_sim_s=_field(body, "max_sim_s", "start"),
                monitor=_field(body, "monitor", "start"),
                vehicles=_field(body, "vehicles", "start"),
                rsus=body.get("rsus", ()),
            )
        if kind == "stop":
            return StopRun(
                run_id=_field(body, "run_id", "stop"),
                reason=body.get("reason", ""),
                sim_s=body.get("sim_s", 0.0),
            )
    except PlumbingError as exc:
        raise PlumbingError(f"{kind} message: {exc}") from None
    raise PlumbingError(f"control: unknown message type {kind!r}")


PRESENCE: Final = ("in", "waiting", "left")
"""A car's presence in the world in a truth report (``TruthReport.presence``)."""

_TRUTH_FIELDS: Final = ("t", "x", "y", "heading", "speed", "accel", "s", "length", "width")


def encode_truth(report: TruthReport) -> bytes:
    """A ground-truth report as bytes (about 150 B)."""
    st = report.state
    return _pack(
        {
            "type": "truth",
            "run_id": report.run_id,
            "vehicle": st.id,
            "step": report.step,
            "state": [float(getattr(st, name)) for name in _TRUTH_FIELDS],
            "mode": report.mode,
            "reason": report.reason,
            "presence": report.presence,
        }
    )


def decode_truth(data: bytes) -> TruthReport:
    """Parse a ground-truth report; :class:`PlumbingError` on anything invalid."""
    body = _unpack(data, "truth")
    if body.get("type") != "truth":
        raise PlumbingError(f"truth: unexpected message type {body.get('type')!r}")
    values = _field(body, "state", "truth")
    if not isinstance(values, list | tuple) or len(values) != len(_TRUTH_FIELDS):
        raise PlumbingError(f"truth: state must be a list of {len(_TRUTH_FIELDS)} numbers")
    for name, value in zip(_TRUTH_FIELDS, values, strict=True):
        lo, hi = TRUTH_BOUNDS[name]
        _check_number(value, f"truth state.{name}", lo=lo, hi=hi)
    vehicle = _field(body, "vehicle", "truth")
    _check_id(vehicle, "truth vehicle")
    state = TruthState(vehicle, *(float(v) for v in values))
    try:
        return TruthReport(
            run_id=_field(body, "run_id", "truth"),
            step=_field(body, "step", "truth"),
            state=state,
            mode=body.get("mode", "AUTO"),
            reason=body.get("reason", ""),
            presence=body.get("presence", "in"),
        )
    except PlumbingError as exc:
        raise PlumbingError(f"truth: {exc}") from None


def encode_stats(report: StatsReport) -> bytes:
    """A stats report as bytes; ValueError (our bug) beyond :data:`MAX_STATS_BYTES`."""
    data = _pack(
        {
            "type": "stats",
            "node": report.node,
            "run_id": report.run_id,
            "final": report.final,
            "snapshot": dict(report.snapshot),
        }
    )
    if len(data) > MAX_STATS_BYTES:
        raise ValueError(f"stats report of {len(data)} B exceeds {MAX_STATS_BYTES} B")
    return data


def decode_stats(data: bytes) -> StatsReport:
    """Parse a stats report; :class:`PlumbingError` on anything invalid.

    The counters themselves are checked when merged (``stats.merge_snapshots``).
    """
    if isinstance(data, bytes | bytearray | memoryview) and len(data) > MAX_STATS_BYTES:
        raise PlumbingError(f"stats: payload of {len(data)} B exceeds {MAX_STATS_BYTES} B")
    body = _unpack(data, "stats")
    if body.get("type") != "stats":
        raise PlumbingError(f"stats: unexpected message type {body.get('type')!r}")
    try:
        return StatsReport(
            node=_field(body, "node", "stats"),
            run_id=body.get("run_id"),
            final=body.get("final", False),
            snapshot=_field(body, "snapshot", "stats"),
        )
    except PlumbingError as exc:
        raise PlumbingError(f"stats: {exc}") from None


# --------------------------------------------------------------------------- authentication


class PlumbingAuth:
    """Signs the plumbing this daemon publishes and verifies what it receives (issue 13).

    Every payload travels as a ``services.edge.trust`` signed blob (Ed25519 over the
    payload, a run tag, a per-signer counter and the signer's certificate). What a blob
    may say depends on its key: a truth report on ``sim/truth/{car}`` only with that
    car's vehicle certificate, a stats report on ``stats/{node}`` only with that node's,
    a control message only with a monitor certificate (:meth:`open`) whose subject is
    the run's ``monitor`` (:meth:`check_control`). Refusals raise :class:`PlumbingError` (counted in
    ``plumbing_malformed``) and are counted by reason in :attr:`refused`.

    Decisions where the issue is silent: the run tag is not checked (a start names a
    run that does not exist yet, and every payload names its run id, which the
    handlers check); replays are refused by the counter window per signer, and the
    counter starts at the signer's start time in milliseconds, so that a restarted
    daemon is not taken for a replay of its earlier incarnation. Liveliness tokens
    carry no payload and cannot be signed: a forged token alone cannot start a run
    (every actor must acknowledge the start with a signed stats report) nor fake an
    RSU (``services.daemons.monitor``: the cars must have heard it).
    """

    def __init__(
        self, credentials: Credentials, *, time_fn: Callable[[], float] = time.time
    ) -> None:
        self.credentials = credentials
        self.signer = Signer(credentials)
        self.signer._counter = int(time_fn() * 1000) & 0xFFFFFFFF
        self.stores = {
            kind: TrustStore(credentials.root, revocation=credentials.revocation)
            for kind in ("control", "truth", "stats")
        }
        """One per kind of payload: a signer's counter runs across its truth and its stats,
        which travel on different keys and queues, so each kind keeps its own replay
        window (else a queue that lags 64 behind the other looks like a replay)."""
        self.refused: dict[str, int] = {}

    @property
    def subject(self) -> str:
        """Who this daemon signs as."""
        return self.credentials.subject

    def seal(self, payload: bytes) -> bytes:
        """``payload`` signed by this daemon."""
        return self.signer.seal_blob(payload)

    def _refuse(self, reason: str, detail: str) -> PlumbingError:
        self.refused[reason] = self.refused.get(reason, 0) + 1
        return PlumbingError(f"unauthenticated ({reason}): {detail}")

    def open(
        self, key: str, blob: bytes, *, prefix: str = keys.DEFAULT_PREFIX
    ) -> tuple[bytes, str]:
        """The payload of ``blob`` received on ``key`` and its signer's subject.

        Raises :class:`PlumbingError` when the blob is not validly signed by a key the
        root certified, is a replay, or names a sender its key does not allow."""
        try:
            parsed = keys.parse(key, prefix=prefix)
        except keys.BadKey as exc:
            raise self._refuse("bad_key", str(exc)) from None
        kind = "stats" if parsed.stream is keys.Stream.STATS else (parsed.parts or ("",))[0]
        store = self.stores.get(kind, self.stores["control"])
        try:
            payload, cert = store.verify_blob(blob, any_run=True)
        except Refused as exc:
            raise self._refuse(exc.reason, f"{key}: {exc}") from None
        named, role = None, None
        if parsed.stream is keys.Stream.STATS:
            named = parsed.node
        elif parsed.parts[:1] == ("truth",) and len(parsed.parts) == 2:
            named, role = parsed.parts[1], Role.VEHICLE
        elif parsed.parts == ("control",):
            role = Role.MONITOR
        if named is not None and cert.subject != named:
            raise self._refuse("wrong_sender", f"{key} signed by {cert.subject}")
        if role is not None and cert.role is not role:
            raise self._refuse("wrong_role", f"{key} signed by {cert.subject} ({cert.role.name})")
        return payload, cert.subject

    def check_control(self, subject: str | None, message: Control, start: StartRun | None) -> None:
        """Refuse (PlumbingError) a control message its signer ``subject`` may not send:
        a start not signed by its ``monitor``, or by an actor of it; a stop not signed by
        the monitor of ``start`` (the run it would stop)."""
        run = message if isinstance(message, StartRun) else start
        if run is None:
            return  # a stop of no run of ours: ignored anyway
        if subject != run.monitor or subject in run.vehicles or subject in run.rsus:
            raise self._refuse(
                "not_monitor", f"{type(message).__name__} of run {message.run_id} by {subject}"
            )


# --------------------------------------------------------------------------- checks


def _check_id(value: object, what: str) -> None:
    if not keys.is_valid_id(value):
        raise PlumbingError(
            f"{what}: {value!r} is not an id (1..{keys.MAX_ID_LEN} of [{keys.ID_CHARS}])"
        )


def _id_tuple(values: object, what: str) -> tuple[str, ...]:
    if isinstance(values, str) or not isinstance(values, list | tuple):
        raise PlumbingError(f"{what}: need a list of ids")
    for value in values:
        _check_id(value, what)
    out = tuple(str(v) for v in values)
    if len(set(out)) != len(out):
        raise PlumbingError(f"{what}: duplicate id")
    return out


def _check_number(
    value: object,
    what: str,
    *,
    lo: float | None = None,
    lo_open: bool = False,
    hi: float | None = None,
) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PlumbingError(f"{what}: need a finite number, got {value!r}")
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise PlumbingError(f"{what}: must be {'>' if lo_open else '>='} {lo}, got {value}")
    if hi is not None and value > hi:
        raise PlumbingError(f"{what}: must be <= {hi}, got {value}")
