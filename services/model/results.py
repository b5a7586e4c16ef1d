"""The run result: one typed record of one run, whichever harness ran it.

Every producer builds a :class:`RunResult` (the in-process harness,
``services.sim.harness``; the monitor daemon, ``services.daemons.monitor``; the
network lab, ``services.supervise.lab.runner``) and every reader reads its
attributes, so mypy sees a renamed field. On disk it is JSON with the keys of
DESIGN.md ("Command-line contract"): :meth:`RunResult.to_json` writes it,
:meth:`RunResult.model_validate_json` reads it back (a lossless round trip), and
``docs/run-result.schema.json`` is its JSON schema (a test keeps it equal to
:func:`schema_json`).

Units: metres, seconds, m/s; a probability or share is a fraction 0..1. No
value is NaN or infinite: an unmeasured gap or PET is ``None`` (JSON ``null``).

Sections that only some runs have are ``None`` and then *absent* from the JSON
(not ``null``), so every file keeps the shape it had before the result was
typed: daemon runs add ``run_id``, ``speed``, ``end_reason``, ``truth``,
``final_stats``, ``network``, ``epoch_unix``, ``actors``, ``degraded``,
``truth_gaps``, ``late_ticks`` (and ``expect_crash``, ``crashes``,
``trace_fields``, ``trace``, ``error``, ``rebuilt_from`` when they apply); lab runs
add ``lab``; in-process and lab runs add ``loss``. ``provenance`` says what
produced the run: package version, git commit when known, the scenario's name,
file and sha256, every channel parameter, the policy and its parameters.

Traffic (in-process runs): each car gains ``insertion_delay_s`` (arrival to insertion at
its route's start: SUMO's depart delay) and ``delay_s`` (finish time minus arrival minus
the free-flow time of its route from rest to rest under its limits and the curve speed
caps, so travel time beyond free flow plus the insertion wait; clipped at 0; None when
the car did not finish), both absent when not measured; the run gains ``summary``
(:class:`RunSummary`): ``vehicles_inserted`` (cars that entered the world),
``vehicles_finished``, ``all_finished``, ``mean_delay_s`` and ``p95_delay_s`` (over the
finished cars; None if none; p95 by linear interpolation), ``throughput_vph``
(finished cars x 3600 / ``sim_s``), ``stops_per_vehicle`` (mean ``stops`` over the
inserted cars; None if none). Definitions in ``services.sim.metrics``.

Decisions where the issue was silent: ``delivery_ratio`` is not a fraction (a
stream's duplicates, or counts lost with a crashed daemon, push it above 1; see
``services.edge.stats.network_section``), so it is only ``>= 0``; ``actors`` and
``lab`` are free-form JSON objects (what each daemon's stats report and the lab
runner carry; documented where they are produced); ``loss`` is kept at the top
level beside ``provenance.channel.loss`` because today's readers look there.

This module is pure (no I/O): the package version, the git commit and the
scenario file's digest are found at the I/O edge (``services.edge.provenance``)
and passed in as an :class:`Origin`.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Final, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializationInfo,
    SerializerFunctionWrapHandler,
    model_serializer,
)

from services.model.types import Policy, RunMode

__all__ = [
    "ChannelParams",
    "CrashEvent",
    "NetworkSection",
    "Origin",
    "Provenance",
    "RunResult",
    "RunSummary",
    "StreamSummary",
    "SumoSection",
    "SumoVehicle",
    "TruthCounts",
    "VehicleResult",
    "schema_json",
]

Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
"""A probability or share, 0..1."""
NonNegative = Annotated[float, Field(ge=0.0)]
"""A finite number >= 0 (metres, seconds, m/s, kbit/s, ms)."""
Count = Annotated[int, Field(ge=0)]
Sha256 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
TraceRow = tuple[float | str, ...]
"""One row of a per-step trace; the columns are named by ``trace_fields``."""
Knob = bool | int | float | str | None
"""One scalar configuration value."""


class _Frozen(BaseModel):
    """Immutable, unknown keys refused, no NaN or infinity anywhere."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, allow_inf_nan=False, use_attribute_docstrings=True
    )


