"""Anchor registration: camera pose (and optionally focal) from user clicks (paper Sec. 6).

A user clicks >= 4 pixels and the model points they show. The pose is solved by Levenberg-Marquardt on
reprojection error (initialised by OpenCV PnP solvers), with the principal point at the image centre, square
pixels and no distortion. The focal comes from a prior (EXIF / user) or a 50 degree horizontal field of view;
with >= 6 non-coplanar clicks it is solved too. Gross mis-clicks are flagged (``outlier_mask``) first by
consensus (RANSAC, then a robust fit with radial distortion: several mis-clicks do not mask each other), then one
at a time by their leave-one-out prediction error. Degenerate input raises :class:`DegenerateAnchors`.

Frames and units: pixels in the OpenCV convention ((0, 0) = centre of the top-left pixel), world points in
model units, ``world_from_camera`` (4, 4) maps OpenCV camera coordinates to world.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from constructaide import camera as cam
from schemas.messages import Intrinsics

DEFAULT_FOV_DEG = 50.0
MIN_CLICKS = 4
MIN_CLICKS_FOR_FOCAL = 6
MIN_CLICKS_FOR_DISTORTION = 8
DISTORTION_PRIOR_SIGMA = 0.1  # weak zero-mean prior on k1 (and k2), as their standard deviation
# Clicks further than this fraction of the width from the pinhole camera that most clicks agree on are gross
# mis-clicks (a neighbouring corner, a slip): beyond what radial distortion puts between a pinhole and a lens.
CONSENSUS_FRAC = 0.03
# Relative standard deviation of a focal prior (EXIF / user) when the focal is solved with it: EXIF 35 mm-equivalent
# focals are whole millimetres (+-0.5 mm of 20-50 mm: a uniform error of sigma 0.6-1.4 %). Residuals are in pixels,
# so the prior counts like one click coordinate with 1 px noise per FOCAL_PRIOR_SIGMA of relative focal error.
FOCAL_PRIOR_SIGMA = 0.015
# Another camera fitting the clicks within max(AMBIGUOUS_RMS_PX, AMBIGUOUS_RMS_RATIO x the solution's RMS) and turned
# more than AMBIGUOUS_TURN_DEG from it makes the clicks ambiguous (see AnchorSolution.ambiguous).
AMBIGUOUS_RMS_PX = 3.0
AMBIGUOUS_RMS_RATIO = 2.0
AMBIGUOUS_TURN_DEG = 15.0
FEW_CLICKS = 6  # up to this many clicks, every three-click (P3P) solution starts a solve too


class DegenerateAnchors(ValueError):
    """The clicks cannot determine a camera (too few, collinear, behind the camera, inconsistent...)."""


@dataclass
class AnchorSolution:
    """Camera solved from clicks.

    ``residuals_px`` (N,): reprojection error of each click under the solution; ``loo_errors_px`` (N,): error of
    each click predicted by the solution without it (NaN when too few clicks to leave one out);
    ``outlier_mask`` (N,) bool: clicks flagged as probable mis-clicks.
    """

    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    residuals_px: np.ndarray
    rms_px: float
    focal_solved: bool
    outlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    loo_errors_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    outlier_threshold_px: float = float("nan")
    distortion_solved: bool = False
    # A focal prior was given but the clicks contradict it (a free focal halves the squared error): solved freely.
    focal_prior_rejected: bool = False
    # Other cameras (world_from_camera (4, 4), f_px) that fit the inlier clicks about as well and look elsewhere
    # (few clicks on one facade: the mirrored pose of a planar target): the clicks alone cannot tell them apart.
    ambiguous: list[tuple[np.ndarray, float]] = field(default_factory=list)

    @property
    def ambiguous_turn_deg(self) -> float:
        """Largest rotation (deg) between this camera and one of ``ambiguous`` (0 when none)."""
        R = self.world_from_camera[:3, :3]
        return max((cam.rotation_angle_deg(T[:3, :3], R) for T, _ in self.ambiguous), default=0.0)


def _residuals(params: np.ndarray, pts: np.ndarray, px: np.ndarray, c: np.ndarray, f_fixed: float | None) -> np.ndarray:
    R = cam.rodrigues_to_matrix(params[:3])
    p_cam = pts @ R.T + params[3:6]
    f = f_fixed if f_fixed is not None else float(np.exp(np.clip(params[6], -20.0, 20.0)))
    z = p_cam[:, 2]
    z_safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
    proj = f * p_cam[:, :2] / z_safe[:, None] + c
    return (proj - px).ravel()


def _distortion_constrained(px: np.ndarray, pts: np.ndarray, width_px: int, height_px: int) -> bool:
    """Whether clicks (N, 2) <-> (N, 3) constrain radial distortion: >= 8 non-coplanar clicks spread over the
    image (bounding box >= 40 % of width and height, the farthest click >= 60 % of the half-diagonal out)."""
    if len(px) < MIN_CLICKS_FOR_DISTORTION or _is_planar(pts):
        return False
    span = np.ptp(px, axis=0)
    c = np.array([(width_px - 1) / 2.0, (height_px - 1) / 2.0])
    r_max = float(np.max(np.linalg.norm(px - c, axis=1)))
    return bool(span[0] >= 0.4 * width_px and span[1] >= 0.4 * height_px and r_max >= 0.6 * np.hypot(*c))


def _focal_prior_residual(log_f: float, focal_prior: tuple[float, float] | None) -> np.ndarray:
    """(1,) residual of a focal prior ``(f_prior_px, relative sigma)`` on log f, or (0,) without a prior."""
    if focal_prior is None:
        return np.zeros(0)
    return np.array([(log_f - np.log(focal_prior[0])) / focal_prior[1]])


def _refine_distortion(
    params: np.ndarray,
    f: float,
    pts: np.ndarray,
    px: np.ndarray,
    c: np.ndarray,
    solve_focal: bool,
    with_k2: bool,
    focal_prior: tuple[float, float] | None = None,
) -> tuple[np.ndarray, float, float, float]:
    """LM over pose (, log f), k1 (, k2) from a pinhole solution, with a weak zero-mean prior on k1, k2 (and the
    focal prior when the focal is solved). Returns (rvec|tvec, f_px, k1, k2)."""
    nk = 2 if with_k2 else 1

    def res(x: np.ndarray) -> np.ndarray:
        R = cam.rodrigues_to_matrix(x[:3])
        p = pts @ R.T + x[3:6]
        z = np.where(np.abs(p[:, 2]) < 1e-9, 1e-9, p[:, 2])
        ff = float(np.exp(np.clip(x[6], -20.0, 20.0))) if solve_focal else f
        k = x[-nk:]
        xy = cam.distort_normalized(p[:, :2] / z[:, None], float(k[0]), float(k[1]) if with_k2 else 0.0)
        prior = k / DISTORTION_PRIOR_SIGMA
        f_prior = _focal_prior_residual(float(x[6]), focal_prior) if solve_focal else np.zeros(0)
        return np.concatenate([(ff * xy + c - px).ravel(), prior, f_prior])

    x0 = np.concatenate([params[:6], [np.log(f)] if solve_focal else [], np.zeros(nk)])
    sol = least_squares(res, x0, method="lm", x_scale="jac", max_nfev=400)
    ff = float(np.exp(np.clip(sol.x[6], -20.0, 20.0))) if solve_focal else f
    k = sol.x[-nk:]
    return sol.x[:6].copy(), ff, float(k[0]), float(k[1]) if with_k2 else 0.0


def _distorted_residuals(params, pts, px, c, f, k1, k2) -> np.ndarray:
    R = cam.rodrigues_to_matrix(params[:3])
    p = pts @ R.T + params[3:6]
    z = np.where(np.abs(p[:, 2]) < 1e-9, 1e-9, p[:, 2])
    return (f * cam.distort_normalized(p[:, :2] / z[:, None], k1, k2) + c - px).ravel()


def _rms(res: np.ndarray) -> float:
    return float(np.sqrt(np.mean(res.reshape(-1, 2) ** 2 * 2))) if res.size else 0.0


def _pnp_inits(pts: np.ndarray, px: np.ndarray, K: np.ndarray, planar: bool) -> list[np.ndarray]:
    """Candidate (rvec, tvec) from several OpenCV solvers; camera_from_world convention."""
    methods = [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP]
    if planar:
        methods.insert(0, cv2.SOLVEPNP_IPPE)
    out = []
    if len(pts) <= FEW_CLICKS:
        # Few clicks may pin a camera only up to the discrete solutions of three of them (two clicks on one spot,
        # a short row): start from every such solution, so that the ambiguity shows (AnchorSolution.ambiguous).
        for sub in itertools.combinations(range(len(pts)), 3):
            k = list(sub)
            try:
                _, rvecs, tvecs = cv2.solveP3P(pts[k], px[k], K, None, flags=cv2.SOLVEPNP_AP3P)
            except cv2.error:
                continue
            for r, t in zip(rvecs, tvecs, strict=False):
                if np.all(np.isfinite(r)) and np.all(np.isfinite(t)):
                    out.append(np.concatenate([np.ravel(r), np.ravel(t)]).astype(np.float64))
    for method in methods:
        try:
            ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(pts, px, K, None, flags=method)
        except cv2.error:
            continue
        if not ok:
            continue
        for r, t in zip(rvecs, tvecs, strict=False):
            if np.all(np.isfinite(r)) and np.all(np.isfinite(t)):
                out.append(np.concatenate([np.ravel(r), np.ravel(t)]).astype(np.float64))
    return out


def _dlt_focal(pts: np.ndarray, px: np.ndarray, c: np.ndarray) -> float | None:
    """Focal (px) from a normalised DLT projection matrix; None when it is not meaningful."""
    n = len(pts)
    mean3, mean2 = pts.mean(0), px.mean(0)
    s3 = np.sqrt(3) / max(np.linalg.norm(pts - mean3, axis=1).mean(), 1e-12)
    s2 = np.sqrt(2) / max(np.linalg.norm(px - mean2, axis=1).mean(), 1e-12)
    T3 = np.diag([s3, s3, s3, 1.0])
    T3[:3, 3] = -s3 * mean3
    T2 = np.diag([s2, s2, 1.0])
    T2[:2, 2] = -s2 * mean2
    X = np.c_[pts, np.ones(n)] @ T3.T
    x = np.c_[px, np.ones(n)] @ T2.T
    A = np.zeros((2 * n, 12))
    A[0::2, 4:8] = -X
    A[0::2, 8:12] = X * x[:, 1:2]
    A[1::2, 0:4] = X
    A[1::2, 8:12] = -X * x[:, 0:1]
    P = np.linalg.svd(A)[2][-1].reshape(3, 4)
    P = np.linalg.inv(T2) @ P @ T3
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-15:
        return None
    # K K^T = M M^T up to scale; with a known principal point f^2 = (M M^T)_00/(M M^T)_22 - cx^2.
    MMt = M @ M.T / (M[2] @ M[2])
    fx2 = MMt[0, 0] - c[0] ** 2
    fy2 = MMt[1, 1] - c[1] ** 2
    vals = [v for v in (fx2, fy2) if v > 0]
    if not vals:
        return None
    return float(np.sqrt(np.mean(vals)))


def _consensus_outliers(
    px: np.ndarray,
    pts: np.ndarray,
    c: np.ndarray,
    f0: float,
    focal_known: bool,
    thr_px: float,
    floor_px: float,
) -> tuple[np.ndarray, float] | None:
    """Clicks (N,) that one camera does not explain, and the distance (px) beyond which a click is out: RANSAC over
    PnP samples (:func:`_pnp_consensus`) within twice ``floor_px``, else within ``thr_px``, for a start; then a
    robust fit of pose (, focal) and radial k1 to the tight consensus's clicks, or to all clicks after a loose one;
    a click further than max(``floor_px``, 4 sigmas of the click noise) from it is out. Several gross
    mis-clicks mask each other in a leave-one-out test (each is predicted by a solve the others bend); neither fit
    is bent by them. None (no decision) unless RANSAC agrees on >= max(6, 0.6 N) clicks and as many stay in."""
    n = len(px)
    need = max(MIN_CLICKS_FOR_FOCAL, 0.6 * n)
    if n < MIN_CLICKS_FOR_FOCAL + 1:
        return None
    best: tuple[np.ndarray, float, np.ndarray] | None = None
    tight = False
    # The tight consensus first (twice the noise floor): at the loose threshold (room for a lens's distortion) two
    # or three mis-clicks in one strip of the photo can agree with a wrong camera bent towards them, and a robust
    # fit with a free k1 then bends the lens to them too. When enough clicks agree within the tight threshold, the
    # camera is fitted to those alone and the others are judged by it.
    for thr in (2.0 * floor_px, thr_px) if 2.0 * floor_px < thr_px else (thr_px,):
        best = _pnp_consensus(px, pts, c, f0, focal_known, thr)
        if best is not None and len(best[2]) >= need:
            tight = thr < thr_px
            break
    if best is None or len(best[2]) < need:
        return None
    x0, f_r, inl = best
    solve_f = not focal_known and not _is_planar(pts)
    use = np.ones(n, bool)  # the clicks fitted: the tight consensus's, else all
    if tight:
        use[:] = False
        use[inl] = True

    def res(x: np.ndarray, sel: np.ndarray = use) -> np.ndarray:
        ff = float(np.exp(np.clip(x[6], -20.0, 20.0))) if solve_f else f_r
        r = _distorted_residuals(x[:6], pts[sel], px[sel], c, ff, float(x[-1]), 0.0)
        return np.r_[r, x[-1] / DISTORTION_PRIOR_SIGMA]

    # A robust fit (to the tight consensus's clicks, else to all) from the consensus pose, with radial k1 under its
    # weak prior (a lens's distortion is not a mis-click): the mis-clicks barely pull it. Graduated: a wide Cauchy
    # loss from the consensus pose, then a bounded (arctan) one at the noise floor, under which a mis-click's pull
    # fades with the square of its distance.
    x = np.r_[x0, [np.log(f_r)] if solve_f else [], 0.0]
    for loss, scale in (("cauchy", thr_px), ("arctan", floor_px)):
        x = least_squares(res, x, method="trf", loss=loss, f_scale=scale, x_scale="jac", max_nfev=200).x
    r_px = np.linalg.norm(res(x, np.ones(n, bool))[:-1].reshape(-1, 2), axis=1)
    # 4 sigmas of the clicks' noise per axis, from the median residual of the clicks fitted (Rayleigh: median =
    # 1.1774 sigma), corrected for the parameters the fit spends on them.
    p = 7 + int(solve_f)
    m = int(use.sum())
    sigma = float(np.median(r_px[use])) / 1.1774 * np.sqrt(2 * m / max(2 * m - p, 1))
    threshold = max(floor_px, 4.0 * sigma)
    out = r_px > threshold
    if n - out.sum() < need:
        return None
    return out, threshold


def _pnp_consensus(
    px: np.ndarray, pts: np.ndarray, c: np.ndarray, f0: float, focal_known: bool, thr_px: float
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """RANSAC over PnP samples within ``thr_px`` at the focal ``f0`` (and, without a known focal, at 0.5-2x it):
    the best (rvec|tvec (6,), focal, inlier indices), or None."""
    best: tuple[np.ndarray, float, np.ndarray] | None = None
    for scale in (1.0,) if focal_known else (1.0, 0.7, 1.4, 0.5, 2.0):
        f = f0 * scale
        K = np.array([[f, 0.0, c[0]], [0.0, f, c[1]], [0.0, 0.0, 1.0]])
        try:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                pts,
                px,
                K,
                None,
                iterationsCount=300,
                reprojectionError=thr_px,
                confidence=0.999,
                flags=cv2.SOLVEPNP_SQPNP,
            )
        except cv2.error:
            continue
        if ok and inl is not None and (best is None or len(inl) > len(best[2])):
            best = (np.r_[np.ravel(rvec), np.ravel(tvec)], f, inl.ravel())
    return best


def _validate(pixels_px, points_in_world) -> tuple[np.ndarray, np.ndarray]:
    px = np.asarray(pixels_px, dtype=np.float64)
    pts = np.asarray(points_in_world, dtype=np.float64)
    if px.ndim != 2 or px.shape[1] != 2:
        raise DegenerateAnchors(f"pixels must have shape (N, 2), got {px.shape}")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DegenerateAnchors(f"world points must have shape (N, 3), got {pts.shape}")
    if len(px) != len(pts):
        raise DegenerateAnchors(f"{len(px)} pixels but {len(pts)} world points")
    if not (np.all(np.isfinite(px)) and np.all(np.isfinite(pts))):
        raise DegenerateAnchors("clicks contain NaN or infinite values")
    if len(px) < MIN_CLICKS:
        raise DegenerateAnchors(f"need at least {MIN_CLICKS} clicks, got {len(px)}")
    extent = float(np.ptp(pts, axis=0).max())
    if extent <= 1e-9 * max(1.0, float(np.abs(pts).max())):
        raise DegenerateAnchors("all clicked model points coincide")
    uniq_pts = len(np.unique(np.round(pts / (extent * 1e-6)), axis=0))
    uniq_px = len(np.unique(np.round(px * 10), axis=0))
    if min(uniq_pts, uniq_px) < MIN_CLICKS:
        raise DegenerateAnchors(
            f"only {min(uniq_pts, uniq_px)} distinct clicks (duplicated pixels or points); need {MIN_CLICKS}"
        )
    s2 = np.linalg.svd(px - px.mean(0), compute_uv=False)
    if s2[1] / np.sqrt(len(px)) < 1.0 or s2[1] < 1e-3 * s2[0]:
        raise DegenerateAnchors("clicked pixels are collinear; spread clicks over the image")
    s3 = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    if s3[1] < 1e-3 * s3[0]:
        raise DegenerateAnchors("clicked model points are collinear; pick points off one line")
    return px, pts


def _is_planar(pts: np.ndarray) -> bool:
    s3 = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
    return bool(s3[2] < 0.02 * s3[0])


def _solve(
    px: np.ndarray,
    pts: np.ndarray,
    c: np.ndarray,
    f0: float,
    solve_focal: bool,
    init: np.ndarray | None = None,
    focal_prior: tuple[float, float] | None = None,
    collect: list[tuple[np.ndarray, float]] | None = None,
) -> tuple[np.ndarray, float, float]:
    """Best (rvec|tvec, f_px, cost) over several initialisations; with ``solve_focal`` and ``focal_prior``
    (f_px, relative sigma) the focal is the maximum a posteriori estimate (the cost includes the prior term).
    ``collect`` receives every initialisation's optimum (rvec|tvec, f_px)."""

    def res_focal(x: np.ndarray) -> np.ndarray:
        return np.concatenate([_residuals(x, pts, px, c, None), _focal_prior_residual(float(x[6]), focal_prior)])

    planar = _is_planar(pts)
    focal_inits = [f0]
    if solve_focal:
        f_dlt = _dlt_focal(pts, px, c)
        if f_dlt is not None and 0.05 * f0 < f_dlt < 20 * f0:
            focal_inits.append(f_dlt)
    best: tuple[np.ndarray, float, float] | None = None

    def run(p0: np.ndarray, f_init: float) -> None:
        nonlocal best
        if solve_focal:
            x0 = np.concatenate([p0, [np.log(f_init)]])
            sol = least_squares(res_focal, x0, method="lm", x_scale="jac", max_nfev=400)
            f = float(np.exp(np.clip(sol.x[6], -20.0, 20.0)))
        else:
            sol = least_squares(_residuals, p0, method="lm", args=(pts, px, c, f_init), x_scale="jac", max_nfev=400)
            f = f_init
        if collect is not None:
            collect.append((sol.x[:6].copy(), f))
        if best is None or sol.cost < best[2]:
            best = (sol.x[:6].copy(), f, float(sol.cost))

    if init is not None:
        run(init, f0)
    else:
        for f_init in focal_inits:
            K = np.array([[f_init, 0, c[0]], [0, f_init, c[1]], [0, 0, 1.0]])
            for p0 in _pnp_inits(pts, px, K, planar):
                run(p0, f_init)
        # If nothing fits well, also start from poses that put every point behind the camera (PnP on the
        # point-reflected model, translation negated): if those fit best, the clicks are reported as behind.
        if best is None or _rms(_residuals(best[0], pts, px, c, best[1])) > 2.0:
            for f_init in focal_inits:
                K = np.array([[f_init, 0, c[0]], [0, f_init, c[1]], [0, 0, 1.0]])
                for p in _pnp_inits(-pts, px, K, planar):
                    run(np.concatenate([p[:3], -p[3:]]), f_init)
    if best is None:
        raise DegenerateAnchors("no pose could be solved from these clicks")
    return best


