"""Nodes on different hosts through a router, on one machine: two network namespaces joined by a veth pair with
private addresses that exist only inside them (no other network is touched). A zenoh router and the camera /
observer run in one namespace, the register node in the other, as zenoh clients of the router; the registrations
must be those of the same run on one host (loopback hub)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from constructaide import camera as cam

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
DRIVER = ROOT / "tests" / "netns_driver.py"
SUBNET = "10.231.77"  # a private /24 on the veth pair only, inside the two namespaces


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "PYOPENGL_PLATFORM": "egl"}


def _netns_usable() -> str | None:
    """Why namespaces cannot be used here (None when they can)."""
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    if shutil.which("ip") is None:
        return "iproute2's ip command is not installed"
    probe = f"caprobe{os.getpid()}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"ip netns add failed: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


def _registrations(stdout: str) -> dict[str, tuple[str, str, np.ndarray]]:
    out = {}
    for line in stdout.splitlines():
        pid, status, method, pose = json.loads(line)
        out[pid] = (status, method, cam.pose_from_tuple(pose) if pose else None)
    return out


def _node_argv(bus: list[str]) -> list[str]:
    return [sys.executable, "-m", "constructaide.app.cli", "node", "register", "--site", "t", *bus]


def _single_host(hub_port: int) -> dict:
    node = subprocess.Popen(
        _node_argv(["--hub-port", str(hub_port)]), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        drv = subprocess.run(
            [sys.executable, str(DRIVER), "--hub-port", str(hub_port)],
            env=_env(),
            capture_output=True,
            text=True,
            timeout=180,
        )
        assert drv.returncode == 0, drv.stderr[-2000:]
        return _registrations(drv.stdout)
    finally:
        node.terminate()
        node.wait(30)


def _two_hosts(tmp: Path) -> dict:
    tag = f"{os.getpid() % 100000}"
    ns_a, ns_b = f"ca{tag}a", f"ca{tag}b"
    veth_a, veth_b = f"cav{tag}a", f"cav{tag}b"
    router_ep = f"tcp/{SUBNET}.1:7447"
    procs: list[subprocess.Popen] = []
    stack = contextlib.ExitStack()
    _ip("netns", "add", ns_a)
    try:
        _ip("netns", "add", ns_b)
        _ip("link", "add", veth_a, "type", "veth", "peer", "name", veth_b)
        _ip("link", "set", veth_a, "netns", ns_a)
        _ip("link", "set", veth_b, "netns", ns_b)
        for ns, dev, addr in ((ns_a, veth_a, f"{SUBNET}.1/24"), (ns_b, veth_b, f"{SUBNET}.2/24")):
            _ip("-n", ns, "addr", "add", addr, "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        in_a, in_b = ["ip", "netns", "exec", ns_a], ["ip", "netns", "exec", ns_b]
        log = stack.enter_context(open(tmp / "router.log", "wb"))
        procs.append(
            subprocess.Popen(
                [*in_a, sys.executable, "-m", "constructaide.app.cli", "router", "--listen", router_ep],
                env=_env(),
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
        client = ["--mode", "client", "--connect", router_ep]
        node_log = stack.enter_context(open(tmp / "register.log", "wb"))
        procs.append(
            subprocess.Popen([*in_b, *_node_argv(client)], env=_env(), stdout=node_log, stderr=subprocess.STDOUT)
        )
        drv = subprocess.run(
            [*in_a, sys.executable, str(DRIVER), *client], env=_env(), capture_output=True, text=True, timeout=180
        )
        assert drv.returncode == 0, drv.stderr[-2000:]
        # the node really is in the other namespace: nothing listens there on the router's address
        routes = subprocess.run([*in_b, "ip", "-4", "addr"], capture_output=True, text=True).stdout
        assert f"{SUBNET}.2/24" in routes and f"{SUBNET}.1/" not in routes
        return _registrations(drv.stdout)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        subprocess.run(["ip", "netns", "del", ns_b], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns_a], capture_output=True)
        stack.close()


def test_nodes_in_two_namespaces_through_a_router_give_the_single_host_results(hub_port: int, tmp_path: Path) -> None:
    why = _netns_usable()
    if why:
        pytest.skip(why)
    one = _single_host(hub_port)
    two = _two_hosts(tmp_path)
    assert len(one) == 4 and set(one) == set(two)
    for pid, (status, method, pose) in one.items():
        s2, m2, p2 = two[pid]
        assert (status, method) == (s2, m2) and status != "failed"
        assert cam.rotation_angle_deg(pose[:3, :3], p2[:3, :3]) < 0.01
        assert np.linalg.norm(pose[:3, 3] - p2[:3, 3]) < 1e-3
