"""Start several nodes as separate processes and supervise them (``constructaide run`` and the demo).

A site TOML config::

    [site]
    name = "demo"

    [bus]                      # optional; default: peer on loopback
    connect = ["tcp/10.0.0.5:7447"]

    [bus.tls]                  # optional: TLS / mutual TLS and ACL, see constructaide.runtime.security
    ca = "certs/ca.pem"
    certs = "certs"

    [bus.acl]
    enabled = true

    [nodes.register]           # one table per node to start; its fields are the node's config
    fast_path = true

    [workers]                  # optional: N partitioned instances of a node kind (constructaide.partition)
    register = 2               # each owns a share of the fixed cameras and of the phone photos
    occlude = 2
    render = 2

With ``[workers]`` the site's fixed camera ids (``[site] cameras = ["cam-a", ...]``) let each worker subscribe to
its own cameras' keys only; without them every worker subscribes to all cameras and skips the others' frames.

    [supervise]                # optional: restart policy (constructaide.app.supervise.RestartPolicy)
    max_crashes = 5
    window_secs = 120

A crashed node is restarted with back-off and reported on the error topic; its ledger and state in
``--state-dir`` let it resume and get what was published while it was down.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from constructaide.app.supervise import RestartPolicy, Supervisor
from constructaide.errors import UserError
from constructaide.runtime import Bus, BusConfig, add_bus_args, open_bus
from constructaide.runtime.security import load_security
from schemas import keys
from schemas.messages import NodeError

MESH_REPAIRS = 2  # restarts of a node the mesh did not reach, before the start fails
MESH_POLL_SECS = 0.2


@dataclass
class NodeProcess:
    name: str
    argv: list[str]
    log_path: Path | None = None
    proc: subprocess.Popen[bytes] | None = None
    _log: object = None
    stopping: bool = False
    env: dict[str, str] = field(default_factory=dict)
    kind: str = ""
    """The node kind (its liveliness token's node); the name when empty."""

    def __post_init__(self) -> None:
        self.kind = self.kind or self.name

    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def restart(self) -> None:
        """Start the process again (after it exited), with the same argv and environment."""
        if self._log is not None:
            self._log.close()  # type: ignore[attr-defined]
            self._log = None
        self.start(self.env)

    def start(self, env: dict[str, str]) -> None:
        self.env = env
        stdout = subprocess.DEVNULL
        if self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            self._log = open(self.log_path, "ab")  # noqa: SIM115 - closed in stop()
            stdout = self._log  # type: ignore[assignment]
        self.proc = subprocess.Popen(self.argv, env=env, stdout=stdout, stderr=subprocess.STDOUT)

    def stop(self, timeout: float = 90.0) -> int | None:
        """SIGINT, then up to ``timeout`` s for the node to drain its queue (its worker gets 60 s), then SIGKILL."""
        self.stopping = True
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._log is not None:
            self._log.close()  # type: ignore[attr-defined]
            self._log = None
        return self.proc.returncode


@dataclass
class Launcher:
    """Runs node processes that share one bus configuration; a context manager that stops them all."""

    site: str
    bus: BusConfig = field(default_factory=BusConfig)
    log_dir: Path | None = None
    procs: list[NodeProcess] = field(default_factory=list)
    state_dir: Path | None = None
    """Passed to the nodes as ``--state-dir`` (ledger and state: a restarted node resumes and gets what it missed)."""
    supervisor: Supervisor | None = None
    security_toml: Path | None = None  # site TOML with [bus.tls]: each node loads its own certificate from it
    mesh_secs: float = 20.0
    """How long :meth:`wait_live` waits for every pair of sessions to connect before it restarts a node."""

    def bus_argv(self) -> list[str]:
        argv = ["--hub-port", str(self.bus.hub_port), "--mode", self.bus.mode]
        if self.security_toml is not None:
            argv += ["--bus-security", str(self.security_toml)]
        for e in self.bus.connect:
            argv += ["--connect", e]
        for e in self.bus.listen:
            argv += ["--listen", e]
        return argv

    def start(
        self,
        node: str,
        config: Path | None = None,
        section: str | None = None,
        sets: list[str] | None = None,
        partition: str | None = None,
        cameras: list[str] | None = None,
    ) -> NodeProcess:
        """Start one node process; ``partition`` ``"I/N"`` makes it worker I of N of its kind (``cameras``: the
        site's fixed camera ids, so it subscribes to its own)."""
        argv = [sys.executable, "-m", "constructaide.app.cli", "node", node, "--site", self.site, *self.bus_argv()]
        if config is not None:
            argv += ["--config", str(config)]
            if section:
                argv += ["--section", section]
        if self.state_dir is not None:
            argv += ["--state-dir", str(self.state_dir)]
        for s in sets or []:
            argv += ["--set", s]
        name = node
        if partition is not None:
            argv += ["--partition", partition]
            if cameras:
                argv += ["--cameras", ",".join(cameras)]
            name = f"{node}-{partition.replace('/', 'of')}"
        log = self.log_dir / f"{name}.log" if self.log_dir else None
        p = NodeProcess(name, argv, log, kind=node)
        env = dict(os.environ)
        env.setdefault("PYOPENGL_PLATFORM", "egl")
        p.start(env)
        self.procs.append(p)
        return p

    def start_workers(
        self,
        node: str,
        count: int,
        config: Path | None = None,
        section: str | None = None,
        sets: list[str] | None = None,
        cameras: list[str] | None = None,
    ) -> list[NodeProcess]:
        """Start ``count`` partitioned instances of ``node`` (one plain instance when ``count`` is 1)."""
        if count < 1:
            raise UserError(f"[workers] {node} = {count}: needs at least 1")
        if count == 1:
            return [self.start(node, config, section, sets)]
        return [self.start(node, config, section, sets, f"{i}/{count}", cameras) for i in range(count)]

    def wait_workers(self, bus: Bus, node: str, count: int, timeout: float = 120.0) -> None:
        """Block until all ``count`` partitioned workers of ``node`` hold their liveliness tokens."""
        want = {f"w{i}of{count}" for i in range(count)}
        cond = threading.Condition()
        live: set[str] = set()

        def on_token(key: str, alive: bool) -> None:
            tag = key.rsplit("/", 1)[-1].split("-", 1)[0]
            with cond:
                (live.add if alive else live.discard)(tag)
                cond.notify_all()

        watcher = bus.watch_tokens(keys.pattern(keys.LIVELINESS, site=self.site, node=node), on_token)
        try:
            with cond:
                if not cond.wait_for(lambda: want <= live, timeout):
                    dead = [p.name for p in self.procs if p.proc is not None and p.proc.poll() is not None]
                    raise UserError(
                        f"{node} workers not live within {timeout:.0f} s: {sorted(want - live)}; exited: "
                        f"{dead or 'none'} (see logs in {self.log_dir})"
                    )
        finally:
            watcher.close()

    def wait_live(self, bus: Bus, names: list[str], timeout: float = 120.0) -> None:
        """Block until every named node has declared its liveliness token and every session on the bus has a
        transport to every other one; fail early if a node died.

        Peers do not relay each other's publications: a pair of peers that failed to connect when they joined (a
        loaded machine) would silently miss each other's data (a recorder without the overlays). A node of such a
        pair is restarted (the one started last; it joins the mesh again) up to twice, with a note on stderr;
        then the start fails and names the pairs."""
        self._wait_tokens(bus, names, timeout)
        for attempt in range(MESH_REPAIRS + 1):
            gaps = self._wait_mesh(bus)
            if not gaps:
                return
            started = [p for p in self.procs if p.returncode() is None]
            order = {p.name: i for i, p in enumerate(started)}
            targets: dict[str, NodeProcess] = {}
            for a, b in gaps:
                ours = [n for n in (a, b) if n in order]
                if ours:
                    last = max(ours, key=order.__getitem__)
                    targets[last] = started[order[last]]
            pairs = ", ".join(f"{a} - {b}" for a, b in gaps)
            if attempt == MESH_REPAIRS or not targets:
                raise UserError(
                    f"no bus transport between {pairs} after {self.mesh_secs:.0f} s: they would miss each other's "
                    f"messages (see logs in {self.log_dir})"
                )
            print(f"bus: no transport between {pairs}; restarting {', '.join(sorted(targets))}", file=sys.stderr)
            for proc in targets.values():
                proc.stop()
                proc.stopping = False
                proc.restart()
            self._wait_tokens(bus, sorted({p.kind for p in targets.values()}), timeout)

    def _wait_tokens(self, bus: Bus, names: list[str], timeout: float) -> None:
        dead = [p.name for p in self.procs if p.proc is not None and p.proc.poll() is not None]
        if dead:
            raise UserError(f"node(s) exited at start: {', '.join(dead)} (see logs in {self.log_dir})")
        try:
            bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=self.site, node=n) for n in names], timeout=timeout)
        except TimeoutError as e:
            dead = [p.name for p in self.procs if p.proc is not None and p.proc.poll() is not None]
            raise UserError(f"{e}; exited: {dead or 'none'} (see logs in {self.log_dir})") from None

    def _wait_mesh(self, bus: Bus) -> list[tuple[str, str]]:
        """The sessions' missing transports, once none is missing or after ``mesh_secs`` (zenoh's Python API has no
        event for a new transport: polled)."""
        deadline = time.monotonic() + self.mesh_secs
        while (gaps := bus.mesh_gaps()) and time.monotonic() < deadline:
            time.sleep(MESH_POLL_SECS)
        return gaps

    def supervise(self, bus: Bus, policy: RestartPolicy | None = None) -> Supervisor:
        """Restart crashed nodes with back-off (:mod:`constructaide.app.supervise`), NodeErrors on ``bus``; a pair
        of sessions left without a transport (a restarted node that did not reach a peer) is reported too."""

        def report(node: str, reason: str) -> None:
            err = NodeError(
                site=self.site, node=node, topic="supervisor", reason=reason, key="", time_ns=time.time_ns()
            )
            bus.publish(keys.key(keys.ERRORS, site=self.site), err)

        self.supervisor = Supervisor(
            lambda: list(self.procs), report, policy or RestartPolicy(), gaps=bus.mesh_gaps
        ).start()
        return self.supervisor

    def stop_all(self) -> dict[str, int | None]:
        if self.supervisor is not None:
            self.supervisor.close()
            self.supervisor = None
        return {p.name: p.stop() for p in reversed(self.procs)}

    def __enter__(self) -> Launcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