def solve_anchor(
    pixels_px,
    points_in_world,
    width_px: int,
    height_px: int,
    focal_px: float | None = None,
    solve_focal: bool | None = None,
    min_outlier_px: float | None = None,
    solve_distortion: bool | None = None,
    solve_k2: bool = False,
    focal_prior_sigma: float | None = FOCAL_PRIOR_SIGMA,
) -> AnchorSolution:
    """Solve a camera from clicks: pixels (N, 2) OpenCV convention, world points (N, 3) in model units.

    ``focal_px`` is the prior (EXIF/user), else a 50 degree horizontal FOV. ``solve_focal``: None = with >= 6
    non-coplanar clicks solve it: freely without a prior; with a prior, as the maximum a posteriori estimate
    under a log-normal prior of relative sigma ``focal_prior_sigma`` (clicks spread in depth and over the image
    move it; clicks that leave focal and distance ambiguous keep it near the prior; None = the old rule: keep
    the prior unless solving freely halves the squared error); a prior the clicks contradict (a free solve halves
    the squared error of the MAP solve) is dropped. True forces a free solve (needs >= 6 non-coplanar clicks);
    False keeps the prior.
    ``min_outlier_px`` (default 0.5% of the width, at least 3 px) is the smallest leave-one-out error flagged.
    ``solve_distortion``: None = estimate radial k1 (and k2 with ``solve_k2``) after the pinhole solve when the
    inlier clicks constrain it (>= 8 non-coplanar clicks spread over the image; weak zero prior, sigma 0.1)
    and it lowers the squared error significantly (> 9 noise variances per parameter);
    False = the paper's k1 = k2 = 0; True forces it. Leave-one-out mis-click detection runs on the pinhole model.
    Raises :class:`DegenerateAnchors` with a reason for unusable input.
    """
    px, pts = _validate(pixels_px, points_in_world)
    if width_px <= 0 or height_px <= 0:
        raise DegenerateAnchors(f"bad image size {width_px}x{height_px}")
    if focal_px is not None and not (np.isfinite(focal_px) and focal_px > 0):
        raise DegenerateAnchors(f"focal prior must be a positive number, got {focal_px}")
    f0 = float(focal_px) if focal_px is not None else float(cam.focal_from_fov(width_px, DEFAULT_FOV_DEG))
    c = np.array([(width_px - 1) / 2.0, (height_px - 1) / 2.0])
    # Gross mis-clicks by consensus (RANSAC within CONSENSUS_FRAC of the width: a lens's distortion stays below it,
    # then a robust fit with distortion); where it cannot decide, one at a time by leave-one-out below.
    floor = min_outlier_px if min_outlier_px is not None else max(3.0, 0.005 * width_px)
    decided = _consensus_outliers(
        px,
        pts,
        c,
        f0,
        focal_px is not None and solve_focal is not True,
        CONSENSUS_FRAC * width_px,
        floor,
    )
    pre = decided[0] if decided is not None else np.zeros(len(px), bool)
    px_s, pts_s = px[~pre], pts[~pre]
    can_solve_focal = len(px_s) >= MIN_CLICKS_FOR_FOCAL and not _is_planar(pts_s)
    if solve_focal and not can_solve_focal:
        raise DegenerateAnchors(
            f"solving the focal needs >= {MIN_CLICKS_FOR_FOCAL} non-coplanar clicks, got {len(px)}"
            + (" coplanar" if _is_planar(pts) else "")
        )
    starts: list[tuple[np.ndarray, float]] = []  # every local optimum the solves reached (for the ambiguity test)
    params, f, cost = _solve(px_s, pts_s, c, f0, bool(solve_focal), collect=starts)
    do_focal = bool(solve_focal)
    prior: tuple[float, float] | None = None
    prior_rejected = False
    if solve_focal is None and can_solve_focal:
        # Auto: without a prior always solve the focal. With a prior, focal and depth trade off for narrow fields
        # of view and clicks bunched on a distant building, so the prior is weighed against the clicks (MAP).
        # A prior the clicks contradict (a free solve halves the clicks' squared error) is dropped.
        p_f, f_f, cost_f = _solve(px_s, pts_s, c, f0, True, collect=starts)
        if focal_px is not None and focal_prior_sigma is not None:
            prior = (f0, float(focal_prior_sigma))
            p_m, f_m, _ = _solve(px_s, pts_s, c, f0, True, focal_prior=prior, collect=starts)
            cost_m = 0.5 * float(np.sum(_residuals(p_m, pts_s, px_s, c, f_m) ** 2))
            if cost_f < 0.5 * cost_m:
                prior = None
                prior_rejected = True
            else:
                p_f, f_f = p_m, f_m
            params, f, do_focal = p_f, f_f, True
        elif focal_px is None or cost_f < 0.5 * cost:
            prior_rejected = focal_px is not None
            params, f, do_focal = p_f, f_f, True
    R = cam.rodrigues_to_matrix(params[:3])
    z = pts_s @ R.T[:, 2] + params[5]
    if np.any(z <= 0):
        raise DegenerateAnchors(
            f"{int(np.sum(z <= 0))} clicked model points would be behind the camera; check pixel/point pairing"
        )
    res = _residuals(params, pts_s, px_s, c, f).reshape(-1, 2)
    residuals = np.linalg.norm(res, axis=1)
    rms = float(np.sqrt(np.mean(residuals**2)))
    if rms > 0.1 * width_px:
        raise DegenerateAnchors(
            f"clicks are inconsistent: reprojection RMS {rms:.0f} px (> 10% of the width); check the pairing"
        )

    # Mis-clicks: repeatedly leave out the click whose removal best explains the rest; flag it when the
    # others predict it far worse than they fit themselves. The pose is then solved without flagged clicks.
    n = len(px)
    loo = np.full(n, np.nan)
    outliers = pre.copy()
    if pre.any():  # predicted by the consensus solve without them
        loo[pre] = np.linalg.norm(_residuals(params, pts[pre], px[pre], c, f).reshape(-1, 2), axis=1)
    threshold = decided[1] if decided is not None else floor
    cur_params, cur_f = params, f
    first = True
    # Left to leave-one-out only when the consensus could not decide (few clicks): it tests on the pinhole model,
    # where a distorted lens's corner clicks look like slips.
    while decided is None and n - outliers.sum() - 1 >= MIN_CLICKS + 1:
        active = np.nonzero(~outliers)[0]
        loo_focal = do_focal and len(active) - 1 >= MIN_CLICKS_FOR_FOCAL
        best_i, best_rms, best_err = -1, np.inf, 0.0
        for i in active:
            keep = active[active != i]
            p_i, f_i, _ = _solve(px[keep], pts[keep], c, cur_f, loo_focal, init=cur_params, focal_prior=prior)
            err = float(np.linalg.norm(_residuals(p_i, pts[i : i + 1], px[i : i + 1], c, f_i)))
            if first:
                loo[i] = err
            rms_i = _rms(_residuals(p_i, pts[keep], px[keep], c, f_i))
            if rms_i < best_rms:
                best_i, best_rms, best_err = int(i), rms_i, err
        first = False
        threshold = max(floor, 5.0 * best_rms)
        if best_err <= threshold:
            break
        outliers[best_i] = True
        keep = np.nonzero(~outliers)[0]
        cur_params, cur_f, _ = _solve(
            px[keep], pts[keep], c, f0, do_focal and len(keep) >= MIN_CLICKS_FOR_FOCAL, focal_prior=prior
        )
    if outliers.any():
        params, f = cur_params, cur_f
        R = cam.rodrigues_to_matrix(params[:3])
        residuals = np.linalg.norm(_residuals(params, pts, px, c, f).reshape(-1, 2), axis=1)
        rms = float(np.sqrt(np.mean(residuals[~outliers] ** 2)))

    k1 = k2 = 0.0
    keep = ~outliers
    do_dist = (
        bool(solve_distortion)
        if solve_distortion is not None
        else _distortion_constrained(px[keep], pts[keep], width_px, height_px)
    )
    if do_dist:
        p_d, f_d, k1_d, k2_d = _refine_distortion(
            params, f, pts[keep], px[keep], c, do_focal, solve_k2, focal_prior=prior
        )
        res_d = np.linalg.norm(_distorted_residuals(p_d, pts, px, c, f_d, k1_d, k2_d).reshape(-1, 2), axis=1)
        # Keep the distortion only when it explains significantly more than noise (in auto mode): the drop in
        # squared error must exceed 9 noise variances per added parameter (variance from the distorted fit,
        # at least (0.5 px)^2), so clicks on an undistorted lens keep k1 = 0 instead of fitting their noise.
        n_par = 6 + int(do_focal) + (2 if solve_k2 else 1)
        sse0, sse1 = float(np.sum(residuals[keep] ** 2)), float(np.sum(res_d[keep] ** 2))
        var = max(sse1 / max(2 * int(keep.sum()) - n_par, 1), 0.25)
        if solve_distortion or sse0 - sse1 > 9.0 * var * (n_par - 6 - int(do_focal)):
            params, f, k1, k2, residuals = p_d, f_d, k1_d, k2_d, res_d
            R = cam.rodrigues_to_matrix(params[:3])
            rms = float(np.sqrt(np.mean(residuals[keep] ** 2)))
        else:
            do_dist = False

    camera_from_world = cam.rigid(R, params[3:6])
    ambiguous = _ambiguous_poses(starts, pts[keep], px[keep], c, R, rms)
    return AnchorSolution(
        intrinsics=cam.centered_intrinsics(width_px, height_px, f, k1, k2),
        world_from_camera=cam.invert_rigid(camera_from_world),
        residuals_px=residuals,
        rms_px=rms,
        focal_solved=do_focal,
        outlier_mask=outliers,
        loo_errors_px=loo,
        outlier_threshold_px=threshold,
        distortion_solved=do_dist,
        focal_prior_rejected=prior_rejected,
        ambiguous=ambiguous,
    )