class VehicleResult(_Frozen):
    """One car's outcome: ``passing_time_s`` from 10 m after its start to 100 m after the
    intersection centre (None if it did not get there); ``first_through`` whether it
    crossed the conflict zone first; ``stops`` how often it came to a standstill on the
    way; ``max_speed_mps`` its top speed; ``finished`` whether it reached its goal;
    ``delay_s`` and ``insertion_delay_s`` as in the module docstring (absent when None)."""

    passing_time_s: NonNegative | None
    first_through: bool
    stops: Count
    max_speed_mps: NonNegative | None
    finished: bool
    delay_s: NonNegative | None = None
    insertion_delay_s: NonNegative | None = None

    @model_serializer(mode="wrap")
    def _omit_unmeasured(
        self, handler: SerializerFunctionWrapHandler, _info: SerializationInfo
    ) -> dict[str, Any]:
        data: dict[str, Any] = handler(self)
        for name in ("delay_s", "insertion_delay_s"):
            if data.get(name, 0) is None:
                del data[name]
        return data


class RunSummary(_Frozen):
    """Traffic figures of one run (module docstring: definitions)."""

    vehicles_inserted: Count
    vehicles_finished: Count
    all_finished: bool
    mean_delay_s: NonNegative | None
    p95_delay_s: NonNegative | None
    throughput_vph: NonNegative | None
    stops_per_vehicle: NonNegative | None


class SumoVehicle(_Frozen):
    """One SUMO vehicle of a co-simulation (``crosspath sumo``, ``services.sumo.cosim``):
    its SUMO id, whether crosspath drove it (``connected``), SUMO's own ``time_loss_s``
    and ``depart_delay_s`` from its tripinfo (None when it did not arrive)."""

    sumo_id: str
    connected: bool
    time_loss_s: NonNegative | None
    depart_delay_s: NonNegative | None


class SumoSection(_Frozen):
    """A co-simulation's SUMO side (``services.sumo.cosim`` defines each figure):
    the network and routes files, SUMO's step [s], the share of vehicles drawn as
    connected, SUMO's own colliding pairs, its mean ``timeLoss`` over the arrived
    vehicles, and each vehicle by its crosspath id."""

    net: str
    routes: str
    step_s: Annotated[float, Field(gt=0.0)]
    connected_share: Fraction
    connected: Count
    collisions: Count
    mean_time_loss_s: NonNegative | None
    vehicles: dict[str, SumoVehicle]


class StreamSummary(_Frozen):
    """One V2X stream of a daemon run (``services.edge.stats.network_section``).

    Not ``services.edge.stats.StreamStats``, the per-node counters this sums.
    ``msgs``/``bytes``: datagrams and payload bytes sent over all nodes; the ``_rx``
    counters what was received; ``kbps_per_vehicle`` offered load per car per run
    second; one-way latencies in wall milliseconds (None when nothing arrived);
    ``delivery_ratio`` received over expected receptions (None when nothing was sent).
    """

    msgs: Count
    bytes: Count
    msgs_rx: Count
    bytes_rx: Count
    malformed: Count
    dropped_stale: Count
    kbps_per_vehicle: NonNegative
    latency_ms_p50: NonNegative | None
    latency_ms_p99: NonNegative | None
    latency_ms_mean: NonNegative | None
    delivery_ratio: NonNegative | None


class NetworkSection(BaseModel):
    """A daemon run's ``network``: one :class:`StreamSummary` per stream name (``fp``,
    ``ap``, ``cmd``, ``beacon``, ...) beside ``total_kbps_per_vehicle``, the one entry
    that is not a stream. The stream names are keys of the JSON object, as written
    today; every one is validated as a :class:`StreamSummary`."""

    model_config = ConfigDict(
        extra="allow", frozen=True, allow_inf_nan=False, use_attribute_docstrings=True
    )
    __pydantic_extra__: dict[str, StreamSummary] = Field(init=False)

    total_kbps_per_vehicle: NonNegative

    @property
    def streams(self) -> dict[str, StreamSummary]:
        """Every stream by name (a copy)."""
        return dict(self.__pydantic_extra__ or {})

    def stream(self, name: str) -> StreamSummary | None:
        """The stream ``name``, or None when the run had none of it."""
        return (self.__pydantic_extra__ or {}).get(name)


class TruthCounts(_Frozen):
    """How the monitor assembled the ground truth: physics ``steps`` recorded, car
    reports missing at their step (``gaps``, never filled in: the sum of
    ``truth_gaps``) and reports that came after their step was closed (``late``;
    still that step's truth, so they count in the safety metrics)."""

    steps: Count
    gaps: Count
    late: Count


