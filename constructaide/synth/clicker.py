"""A simulated site user who clicks anchors on request: for a synthetic-site photo, N pixels on BIM elements with
their 3D model points, read from the site's truth (what a person clicking model corners in the browser would give;
used by ``constructaide demo --answer-anchor-requests`` and the benches, never by the nodes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam

from .truth import load_cameras, load_depth, load_ids


def spread_sample(px: NDArray[np.float64], n: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices of ``n`` of the (M, 2) pixels spread over the image by greedy farthest-point sampling."""
    idx = [int(rng.integers(len(px)))]
    dist = np.linalg.norm(px - px[idx[0]], axis=1)
    for _ in range(min(n, len(px)) - 1):
        k = int(np.argmax(dist))
        idx.append(k)
        dist = np.minimum(dist, np.linalg.norm(px - px[k], axis=1))
    return np.array(idx, dtype=np.int64)


def simulated_clicks(
    site_dir: Path,
    photo_rel: str,
    n_clicks: int = 12,
    noise_px: float = 1.0,
    seed: int = 0,
    cameras: dict[str, dict] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Clicks for one photo (``photo_rel`` relative to ``photos/``): pixels (N, 2) and model points (N, 3) in
    metres. Candidate pixels show a BIM element (truth ID image > 0) away from ID edges (the 5x5 neighbourhood
    shows the same element, so no click lands on a silhouette); N of them are spread over the image; the model
    point is the true depth back-projected through the true camera (lens distortion included); the pixel is the
    true pixel + N(0, noise_px) noise. Raises ValueError when fewer than N pixels are clickable."""
    rec = (cameras or load_cameras(site_dir))[photo_rel]
    K = np.asarray(rec["K"], dtype=np.float64)
    rng = np.random.default_rng(seed + sum(map(ord, photo_rel)))
    depth = load_depth(site_dir, photo_rel).astype(np.float64)
    ids = load_ids(site_dir, photo_rel)
    same = (ids > 0) & (depth > 0)
    for dv in (-2, 2):
        same &= np.roll(ids, dv, axis=0) == ids
    for du in (-2, 2):
        same &= np.roll(ids, du, axis=1) == ids
    same[:3], same[-3:], same[:, :3], same[:, -3:] = False, False, False, False
    vv, uu = np.nonzero(same)
    if len(uu) < n_clicks:
        raise ValueError(f"{photo_rel}: only {len(uu)} clickable BIM pixels")
    sub = rng.choice(len(uu), min(len(uu), 20000), replace=False)
    px_all = np.c_[uu[sub], vv[sub]].astype(np.float64)
    px = px_all[spread_sample(px_all, n_clicks, rng)]
    xy = cam.undistort_normalized((px - K[:2, 2]) / [K[0, 0], K[1, 1]], rec["k1"], rec["k2"])
    z = depth[px[:, 1].astype(int), px[:, 0].astype(int)]
    T = np.asarray(rec["world_from_camera"], dtype=np.float64)
    world = np.c_[xy * z[:, None], z] @ T[:3, :3].T + T[:3, 3]
    return px + rng.normal(0.0, noise_px, px.shape), world
