"""``constructaide`` command line: one entry for every node and tool.

Errors the user can fix print as one line (exit 2); unexpected ones print one line too, with
``CONSTRUCTAIDE_DEBUG=1`` for the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from constructaide.errors import UserError

NODE_MODULES = {
    "ingest": "nodes.ingest.node",
    "register": "nodes.register.node",
    "occlude": "nodes.occlude.node",
    "render": "nodes.render.node",
    "recorder": "nodes.recorder.node",
    "dashboard": "nodes.dashboard.node",
    "workbench": "nodes.workbench.node",
    "progress": "nodes.progress.node",
}

USAGE = """usage: constructaide COMMAND [ARGS...]

main job
  demo                 run every node on the embedded synthetic site; writes .mcap and .rrd
  run CONFIG.toml      start all nodes of a site from a TOML config
nodes and bus
  node NAME [...]      run one node (ingest, register, occlude, render, recorder, dashboard, workbench,
                       progress)
  router               run a zenoh router so nodes on several machines can meet
  certs --out DIR      make a test CA and a certificate per node role (TLS, mutual TLS, ACL)
  status               list live nodes
  push FILES --camera ID
                       publish photo files as a camera would
recordings
  workbench --recording FILE [--host H] [--port P] [--live]
                       open a recording in the browser workbench (review; --live publishes answers)
  replay FILE [--rate R|max]
                       re-publish a recording so nodes process it again
  recording repair FILE
                       recover the complete chunks of a truncated recording
tools
  synth --out DIR      generate a synthetic construction site with ground truth
  bim summary MODEL... element counts, schedule and states of IFC models
  register --images DIR --anchors FILE --out DIR
                       batch model-assisted SfM to a COLMAP text model
  render --photo ID --mode MODE --out FILE.png
                       render one overlay from a recording
progress
  progress --recording FILE --out DIR
                       per-photo evidence and per-element progress of a recording (observations.csv, elements.csv)
  export ifc|bcf|csv|mp4|gltf --recording FILE --out PATH
                       detected progress for other tools: IFC with actual dates, BCF issues, CSV report,
                       time-lapse MP4 per fixed camera, glTF of the model with the registered cameras

