"""Densification of the sparse cloud once photos are registered: epipolar-guided matching and track extension.

Registration needs a few hundred well-spread tracks; the static-occlusion test (paper Sec. 4.1.2) needs many more
3D points in every photo, on the fence, the ground and the trees as much as on the building. With the cameras
known, matching is no longer a blind search over the whole image: a feature in view ``a`` can only match features
of view ``b`` near its epipolar line, so repeated texture (printed hoardings, brick, windows) that defeats the
global ratio test is disambiguated by geometry. Steps:

1. **pairs**: for each view, the registered views that see the same scene with enough parallax — the camera-centre
   baseline must subtend at least ``min_angle_deg`` at the view's scene depth (so frames of one fixed camera are
   never paired, they have no baseline), the viewing directions must be less than ``max_view_angle_deg`` apart and
   a grid of rays at the scene depth must land in the other image (overlap); the ``pairs_per_view`` best by
   overlap, then one pair per pair of viewpoints, nearest in time (the scene changes while a building grows);
2. **guided matching** per pair: candidates near the epipolar line (``epipolar_frac`` of the width, both ways;
   undistorted) with positive depth in both cameras and a SIFT scale consistent with those depths
   (``max_scale_ratio``); best candidate by RootSIFT similarity, ratio test against the second-best *candidate*
   (``ratio``), mutual in both directions;
3. **triangulation**: linear (DLT) in normalised coordinates, kept when the rays are at least ``min_angle_deg``
   apart, in front of both cameras and reprojected within ``max_reproj_frac`` of the width in both (distortion
   included);
4. **tracks**: matches of all pairs joined by union-find over (view, feature); a track with two features in one
   view is dropped; tracks re-triangulated from all their observations and observations beyond ``max_reproj_frac``
   removed;
5. **track extension**: every point is looked for in every registered view it projects into (fixed cameras'
   other frames above all): the feature nearest the projection (within ``extend_frac``) whose descriptor is within
   ``extend_max_dist`` of the track's becomes an observation. A point on something that moved finds no such
   feature and is not extended.

Pure numpy/OpenCV; inputs and outputs are arrays (see :class:`View`, :class:`DensePoints`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from constructaide import camera as cam
from nodes.register.recon import Reconstruction
from schemas.messages import Intrinsics


@dataclass(frozen=True)
class DensifyParams:
    """Tuning of :func:`densify`. ``*_frac`` thresholds are fractions of the width of the view concerned (the
    registration's own PnP threshold is 1 % of the width; poses registered from a few clicks are off by a few
    pixels, and the band must hold their true matches)."""

    pairs_per_view: int = 4
    min_angle_deg: float = 2.0  # the paper's minimum triangulation angle
    max_view_angle_deg: float = 50.0  # SIFT rarely matches across wider angles; wider pairs add mostly noise
    min_overlap: float = 0.15  # fraction of a 12x9 grid of rays (at the scene depth) landing in the other view
    epipolar_frac: float = 0.008
    ratio: float = 0.8  # Lowe's ratio, but against the second-best epipolar candidate
    max_desc_dist: float = 0.5  # absolute RootSIFT distance cap (unit vectors: 0 same, sqrt(2) orthogonal)
    max_reproj_frac: float = 0.006
    max_scale_ratio: float = 1.6  # observed / depth-predicted SIFT scale in the second view (when scales are known)
    max_features: int = 4000  # strongest-scale features per view used (all when fewer)
    extend_frac: float = 0.003
    extend_max_dist: float = 0.45
    max_depth_factor: float = 6.0  # points farther than this x the view's scene depth are dropped (near-parallel rays)
    shortlist: int = 8  # most similar features checked against the geometry per feature
    chunk_rows: int = 1024


@dataclass
class View:
    """One registered photo: intrinsics, pose (4, 4) ``world_from_camera``, keypoints (N, 2) px (OpenCV pixel
    convention), unit RootSIFT descriptors (N, 128) float32, optional keypoint scales (N,) px, capture time (ns,
    0 unknown) and a scene depth (m) along the optical axis (median depth of the points it sees; None: unknown)."""

    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    keypoints_px: np.ndarray
    descriptors: np.ndarray
    scales_px: np.ndarray | None = None
    capture_time_ns: int = 0
    scene_depth_m: float | None = None


@dataclass
class DensePoints:
    """New points (P, 3) world metres and their observations: point index (M,), view index (M,), feature index
    (M,). ``pairs`` lists the view pairs matched; ``num_matches`` the guided matches before triangulation."""

    points_m: np.ndarray
    obs_point: np.ndarray
    obs_view: np.ndarray
    obs_feature: np.ndarray
    pairs: list[tuple[int, int]]
    num_matches: int
    known_new_obs: np.ndarray  # (K', 3) new observations of the known points: (known point, view, feature)
    known_verified: np.ndarray  # (K,) bool: known tracks confirmed by guided matching (see verify_tracks)

    @property
    def num_points(self) -> int:
        return len(self.points_m)

    def observations_of(self, view: int) -> tuple[np.ndarray, np.ndarray]:
        """(point indices (K,), feature indices (K,)) observed in ``view``."""
        sel = self.obs_view == view
        return self.obs_point[sel], self.obs_feature[sel]


def _px(v: View, frac: float) -> float:
    """A fraction of the view's width in pixels."""
    return frac * v.intrinsics.width_px


