"""SIFT features, matching and two-view geometric filtering (OpenCV).

Keypoints are in full-resolution pixels, OpenCV convention ((0, 0) = centre of the top-left pixel), even when
detection ran on a downscaled image. Descriptors are RootSIFT (L1-normalised, square-rooted SIFT), float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Features:
    """Keypoints (N, 2) float32 px, RootSIFT descriptors (N, 128) float32, scales (N,) px, image size; optionally
    the descriptors projected on a collection's principal components (N, K) float32 (see :func:`project_pca`),
    which :func:`match_features` then uses to shortlist candidates."""

    keypoints_px: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray
    width_px: int
    height_px: int
    descriptors_pca: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.keypoints_px)


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Grey uint8 image from grey/BGR/BGRA uint8 input."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {img.dtype}")
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"unsupported image shape {img.shape}")


def extract_features(
    image_gray_u8: np.ndarray,
    max_features: int = 8000,
    max_side_px: int | None = None,
    contrast_threshold: float = 0.01,
) -> Features:
    """SIFT keypoints and RootSIFT descriptors of a grey uint8 image (H, W).

    With ``max_side_px`` the image is downscaled (INTER_AREA) so its longer side is at most that; keypoints and
    scales are returned in full-resolution pixels. ``contrast_threshold`` is SIFT's (OpenCV default 0.04); the
    lower default finds features on weakly textured surfaces (plaster, concrete); ``max_features`` keeps the
    strongest.
    """
    gray = to_gray_u8(image_gray_u8)
    h, w = gray.shape
    scale = 1.0
    work = gray
    if max_side_px is not None and max(h, w) > max_side_px:
        scale = max_side_px / max(h, w)
        work = cv2.resize(gray, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT_create(  # type: ignore[attr-defined]
        nfeatures=max_features, contrastThreshold=contrast_threshold
    )
    kps, desc = sift.detectAndCompute(work, None)
    if desc is None or len(kps) == 0:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32), w, h)
    pts = np.array([k.pt for k in kps], dtype=np.float64)
    sizes = np.array([k.size for k in kps], dtype=np.float64)
    if scale != 1.0:
        sx, sy = work.shape[1] / w, work.shape[0] / h
        pts = (pts + 0.5) / np.array([sx, sy]) - 0.5
        sizes = sizes / scale
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)
    desc = np.sqrt(desc)
    return Features(pts.astype(np.float32), desc, sizes.astype(np.float32), w, h)


def _top_two(
    A: np.ndarray, BT: np.ndarray, chunk_rows: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row of ``A @ BT`` (one float32 product per chunk of ``chunk_rows`` rows): the best column and its
    value, the second-best column and its value, and every column's maximum: ``(j1, s1, j2, s2, col_best)``."""
    n = len(A)
    j1 = np.empty(n, dtype=np.int64)
    j2 = np.empty(n, dtype=np.int64)
    s1 = np.empty(n, dtype=np.float32)
    s2 = np.empty(n, dtype=np.float32)
    col_best = np.full(BT.shape[1], -np.inf, dtype=np.float32)
    for r0 in range(0, n, chunk_rows):
        S = A[r0 : r0 + chunk_rows] @ BT
        np.maximum(col_best, S.max(0), out=col_best)
        rows = np.arange(len(S))
        j = S.argmax(1)
        j1[r0 : r0 + len(S)] = j
        s1[r0 : r0 + len(S)] = S[rows, j]
        S[rows, j] = -np.inf
        k = S.argmax(1)
        j2[r0 : r0 + len(S)] = k
        s2[r0 : r0 + len(S)] = S[rows, k]
    return j1, s1, j2, s2, col_best


def match_features(a: Features, b: Features, ratio: float = 0.8, chunk_rows: int = 2048) -> np.ndarray:
    """Mutual nearest-neighbour matches passing Lowe's ratio test: (M, 2) int indices (into a, into b).

    Exact brute force by one float32 matrix product per row chunk (descriptors are unit vectors, so
    ``|x - y|^2 = 2 - 2 x.y``). Per row the best and second-best similarity come from the product; the mutual
    check compares a row's best with its column's maximum (a contiguous reduction, no column argmax).
    """
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), dtype=int)
    if a.descriptors_pca is not None and b.descriptors_pca is not None:
        return _match_pca(a, b, ratio, chunk_rows)
    best_j, s1, _, s2, col_best = _top_two(_unit_rows(a.descriptors), _unit_rows(b.descriptors).T, chunk_rows)
    # Ratio test on distances, squared: d1 < r d2  <=>  2 - 2 s1 < r^2 (2 - 2 s2).
    d1_sq = np.maximum(2 - 2 * s1, 0)
    d2_sq = np.maximum(2 - 2 * s2, 0)
    good = (d1_sq < ratio * ratio * d2_sq) & (s1 >= col_best[best_j])
    ia = np.nonzero(good)[0]
    return np.stack([ia, best_j[ia]], axis=1).astype(int)


