"""Pose estimation pieces: constrained PnP refinement, rotation about a known centre, epipolar checks."""

from __future__ import annotations

import cv2
import msgspec
import numpy as np
from scipy.optimize import least_squares

from constructaide import camera as cam
from constructaide.geo import horizontal_distance_m
from nodes.register.config import MapperConfig
from nodes.register.recon import Reconstruction, focal_prior
from schemas.messages import GeoPoint, Intrinsics


def with_focal(intr: Intrinsics, f_px: float) -> Intrinsics:
    """``intr`` with another focal (px)."""
    return msgspec.structs.replace(intr, f_px=float(f_px))


def rays_from_pixels(intr: Intrinsics, world_from_camera: np.ndarray, pixels_px: np.ndarray) -> np.ndarray:
    """Unit viewing rays (N, 3) in world coordinates of pixels (N, 2)."""
    xy = cam.pixels_to_normalized(intr, pixels_px)
    d = np.c_[xy, np.ones(len(xy))]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d @ np.asarray(world_from_camera)[:3, :3].T


def tilt_deg(world_from_camera: np.ndarray) -> float:
    """Angle (deg) between the image's up direction (camera -y) and world up (+z)."""
    up = -np.asarray(world_from_camera)[:3, 1]
    return float(np.degrees(np.arccos(np.clip(up[2] / np.linalg.norm(up), -1.0, 1.0))))


def rotation_deviation(
    this_from_other: np.ndarray, intr_other: Intrinsics, cx_px: float, cy_px: float
) -> tuple[float, float]:
    """How far a pixel homography (other -> this) is from a pure rotation + zoom about a common camera centre.

    For ``H = K_this R K_other^-1`` with square pixels and principal point (cx, cy) of this image, the rows of
    ``H K_other`` minus the principal-point terms are ``f_this`` times orthonormal rows. Returns the implied focal
    of this image (px) and the deviation (0 for an exact rotation: relative norm mismatch and cosines of the angles
    between the rows). A plane seen from two different centres gives a clearly non-zero deviation.
    """
    M = np.asarray(this_from_other, np.float64) @ cam.K_matrix(intr_other)
    r3 = M[2]
    n3 = np.linalg.norm(r3)
    if n3 < 1e-15:
        return float("nan"), float("inf")
    r1 = M[0] - cx_px * r3
    r2 = M[1] - cy_px * r3
    n1, n2 = np.linalg.norm(r1), np.linalg.norm(r2)
    f1, f2 = n1 / n3, n2 / n3
    f = 0.5 * (f1 + f2)
    dev = max(
        abs(f1 - f2) / max(float(f), 1e-12),
        abs(r1 @ r2) / (n1 * n2 + 1e-18),
        abs(r1 @ r3) / (n1 * n3 + 1e-18),
        abs(r2 @ r3) / (n2 * n3 + 1e-18),
    )
    return float(f), float(dev)


def rotation_from_homography(
    this_from_other: np.ndarray, intr_other: Intrinsics, intr_this: Intrinsics, other_from_world: np.ndarray
) -> np.ndarray:
    """Camera-from-world rotation (3, 3) of this image from a rotation homography (other pixels -> this pixels):
    ``H ~ K_this R_rel K_other^-1``, ``R_rel`` projected on the rotations, times the other's rotation (3, 3)."""
    M = np.linalg.inv(cam.K_matrix(intr_this)) @ np.asarray(this_from_other, np.float64) @ cam.K_matrix(intr_other)
    U, _, Vt = np.linalg.svd(M / np.cbrt(np.linalg.det(M)))
    R_rel = U @ Vt
    if np.linalg.det(R_rel) < 0:
        R_rel = -R_rel
    return R_rel @ np.asarray(other_from_world)[:3, :3]


def _rot_residuals(params: np.ndarray, rays_cam0: np.ndarray, px: np.ndarray, intr: Intrinsics, solve_f: bool):
    R = cam.rodrigues_to_matrix(params[:3])
    f = float(np.exp(params[3])) if solve_f else intr.f_px
    d = rays_cam0 @ R.T
    z = np.where(d[:, 2] > 1e-6, d[:, 2], 1e-6)
    xy = cam.distort_normalized(d[:, :2] / z[:, None], intr.k1, intr.k2)
    return (xy * np.array([f, f * intr.fy_over_fx]) + np.array([intr.cx_px, intr.cy_px]) - px).ravel()