def _centre(v: View) -> np.ndarray:
    return np.asarray(v.world_from_camera, np.float64)[:3, 3]


def _axis(v: View) -> np.ndarray:
    return np.asarray(v.world_from_camera, np.float64)[:3, 2]


def scene_depth(v: View, points_m: np.ndarray | None = None, default_m: float = 20.0) -> float:
    """The view's scene depth (m): its own ``scene_depth_m``, else the median positive depth of ``points_m``
    (P, 3) inside its image, else ``default_m``."""
    if v.scene_depth_m is not None and v.scene_depth_m > 0:
        return float(v.scene_depth_m)
    if points_m is not None and len(points_m):
        px, z = cam.project_points(v.intrinsics, cam.invert_rigid(v.world_from_camera), points_m)
        w, h = v.intrinsics.width_px, v.intrinsics.height_px
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        if ok.sum() >= 5:
            return float(np.median(z[ok]))
    return default_m


def overlap_fraction(a: View, b: View, depth_m: float) -> float:
    """Fraction of a 12 x 9 grid of rays of ``a`` at ``depth_m`` that project inside ``b`` (in front of it)."""
    ia = a.intrinsics
    u, v = np.meshgrid(np.linspace(0.05, 0.95, 12) * ia.width_px, np.linspace(0.05, 0.95, 9) * ia.height_px)
    xy = cam.pixels_to_normalized(ia, np.stack([u.ravel(), v.ravel()], axis=1))
    p_cam = np.concatenate([xy * depth_m, np.full((len(xy), 1), depth_m)], axis=1)
    T = np.asarray(a.world_from_camera, np.float64)
    p_world = p_cam @ T[:3, :3].T + T[:3, 3]
    px, z = cam.project_points(b.intrinsics, cam.invert_rigid(b.world_from_camera), p_world)
    ib = b.intrinsics
    inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < ib.width_px) & (px[:, 1] >= 0) & (px[:, 1] < ib.height_px)
    return float(inside.mean())


def viewpoint_clusters(views: Sequence[View], depths_m: Sequence[float], frac: float = 0.02) -> np.ndarray:
    """(V,) cluster id per view: views whose centres are within ``frac`` x the scene depth of a cluster's first
    view share it (a fixed camera's frames; a phone photo retaken from the same spot)."""
    ids = np.full(len(views), -1, np.int64)
    heads: list[int] = []
    for i, v in enumerate(views):
        for k, h in enumerate(heads):
            if np.linalg.norm(_centre(v) - _centre(views[h])) < frac * min(depths_m[i], depths_m[h]):
                ids[i] = k
                break
        else:
            ids[i] = len(heads)
            heads.append(i)
    return ids


