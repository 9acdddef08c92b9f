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
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import threading
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from constructaide.errors import UserError
from constructaide.runtime import Bus, BusConfig, add_bus_args, open_bus
from constructaide.runtime.security import load_security
from schemas import keys


@dataclass
class NodeProcess:
    name: str
    argv: list[str]
    log_path: Path | None = None
    proc: subprocess.Popen[bytes] | None = None
    _log: object = None

    def start(self, env: dict[str, str]) -> None:
        stdout = subprocess.DEVNULL
        if self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            self._log = open(self.log_path, "ab")  # noqa: SIM115 - closed in stop()
            stdout = self._log  # type: ignore[assignment]
        self.proc = subprocess.Popen(self.argv, env=env, stdout=stdout, stderr=subprocess.STDOUT)

    def stop(self, timeout: float = 90.0) -> int | None:
        """SIGINT, then up to ``timeout`` s for the node to drain its queue (its worker gets 60 s), then SIGKILL."""
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
        return self.proc.returncode


@dataclass
class Launcher:
    """Runs node processes that share one bus configuration; a context manager that stops them all."""

    site: str
    bus: BusConfig = field(default_factory=BusConfig)
    log_dir: Path | None = None
    procs: list[NodeProcess] = field(default_factory=list)
    security_toml: Path | None = None  # site TOML with [bus.tls]: each node loads its own certificate from it

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
        self, node: str, config: Path | None = None, section: str | None = None, sets: list[str] | None = None
    ) -> NodeProcess:
        argv = [sys.executable, "-m", "constructaide.app.cli", "node", node, "--site", self.site, *self.bus_argv()]
        if config is not None:
            argv += ["--config", str(config)]
            if section:
                argv += ["--section", section]
        for s in sets or []:
            argv += ["--set", s]
        log = self.log_dir / f"{node}.log" if self.log_dir else None
        p = NodeProcess(node, argv, log)
        env = dict(os.environ)
        env.setdefault("PYOPENGL_PLATFORM", "egl")
        p.start(env)
        self.procs.append(p)
        return p

    def wait_live(self, bus: Bus, names: list[str], timeout: float = 120.0) -> None:
        """Block until every named node has declared its liveliness token; fail early if one died."""
        dead = [p.name for p in self.procs if p.proc is not None and p.proc.poll() is not None]
        if dead:
            raise UserError(f"node(s) exited at start: {', '.join(dead)} (see logs in {self.log_dir})")
        try:
            bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=self.site, node=n) for n in names], timeout=timeout)
        except TimeoutError as e:
            dead = [p.name for p in self.procs if p.proc is not None and p.proc.poll() is not None]
            raise UserError(f"{e}; exited: {dead or 'none'} (see logs in {self.log_dir})") from None

    def stop_all(self) -> dict[str, int | None]:
        return {p.name: p.stop() for p in reversed(self.procs)}

    def __enter__(self) -> Launcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


@contextlib.contextmanager
def site_processes(
    site: str, bus: BusConfig, log_dir: Path | None, security_toml: Path | None = None
) -> Iterator[Launcher]:
    launcher = Launcher(site=site, bus=bus, log_dir=log_dir, security_toml=security_toml)
    try:
        yield launcher
    finally:
        launcher.stop_all()


def run_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="constructaide run", description="Start all nodes of a site from a TOML config.")
    p.add_argument("config", type=Path)
    p.add_argument("--log-dir", type=Path, default=Path("recordings/logs"))
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
    with site_processes(site, bus, args.log_dir, security_toml) as launcher, open_bus(bus) as session:
        for name in nodes:
            launcher.start(name, args.config, f"nodes.{name}")
        launcher.wait_live(session, list(nodes))
        print(
            f"site {site}: {len(nodes)} nodes live ({', '.join(nodes)}); logs in {args.log_dir}; Ctrl-C to stop",
            file=sys.stderr,
        )
        stop.wait()
    return 0
