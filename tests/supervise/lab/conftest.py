"""Fixtures and traffic helpers for the network lab tests (real namespaces, real nftables).

A lab test needs root, ``ip``, ``nft`` and ``tc``. Without them it is skipped on
a developer machine and FAILS when env ``CI`` is set, so CI never silently
passes without having exercised the lab.
"""

from __future__ import annotations

import itertools
import json
import os
import secrets
import select
import subprocess
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import pytest

from services.supervise.lab.netns import Lab, LabError, LabPlan, down_all, prerequisites

SESSION = f"t{secrets.token_hex(3)}"
"""Prefix of every lab this test session makes (lab names are ``SESSION`` + a counter)."""
_COUNTER = itertools.count()

PY = sys.executable

_RECEIVER = r"""
import json, socket, sys, time
port, deadline = int(sys.argv[1]), time.monotonic() + float(sys.argv[2])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, 33, 8 << 20)  # SO_RCVBUFFORCE: never lose to a full buffer
s.bind(("0.0.0.0", port))
s.settimeout(0.1)
print("ready", flush=True)
seqs, nbytes = [], 0
while time.monotonic() < deadline:
    try:
        data, (src, _) = s.recvfrom(65535)
    except TimeoutError:
        continue
    if src.startswith("10.231.2.") and data == b"stop":
        break
    if src.startswith("10.231.1."):
        seqs.append(int.from_bytes(data[:4], "big"))
        nbytes += len(data)
print(json.dumps({"seqs": seqs, "bytes": nbytes}), flush=True)
"""

_SENDER = r"""
import socket, sys, time
dst, port, count, size, seconds = (
    sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5]))
stops = sys.argv[6:]
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
pad = bytes(max(0, size - 4))
sent = 0
end = time.monotonic() + seconds
while (sent < count) if count else (time.monotonic() < end):
    try:
        s.sendto(sent.to_bytes(4, "big") + pad, (dst, port))
        sent += 1
    except OSError:
        time.sleep(0.0005)
    if count and sent % 50 == 0:
        time.sleep(0.002)
time.sleep(0.05)
for addr in stops:
    for _ in range(3):
        s.sendto(b"stop", (addr, port))
print(sent)
"""

_TCP_SERVER = r"""
import socket, sys
s = socket.create_server((sys.argv[1], int(sys.argv[2])))
s.settimeout(10)
print("ready", flush=True)
conn, _ = s.accept()
conn.settimeout(10)
total = 0
while chunk := conn.recv(65536):
    total += len(chunk)
print(total, flush=True)
"""

_TCP_CLIENT = r"""
import socket, sys
with socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=10) as c:
    c.sendall(bytes(int(sys.argv[3])))
"""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test that builds a real lab ``lab`` (``make test-fast`` leaves them out)."""
    for item in items:
        if "lab_ready" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.lab)


def new_lab_name() -> str:
    return f"{SESSION}{next(_COUNTER)}"


def _missing() -> list[str]:
    missing = prerequisites()
    if missing:
        return missing
    probe = Lab(new_lab_name())
    try:
        probe.up(LabPlan.build(probe.name, cars=["probe"], monitor=None))
    except LabError as exc:
        return [f"network namespaces ({exc})"]
    finally:
        probe.down()
    return []


@pytest.fixture(scope="session")
def lab_ready() -> Iterator[None]:
    """Root and tools present and a namespace can be made; else skip (FAIL under CI)."""
    missing = _missing()
    if missing:
        message = "network lab unavailable, missing: " + "; ".join(missing)
        if os.environ.get("CI"):
            pytest.fail(message + " (CI is set: run deploy/lab/install-sysdeps.sh as root)")
        pytest.skip(message)
    yield
    down_all(f"cpl-{SESSION}")  # whatever a failed test left behind


@pytest.fixture(scope="module")
def lab3(lab_ready: None) -> Iterator[Lab]:
    """Three nodes: cars ``a`` and ``b``, RSU ``r``."""
    lab = Lab(new_lab_name())
    lab.up(LabPlan.build(lab.name, cars=["a", "b"], rsus=["r"], monitor=None))
    yield lab
    lab.down()


@dataclass(frozen=True, slots=True)
class Received:
    seqs: list[int]
    nbytes: int


def _await_ready(proc: subprocess.Popen[bytes], what: str) -> None:
    if proc.stdout is None:
        raise RuntimeError("no stdout pipe")
    readable, _, _ = select.select([proc.stdout], [], [], 10.0)
    line = proc.stdout.readline() if readable else b""
    if line.strip() != b"ready":
        proc.kill()
        _, err = proc.communicate(timeout=5)
        raise RuntimeError(f"{what} did not start: {line!r} {err.decode(errors='replace')}")


def udp_transfer(
    lab: Lab,
    sender: str,
    receivers: Sequence[str],
    *,
    dst: str,
    count: int = 0,
    size: int = 64,
    seconds: float = 0.0,
    port: int = 40000,
) -> tuple[int, dict[str, Received]]:
    """Send ``count`` datagrams (or for ``seconds``) on the air from ``sender`` to ``dst``;
    each receiver counts what arrives from air addresses until a stop arrives over the wire.
    Returns (datagrams sent, per receiver what it got)."""
    procs = {
        r: lab.exec(
            r,
            [PY, "-c", _RECEIVER, str(port), "20"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for r in receivers
    }
    try:
        for r, proc in procs.items():
            _await_ready(proc, f"receiver in {r}")
        stops = [lab.wire_addr(r) for r in receivers]
        done = lab.run(
            sender,
            [PY, "-c", _SENDER, dst, str(port), str(count), str(size), str(seconds), *stops],
            timeout=30,
        )
        sent = int(done.stdout)
        got: dict[str, Received] = {}
        for r, proc in procs.items():
            out, err = proc.communicate(timeout=25)
            if proc.returncode != 0:
                raise RuntimeError(f"receiver in {r} failed: {err.decode(errors='replace')}")
            data = json.loads(out)
            got[r] = Received(seqs=list(data["seqs"]), nbytes=int(data["bytes"]))
        return sent, got
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=5)


def tcp_transfer(lab: Lab, client: str, server: str, addr: str, nbytes: int, port: int) -> int:
    """Send ``nbytes`` over TCP from ``client`` to ``server`` listening on ``addr``;
    returns how many bytes the server received."""
    proc = lab.exec(
        server,
        [PY, "-c", _TCP_SERVER, addr, str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        _await_ready(proc, f"TCP server in {server}")
        lab.run(client, [PY, "-c", _TCP_CLIENT, addr, str(port), str(nbytes)], timeout=20)
        out, err = proc.communicate(timeout=15)
        if proc.returncode != 0:
            raise RuntimeError(f"TCP server failed: {err.decode(errors='replace')}")
        return int(out)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