def select_pairs(
    views: Sequence[View], depths_m: Sequence[float], params: DensifyParams, only_view: int | None = None
) -> list[tuple[int, int]]:
    """View pairs (i < j) worth guided matching (see the module docstring, step 1): per view the
    ``pairs_per_view`` best partners by overlap, then one pair per pair of viewpoints (nearest in time): the other
    frames of a fixed camera add only duplicates, which track extension finds anyway. With ``only_view`` only the
    pairs of that view (a photo just registered in streaming)."""
    n = len(views)
    clusters = viewpoint_clusters(views, depths_m)
    min_angle = np.radians(params.min_angle_deg)
    cos_max = np.cos(np.radians(params.max_view_angle_deg))
    best: dict[tuple[int, int], tuple[int, tuple[int, int]]] = {}
    for i in range(n) if only_view is None else [only_view]:
        cands = []
        for j in range(n):
            if j == i or clusters[j] == clusters[i]:
                continue
            baseline = float(np.linalg.norm(_centre(views[i]) - _centre(views[j])))
            if baseline < 2.0 * depths_m[i] * np.tan(min_angle / 2.0):
                continue
            if float(_axis(views[i]) @ _axis(views[j])) < cos_max:
                continue
            ov = max(
                overlap_fraction(views[i], views[j], depths_m[i]), overlap_fraction(views[j], views[i], depths_m[j])
            )
            if ov < params.min_overlap:
                continue
            dt = abs(views[i].capture_time_ns - views[j].capture_time_ns)
            cands.append((-round(ov, 1), dt, j))
        picked: set[int] = set()
        for _, dt, j in sorted(cands):
            if len(picked) >= params.pairs_per_view:
                break
            if clusters[j] in picked:
                continue
            picked.add(int(clusters[j]))
            key = (int(min(clusters[i], clusters[j])), int(max(clusters[i], clusters[j])))
            if key not in best or dt < best[key][0]:
                best[key] = (dt, (min(i, j), max(i, j)))
    return sorted(p for _, p in best.values())


def _strongest(v: View, max_features: int) -> np.ndarray:
    """Indices of the (up to) ``max_features`` largest-scale features of the view."""
    n = len(v.keypoints_px)
    if n <= max_features or v.scales_px is None:
        return np.arange(min(n, max_features))
    return np.sort(np.argsort(-np.asarray(v.scales_px))[:max_features])


