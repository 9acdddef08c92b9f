"""``constructaide push``: publish photo files as a camera would."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from constructaide.errors import UserError
from constructaide.runtime import BusConfig, add_bus_args, open_bus
from schemas import keys


def main(argv: list[str]) -> int:
    from constructaide.photos import PhotoError, photo_from_file

    p = argparse.ArgumentParser(prog="constructaide push", description="Publish photo files (JPEG/PNG) on the bus.")
    p.add_argument("files", nargs="+", type=Path)
    p.add_argument("--camera", default=None, help="fixed camera id (omit for phone photos)")
    p.add_argument("--site", default="demo")
    p.add_argument("--tz", default="UTC", help="site IANA time zone for photos whose EXIF has no offset")
    p.add_argument("--use-mtime", action="store_true", help="stamp photos without EXIF time with the file time")
    p.add_argument("--wait-for", default="*", help="node that must be live before publishing (default: any)")
    p.add_argument("--timeout", type=float, default=30.0)
    add_bus_args(p)
    args = p.parse_args(argv)
    if args.camera is not None:
        keys.check_chunk(args.camera, "camera")
    missing = [str(f) for f in args.files if not f.is_file()]
    if missing:
        raise UserError(f"no such file: {', '.join(missing[:3])}")
    from constructaide.runtime.security import camera_role

    with open_bus(BusConfig.from_args(args, role=camera_role(args.camera) if args.camera else "admin")) as bus:
        try:
            bus.wait_for_tokens(
                [
                    keys.pattern(
                        keys.LIVELINESS, site=args.site, **({} if args.wait_for == "*" else {"node": args.wait_for})
                    )
                ],
                timeout=args.timeout,
            )
        except TimeoutError:
            raise UserError(
                f"no node live on site {args.site!r} within {args.timeout:.0f} s; start one first"
            ) from None
        sent = 0
        for f in tqdm(args.files, desc="push", unit="photo", file=sys.stderr):
            try:
                photo = photo_from_file(f, camera_id=args.camera, site=args.site, tz=args.tz, use_mtime=args.use_mtime)
            except PhotoError as e:
                raise UserError(f"{e} ({sent} photo(s) pushed before it)") from None
            bus.publish(keys.key(keys.PHOTO, site=args.site, camera=args.camera), photo)
            sent += 1
    print(f"pushed {sent} photo(s) to site {args.site}")
    return 0
