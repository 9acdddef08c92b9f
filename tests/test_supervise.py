"""Supervision: the restart policy (pure), the supervisor loop on fake processes, and a real SIGKILLed node."""

from __future__ import annotations

import signal
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from constructaide.app.launch import Launcher
from constructaide.app.supervise import RestartPolicy, Supervisor, decide, describe_exit
from constructaide.runtime import BusConfig, open_bus
from schemas import keys
from schemas.messages import NodeError, Photo

ECHO = Path(__file__).with_name("echo_node.py")


def test_backoff_grows_then_gives_up_within_the_window() -> None:
    pol = RestartPolicy(
        backoff_initial_secs=1.0, backoff_factor=2.0, backoff_max_secs=5.0, max_crashes=4, window_secs=60
    )
    times: list[float] = []
    delays = []
    for t in (0.0, 1.0, 3.0):
        times.append(t)
        d = decide(pol, times, t)
        assert d.restart
        delays.append(d.delay_secs)
    assert delays == [1.0, 2.0, 4.0]
    times.append(7.0)
    d = decide(pol, times, 7.0)
    assert not d.restart and d.crashes_in_window == 4 and "stopped" in d.reason
    # Crashes spread out beyond the window never add up: the delay stays at the first step.
    spaced = [0.0, 100.0, 200.0, 300.0, 400.0]
    assert all(decide(pol, spaced[: i + 1], spaced[i]).delay_secs == 1.0 for i in range(5))
    assert decide(RestartPolicy(backoff_max_secs=3.0), [0.0] * 4, 0.0).delay_secs == 3.0


def test_describe_exit() -> None:
    assert describe_exit(-signal.SIGKILL) == "killed by SIGKILL"
    assert describe_exit(3) == "exited with code 3"


@dataclass
class FakeProc:
    name: str
    code: int | None = None
    starts: int = 1
    stopping: bool = False

    def returncode(self) -> int | None:
        return self.code

    def restart(self) -> None:
        self.starts += 1
        self.code = None


def test_supervisor_restarts_after_the_delay_and_stops_a_crash_loop() -> None:
    now = [0.0]
    reports: list[tuple[str, str]] = []
    p = FakeProc("register")
    pol = RestartPolicy(backoff_initial_secs=1.0, max_crashes=3, window_secs=100)
    sup = Supervisor(lambda: [p], lambda n, r: reports.append((n, r)), pol, clock=lambda: now[0])
    sup.check()
    assert p.starts == 1 and not reports
    p.code = -9
    sup.check()
    assert "killed by SIGKILL" in reports[-1][1] and p.starts == 1
    now[0] = 0.5
    sup.check()
    assert p.starts == 1  # back-off not over
    now[0] = 1.0
    sup.check()
    assert p.starts == 2 and [e.kind for e in sup.events] == ["crash", "restart"]
    for t in (2.0, 5.0):  # two more crashes within the window: the third is the last
        p.code = 1
        now[0] = t
        sup.check()
        now[0] = t + 2.5
        sup.check()
    assert [e.kind for e in sup.events][-2:] == ["crash", "give_up"]
    assert p.starts == 3 and "stopped, not restarted" in reports[-1][1]
    now[0] = 50.0
    sup.check()
    assert p.starts == 3  # given up for good
    stopped = FakeProc("render", code=0, stopping=True)  # a node being stopped is not a crash
    sup2 = Supervisor(lambda: [stopped], lambda n, r: reports.append((n, r)), pol, clock=lambda: now[0])
    sup2.check()
    assert sup2.events == []