def _relative(a: View, b: View) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of camera b from camera a: x_b = R x_a + t."""
    b_from_world = cam.invert_rigid(np.asarray(b.world_from_camera, np.float64))
    T = b_from_world @ np.asarray(a.world_from_camera, np.float64)
    return T[:3, :3], T[:3, 3]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def triangulate_dlt(cams_from_world: Sequence[np.ndarray], xy_norm: Sequence[np.ndarray]) -> np.ndarray:
    """Linear triangulation of P points seen in V views: ``cams_from_world`` V x (3, 4) or (4, 4),
    ``xy_norm`` V x (P, 2) undistorted normalised coordinates. Returns (P, 3) (NaN where degenerate)."""
    rows = []
    for T, xy in zip(cams_from_world, xy_norm, strict=True):
        P = np.asarray(T, np.float64)[:3]
        rows.append(xy[:, 0:1] * P[2] - P[0])
        rows.append(xy[:, 1:2] * P[2] - P[1])
    A = np.stack(rows, axis=1)  # (P, 2V, 4)
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = X[:, :3] / X[:, 3:4]
    pts[np.abs(X[:, 3]) < 1e-12] = np.nan
    return pts


def _reproj_px(v: View, pts: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    proj, z = cam.project_points(v.intrinsics, cam.invert_rigid(v.world_from_camera), pts)
    err = np.linalg.norm(proj - px, axis=1)
    err[~np.isfinite(err)] = np.inf
    return err, z


def _candidate_ok(
    a: View, b: View, params: DensifyParams, R: np.ndarray, t: np.ndarray, E: np.ndarray, xa_h, xb_h, sa, sb, r, c
) -> np.ndarray:
    """(K,) bool for candidate pairs (feature r of a, feature c of b), homogeneous normalised rays ``xa_h``/``xb_h``:
    within ``epipolar_frac`` of the width of each other's epipolar line, positive depth in both cameras and (with
    scales) a SIFT scale in b within ``max_scale_ratio`` of the one the triangulated depths predict."""
    xa_r, xb_c = xa_h[r], xb_h[c]
    lb = xa_r @ E.T  # epipolar lines of a's features in b
    la = xb_c @ E  # and of b's in a
    res = np.einsum("nk,nk->n", lb, xb_c)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = (
            np.abs(res) / np.hypot(lb[:, 0], lb[:, 1]) * b.intrinsics.f_px
            < params.epipolar_frac * b.intrinsics.width_px
        )
        ok &= (
            np.abs(res) / np.hypot(la[:, 0], la[:, 1]) * a.intrinsics.f_px
            < params.epipolar_frac * a.intrinsics.width_px
        )
    # depths: with z_b x_b = z_a R x_a + t, z_a = ((R x_a) x x_b) . (x_b x t) / |(R x_a) x x_b|^2 and
    # z_b = ((R x_a) x x_b) . ((R x_a) x t) / |.|^2 (cheirality: both positive)
    Rxa = xa_r @ R.T
    cr = np.cross(Rxa, xb_c)
    cr2 = np.maximum(np.einsum("nk,nk->n", cr, cr), 1e-18)
    z_a = np.einsum("nk,nk->n", cr, np.cross(xb_c, t)) / cr2
    z_b = np.einsum("nk,nk->n", cr, np.cross(Rxa, t)) / cr2
    ok &= (z_a > 0) & (z_b > 0)
    if sa is not None and sb is not None:
        # SIFT scale follows the depth: a point at depths z_a, z_b has scales in the ratio f_b z_a / (f_a z_b)
        with np.errstate(divide="ignore", invalid="ignore"):
            pred = sa[r] * (b.intrinsics.f_px * z_a) / (a.intrinsics.f_px * z_b)
            ok &= np.abs(np.log(sb[c] / pred)) < np.log(params.max_scale_ratio)
    return ok


def guided_matches(a: View, b: View, params: DensifyParams, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Epipolar-guided mutual matches (M, 2) as (feature in a, feature in b), among features ``ia`` / ``ib``.

    Each feature's ``shortlist`` most similar features of the other view (one float32 product per row chunk) are
    checked against the geometry (:func:`_candidate_ok`); the best valid one must pass the ratio test against the
    second-best valid one, or, when none is left in the shortlist, against the last shortlisted similarity (an
    upper bound of every candidate outside it, so the test is conservative). Mutual: each side's best valid.
    """
    if len(ia) < 2 or len(ib) < 2:
        return np.zeros((0, 2), int)
    R, t = _relative(a, b)
    E = _skew(t) @ R  # x_b^T E x_a = 0 in normalised coordinates
    xa = cam.pixels_to_normalized(a.intrinsics, a.keypoints_px[ia])
    xb = cam.pixels_to_normalized(b.intrinsics, b.keypoints_px[ib])
    xa_h = np.concatenate([xa, np.ones((len(xa), 1))], axis=1)
    xb_h = np.concatenate([xb, np.ones((len(xb), 1))], axis=1)
    sa = None if a.scales_px is None else np.asarray(a.scales_px, np.float64)[ia]
    sb = None if b.scales_px is None else np.asarray(b.scales_px, np.float64)[ib]
    da = np.ascontiguousarray(a.descriptors[ia], np.float32)
    db = np.ascontiguousarray(b.descriptors[ib], np.float32)
    k = min(params.shortlist, len(ib) - 1)
    r2 = params.ratio * params.ratio  # ratio test on distances: d1 < r d2 <=> 2 - 2 s1 < r^2 (2 - 2 s2)
    s_min = 1.0 - 0.5 * params.max_desc_dist**2
    rows_all, cols_all, sims_all, ok_all = [], [], [], []
    row_s1 = np.full(len(ia), -np.inf, np.float32)
    row_s2 = np.full(len(ia), -np.inf, np.float32)
    row_j = np.full(len(ia), -1, np.int64)
    for r0 in range(0, len(ia), params.chunk_rows):
        S = da[r0 : r0 + params.chunk_rows] @ db.T
        top = np.empty((len(S), k + 1), np.int64)  # the k + 1 most similar, best first (repeated argmax is
        sims = np.empty((len(S), k + 1), np.float32)  # several times faster than argpartition for small k)
        rows = np.arange(len(S))
        for q in range(k + 1):
            top[:, q] = S.argmax(axis=1)
            sims[:, q] = S[rows, top[:, q]]
            S[rows, top[:, q]] = -np.inf
        rr = np.repeat(np.arange(r0, r0 + len(S)), k)
        cc = top[:, :k].ravel()
        ok = _candidate_ok(a, b, params, R, t, E, xa_h, xb_h, sa, sb, rr, cc).reshape(len(S), k)
        valid_s = np.where(ok, sims[:, :k], -np.inf)
        first = np.argmax(ok, axis=1)
        has = ok.any(axis=1)
        s1 = np.where(has, valid_s[rows, first], -np.inf)
        valid_s[rows, first] = -np.inf
        s2 = np.maximum(valid_s.max(axis=1), sims[:, k])  # second valid, or the bound beyond the shortlist
        row_s1[r0 : r0 + len(S)] = s1
        row_s2[r0 : r0 + len(S)] = s2
        row_j[r0 : r0 + len(S)] = np.where(has, top[rows, first], -1)
        rows_all.append(rr)
        cols_all.append(cc)
        sims_all.append(sims[:, :k].ravel())
        ok_all.append(ok.ravel())
    good = (row_j >= 0) & (row_s1 >= s_min)
    good &= np.maximum(2 - 2 * row_s1, 0) < r2 * np.maximum(2 - 2 * row_s2, 0)
    # mutual: a's feature must be the most similar valid candidate of its b feature among all valid pairs seen
    rr, cc, ss, okk = (np.concatenate(x) for x in (rows_all, cols_all, sims_all, ok_all))
    col_best = np.full(len(ib), -np.inf, np.float32)
    np.maximum.at(col_best, cc[okk], ss[okk])
    rows_ok = np.flatnonzero(good)
    mutual = row_s1[rows_ok] >= col_best[row_j[rows_ok]]
    rows_ok = rows_ok[mutual]
    return np.stack([ia[rows_ok], ib[row_j[rows_ok]]], axis=1).astype(int)


