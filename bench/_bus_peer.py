"""Peer process for bench/bus.py: answers every Photo with a tiny Registration (zenoh callback thread)."""

from __future__ import annotations

import argparse
import signal
import threading

from constructaide.runtime import BusConfig, add_bus_args, open_bus
from schemas import codec, keys
from schemas.messages import Photo, Registration


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--site", default="bench")
    add_bus_args(p)
    args = p.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    with open_bus(BusConfig.from_args(args)) as bus:

        def on_photo(key: str, payload: bytes) -> None:
            photo = codec.decode(payload, Photo)
            reply = Registration(
                site=photo.site, photo_id=photo.photo_id, status="failed", message=str(len(photo.data))
            )
            bus.publish(
                keys.key(keys.REGISTRATION, site=args.site, camera=photo.camera_id, photo=photo.photo_id), reply
            )

        sub = bus.subscribe(keys.pattern(keys.PHOTO, site=args.site), on_photo)
        token = bus.declare_token(keys.key(keys.LIVELINESS, site=args.site, node="benchpeer", instance="0"))
        stop.wait()
        token.close()
        sub.close()


if __name__ == "__main__":
    main()
