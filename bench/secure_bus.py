"""Bus throughput with TLS vs without, in the same run: plain TCP, TLS with mutual TLS, and TLS + access control.

Same measurement as bench/bus.py (two processes on loopback; round trip Photo -> Registration; burst throughput
with congestion control BLOCK), once per security setting. Certificates come from ``constructaide certs`` in a
temporary folder; the peer process runs with the ``register`` role (it may publish registrations under the ACL).

    python bench/secure_bus.py [--quick] [--repeats N]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _report import code_version, median, table, write_section  # noqa: E402
from bus import run_case  # noqa: E402

from constructaide.runtime import BusConfig, open_bus  # noqa: E402
from constructaide.runtime.security import NODE_ROLES, TRUSTED_ROLES, load_security, make_certs  # noqa: E402
from schemas import keys  # noqa: E402

SITE = "bench"
HERE = Path(__file__).resolve().parent
CASES = {
    "tcp": "",
    "tls + mtls": '[bus.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n',
    "tls + mtls + acl": '[bus.tls]\nca = "certs/ca.pem"\ncerts = "certs"\n\n[bus.acl]\nenabled = true\n',
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer messages")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case; the median is reported")
    args = ap.parse_args()
    pings, burst = (10, 20) if args.quick else (30, 100)
    rows: list[list[object]] = []
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        make_certs(Path(tmp) / "certs", [*TRUSTED_ROLES, *NODE_ROLES])
        buses = {}
        for i, (case, body) in enumerate(CASES.items()):  # all three set up at once, then measured in turn
            toml = Path(tmp) / f"site-{i}.toml"
            toml.write_text(f'[site]\nname = "{SITE}"\n\n' + body)
            security = load_security(toml, "router")
            proto = "tls" if security else "tcp"
            bus = stack.enter_context(open_bus(BusConfig(listen=[f"{proto}/127.0.0.1:0"], security=security)))
            argv = [sys.executable, str(HERE / "_bus_peer.py"), "--site", SITE, "--hub-port", str(bus.listen_port())]
            if security:
                argv += ["--bus-security", str(toml), "--role", "register"]
            peer = subprocess.Popen(argv, stdout=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(HERE.parent)})
            stack.callback(lambda p=peer: (p.terminate(), p.wait(60)))
            bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=SITE, node="benchpeer")], timeout=60)
            buses[case] = bus
        for mib in (1, 8):
            n = burst if mib == 1 else burst // 4
            runs: dict[str, list[tuple[float, float, float]]] = {c: [] for c in buses}
            for bus in buses.values():
                run_case(bus, mib, 2, 2)  # warm-up, not counted
            for _ in range(args.repeats):  # round robin: machine load shifts hit every case alike
                for c, bus in buses.items():
                    runs[c].append(run_case(bus, mib, pings, n))
            base = median([r[2] for r in runs["tcp"]])
            for c, rs in runs.items():
                mibs = median([r[2] for r in rs])
                rows.append([c, f"{mib} MiB", median([r[0] for r in rs]), median([r[1] for r in rs]), mibs,
                             f"{mibs / base:.2f}"])  # fmt: skip
                print(rows[-1], flush=True)
    out = table(["link", "payload", "round trip ms (median)", "messages/s", "MiB/s", "MiB/s vs tcp"], rows)
    out += (
        "\n\nTwo processes on loopback (zenoh peers, congestion control BLOCK), the bench's session is the hub. "
        "Round trip = Photo out, Registration back, sequential; throughput = a burst of Photos until the peer "
        f"answered all. Median of {args.repeats} runs per row, the cases measured in turn after a warm-up; "
        f"all rows from the same run ({code_version()}). "
        "TLS: rustls in zenoh, ECDSA P-256 certificates from `constructaide certs`."
    )
    print(out)
    write_section("secure bus (TLS vs TCP)", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