def test_a_pair_of_sessions_left_unlinked_is_reported_once() -> None:
    """A restarted node that did not reach a peer: the bus's missing transport, seen for mesh_report_secs, becomes a
    NodeError once; a short gap (a node restarting) does not; linked again, a new gap is news again."""
    now = [0.0]
    gaps: list[tuple[str, str]] = []
    reports: list[tuple[str, str]] = []
    sup = Supervisor(
        lambda: [],
        lambda n, r: reports.append((n, r)),
        clock=lambda: now[0],
        gaps=lambda: list(gaps),
        mesh_every_secs=5.0,
        mesh_report_secs=20.0,
    )
    gaps[:] = [("render", "recorder")]
    for t in (0.0, 5.0, 10.0):
        now[0] = t
        sup.check()
    gaps[:] = []  # linked within 20 s: nothing to report
    now[0] = 15.0
    sup.check()
    gaps[:] = [("recorder", "render")]  # the same pair, named the other way round
    for t in range(20, 60, 5):
        now[0] = float(t)
        sup.check()
    assert reports == [
        ("recorder", "no bus transport between recorder and render for 20 s: they miss each other's messages")
    ]
    gaps[:] = []
    now[0] = 62.0
    sup.check()  # linked again
    gaps[:] = [("recorder", "render")]
    for t in (70.0, 80.0, 90.0):
        now[0] = t
        sup.check()
    assert len(reports) == 2 and [e.kind for e in sup.events] == ["mesh_gap", "mesh_gap"]


@pytest.mark.zenoh
def test_sigkilled_node_is_restarted_and_reported(hub_port: int, tmp_path: Path) -> None:
    site = "sup"
    live = keys.pattern(keys.LIVELINESS, site=site, node="echo")
    with open_bus(BusConfig(hub_port=hub_port)) as bus:
        errors = bus.collect(keys.key(keys.ERRORS, site=site))
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=site))
        with Launcher(site=site, bus=BusConfig(hub_port=hub_port), state_dir=tmp_path) as launcher:
            argv = [
                sys.executable,
                str(ECHO),
                "--site",
                site,
                "--hub-port",
                str(hub_port),
                "--state-dir",
                str(tmp_path),
            ]
            launcher.procs.append(p := _node_process(argv))
            bus.wait_for_tokens([live], timeout=30)
            sup = launcher.supervise(bus, RestartPolicy(backoff_initial_secs=0.2))
            assert p.proc is not None
            first_pid = p.proc.pid
            p.proc.send_signal(signal.SIGKILL)
            sup.wait_event("restart", node="echo", timeout=30)
            bus.wait_for_tokens([live], timeout=30)
            assert p.proc.pid != first_pid
            msg = Photo(site=site, photo_id="after", camera_id="c", capture_time_ns=1, data=b"x")
            bus.publish(keys.key(keys.PHOTO, site=site, camera="c"), msg)
            regs.wait(1, timeout=30)
            ((_, err),) = errors.wait(1, timeout=10)
            assert isinstance(err, NodeError) and err.node == "echo" and err.topic == "supervisor"
            assert "killed by SIGKILL" in err.reason and "restart 1" in err.reason


@pytest.mark.zenoh
def test_node_started_with_sigint_ignored_still_stops_cleanly_on_sigint(hub_port: int, tmp_path: Path) -> None:
    """A script started in the background (``cmd &``) hands its children SIGINT ignored; the launcher's stop
    (SIGINT, drain, then SIGKILL after its timeout) must still land as a clean exit, not a kill."""
    import os
    import subprocess

    from constructaide.app.launch import NodeProcess

    site = "sigign"
    live = keys.pattern(keys.LIVELINESS, site=site, node="echo")
    argv = [sys.executable, str(ECHO), "--site", site, "--hub-port", str(hub_port), "--state-dir", str(tmp_path)]
    with open_bus(BusConfig(hub_port=hub_port)) as bus:
        p = NodeProcess("echo", argv)
        p.env = dict(os.environ)
        p.proc = subprocess.Popen(  # as a background shell starts it: SIGINT ignored from exec on
            argv, env=p.env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)
        )
        try:
            bus.wait_for_tokens([live], timeout=30)
            assert p.stop(timeout=30) == 0  # exited by its own handler: SIGKILL would give -9
        finally:
            if p.proc.poll() is None:
                p.proc.kill()
                p.proc.wait()


def _node_process(argv: list[str]):
    import os

    from constructaide.app.launch import NodeProcess

    p = NodeProcess("echo", argv)
    p.start(dict(os.environ))
    return p
