"""Sessions that query right after they joined the embedded hub: do they reach the other peers' data?

A hub session and a publishing peer (``open_bus(BusConfig(hub_port=...))``, the embedded loopback scheme every node
uses by default) hold a latched value and a recent publication; a third session joins and at once asks for them
(a node restarting: its latched inputs, then its catch-up on the bus history). Reported per kind of query: how many
of ``--joins`` joins came back without the other peer's data, and the median seconds from the start of the join
(``open_bus``) to the answer. Fresh hub, peer and joiner for every join; one after another, in this process.

    python bench/joinrace.py [--joins 30] [--no-write]
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench._report import code_version, median, table, write_section  # noqa: E402
from constructaide.runtime import BusConfig, open_bus  # noqa: E402

LATCHED, PHOTO = "constructaide/bench/bim/model", "constructaide/bench/photo/cam-a"


def free_hub_port() -> int:
    """A loopback port for a fresh hub (bound and released; the hub binds it a moment later)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def one_join(kind: str) -> tuple[bool, float]:
    """(the joiner got the peer's data, seconds from the join's start to the answer)."""
    hub_port = free_hub_port()
    with open_bus(BusConfig(hub_port=hub_port)), open_bus(BusConfig(hub_port=hub_port)) as peer:
        payload = os.urandom(1000)
        peer.publish(LATCHED if kind == "latched" else PHOTO, payload, latched=kind == "latched")
        t0 = time.perf_counter()
        with open_bus(BusConfig(hub_port=hub_port)) as late:
            if kind == "latched":
                got = [p for _k, p in late.collect(LATCHED, decode=False, fetch_latched=True).items]
            else:
                got = [p.payload for p in late.history("constructaide/bench/**", 0, timeout=10)]
            return got == [payload], time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--joins", type=int, default=30)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    rows = []
    for kind, label in (("latched", "latched fetch (fetch_latched=True)"), ("history", "history query (catch-up)")):
        results = [one_join(kind) for _ in range(args.joins)]
        missed = sum(1 for ok, _ in results if not ok)
        rows.append([label, args.joins, missed, f"{median([s for _, s in results]):.3f}"])
    body = table(["query right after joining", "joins", "missed the peer's data", "median s (join + answer)"], rows)
    print(body)
    if not args.no_write:
        note = (
            f"Code: {code_version()}. A hub, a publishing peer and a joiner on loopback (the embedded scheme), fresh "
            "for every join; the joiner asks at once after `open_bus` returns."
        )
        write_section("join race (late joiners)", note + "\n\n" + body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
