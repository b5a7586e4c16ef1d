"""Flood benchmark (issue 13): a real RSU daemon and cars under 5000 future paths per second.

Setup: the RSU and every car of the paper scenario run as daemons (own OS processes) on
loopback Zenoh, scouting off, signed with a throw-away authority, as ``crosspath up``
starts them; a monitor process runs one ``rsu``-mode run after the other at speed 1
while they stay up (so a phase is whole runs: at least ``duration_s``). A *flooder* (another OS
process, a Zenoh peer connected to the RSU's and the cars' endpoints, loopback only)
publishes valid-looking future paths that are unsigned or signed by a key no authority
certified: ``ids`` fake vehicle ids (500) in turn, or a new id on every datagram (a pool
of :data:`NEW_ID_POOL` distinct ids, larger than every bound of the receive path), at
``rate_hz`` (5000) for at most the phase's duration: bounded in count and time.

Phases, each ``duration_s`` wall seconds (60 in ``bench``, a few in tests), in one
invocation, after one unmeasured warm-up run: ``baseline`` (no flood), ``flood`` (500
ids), ``flood_new_ids``. Per phase:

- ``decision_ms_p99``: the RSU's receive-to-decision latency, p99 over its runs' worst:
  wall time from a future or autonomous path's arrival on the Zenoh thread to the end
  of ``RsuCore.on_message`` and the sending of what it decided (the ``receive``
  section of the RSU's stats, ``services.edge.transport.ReceiveStats``);
- ``tick_late_ms_max``: the largest lag of any actor's control-loop tick behind its due
  time (``max_tick_lag_s``), per actor in ``tick_late_ms_max_by_node``, the RSU's alone
  in ``rsu_tick_late_ms_max`` (the issue's "its tick"), the p99 of each run's ticks
  likewise (``tick_late_ms_p99_by_node``, ``rsu_tick_late_ms_p99``: the largest of the
  runs' p99s), and ``late_ticks`` (ticks more than a period late);
- ``memory_growth_pct``: per daemon, resident memory at the end of the phase against
  its start (median of the first and of the last :data:`RSS_WINDOW` samples, one every
  :data:`RSS_PERIOD_S`), and the largest of them;
- ``runs``, ``collisions``, ``all_finished``, ``passing_time_s`` (mean over runs, per
  car): the runs were unharmed;
- ``refused`` / ``rate_limited`` / ``overflow``: what the receive paths dropped, and
  ``flood_sent`` what the flooder sent. In a run the daemons declare only the run's
  senders' keys (``DaemonShell.scope_v2x``), so the flood's fake ids reach none of them
  and ``refused`` stays about 0; with more senders than ``MAX_SCOPED_KEYS`` they keep
  the wildcard and refuse each datagram on the network thread instead;
- ``cpu_pct_by_node``: each daemon's CPU time (user + system, ``/proc/<pid>/stat``) over
  the phase's wall time [% of one core]: what receiving the flood costs it.

The figures are only as good as the machine is idle: the daemons, the monitor and the
flooder share its cores (the flooder alone takes most of one), and ``baseline`` shows
what the same machine gives without a flood.

``verified_fp_per_s``: the RSU's throughput of verified future paths on one core
(decode and Ed25519 verification of a signed worst-case future path, in a loop in this
process), when ``services.edge.trust`` is importable.

:func:`flood_section` is what ``bench security`` calls; ``python -m services.bench.flood``
runs it alone.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import multiprocessing
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from protocol import FuturePath, Header, Mode, encode
from protocol import keys as keyexpr
from services.edge.args import output_file, positive_float
from services.model.results import RunResult
from services.supervise.launcher import (
    REPO_ROOT,
    Endpoints,
    actor_commands,
    daemon_env,
    loopback_endpoints,
    make_run_authority,
)

__all__ = [
    "MAX_FLOOD_S",
    "NEW_ID_POOL",
    "FloodSpec",
    "flood_datagrams",
    "flood_section",
    "measure",
    "run_flood",
    "verify_throughput",
]

PAPER: Final = REPO_ROOT / "scenarios" / "paper-blind-intersection.toml"

MAX_FLOOD_S: Final = 300.0
"""A flood never lasts longer than this [wall s], whatever is asked."""

MAX_FLOOD_RATE_HZ: Final = 50_000.0
"""Nor is it faster than this [datagrams per s]."""

NEW_ID_POOL: Final = 20_000
"""Distinct fake ids of the new-id-per-datagram flood (beyond every per-sender bound)."""

RSS_PERIOD_S: Final = 0.5
"""Wall seconds between two samples of every daemon's resident memory."""

