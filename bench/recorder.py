"""MCAP recorder file throughput: write (flush per photo), read back, repair a truncated file.

For 1 MiB and 8 MiB Photo payloads (random bytes, like JPEG: incompressible): MiB/s of
``RecordingWriter.write`` with a chunk flush after every photo, of ``iter_recording``, and of
``repair`` on the same file cut in the middle. Baseline: the same payload bytes written with
plain ``file.write`` + ``flush`` (ratio = recorder MiB/s / baseline MiB/s).

    python bench/recorder.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _report import median, table, write_section  # noqa: E402

from nodes.recorder import mcapio  # noqa: E402
from schemas import codec, keys  # noqa: E402
from schemas.messages import Photo  # noqa: E402


def one_run(tmp: Path, payload_mib: int, count: int) -> dict[str, float]:
    data = np.random.default_rng(payload_mib).integers(0, 256, payload_mib << 20, dtype=np.uint8).tobytes()
    payloads = [
        codec.encode(Photo(site="b", photo_id=f"p{i}", camera_id="c", capture_time_ns=i, data=data))
        for i in range(count)
    ]
    mib = sum(len(p) for p in payloads) / 2**20
    key = keys.key(keys.PHOTO, site="b", camera="c")

    raw = tmp / "raw.bin"
    t0 = time.perf_counter()
    with open(raw, "wb") as f:
        for p in payloads:
            f.write(p)
            f.flush()
    baseline = mib / (time.perf_counter() - t0)
    raw.unlink()

    path = tmp / "rec.mcap"
    t0 = time.perf_counter()
    with mcapio.RecordingWriter(path) as w:
        for i, p in enumerate(payloads):
            w.write(key, p, i)
    write = mib / (time.perf_counter() - t0)

    t0 = time.perf_counter()
    n = sum(1 for _ in mcapio.iter_recording(path))
    read = mib / (time.perf_counter() - t0)
    assert n == count

    cut = tmp / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    t0 = time.perf_counter()
    report = mcapio.repair(cut, tmp / "fixed.mcap")
    repair_secs = time.perf_counter() - t0
    repaired = report.messages * len(payloads[0]) / 2**20 / repair_secs
    path.unlink()
    return {"baseline": baseline, "write": write, "read": read, "repair": repaired, "recovered": report.messages}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer messages")
    ap.add_argument("--repeats", type=int, default=3, help="runs per case; the median is reported")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for mib, count in ((1, 20 if args.quick else 100), (8, 4 if args.quick else 16)):
            runs = [one_run(Path(d), mib, count) for _ in range(args.repeats)]
            med = {k: median([r[k] for r in runs]) for k in runs[0]}
            rows.append(
                [
                    f"{mib} MiB x {count}",
                    med["baseline"],
                    med["write"],
                    med["write"] / med["baseline"],
                    med["read"],
                    med["repair"],
                    f"{int(med['recovered'])}/{count}",
                ]
            )
    headers = [
        "payload",
        "raw write MiB/s",
        "recorder write MiB/s",
        "ratio",
        "read MiB/s",
        "repair MiB/s",
        "recovered (cut at 50%)",
    ]
    body = table(headers, rows)
    print(body)
    write_section(
        "recorder",
        "Recorder file I/O (zstd chunks, chunk flushed after every photo), median of "
        f"{args.repeats} runs; random payload bytes (incompressible, like JPEG).\n\n" + body,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