def _triangulate_pair(a: View, b: View, m: np.ndarray, depth_a: float, params: DensifyParams):
    """Points (M, 3) of matches ``m`` and a validity mask (M,) (angle, cheirality, reprojection, depth cap)."""
    if len(m) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    Ta, Tb = cam.invert_rigid(a.world_from_camera), cam.invert_rigid(b.world_from_camera)
    xa = cam.pixels_to_normalized(a.intrinsics, a.keypoints_px[m[:, 0]])
    xb = cam.pixels_to_normalized(b.intrinsics, b.keypoints_px[m[:, 1]])
    pts = triangulate_dlt([Ta, Tb], [xa, xb])
    ok = np.all(np.isfinite(pts), axis=1)
    ra, rb = pts - _centre(a), pts - _centre(b)
    with np.errstate(invalid="ignore"):
        cos = np.sum(ra * rb, axis=1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-12)
    ok &= cos < np.cos(np.radians(params.min_angle_deg))
    ea, za = _reproj_px(a, pts, a.keypoints_px[m[:, 0]])
    eb, zb = _reproj_px(b, pts, b.keypoints_px[m[:, 1]])
    ok &= (za > 0) & (zb > 0) & (ea < _px(a, params.max_reproj_frac)) & (eb < _px(b, params.max_reproj_frac))
    ok &= za < params.max_depth_factor * depth_a
    return pts, ok


class _UnionFind:
    def __init__(self) -> None:
        self.parent: dict[int, int] = {}

    def find(self, x: int) -> int:
        root = x
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        while self.parent.get(x, x) != root:
            self.parent[x], x = root, self.parent[x]
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def _tracks_from_matches(
    matches: dict[tuple[int, int], np.ndarray], offsets: np.ndarray
) -> list[list[tuple[int, int]]]:
    """Tracks [(view, feature), ...] joining pairwise matches; tracks with two features in one view dropped."""
    uf = _UnionFind()
    for (i, j), m in matches.items():
        for fa, fb in m:
            uf.union(int(offsets[i] + fa), int(offsets[j] + fb))
    groups: dict[int, list[int]] = {}
    for (i, j), m in matches.items():
        for k in np.concatenate([offsets[i] + m[:, 0], offsets[j] + m[:, 1]]).tolist():
            groups.setdefault(uf.find(int(k)), []).append(int(k))
    tracks = []
    for members in groups.values():
        ids = sorted(set(members))
        views = np.searchsorted(offsets, ids, side="right") - 1
        if len(set(views.tolist())) != len(ids):
            continue
        tracks.append([(int(v), int(k - offsets[v])) for v, k in zip(views, ids, strict=True)])
    return tracks


