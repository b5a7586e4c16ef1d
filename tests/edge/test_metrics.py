"""Prometheus metrics: scraped over HTTP from real daemons, totals that never go down,
the same numbers as the run result, systemd readiness, and the Grafana dashboard."""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from services.daemons.host import host_configs
from services.daemons.monitor import MonitorConfig, MonitorService
from services.daemons.rsu import RsuDaemon, RsuDaemonConfig
from services.daemons.vehicle import VehicleDaemon, VehicleDaemonConfig
from services.edge.lifecycle import EXIT_CONFIG, ServiceExit, serve
from services.edge.metrics import (
    LATENCY_BUCKETS_S,
    METRICS,
    Carry,
    DaemonMetrics,
    _histogram_values,
    _rebucket,
)
from services.edge.notify import notify, notify_socket_address
from services.edge.settings import ZenohSettings
from services.edge.stats import LatencyHistogram
from services.edge.transport import V2X_QOS, MemoryBus, MemoryTransport, ZenohTransport
from services.model.scenario import load_scenario
from services.model.types import RunMode
from services.supervise.launcher import free_ports
from tests.daemons.test_daemons import PAPER, config

REPO = Path(__file__).resolve().parents[2]
DASHBOARD = REPO / "deploy" / "grafana" / "crosspath-dashboard.json"
DAEMON = (sys.executable, "-m", "services.cli.main")
METRICS_HOST = ("--metrics-host", "127.0.0.1")

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def parse(text: str) -> Samples:
    """Every sample of a scrape: (name, labels) -> value."""
    out: Samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def total(samples: Samples, name: str, **labels: str) -> float:
    """Sum of ``name`` over the series whose labels include ``labels``."""
    want = set(labels.items())
    return sum(v for (n, ls), v in samples.items() if n == name and want <= ls)