def fit_rotation_about_centre(
    rays_in_world: np.ndarray,
    pixels_px: np.ndarray,
    intr: Intrinsics,
    camera_from_world_rotation0: np.ndarray,
    solve_focal: bool = True,
    focal_prior: tuple[float, float] | None = None,
) -> tuple[np.ndarray, Intrinsics, np.ndarray]:
    """Camera rotation (and focal) about a known centre from rays (N, 3, world, unit) seen at pixels (N, 2); the
    lens distortion, principal point and aspect are ``intr``'s. Levenberg-Marquardt from
    ``camera_from_world_rotation0`` (3, 3) and ``intr.f_px``; ``focal_prior`` (f px, relative sigma) holds the focal
    near a prior. Returns the ``camera_from_world`` rotation (3, 3), the intrinsics with the new focal and
    per-point residuals (N,) in px."""
    R0 = np.asarray(camera_from_world_rotation0, np.float64)
    rays_cam0 = rays_in_world @ R0.T
    x0 = np.zeros(4 if solve_focal else 3)
    if solve_focal:
        x0[3] = np.log(intr.f_px)

    def res(x: np.ndarray) -> np.ndarray:
        r = _rot_residuals(x, rays_cam0, pixels_px, intr, solve_focal)
        if solve_focal and focal_prior is not None:
            r = np.concatenate([r, [(x[3] - np.log(focal_prior[0])) / focal_prior[1]]])
        return r

    sol = least_squares(res, x0, method="lm", x_scale="jac", max_nfev=200)
    R = cam.rodrigues_to_matrix(sol.x[:3]) @ R0
    f = float(np.exp(sol.x[3])) if solve_focal else intr.f_px
    r = _rot_residuals(sol.x, rays_cam0, pixels_px, intr, solve_focal).reshape(-1, 2)
    return R, with_focal(intr, f), np.linalg.norm(r, axis=1)


def _pose_residuals(params: np.ndarray, pts: np.ndarray, px: np.ndarray, intr: Intrinsics, solve_f: bool):
    f = float(np.exp(params[6])) if solve_f else intr.f_px
    return (project_pose(intr, params[:3], params[3:6], f, pts) - px).ravel()


def refine_pose_focal(
    points_in_world: np.ndarray,
    pixels_px: np.ndarray,
    intr: Intrinsics,
    world_from_camera: np.ndarray,
    solve_focal: bool = True,
    robust_px: float | None = 2.0,
) -> tuple[np.ndarray, Intrinsics, np.ndarray]:
    """Refinement of a 6-DOF pose (and focal) on 2D-3D correspondences (N, 3) <-> (N, 2); ``robust_px`` sets a
    soft-L1 loss scale (None: plain least squares). Returns ``world_from_camera`` (4, 4), intrinsics and per-point
    residuals (N,) in px."""
    T = cam.invert_rigid(np.asarray(world_from_camera, np.float64))
    x0 = np.concatenate([cam.matrix_to_rodrigues(T[:3, :3]), T[:3, 3]] + ([[np.log(intr.f_px)]] if solve_focal else []))
    args = (points_in_world, pixels_px, intr, solve_focal)
    if robust_px is None:
        sol = least_squares(_pose_residuals, x0, method="lm", args=args, x_scale="jac")
    else:
        sol = least_squares(
            _pose_residuals, x0, method="trf", loss="soft_l1", f_scale=robust_px, args=args, x_scale="jac", max_nfev=50
        )
    R = cam.rodrigues_to_matrix(sol.x[:3])
    f = float(np.exp(sol.x[6])) if solve_focal else intr.f_px
    res = _pose_residuals(sol.x, points_in_world, pixels_px, intr, solve_focal).reshape(-1, 2)
    return cam.invert_rigid(cam.rigid(R, sol.x[3:6])), with_focal(intr, f), np.linalg.norm(res, axis=1)


def project_pose(intr: Intrinsics, rvec: np.ndarray, t: np.ndarray, f: float, pts: np.ndarray) -> np.ndarray:
    R = cam.rodrigues_to_matrix(rvec)
    p = pts @ R.T + t
    xy = p[:, :2] / np.maximum(p[:, 2:3], 1e-9)
    r2 = np.sum(xy * xy, axis=1, keepdims=True)
    xy = xy * (1 + intr.k1 * r2 + intr.k2 * r2 * r2)
    return xy * np.array([f, f * intr.fy_over_fx]) + np.array([intr.cx_px, intr.cy_px])


