"""Supervision of node processes: restart a crashed node with back-off, stop one that crashes in a loop.

:class:`RestartPolicy` and :func:`decide` are pure (times in seconds, any monotonic clock). :class:`Supervisor`
watches the processes of a :class:`~constructaide.app.launch.Launcher`, restarts them as the policy says and
reports each crash and each give-up as a NodeError on the site's error topic (``node`` = the crashed node,
``topic`` = ``supervisor``); the restarted node declares its liveliness token again.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

log = logging.getLogger("constructaide.supervisor")


@dataclass(frozen=True)
class RestartPolicy:
    """Delay before restart ``n`` (1-based, counting crashes within ``window_secs``):
    ``min(backoff_max_secs, backoff_initial_secs * backoff_factor ** (n - 1))``; the node is given up when it
    crashed ``max_crashes`` times within ``window_secs``."""

    backoff_initial_secs: float = 0.5
    backoff_factor: float = 2.0
    backoff_max_secs: float = 30.0
    max_crashes: int = 5
    window_secs: float = 120.0


@dataclass(frozen=True)
class Decision:
    restart: bool
    delay_secs: float
    crashes_in_window: int
    reason: str


def decide(policy: RestartPolicy, crash_times: list[float], now: float) -> Decision:
    """What to do after the last crash (``crash_times`` includes it; all <= ``now``)."""
    recent = [t for t in crash_times if now - t <= policy.window_secs]
    n = len(recent)
    if n >= policy.max_crashes:
        return Decision(False, 0.0, n, f"crashed {n} times within {policy.window_secs:.0f} s: stopped, not restarted")
    delay = min(policy.backoff_max_secs, policy.backoff_initial_secs * policy.backoff_factor ** max(0, n - 1))
    return Decision(True, delay, n, f"restart {n} within {policy.window_secs:.0f} s in {delay:.1f} s")


def describe_exit(code: int | None) -> str:
    if code is None:
        return "running"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


class Supervised(Protocol):
    """What the supervisor needs of a node process (``NodeProcess`` of the launcher)."""

    name: str
    stopping: bool

    def returncode(self) -> int | None: ...

    def restart(self) -> None: ...


@dataclass
class Event:
    time: float
    node: str
    kind: str  # "crash", "restart", "give_up", "mesh_gap"
    detail: str


@dataclass
class Supervisor:
    """Polls ``procs()`` every ``poll_secs``; ``report(node, reason)`` publishes the NodeError. A context manager."""

    procs: Callable[[], list[Any]]
    report: Callable[[str, str], None]
    policy: RestartPolicy = field(default_factory=RestartPolicy)
    poll_secs: float = 0.2
    clock: Callable[[], float] = time.monotonic
    events: list[Event] = field(default_factory=list)
    gaps: Callable[[], list[tuple[str, str]]] | None = None
    """The bus's missing transports (:meth:`~constructaide.runtime.bus.Bus.mesh_gaps`): a pair of sessions without
    one for ``mesh_report_secs`` is reported once (it misses each other's messages; a restart would not bring
    back what was lost)."""
    mesh_every_secs: float = 5.0
    mesh_report_secs: float = 20.0

    def __post_init__(self) -> None:
        self._gap_since: dict[tuple[str, ...], float] = {}
        self._gap_reported: set[tuple[str, ...]] = set()
        self._next_mesh = 0.0
        self._crashes: dict[str, list[float]] = {}
        self._due: dict[int, tuple[float, Any]] = {}
        self._given_up: set[int] = set()
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name="supervisor", daemon=True)

    def start(self) -> Supervisor:
        self._thread.start()
        return self

    def _event(self, node: str, kind: str, detail: str) -> None:
        with self._cond:
            self.events.append(Event(self.clock(), node, kind, detail))
            self._cond.notify_all()

    def wait_event(self, kind: str, count: int = 1, node: str | None = None, timeout: float = 60.0) -> list[Event]:
        """Block until ``count`` events of ``kind`` (for ``node``) happened; TimeoutError otherwise."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                found = [e for e in self.events if e.kind == kind and (node is None or e.node == node)]
                if len(found) >= count:
                    return found
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{len(found)} of {count} {kind} events within {timeout:.0f} s")
                self._cond.wait(left)

    def check(self) -> None:
        """One pass: note crashes, restart what is due (called by the thread; public for tests)."""
        now = self.clock()
        for p in self.procs():
            pid = id(p)
            if p.stopping or pid in self._given_up:
                continue
            if pid in self._due:
                at, _ = self._due[pid]
                if now >= at:
                    del self._due[pid]
                    try:
                        p.restart()
                        self._event(p.name, "restart", "restarted")
                        log.warning("node %s restarted", p.name)
                    except OSError as e:
                        self.report(p.name, f"node {p.name}: restart failed: {e}")
                continue
            code = p.returncode()
            if code is None:
                continue
            times = self._crashes.setdefault(p.name, [])
            times.append(now)
            d = decide(self.policy, times, now)
            why = f"node {p.name} {describe_exit(code)}; {d.reason}"
            log.warning("%s", why)
            self._event(p.name, "crash", why)
            self.report(p.name, why)
            if d.restart:
                self._due[pid] = (now + d.delay_secs, p)
            else:
                self._given_up.add(pid)
                self._event(p.name, "give_up", why)
        self._check_mesh(now)

    def _check_mesh(self, now: float) -> None:
        if self.gaps is None or now < self._next_mesh:
            return
        self._next_mesh = now + self.mesh_every_secs
        current = {tuple(sorted(g)) for g in self.gaps()}
        for pair in [p for p in self._gap_since if p not in current]:  # linked again: a new gap is news again
            del self._gap_since[pair]
            self._gap_reported.discard(pair)
        for pair in current:
            since = self._gap_since.setdefault(pair, now)
            if now - since >= self.mesh_report_secs and pair not in self._gap_reported:
                self._gap_reported.add(pair)
                why = (
                    f"no bus transport between {' and '.join(pair)} for {now - since:.0f} s: they miss each other's "
                    "messages"
                )
                log.warning("%s", why)
                self._event(pair[0], "mesh_gap", why)
                self.report(pair[0], why)

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_secs):
            try:
                self.check()
            except Exception:  # the supervisor never dies of a report that failed
                log.exception("supervisor pass failed")

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10)

    def __enter__(self) -> Supervisor:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