@contextlib.contextmanager
def site_processes(
    site: str,
    bus: BusConfig,
    log_dir: Path | None,
    state_dir: Path | None = None,
    security_toml: Path | None = None,
) -> Iterator[Launcher]:
    launcher = Launcher(site=site, bus=bus, log_dir=log_dir, state_dir=state_dir, security_toml=security_toml)
    try:
        yield launcher
    finally:
        launcher.stop_all()


def run_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="constructaide run", description="Start all nodes of a site from a TOML config.")
    p.add_argument("config", type=Path)
    p.add_argument("--log-dir", type=Path, default=Path("recordings/logs"))
    p.add_argument(
        "--state-dir",
        type=Path,
        default=None,
        help="nodes' ledgers and state (a restarted node resumes there; default: 'state' beside the log folder); "
        "'none' to start every node empty",
    )
    p.add_argument("--no-supervise", action="store_true", help="do not restart crashed nodes")
    add_bus_args(p)
    args = p.parse_args(argv)
    try:
        doc = tomllib.loads(args.config.read_text())
    except FileNotFoundError:
        raise UserError(f"config file not found: {args.config}") from None
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{args.config} is not valid TOML: {e}") from None
    site = doc.get("site", {}).get("name")
    if not site:
        raise UserError(f"{args.config}: [site] name is required")
    nodes = doc.get("nodes", {})
    if not nodes:
        raise UserError(f"{args.config}: no [nodes.NAME] tables, nothing to run")
    bus_doc = doc.get("bus", {})
    bus = BusConfig.from_args(args, role="router")
    bus.connect = bus.connect or list(bus_doc.get("connect", []))
    bus.listen = bus.listen or list(bus_doc.get("listen", []))
    if args.mode is None and bus_doc.get("mode"):
        bus.mode = str(bus_doc["mode"])
    security_toml = None
    if "tls" in bus_doc or "acl" in bus_doc:
        security_toml = args.config.resolve()
        bus.security = load_security(security_toml, "router")  # this session relays for the nodes
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    workers = {str(k): int(v) for k, v in doc.get("workers", {}).items()}
    unknown = sorted(set(workers) - set(nodes))
    if unknown:
        raise UserError(f"{args.config}: [workers] names nodes without a [nodes.NAME] table: {', '.join(unknown)}")
    cameras = [str(c) for c in doc.get("site", {}).get("cameras", [])]
    state_dir = args.state_dir or args.log_dir.parent / "state"
    state_dir = None if str(state_dir).lower() == "none" else state_dir
    with site_processes(site, bus, args.log_dir, state_dir, security_toml) as launcher, open_bus(bus) as session:
        for name in nodes:
            launcher.start_workers(name, workers.get(name, 1), args.config, f"nodes.{name}", cameras=cameras)
        launcher.wait_live(session, list(nodes))
        for name, count in workers.items():
            if count > 1:
                launcher.wait_workers(session, name, count)
        if not args.no_supervise:
            launcher.supervise(session, _policy(doc.get("supervise", {}), args.config))
        print(
            f"site {site}: {len(nodes)} nodes live ({', '.join(nodes)}); logs in {args.log_dir}; Ctrl-C to stop",
            file=sys.stderr,
        )
        stop.wait()
    return 0


def _policy(doc: dict, path: Path) -> RestartPolicy:
    """``[supervise]`` table of the site TOML: the fields of :class:`RestartPolicy`."""
    try:
        return RestartPolicy(**doc)
    except TypeError as e:
        raise UserError(f"{path}: bad [supervise] table: {e}") from None