def _ambiguous_poses(
    starts: list[tuple[np.ndarray, float]], pts: np.ndarray, px: np.ndarray, c: np.ndarray, R: np.ndarray, rms: float
) -> list[tuple[np.ndarray, float]]:
    """Local optima among ``starts`` (rvec|tvec, f) that fit the clicks ``px`` (N, 2) of ``pts`` (N, 3) within
    ``max(AMBIGUOUS_RMS_PX, AMBIGUOUS_RMS_RATIO * rms)`` (pinhole), with every point in front, and whose rotation is
    more than ``AMBIGUOUS_TURN_DEG`` from the solution's ``R``: (world_from_camera, f_px), one per direction."""
    out: list[tuple[np.ndarray, float]] = []
    limit = max(AMBIGUOUS_RMS_PX, AMBIGUOUS_RMS_RATIO * rms)
    for x, f in starts:
        R_alt = cam.rodrigues_to_matrix(x[:3])
        if cam.rotation_angle_deg(R_alt, R) <= AMBIGUOUS_TURN_DEG:
            continue
        if np.any(pts @ R_alt.T[:, 2] + x[5] <= 0) or _rms(_residuals(x, pts, px, c, f)) > limit:
            continue
        if any(cam.rotation_angle_deg(R_alt, o[0][:3, :3].T) <= AMBIGUOUS_TURN_DEG for o in out):
            continue
        out.append((cam.invert_rigid(cam.rigid(R_alt, x[3:6])), f))
    return out
