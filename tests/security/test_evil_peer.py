"""Real daemons over Zenoh, signed (``crosspath up``), with an evil Zenoh peer (issue 13).

The evil peer joins the daemons' endpoints and, during the run, sends car B:

- INITIATE C_FAST and C_FAST coordinated paths on ``rsu1``'s command key, signed by
  an ``rsu1`` key of another authority, dated with the run's current time (copied
  from B's own future paths);
- the same unsigned from an RSU id that is in no scenario (``evil``);
- every genuine command datagram again, 0.3 s later (a replay).

All of it is refused and counted by car B, and the run is unharmed: no collision,
both cars finish, passing times as the in-process harness's.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from protocol import (
    Command,
    CoordinatedPath,
    Header,
    Mode,
    ModeCommand,
    decode,
    encode,
)
from protocol.auth import run_tag, seal
from services.edge.trust import Authority, rsu_grants
from services.model.scenario import load_scenario
from services.model.types import RunMode
from services.sim.harness import SimOptions, simulate
from services.supervise.launcher import prepare_up

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"
SPEED = 6.0


class EvilPeer(threading.Thread):
    """A Zenoh peer on the daemons' endpoints that forges and replays commands to B."""

    def __init__(self, connect: list[str], forger: Authority, prefix: str = "crosspath") -> None:
        super().__init__(daemon=True)
        self.connect = connect
        creds = forger.credentials("rsu1")
        self.forged_key, self.forged_cert = creds.key, creds.certificate
        self.prefix = prefix
        self.stop = threading.Event()
        self.sent: dict[str, int] = {"forged": 0, "evil_id": 0, "replayed": 0}
        self.time_us: int | None = None
        self.run_seen: int = 0
        self._replays: list[tuple[float, str, bytes]] = []
        self._lock = threading.Lock()

    def run(self) -> None:
        import zenoh

        config = zenoh.Config()
        config.insert_json5("mode", json.dumps("peer"))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps(self.connect))
        session: Any = zenoh.open(config)
        p = self.prefix

        def on_fp(sample: Any) -> None:
            data = bytes(sample.payload.to_bytes())
            try:
                message = decode(data)
            except ValueError:
                return
            self.time_us = message.header.time_us
            auth = message.header.auth
            if len(auth) > 6:  # scheme, form, then the run tag this run signs with
                self.run_seen = int.from_bytes(auth[2:6], "little")

        def on_cmd(sample: Any) -> None:
            with self._lock:
                self._replays.append(
                    (time.monotonic() + 0.3, str(sample.key_expr), bytes(sample.payload.to_bytes()))
                )

        subs = [
            session.declare_subscriber(f"{p}/v2x/fp/B", on_fp),
            session.declare_subscriber(f"{p}/v2x/rsu/rsu1/cmd/B", on_cmd),
        ]
        seq = 10_000_000
        try:
            while not self.stop.wait(0.05):
                with self._lock:
                    due = [r for r in self._replays if r[0] <= time.monotonic()]
                    self._replays = [r for r in self._replays if r[0] > time.monotonic()]
                for _, key, data in due:
                    session.put(key, data)
                    self.sent["replayed"] += 1
                if self.time_us is None:
                    continue
                seq += 1
                header = Header("rsu1", seq, self.time_us)
                cmd = ModeCommand(header, "B", Command.INITIATE, Mode.C_FAST)
                pts = np.array(
                    [[1.75, -30.0, self.time_us / 1e6], [1.75, 30.0, 1 + self.time_us / 1e6]]
                )
                path = CoordinatedPath(header, "B", Mode.C_FAST, pts, np.array([60.0, 60.0]))
                for m, cert in ((cmd, self.forged_cert), (path, None)):  # full and digest
                    data = seal(encode(m), self.forged_key, self.run_seen, cert)
                    session.put(f"{p}/v2x/rsu/rsu1/cmd/B", data)
                    self.sent["forged"] += 1
                evil = ModeCommand(
                    Header("evil", seq, self.time_us), "B", Command.INITIATE, Mode.C_FAST
                )
                session.put(f"{p}/v2x/rsu/evil/cmd/B", encode(evil))
                self.sent["evil_id"] += 1
        finally:
            for sub in subs:
                sub.undeclare()
            session.close()


@pytest.mark.daemons
@pytest.mark.slow  # about 30 s: four daemons, a run at speed 6 and the harness reference
def test_forged_and_replayed_commands_from_an_evil_peer_are_refused(tmp_path: Path) -> None:
    scenario = load_scenario(PAPER)
    up = prepare_up(PAPER, RunMode.RSU, speed=SPEED, run_dir=tmp_path / "run", start_delay_s=1.5)
    connect = []
    for argv in up.launcher.commands.values():
        connect += [argv[i + 1] for i, a in enumerate(argv) if a == "--listen"]
    forger = Authority.init(tmp_path / "evil-pki")
    forger.provision([], rsu_grants(scenario), [])
    peer = EvilPeer([c for c in connect if c.startswith("tcp/")], forger)
    peer.start()
    try:
        outcome = up.execute()
    finally:
        peer.stop.set()
        peer.join(timeout=10)
    result = outcome.result
    assert result is not None, outcome.failure
    assert peer.sent["forged"] > 10 and peer.sent["evil_id"] > 5 and peer.sent["replayed"] > 5
    assert result.collisions == 0 and result.all_finished
    actors = result.actors or {}
    auth_b: dict[str, int] = actors["B"]["auth"]
    # forged with its certificate: not our root; with its digest: a key we never saw
    why = f"auth {auth_b}, sent {peer.sent}, receive {actors['B']['receive'].get('cmd')}"
    assert auth_b.get("bad_certificate", 0) > 0, why
    assert auth_b.get("unknown_key", 0) > 0, why
    assert auth_b.get("replay", 0) > 0, why
    refused_evil = actors["B"]["receive"]["cmd"]["refused"]
    assert refused_evil > 0  # the "evil" RSU is no node of the run
    reference = simulate(scenario, SimOptions(mode=RunMode.RSU, seed=0))
    for vid, ref in reference.vehicles.items():
        got = result.vehicles[vid].passing_time_s
        assert got == pytest.approx(ref.passing_time_s, rel=0.05), (vid, got, ref.passing_time_s)
    assert run_tag(result.run_id) == peer.run_seen  # it signed with the genuine run tag