def _match_pca(a: Features, b: Features, ratio: float, chunk_rows: int) -> np.ndarray:
    """As :func:`match_features`, with the best and second-best candidates of each row (and the column maxima
    of the mutual check) from the products of the projected descriptors, then the ratio test on the exact
    similarities of those two candidates."""
    pa = np.ascontiguousarray(a.descriptors_pca, dtype=np.float32)
    pbT = np.ascontiguousarray(b.descriptors_pca, dtype=np.float32).T
    j1, s1, j2, _, col_best = _top_two(pa, pbT, chunk_rows)
    da = _unit_rows(a.descriptors)
    db = _unit_rows(b.descriptors)
    e1 = np.einsum("ij,ij->i", da, db[j1])
    e2 = np.einsum("ij,ij->i", da, db[j2])
    d1_sq = np.maximum(2 - 2 * e1, 0)
    d2_sq = np.maximum(2 - 2 * np.minimum(e2, e1), 0)
    good = (d1_sq < ratio * ratio * d2_sq) & (s1 >= col_best[j1]) & (e2 <= e1)
    ia = np.nonzero(good)[0]
    return np.stack([ia, j1[ia]], axis=1).astype(int)


def pca_basis(descriptor_sets: list[np.ndarray], dims: int = 64, sample: int = 20000, seed: int = 0) -> np.ndarray:
    """Principal directions (128, dims) float32 of a collection's descriptors (uncentred: dot products of unit
    descriptors are what matching compares), from a random sample of at most ``sample`` rows."""
    rng = np.random.default_rng(seed)
    allx = np.vstack([d for d in descriptor_sets if len(d)]).astype(np.float32)
    if len(allx) > sample:
        allx = allx[rng.choice(len(allx), sample, replace=False)]
    # Right singular vectors of the sample = eigenvectors of its (128, 128) Gram matrix (~20x faster than an SVD).
    gram = allx.T.astype(np.float64) @ allx.astype(np.float64)
    vals, vecs = np.linalg.eigh(gram)
    order = np.argsort(vals)[::-1][:dims]
    return np.ascontiguousarray(vecs[:, order].astype(np.float32))


def project_pca(f: Features, basis: np.ndarray) -> Features:
    """``f`` with ``descriptors_pca`` = descriptors (N, 128) @ basis (128, K)."""
    proj = (_unit_rows(f.descriptors) @ basis).astype(np.float32)
    return Features(f.keypoints_px, f.descriptors, f.scales, f.width_px, f.height_px, proj)


def _unit_rows(desc: np.ndarray) -> np.ndarray:
    """float32 C-contiguous rows scaled to unit L2 norm (RootSIFT already is; then no copy beyond the cast)."""
    d = np.ascontiguousarray(desc, dtype=np.float32)
    if len(d) == 0:
        return d
    sq = np.einsum("ij,ij->i", d, d)
    if np.all(np.abs(sq - 1) < 1e-4):
        return d
    return d / np.maximum(np.sqrt(sq), 1e-12)[:, None]


def ransac_iterations(num_matches: int, min_inliers: int, sample_size: int = 7, confidence: float = 0.999) -> int:
    """RANSAC iterations needed to draw, with ``confidence``, one all-inlier sample from ``num_matches``
    matches of which ``min_inliers`` are inliers (the fewest that would be accepted); at least 50."""
    if num_matches <= 0 or min_inliers >= num_matches:
        return 50
    w = max(min_inliers, sample_size) / num_matches
    p = w**sample_size
    if p <= 0:
        return 1_000_000
    return max(50, int(np.ceil(np.log(1 - confidence) / np.log1p(-p))))


def filter_matches_fundamental(
    kp_a: np.ndarray, kp_b: np.ndarray, matches: np.ndarray, threshold_px: float, max_iters: int = 10000
) -> tuple[np.ndarray | None, np.ndarray]:
    """Fundamental matrix (b^T F a = 0) by RANSAC and the inlier mask (M,) of ``matches``.

    ``max_iters`` caps the RANSAC iterations (see :func:`ransac_iterations` for a bound that still finds a
    model with a given number of inliers). Returns (None, all-False) with fewer than 8 matches or when RANSAC
    fails.
    """
    mask = np.zeros(len(matches), dtype=bool)
    if len(matches) < 8:
        return None, mask
    pa = np.asarray(kp_a, np.float64)[matches[:, 0]]
    pb = np.asarray(kp_b, np.float64)[matches[:, 1]]
    F, inl = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, threshold_px, 0.999, int(max_iters))
    if F is None or inl is None or F.shape != (3, 3):
        F, inl = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, threshold_px, 0.999, int(max_iters))
    if F is None or inl is None or F.shape != (3, 3):
        return None, mask
    return F, inl.ravel().astype(bool)


def homography_inlier_ratio(
    kp_a: np.ndarray, kp_b: np.ndarray, matches: np.ndarray, threshold_px: float
) -> tuple[np.ndarray | None, float]:
    """Homography H (pixels of a -> pixels of b) by RANSAC and the fraction of ``matches`` it explains."""
    if len(matches) < 8:
        return None, 0.0
    pa = np.asarray(kp_a, np.float64)[matches[:, 0]]
    pb = np.asarray(kp_b, np.float64)[matches[:, 1]]
    H, inl = cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, threshold_px, maxIters=10000, confidence=0.999)
    if H is None or inl is None:
        H, inl = cv2.findHomography(pa, pb, cv2.RANSAC, threshold_px, maxIters=5000, confidence=0.999)
    if H is None or inl is None:
        return None, 0.0
    return H, float(inl.ravel().astype(bool).mean())
