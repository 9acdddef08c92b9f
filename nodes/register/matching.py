"""Pair verification (ratio-test matches pruned by a RANSAC fundamental matrix) and pair selection."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from nodes.register.config import MapperConfig
from nodes.register.features import (
    Features,
    filter_matches_fundamental,
    match_features,
    ransac_iterations,
)
from nodes.register.recon import PairGeometry, Reconstruction


def _largest_scales(f: Features, n: int) -> Features:
    keep = np.argsort(-f.scales)[:n]
    pca = None if f.descriptors_pca is None else f.descriptors_pca[keep]
    return Features(f.keypoints_px[keep], f.descriptors[keep], f.scales[keep], f.width_px, f.height_px, pca)


def verify_pair(a: Features, b: Features, cfg: MapperConfig) -> PairGeometry | None:
    """Ratio-test matches pruned by a RANSAC fundamental matrix; None with fewer than ``min_pair_inliers``.

    Preemptive matching (as in VisualSFM): the ``preemptive_features`` largest-scale features are matched first
    and the pair is skipped when fewer than ``preemptive_min_matches`` of them match.
    """
    n_pre = cfg.preemptive_features
    if n_pre and len(a) > 2 * n_pre and len(b) > 2 * n_pre:
        pre = match_features(_largest_scales(a, n_pre), _largest_scales(b, n_pre), cfg.ratio)
        if len(pre) < cfg.preemptive_min_matches:
            return None
    m = match_features(a, b, cfg.ratio)
    if len(m) < cfg.min_pair_inliers:
        return None
    thr = max(1.0, cfg.fundamental_threshold_frac * max(a.width_px, b.width_px))
    # No more iterations than needed to find a model with the fewest inliers a pair may have (most pairs of
    # a collection do not overlap and have a few dozen chance matches: they cost ~100 iterations, not 10000).
    iters = min(10000, ransac_iterations(len(m), cfg.min_pair_inliers))
    F, inl = filter_matches_fundamental(a.keypoints_px, b.keypoints_px, m, thr, max_iters=iters)
    if F is None or inl.sum() < cfg.min_pair_inliers:
        return None
    return PairGeometry(m[inl], F, len(m))


def select_pairs(features: list[Features], cfg: MapperConfig, seed: int = 0) -> list[tuple[int, int]]:
    """All pairs for small sets; for more than ``max_exhaustive_images`` a bag-of-words shortlist (each image with
    its ``shortlist_size`` most similar images by tf-idf cosine over a k-means vocabulary of RootSIFT)."""
    n = len(features)
    if n <= cfg.max_exhaustive_images:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    rng = np.random.default_rng(seed)
    sample = []
    for f in features:
        if len(f):
            sample.append(f.descriptors[rng.choice(len(f), min(len(f), 300), replace=False)])
    data = np.vstack(sample).astype(np.float32)
    k = int(min(1024, max(16, len(data) // 4)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-3)
    cv2.setRNGSeed(seed)
    _, _, centers = cv2.kmeans(data, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    hist = np.zeros((n, k))
    for i, f in enumerate(features):
        if len(f):
            words = np.array([m.trainIdx for m in matcher.match(f.descriptors, centers)])
            hist[i] = np.bincount(words, minlength=k)
    idf = np.log(n / np.maximum((hist > 0).sum(0), 1))
    h = hist * idf
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    sim = h @ h.T
    np.fill_diagonal(sim, -np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(-sim[i])[: cfg.shortlist_size]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def match_image(
    recon: Reconstruction, idx: int, others: list[int], cfg: MapperConfig, progress: Callable[[], None] | None = None
) -> int:
    """Verify pairs between image ``idx`` and ``others``; stores them; returns how many pairs were kept."""
    kept = 0
    for o in others:
        if o == idx:
            continue
        i, j = min(idx, o), max(idx, o)
        if (i, j) in recon.pairs:
            kept += 1
            continue
        g = verify_pair(recon.images[i].features, recon.images[j].features, cfg)
        if g is not None:
            recon.pairs[(i, j)] = g
            kept += 1
        if progress is not None:
            progress()
    return kept
