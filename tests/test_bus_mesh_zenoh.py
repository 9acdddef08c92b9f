"""Real zenoh sessions: the launcher sees peers that have no transport between them and restarts one to repair it.

A peer mesh does not relay: two peers without a transport silently miss each other's publications (a CI run once
recorded no overlay at all: the render node and the recorder had not connected).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from constructaide.app.launch import Launcher, NodeProcess
from constructaide.errors import UserError
from constructaide.runtime import BusConfig, open_bus
from constructaide.runtime.bus import Collector

pytestmark = pytest.mark.zenoh

# a peer that reaches the hub only: no listener for others to connect to, no gossip autoconnect of its own
ISOLATED = {
    "scouting/gossip/autoconnect": {"peer": [], "router": []},
    "listen/endpoints": [],
    "adminspace/enabled": True,
}

FAKE_NODE = r"""
import signal, sys
from pathlib import Path
from constructaide.runtime import BusConfig, open_bus
from schemas import keys

port, starts, isolated_runs = int(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
signal.signal(signal.SIGINT, signal.default_int_handler)  # started from a background shell, SIGINT comes ignored
n = len(starts.read_text().splitlines()) if starts.exists() else 0
with starts.open("a") as f:
    f.write("start\n")
isolated = n < isolated_runs
extra = ISOLATED if isolated else {}
connect = [f"tcp/127.0.0.1:{port}"] if isolated else []
cfg = BusConfig(connect=connect, hub_port=port, name="fake", extra_json5=extra)
with open_bus(cfg) as bus:
    token = bus.declare_token(keys.key(keys.LIVELINESS, site="mesh", node="fake", instance="i0"))
    try:
        signal.pause()
    except KeyboardInterrupt:
        pass
    token.close()
"""


def _fake_node(tmp_path: Path, port: int, isolated_runs: int) -> tuple[NodeProcess, Path]:
    script = tmp_path / "fake_node.py"
    script.write_text(f"ISOLATED = {ISOLATED!r}\n" + FAKE_NODE)
    starts = tmp_path / "starts.txt"
    proc = NodeProcess("fake", [sys.executable, str(script), str(port), str(starts), str(isolated_runs)])
    return proc, starts


def _hub(name: str = "hub"):
    return open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], name=name))


def test_mesh_gaps_names_the_peers_without_a_transport() -> None:
    with _hub() as hub:
        port = hub.listen_port()
        with (
            open_bus(BusConfig(hub_port=port, name="alpha")) as alpha,
            open_bus(BusConfig(hub_port=port, name="beta")),
        ):
            assert hub.mesh_gaps() == [] and alpha.mesh_gaps() == []  # joined: every session reaches every other
            with open_bus(BusConfig(connect=[f"tcp/127.0.0.1:{port}"], name="gamma", extra_json5=ISOLATED)) as gamma:
                gaps = {frozenset(g) for g in hub.mesh_gaps()}
                assert gaps == {frozenset({"alpha", "gamma"}), frozenset({"beta", "gamma"})}
                # a peer that does not reach gamma still sees the gap, gamma named by its id
                gamma_id = str(gamma.session.info.zid())[:8]
                assert frozenset({"beta", gamma_id}) in {frozenset(g) for g in alpha.mesh_gaps()}
                # what the check is for: gamma's publications do not reach alpha, though the hub is linked to both
                got = Collector(decode=False)
                got.sub = alpha.subscribe("mesh/**", got)
                gamma.publish("mesh/x", b"lost")
                with pytest.raises(TimeoutError):
                    got.wait(1, timeout=1.0)


def test_launcher_restarts_a_node_the_mesh_did_not_reach(tmp_path: Path) -> None:
    with _hub() as bus, open_bus(BusConfig(hub_port=bus.listen_port(), name="watcher")):
        hub_port = bus.listen_port()
        launcher = Launcher(site="mesh", bus=BusConfig(hub_port=hub_port), mesh_secs=2.0)
        proc, starts = _fake_node(tmp_path, hub_port, isolated_runs=1)
        proc.start(dict(os.environ))
        launcher.procs.append(proc)
        try:
            launcher.wait_live(bus, ["fake"], timeout=60)
            assert starts.read_text().splitlines() == ["start", "start"]  # restarted once, then linked
            assert bus.mesh_gaps() == []
        finally:
            launcher.stop_all()


def test_launcher_fails_naming_the_pair_when_restarts_do_not_help(tmp_path: Path) -> None:
    with _hub() as bus, open_bus(BusConfig(hub_port=bus.listen_port(), name="watcher")):
        hub_port = bus.listen_port()
        launcher = Launcher(site="mesh", bus=BusConfig(hub_port=hub_port), mesh_secs=1.0)
        proc, starts = _fake_node(tmp_path, hub_port, isolated_runs=99)
        proc.start(dict(os.environ))
        launcher.procs.append(proc)
        try:
            with pytest.raises(UserError, match="no bus transport between .*fake"):
                launcher.wait_live(bus, ["fake"], timeout=60)
            assert len(starts.read_text().splitlines()) == 3  # two restarts, then the start fails
        finally:
            launcher.stop_all()