RSS_WINDOW: Final = 5
"""Samples whose median is a phase's start (first ones) and end (last ones) memory."""

WARMUP_S: Final = 3.0
"""Wall seconds a phase runs before its memory baseline is taken."""

MAX_RUNS: Final = 50
"""Most runs of one phase (a phase whose monitor writes no result still ends)."""

FLOOD_TAIL_S: Final = 120.0
"""A phase's flood is sized for its duration plus this (the last run may overrun); it
is stopped when the phase's last run is over."""


@dataclass(frozen=True, slots=True)
class FloodSpec:
    """What the flooder sends: ``rate_hz`` datagrams per wall second for ``duration_s``,
    future paths from ``ids`` fake senders in turn, or a new sender each time
    (``new_ids``); ``signed``: signed by an uncertified key (else unsigned)."""

    rate_hz: float = 5000.0
    ids: int = 500
    new_ids: bool = False
    duration_s: float = 10.0
    signed: bool = True
    prefix: str = keyexpr.DEFAULT_PREFIX

    def __post_init__(self) -> None:
        if not 0.0 < self.rate_hz <= MAX_FLOOD_RATE_HZ:
            raise ValueError(f"rate must be in (0, {MAX_FLOOD_RATE_HZ:g}] Hz")
        if not 0.0 < self.duration_s <= MAX_FLOOD_S:
            raise ValueError(f"duration must be in (0, {MAX_FLOOD_S:g}] s")
        if not 1 <= self.ids <= NEW_ID_POOL:
            raise ValueError(f"ids must be in 1..{NEW_ID_POOL}")

    @property
    def max_count(self) -> int:
        """The most datagrams this flood sends."""
        return math.ceil(self.rate_hz * self.duration_s)


def _fake_path(sender: str, seq: int) -> FuturePath:
    """A plausible future path: 40 points, 4 s, on the paper scenario's west approach."""
    n = 40
    pts = np.column_stack(
        [np.linspace(-60.0, -20.0, n), np.full(n, -1.75), np.linspace(0.0, 4.0, n)]
    )
    return FuturePath(
        Header(sender, seq, 1_000_000), -60.0, -1.75, 10.0, 0.0, 4.5, 1.8, Mode.AUTO, pts
    )


def flood_datagrams(spec: FloodSpec) -> list[tuple[str, bytes]]:
    """The (key, payload) pool the flooder cycles through."""
    count = NEW_ID_POOL if spec.new_ids else spec.ids
    sealer = _wrong_sealer() if spec.signed else None
    out: list[tuple[str, bytes]] = []
    for i in range(count):
        sender = f"{'x' if spec.new_ids else 'f'}{i:05d}"
        payload = encode(_fake_path(sender, i + 1))
        if sealer is not None:
            payload = sealer(payload)
        out.append((keyexpr.future_path(sender, prefix=spec.prefix), payload))
    return out


def _wrong_sealer() -> Any:
    """Signs with a fresh key no authority certified (None without ``protocol.auth``)."""
    try:
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        from protocol.auth import seal
    except ImportError:  # pragma: no cover - the signing layer is optional here
        return None
    key = Ed25519PrivateKey.generate()
    return lambda datagram: seal(datagram, key, 0)


