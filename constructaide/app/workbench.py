"""``constructaide workbench --recording FILE``: open a recording in the browser workbench for review.

Every message of the recording is loaded into the workbench; anchor answers are solved and shown, annotations
kept, but nothing is published unless ``--live`` (then the workbench node joins the bus, publishes what people
make and keeps receiving the live site).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

import msgspec

from constructaide.errors import UserError
from constructaide.runtime import BusConfig, add_bus_args, open_bus, start_node
from nodes.recorder.mcapio import RecordingError, iter_messages
from nodes.workbench.api import HttpServer, make_app
from nodes.workbench.node import SPEC, Config, access_token
from nodes.workbench.service import Workbench
from schemas import codec
from schemas.messages import Message


def load_recording(path: Path) -> tuple[list[Message], int]:
    """Decoded messages of a recording (file order) and the number of records that did not decode."""
    if not path.is_file():
        raise UserError(f"recording not found: {path}")
    out: list[Message] = []
    bad = 0
    try:
        for rec in iter_messages(path, allow_truncated=True):
            try:
                out.append(codec.decode(rec.payload))
            except (msgspec.DecodeError, msgspec.ValidationError):
                bad += 1
    except RecordingError as e:
        raise UserError(str(e)) from None
    return out, bad


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="constructaide workbench", description=__doc__)
    ap.add_argument("--recording", type=Path, required=True, help="MCAP recording to open")
    ap.add_argument("--host", default="127.0.0.1", help="address to serve on (non-loopback needs a token)")
    ap.add_argument("--port", type=int, default=8770, help="TCP port (0: any free port)")
    ap.add_argument("--token", default="", help="access token (generated when serving a non-loopback host)")
    ap.add_argument("--site", default=None, help="site id (default: the recording's)")
    ap.add_argument("--live", action="store_true", help="publish anchor clicks and annotations on the bus")
    add_bus_args(ap)
    args = ap.parse_args(argv)
    messages, bad = load_recording(args.recording)
    if not messages:
        raise UserError(f"{args.recording} holds no decodable messages")
    site = args.site or messages[0].site
    config = Config(site=site, host=args.host, port=args.port, token=args.token, live=args.live)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    note = f" ({bad} undecodable records skipped)" if bad else ""
    if args.live:
        with open_bus(BusConfig.from_args(args)) as bus, start_node(SPEC, config, bus) as node:
            for m in messages:
                node.obj.workbench.apply(m)
            print(f"workbench (live, site {site}): {node.obj.url}  {len(messages)} messages{note}; Ctrl-C to stop")
            sys.stdout.flush()
            stop.wait()
        return 0
    wb = Workbench(site, publish=None)
    try:
        for m in messages:
            wb.apply(m)
        token = access_token(config)
        try:
            server = HttpServer(make_app(wb, token), args.host, args.port)
        except OSError as e:
            raise UserError(str(e)) from None
        with server:
            url = server.url + (f"?token={token}" if token else "")
            print(f"workbench (review, nothing is published): {url}  {len(messages)} messages{note}; Ctrl-C to stop")
            sys.stdout.flush()
            stop.wait()
    finally:
        wb.close()
    return 0
