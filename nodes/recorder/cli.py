"""Command lines for recordings: ``recording repair`` and ``replay``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from constructaide.errors import UserError
from nodes.recorder.mcapio import RecordingError, iter_messages, parse_rate, repair, replay
from schemas import keys

_INPUT_TOPICS = (
    "constructaide/*/photo/*",
    "constructaide/*/bim/model",
    "constructaide/*/bim/update",
    "constructaide/*/anchors/*",
    "constructaide/*/annotation/*",
)


def recording_site(path: Path) -> str | None:
    """Site of the first recorded key (``constructaide/<site>/...``), None for an empty recording."""
    for msg in iter_messages(path, allow_truncated=True):
        parts = msg.key.split("/")
        return parts[1] if len(parts) > 2 else None
    return None


def repair_main(argv: list[str] | None = None) -> int:
    """``recording repair FILE [--out FILE]``: recover every complete chunk of a damaged recording."""
    parser = argparse.ArgumentParser(
        prog="constructaide recording repair",
        description="Copy every complete chunk/record of a truncated or corrupt MCAP recording into a valid file.",
    )
    parser.add_argument("file", type=Path, help="recording to repair (.mcap)")
    parser.add_argument("--out", type=Path, help="output file (default: FILE with .repaired.mcap; may equal FILE)")
    args = parser.parse_args(argv)
    src: Path = args.file
    if not src.is_file():
        raise UserError(f"no such recording: {src}")
    out: Path = args.out or src.with_name(src.stem + ".repaired.mcap")
    try:
        report = repair(src, out)
    except ValueError as exc:
        raise UserError(f"{src}: {exc}") from None
    print(report.summary())
    return 0


def replay_main(argv: list[str] | None = None) -> int:
    """``replay FILE [--rate 1.0|max] [--site S] [--topics GLOB ...]``: re-publish a recording on the bus."""
    from constructaide.runtime import BusConfig, add_bus_args, open_bus

    parser = argparse.ArgumentParser(
        prog="constructaide replay",
        description="Re-publish a recording so the nodes process it again (timing by log time / rate).",
    )
    parser.add_argument("file", type=Path, help="recording (.mcap)")
    parser.add_argument("--rate", default="1.0", help="speed factor (1.0 = real time) or 'max' (default 1.0)")
    parser.add_argument("--site", help="publish under this site instead of the recorded one")
    parser.add_argument(
        "--topics",
        action="append",
        default=[],
        metavar="GLOB",
        help="only keys matching this glob (fnmatch, '*' spans '/'); repeatable",
    )
    parser.add_argument(
        "--inputs-only",
        action="store_true",
        help="only what the nodes consume from outside (photos, BIM, anchors, annotations), not derived outputs",
    )
    parser.add_argument("--allow-truncated", action="store_true", help="replay the complete part of a damaged file")
    parser.add_argument(
        "--wait-for",
        action="append",
        default=[],
        metavar="NODE",
        help="wait until this node is live on the target site before publishing (repeatable; default: any node)",
    )
    parser.add_argument(
        "--wait-secs", type=float, default=10.0, help="how long to wait for live nodes (0: publish at once)"
    )
    add_bus_args(parser)
    args = parser.parse_args(argv)
    if not args.file.is_file():
        raise UserError(f"no such recording: {args.file}")
    try:
        rate = parse_rate(args.rate)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    topics = list(args.topics) + (list(_INPUT_TOPICS) if args.inputs_only else [])
    from tqdm import tqdm

    try:
        site = args.site or recording_site(args.file)
        with open_bus(BusConfig.from_args(args)) as bus, tqdm(unit="msg", file=sys.stderr, desc="replay") as bar:
            if args.wait_secs > 0 and site is not None:
                # zenoh only delivers to subscribers it already knows: wait for the nodes' liveliness tokens.
                patterns = [keys.pattern(keys.LIVELINESS, site=site, node=n) for n in args.wait_for] or [
                    keys.pattern(keys.LIVELINESS, site=site)
                ]
                try:
                    bus.wait_for_tokens(patterns, args.wait_secs)
                except TimeoutError as exc:
                    raise UserError(
                        f"no live node on site {site} to replay to ({exc}); start the nodes first"
                    ) from None
            count = replay(
                args.file,
                lambda key, payload: bus.publish(key, payload, latched=keys.parse(keys.BIM_MODEL, key) is not None),
                rate,
                topics=topics,
                site=args.site,
                allow_truncated=args.allow_truncated,
                progress=lambda _msg: bar.update(1),
            )
    except RecordingError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:
        raise UserError(f"{args.file}: {exc}") from None
    print(f"replayed {count} messages from {args.file}")
    return 0