async def scrape_async(port: int, path: str = "/metrics") -> tuple[int, str]:
    """GET over loopback from inside the serving loop (a blocking client would stall it)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n".encode())
    await writer.drain()
    data = await asyncio.wait_for(reader.read(), 10.0)
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body.decode()


def scrape(port: int) -> Samples:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        assert response.status == 200
        assert response.headers["Content-Type"].startswith("text/plain; version=")
        return parse(response.read().decode())


# --------------------------------------------------------------------------- pieces


def test_carry_keeps_totals_monotone_across_replaced_counters() -> None:
    carry = Carry()
    run1 = {"x": 3}
    assert carry.read("s", run1, dict) == {"x": 3}
    run1["x"] = 5  # counted after the last read, before the run's counters are replaced
    assert carry.read("s", None, dict) == {"x": 5}
    run2 = {"x": 1, "y": 2}
    assert carry.read("s", run2, dict) == {"x": 6, "y": 2}
    assert carry.read("s", run2, dict) == {"x": 6, "y": 2}  # same object: not added twice
    run3: dict[str, int] = {}
    assert carry.read("s", run3, dict) == {"x": 6, "y": 2}


def test_latency_buckets_are_cumulative_and_never_overcount() -> None:
    hist = LatencyHistogram()
    samples = [0.0, 0.0003, 0.0009, 0.004, 0.02, 0.02, 0.3, 5.0]
    for s in samples:
        hist.add(s)
    buckets = dict(_rebucket(_histogram_values(hist), LATENCY_BUCKETS_S))
    assert buckets["+Inf"] == len(samples)
    counts = [buckets[repr(float(b))] for b in LATENCY_BUCKETS_S]
    assert counts == sorted(counts)
    for bound, got in zip(LATENCY_BUCKETS_S, counts, strict=True):
        exact = sum(1 for s in samples if s <= bound)
        below = sum(1 for s in samples if s <= bound / 1.048)  # one source bucket lower
        assert below <= got <= exact, bound
    assert buckets["0.001"] == 3 and buckets["0.025"] == 6


async def test_a_port_in_use_is_one_line_and_exit_78() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ServiceExit) as info:
            await DaemonMetrics("A", "vehicle").serve("127.0.0.1", port)
    assert info.value.exit_code == EXIT_CONFIG
    assert f"metrics endpoint 127.0.0.1:{port}: " in str(info.value)


def test_notify_speaks_to_the_socket_systemd_names(tmp_path: Path) -> None:
    assert notify("READY=1", {}) is False  # not under systemd: a no-op
    assert notify_socket_address({"NOTIFY_SOCKET": "@abc"}) == b"\0abc"
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        assert notify("READY=1\nSTATUS=running", {"NOTIFY_SOCKET": path}) is True
        assert sock.recv(4096) == b"READY=1\nSTATUS=running"
    assert notify("READY=1", {"NOTIFY_SOCKET": path}) is False  # nobody listens: logged


def test_cars_sharing_a_process_get_a_metrics_port_each() -> None:
    cfg = config(
        VehicleDaemonConfig,
        node_id="A",
        scenario=str(PAPER),
        metrics_port=9500,
        **{"zenoh.listen": ["tcp/127.0.0.1:7001", "tcp/127.0.0.1:7002"]},
    )
    assert [c.metrics_port for c in host_configs(cfg, ["A", "B"])] == [9500, 9501]
    free = cfg.model_copy(update={"metrics_port": 0})
    assert [c.metrics_port for c in host_configs(free, ["A", "B"])] == [0, 0]


# --------------------------------------------------------------------------- a whole run


async def test_a_run_shows_in_every_actors_metrics_as_in_its_result() -> None:
    """Every actor of a memory-bus run serves its metrics; after two runs the counters
    are the sums of both runs' network sections (never reset), and the cores' decisions
    and mode changes show."""
    scenario = load_scenario(PAPER)
    bus = MemoryBus()
    stop = asyncio.Event()
    actors: list[VehicleDaemon | RsuDaemon] = []
    for v in scenario.vehicles:
        cfg = config(VehicleDaemonConfig, node_id=v.id, scenario=str(PAPER), metrics_port=0)
        actors.append(VehicleDaemon(cfg, scenario, MemoryTransport(bus)))
    for r in scenario.rsus:
        rcfg = config(RsuDaemonConfig, node_id=r.id, scenario=str(PAPER), metrics_port=0)
        actors.append(RsuDaemon(rcfg, scenario, MemoryTransport(bus)))
    tasks = [asyncio.ensure_future(serve(a, install_signals=False, stop=stop)) for a in actors]
    fp_sent = 0
    try:
        # an rsu run at the speed the daemon tests use, then a quicker fp-only one
        for seed, mode, speed in ((1, RunMode.RSU, 10.0), (2, RunMode.FP_ONLY, 20.0)):
            mcfg = config(
                MonitorConfig,
                scenario=str(PAPER),
                mode=str(mode),
                seed=seed,
                start_delay_s=0.2,
                stats_wait_s=5.0,
                run_id=f"metrics-{seed}",
                **{"time.speed": speed},
            )
            monitor = MonitorService(mcfg, scenario, MemoryTransport(bus))
            assert await serve(monitor, install_signals=False) == 0
            assert monitor.result is not None and monitor.result.network is not None
            assert monitor.result.mode is mode and monitor.result.error is None
            fp = monitor.result.network.stream("fp")
            assert fp is not None
            fp_sent += fp.msgs
            await asyncio.sleep(0.5)  # the actors' end of run (drain, final report)
        scraped: dict[str, Samples] = {}
        for actor in actors:
            server = actor.shell._metrics_server
            assert server is not None and server.port is not None
            status, body = await scrape_async(server.port)
            assert status == 200
            scraped[actor.node] = parse(body)
            assert (await scrape_async(server.port, "/nope"))[0] == 404
    finally:
        stop.set()
        codes = await asyncio.gather(*tasks)
    assert codes == [0] * len(actors)
    cars = [v.id for v in scenario.vehicles]
    rsu = scenario.rsus[0].id
    # the same datagrams as the two results' network sections, summed over both runs
    sent = sum(total(scraped[c], "crosspath_v2x_sent_messages_total", stream="fp") for c in cars)
    assert sent == fp_sent > 0
    for node, samples in scraped.items():
        assert total(samples, "crosspath_daemon_info", node=node) == 1.0
        assert total(samples, "crosspath_run_active") == 0.0
        assert total(samples, "process_resident_memory_bytes") > 0
        ticks = total(samples, "crosspath_ticks_total", node=node)
        assert ticks > 0
        assert total(samples, "crosspath_tick_lag_seconds_count", node=node) == ticks
    rsu_samples = scraped[rsu]
    assert total(rsu_samples, "crosspath_v2x_received_messages_total", stream="fp") > 0
    assert total(rsu_samples, "crosspath_v2x_latency_seconds_count", stream="fp") > 0
    assert total(rsu_samples, "crosspath_receive_delivered_messages_total", stream="fp") > 0
    assert total(rsu_samples, "crosspath_rsu_decisions_total") > 0
    assert total(rsu_samples, "crosspath_rsu_actions_total", action="initiation") > 0
    assert total(rsu_samples, "crosspath_rsu_conflicts_total") >= 0
    names = {name for samples in scraped.values() for name, _labels in samples}
    names |= {n.removesuffix("_count") for n in names}  # a histogram's family name
    assert set(METRICS) - {"crosspath_zenoh_links"} <= names  # (no Zenoh on a memory bus)
    modes = sum(total(scraped[c], "crosspath_mode_changes_total") for c in cars)
    commands = sum(
        total(scraped[c], "crosspath_v2x_received_messages_total", stream="cmd") for c in cars
    )
    # a car that got the RSU's commands changed mode (none arrive in time only when the
    # machine is so loaded that every command is stale)
    assert modes > 0 or commands == 0
    assert all(total(scraped[c], "crosspath_vehicle_mode") == 0.0 for c in cars)  # no run: no mode


# --------------------------------------------------------------------------- real processes


def _env(**extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), **extra}


def _wait_notify(sock: socket.socket, want: bytes, proc: subprocess.Popen[str]) -> None:
    deadline = time.monotonic() + 60.0
    got: list[bytes] = []
    while time.monotonic() < deadline:
        sock.settimeout(0.5)
        try:
            got.append(sock.recv(4096))
        except TimeoutError:
            assert proc.poll() is None, proc.communicate()[1]
            continue
        if any(want in g for g in got):
            return
    raise AssertionError(f"no {want!r} from the daemon, got {got}")


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        yield sock, path


@pytest.mark.daemons
def test_a_daemon_process_is_ready_then_serves_its_metrics(
    tmp_path: Path, notify_socket: tuple[socket.socket, str]
) -> None:
    """``crosspath rsu --metrics-port P`` under a fake systemd: READY=1 once it listens,
    the scrape shows what a peer sent wrong, STOPPING=1 and exit 0 on SIGTERM."""
    sock, path = notify_socket
    ((_udp, tcp), (mport, _)) = free_ports(2)
    endpoint = f"tcp/127.0.0.1:{tcp}"
    cfg = tmp_path / "rsu.toml"
    cfg.write_text(
        f'node_id = "rsu1"\nscenario = "{PAPER}"\nmetrics_host = "127.0.0.1"\n'
        f'[zenoh]\nlisten = ["{endpoint}"]\n'
    )
    proc = subprocess.Popen(
        [*DAEMON, "rsu", "--config", str(cfg), "--metrics-port", str(mport)],
        cwd=REPO,
        env=_env(NOTIFY_SOCKET=path),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    loop = asyncio.new_event_loop()  # the peer only publishes: nothing runs on it
    peer = ZenohTransport(ZenohSettings(connect=[endpoint]), loop=loop)
    try:
        _wait_notify(sock, b"READY=1", proc)
        first = scrape(mport)  # ready means listening: no retry needed
        assert total(first, "crosspath_daemon_info", node="rsu1", service="rsu") == 1.0
        assert total(first, "crosspath_v2x_sent_messages_total") == 0.0
        peer.open()
        deadline = time.monotonic() + 20.0
        while True:  # garbage on a car's future-path key: counted, dropped
            peer.publish("crosspath/v2x/fp/A", b"\x00garbage", V2X_QOS)
            samples = scrape(mport)
            if total(samples, "crosspath_dropped_messages_total", stream="fp") > 0:
                break
            assert time.monotonic() < deadline, "the daemon never counted the garbage"
            time.sleep(0.2)
        assert total(samples, "crosspath_zenoh_links", node="rsu1") >= 1
        assert total(samples, "crosspath_receive_offered_messages_total", stream="fp") > 0
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(f"http://127.0.0.1:{mport}/other", timeout=10)
        assert info.value.code == 404
        proc.send_signal(signal.SIGTERM)
        _wait_notify(sock, b"STOPPING=1", proc)
        _out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
    finally:
        peer.close()
        loop.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.daemons
def test_the_router_serves_metrics_and_notifies(
    notify_socket: tuple[socket.socket, str],
) -> None:
    sock, path = notify_socket
    ((_udp, tcp), (mport, _)) = free_ports(2)
    listen = f"tcp/127.0.0.1:{tcp}"
    proc = subprocess.Popen(
        [*DAEMON, "router", "--listen", listen, *("--metrics-port", str(mport)), *METRICS_HOST],
        cwd=REPO,
        env=_env(NOTIFY_SOCKET=path),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_notify(sock, b"READY=1", proc)
        samples = scrape(mport)
        assert total(samples, "crosspath_daemon_info", service="router") == 1.0
        assert total(samples, "crosspath_zenoh_links") == 0.0
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


# --------------------------------------------------------------------------- dashboard


def _exprs(node: object) -> Iterator[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("expr", "definition") and isinstance(value, str):
                yield value
            else:
                yield from _exprs(value)
    elif isinstance(node, list):
        for item in node:
            yield from _exprs(item)


def test_the_dashboard_queries_only_metrics_the_daemons_export() -> None:
    board = json.loads(DASHBOARD.read_text())
    assert board["title"] and board["uid"] and isinstance(board["panels"], list)
    exported = set(METRICS)
    for name in list(exported):  # histograms and counters as Prometheus exposes them
        exported |= {f"{name}_bucket", f"{name}_sum", f"{name}_count"}
    exprs = list(_exprs(board))
    assert len(exprs) >= 10
    used: set[str] = set()
    for expr in exprs:
        names = set(
            re.findall(r"\b(crosspath_[a-z0-9_]+|process_[a-z0-9_]+|python_[a-z0-9_]+)", expr)
        )
        assert names, f"no metric in {expr!r}"
        for name in names:
            if name.startswith(("process_", "python_")):
                continue  # prometheus-client's own collectors
            assert name in exported, f"{name} in {expr!r} is not exported"
        used |= names
    # the list: messages and bytes, latency, modes, decisions, conflicts, drops,
    # queues, tick lateness
    for needed in (
        "crosspath_v2x_sent_messages_total",
        "crosspath_v2x_sent_bytes_total",
        "crosspath_v2x_latency_seconds_bucket",
        "crosspath_mode_changes_total",
        "crosspath_rsu_decisions_total",
        "crosspath_rsu_conflicts_total",
        "crosspath_dropped_messages_total",
        "crosspath_receive_queue_peak_lanes",
        "crosspath_tick_lag_seconds_bucket",
    ):
        assert needed in used, needed
    ids = [p["id"] for p in board["panels"]]
    assert len(ids) == len(set(ids))
    assert not any(math.isnan(float(p["gridPos"]["y"])) for p in board["panels"])