def _retriangulate(views: Sequence[View], track: list[tuple[int, int]], params: DensifyParams):
    """Multi-view point of a track and the observations consistent with it (reprojection), or None."""
    for _ in range(2):
        if len(track) < 2:
            return None
        Ts = [cam.invert_rigid(views[v].world_from_camera) for v, _ in track]
        xs = [cam.pixels_to_normalized(views[v].intrinsics, views[v].keypoints_px[f : f + 1]) for v, f in track]
        X = triangulate_dlt(Ts, xs)[0]
        if not np.all(np.isfinite(X)):
            return None
        keep = []
        for v, f in track:
            e, z = _reproj_px(views[v], X[None], views[v].keypoints_px[f : f + 1])
            if z[0] > 0 and e[0] < _px(views[v], params.max_reproj_frac):
                keep.append((v, f))
        if len(keep) == len(track):
            return X, keep
        track = keep
    return None


def extend_tracks(
    views: Sequence[View],
    points_m: np.ndarray,
    track_desc: np.ndarray,
    seen: np.ndarray,
    free: list[np.ndarray],
    params: DensifyParams,
) -> list[tuple[int, int, int]]:
    """New observations (point, view, feature) of points (P, 3) with unit descriptors (P, 128) in views whose
    ``seen`` (V, P) bool is False: the feature nearest to the projection (within ``extend_frac`` of the width)
    when it is still ``free`` (per view (N,) bool) and its descriptor is within ``extend_max_dist`` of the
    track's; one point per feature (the most similar)."""
    from scipy.spatial import cKDTree

    out: list[tuple[int, int, int]] = []
    s_min = 1.0 - 0.5 * params.extend_max_dist**2
    for vi, v in enumerate(views):
        if len(v.keypoints_px) == 0 or len(points_m) == 0:
            continue
        px, z = cam.project_points(v.intrinsics, cam.invert_rigid(v.world_from_camera), points_m)
        w, h = v.intrinsics.width_px, v.intrinsics.height_px
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        cand = np.flatnonzero(inside & ~seen[vi])
        if len(cand) == 0:
            continue
        dist, f = cKDTree(np.asarray(v.keypoints_px, np.float64)).query(
            px[cand], k=1, distance_upper_bound=_px(v, params.extend_frac)
        )
        hit = np.isfinite(dist)
        cand, f = cand[hit], f[hit]
        ok = free[vi][f]
        cand, f = cand[ok], f[ok]
        sim = np.einsum("nk,nk->n", v.descriptors[f], track_desc[cand])
        ok = sim >= s_min
        cand, f, sim = cand[ok], f[ok], sim[ok]
        order = np.argsort(-sim, kind="stable")
        _, first = np.unique(f[order], return_index=True)
        sel = order[first]
        out += [(int(p), vi, int(k)) for p, k in zip(cand[sel], f[sel], strict=True)]
    return out


def _mean_descriptors(views: Sequence[View], obs: list[list[tuple[int, int]]]) -> np.ndarray:
    """(P, 128) unit mean descriptor of each track's observations."""
    if not obs:
        return np.zeros((0, 128), np.float32)
    desc = np.stack(
        [np.mean([views[v].descriptors[f] for v, f in o], axis=0) if o else np.zeros(128) for o in obs]
    ).astype(np.float32)
    return desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)


def verify_tracks(
    views: Sequence[View],
    obs: list[list[tuple[int, int]]],
    clusters: np.ndarray,
    params: DensifyParams,
) -> np.ndarray:
    """(K,) bool: tracks (lists of (view, feature)) of which at least one observation pair from two viewpoints less
    than ``max_view_angle_deg`` apart is what epipolar-guided matching finds (the feature is the best, unambiguous
    candidate along the other's epipolar line). Blind matching keeps wrong matches of repeated texture that happen
    to lie near the epipolar line; triangulated from two views they reproject perfectly, so reprojection cannot
    reject them."""
    by_pair: dict[tuple[int, int], list[tuple[int, int, int]]] = {}
    cos_max = np.cos(np.radians(params.max_view_angle_deg))  # SIFT does not match wider: a "match" there is noise
    for t, o in enumerate(obs):
        for x in range(len(o)):
            for y in range(x + 1, len(o)):
                (va, fa), (vb, fb) = o[x], o[y]
                if clusters[va] == clusters[vb] or float(_axis(views[va]) @ _axis(views[vb])) < cos_max:
                    continue
                if va > vb:
                    va, fa, vb, fb = vb, fb, va, fa
                by_pair.setdefault((va, vb), []).append((t, fa, fb))
    ok = np.zeros(len(obs), bool)
    for (va, vb), items in by_pair.items():
        arr = np.array(items, np.int64)
        arr = arr[~ok[arr[:, 0]]]
        if len(arr) == 0:
            continue
        ia = np.unique(arr[:, 1])
        m = guided_matches(views[va], views[vb], params, ia, np.arange(len(views[vb].keypoints_px)))
        found = dict(zip(m[:, 0].tolist(), m[:, 1].tolist(), strict=True))
        hit = np.array([found.get(int(fa), -1) == int(fb) for _, fa, fb in arr])
        ok[arr[hit, 0]] = True
    return ok


