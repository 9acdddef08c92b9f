"""Documentation images of what the system itself produced: photos, overlays and occlusion masks from a recording.

Unlike ``render_docs.py`` (true cameras), everything here comes out of a `constructaide demo` run: the register
node's poses, the occlude node's masks and the render node's overlays, as recorded in the MCAP file. For each
chosen photo it writes ``<out>/pipeline_<n>.png``: the photo, the state4d and progress overlays composited over
it, and the combined occlusion mask tinted red.

    python bench/docs_from_recording.py recordings/demo-<time>.mcap [--photos 2] [--out docs]

Photos are chosen among those with a registration, overlays of both modes and a combined mask: the latest
fixed-camera frame that is not its camera's newest (whose dynamic mask is still provisional) and the latest phone
photo (registered automatically when one is, else from an anchor).
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from constructaide.imagecodec import decode_bgr, decode_mask, decode_unchanged  # noqa: E402
from constructaide.recording import decoded_messages  # noqa: E402
from schemas.messages import OcclusionMask, Overlay, Photo, Registration  # noqa: E402

MODES = ("state4d", "progress")


def over(photo_bgr: np.ndarray, layer: np.ndarray) -> np.ndarray:
    """Alpha-composite an overlay (BGRA layer, or an already composited BGR image) over the photo (H, W, 3)."""
    if layer.ndim == 3 and layer.shape[2] == 4:
        a = layer[..., 3:4].astype(np.float32) / 255.0
        return (layer[..., :3] * a + photo_bgr * (1.0 - a)).astype(np.uint8)
    return layer[..., :3]


def tint(photo_bgr: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Photo with occluded pixels (mask > 0) tinted red at 55 %."""
    out = photo_bgr.astype(np.float32)
    m = mask > 0
    out[m] = out[m] * 0.45 + np.array([0, 0, 255], np.float32) * 0.55
    return out.astype(np.uint8)


def collect(path: Path) -> tuple[dict, dict, dict, dict]:
    """Latest Photo, Registration, Overlay per mode and combined OcclusionMask per photo id."""
    photos: dict[str, Photo] = {}
    regs: dict[str, Registration] = {}
    overlays: dict[str, dict[str, Overlay]] = defaultdict(dict)
    masks: dict[str, OcclusionMask] = {}
    for _key, msg in decoded_messages(path, (Photo, Registration, Overlay, OcclusionMask), allow_truncated=True):
        if isinstance(msg, Photo):
            photos[msg.photo_id] = msg
        elif isinstance(msg, Registration):
            regs[msg.photo_id] = msg
        elif isinstance(msg, Overlay) and msg.mode in MODES:
            overlays[msg.photo_id][msg.mode] = msg
        elif isinstance(msg, OcclusionMask) and msg.kind == "combined" and msg.status == "ok":
            masks[msg.photo_id] = msg
    return photos, regs, overlays, masks


def choose(photos: dict, regs: dict, overlays: dict, masks: dict, n: int) -> list[str]:
    """Up to ``n`` photo ids: the latest complete fixed-camera frame, then the latest complete phone photo."""
    complete = [
        pid
        for pid, p in photos.items()
        if pid in regs and regs[pid].status != "failed" and all(m in overlays[pid] for m in MODES) and pid in masks
    ]
    complete.sort(key=lambda pid: photos[pid].capture_time_ns, reverse=True)
    # A camera's newest frame has provisional dynamic masks (no later neighbour yet: fresh construction and a
    # parked truck look alike); the node refines them when the next frame arrives, so show a refined frame.
    newest: dict[str, int] = {}
    for p in photos.values():
        if p.camera_id:
            newest[p.camera_id] = max(newest.get(p.camera_id, 0), p.capture_time_ns)
    fixed = [
        pid for pid in complete if photos[pid].camera_id and photos[pid].capture_time_ns < newest[photos[pid].camera_id]
    ]
    phone = [pid for pid in complete if not photos[pid].camera_id]
    phone.sort(key=lambda pid: regs[pid].status != "auto")  # automatic registrations first (stable sort)
    picked = fixed[:1] + phone[:1]
    picked += [pid for pid in complete if pid not in picked]
    return picked[:n]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--photos", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--width", type=int, default=960, help="width of each panel in px")
    args = ap.parse_args(argv)
    photos, regs, overlays, masks = collect(args.recording)
    picked = choose(photos, regs, overlays, masks, args.photos)
    if not picked:
        print("no photo has a registration, both overlays and a combined mask in this recording", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    for i, pid in enumerate(picked, 1):
        p, r = photos[pid], regs[pid]
        img = decode_bgr(p.data, f"photo {pid}")
        panels = [img] + [over(img, decode_unchanged(overlays[pid][m].image_png, "overlay")) for m in MODES]
        panels.append(tint(img, decode_mask(masks[pid].mask_png)))
        h = round(img.shape[0] * args.width / img.shape[1])
        panels = [cv2.resize(x, (args.width, h), interpolation=cv2.INTER_AREA) for x in panels]
        sheet = np.vstack([np.hstack(panels[:2]), np.hstack(panels[2:])])
        out = args.out / f"pipeline_{i}.png"
        cv2.imwrite(str(out), sheet)
        who = p.camera_id or "phone"
        print(
            f"{out}: {p.filename or pid} ({who}), registration {r.status} ({r.method}), "
            f"{r.num_inliers} inliers, RMS {r.reprojection_rms_px:.2f} px"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
