"""Contact sheet of a site: a few frames across time per fixed camera plus a row of phone photos."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from PIL import Image


def make_contact_sheet(site_dir: Path, out_png: Path, columns: int = 5, thumb_w: int = 288) -> Path:
    """Write a PNG grid: one row per fixed camera (frames evenly spread over time), one row of phone photos.

    Thumbnails are labelled with their photo path; the sheet is palette-quantised to stay small.
    """
    photos = Path(site_dir) / "photos"
    rows: list[list[Path]] = []
    for cam in sorted(p for p in photos.iterdir() if p.is_dir() and p.name != "phone"):
        frames = sorted(cam.glob("*.jpg"))
        pick = np.linspace(0, len(frames) - 1, min(columns, len(frames))).round().astype(int)
        rows.append([frames[i] for i in pick])
    phone = sorted((photos / "phone").rglob("*.jpg"))
    if phone:
        pick = np.linspace(0, len(phone) - 1, min(columns, len(phone))).round().astype(int)
        rows.append([phone[i] for i in pick])
    if not rows:
        raise ValueError(f"no photos under {photos}")
    thumb_h = thumb_w * 9 // 16
    sheet = np.full((len(rows) * (thumb_h + 4) + 4, columns * (thumb_w + 4) + 4, 3), 255, np.uint8)
    for r, row in enumerate(rows):
        for c, path in enumerate(row):
            img = cv2.imread(str(path))
            h, w = img.shape[:2]
            scale = max(thumb_w / w, thumb_h / h)
            img = cv2.resize(img, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
            y0, x0 = (img.shape[0] - thumb_h) // 2, (img.shape[1] - thumb_w) // 2
            img = np.ascontiguousarray(img[y0 : y0 + thumb_h, x0 : x0 + thumb_w])
            label = str(path.relative_to(photos))
            cv2.rectangle(img, (0, 0), (thumb_w, 16), (0, 0, 0), -1)
            cv2.putText(img, label, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
            y, x = 4 + r * (thumb_h + 4), 4 + c * (thumb_w + 4)
            sheet[y : y + thumb_h, x : x + thumb_w] = img
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(sheet[..., ::-1]).quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(out_png, optimize=True)
    return out_png


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Contact sheet PNG of a synthetic site.")
    parser.add_argument("site", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    make_contact_sheet(args.site, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
