"""Ground-truth loaders for the registration benchmark and tests (evaluation code only).

Conventions differ per set:

* Middlebury ``templeSparseRing/templeSR_par.txt``: first line = count, then per image
  ``name k11..k33 r11..r33 t1 t2 t3`` with ``P = K [R | t]`` and R, t world-to-camera. K has fx != fy and an
  off-centre principal point.
* Strecha ``fountain-P11/gt_dense_cameras/NNNN.jpg.camera``: rows 1-3 K, row 4 distortion (zero), rows 5-7 R
  **camera-to-world**, row 8 camera centre C, row 9 width height. World-to-camera is ``R^T``, ``t = -R^T C``.

Both use pixel (0, 0) = centre of the top-left pixel here (OpenCV), as the project does.

Simulated anchor clicks (:func:`simulate_anchor_clicks`): SIFT matches between the anchor image and its nearest
ground-truth neighbour are triangulated with the ground-truth cameras; points reprojecting within 0.5 px in both
views are "model points"; N of them, spread over the image by farthest-point sampling, become clicks: pixel =
ground-truth projection into the anchor image + N(0, 1 px) noise, world = the triangulated point. Draw ``seed``
of image i uses the generator seeded with (seed, i), so draws are independent across images and seeds.

Realistic clicks (:func:`simulate_realistic_clicks`, the benches' "realistic-click rows"): a person clicks
distinctive image points - strong Shi-Tomasi corners that ground truth triangulates in two or three views
(:func:`realistic_click_targets`) - with the synthetic site's user model (``constructaide.synth.clicker``:
1.5 px noise per axis, about one gross mis-click in 20, the mis-clicked indices returned). These sets have no
model, so the model point of a click is ground truth. For the synthetic site, :func:`simulate_synth_clicks`
(careful user: corners, no mis-clicks) and :func:`simulate_realistic_synth_clicks` (the demo's user) click
visible element corners with the exact model vertex.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from constructaide import camera as cam
from constructaide.synth.clicker import MISS_RATE, NOISE_PX, Clicks, SiteClicker, click_points
from constructaide.synth.clicker import spread_sample as farthest_point_sample
from nodes.register.features import extract_features, filter_matches_fundamental, match_features

DATA_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TEMPLE_DIR = DATA_ROOT / "middlebury" / "templeSparseRing"
FOUNTAIN_DIR = DATA_ROOT / "strecha" / "fountain-P11"


@dataclass
class GtCamera:
    """Ground-truth camera: K (3, 3) (may be non-square, off-centre), ``camera_from_world`` (4, 4), radial k1, k2
    (the project's model, synthetic site only). ``name``: image path relative to the images folder."""

    name: str
    path: Path
    K: np.ndarray
    camera_from_world: np.ndarray
    width_px: int
    height_px: int
    k1: float = 0.0
    k2: float = 0.0

    @property
    def P(self) -> np.ndarray:
        return self.K @ self.camera_from_world[:3]

    @property
    def world_from_camera(self) -> np.ndarray:
        return cam.invert_rigid(self.camera_from_world)

    def project(self, points_in_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and depths (N,) of world points (N, 3)."""
        p = points_in_world @ self.camera_from_world[:3, :3].T + self.camera_from_world[:3, 3]
        xy = p[:, :2] / p[:, 2:3]
        xy = cam.distort_normalized(xy, self.k1, self.k2)
        uv = xy @ self.K[:2, :2].T + self.K[:2, 2]
        return uv, p[:, 2]

    def visible(self, points_in_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and a mask (N,) of the world points this camera sees: in front, inside the image, and
        within the radius where its lens model is one-to-one (r (1 + k1 r^2 + k2 r^4) still increasing: beyond
        it, radial distortion folds points from far outside the view back into the image)."""
        uv, z = self.project(points_in_world)
        p = points_in_world @ self.camera_from_world[:3, :3].T + self.camera_from_world[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            r2 = np.sum((p[:, :2] / p[:, 2:3]) ** 2, axis=1)
        monotone = 1 + 3 * self.k1 * r2 + 5 * self.k2 * r2**2 > 0
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < self.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height_px)
        return uv, (z > 0) & inside & monotone


def load_temple(root: Path = TEMPLE_DIR) -> list[GtCamera]:
    lines = (root / "templeSR_par.txt").read_text().split("\n")
    n = int(lines[0])
    out = []
    for line in lines[1 : n + 1]:
        parts = line.split()
        vals = np.array([float(v) for v in parts[1:]])
        K = vals[:9].reshape(3, 3)
        R = vals[9:18].reshape(3, 3)
        t = vals[18:21]
        img = cv2.imread(str(root / parts[0]), cv2.IMREAD_GRAYSCALE)
        h, w = img.shape
        out.append(GtCamera(parts[0], root / parts[0], K, cam.rigid(R, t), w, h))
    return out


def load_fountain(root: Path = FOUNTAIN_DIR) -> list[GtCamera]:
    out = []
    for f in sorted((root / "gt_dense_cameras").glob("*.camera")):
        rows = [[float(v) for v in r.split()] for r in f.read_text().strip().split("\n")]
        K = np.array(rows[0:3])
        R_wc = np.array(rows[4:7])
        C = np.array(rows[7])
        w, h = int(rows[8][0]), int(rows[8][1])
        name = f.name.removesuffix(".camera")
        out.append(GtCamera(name, root / "images" / name, K, cam.rigid(R_wc.T, -R_wc.T @ C), w, h))
    return out


def triangulate_gt(a: GtCamera, b: GtCamera, px_a: np.ndarray, px_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear triangulation with ground-truth cameras; returns points (N, 3) and max reprojection error (N,) px."""
    A = np.stack(
        [
            px_a[:, 0:1] * a.P[2] - a.P[0],
            px_a[:, 1:2] * a.P[2] - a.P[1],
            px_b[:, 0:1] * b.P[2] - b.P[0],
            px_b[:, 1:2] * b.P[2] - b.P[1],
        ],
        axis=1,
    )
    Xh = np.linalg.svd(A)[2][:, -1]
    X = Xh[:, :3] / Xh[:, 3:4]
    ea = np.linalg.norm(a.project(X)[0] - px_a, axis=1)
    eb = np.linalg.norm(b.project(X)[0] - px_b, axis=1)
    za, zb = a.project(X)[1], b.project(X)[1]
    err = np.maximum(ea, eb)
    err[(za <= 0) | (zb <= 0)] = np.inf
    return X, err


def triangulate_views(views: list[GtCamera], pixels: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Linear triangulation of (N, 2) pixels in each of several ground-truth views: points (N, 3) and the
    largest reprojection error (N,) px over the views (inf when behind one)."""
    rows = []
    for c, px in zip(views, pixels, strict=True):
        rows += [px[:, 0:1] * c.P[2] - c.P[0], px[:, 1:2] * c.P[2] - c.P[1]]
    Xh = np.linalg.svd(np.stack(rows, axis=1))[2][:, -1]
    X = Xh[:, :3] / Xh[:, 3:4]
    err = np.zeros(len(X))
    for c, px in zip(views, pixels, strict=True):
        uv, z = c.project(X)
        err = np.maximum(err, np.where(z > 0, np.linalg.norm(uv - px, axis=1), np.inf))
    return X, err


def gt_points_from_pair(a: GtCamera, b: GtCamera, max_side_px: int = 1600, max_err_px: float = 0.5) -> np.ndarray:
    """World points (N, 3) triangulated from SIFT matches of two ground-truth images."""
    return gt_matches_from_pair(a, b, max_side_px, max_err_px)[2]


def gt_matches_from_pair(
    a: GtCamera, b: GtCamera, max_side_px: int = 1600, max_err_px: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SIFT matches of two ground-truth images triangulated with the ground-truth cameras: keypoints in image a
    (N, 2) and b (N, 2) px and world points (N, 3), those reprojecting within ``max_err_px`` (per 1600 px of
    width) in both."""
    fa = extract_features(cv2.imread(str(a.path), cv2.IMREAD_GRAYSCALE), 4000, max_side_px)
    fb = extract_features(cv2.imread(str(b.path), cv2.IMREAD_GRAYSCALE), 4000, max_side_px)
    m = match_features(fa, fb, 0.75)
    _, inl = filter_matches_fundamental(fa.keypoints_px, fb.keypoints_px, m, max(1.0, a.width_px / 1000))
    m = m[inl]
    px_a, px_b = fa.keypoints_px[m[:, 0]].astype(np.float64), fb.keypoints_px[m[:, 1]].astype(np.float64)
    X, err = triangulate_gt(a, b, px_a, px_b)
    ok = err < max_err_px * max(1.0, a.width_px / 1600)
    return px_a[ok], px_b[ok], X[ok]


def nearest_view(cams: list[GtCamera], i: int) -> int:
    """Index of the camera with the most similar viewing direction to camera i among those with a baseline of at
    least 5 % of the mean camera distance from the cameras' centroid (some sets repeat a pose)."""
    return near_views(cams, i, 1)[0]


def near_views(cams: list[GtCamera], i: int, n: int) -> list[int]:
    """The ``n`` cameras with the most similar viewing directions to camera i, most similar first, among those
    with a baseline (as :func:`nearest_view`, which is the first of them)."""
    centres = np.array([c.world_from_camera[:3, 3] for c in cams])
    scale = float(np.mean(np.linalg.norm(centres - centres.mean(0), axis=1)))
    d = [cams[j].world_from_camera[:3, 2] for j in range(len(cams))]
    ok = [j for j in range(len(cams)) if j != i and np.linalg.norm(centres[j] - centres[i]) > 0.05 * scale]
    return sorted(ok, key=lambda j: -float(d[i] @ d[j]))[:n]


def simulate_anchor_clicks(
    cams: list[GtCamera], i: int, n_clicks: int = 12, noise_px: float = 1.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Clicks (pixels (N, 2), world (N, 3)) for camera i; see the module docstring for how."""
    rng = np.random.default_rng((seed, i))
    X = gt_points_from_pair(cams[i], cams[nearest_view(cams, i)])
    px, _ = cams[i].project(X)
    pick = farthest_point_sample(px, n_clicks, rng)
    return px[pick] + rng.normal(0.0, noise_px, (len(pick), 2)), X[pick]


def strong_corners(image_gray: np.ndarray, max_corners: int = 4000, quality: float = 0.05) -> np.ndarray:
    """Shi-Tomasi corners (N, 2) px of a grey image, refined to sub-pixel: the distinctive points a person can
    click precisely (at least 0.4 % of the width apart; corner strength above ``quality`` x the strongest; those
    whose sub-pixel refinement moves them more than 1 px, not a sharp corner, are left out)."""
    min_dist = max(3.0, 0.004 * image_gray.shape[1])
    c = cv2.goodFeaturesToTrack(image_gray, max_corners, quality, min_dist, blockSize=5)
    if c is None:
        return np.zeros((0, 2))
    raw = c.reshape(-1, 2).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    sub = cv2.cornerSubPix(image_gray, raw.copy().reshape(-1, 1, 2), (5, 5), (-1, -1), crit).reshape(-1, 2)
    return sub[np.linalg.norm(sub - raw, axis=1) <= 1.0].astype(np.float64)


def _ecc_match(
    gray_a: np.ndarray, gray_b: np.ndarray, c: np.ndarray, A: np.ndarray, half: int = 10, min_rho: float = 0.9
) -> np.ndarray:
    """Where pixel ``c`` (2,) of float32 image a is in image b: the (2 x 2h+1)^2 patch around it aligned to b by
    ECC (affine motion) from the affine prediction ``A`` (3, 2) (``[u, v, 1] @ A`` maps a to b); NaN when the
    patch leaves an image, ECC fails, its correlation is below ``min_rho`` or it moved the point more than 0.2 %
    of the width (at least 2 px) from the prediction."""
    x0, y0 = int(round(c[0])) - half, int(round(c[1])) - half
    side = 2 * half + 1
    if x0 < 0 or y0 < 0 or x0 + side > gray_a.shape[1] or y0 + side > gray_a.shape[0]:
        return np.full(2, np.nan)
    # Search a window of b around the prediction (ECC warps only what the template covers).
    centre = np.r_[c, 1.0] @ A
    m = 4 * side
    bx0, by0 = int(centre[0]) - m, int(centre[1]) - m
    if bx0 < 0 or by0 < 0 or bx0 + 2 * m > gray_b.shape[1] or by0 + 2 * m > gray_b.shape[0]:
        return np.full(2, np.nan)
    W = np.ascontiguousarray(np.c_[A[:2].T, A[2] + A[:2].T @ [x0, y0] - [bx0, by0]], dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    try:
        rho, W = cv2.findTransformECC(
            np.ascontiguousarray(gray_a[y0 : y0 + side, x0 : x0 + side]),
            np.ascontiguousarray(gray_b[by0 : by0 + 2 * m, bx0 : bx0 + 2 * m]),
            W,
            cv2.MOTION_AFFINE,
            crit,
            None,
            1,
        )
    except cv2.error:
        return np.full(2, np.nan)
    found = W.astype(np.float64) @ [c[0] - x0, c[1] - y0, 1.0] + [bx0, by0]
    if rho < min_rho or np.linalg.norm(found - centre[:2]) > max(2.0, 0.002 * gray_b.shape[1]):
        return np.full(2, np.nan)
    return found


def realistic_click_targets(cams: list[GtCamera], i: int, max_err_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """What a person can click in image i of a real set, and the model points: the Shi-Tomasi corners of the
    image (:func:`strong_corners`) found in one or both of its two nearest views and triangulated with the
    ground-truth cameras. Each corner's position in another view is predicted by the local affine map of the 12
    nearest ground-truth SIFT matches (:func:`gt_matches_from_pair`) and refined by ECC alignment of the
    21 x 21 px patch (affine, correlation >= 0.9, at most 0.2 % of the width, >= 2 px, from the prediction:
    :func:`_ecc_match`); a corner is kept when its point reprojects within ``max_err_px`` (per 1600 px of
    width) in every view it was found in (two or three). Returns the points'
    ground-truth projections into image i (N, 2) px and the points (N, 3). There is no model of these sets: the
    "model point" is ground truth, as in :func:`simulate_anchor_clicks`."""
    a = cams[i]
    gray_a = cv2.imread(str(a.path), cv2.IMREAD_GRAYSCALE)
    corners = strong_corners(gray_a)
    gray_a = gray_a.astype(np.float32)
    views, matched = [a], [corners]
    for j in near_views(cams, i, 2):
        b = cams[j]
        kp_a, kp_b, _ = gt_matches_from_pair(a, b)
        k = min(12, len(kp_a))
        m = np.full_like(corners, np.nan)
        if k >= 3 and len(corners):
            gray_b = cv2.imread(str(b.path), cv2.IMREAD_GRAYSCALE).astype(np.float32)
            dist, nn = cKDTree(kp_a).query(corners, k=k)
            for r in np.nonzero(dist[:, -1] < 0.1 * a.width_px)[0]:  # interpolate the affine, never extrapolate
                A = np.linalg.lstsq(np.c_[kp_a[nn[r]], np.ones(k)], kp_b[nn[r]], rcond=None)[0]
                m[r] = _ecc_match(gray_a, gray_b, corners[r], A)
        views.append(b)
        matched.append(m)
    found = np.stack([np.all(np.isfinite(m), axis=1) for m in matched[1:]], axis=1)  # (N, views - 1)
    px_out, X_out = [], []
    for pattern in {tuple(f) for f in found if f.any()}:  # triangulate in every view the corner was found in
        rows = np.all(found == pattern, axis=1)
        use = [0] + [v + 1 for v, f in enumerate(pattern) if f]
        X, err = triangulate_views([views[v] for v in use], [matched[v][rows] for v in use])
        good = err < max_err_px * max(1.0, a.width_px / 1600)
        px_out.append(a.project(X[good])[0])
        X_out.append(X[good])
    if not px_out:
        return np.zeros((0, 2)), np.zeros((0, 3))
    return np.vstack(px_out).reshape(-1, 2), np.vstack(X_out).reshape(-1, 3)


def simulate_realistic_clicks(
    cams: list[GtCamera],
    i: int,
    n_clicks: int = 12,
    noise_px: float = NOISE_PX,
    seed: int = 0,
    miss_rate: float = MISS_RATE,
    *,
    targets: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A person's clicks for camera i of a real set: pixels (N, 2), world points (N, 3) and the indices of the
    gross mis-clicks (K,); see :func:`realistic_click_set`."""
    c = realistic_click_set(cams, i, n_clicks, noise_px, seed, miss_rate, targets=targets)
    return c.pixels_px, c.points_in_world_m, c.mis_clicked


def realistic_click_set(
    cams: list[GtCamera],
    i: int,
    n_clicks: int = 12,
    noise_px: float = NOISE_PX,
    seed: int = 0,
    miss_rate: float = MISS_RATE,
    *,
    targets: tuple[np.ndarray, np.ndarray] | None = None,
) -> Clicks:
    """:func:`simulate_realistic_clicks` with everything the user model knows (a
    :class:`constructaide.synth.clicker.Clicks`: true projections, mis-click kinds, clickable count). The
    clickable points are strong image corners that ground truth triangulates (:func:`realistic_click_targets`);
    the clicks are those of the synthetic site's user (:func:`constructaide.synth.clicker.click_points`: spread
    over the image, ``noise_px`` Gaussian noise per axis, ``miss_rate`` gross mis-clicks: a neighbouring corner
    10-80 px away or a slip 10-60 px off, the world point staying the intended one). Draw ``seed`` of image i
    uses the generator seeded with (seed, i, 1). ``targets``: :func:`realistic_click_targets` of image i, to draw
    several times without recomputing it. Raises ValueError with fewer than 4 clickable corners."""
    target, X = targets if targets is not None else realistic_click_targets(cams, i)
    size = (cams[i].width_px, cams[i].height_px)
    return click_points(target, X, np.random.default_rng((seed, i, 1)), size, n_clicks, noise_px, miss_rate)


def checkpoints(cams: list[GtCamera], max_points: int = 600, seed: int = 0, max_side_px: int = 1600) -> np.ndarray:
    """Ground-truth 3D checkpoints (N, 3): GT-triangulated feature points of every other image and its nearest
    view."""
    pts = []
    for i in range(0, len(cams), 2):
        pts.append(gt_points_from_pair(cams[i], cams[nearest_view(cams, i)], max_side_px))
    X = np.vstack(pts)
    rng = np.random.default_rng(seed)
    if len(X) > max_points:
        X = X[rng.choice(len(X), max_points, replace=False)]
    return X


def load_synth(site_dir: Path) -> list[GtCamera]:
    """Synthetic site cameras from ``truth/cameras.json`` (evaluation only), names relative to ``photos/``."""
    import json

    recs = json.loads((Path(site_dir) / "truth" / "cameras.json").read_text())
    out = []
    for rel in sorted(recs):
        r = recs[rel]
        T = np.asarray(r["world_from_camera"], dtype=np.float64)
        out.append(
            GtCamera(
                rel,
                Path(site_dir) / "photos" / rel,
                np.asarray(r["K"], dtype=np.float64),
                cam.invert_rigid(T),
                int(r["width"]),
                int(r["height"]),
                float(r["k1"]),
                float(r["k2"]),
            )
        )
    return out


def synth_checkpoints(site_dir: Path, cams: list[GtCamera], per_photo: int = 60, seed: int = 0) -> np.ndarray:
    """Checkpoints (N, 3) on the building: ground-truth depth maps back-projected at random pixels that show a BIM
    element (ground-truth ID image > 0), as overlays care about the model."""
    from constructaide.synth.truth import load_depth, load_ids

    rng = np.random.default_rng(seed)
    pts = []
    for c in cams:
        depth = load_depth(site_dir, c.name)
        vv, uu = np.nonzero((depth > 0) & (load_ids(site_dir, c.name) > 0))
        pick = rng.choice(len(uu), min(per_photo, len(uu)), replace=False)
        px = np.c_[uu[pick], vv[pick]].astype(np.float64)
        xy_d = (px - c.K[:2, 2]) / [c.K[0, 0], c.K[1, 1]]
        xy = cam.undistort_normalized(xy_d, c.k1, c.k2)
        z = depth[vv[pick], uu[pick]].astype(np.float64)
        p_cam = np.c_[xy * z[:, None], z]
        T = c.world_from_camera
        pts.append(p_cam @ T[:3, :3].T + T[:3, 3])
    return np.vstack(pts)


def simulate_synth_clicks(
    site_dir: Path, c: GtCamera, n_clicks: int = 12, noise_px: float = 1.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Careful-user clicks (pixels (N, 2), world (N, 3)) for one synthetic-site photo: the visible element
    corners of :class:`constructaide.synth.clicker.SiteClicker` (the demo's simulated user) with ``noise_px``
    noise per axis but **no gross mis-clicks** (see :func:`simulate_realistic_synth_clicks` for those). Reads
    truth/. Raises ValueError when fewer than 4 corners are clickable."""
    clicks = _site_clicker(Path(site_dir)).clicks(c.name, n_clicks, noise_px, seed, miss_rate=0.0)
    return clicks.pixels_px, clicks.points_in_world_m


def simulate_realistic_synth_clicks(
    site_dir: Path,
    c: GtCamera,
    n_clicks: int = 12,
    noise_px: float = NOISE_PX,
    seed: int = 0,
    miss_rate: float = MISS_RATE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The realistic user's clicks for one synthetic-site photo, as the demo answers requests with: pixels (N, 2),
    world points (N, 3; exact model vertices) and the indices of the gross mis-clicks (K,)
    (:meth:`constructaide.synth.clicker.SiteClicker.clicks`: visible corners, ``noise_px`` per axis, ``miss_rate``
    mis-clicks). Reads truth/. Raises ValueError when fewer than 4 corners are clickable."""
    clicks = _site_clicker(Path(site_dir)).clicks(c.name, n_clicks, noise_px, seed, miss_rate)
    return clicks.pixels_px, clicks.points_in_world_m, clicks.mis_clicked


@functools.lru_cache(maxsize=4)
def _site_clicker(site_dir: Path) -> SiteClicker:
    return SiteClicker(site_dir)
