"""Greedy farthest-point sampling (pure numpy)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def farthest_point_order(
    points: ArrayLike, first: list[int], n: int | None = None, also_from: ArrayLike | None = None
) -> NDArray[np.int64]:
    """Indices of ``n`` (default all) of the (M, D) ``points``: ``first`` as given, then each next one the point
    farthest (Euclidean) from those already picked and from the (K, D) ``also_from`` points; no index twice, ties
    to the lowest index."""
    pts = np.asarray(points, np.float64)
    pts = pts.reshape(len(pts), -1)
    count = len(pts) if n is None else min(n, len(pts))
    picked = [int(i) for i in first][:count]
    dist = np.full(len(pts), np.inf)
    refs = [pts[i] for i in picked]
    if also_from is not None:
        refs += list(np.asarray(also_from, np.float64).reshape(-1, pts.shape[1]))
    for r in refs:
        dist = np.minimum(dist, np.linalg.norm(pts - r, axis=1))
    dist[picked] = -np.inf
    while len(picked) < count:
        k = int(np.argmax(dist))
        picked.append(k)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
        dist[picked] = -np.inf
    return np.array(picked, dtype=np.int64)
