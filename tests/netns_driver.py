"""Test driver for the multi-host test: a camera and an observer in one process.

``python tests/netns_driver.py BUS-ARGS...`` waits for a register node on the bus, pushes a fixed camera's
anchor frame and its clicks, then three more frames, and prints the four registrations as JSON lines
(photo id, status, method, world_from_camera). Run on one host (loopback hub) and across network namespaces
through a router, the output must agree.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_register_stream_node import SITE, H, W, clicks_msg, make_photo  # noqa: E402
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera  # noqa: E402

from constructaide.runtime import BusConfig, add_bus_args, open_bus  # noqa: E402
from schemas import keys  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--timeout", type=float, default=90.0)
    add_bus_args(ap)
    args = ap.parse_args()
    site = SITE
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(11)
    frames = [(intr, T)] + [jitter(T, intr, rng, 0.3, 0.005) for _ in range(3)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), "cam-z", k) for k, (i, t) in enumerate(frames)]
    px, pts = anchor_clicks(intr, T, noise_px=0.2)
    with open_bus(BusConfig.from_args(args)) as bus:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=site))
        bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=site, node="register")], timeout=args.timeout)
        photo_key = keys.key(keys.PHOTO, site=site, camera="cam-z")
        clicks = clicks_msg(photos[0].photo_id, px, pts)
        bus.publish(photo_key, photos[0])
        bus.publish(keys.key(keys.ANCHORS, site=site, photo=photos[0].photo_id), clicks)
        regs.wait(1, timeout=args.timeout)
        for p in photos[1:]:
            bus.publish(photo_key, p)
        for _k, r in regs.wait(len(photos), timeout=args.timeout):
            print(json.dumps([r.photo_id, r.status, r.method, list(r.world_from_camera)]), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