def densify(
    views: Sequence[View],
    params: DensifyParams | None = None,
    known_points_m: np.ndarray | None = None,
    known_obs: list[list[tuple[int, int]]] | None = None,
    progress: Callable[[int, int], None] | None = None,
    only_view: int | None = None,
) -> DensePoints:
    """Guided matching, triangulation, tracks and track extension over registered ``views``.

    ``known_points_m`` (K, 3) with their observations ``known_obs`` (K lists of (view, feature)): the cloud the
    registration already has. Its features are not matched again, its points set the views' scene depths, are
    checked by guided matching (``DensePoints.known_verified``, see :func:`verify_tracks`) and are extended too
    (``DensePoints.known_new_obs``). ``progress(done, total)`` is called after each matched pair.

    ``only_view`` (streaming: one photo just registered): only that view's pairs are matched, only the known
    tracks it observes are verified (``known_verified`` False for the others: not checked), known tracks are not
    extended, and only the new points are.
    """
    params = params or DensifyParams()
    n = len(views)
    known = np.zeros((0, 3)) if known_points_m is None else np.asarray(known_points_m, np.float64).reshape(-1, 3)
    known_obs = known_obs or [[] for _ in range(len(known))]
    if len(known_obs) != len(known):
        raise ValueError(f"{len(known)} known points but {len(known_obs)} observation lists")
    free = [np.ones(len(v.keypoints_px), bool) for v in views]
    for o in known_obs:
        for v, f in o:
            free[v][f] = False
    seen_by: list[list[int]] = [[] for _ in views]
    for p, o in enumerate(known_obs):
        for vv in {v for v, _ in o}:
            seen_by[vv].append(p)
    depths = [scene_depth(v, known[seen_by[vi]] if len(seen_by[vi]) >= 5 else known) for vi, v in enumerate(views)]
    clusters = viewpoint_clusters(views, depths)
    if only_view is None:
        verified = verify_tracks(views, known_obs, clusters, params)
        for vi, view in enumerate(views):  # scene depths again from the confirmed points only
            own = [p for p in seen_by[vi] if verified[p]]
            if len(own) >= 5:
                depths[vi] = scene_depth(view, known[own])
    else:  # the new view's tracks only
        verified = np.zeros(len(known), bool)
        mine = np.array(seen_by[only_view], np.int64)
        if len(mine):
            verified[mine] = verify_tracks(views, [known_obs[p] for p in mine], clusters, params)
    pairs = select_pairs(views, depths, params, only_view)
    subsets = [s[free[vi][s]] for vi, s in enumerate(_strongest(v, params.max_features) for v in views)]
    offsets = np.concatenate([[0], np.cumsum([len(v.keypoints_px) for v in views])]).astype(np.int64)
    matches: dict[tuple[int, int], np.ndarray] = {}
    num_matches = 0
    for k, (i, j) in enumerate(pairs):
        m = guided_matches(views[i], views[j], params, subsets[i], subsets[j])
        num_matches += len(m)
        _, ok = _triangulate_pair(views[i], views[j], m, depths[i], params)
        if ok.any():
            matches[(i, j)] = m[ok]
        if progress is not None:
            progress(k + 1, len(pairs))
    pts_list: list[np.ndarray] = []
    obs: list[list[tuple[int, int]]] = []
    for track in _tracks_from_matches(matches, offsets):
        res = _retriangulate(views, track, params)
        if res is None:
            continue
        X, keep = res
        if not any(np.linalg.norm(X - _centre(views[v])) < params.max_depth_factor * depths[v] for v, _ in keep):
            continue
        pts_list.append(X)
        obs.append(keep)
        for v, f in keep:
            free[v][f] = False
    points = np.array(pts_list, np.float64).reshape(-1, 3)
    # extend the new tracks and the known ones in one pass (new first in the point index)
    all_pts = np.concatenate([points, known])
    # unconfirmed known tracks are not extended; with only_view none are (the caller extends its own map)
    all_obs = obs + [o if verified[k] and only_view is None else [] for k, o in enumerate(known_obs)]
    seen = np.zeros((n, len(all_pts)), bool)
    for p, o in enumerate(all_obs):
        seen[:, p] = not o  # nothing to extend from
        for v, _ in o:
            seen[v, p] = True
    known_new: list[tuple[int, int, int]] = []
    if len(all_pts) and n:
        for p, vi, f in extend_tracks(views, all_pts, _mean_descriptors(views, all_obs), seen, free, params):
            if p < len(points):
                obs[p].append((vi, f))
            else:
                known_new.append((p - len(points), vi, f))
    op = np.array([p for p, o in enumerate(obs) for _ in o], np.int64)
    ov = np.array([v for o in obs for v, _ in o], np.int64)
    of = np.array([f for o in obs for _, f in o], np.int64)
    return DensePoints(points, op, ov, of, pairs, num_matches, np.array(known_new, np.int64).reshape(-1, 3), verified)