def _loopback_only(endpoints: Sequence[str]) -> None:
    for endpoint in endpoints:
        proto, _, rest = endpoint.partition("/")
        if proto not in ("udp", "tcp") or not rest.startswith("127."):
            raise ValueError(f"the flooder only sends to loopback, not to {endpoint!r}")


def run_flood(connect: Sequence[str], spec: FloodSpec, stop: Any = None) -> int:
    """Send the flood to the peers at ``connect`` (loopback locators); datagrams sent.

    Paced in 10 ms slices; stops at ``spec.duration_s``, ``spec.max_count`` or once
    ``stop`` (an event, e.g. a ``multiprocessing.Event``) is set."""
    import zenoh

    _loopback_only(connect)
    pool = flood_datagrams(spec)
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("peer"))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    session = zenoh.open(config)
    sent = 0
    try:
        time.sleep(1.0)  # links up
        start = time.monotonic()
        while sent < spec.max_count and not (stop is not None and stop.is_set()):
            elapsed = time.monotonic() - start
            if elapsed >= spec.duration_s:
                break
            due = min(spec.max_count, int(elapsed * spec.rate_hz))
            while sent < due:
                key, payload = pool[sent % len(pool)]
                session.put(
                    key,
                    payload,
                    congestion_control=zenoh.CongestionControl.DROP,
                    express=True,
                )
                sent += 1
            time.sleep(0.01)
    finally:
        closable: Any = session
        closable.close()
    return sent


def _flood_child(connect: list[str], spec: FloodSpec, result: Any, stop: Any) -> None:
    result.value = run_flood(connect, spec, stop)


# --------------------------------------------------------------------------- daemons