`constructaide COMMAND --help` for the options of each command.
"""


def _delegate(module: str, func: str = "main") -> Callable[[list[str]], int]:
    def run(argv: list[str]) -> int:
        mod = importlib.import_module(module)
        return int(getattr(mod, func)(argv) or 0)

    return run


def _node(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: constructaide node {" + ",".join(NODE_MODULES) + "} [--site S] [--config F] [--set k=v] ...")
        return 0 if argv else 2
    name = argv[0]
    if name not in NODE_MODULES:
        raise UserError(f"unknown node {name!r}; choose one of: {', '.join(NODE_MODULES)}")
    mod = importlib.import_module(NODE_MODULES[name])
    from constructaide.runtime import run_node_cli

    return run_node_cli(mod.SPEC, argv[1:], prog=f"constructaide node {name}")


def _recording(argv: list[str]) -> int:
    if not argv or argv[0] != "repair":
        raise UserError("usage: constructaide recording repair FILE [--out FILE]")
    return _delegate("nodes.recorder.cli", "repair_main")(argv[1:])


def _bim(argv: list[str]) -> int:
    if not argv or argv[0] != "summary":
        raise UserError("usage: constructaide bim summary MODEL... [--schedule FILE] [--at ISO] [--json]")
    return _delegate("nodes.ingest.cli", "bim_summary_main")(argv[1:])


def _status(argv: list[str]) -> int:
    from constructaide.runtime import BusConfig, add_bus_args, open_bus

    p = argparse.ArgumentParser(prog="constructaide status", description="List live nodes (liveliness tokens).")
    p.add_argument("--site", default="*", help="site id (default: all)")
    p.add_argument("--timeout", type=float, default=2.0)
    add_bus_args(p)
    args = p.parse_args(argv)
    with open_bus(BusConfig.from_args(args)) as bus:
        tokens = bus.live_tokens(f"constructaide/{args.site}/@live/**", timeout=args.timeout)
    if not tokens:
        print("no live nodes")
        return 1
    print(f"{'site':<16} {'node':<12} instance")
    for t in tokens:
        parts = t.split("/")
        print(f"{parts[1]:<16} {parts[3]:<12} {parts[4] if len(parts) > 4 else ''}")
    return 0


def _router(argv: list[str]) -> int:
    import signal

    from constructaide.runtime import BusConfig, open_bus

    p = argparse.ArgumentParser(prog="constructaide router", description="Run a zenoh router (no zenohd needed).")
    p.add_argument("--listen", action="append", default=None, help="endpoint (default tcp/0.0.0.0:7447)")
    p.add_argument("--connect", action="append", default=None, help="other routers to connect to")
    p.add_argument("--bus-security", metavar="SITE.toml", help="site TOML with [bus.tls] / [bus.acl]")
    args = p.parse_args(argv)
    security = None
    if args.bus_security:
        from constructaide.runtime.security import load_security

        security = load_security(args.bus_security, "router")
    default_listen = f"{'tls' if security else 'tcp'}/0.0.0.0:7447"
    cfg = BusConfig(
        mode="router", listen=args.listen or [default_listen], connect=args.connect or [], security=security
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with open_bus(cfg) as bus:
        print(f"router listening on {', '.join(bus.locators())}; Ctrl-C to stop", file=sys.stderr, flush=True)
        stop.wait()
    return 0


def _certs(argv: list[str]) -> int:
    from constructaide.runtime.security import NODE_ROLES, TRUSTED_ROLES, camera_role, make_certs

    p = argparse.ArgumentParser(
        prog="constructaide certs",
        description="Make a test CA and one certificate per role (common name = role) for [bus.tls] / [bus.acl].",
    )
    p.add_argument("--out", type=Path, required=True, help="folder for ca.pem, ca.key, <role>.pem, <role>.key")
    p.add_argument("--camera", action="append", default=[], help="camera id (a camera-<id> certificate); repeat")
    p.add_argument("--host", action="append", default=None, help="name/IP in the certificates (default localhost, "
                   "127.0.0.1); repeat")  # fmt: skip
    p.add_argument("--days", type=int, default=365)
    args = p.parse_args(argv)
    roles = [*TRUSTED_ROLES, *NODE_ROLES, *(camera_role(c) for c in args.camera)]
    written = make_certs(args.out, roles, args.host, args.days)
    print(f"wrote {len(written)} files to {args.out} (CA + {len(roles)} roles: {', '.join(roles)}); test use only")
    return 0


COMMANDS: dict[str, Callable[[list[str]], int]] = {
    "demo": _delegate("constructaide.app.demo", "main"),
    "run": _delegate("constructaide.app.launch", "run_main"),
    "node": _node,
    "router": _router,
    "certs": _certs,
    "status": _status,
    "push": _delegate("constructaide.app.push", "main"),
    "replay": _delegate("nodes.recorder.cli", "replay_main"),
    "workbench": _delegate("constructaide.app.workbench", "main"),
    "recording": _recording,
    "synth": _delegate("constructaide.synth.cli", "main"),
    "bim": _bim,
    "register": _delegate("nodes.register.batch", "main"),
    "render": _delegate("nodes.render.cli", "main"),
    "progress": _delegate("nodes.progress.batch", "main"),
    "export": _delegate("nodes.progress.exports", "main"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return 0 if argv else 2
    if argv[0] == "--version":
        from constructaide import __version__

        print(__version__)
        return 0
    cmd = COMMANDS.get(argv[0])
    if cmd is None:
        print(f"constructaide: error: unknown command {argv[0]!r} (see constructaide --help)", file=sys.stderr)
        return 2
    try:
        return cmd(argv[1:])
    except UserError as e:
        print(f"constructaide {argv[0]}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"constructaide {argv[0]}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # one clear line; traceback on request
        if os.environ.get("CONSTRUCTAIDE_DEBUG"):
            raise
        print(
            f"constructaide {argv[0]}: error: {type(e).__name__}: {e} (CONSTRUCTAIDE_DEBUG=1 for details)",
            file=sys.stderr,
        )
        return 1


def cache_dir() -> Path:
    """Where generated sites and other caches live: ``$CONSTRUCTAIDE_CACHE`` or ``./.cache``."""
    return Path(os.environ.get("CONSTRUCTAIDE_CACHE", Path.cwd() / ".cache"))


if __name__ == "__main__":
    sys.exit(main())
