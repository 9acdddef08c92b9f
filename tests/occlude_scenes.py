"""Seeded synthetic scenes for the occlude tests (not collected: no test_ prefix).

* :func:`dynamic_sequence`: a textured static scene seen by a fixed camera with small jitter and
  global lighting changes, and a coloured "vehicle" that moves between frames (truth masks).
* :func:`static_scene`: a facade (model: wall + basement below ground), a fence in front of it and
  the ground, seen by a registered camera; sparse points sampled on the visible surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from constructaide.camera import centered_intrinsics, look_at
from constructaide.modelview import ModelView
from schemas.messages import Intrinsics


def textured_background(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """uint8 BGR (h, w, 3) smooth multi-scale colour texture."""
    img = np.zeros((h, w, 3), np.float32)
    for cell, amp in ((64, 90.0), (16, 50.0), (4, 25.0)):
        noise = rng.uniform(-1, 1, (max(2, h // cell), max(2, w // cell), 3)).astype(np.float32)
        img += amp * cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(img + 128.0, 0, 255).astype(np.uint8)


@dataclass
class DynamicFrame:
    image: np.ndarray  # uint8 BGR (h, w, 3)
    truth: np.ndarray  # uint8 (h, w) 0/255 true dynamic occluder
    shift_px: tuple[float, float]  # jitter of this frame (dx, dy)


def dynamic_sequence(
    seed: int, n: int, h: int = 270, w: int = 480, gains: tuple[float, ...] | None = None, jitter_px: float = 2.0
) -> list[DynamicFrame]:
    """``n`` frames of a fixed camera; the box moves along the image; lighting gain per frame."""
    rng = np.random.default_rng(seed)
    scene = textured_background(rng, h + 40, w + 40)
    frames = []
    for i in range(n):
        gain = gains[i] if gains is not None else float(rng.uniform(0.7, 1.3))
        dx, dy = (rng.uniform(-jitter_px, jitter_px, 2) if i else np.zeros(2)).tolist()
        M = np.float32([[1, 0, dx - 20], [0, 1, dy - 20]])
        img = cv2.warpAffine(scene, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.float32)
        truth = np.zeros((h, w), np.uint8)
        bw, bh = w // 6, h // 4
        slot = (list(range(0, n, 2)) + list(range(1, n, 2)))[i]  # consecutive frames far apart
        x0 = int((w - bw) * (slot + 0.5) / n)
        y0 = int(h * 0.55)
        cv2.rectangle(truth, (x0, y0), (x0 + bw - 1, y0 + bh - 1), 255, -1)
        cv2.circle(truth, (x0 + bw // 2, y0), bh // 3, 255, -1)
        color = np.array([30, 60, 200], np.float32) + rng.normal(0, 5, (h, w, 3)).astype(np.float32)
        img = np.where(truth[..., None] > 0, color, img)
        img = img * gain + rng.normal(0, 2.0, img.shape)
        frames.append(DynamicFrame(np.clip(img, 0, 255).astype(np.uint8), truth, (dx, dy)))
    return frames


@dataclass
class StaticScene:
    image: np.ndarray  # uint8 BGR (h, w, 3)
    intrinsics: Intrinsics
    world_from_camera: np.ndarray  # (4, 4)
    model_meshes: dict[str, tuple[np.ndarray, np.ndarray]]
    points_m: np.ndarray  # (N, 3) sparse points on visible surfaces
    pixels_px: np.ndarray  # (N, 2) their observations
    truth: np.ndarray  # uint8 (h, w) 0/255: something in front of the model
    terrain_height_m: float = 0.0


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    return np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32)


def static_scene(seed: int, w: int = 960, h: int = 540, num_points: int = 3000, k1: float = 0.0) -> StaticScene:
    """Facade (y = 0, basement to z = -3) behind a fence (y = -5) on ground z = 0."""
    rng = np.random.default_rng(seed)
    intr = centered_intrinsics(w, h, 0.9 * w, k1=k1)
    wfc = look_at((1.5, -22.0, 3.0), (0.0, 0.0, 1.0))
    model = {"wall": _box((16.0, 0.4, 9.0), (0.0, 0.2, 1.5)), "column": _box((0.6, 0.6, 6.0), (5.0, -1.0, 3.0))}
    fence = {"fence": _box((7.0, 0.1, 2.2), (-2.0, -5.0, 1.1))}
    ground = {"ground": _box((60.0, 60.0, 0.2), (0.0, 0.0, -0.1))}
    depths = []
    for meshes in (model, fence, ground):
        r = ModelView(meshes)
        depths.append(r.maps(intr, wfc, w, h))
        r.close()
    d = np.stack([m.depth_m for m in depths])
    label = np.argmin(d, axis=0)
    label[~np.isfinite(d.min(axis=0))] = 3  # sky
    colours = np.array([[150, 150, 160], [40, 90, 140], [60, 140, 90], [230, 200, 170]], np.float32)
    img = colours[label] + textured_background(rng, h, w).astype(np.float32) * 0.25 - 32.0
    img = np.clip(img + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)
    truth = ((label == 1) | (label == 2)) & np.isfinite(d[0])
    # sparse points: random pixels of visible surfaces, their true 3D point plus 1 cm noise
    vis = np.flatnonzero(label.ravel() < 3)
    pick = rng.choice(vis, size=min(num_points, len(vis)), replace=False)
    vi, ui = np.unravel_index(pick, (h, w))
    pts = np.stack(
        [depths[lab].point_in_world_m[v, u] for lab, v, u in zip(label[vi, ui], vi, ui, strict=True)]
    ).astype(np.float64)
    pts += rng.normal(0, 0.01, pts.shape)
    return StaticScene(
        img,
        intr,
        wfc,
        model,
        pts,
        np.stack([ui, vi], axis=1).astype(np.float64),
        (truth * 255).astype(np.uint8),
    )


def iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a > 0, b > 0
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union
