"""The simulated user's anchor clicks, and whether the anchor solve flags the gross mis-clicks.

For every photo of the synthetic site (sizes and seeds from the command line) and every image of the real sets
(templeSparseRing, fountain-P11, when ``../shared/data`` has them), ``--draws`` user seeds: the realistic user
clicks (synthetic: visible element corners, :class:`constructaide.synth.clicker.SiteClicker`; real sets: strong
image corners that ground truth triangulates, ``bench/_datasets.py:simulate_realistic_clicks``; 12 clicks,
1.5 px noise per axis, about one gross mis-click in 20) and the shipping anchor solve
(``constructaide.anchorsolve.solve_anchor``, focal prior: EXIF on the synthetic site as the register node reads it,
the ground-truth mean focal on the real sets as ``bench/registration.py`` gives it) solves each click set.

Reported: clickable corners per photo, click error of the clicks that are not mis-clicks (distance from the true
projection of the model point), the mis-click rate, the share of mis-clicks the solve flags (by kind: a
neighbouring corner clicked instead, or a slip 10-60 px off), good clicks flagged, and the viewing-angle error of
the solved camera. Each missed mis-click is listed with its offset and the solve's threshold.

Run: ``python bench/anchor_clicks.py [--sizes small] [--seeds 0,7] [--draws 4] [--no-real] [--no-write]``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _datasets import (  # noqa: E402
    FOUNTAIN_DIR,
    TEMPLE_DIR,
    load_fountain,
    load_temple,
    realistic_click_set,
    realistic_click_targets,
)
from _report import table, write_section  # noqa: E402

from constructaide import camera as cam  # noqa: E402
from constructaide.anchorsolve import DegenerateAnchors, solve_anchor  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.clicker import MIN_CLICKS, SiteClicker, TooFewCorners  # noqa: E402
from constructaide.synth.truth import true_camera  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


class Tally:
    """Counts over click sets of one row."""

    def __init__(self) -> None:
        self.photos = self.sets = self.few = self.unclickable = self.degenerate = self.refused_clean = 0
        self.clickable: list[int] = []
        self.err_px: list[float] = []
        self.clicks = self.good_flagged = 0
        self.miss = {"neighbour": [0, 0], "slip": [0, 0]}  # kind -> [mis-clicks, flagged]
        self.angle_deg: list[float] = []
        self.missed: list[str] = []

    def add(
        self,
        name: str,
        px: np.ndarray,
        world: np.ndarray,
        target: np.ndarray,
        mis: np.ndarray,
        kinds: tuple[str, ...] | list[str],
        size: tuple[int, int],
        focal: float | None,
        world_from_camera_gt: np.ndarray,
    ) -> None:
        self.sets += 1
        good = np.ones(len(px), dtype=bool)
        good[mis] = False
        self.clicks += len(px)
        self.err_px += list(np.linalg.norm(px[good] - target[good], axis=1))
        try:
            sol = solve_anchor(px, world, size[0], size[1], focal_px=focal)
        except DegenerateAnchors:  # the solve refuses the set: its mis-clicks are not flagged
            self.degenerate += 1
            self.refused_clean += int(len(mis) == 0)
            for k, kind in zip(mis, kinds, strict=True):
                self.miss[kind][0] += 1
                self.missed.append(
                    f"{name}: {kind} mis-click {np.linalg.norm(px[k] - target[k]):.1f} px off, "
                    f"in a set of {len(px)} with {len(mis)} mis-clicks the solve refused"
                )
            return
        self.angle_deg.append(cam.viewing_angle_deg(sol.world_from_camera, world_from_camera_gt))
        self.good_flagged += int(np.sum(sol.outlier_mask[good]))
        for k, kind in zip(mis, kinds, strict=True):
            self.miss[kind][0] += 1
            hit = bool(sol.outlier_mask[k])
            self.miss[kind][1] += int(hit)
            if not hit:
                off = float(np.linalg.norm(px[k] - target[k]))
                loo = sol.loo_errors_px[k]
                err = (
                    f"leave-one-out error {loo:.1f} px"
                    if np.isfinite(loo)
                    else f"residual {sol.residuals_px[k]:.1f} px under the consensus solve"
                )
                self.missed.append(
                    f"{name}: {kind} mis-click {off:.1f} px off, {err}, threshold {sol.outlier_threshold_px:.1f} px"
                )

    def row(self, label: str) -> list[object]:
        n_miss = sum(v[0] for v in self.miss.values())
        n_flag = sum(v[1] for v in self.miss.values())
        err = np.asarray(self.err_px)

        def rate(kind: str) -> str:
            m, f = self.miss[kind]
            return f"{f}/{m}" if m else "-"

        return [
            label,
            self.photos,
            f"{int(np.median(self.clickable))} ({min(self.clickable)}-{max(self.clickable)})"
            if self.clickable
            else "-",
            f"{self.few}/{self.unclickable}",
            self.sets,
            f"{np.sqrt(np.mean(err**2)):.2f}" if len(err) else "-",
            f"{np.percentile(err, 95):.2f}" if len(err) else "-",
            f"{err.max():.2f}" if len(err) else "-",
            f"{n_miss}/{self.clicks} ({100 * n_miss / max(self.clicks, 1):.1f} %)",
            f"{n_flag}/{n_miss} ({100 * n_flag / max(n_miss, 1):.0f} %)",
            rate("neighbour"),
            rate("slip"),
            f"{self.good_flagged}/{self.clicks - n_miss}",
            f"{np.median(self.angle_deg):.3f}" if self.angle_deg else "-",
            f"{self.degenerate} ({self.refused_clean} without mis-click)",
        ]


def exif_focal_px(path: Path) -> float | None:
    """EXIF FocalLengthIn35mmFilm as pixels (the diagonal crop factor, as the register node reads it)."""
    with Image.open(path) as img:
        f35 = img.getexif().get_ifd(0x8769).get(0xA405)
        w, h = img.size
    return cam.focal_px_from_35mm(float(f35), w, h) if f35 else None


def synth_rows(size: str, seed: int, draws: int) -> tuple[Tally, Tally]:
    """(fixed cameras, phones) over every photo of the site, ``draws`` user seeds each."""
    site = ensure_site(size, seed, Path(os.environ.get("CONSTRUCTAIDE_CACHE", ROOT / ".cache")) / "synth")
    user = SiteClicker(site)
    fixed, phone = Tally(), Tally()
    for rel in sorted(user.cameras):
        t = phone if rel.startswith("phone/") else fixed
        t.photos += 1
        _, wfc = true_camera(site, rel, user.cameras)
        focal = exif_focal_px(site / "photos" / rel)
        for d in range(draws):
            try:
                c = user.clicks(rel, seed=d)
            except TooFewCorners:
                t.unclickable += int(d == 0)
                continue
            if d == 0:
                t.clickable.append(c.n_clickable)
                t.few += int(c.few)
            size_px = (user.cameras[rel]["width"], user.cameras[rel]["height"])
            t.add(
                f"{size}/{seed} {rel} draw {d}",
                c.pixels_px,
                c.points_in_world_m,
                c.target_px,
                c.mis_clicked,
                c.miss_kinds,
                size_px,
                focal,
                wfc,
            )
    return fixed, phone


def real_row(name: str, cams: list, draws: int) -> Tally:
    """Every image of a real set, ``draws`` user seeds each."""
    t = Tally()
    focal = float(np.mean([(c.K[0, 0] + c.K[1, 1]) / 2 for c in cams]))
    for i, c in enumerate(cams):
        t.photos += 1
        targets = realistic_click_targets(cams, i)
        if len(targets[0]) < 4:
            t.unclickable += 1
            continue
        t.clickable.append(len(targets[0]))
        t.few += int(len(targets[0]) < MIN_CLICKS)
        for d in range(draws):
            k = realistic_click_set(cams, i, seed=d, targets=targets)
            t.add(
                f"{name} {c.name} draw {d}",
                k.pixels_px,
                k.points_in_world_m,
                k.target_px,
                k.mis_clicked,
                k.miss_kinds,
                (c.width_px, c.height_px),
                focal,
                c.world_from_camera,
            )
    return t


HEADERS = [
    "photos",
    "clickable corners, median (range)",
    "< 6 / < 4 clickable",
    "click sets",
    "click error rms px",
    "p95 px",
    "max px",
    "gross mis-clicks",
    "flagged by the solve",
    "neighbour flagged",
    "slip flagged",
    "good clicks flagged",
    "view angle err, median deg",
    "sets refused by the solve",
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="small", help="synthetic site sizes, comma-separated")
    ap.add_argument("--seeds", default="0,7", help="synthetic site seeds, comma-separated")
    ap.add_argument("--draws", type=int, default=4, help="user seeds per photo")
    ap.add_argument("--no-real", action="store_true", help="skip templeSparseRing and fountain-P11")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args()
    rows, missed = [], []
    for size in args.sizes.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            fixed, phone = synth_rows(size, seed, args.draws)
            rows += [fixed.row(f"synthetic {size} seed {seed}, fixed cameras"), phone.row(f"... seed {seed}, phones")]
            missed += fixed.missed + phone.missed
            print(rows[-2], rows[-1], sep="\n", flush=True)
    if not args.no_real:
        for name, root, load in (
            ("templeSparseRing", TEMPLE_DIR, load_temple),
            ("fountain-P11", FOUNTAIN_DIR, load_fountain),
        ):
            if not root.exists():
                print(f"{name}: not present at {root}, skipped")
                continue
            t = real_row(name, load(), args.draws)
            rows.append(t.row(f"{name} (model point = ground truth)"))
            missed += t.missed
            print(rows[-1], flush=True)
    body = (
        "The realistic simulated user (`constructaide.synth.clicker`; real sets: "
        "`bench/_datasets.py:simulate_realistic_clicks`): up to 12 clicks on visible corners spread over the image, "
        "1.5 px Gaussian noise per axis, about 1 click in 20 a gross mis-click (a neighbouring corner 10-80 px "
        f"away, or a slip 10-60 px off), {args.draws} user seeds per photo. Each click set is solved by "
        "`constructaide.anchorsolve.solve_anchor` (focal prior: EXIF on the synthetic site, the ground-truth "
        "mean focal on the real sets); 'flagged' = its `outlier_mask`; a set it refuses (`DegenerateAnchors`) "
        "counts its mis-clicks as not flagged. Click error = distance of a click that is "
        "not a mis-click from the true projection of its model point. View angle error of the solved camera "
        "against ground truth, all click sets.\n\n"
        + table(["row", *HEADERS], rows)
        + "\n\nMis-clicks the solve did not flag (a refused set's count as not flagged):\n\n"
        + ("\n".join(f"- {m}" for m in missed) if missed else "- none")
    )
    print(body)
    if not args.no_write:
        write_section("anchor clicks (simulated user)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
