"""SIFT extraction, matching, fundamental / homography filtering on small synthetic images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from nodes.register.features import (
    Features,
    extract_features,
    filter_matches_fundamental,
    homography_inlier_ratio,
    match_features,
)


def texture(seed: int = 0, w: int = 640, h: int = 480) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 255, (h // 8, w // 8), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(60):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        cv2.circle(img, c, int(rng.integers(4, 30)), int(rng.integers(0, 255)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


H_TRUE = np.array([[0.95, 0.08, 20.0], [-0.05, 1.02, 12.0], [1e-5, 2e-5, 1.0]])


def test_extract_returns_rootsift_in_full_resolution():
    img = texture()
    full = extract_features(img)
    half = extract_features(img, max_side_px=320)
    assert len(full) > 300 and len(half) > 100
    assert full.descriptors.shape == (len(full), 128) and full.descriptors.dtype == np.float32
    assert np.allclose(np.linalg.norm(full.descriptors, axis=1), 1.0, atol=1e-4)
    assert (half.width_px, half.height_px) == (640, 480)
    # Keypoints found at half resolution land on full-resolution keypoints of the same image.
    m = match_features(half, full)
    d = np.linalg.norm(half.keypoints_px[m[:, 0]] - full.keypoints_px[m[:, 1]], axis=1)
    assert len(m) > 50
    assert np.median(d) < 1.0
    assert half.scales.max() > 4.0  # scales in full-resolution pixels


def test_match_and_homography_of_a_warped_image():
    img = texture(1)
    warped = cv2.warpPerspective(img, H_TRUE, (640, 480))
    a, b = extract_features(img), extract_features(warped)
    m = match_features(a, b, ratio=0.8)
    assert len(m) > 150
    assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)  # mutual
    H, ratio = homography_inlier_ratio(a.keypoints_px, b.keypoints_px, m, 2.0)
    assert ratio > 0.8
    corners = np.array([[0, 0], [639, 0], [639, 479], [0, 479]], np.float64).reshape(-1, 1, 2)
    err = cv2.perspectiveTransform(corners, H) - cv2.perspectiveTransform(corners, H_TRUE)
    assert np.abs(err).max() < 2.0


def test_fundamental_filter_drops_injected_outliers():
    rng = np.random.default_rng(2)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (300, 3))
    K = np.array([[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1.0]])
    R = cv2.Rodrigues(np.array([0.0, 0.15, 0.0]))[0]
    pa = X @ K.T
    pa = pa[:, :2] / pa[:, 2:]
    pb = (X @ R.T + [-0.8, 0, 0]) @ K.T
    pb = pb[:, :2] / pb[:, 2:]
    pb[:60] = rng.uniform([0, 0], [640, 480], (60, 2))  # 20 % wrong matches
    matches = np.c_[np.arange(300), np.arange(300)]
    F, inl = filter_matches_fundamental(pa.astype(np.float32), pb.astype(np.float32), matches, 1.0)
    assert F is not None
    assert inl[60:].mean() > 0.97
    assert inl[:60].mean() < 0.15
    assert filter_matches_fundamental(pa, pb, matches[:5], 1.0)[0] is None


def test_homography_ratio_low_for_a_3d_scene():
    rng = np.random.default_rng(3)
    X = rng.uniform([-3, -3, 3], [3, 3, 12], (400, 3))
    K = np.array([[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1.0]])
    pa = X @ K.T
    pb = (X + [1.5, 0, 0]) @ K.T
    m = np.c_[np.arange(400), np.arange(400)]
    _, ratio = homography_inlier_ratio(pa[:, :2] / pa[:, 2:], pb[:, :2] / pb[:, 2:], m, 2.0)
    assert ratio < 0.5


def test_empty_features_match_nothing():
    empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32), 10, 10)
    blank = extract_features(np.full((120, 160), 128, np.uint8))
    assert len(blank) == 0
    assert match_features(empty, blank).shape == (0, 2)
    with pytest.raises(ValueError, match="uint8"):
        extract_features(np.zeros((10, 10), np.float32))


def test_matching_equals_brute_force_mutual_ratio_reference():
    """Chunked matching (column maxima, no column argmax) equals a plain brute-force mutual + ratio reference."""
    rng = np.random.default_rng(21)
    base = rng.normal(size=(300, 128))
    da = base[:250] + rng.normal(0, 0.3, (250, 128))
    db = np.vstack([base[50:] + rng.normal(0, 0.3, (250, 128)), rng.normal(size=(80, 128))])
    da /= np.linalg.norm(da, axis=1, keepdims=True)
    db /= np.linalg.norm(db, axis=1, keepdims=True)

    def feats(d):
        return Features(np.zeros((len(d), 2), np.float32), d.astype(np.float32), np.ones(len(d), np.float32), 64, 64)

    a, b = feats(da), feats(db)
    dist = np.linalg.norm(da[:, None, :] - db[None, :, :], axis=2)
    order = np.argsort(dist, axis=1)
    j1 = order[:, 0]
    ratio_ok = dist[np.arange(len(da)), j1] < 0.8 * dist[np.arange(len(da)), order[:, 1]]
    mutual = np.argmin(dist, axis=0)[j1] == np.arange(len(da))
    ref = {(i, int(j1[i])) for i in np.nonzero(ratio_ok & mutual)[0]}
    for chunk in (7, 64, 4096):
        got = {tuple(m) for m in match_features(a, b, 0.8, chunk_rows=chunk).tolist()}
        assert got == ref
    assert len(ref) > 100


def test_ransac_iterations_bound():
    from nodes.register.features import ransac_iterations

    # Standard formula log(1 - p) / log(1 - w^7) with w = min inliers / matches.
    assert ransac_iterations(40, 20) == int(np.ceil(np.log(0.001) / np.log(1 - 0.5**7)))
    assert ransac_iterations(20, 20) == 50  # every match must be an inlier: the floor
    assert ransac_iterations(30, 20) < ransac_iterations(40, 20) < ransac_iterations(60, 20)
    # A pair with a few dozen chance matches is cheap; a big pair is capped by the caller (10000).
    assert ransac_iterations(30, 20) < 200
    assert ransac_iterations(500, 20) > 10000


def test_pca_shortlist_matching_agrees_with_exact_matching():
    """Candidates from 64 principal components, ratio test on exact similarities: nearly the exact matches."""
    from nodes.register.features import pca_basis, project_pca

    a = extract_features(texture(3))
    warped = cv2.warpPerspective(texture(3), H_TRUE, (640, 480))
    b = extract_features(warped)
    exact = {tuple(m) for m in match_features(a, b).tolist()}
    basis = pca_basis([a.descriptors, b.descriptors], 64)
    assert basis.shape == (128, 64)
    pa, pb = project_pca(a, basis), project_pca(b, basis)
    assert pa.descriptors_pca is not None and pa.descriptors_pca.shape == (len(a), 64)
    approx = {tuple(m) for m in match_features(pa, pb).tolist()}
    assert len(exact) > 200
    assert len(exact & approx) >= 0.97 * len(exact)
    assert len(approx - exact) <= 0.03 * len(exact)
