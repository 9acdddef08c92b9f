"""Simulated user clicks: visible element corners with 1 px Gaussian pixel noise (evaluation-free input)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from constructaide.camera import invert_rigid, project_points
from schemas.messages import Intrinsics

from .building import Element


def visible_corners(
    elements: list[Element],
    element_index: dict[str, int],
    intr: Intrinsics,
    world_from_camera: NDArray[np.float64],
    ids: NDArray[np.uint16],
    depth_m: NDArray[np.float32],
    margin_px: int = 4,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Corners of ``elements`` that are visible in a photo: (N, 2) exact pixels and (N, 3) world points.

    Visible = inside the image, above the ground, and in a 3x3 window around the pixel the ID image shows the
    element and the rendered depth matches the corner's depth (within 2 % + 5 cm).
    """
    H, W = ids.shape
    cam_from_world = invert_rigid(world_from_camera)
    pix_out, world_out = [], []
    for e in elements:
        pts = np.unique(np.round(e.vertices_m, 6), axis=0)
        px, z = project_points(intr, cam_from_world, pts)
        idx = element_index[e.key]
        for p, zz, w in zip(px, z, pts, strict=True):
            if not np.all(np.isfinite(p)) or zz <= 0:
                continue
            u, v = int(round(p[0])), int(round(p[1]))
            if not (margin_px <= u < W - margin_px and margin_px <= v < H - margin_px):
                continue
            if w[2] < 0.05:  # below the ground surface
                continue
            win_ids = ids[v - 1 : v + 2, u - 1 : u + 2]
            win_d = depth_m[v - 1 : v + 2, u - 1 : u + 2]
            if not np.any(win_ids == idx):
                continue
            if np.min(np.abs(win_d - zz)) > 0.02 * zz + 0.05:
                continue
            pix_out.append(p)
            world_out.append(w)
    return np.asarray(pix_out).reshape(-1, 2), np.asarray(world_out).reshape(-1, 3)


def choose_clicks(
    pixels: NDArray[np.float64], world: NDArray[np.float64], rng: np.random.Generator, noise_px: float = 1.0
) -> list[dict] | None:
    """6-12 well-spread clicks (greedy farthest point in the image) with Gaussian pixel noise, or None when
    fewer than 6 corners are visible."""
    if len(pixels) < 6:
        return None
    n = int(min(rng.integers(6, 13), len(pixels)))
    chosen = [int(rng.integers(0, len(pixels)))]
    d = np.linalg.norm(pixels - pixels[chosen[0]], axis=1)
    while len(chosen) < n:
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(pixels - pixels[k], axis=1))
    out = []
    for k in chosen:
        noisy = pixels[k] + rng.normal(0.0, noise_px, 2)
        out.append(
            {
                "pixel": [round(float(noisy[0]), 2), round(float(noisy[1]), 2)],
                "world": [round(float(c), 4) for c in world[k]],
            }
        )
    return out
