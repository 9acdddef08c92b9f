"""Synthetic site generation time: `tiny` and `small` (and `default` without --quick), median of several runs.

Baseline ratio: wall time relative to the budget of the issue (small < 60 s, default "a few minutes" = 300 s).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _report import median, table, write_section  # noqa: E402

from constructaide.synth import build_site  # noqa: E402

BUDGET_S = {"tiny": 60.0, "small": 60.0, "default": 300.0}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="tiny and small only, one run each")
    args = parser.parse_args()
    plan = [("tiny", 1), ("small", 1)] if args.quick else [("tiny", 3), ("small", 3), ("default", 1)]
    rows = []
    for size, runs in plan:
        times, photos = [], 0
        for _ in range(runs):
            tmp = Path(tempfile.mkdtemp(prefix=f"synth-{size}-"))
            try:
                t0 = time.perf_counter()
                build_site(tmp / "site", seed=0, size=size, progress=False)
                times.append(time.perf_counter() - t0)
                photos = sum(1 for _ in (tmp / "site" / "photos").rglob("*.jpg"))
            finally:
                shutil.rmtree(tmp)
        t = median(times)
        rows.append([size, photos, runs, t, t / photos, BUDGET_S[size], t / BUDGET_S[size]])
        print(f"{size}: {t:.1f} s for {photos} photos", flush=True)
    body = (
        "Wall time of `build_site` (IFC + GLB + textures + rendering + truth + anchors), median of the runs; the "
        "machine is shared with other jobs, so expect noise. Ratio = time / budget from issue 3.\n\n"
        + table(["size", "photos", "runs", "wall s", "s/photo", "budget s", "ratio"], rows)
    )
    print(body)
    write_section("synth", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