def solve_pose_epipolar(
    intr: Intrinsics,
    rvec0: np.ndarray,
    t0: np.ndarray,
    points_in_world: np.ndarray,
    pixels_px: np.ndarray,
    click_points_in_world: np.ndarray,
    click_lines: np.ndarray,
    epipolar_weight: float,
    solve_focal: bool,
    loss_scale_px: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The paper's constrained PnP: min over (R, t[, f]) of robust reprojection error of (N, 3) points to their
    pixels plus the distance of projected click model points (K, 3) to their epipolar lines (K, 3)."""

    def res(x: np.ndarray) -> np.ndarray:
        f = float(np.exp(x[6])) if solve_focal else intr.f_px
        r = (project_pose(intr, x[:3], x[3:6], f, points_in_world) - pixels_px).ravel()
        if len(click_lines):
            q = project_pose(intr, x[:3], x[3:6], f, click_points_in_world)
            d = np.sum(q * click_lines[:, :2], axis=1)
            r = np.concatenate([r, epipolar_weight * (d + click_lines[:, 2])])
        return r

    x0 = np.concatenate([rvec0, t0] + ([[np.log(intr.f_px)]] if solve_focal else []))
    sol = least_squares(res, x0, method="trf", loss="soft_l1", f_scale=loss_scale_px, x_scale="jac", max_nfev=100)
    f = float(np.exp(sol.x[6])) if solve_focal else intr.f_px
    return sol.x[:3], sol.x[3:6], f


def horizontal_apart_m(a: GeoPoint | None, b: GeoPoint | None) -> float:
    """Horizontal distance (m) between two GPS positions, NaN when either is missing."""
    if a is None or b is None:
        return float("nan")
    return horizontal_distance_m(a, b)


def epipolar_distances(x_other: np.ndarray, x_this: np.ndarray, this_from_other: np.ndarray) -> np.ndarray:
    """(M,) distance (normalised units of this camera) of matched normalised points ``x_this`` (M, 2) to the
    epipolar lines of their matches ``x_other`` (M, 2) in another camera, under the relative pose
    ``this_from_other`` (4, 4)."""
    T = np.asarray(this_from_other, np.float64)
    t = T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    ln = np.c_[x_other, np.ones(len(x_other))] @ (tx @ T[:3, :3]).T
    return np.abs(np.sum(ln[:, :2] * x_this, axis=1) + ln[:, 2]) / np.maximum(np.linalg.norm(ln[:, :2], axis=1), 1e-12)


def epipolar_agreement(
    x_other: np.ndarray, x_this: np.ndarray, this_from_other: np.ndarray, f_px: float, thr_px: float
) -> tuple[int, int]:
    """Of matched normalised points (M, 2) in another camera and in this one, how many lie within ``thr_px``
    (this image's px, ``f_px``) of their epipolar lines under the relative pose ``this_from_other`` (4, 4): (agreeing,
    counted). Cameras sharing a centre have no epipolar geometry: nothing is counted."""
    T = np.asarray(this_from_other, np.float64)
    if np.linalg.norm(T[:3, 3]) < 1e-9 * max(1.0, float(np.abs(T[:3, :3]).max())):
        return 0, 0
    d = epipolar_distances(x_other, x_this, T)
    return int(np.sum(d * f_px < thr_px)), len(x_this)


def agreement_partners(recon: Reconstruction, idx: int, max_gps_apart_m: float | None = None) -> list[int]:
    """Registered images whose verified matches with image ``idx`` test a candidate pose of it: every registered
    image paired with it, except that a fixed camera with registered frames of its own is checked against those
    only, and a photo with GPS against the photos within ``max_gps_apart_m`` of it when there are any."""
    partners = [j for j in recon.registered_indices() if j != idx and recon.pair(j, idx) is not None]
    im = recon.images[idx]
    own = im.camera_id
    if own is not None and any(recon.images[j].camera_id == own for j in partners):
        # A fixed camera's own earlier frames overlap its view for sure; other cameras' pairs may be matches of
        # repeated texture only, which no pose explains.
        return [j for j in partners if recon.images[j].camera_id == own]
    if max_gps_apart_m is not None and im.gps is not None:
        # Photos whose GPS positions lie further apart than a view of the site spans share repeated texture (the
        # same print on two sides of a site), not the same surfaces: their pairs do not count.
        near = [j for j in partners if not horizontal_apart_m(im.gps, recon.images[j].gps) > max_gps_apart_m]
        return near or partners
    return partners


def pose_pair_agreement(
    recon: Reconstruction,
    idx: int,
    intr: Intrinsics,
    world_from_camera: np.ndarray,
    thr_px: float,
    max_gps_apart_m: float | None = None,
) -> float:
    """Fraction of the verified matches between image ``idx`` and registered images (:func:`agreement_partners`)
    whose epipolar distance (px, in image ``idx``) under the candidate pose is below ``thr_px`` (1.0 without such
    pairs; pairs sharing the camera centre are not counted). A pose fitted to matches on repeated texture (the
    same lettering on two sides of a site) disagrees with the other matches."""
    n_ok, n_all = 0, 0
    this_from_world = cam.invert_rigid(world_from_camera)
    partners = agreement_partners(recon, idx, max_gps_apart_m)
    for j in partners:
        ok, n = _pair_agreement(recon, j, idx, intr, this_from_world, thr_px)
        n_ok, n_all = n_ok + ok, n_all + n
    return n_ok / n_all if n_all else 1.0


def _pair_agreement(
    recon: Reconstruction, j: int, idx: int, intr: Intrinsics, this_from_world: np.ndarray, thr_px: float
) -> tuple[int, int]:
    """(agreeing, counted) verified matches of registered image ``j`` with image ``idx`` (:func:`epipolar_agreement`
    under the candidate ``this_from_world``); (0, 0) without a pair."""
    p = recon.pair(j, idx)
    if p is None:
        return 0, 0
    m, _ = p
    o = recon.images[j]
    xj = cam.pixels_to_normalized(o.camera, o.features.keypoints_px[m[:, 0]].astype(np.float64))
    xi = cam.pixels_to_normalized(intr, recon.images[idx].features.keypoints_px[m[:, 1]].astype(np.float64))
    return epipolar_agreement(xj, xi, this_from_world @ o.pose, intr.f_px, thr_px)


def fixed_partners(recon: Reconstruction, idx: int, min_matches: int = 0) -> list[int]:
    """Registered fixed cameras' frames sharing at least ``min_matches`` verified matches with image ``idx``."""
    out = []
    for j in recon.registered_indices():
        p = recon.pair(j, idx) if j != idx and recon.images[j].camera_id is not None else None
        if p is not None and len(p[0]) >= min_matches:
            out.append(j)
    return out


def best_pair_agreement(
    recon: Reconstruction, idx: int, intr: Intrinsics, world_from_camera: np.ndarray, thr_px: float
) -> tuple[int, str]:
    """The most verified matches one registered fixed camera's frame (:func:`fixed_partners`) shares with image
    ``idx`` that lie within ``thr_px`` (px, in image ``idx``) of their epipolar lines under the candidate pose, and
    that frame's name ("" without pairs). Phone photos do not vouch for each other: two photos of one visit share
    the hoarding print's repeats, which agree with wrong poses by the hundred (BENCHMARKS 'phones found by the
    model')."""
    best, name = 0, ""
    this_from_world = cam.invert_rigid(world_from_camera)
    for j in fixed_partners(recon, idx):
        ok, _n = _pair_agreement(recon, j, idx, intr, this_from_world, thr_px)
        if ok > best:
            best, name = ok, recon.images[j].name
    return best, name


def pair_rotation(recon: Reconstruction, a: int, b: int, intr_b: Intrinsics, cfg: MapperConfig) -> np.ndarray | None:
    """Rotation ``b_from_a`` (3, 3) of images ``a`` (registered) and ``b`` (intrinsics ``intr_b``) from their
    verified matches alone: the pair's fundamental matrix made essential, decomposed with the cheirality test.
    None without a pair of at least 8 matches."""
    p = recon.pair(a, b)
    if p is None or len(p[0]) < 8:
        return None
    m, F = p
    ia = recon.images[a]
    Ka, Kb = cam.K_matrix(ia.camera), cam.K_matrix(intr_b)
    xa = cam.pixels_to_normalized(ia.camera, ia.features.keypoints_px[m[:, 0]].astype(np.float64))
    xb = cam.pixels_to_normalized(intr_b, recon.images[b].features.keypoints_px[m[:, 1]].astype(np.float64))
    E = Kb.T @ F @ Ka
    _, R, _, _ = cv2.recoverPose(E, xa, xb, np.eye(3))
    return np.asarray(R, np.float64)


def pair_rotation_agreement(
    recon: Reconstruction, idx: int, intr: Intrinsics, world_from_camera: np.ndarray, cfg: MapperConfig
) -> tuple[float, int]:
    """Rotation test of a candidate pose of image ``idx``: over its partners (:func:`agreement_partners`) with at
    least ``cfg.rotation_check_min_matches`` verified matches, the match-weighted fraction whose pair geometry's
    own rotation (:func:`pair_rotation`) lies within ``cfg.rotation_check_max_deg`` of the rotation the candidate
    gives, and how many pairs were counted ((1.0, 0) without any). Epipolar distances alone do not see a pose
    fitted to matches on one repeated planar print: a plane's matches fit many epipolar geometries; the relative
    rotation of the pairs does."""
    this_from_world = cam.invert_rigid(world_from_camera)
    w_ok, w_all, n = 0.0, 0.0, 0
    for j in agreement_partners(recon, idx, cfg.agreement_max_gps_apart_m):
        p = recon.pair(j, idx)
        if p is None or len(p[0]) < cfg.rotation_check_min_matches:
            continue
        R_e = pair_rotation(recon, j, idx, intr, cfg)
        if R_e is None:
            continue
        R_c = (this_from_world @ recon.images[j].pose)[:3, :3]
        ang = float(np.degrees(np.arccos(np.clip((np.trace(R_e.T @ R_c) - 1.0) / 2.0, -1.0, 1.0))))
        w = float(len(p[0]))
        w_all += w
        w_ok += w * (ang <= cfg.rotation_check_max_deg)
        n += 1
    return (w_ok / w_all if w_all else 1.0), n


def relative_rotation_deg(recon: Reconstruction, a: int, b: int, cfg: MapperConfig) -> float:
    """Rotation angle (deg) between the cameras of images ``a`` and ``b`` from their verified matches: the pair's
    fundamental matrix made essential with each image's pinhole matrix (registered: its intrinsics without
    distortion; else its focal prior and a centred principal point), decomposed with the cheirality test. NaN
    without a pair."""
    p = recon.pair(a, b)
    if p is None or len(p[0]) < 8:
        return float("nan")
    m, F = p
    K, xy = [], []
    for i, col in ((a, 0), (b, 1)):
        im = recon.images[i]
        intr = im.intrinsics
        if intr is None:
            intr = cam.centered_intrinsics(im.width_px, im.height_px, focal_prior(im, cfg))
        Ki = cam.K_matrix(intr)
        px = im.features.keypoints_px[m[:, col]].astype(np.float64)
        K.append(Ki)
        xy.append((px - Ki[:2, 2]) / np.diag(Ki)[:2])
    E = K[1].T @ F @ K[0]
    _, R, _, _ = cv2.recoverPose(E, xy[0], xy[1], np.eye(3))
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def focal_from_fundamental(F_u_from_r: np.ndarray, K_ref: np.ndarray, width_px: int, height_px: int) -> float | None:
    """Focal (px) of an uncalibrated image from its fundamental matrix with a calibrated one (``x_u^T F x_r = 0``,
    reference pinhole ``K_ref``; a centred principal point assumed): the focal whose essential matrix
    ``K_u^T F K_ref`` is closest to having two equal singular values (a search over 0.3-3 widths, then refined).
    None when the pair does not determine it (no clear minimum)."""
    F = np.asarray(F_u_from_r, np.float64)
    c = np.array([(width_px - 1) / 2.0, (height_px - 1) / 2.0])

    def cost(f: float) -> float:
        K = np.array([[f, 0.0, c[0]], [0.0, f, c[1]], [0.0, 0.0, 1.0]])
        sv = np.linalg.svd(K.T @ F @ K_ref, compute_uv=False)
        return float((sv[0] - sv[1]) / max(sv[0], 1e-18))

    fs = np.geomspace(0.3 * width_px, 3.0 * width_px, 200)
    costs = np.array([cost(f) for f in fs])
    k = int(np.argmin(costs))
    if k in (0, len(fs) - 1) or costs[k] > 0.5 * float(np.median(costs)):
        return None
    lo, hi = fs[k - 1], fs[k + 1]
    for _ in range(40):  # golden-section refinement
        m1, m2 = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
        if cost(m1) < cost(m2):
            hi = m2
        else:
            lo = m1
    return float(0.5 * (lo + hi))
