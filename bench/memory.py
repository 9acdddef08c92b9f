"""Memory of the register node over many frames of fixed cameras: bounded map vs the unbounded map.

    nice -n 10 python bench/memory.py [--frames 200] [--every 50] [--no-write]

The shipping :class:`nodes.register.node.RegisterNode`, in-process on the in-process bus (no zenoh: the figures
are the node's own state, not the bus's), fed the frames bench/chaos.py streams: the small synthetic site's
(seed 0) fixed-camera frames, repeated with new photo ids and capture times a repeat's span later, after the
site's up-front anchor clicks. Two runs in one process each (fresh subprocess per variant): the node at its
default config (``stream.max_map_images_per_camera`` = 8) and the baseline without that bound (0: the map keeps
every key frame, as before the bound). Sampled every ``--every`` frames: resident memory (RSS), map images,
verified pairs, map tracks, pose records, seconds per frame over the last interval.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import code_version, table, write_section  # noqa: E402


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


def child(frames_n: int, every: int, cap: int | None) -> None:
    """One variant in this process; prints one JSON line per sample."""
    from chaos import SITE, frames

    from constructaide import sitedir
    from constructaide.runtime import NodeContext
    from constructaide.runtime.local import LocalBus
    from constructaide.synth import ensure_site
    from nodes.register.node import Config, RegisterNode
    from nodes.register.streaming import StreamConfig
    from schemas import keys

    site = ensure_site("small", 0, ROOT / ".cache" / "synth")
    stream, by_rel = frames(site, frames_n)
    cfg = Config(site=SITE) if cap is None else Config(site=SITE, stream=StreamConfig(max_map_images_per_camera=cap))
    bus = LocalBus()
    regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
    node = RegisterNode(cfg, NodeContext(bus, SITE, "register"))
    for a in sitedir.anchor_messages(SITE, site, by_rel):
        node.on_anchors(a, "")
    t, done = time.perf_counter(), 0
    for i, photo in enumerate(stream):
        node.on_photo(photo, "")
        if (i + 1) % every == 0 or i + 1 == len(stream):
            r = node.registrar
            now = time.perf_counter()
            latest = {m.photo_id: m.status for _, m in regs.items}
            sample = {
                "frames": i + 1,
                "rss_mib": rss_mib(),
                "map_images": len(r.recon.images),
                "pairs": len(r.recon.pairs),
                "tracks": len(r.recon.track_obs),
                "poses": len(r.poses),
                "failed": sum(s == "failed" for s in latest.values()),
                "secs_per_frame": (now - t) / (i + 1 - done),
            }
            print(json.dumps(sample), flush=True)
            t, done = now, i + 1


def run_variant(frames_n: int, every: int, cap: int | None) -> list[dict]:
    cmd = [sys.executable, __file__, "--child", "--frames", str(frames_n), "--every", str(every)]
    if cap is not None:
        cmd += ["--cap", str(cap)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--cap", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.frames, args.every, args.cap)
        return 0
    variants = {"default (8 map images per camera)": None, "baseline: unbounded map": 0}
    results = {}
    for name, cap in variants.items():
        print(f"{name} ...", file=sys.stderr)
        results[name] = run_variant(args.frames, args.every, cap)
    headers = ["variant", "frames", "RSS MiB", "map images", "pairs", "tracks", "pose records", "failed", "s/frame"]
    rows = [
        [
            name,
            s["frames"],
            round(s["rss_mib"]),
            s["map_images"],
            s["pairs"],
            s["tracks"],
            s["poses"],
            s["failed"],
            round(s["secs_per_frame"], 2),
        ]
        for name, samples in results.items()
        for s in samples
    ]
    out = table(headers, rows)
    print(out)
    last = {name: samples[-1] for name, samples in results.items()}
    (d, dv), (b, bv) = last.items()
    ratio = dv["rss_mib"] / bv["rss_mib"]
    line = (
        f"frames {dv['frames']}: RSS {dv['rss_mib']:.0f} MiB bounded vs {bv['rss_mib']:.0f} MiB unbounded "
        f"(ratio {ratio:.2f}), map images {dv['map_images']} vs {bv['map_images']}"
    )
    print(line)
    if not args.no_write:
        body = (
            f"Code: {code_version()}. The register node in-process (in-process bus), fed bench/chaos.py's frames "
            "(the small site's 3 fixed cameras, seed 0, repeated with later capture times) after the site's "
            "up-front anchors; each variant in a fresh subprocess, one run each (the figures are sizes, not "
            "timings; s/frame is informative only, the machine was shared).\n\n" + out + "\n\n" + line
        )
        write_section("memory (register node)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
