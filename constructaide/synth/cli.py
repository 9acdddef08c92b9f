"""``constructaide synth --out DIR [--seed N] [--size tiny|small|default|large]``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .config import SIZES
from .site import build_site


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="constructaide synth", description="Render a synthetic construction site with ground truth."
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder (must not exist or be empty)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed -> identical site)")
    parser.add_argument("--size", choices=list(SIZES), default="default", help="site size")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    out = build_site(args.out, seed=args.seed, size=args.size, progress=not args.quiet)
    n = sum(1 for _ in (out / "photos").rglob("*.jpg"))
    print(f"wrote {out} ({n} photos, size={args.size}, seed={args.seed})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
