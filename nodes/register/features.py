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
    """Keypoints (N, 2) float32 px, RootSIFT descriptors (N, 128) float32, scales (N,) px, image size."""

    keypoints_px: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray
    width_px: int
    height_px: int

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
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold)
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


def match_features(a: Features, b: Features, ratio: float = 0.8, chunk_rows: int = 2048) -> np.ndarray:
    """Mutual nearest-neighbour matches passing Lowe's ratio test: (M, 2) int indices (into a, into b).

    Exact brute force by one float32 matrix product per row chunk (descriptors are unit vectors, so
    ``|x - y|^2 = 2 - 2 x.y``); both directions come from the same products.
    """
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), dtype=int)
    da = a.descriptors / np.maximum(np.linalg.norm(a.descriptors, axis=1, keepdims=True), 1e-12)
    db = b.descriptors / np.maximum(np.linalg.norm(b.descriptors, axis=1, keepdims=True), 1e-12)
    da, db = da.astype(np.float32), db.astype(np.float32)
    best_j = np.zeros(len(da), dtype=np.int64)
    s1 = np.zeros(len(da), dtype=np.float32)
    s2 = np.zeros(len(da), dtype=np.float32)
    col_best = np.full(len(db), -np.inf, dtype=np.float32)
    col_arg = np.zeros(len(db), dtype=np.int64)
    cols = np.arange(len(db))
    for r0 in range(0, len(da), chunk_rows):
        S = da[r0 : r0 + chunk_rows] @ db.T
        rows = np.arange(len(S))
        cmax = np.ascontiguousarray(S.T).argmax(1)  # column argmax on a contiguous copy: ~3x faster than axis 0
        cval = S[cmax, cols]
        better = cval > col_best
        col_best[better] = cval[better]
        col_arg[better] = cmax[better] + r0
        j = S.argmax(1)
        best_j[r0 : r0 + len(S)] = j
        s1[r0 : r0 + len(S)] = S[rows, j]
        S[rows, j] = -np.inf
        s2[r0 : r0 + len(S)] = S.max(1)
    d1 = np.sqrt(np.maximum(2 - 2 * s1, 0))
    d2 = np.sqrt(np.maximum(2 - 2 * s2, 0))
    ia = np.arange(len(da))
    good = (d1 < ratio * d2) & (col_arg[best_j] == ia)
    return np.stack([ia[good], best_j[good]], axis=1).astype(int)


def filter_matches_fundamental(
    kp_a: np.ndarray, kp_b: np.ndarray, matches: np.ndarray, threshold_px: float
) -> tuple[np.ndarray | None, np.ndarray]:
    """Fundamental matrix (b^T F a = 0) by RANSAC and the inlier mask (M,) of ``matches``.

    Returns (None, all-False) with fewer than 8 matches or when RANSAC fails.
    """
    mask = np.zeros(len(matches), dtype=bool)
    if len(matches) < 8:
        return None, mask
    pa = np.asarray(kp_a, np.float64)[matches[:, 0]]
    pb = np.asarray(kp_b, np.float64)[matches[:, 1]]
    F, inl = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, threshold_px, 0.999, 10000)
    if F is None or inl is None or F.shape != (3, 3):
        F, inl = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, threshold_px, 0.999, 10000)
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
