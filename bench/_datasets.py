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
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from constructaide import camera as cam
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


def gt_points_from_pair(a: GtCamera, b: GtCamera, max_side_px: int = 1600, max_err_px: float = 0.5) -> np.ndarray:
    """World points (N, 3) triangulated from SIFT matches of two ground-truth images."""
    fa = extract_features(cv2.imread(str(a.path), cv2.IMREAD_GRAYSCALE), 4000, max_side_px)
    fb = extract_features(cv2.imread(str(b.path), cv2.IMREAD_GRAYSCALE), 4000, max_side_px)
    m = match_features(fa, fb, 0.75)
    _, inl = filter_matches_fundamental(fa.keypoints_px, fb.keypoints_px, m, max(1.0, a.width_px / 1000))
    m = m[inl]
    X, err = triangulate_gt(a, b, fa.keypoints_px[m[:, 0]], fb.keypoints_px[m[:, 1]])
    return X[err < max_err_px * max(1.0, a.width_px / 1600)]


def nearest_view(cams: list[GtCamera], i: int) -> int:
    """Index of the camera with the most similar viewing direction to camera i among those with a baseline of at
    least 5 % of the mean camera distance from the cameras' centroid (some sets repeat a pose)."""
    centres = np.array([c.world_from_camera[:3, 3] for c in cams])
    scale = float(np.mean(np.linalg.norm(centres - centres.mean(0), axis=1)))
    d = [cams[j].world_from_camera[:3, 2] for j in range(len(cams))]
    ok = [j for j in range(len(cams)) if j != i and np.linalg.norm(centres[j] - centres[i]) > 0.05 * scale]
    return max(ok, key=lambda j: float(d[i] @ d[j]))


def simulate_anchor_clicks(
    cams: list[GtCamera], i: int, n_clicks: int = 12, noise_px: float = 1.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Clicks (pixels (N, 2), world (N, 3)) for camera i; see the module docstring for how."""
    rng = np.random.default_rng((seed, i))
    X = gt_points_from_pair(cams[i], cams[nearest_view(cams, i)])
    px, _ = cams[i].project(X)
    pick = farthest_point_sample(px, n_clicks, rng)
    return px[pick] + rng.normal(0.0, noise_px, (len(pick), 2)), X[pick]


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
    """Simulated user clicks (pixels (N, 2), world (N, 3)) for one synthetic-site photo (reads truth/; see
    :func:`constructaide.synth.clicker.simulated_clicks`, the same simulated user the demo answers requests
    with)."""
    from constructaide.synth.clicker import simulated_clicks

    return simulated_clicks(site_dir, c.name, n_clicks, noise_px, seed)