class CrashEvent(_Frozen):
    """A node's liveliness ``lost`` or ``back`` at run time ``t_s``: an expected crash node's
    (the monitor), or an actor the launcher saw exit unexpectedly (``lost`` only)."""

    node: str
    event: Literal["lost", "back"]
    t_s: float | None


class ChannelParams(_Frozen):
    """The V2X channel of a run.

    ``kind``: ``memory`` (the in-process harness's seeded channel: ``loss`` per
    receiver, one-way ``latency_s`` plus uniform ``jitter_s``), ``zenoh`` (real
    daemons over a real network: latency and jitter are the network's own, measured in
    ``network``, so None here; ``loss`` 0 as none is injected) or ``lab`` (daemons in
    the network lab: ``loss`` injected on every radio interface, optional Gilbert
    ``burst`` [packets] and ``rate_mbit`` limit).
    """

    kind: Literal["memory", "zenoh", "lab"]
    loss: Fraction = 0.0
    latency_s: NonNegative | None = None
    jitter_s: NonNegative | None = None
    burst: Annotated[float, Field(ge=1.0)] | None = None
    rate_mbit: Annotated[float, Field(gt=0.0)] | None = None


class Origin(_Frozen):
    """Where the code and the scenario of a run came from, found at the I/O edge
    (``services.edge.provenance.origin``) and handed to the pure harness. Every field
    is None when unknown."""

    version: str | None = None
    """The ``crosspath`` package version."""
    commit: str | None = None
    """The git commit of the source tree, when it is a checkout."""
    scenario_file: str | None = None
    """The scenario file's path as given."""
    scenario_sha256: Sha256 | None = None
    """sha256 of the scenario file's bytes."""


class Provenance(_Frozen):
    """What produced a run: code, scenario, channel and RSU policy with every knob.

    ``policy_params`` maps each RSU of the run to the scalar fields of its
    ``RsuConfig`` (``services.rsu.config``: margins, horizons, the ``slot`` and hold
    knobs, ...; its geometry left out); empty when no RSU ran.
    """

    version: str | None
    commit: str | None
    scenario: str
    scenario_file: str | None
    scenario_sha256: Sha256 | None
    channel: ChannelParams
    policy: Policy | None
    policy_params: dict[str, dict[str, Knob]] = Field(default_factory=dict)


_OPTIONAL: Final = frozenset(
    {
        "loss",
        "run_id",
        "speed",
        "end_reason",
        "truth",
        "final_stats",
        "network",
        "epoch_unix",
        "actors",
        "expect_crash",
        "crashes",
        "trace_fields",
        "trace",
        "error",
        "degraded",
        "truth_gaps",
        "late_ticks",
        "rebuilt_from",
        "lab",
        "provenance",
        "summary",
        "sumo",
    }
)
"""Sections written only when set (absent from the JSON when None)."""


