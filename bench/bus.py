"""Bus throughput and latency between two processes, with and without the MCAP recorder attached.

For each payload size (1 MiB and 8 MiB Photo messages): round-trip latency (publish a Photo, the peer
process answers with a Registration; median of N sequential pings) and throughput (publish N photos
back to back with congestion control BLOCK; time until the peer has answered all). "with recorder"
runs the recorder node as a third process writing every message to MCAP (zstd) meanwhile.

    python bench/bus.py [--quick]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _report import median, table, write_section  # noqa: E402

from constructaide.runtime import BusConfig, open_bus  # noqa: E402
from schemas import keys  # noqa: E402
from schemas.messages import Photo  # noqa: E402

SITE = "bench"
HERE = Path(__file__).resolve().parent


def run_case(bus, payload_mib: int, pings: int, burst: int) -> tuple[float, float, float]:
    """Returns (median round trip ms, messages/s, MiB/s)."""
    # Incompressible bytes, like JPEG data (a repeated pattern would flatter the recorder's zstd).
    rng_bytes = np.random.default_rng(payload_mib).bytes(payload_mib * 2**20)
    regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE), decode=False)
    rtts = []
    seq = 0
    for _ in range(pings):
        seq += 1
        photo = Photo(site=SITE, photo_id=f"p{payload_mib}-{seq}", camera_id="cam", capture_time_ns=seq, data=rng_bytes)
        t0 = time.perf_counter()
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam"), photo)
        regs.wait(seq, timeout=60)
        rtts.append((time.perf_counter() - t0) * 1e3)
    t0 = time.perf_counter()
    for _ in range(burst):
        seq += 1
        photo = Photo(site=SITE, photo_id=f"p{payload_mib}-{seq}", camera_id="cam", capture_time_ns=seq, data=rng_bytes)
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam"), photo)
    regs.wait(seq, timeout=300)
    secs = time.perf_counter() - t0
    regs.close()
    return median(rtts), burst / secs, burst * payload_mib / secs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer messages")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case; the median is reported")
    args = ap.parse_args()
    pings, burst = (10, 20) if args.quick else (30, 100)
    rows = []
    for recorder in (False, True):
        with tempfile.TemporaryDirectory() as tmp, open_bus(BusConfig(listen=["tcp/127.0.0.1:0"])) as bus:
            port = bus.listen_port()  # the bench's session is the hub; the peers join it
            procs = [
                subprocess.Popen(
                    [sys.executable, str(HERE / "_bus_peer.py"), "--site", SITE, "--hub-port", str(port)],
                    stdout=subprocess.DEVNULL,
                )
            ]
            expect = [keys.pattern(keys.LIVELINESS, site=SITE, node="benchpeer")]
            if recorder:
                procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "constructaide.app.cli", "node", "recorder", "--site", SITE]
                        + ["--hub-port", str(port), "--set", f"directory='{tmp}'"],
                        stdout=subprocess.DEVNULL,
                    )
                )
                expect.append(keys.pattern(keys.LIVELINESS, site=SITE, node="recorder"))
            try:
                bus.wait_for_tokens(expect, timeout=60)
                for mib in (1, 8):
                    runs = [run_case(bus, mib, pings, burst if mib == 1 else burst // 4) for _ in range(args.repeats)]
                    rtt = median([r[0] for r in runs])
                    mps = median([r[1] for r in runs])
                    mibs = median([r[2] for r in runs])
                    rows.append([f"{mib} MiB", "yes" if recorder else "no", rtt, mps, mibs])
                    print(rows[-1], flush=True)
            finally:
                for p in procs:
                    p.terminate()
                    p.wait(60)
            if recorder:
                files = list(Path(tmp).glob("*.mcap"))
                size = sum(f.stat().st_size for f in files)
                rows[-1].append(f"{len(files)} file(s), {size / 2**20:.0f} MiB")
    for r in rows:
        if len(r) == 5:
            r.append("")
    body = table(["payload", "recorder", "round trip ms (median)", "messages/s", "MiB/s", "mcap written"], rows)
    body += (
        "\n\nTwo processes on loopback (zenoh peer, TCP, congestion control BLOCK). Round trip = Photo out, "
        "Registration back, sequential. Throughput = burst of Photos until the peer answered all. "
        f"Median of {args.repeats} runs per row."
    )
    print(body)
    write_section("bus", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
