"""Late joiner's latched fetch by payload size, with one holder and with a second, slow holder of the same key.

A hub session publishes random bytes latched on a concrete key (``ZenohBus.publish(latched=True)``, default
``chunk_bytes``: 40 MiB goes in parts); a new process joins it and subscribes with ``fetch_latched=True`` (what a
node's latched input does). Reported: seconds from the joiner's session open until its callback holds the
payload, and until ``subscribe`` returns. "slow second holder": another session also declares a queryable on the
key and answers (with nothing) only after ``--slow-secs``, like a starved or frozen node that latched the key
earlier; baseline in the same run: the same size with one holder. Median of ``--runs``; joins one after another.

    python bench/latejoin.py [--runs 7] [--slow-secs 2] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench._report import code_version, median, table, write_section  # noqa: E402
from constructaide.runtime import BusConfig, open_bus  # noqa: E402

KEY = "constructaide/bench/bim/model"
SIZES = [("1 KiB", 2**10), ("0.3 MiB", int(0.3 * 2**20)), ("5 MiB", 5 * 2**20), ("40 MiB", 40 * 2**20)]
JOINER = r"""
import json, sys, threading, time
from constructaide.runtime import BusConfig, open_bus
port, key = int(sys.argv[1]), sys.argv[2]
got, box = threading.Event(), {}
with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])) as bus:
    t_open = time.perf_counter()
    def on_payload(k, payload):
        box["recv"], box["n"] = time.perf_counter(), len(payload)
        got.set()
    sub = bus.subscribe(key, on_payload, fetch_latched=True)
    t_ret = time.perf_counter()
    ok = got.wait(120)
    sub.close()
out = {"ok": ok, "returned_s": t_ret - t_open}
if ok:
    out.update(received_s=box["recv"] - t_open, nbytes=box["n"])
print(json.dumps(out))
"""


def joins(port: int, runs: int) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = []
    for _ in range(runs):
        p = subprocess.run(
            [sys.executable, "-c", JOINER, str(port), KEY],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        if p.returncode != 0:
            raise RuntimeError(f"joiner failed: {p.stderr.strip().splitlines()[-3:]}")
        out.append(json.loads(p.stdout.strip().splitlines()[-1]))
    return out


def case(size: int, runs: int, slow_secs: float | None) -> tuple[list[dict], int]:
    """Joins of a hub holding ``size`` random bytes latched, and how many queries the slow holder got."""
    timers: list[threading.Timer] = []

    def slow(query: Any) -> None:
        # no reply; the final (the end of this holder's answer) goes with query.drop(), after slow_secs
        timers.append(t := threading.Timer(slow_secs or 0.0, query.drop))
        t.start()

    with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"])) as hub:
        port = hub.listen_port()
        hub.publish(KEY, os.urandom(size), latched=True)
        if slow_secs is None:
            return joins(port, runs), 0
        with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])) as other:
            q = other.session.declare_queryable(KEY, slow)
            try:
                return joins(port, runs), len(timers)
            finally:
                for t in timers:
                    t.join()
                q.undeclare()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--slow-secs", type=float, default=2.0, help="when the slow second holder answers")
    ap.add_argument("--no-write", action="store_true", help="print only, do not update BENCHMARKS.md")
    args = ap.parse_args(argv)
    load_before = os.getloadavg()[0]
    rows: list[list[object]] = []
    for name, size in SIZES:
        base: float | None = None
        for label, slow in [("one holder", None), (f"+ a holder answering after {args.slow_secs:g} s", args.slow_secs)]:
            js, asked = case(size, args.runs, slow)
            ok = [j for j in js if j["ok"] and j["nbytes"] == size]
            print(f"{name} {label}: {js} (slow holder asked {asked} times)", file=sys.stderr, flush=True)
            if not ok:
                rows.append([name, label, f"FAILED 0/{len(js)}", "", "", "", ""])
                continue
            rec = median([j["received_s"] for j in ok])
            base = rec if base is None else base
            rows.append(
                [
                    name,
                    label,
                    rec,
                    max(j["received_s"] for j in ok),
                    median([j["returned_s"] for j in ok]),
                    rec / base,
                    f"{len(ok)}/{len(js)}" + ("" if slow is None else f", slow holder asked {asked}"),
                ]
            )
    headers = [
        "payload",
        "latched holders",
        "holds payload s (median)",
        "max s",
        "subscribe returned s",
        "ratio vs one holder",
        "joins that got it",
    ]
    body = (
        f"Code: {code_version()}. Late joiner (zenoh, loopback; a new process per join, seconds from its session "
        f"open) of a hub session holding random bytes latched on one key (default chunk_bytes), median of "
        f"{args.runs}:\n\n"
        + table(headers, rows)
        + f"\n\nMachine load average (1 min) at start / end: {load_before:.1f} / {os.getloadavg()[0]:.1f} (shared "
        f"machine; seconds scale with its load)."
    )
    print(body)
    if not args.no_write:
        write_section("latejoin", body, f"python bench/latejoin.py --runs {args.runs} --slow-secs {args.slow_secs:g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