class RunResult(_Frozen):
    """One run's result (see the module docstring). The first block is what every run
    has; then the sections of daemon and lab runs, and the provenance."""

    mode: RunMode
    policy: Policy | None
    """The RSU's velocity policy; None unless ``mode`` is ``rsu``."""
    seed: Count
    collisions: Count
    min_gap_m: NonNegative | None
    """Smallest distance between two footprints over the run; None if never measured."""
    min_pet_s: NonNegative | None
    """Smallest post-encroachment time in a conflict zone; None if no two cars crossed."""
    min_conflict_pet_s: NonNegative | None
    """Smallest post-encroachment time at a conflict area, where two cars' paths meet
    (``services.sim.metrics``): at merges ``min_pet_s`` counts any joint occupancy of
    the zone; None if no two conflicting cars both reached their area."""
    sim_s: NonNegative
    """Run time simulated [s]."""
    wall_s: NonNegative
    """Wall time the run took [s]."""
    mean_passing_time_s: NonNegative | None
    all_finished: bool
    vehicles: dict[str, VehicleResult]
    scenario: str
    """The scenario's name."""
    start_times: dict[str, NonNegative]
    """Each car's start [run s]."""
    harness: Literal["in-process", "daemons"]
    speedup_vs_real_time: NonNegative | None

    loss: Fraction | None = None
    """V2X loss probability per receiver (in-process and lab runs)."""
    run_id: str | None = None
    speed: Annotated[float, Field(gt=0.0)] | None = None
    """Run seconds per wall second (daemon runs)."""
    end_reason: str | None = None
    truth: TruthCounts | None = None
    final_stats: list[str] | None = None
    """Nodes whose final stats report arrived."""
    network: NetworkSection | None = None
    epoch_unix: float | None = None
    """Wall clock (Unix s) of run time 0."""
    actors: dict[str, dict[str, Any]] | None = None
    """Per node: ``final``, ``v2x`` totals and whatever its stats reports carried."""
    expect_crash: list[str] | None = None
    crashes: list[CrashEvent] | None = None
    trace_fields: list[str] | None = None
    trace: list[TraceRow] | None = None
    error: str | None = None
    """Why the run failed; None when it completed."""
    degraded: bool | None = None
    """Daemon runs: the run is not a clean measurement, its safety metrics may miss
    something: some car's truth is missing at some step (``truth_gaps``) or some
    actor's control loop ran more than a tick behind the run clock (``late_ticks``)."""
    truth_gaps: dict[str, Count] | None = None
    """Per car, recorded physics steps its ground truth is missing from (daemon runs;
    never filled in from another step: those steps measure nothing for its pairs)."""
    late_ticks: dict[str, Count] | None = None
    """Per actor, control-loop ticks that ran more than one tick period behind the run
    clock (from its stats; daemon runs)."""
    rebuilt_from: str | None = None
    """The step log this result was rebuilt from (``crosspath results rebuild``)."""
    lab: dict[str, Any] | None = None
    """The network lab's section (``services.supervise.lab.runner``)."""
    provenance: Provenance | None = None
    summary: RunSummary | None = None
    """Traffic figures (in-process runs)."""
    sumo: SumoSection | None = None
    """SUMO's side of a co-simulation (``crosspath sumo``)."""

    @model_serializer(mode="wrap")
    def _omit_absent_sections(
        self, handler: SerializerFunctionWrapHandler, _info: SerializationInfo
    ) -> dict[str, Any]:
        data: dict[str, Any] = handler(self)
        for name in _OPTIONAL:
            if data.get(name, 0) is None:
                del data[name]
        return data

    @classmethod
    def failed(
        cls,
        *,
        mode: RunMode | str,
        policy: Policy | str | None,
        seed: int,
        scenario: str,
        harness: Literal["in-process", "daemons"],
        error: str,
        **sections: Any,
    ) -> RunResult:
        """The result of a run that recorded nothing (no car, no step): ``error`` says why."""
        return cls.model_validate(
            {
                "mode": mode,
                "policy": policy,
                "seed": seed,
                "collisions": 0,
                "min_gap_m": None,
                "min_pet_s": None,
                "min_conflict_pet_s": None,
                "sim_s": 0.0,
                "wall_s": 0.0,
                "mean_passing_time_s": None,
                "all_finished": False,
                "vehicles": {},
                "scenario": scenario,
                "start_times": {},
                "harness": harness,
                "speedup_vs_real_time": None,
                "error": error,
                **sections,
            }
        )

    @property
    def ok(self) -> bool:
        """The run completed (no ``error``)."""
        return self.error is None

    def to_dict(self) -> dict[str, Any]:
        """The JSON-able form (the keys of the file on disk)."""
        return self.model_dump(mode="json")

    def to_json(self, indent: int | None = 2) -> str:
        """Strict JSON (no NaN) with the keys of DESIGN.md; no final newline."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    def updated(self, **changes: Any) -> RunResult:
        """A copy with ``changes``, validated again (``model_copy`` would not validate)."""
        return RunResult.model_validate({**dict(self), **changes})

    def without_trace(self) -> RunResult:
        """The same result without ``trace`` and ``trace_fields``."""
        return self.updated(trace=None, trace_fields=None)

    def trace_columns(self) -> dict[str, int]:
        """Column index of each name in ``trace_fields`` (empty without a trace)."""
        return {name: i for i, name in enumerate(self.trace_fields or ())}


def schema_json() -> str:
    """The JSON schema of :class:`RunResult` as written to ``docs/run-result.schema.json``."""
    return json.dumps(RunResult.model_json_schema(), indent=2, sort_keys=True) + "\n"