def _rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def _cpu_s(pid: int) -> float | None:
    """CPU time (user + system) a process has used so far [s]: /proc/<pid>/stat."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _actor_argv(
    scenario: Path,
    speed: float,
    endpoints: Mapping[str, Endpoints],
    monitor: str,
    keys_dir: Path | None,
) -> tuple[dict[str, list[str]], list[str]]:
    """Argv of every actor (connected to each other, not to the monitor) and the argv
    head of a monitor that connects to all of them."""
    commands = actor_commands(
        scenario,
        "rsu",
        "paper",
        0,
        speed,
        endpoints,
        monitor=monitor,
        zenoh_options={"transport/link/tx/lease": 2000},
        keys_dir=keys_dir,
    )
    mon = endpoints[monitor].locators
    actors: dict[str, list[str]] = {}
    for node, argv in commands.items():
        if node == monitor:
            continue
        clean: list[str] = []
        skip = False
        for i, arg in enumerate(argv):
            if skip:
                skip = False
                continue
            if arg == "--connect" and i + 1 < len(argv) and argv[i + 1] in mon:
                skip = True
                continue
            clean.append(arg)
        actors[node] = clean
    head = commands[monitor]
    connect: list[str] = []
    for node in actors:
        for locator in endpoints[node].locators:
            connect += ["--connect", locator]
    return actors, head + connect


@dataclass
class _Phase:
    name: str
    results: list[RunResult]
    rss: dict[str, list[int]]
    flood_sent: int
    cpu_pct: dict[str, float]


def _run_phase(
    name: str,
    duration_s: float,
    monitor_head: list[str],
    actors: Mapping[str, subprocess.Popen[bytes]],
    run_dir: Path,
    flood: tuple[list[str], FloodSpec] | None,
) -> _Phase:
    """Runs back to back for ``duration_s`` (the last one may overrun), with the flood."""
    ctx = multiprocessing.get_context("spawn")
    flooder = None
    sent = ctx.Value("q", 0)
    stop = ctx.Event()
    if flood is not None:
        connect, spec = flood
        flooder = ctx.Process(target=_flood_child, args=(connect, spec, sent, stop), daemon=True)
        flooder.start()
        time.sleep(1.5)  # the flood is on before the first run starts
    rss: dict[str, list[int]] = {node: [] for node in actors}
    results: list[RunResult] = []
    cpu_start = {node: _cpu_s(child.pid) for node, child in actors.items()}
    start = time.monotonic()
    warm_until = start + WARMUP_S
    index = 0
    try:
        while (time.monotonic() - start < duration_s or not results) and index < MAX_RUNS:
            index += 1
            out = run_dir / f"{name}-{index}.json"
            argv = [*monitor_head, "--json", str(out), "--run-id", f"{name}-{index}"]
            argv += ["--start-delay", "0.5"]
            with (run_dir / f"monitor-{name}-{index}.log").open("wb") as log:
                proc = subprocess.Popen(
                    argv, cwd=REPO_ROOT, env=daemon_env(), stdout=log, stderr=subprocess.STDOUT
                )
                while proc.poll() is None:
                    if time.monotonic() >= warm_until:
                        for node, child in actors.items():
                            kb = _rss_kb(child.pid)
                            if kb is not None:
                                rss[node].append(kb)
                    time.sleep(RSS_PERIOD_S)
                    if time.monotonic() - start > duration_s + 180.0:
                        proc.kill()
            if out.exists():
                results.append(RunResult.model_validate_json(out.read_bytes()))
        wall = time.monotonic() - start
        cpu_pct: dict[str, float] = {}
        for node, child in actors.items():
            before, after = cpu_start[node], _cpu_s(child.pid)
            if before is not None and after is not None and wall > 0:
                cpu_pct[node] = round((after - before) / wall * 100.0, 1)
    finally:
        if flooder is not None:  # the flood lasts as long as the phase's runs, no longer
            stop.set()
            flooder.join(10.0)
            if flooder.is_alive():
                flooder.terminate()
                flooder.join(5.0)
    return _Phase(name, results, rss, int(sent.value), cpu_pct)


def _growth_pct(samples: Sequence[int]) -> float | None:
    if len(samples) < 2 * RSS_WINDOW:
        return None
    first = statistics.median(samples[:RSS_WINDOW])
    last = statistics.median(samples[-RSS_WINDOW:])
    return round((last - first) / first * 100.0, 2)


def _summary(phase: _Phase, rsu: str) -> dict[str, Any]:
    results = phase.results
    p99s: list[float] = []
    by_node: dict[str, float] = {}
    p99_by_node: dict[str, float] = {}
    late = 0
    dropped = {"refused": 0, "rate_limited": 0, "overflow": 0}
    passing: dict[str, list[float]] = {}
    for result in results:
        actors = result.actors or {}
        for node, entry in actors.items():
            data = entry if isinstance(entry, Mapping) else {}
            lag = data.get("max_tick_lag_s")
            if isinstance(lag, int | float):
                by_node[node] = max(by_node.get(node, 0.0), float(lag))
            lag_p99 = data.get("tick_lag_s_p99")
            if isinstance(lag_p99, int | float):
                p99_by_node[node] = max(p99_by_node.get(node, 0.0), float(lag_p99))
            late += int(data.get("late_ticks") or 0)
            receive = data.get("receive")
            if isinstance(receive, Mapping):
                for label, stats in receive.items():
                    if not isinstance(stats, Mapping):
                        continue
                    for k in dropped:
                        dropped[k] += int(stats.get(k) or 0)
                    p99 = stats.get("latency_ms_p99")
                    if node == rsu and label in ("fp", "ap") and isinstance(p99, int | float):
                        p99s.append(float(p99))
        for vid, vehicle in result.vehicles.items():
            if vehicle.passing_time_s is not None:
                passing.setdefault(vid, []).append(vehicle.passing_time_s)
    growth = {node: _growth_pct(s) for node, s in phase.rss.items()}
    known = [abs(g) for g in growth.values() if g is not None]
    return {
        "runs": len(results),
        "ok_runs": sum(1 for r in results if r.ok),
        "collisions": sum(r.collisions for r in results),
        "all_finished": bool(results) and all(r.all_finished for r in results),
        "decision_ms_p99": max(p99s) if p99s else None,
        "tick_late_ms_max": round(max(by_node.values()) * 1e3, 2) if by_node else None,
        "tick_late_ms_max_by_node": {n: round(v * 1e3, 2) for n, v in sorted(by_node.items())},
        "rsu_tick_late_ms_max": round(by_node[rsu] * 1e3, 2) if rsu in by_node else None,
        "tick_late_ms_p99_by_node": {n: round(v * 1e3, 2) for n, v in sorted(p99_by_node.items())},
        "rsu_tick_late_ms_p99": (round(p99_by_node[rsu] * 1e3, 2) if rsu in p99_by_node else None),
        "late_ticks": late,
        "memory_growth_pct": growth,
        "memory_growth_pct_max": max(known) if known else None,
        "memory_kb_end": {n: (s[-1] if s else None) for n, s in phase.rss.items()},
        "passing_time_s": {v: round(statistics.fmean(t), 3) for v, t in sorted(passing.items())},
        "cpu_pct_by_node": dict(sorted(phase.cpu_pct.items())),
        "flood_sent": phase.flood_sent,
        **dropped,
    }


def measure(
    duration_s: float = 60.0,
    rate_hz: float = 5000.0,
    ids: int = 500,
    *,
    speed: float = 1.0,
    scenario: Path = PAPER,
    run_dir: Path | None = None,
    phases: Sequence[str] = ("baseline", "flood", "flood_new_ids"),
    insecure: bool = False,
    warm_up: bool = True,
) -> dict[str, Any]:
    """Run the phases (module docstring) against fresh daemons, signed with a throw-away
    authority unless ``insecure``; their summaries. ``warm_up=False`` skips the unmeasured
    first run (its only use is the memory figure: tests that check counts skip it)."""
    from services.model.scenario import load_scenario

    sc = load_scenario(scenario)
    rsu = sc.rsus[0].id
    nodes = ["monitor", *(r.id for r in sc.rsus), *(v.id for v in sc.vehicles)]
    endpoints = loopback_endpoints(nodes)
    directory = Path(tempfile.mkdtemp(prefix="crosspath-flood-")) if run_dir is None else run_dir
    directory.mkdir(parents=True, exist_ok=True)
    keys_dir = None if insecure else make_run_authority(directory / "keys", sc)
    actor_argv, monitor_head = _actor_argv(scenario, speed, endpoints, "monitor", keys_dir)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    logs = []
    out: dict[str, Any] = {
        "duration_s": duration_s,
        "rate_hz": rate_hz,
        "ids": ids,
        "speed": speed,
        "signed": not insecure,
        "run_dir": str(directory),
    }
    try:
        for node, argv in actor_argv.items():
            log = (directory / f"{node}.log").open("wb")
            logs.append(log)
            procs[node] = subprocess.Popen(
                argv,
                cwd=REPO_ROOT,
                env=daemon_env(),
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
            time.sleep(0.3)
        time.sleep(2.0)
        connect = [loc for node in actor_argv for loc in endpoints[node].locators]
        # one unmeasured run first: a daemon's first run allocates what it keeps (imports,
        # caches), which would read as growth of the first phase
        if warm_up:
            _run_phase("warmup", 0.0, monitor_head, procs, directory, None)
        for name in phases:
            flood = None
            if name != "baseline":
                spec = FloodSpec(
                    rate_hz=rate_hz,
                    ids=ids,
                    new_ids=name == "flood_new_ids",
                    duration_s=min(MAX_FLOOD_S, duration_s + FLOOD_TAIL_S),
                )
                flood = (connect, spec)
            phase = _run_phase(name, duration_s, monitor_head, procs, directory, flood)
            out[name] = _summary(phase, rsu)
        out["crashed"] = sorted(n for n, p in procs.items() if p.poll() is not None)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        for proc in procs.values():
            try:
                proc.wait(10.0)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        for log in logs:
            log.close()
    return out


def verify_throughput(seconds: float = 1.0) -> float | None:
    """Signed worst-case future paths decoded and verified per second on one core (this
    thread), or None without the signing layer."""
    try:
        from protocol import Kind, decode, max_points
        from services.edge.trust import Authority, Signer, TrustStore
    except ImportError:  # pragma: no cover
        return None
    with tempfile.TemporaryDirectory() as tmp:
        authority = Authority.init(Path(tmp))
        authority.issue_vehicle("A")
        creds = authority.credentials("A")
    signer = Signer(creds, cert_every_s=1e9)
    n = max_points(Kind.FUTURE_PATH)
    pts = np.column_stack(
        [np.linspace(-200.0, 200.0, n), np.full(n, -1.75), np.linspace(0.0, 10.0, n)]
    )
    store = TrustStore(creds.root)
    first = signer.seal(encode(_path("A", 1, pts)))
    store.verify_datagram(first, decode(first))  # the certificate is cached from now on
    datagrams = [signer.seal(encode(_path("A", seq, pts))) for seq in range(2, 20_002)]
    done = 0
    start = time.perf_counter()
    while done < len(datagrams) and time.perf_counter() - start < seconds:
        datagram = datagrams[done]
        store.verify_datagram(datagram, decode(datagram))
        done += 1
    return round(done / (time.perf_counter() - start), 1)


def _path(sender: str, seq: int, pts: Any) -> FuturePath:
    return FuturePath(
        Header(sender, seq, seq * 100_000), -200.0, -1.75, 10.0, 0.0, 4.5, 1.8, Mode.AUTO, pts
    )


def flood_section(
    duration_s: float = 60.0, rate_hz: float = 5000.0, ids: int = 500
) -> dict[str, Any]:
    """The keys ``bench security`` writes: ``flood_decision_latency_ms_p99``,
    ``flood_memory_growth_pct``, ``flood_tick_late_ms_max``, their ``baseline_*`` from
    the same run, ``verified_fp_per_s`` and the full per-phase summaries (``flood``)."""
    data = measure(duration_s, rate_hz, ids)
    flood = data.get("flood", {})
    new_ids = data.get("flood_new_ids", {})
    base = data.get("baseline", {})

    def worst(key: str) -> float | None:
        values = [p.get(key) for p in (flood, new_ids)]
        known = [float(v) for v in values if isinstance(v, int | float)]
        return max(known) if known else None

    return {
        "flood_decision_latency_ms_p99": worst("decision_ms_p99"),
        "flood_memory_growth_pct": worst("memory_growth_pct_max"),
        "flood_tick_late_ms_max": worst("tick_late_ms_max"),
        "flood_rsu_tick_late_ms_max": worst("rsu_tick_late_ms_max"),
        "flood_rsu_tick_late_ms_p99": worst("rsu_tick_late_ms_p99"),
        "baseline_decision_latency_ms_p99": base.get("decision_ms_p99"),
        "baseline_memory_growth_pct": base.get("memory_growth_pct_max"),
        "baseline_tick_late_ms_max": base.get("tick_late_ms_max"),
        "baseline_rsu_tick_late_ms_max": base.get("rsu_tick_late_ms_max"),
        "baseline_rsu_tick_late_ms_p99": base.get("rsu_tick_late_ms_p99"),
        "verified_fp_per_s": verify_throughput(),
        "flood": data,
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m services.bench.flood [--duration S] [--json OUT]``."""
    parser = argparse.ArgumentParser(prog="python -m services.bench.flood")
    parser.add_argument("--duration", type=positive_float, default=60.0, metavar="S")
    parser.add_argument("--rate", type=positive_float, default=5000.0, metavar="HZ")
    parser.add_argument("--json", type=output_file, metavar="OUT")
    args = parser.parse_args(argv)
    doc = flood_section(args.duration, args.rate)
    text = json.dumps(doc, indent=2)
    sys.stdout.write(text + "\n")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