def densify_reconstruction(
    recon: Reconstruction,
    params: DensifyParams | None = None,
    capture_times_ns: list[int] | None = None,
    progress: Callable[[int, int], None] | None = None,
    only: int | None = None,
) -> dict:
    """Densify a reconstruction in place (:func:`densify`): new tracks for the guided matches and new observations
    of the existing tracks in the registered images, and ``point_verified`` for the tracks guided matching
    confirms. ``only`` (streaming: an image just registered): only its pairs, see :func:`densify`'s ``only_view``;
    earlier verifications are kept. ``capture_times_ns`` per image (None: each image's own). Returns counts for the
    report."""
    t0 = time.perf_counter()
    reg = recon.registered_indices()
    if len(reg) < 2:
        return {"new_points": 0, "new_observations": 0, "pairs": 0, "secs": 0.0}
    local = {i: k for k, i in enumerate(reg)}
    views = [
        View(
            recon.images[i].intrinsics,  # type: ignore[arg-type]
            np.asarray(recon.images[i].world_from_camera, np.float64),
            recon.images[i].features.keypoints_px.astype(np.float64),
            recon.images[i].features.descriptors,
            recon.images[i].features.scales,
            capture_times_ns[i] if capture_times_ns else recon.images[i].capture_time_ns,
        )
        for i in reg
    ]
    known = np.flatnonzero(np.all(np.isfinite(recon.points), axis=1))
    known_obs = [[(local[i], f) for i, f in recon.track_obs[t].items() if i in local] for t in known]
    if only is not None and only not in local:
        return {"new_points": 0, "new_observations": 0, "pairs": 0, "secs": 0.0}
    only_view = None if only is None else local[only]
    dense = densify(views, params, recon.points[known], known_obs, progress=progress, only_view=only_view)
    first = len(recon.points)
    recon._add_tracks(dense.num_points)
    recon.points[first:] = dense.points_m
    new_tracks: list[dict[int, int]] = [{} for _ in range(dense.num_points)]
    for p, v, f in zip(dense.obs_point, dense.obs_view, dense.obs_feature, strict=True):
        new_tracks[p][reg[v]] = int(f)
        recon.feature_track[reg[v]][f] = first + p
    for p, obs in enumerate(new_tracks):
        i, f = next(iter(obs.items()))
        colors = recon.images[i].colors_rgb_u8
        if colors is not None:
            recon.colors[first + p] = colors[f]
    recon.track_obs.extend(new_tracks)
    for k, v, f in dense.known_new_obs:
        t = int(known[k])
        recon.track_obs[t][reg[v]] = int(f)
        recon.feature_track[reg[v]][f] = t
    recon.point_verified[known] |= dense.known_verified
    recon.point_verified[first:] = True
    recon.densified = True
    secs = time.perf_counter() - t0
    recon.timings_secs["densify"] = secs
    return {
        "confirmed_registration_points": int(dense.known_verified.sum()),
        "registration_points": len(known),
        "new_points": dense.num_points,
        "new_observations": int(len(dense.obs_point) + len(dense.known_new_obs)),
        "pairs": len(dense.pairs),
        "secs": secs,
    }
