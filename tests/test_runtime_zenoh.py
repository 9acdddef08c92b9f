"""Real zenoh sessions in separate processes: typed exchange, restart, malformed payloads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from constructaide.runtime import BusConfig, open_bus
from schemas import keys
from schemas.messages import NodeError, Photo, Registration

pytestmark = pytest.mark.zenoh
ECHO = Path(__file__).with_name("echo_node.py")


def start_echo(site: str, port: int, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, str(ECHO), "--site", site, "--hub-port", str(port), *extra],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        proc.wait(20)


def photo(site: str, photo_id: str, camera: str = "cam-a") -> tuple[str, Photo]:
    msg = Photo(
        site=site, photo_id=photo_id, camera_id=camera, capture_time_ns=1_700_000_000_000_000_000, data=b"\xff\xd8"
    )
    return keys.key(keys.PHOTO, site=site, camera=camera), msg


def test_typed_exchange_restart_and_malformed(hub_port: int) -> None:
    site = "rt"
    live = keys.pattern(keys.LIVELINESS, site=site, node="echo")
    # The test's session is the hub (it owns the port); the node connects to it.
    with open_bus(BusConfig(hub_port=hub_port)) as bus:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=site))
        errors = bus.collect(keys.key(keys.ERRORS, site=site))
        proc = start_echo(site, hub_port, "--set", "reply_message='hello'")
        try:
            bus.wait_for_tokens([live], timeout=30)
            bus.publish(*photo(site, "p1"))
            ((key, reg),) = regs.wait(1, timeout=20)
            assert isinstance(reg, Registration)
            assert key == "constructaide/rt/registration/cam-a/p1"
            assert reg.photo_id == "p1" and reg.message == "hello"

            # Malformed payload and a raising handler: NodeErrors, and the node survives.
            bus.publish(keys.key(keys.PHOTO, site=site, camera="cam-a"), b"\x93not a photo")
            bus.publish(*photo(site, "raise"))
            errs = errors.wait(2, timeout=20)
            assert all(isinstance(e, NodeError) and e.node == "echo" for _, e in errs)
            reasons = " | ".join(e.reason for _, e in errs)
            assert "cannot decode Photo" in reasons and "asked to raise" in reasons
            assert errs[0][1].key == "constructaide/rt/photo/cam-a"
            bus.publish(*photo(site, "p2"))
            regs.wait(2, timeout=20)
            assert proc.poll() is None

            # Kill the node; its token goes away; a restarted node rejoins without restarting the test's session.
            proc.kill()
            proc.wait(20)
            gone = bus.collect(keys.key(keys.ERRORS, site=site))  # unrelated collector stays quiet
            tokens_after_kill = _wait_tokens_gone(bus, live)
            assert tokens_after_kill == []
            proc = start_echo(site, hub_port)
            bus.wait_for_tokens([live], timeout=30)
            bus.publish(*photo(site, "p3"))
            got = regs.wait(3, timeout=20)
            assert got[-1][1].photo_id == "p3" and got[-1][1].message == "echo"
            assert gone.items == []
        finally:
            stop(proc)


def _wait_tokens_gone(bus, keyexpr: str, timeout: float = 20.0) -> list[str]:
    import threading

    gone = threading.Event()

    def on_token(key: str, alive: bool) -> None:
        if not alive:
            gone.set()

    watcher = bus.watch_tokens(keyexpr, on_token)
    try:
        if bus.live_tokens(keyexpr):
            gone.wait(timeout)
        return bus.live_tokens(keyexpr)
    finally:
        watcher.close()


def test_router_joins_nodes_across_sessions_and_status_lists_them() -> None:
    """`constructaide router` lets client/peer sessions that only know the router meet; `status` sees the node. The
    router binds a port the system picks and says which."""
    site = "rtr"
    router = subprocess.Popen(
        [sys.executable, "-m", "constructaide.app.cli", "router", "--listen", "tcp/127.0.0.1:0"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert router.stderr is not None
    line = router.stderr.readline()  # printed once the router is listening
    assert line.startswith("router listening on tcp/127.0.0.1:"), line
    endpoint = line.split()[3].rstrip(";,")
    port = int(endpoint.rsplit(":", 1)[1])
    assert port > 0
    echo = start_echo(site, port, "--mode", "client", "--connect", endpoint)
    try:
        with open_bus(BusConfig(mode="client", connect=[endpoint])) as bus:
            regs = bus.collect(keys.pattern(keys.REGISTRATION, site=site))
            bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=site, node="echo")], timeout=30)
            bus.publish(*photo(site, "via-router"))
            ((_, reg),) = regs.wait(1, timeout=20)
            assert reg.photo_id == "via-router"
        status = subprocess.run(
            [
                sys.executable,
                "-m",
                "constructaide.app.cli",
                "status",
                "--site",
                site,
                "--mode",
                "client",
                "--connect",
                endpoint,
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert status.returncode == 0, status.stderr
        assert "echo" in status.stdout and site in status.stdout
    finally:
        stop(echo)
        stop(router)
        router.stderr.close()


def test_blocked_publishers_wait_instead_of_dropping_the_peer() -> None:
    """zenoh's default takes a transport down after a BLOCK message waited 5 s for room, losing every later message
    to that peer (seen: the occlude node stopped getting registrations while it worked through a burst)."""
    import json

    from constructaide.runtime.bus import BLOCK_WAIT_BEFORE_CLOSE_US

    block = json.loads(BusConfig(hub_port=7447).zenoh_config().get_json("transport/link/tx/queue/congestion_control"))
    assert block["block"]["wait_before_close"] == BLOCK_WAIT_BEFORE_CLOSE_US >= 60_000_000
