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


class Vocabulary:
    """Bag of visual words over (RootSIFT, unit) descriptors: k-means centres (k, 128) and inverse document
    frequencies (k,); :meth:`histogram` gives an image's unit tf-idf vector for cosine-similarity retrieval."""

    def __init__(self, centres: np.ndarray, idf: np.ndarray | None = None) -> None:
        c = np.asarray(centres, np.float32)
        self.centres = c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
        self.idf = np.ones(len(c)) if idf is None else np.asarray(idf, np.float64)

    @classmethod
    def build(
        cls, descriptor_sets: list[np.ndarray], max_words: int = 1024, per_image: int = 300, seed: int = 0
    ) -> Vocabulary | None:
        """Vocabulary of at most ``max_words`` words (a quarter of the sampled descriptors at most) from up to
        ``per_image`` descriptors of each set, with idf over the sets; None when there are too few descriptors."""
        rng = np.random.default_rng(seed)
        sample = [d[rng.choice(len(d), min(len(d), per_image), replace=False)] for d in descriptor_sets if len(d)]
        if not sample:
            return None
        data = np.vstack(sample).astype(np.float32)
        k = int(min(max_words, len(data) // 4))
        if k < 8:
            return None
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-3)
        cv2.setRNGSeed(seed)
        _, _, centres = cv2.kmeans(data, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
        voc = cls(centres)
        df = np.zeros(k)
        for d in descriptor_sets:
            df[np.unique(voc.words(d))] += 1
        voc.idf = np.log(len(descriptor_sets) / np.maximum(df, 1))
        return voc

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Nearest word (N,) of each descriptor (N, 128) by dot product (unit vectors)."""
        d = np.asarray(descriptors, np.float32)
        out = np.zeros(len(d), np.int64)
        for s0 in range(0, len(d), 4096):
            out[s0 : s0 + 4096] = np.argmax(d[s0 : s0 + 4096] @ self.centres.T, axis=1)
        return out

    def histogram(self, descriptors: np.ndarray) -> np.ndarray:
        """Unit tf-idf vector (k,) of an image's descriptors (zeros without any)."""
        h = np.bincount(self.words(descriptors), minlength=len(self.centres)).astype(np.float64) * self.idf
        return h / max(float(np.linalg.norm(h)), 1e-12)


def select_pairs(features: list[Features], cfg: MapperConfig, seed: int = 0) -> list[tuple[int, int]]:
    """All pairs for small sets; for more than ``max_exhaustive_images`` a bag-of-words shortlist (each image with
    its ``shortlist_size`` most similar images by tf-idf cosine over a k-means vocabulary of RootSIFT)."""
    n = len(features)
    if n <= cfg.max_exhaustive_images:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    voc = Vocabulary.build([f.descriptors for f in features], seed=seed)
    if voc is None:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    h = np.stack([voc.histogram(f.descriptors) for f in features])
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
