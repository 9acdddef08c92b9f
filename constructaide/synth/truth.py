"""Readers for a site's ``truth/`` folder. For tests, benchmarks and scoring only: system code must not use it."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide.camera import centered_intrinsics
from schemas.messages import Intrinsics


def truth_rel(kind: str, photo_rel: str) -> str:
    """Path of a per-photo truth file relative to ``truth/``: ``ids``/``masks/static``/``masks/dynamic`` are
    ``<kind>/<photo_rel without .jpg>.png``, ``depth`` is ``depth/<photo_rel without .jpg>.npz``."""
    stem = photo_rel[: -len(".jpg")] if photo_rel.endswith(".jpg") else photo_rel
    return f"{kind}/{stem}.npz" if kind == "depth" else f"{kind}/{stem}.png"


def load_cameras(site_dir: Path) -> dict[str, dict]:
    """``truth/cameras.json``: photo path (relative to photos/) -> camera record."""
    return json.loads((Path(site_dir) / "truth" / "cameras.json").read_text())


def true_camera(
    site_dir: Path, photo_rel: str, cameras: dict[str, dict] | None = None
) -> tuple[Intrinsics, NDArray[np.float64]]:
    """(Intrinsics, world_from_camera (4, 4)) of a photo."""
    rec = (cameras or load_cameras(site_dir))[photo_rel]
    K = np.asarray(rec["K"])
    intr = centered_intrinsics(rec["width"], rec["height"], K[0, 0], rec["k1"], rec["k2"])
    return intr, np.asarray(rec["world_from_camera"], dtype=np.float64)


def load_ids(site_dir: Path, photo_rel: str) -> NDArray[np.uint16]:
    """(H, W) uint16 element index image (0 = no element; see ``element_index``)."""
    img = cv2.imread(str(Path(site_dir) / "truth" / truth_rel("ids", photo_rel)), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"no ID image for {photo_rel}")
    return img


def load_depth(site_dir: Path, photo_rel: str) -> NDArray[np.float32]:
    """(H, W) float32 z-depth in metres (0 = sky)."""
    with np.load(Path(site_dir) / "truth" / truth_rel("depth", photo_rel)) as z:
        return z["depth_m"]


def load_mask(site_dir: Path, photo_rel: str, kind: str) -> NDArray[np.bool_]:
    """(H, W) bool occluder mask; ``kind`` is "static" or "dynamic"."""
    img = cv2.imread(str(Path(site_dir) / "truth" / truth_rel(f"masks/{kind}", photo_rel)), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"no {kind} mask for {photo_rel}")
    return img > 127


def element_index(site_dir: Path) -> dict[int, str]:
    """Index in the ID images -> element GlobalId (index 0, the background, is omitted)."""
    raw = json.loads((Path(site_dir) / "truth" / "element_index.json").read_text())
    return {int(k): v for k, v in raw.items() if v is not None}


def element_states(site_dir: Path) -> dict:
    """``truth/element_states.json``: {"elements": {GlobalId: {...}}, "photos": {photo_rel: [GlobalId, ...]}}."""
    return json.loads((Path(site_dir) / "truth" / "element_states.json").read_text())
