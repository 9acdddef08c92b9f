"""Registration steps of the incremental mapper: anchors, homography transfer, relative-pose bootstrap, PnP."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np

from constructaide import camera as cam
from constructaide.anchorsolve import AnchorSolution, DegenerateAnchors, solve_anchor
from nodes.register.config import MapperConfig
from nodes.register.features import (
    homography_inlier_ratio,
)
from nodes.register.gps import gps_check
from nodes.register.pose import (
    fit_rotation_about_centre,
    focal_from_fundamental,
    horizontal_apart_m,
    pair_rotation_agreement,
    pose_pair_agreement,
    project_pose,
    rays_from_pixels,
    relative_rotation_deg,
    rotation_deviation,
    rotation_from_homography,
    solve_pose_epipolar,
    tilt_deg,
    with_focal,
)
from nodes.register.recon import (
    Clicks,
    ImageState,
    Reconstruction,
    anchor_focal_kwargs,
    focal_prior,
    focal_sigma_frac,
    obs_threshold_px,
)
from schemas.messages import Intrinsics

PoseCheck = Callable[[int, Intrinsics, np.ndarray], str]
"""Why a candidate automatic pose (image index, its lens, world_from_camera (4, 4)) contradicts what the photo shows
("" when it does not; :class:`nodes.register.modelsearch.OutlineCheck`)."""


def register_anchor(recon: Reconstruction, idx: int, clicks: Clicks, cfg: MapperConfig) -> AnchorSolution:
    """Solve image ``idx`` from user clicks; marks it an anchor. Raises DegenerateAnchors."""
    im = recon.images[idx]
    px, world = np.asarray(clicks[0], float), np.asarray(clicks[1], float)
    sol = solve_anchor(
        px, world, im.width_px, im.height_px, solve_distortion=cfg.anchor_distortion, **anchor_focal_kwargs(im, cfg)
    )
    n_out = int(sol.outlier_mask.sum())
    if n_out and len(px) - n_out < cfg.min_anchor_inliers:
        # A few clicks of which some are wrong leave the camera ambiguous (several poses fit 4-5 points).
        raise DegenerateAnchors(
            f"{n_out} of {len(px)} clicks look mis-placed and {len(px) - n_out} are not enough to be sure of the "
            f"camera (at least {cfg.min_anchor_inliers}); please check or add clicks"
        )
    if sol.ambiguous:
        sol = disambiguate_anchor(recon, idx, sol, px, world, cfg)
    im.intrinsics, im.world_from_camera = sol.intrinsics, sol.world_from_camera
    im.status, im.method, im.anchor = "anchor", "anchor", sol
    im.lens_held = False
    im.solved_focal_px = sol.intrinsics.f_px if sol.focal_solved else None
    im.focal_prior_rejected = sol.focal_prior_rejected
    im.clicks, im.click_inliers = (px, world), ~sol.outlier_mask
    im.click_sigma_px = 1.0
    im.num_inliers = int(np.sum(~sol.outlier_mask))
    im.rms_px = sol.rms_px
    im.message = f"{len(px)} clicks, rms {sol.rms_px:.2f} px" + (f", {n_out} flagged as mis-clicks" if n_out else "")
    return sol


def disambiguate_anchor(
    recon: Reconstruction, idx: int, sol: AnchorSolution, px: np.ndarray, world: np.ndarray, cfg: MapperConfig
) -> AnchorSolution:
    """The one of the cameras the clicks of image ``idx`` cannot tell apart (``sol`` and ``sol.ambiguous``, e.g.
    three distinct clicked points and their mirrored solution) that the photo's GPS agrees with, when GPS refuses
    the others (:func:`gps_check` against the registered photos). Raises DegenerateAnchors (a request for more
    clicks, saying why) when GPS cannot decide."""
    im = recon.images[idx]
    cands = [(sol.world_from_camera, sol.intrinsics.f_px), *sol.ambiguous]
    why = [gps_check(recon, idx, T, cfg) for T, _ in cands]
    agree = [k for k, w in enumerate(why) if not w]
    if len(agree) == 1 and any(why):
        k = agree[0]
        if k == 0:
            return sol
        T, f = cands[k]
        intr = cam.centered_intrinsics(im.width_px, im.height_px, f)
        proj, _ = cam.project_points(intr, cam.invert_rigid(T), world)
        res = np.linalg.norm(proj - px, axis=1)
        rms = float(np.sqrt(np.mean(res[~sol.outlier_mask] ** 2)))
        return replace(sol, intrinsics=intr, world_from_camera=T, residuals_px=res, rms_px=rms, ambiguous=[])
    gps = "GPS cannot decide" if not any(why) else "GPS agrees with none of them" if not agree else "nor can GPS"
    raise DegenerateAnchors(
        f"the {len(px)} clicks fit {len(cands)} cameras up to {sol.ambiguous_turn_deg:.0f} deg apart ({gps}); "
        "please add clicks spread over the photo, on points at different depths"
    )


def inherited_intrinsics(src: ImageState, im: ImageState, cfg: MapperConfig) -> Intrinsics:
    """Starting intrinsics of image ``im`` seen from (nearly) the viewpoint of registered ``src``: ``src``'s lens
    (distortion, principal point, aspect) when both have the same size and focal prior (one physical camera),
    else a centred pinhole at ``im``'s focal prior."""
    si = src.intrinsics
    same_camera = (si is not None and (si.width_px, si.height_px) == (im.width_px, im.height_px)) and (
        im.focal_prior_px is None
        or src.focal_prior_px is None
        or abs(im.focal_prior_px / src.focal_prior_px - 1) < 0.02
    )
    if same_camera and si is not None:
        return si
    return cam.centered_intrinsics(im.width_px, im.height_px, focal_prior(im, cfg))


def try_homography_transfer(recon: Reconstruction, src: int, idx: int, cfg: MapperConfig) -> bool:
    """Register ``idx`` from registered image ``src`` when one homography explains >= ``homography_min_inlier_ratio``
    of their verified matches and it is a rotation (+ zoom) about a shared centre (paper Sec. 6, same viewpoint):
    rotation and focal fitted about ``src``'s centre on the rays of the matches it explains, the lens inherited
    from ``src`` (:func:`inherited_intrinsics`), the focal under ``idx``'s prior; ``src``'s clicks, warped by the
    homography, go with it as constraints of the adjustments. Returns True when registered."""
    a, im = recon.images[src], recon.images[idx]
    p = recon.pair(src, idx)
    if p is None or not a.registered or len(p[0]) < cfg.homography_min_matches:
        return False
    # The transfer's premise is the same viewpoint; GPS fixes far apart say otherwise (a repeated print, e.g. site
    # hoarding, gives one homography for most matches of two photos taken 50 m apart, and no image test can tell).
    apart = horizontal_apart_m(a.gps, im.gps)
    if cfg.gps_max_homography_distance_m is not None and apart > cfg.gps_max_homography_distance_m:
        im.message = f"homography from {a.name} refused: GPS positions {apart:.0f} m apart"
        return False
    m, _ = p
    thr = max(1.0, cfg.homography_threshold_frac * im.width_px)
    H, ratio = homography_inlier_ratio(a.features.keypoints_px, im.features.keypoints_px, m, thr)
    if H is None or ratio < cfg.homography_min_inlier_ratio:
        return False
    intr0 = inherited_intrinsics(a, im, cfg)
    # A plane (a facade) also gives one homography for most matches from far-apart viewpoints; only rotation
    # (+ zoom) homographies mean the same viewpoint.
    f_h, dev = rotation_deviation(H, a.camera, intr0.cx_px, intr0.cy_px)
    if not dev <= cfg.homography_max_rotation_deviation:
        return False
    intr0 = with_focal(intr0, f_h)
    pk = a.features.keypoints_px[m[:, 0]].astype(np.float64)
    pn = im.features.keypoints_px[m[:, 1]].astype(np.float64)
    good = np.linalg.norm(cv2.perspectiveTransform(pk.reshape(-1, 1, 2), H).reshape(-1, 2) - pn, axis=1) < thr
    if good.sum() < cfg.homography_min_matches:
        return False
    sigma = focal_sigma_frac(im, cfg)
    prior = (focal_prior(im, cfg), float(sigma)) if np.isfinite(sigma) else None
    if prior is not None and abs(np.log(f_h / prior[0])) > 3 * prior[1] + 0.005:
        # The homography measures the zoom against a registered photo (the focal is well determined from the
        # many rays): a prior it contradicts is dropped, as when clicks contradict it.
        prior = None
        im.focal_prior_rejected = True
    T_a = cam.invert_rigid(a.pose)
    rays = rays_from_pixels(a.camera, a.pose, pk)
    R0 = rotation_from_homography(H, a.camera, intr0, T_a)
    R, intr, res = fit_rotation_about_centre(rays[good], pn[good], intr0, R0, True, prior)
    inl = np.nonzero(good)[0][res < thr]
    if len(inl) >= cfg.homography_min_matches:
        R, intr, res = fit_rotation_about_centre(rays[inl], pn[inl], intr, R, True, prior)
    rms = float(np.sqrt(np.mean(res**2))) if len(res) else float("inf")
    if len(inl) < cfg.homography_min_matches or rms > cfg.homography_max_rms_frac * im.width_px:
        im.message = f"homography from {a.name}: rotation about its centre leaves {rms:.1f} px (a moved camera?)"
        return False
    world_from_camera = cam.rigid(R.T, a.pose[:3, 3])
    why = gps_check(recon, idx, world_from_camera, cfg)
    if why:
        im.message = f"homography from {a.name} refused: {why}"
        return False
    im.intrinsics, im.world_from_camera = intr, world_from_camera
    im.status, im.method = "auto", "homography"
    im.centre_source = src if cfg.homography_shares_centre else None
    im.lens_source = src if intr0.k1 == a.camera.k1 and intr0.k2 == a.camera.k2 else None
    im.num_inliers, im.rms_px = len(inl), rms
    n_warped = 0
    if a.clicks is not None:
        keep = a.click_inliers if a.click_inliers is not None else np.ones(len(a.clicks[0]), bool)
        warped = cv2.perspectiveTransform(a.clicks[0][keep].reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
        inside = np.all(np.isfinite(warped), axis=1) & np.all(
            (warped >= -0.5) & (warped <= np.array([im.width_px, im.height_px]) - 0.5), axis=1
        )
        if inside.sum() >= 4:
            im.clicks, im.click_inliers = (warped[inside], a.clicks[1][keep][inside]), np.ones(int(inside.sum()), bool)
            im.click_sigma_px = a.click_sigma_px
            n_warped = int(inside.sum())
    im.message = (
        f"homography from {a.name} ({ratio:.0%} inliers), rotation about its centre on {len(inl)} rays, "
        f"rms {rms:.2f} px, {n_warped} warped clicks"
    )
    return True


def epipolar_constraints(recon: Reconstruction, idx: int) -> tuple[np.ndarray, np.ndarray]:
    """Model points (K, 3) of anchor clicks and their epipolar lines (K, 3) in image ``idx`` (normalised so
    a·u + b·v + c is a distance in pixels)."""
    pts, lines = [], []
    for a_idx, a in enumerate(recon.images):
        if a.status != "anchor" or a.clicks is None or a_idx == idx:
            continue
        p = recon.pair(a_idx, idx)
        if p is None:
            continue
        _, F = p  # x_idx^T F x_a = 0
        keep = a.click_inliers if a.click_inliers is not None else np.ones(len(a.clicks[0]), bool)
        x_a = np.c_[a.clicks[0][keep], np.ones(int(keep.sum()))]
        ln = x_a @ F.T
        ln /= np.maximum(np.linalg.norm(ln[:, :2], axis=1, keepdims=True), 1e-12)
        pts.append(a.clicks[1][keep])
        lines.append(ln)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.vstack(pts), np.vstack(lines)


def anchor_request_order(
    recon: Reconstruction, unreg: list[int], counts: dict[int, int], cfg: MapperConfig
) -> list[int]:
    """Unregistered images in the order anchor clicks are asked for: fewest matched tracks first (the paper). While
    nothing is triangulated yet (every image ties at zero: the second anchor, which fixes the model frame with the
    first), the image most strongly linked to a registered image goes first: over registered images sharing
    >= ``cfg.anchor_request_min_shared_matches`` verified matches, the largest matches x sin^2 of the relative
    rotation (a point's depth precision from two rays grows with the sine of their angle); images without such a
    link last. Other ties in collection order."""
    bootstrap = not np.isfinite(recon.points).all(axis=1).any()
    if cfg.anchor_request_min_shared_matches <= 0 or not bootstrap:
        return sorted(unreg, key=lambda i: counts[i])
    registered = recon.registered_indices()
    strength: dict[int, float] = {}
    for u in unreg:
        scores = [-1.0]
        for r in registered:
            p = recon.pair(r, u)
            if p is not None and len(p[0]) >= cfg.anchor_request_min_shared_matches:
                angle = relative_rotation_deg(recon, r, u, cfg)
                if np.isfinite(angle):
                    scores.append(len(p[0]) * np.sin(np.radians(min(angle, 90.0))) ** 2)
        strength[u] = max(scores)
    return sorted(unreg, key=lambda i: (counts[i], -strength[i]))


def _neighbour_scale_ratios(
    click_px: np.ndarray, click_depth_m: np.ndarray, px: np.ndarray, depth_unit: np.ndarray, radius_px: float, k: int
) -> np.ndarray:
    """Per click (K, 2) with its model depth (K,): the model depth over the median unit depth of the <= ``k``
    nearest of the points (N, 2) px with unit depths (N,) within ``radius_px`` (NaN without at least 3, or when
    their depths spread by more than 5 % about their median: the click is on an edge between surfaces)."""
    out = np.full(len(click_px), np.nan)
    for c, (p, d) in enumerate(zip(click_px, click_depth_m, strict=True)):
        dist = np.linalg.norm(px - p, axis=1)
        near = np.argsort(dist)[:k]
        near = near[dist[near] <= radius_px]
        if len(near) < 3 or d <= 0:
            continue
        z = depth_unit[near]
        zm = float(np.median(z))
        # Neighbours at several depths (the click sits on an edge between surfaces): no ratio from them.
        if zm > 0 and float(np.median(np.abs(z / zm - 1))) <= 0.05:
            out[c] = d / zm
    return out


def _transfer_clicks(
    click_px: np.ndarray, px_a: np.ndarray, px_b: np.ndarray, radius_px: float, max_err_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Clicks (K, 2) of image a carried into image b by a local homography of the nearest matches (px_a (N, 2) ->
    px_b (N, 2)) within ``radius_px``: (pixels (K, 2) in b, ok (K,) bool where >= 8 neighbours fit it within
    ``max_err_px``)."""
    out = np.full((len(click_px), 2), np.nan)
    ok = np.zeros(len(click_px), bool)
    for c, p in enumerate(click_px):
        dist = np.linalg.norm(px_a - p, axis=1)
        near = np.argsort(dist)[:24]
        near = near[dist[near] <= radius_px]
        if len(near) < 8:
            continue
        H, inl = cv2.findHomography(px_a[near], px_b[near], cv2.RANSAC, max_err_px)
        if H is None or inl is None or inl.sum() < 8:
            continue
        q = cv2.perspectiveTransform(p.reshape(1, 1, 2).astype(np.float64), H).reshape(2)
        out[c], ok[c] = q, bool(np.all(np.isfinite(q)))
    return out, ok


def _relative_motions(
    x_r: np.ndarray, x_u: np.ndarray, thr: float, rotation_only_deviation: float
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Candidate motions (R (3, 3), unit t (3,), inlier mask (M,)) from normalised matches (M, 2) of a reference
    and a new image: the essential matrix's (RANSAC, cheirality) and, since a (nearly) planar scene leaves it
    ambiguous, the decompositions of the homography of the matches; none when that homography is a rotation
    (deviation below ``rotation_only_deviation``, :func:`~nodes.register.pose.rotation_deviation`)."""
    out = []
    E, mask = cv2.findEssentialMat(x_r, x_u, np.eye(3), cv2.RANSAC, 0.999, thr)
    if E is not None and E.shape == (3, 3):
        _, R, t, mask = cv2.recoverPose(E, x_r, x_u, np.eye(3), mask=mask)
        out.append((R, t.ravel() / max(float(np.linalg.norm(t)), 1e-12), mask.ravel() > 0))
    H, hmask = cv2.findHomography(x_r, x_u, cv2.RANSAC, thr)
    if H is not None and hmask is not None and hmask.sum() >= 0.5 * len(x_r):
        unit = Intrinsics(width_px=2, height_px=2, f_px=1.0, cx_px=0.0, cy_px=0.0)
        if rotation_deviation(H, unit, 0.0, 0.0)[1] <= rotation_only_deviation:
            return []  # one rotation explains the matches: the same viewpoint, no baseline to measure
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, np.eye(3))
        for R, t in zip(Rs, ts, strict=True):
            n = np.linalg.norm(t)
            if n > 1e-9:
                out.append((R, t.ravel() / n, hmask.ravel() > 0))
    return out


def _rotation_residual_deg(x_a: np.ndarray, x_b: np.ndarray) -> np.ndarray:
    """Angles (M,) in degrees between the rays of normalised matches (M, 2) <-> (M, 2) after the rotation that best
    aligns them (Kabsch on the unit rays, refitted twice without the matches beyond 3x the median + 0.1 deg): what
    no rotation of the camera explains, i.e. the least image motion a baseline must account for."""
    a = np.c_[x_a, np.ones(len(x_a))]
    b = np.c_[x_b, np.ones(len(x_b))]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    keep = np.ones(len(a), bool)
    ang = np.zeros(len(a))
    for _ in range(3):
        U, _s, Vt = np.linalg.svd(b[keep].T @ a[keep])
        R = U @ np.diag([1.0, 1.0, float(np.linalg.det(U @ Vt))]) @ Vt
        ang = np.degrees(np.arccos(np.clip(np.sum((a @ R.T) * b, axis=1), -1, 1)))
        keep = ang <= 3 * np.median(ang) + 0.1
    return ang


def own_camera_frames(recon: Reconstruction, idx: int) -> list[int]:
    """Registered frames of image ``idx``'s fixed camera (none for phones), whether or not they share verified
    matches with it."""
    cam_id = recon.images[idx].camera_id
    if cam_id is None:
        return []
    return [j for j in recon.registered_indices() if j != idx and recon.images[j].camera_id == cam_id]


def try_relative_pose(
    recon: Reconstruction, ref: int, idx: int, cfg: MapperConfig, check: PoseCheck | None = None
) -> bool:
    """Register image ``idx`` from its verified matches with registered image ``ref`` when too few of them reach
    triangulated tracks: the relative motion of the two cameras (:func:`_relative_motions`, ``ref``'s intrinsics,
    ``idx``'s focal prior), ``ref``'s pose held, and the baseline's length from what is known in ``ref``'s view:
    the triangulated points among the matches (their depth over the unit-baseline depth), else ``ref``'s clicks
    (each click's model depth over the unit-baseline depths of the matches around it). The motion whose length
    ratios agree best is taken: the most within ``bootstrap_max_scale_spread`` of each other, at least 3 and
    ``bootstrap_min_scale_agreement`` of them (the wrong motion of a planar scene gives a tilted plane, whose ratios
    drift across the image; a click on an edge or on something in front disagrees alone). The clicks are
    then carried into ``idx`` by local homographies of their neighbouring matches (checked against the pose and
    kept as constraints that hold the baseline in the adjustments). Needs a median ray angle of
    ``bootstrap_min_parallax_deg`` (``bootstrap_min_parallax_deg_own_camera`` between frames of one fixed camera); a
    fixed camera's frame with registered frames of its own camera is placed relative to those only; at most
    ``bootstrap_max_parallax_deg`` (descriptors match across smaller changes of view: more is a motion of wrong
    matches). ``check`` has the last word. Returns True when registered."""
    r, im = recon.images[ref], recon.images[idx]
    p = recon.pair(ref, idx)
    if p is None or len(p[0]) < cfg.bootstrap_min_matches or r.intrinsics is None:
        return False
    if im.camera_id is not None and r.camera_id != im.camera_id and own_camera_frames(recon, idx):
        # A fixed camera's registered frames see from (nearly) its place: a motion to another camera's frame, scaled
        # by that frame's points, is checked against them by rotation only (their pair has no baseline to test), or
        # not at all when the knock left them no verified pair with the frame; such a motion placed a knocked
        # camera 2.7 deg and 3 m off (CI, small site without BIM depth, twice).
        im.message = f"relative pose from {r.name} (another camera) not tried: frames of its own camera are registered"
        return False
    m, _ = p
    px_r = r.features.keypoints_px[m[:, 0]].astype(np.float64)
    px_u = im.features.keypoints_px[m[:, 1]].astype(np.float64)
    intr_u = camera_lens(recon, idx, cfg)
    if not np.isfinite(focal_sigma_frac(im, cfg)) and im.camera_id is None:
        # No focal prior (no EXIF): the pair's fundamental matrix with the calibrated reference gives it.
        f_u = focal_from_fundamental(p[1], cam.K_matrix(r.camera), im.width_px, im.height_px)
        if f_u is not None:
            intr_u = with_focal(intr_u, f_u)
    x_r = cam.pixels_to_normalized(r.intrinsics, px_r)
    x_u = cam.pixels_to_normalized(intr_u, px_u)
    thr = max(cfg.fundamental_threshold_frac * im.width_px / intr_u.f_px, 1e-4)
    T_r = cam.invert_rigid(r.pose)  # ref camera from world
    tracks_all = recon.feature_track[ref][m[:, 0]]
    clicks = None
    if r.clicks is not None:
        keep = r.click_inliers if r.click_inliers is not None else np.ones(len(r.clicks[0]), bool)
        cw = r.clicks[1][keep]
        clicks = (r.clicks[0][keep], cw, (cw @ T_r[:3, :3].T + T_r[:3, 3])[:, 2])
    radius = cfg.bootstrap_click_radius_frac * r.width_px
    own_camera = im.camera_id is not None and r.camera_id == im.camera_id
    min_parallax = cfg.bootstrap_min_parallax_deg_own_camera if own_camera else cfg.bootstrap_min_parallax_deg
    best = None
    why = f"relative pose from {r.name}: no motion with enough matches in front of both cameras"
    motions = _relative_motions(x_r, x_u, thr, cfg.homography_max_rotation_deviation)
    if not motions:
        why = f"relative pose from {r.name}: one rotation explains the matches (the same viewpoint, no baseline)"
    shown = float(np.median(_rotation_residual_deg(x_r, x_u))) * np.pi / 180 * intr_u.f_px
    if motions and shown < cfg.bootstrap_min_translation_frac * im.width_px:
        # A short baseline leaves the motion undetermined: a rotation and a translation trade off, and the lens
        # model's small errors pick among motions degrees apart (a knocked mast camera, 0.56 m at 40 m: a motion
        # 3 deg off, scaled by the clicks to 2 m, passed every other test).
        im.message = (
            f"relative pose from {r.name}: one rotation explains the matches to {shown:.1f} px (median): too "
            "short a baseline to measure"
        )
        return False
    for R, t, inl in motions:
        if inl.sum() < cfg.bootstrap_min_matches // 2:
            continue
        P1 = np.hstack([R, t[:, None]])
        Xh = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), P1, x_r[inl].T, x_u[inl].T)
        X = (Xh[:3] / Xh[3]).T
        front = (X[:, 2] > 0) & (X @ R[2] + t[2] > 0)
        if front.sum() < cfg.bootstrap_min_matches // 2:
            continue
        X, sel = X[front], np.nonzero(inl)[0][front]
        c1 = -R.T @ t
        cosang = np.sum(X * (X - c1), axis=1) / (np.linalg.norm(X, axis=1) * np.linalg.norm(X - c1, axis=1))
        parallax = float(np.median(np.degrees(np.arccos(np.clip(cosang, -1, 1)))))
        if parallax < min_parallax:
            why = f"relative pose from {r.name}: median parallax {parallax:.1f} deg too small (< {min_parallax:g})"
            continue
        if parallax > cfg.bootstrap_max_parallax_deg:
            most = cfg.bootstrap_max_parallax_deg
            why = f"relative pose from {r.name}: median parallax {parallax:.0f} deg (> {most:g}: too wide to match)"
            continue
        # Baseline length: triangulated tracks among the matches, else the clicks.
        tr = tracks_all[sel]
        known = tr >= 0
        known[known] = np.all(np.isfinite(recon.points[tr[known]]), axis=1)
        if (
            not cfg.trust_model_points and known.any()
        ):  # unconfirmed model points: the depth of whatever the model shows
            k = np.nonzero(known)[0]
            known[k] = ~(recon.point_from_model[tr[k]] & ~recon.point_confirmed[tr[k]])
        source = np.zeros(0, np.int64)  # the clicks the ratios come from (none for track points)
        min_points = cfg.bootstrap_min_scale_points_own_camera if own_camera else cfg.bootstrap_min_scale_points
        if known.sum() >= min_points:
            ratios = (recon.points[tr[known]] @ T_r[:3, :3].T + T_r[:3, 3])[:, 2] / X[known, 2]
            how = f"{int(known.sum())} triangulated points"
        elif clicks is not None:
            ratios = _neighbour_scale_ratios(clicks[0], clicks[2], px_r[sel], X[:, 2], radius, 8)
            source = np.nonzero(np.isfinite(ratios))[0]
            ratios = ratios[source]
            how = f"{len(ratios)} clicks"
        else:
            ratios = np.zeros(0)
        if len(ratios) < 3 or not np.all(ratios > 0):
            why = f"relative pose from {r.name}: no known depth in {r.name} to fix the baseline"
            continue
        # The largest set of ratios agreeing within the tolerance (clicks on an edge or on something in front
        # disagree; the wrong motion of a planar scene drifts them all across the image).
        tol = cfg.bootstrap_max_scale_spread
        agree = np.abs(ratios[None, :] / ratios[:, None] - 1) <= tol
        centre = int(np.argmax(agree.sum(1)))
        members = ratios[agree[centre]]
        score = (len(members) / len(ratios), -float(np.std(members / np.median(members))))
        if best is None or score > best[0]:
            used = source[agree[centre]] if len(source) else source
            best = (score, R, t, float(np.median(members)), sel, parallax, how, len(members), len(ratios), used)
    if best is None:
        im.message = why
        return False
    _, R, t, scale, sel, parallax, how, n_agree, n_all, used = best
    if n_agree < max(3, cfg.bootstrap_min_scale_agreement * n_all):
        im.message = (
            f"relative pose from {r.name}: baseline lengths from {how} disagree (only {n_agree} of {n_all} within "
            f"{cfg.bootstrap_max_scale_spread:.0%})"
        )
        return False
    transferred = None
    if clicks is not None and len(used):
        # Only the clicks whose surroundings agreed on the scale are carried (on one surface, a local homography
        # of the matches around them carries them well).
        q, ok = _transfer_clicks(clicks[0][used], px_r[sel], px_u[sel], radius, 2.0)
        if ok.sum() >= 3:
            transferred = (q[ok], clicks[1][used][ok])
    front = sel
    T_u = cam.rigid(R, scale * t) @ T_r  # idx camera from world
    world_from_camera = cam.invert_rigid(T_u)
    if transferred is not None:
        # The carried clicks are an independent check: their model points must land where the matches put them.
        off = cam.median_click_error_px(intr_u, world_from_camera, transferred[0], transferred[1])
        if not off <= cfg.click_check_max_frac * im.width_px:
            im.message = f"relative pose from {r.name} puts the carried clicks {off:.0f} px off (median)"
            return False
    agree = pose_pair_agreement(
        recon, idx, intr_u, world_from_camera, 2 * cfg.pnp_inlier_frac * im.width_px, cfg.agreement_max_gps_apart_m
    )
    if agree < cfg.min_pose_pair_agreement:
        im.message = f"relative pose from {r.name} explains only {agree:.0%} of the verified matches"
        return False
    why = rotation_refusal(recon, idx, intr_u, world_from_camera, cfg)
    if why:
        im.message = f"relative pose from {r.name} refused: {why}"
        return False
    # One registered photo with GPS already checks the baseline's length (the distance between the two centres).
    why = gps_check(recon, idx, world_from_camera, cfg, min_references=1)
    why = why or (check(idx, intr_u, world_from_camera) if check is not None else "")
    if why:
        im.message = f"relative pose from {r.name} refused: {why}"
        return False
    im.intrinsics, im.world_from_camera = intr_u, world_from_camera
    im.status, im.method = "auto", "relative"
    im.num_inliers = len(front)
    if transferred is not None:
        im.clicks, im.click_inliers = transferred, np.ones(len(transferred[0]), bool)
    im.message = f"relative pose from {r.name}: {len(front)} matches, parallax {parallax:.1f} deg, baseline from {how}"
    return True


def camera_lens(recon: Reconstruction, idx: int, cfg: MapperConfig) -> Intrinsics:
    """Starting lens of image ``idx``: that of the latest registered photo of the same fixed camera and size (its
    distortion, principal point, aspect; its focal too unless ``idx`` has a focal prior of its own), else a centred
    pinhole at ``idx``'s focal prior."""
    im = recon.images[idx]
    if im.camera_id is not None:
        for j in range(len(recon.images) - 1, -1, -1):
            o = recon.images[j]
            if j != idx and o.registered and o.camera_id == im.camera_id and o.intrinsics is not None:
                if (o.width_px, o.height_px) == (im.width_px, im.height_px):
                    known = cfg.focal_px is not None or im.focal_prior_px is not None
                    return with_focal(o.intrinsics, focal_prior(im, cfg)) if known else o.intrinsics
    return cam.centered_intrinsics(im.width_px, im.height_px, focal_prior(im, cfg))


def usable_track_matches(recon: Reconstruction, idx: int, cfg: MapperConfig) -> tuple[np.ndarray, np.ndarray]:
    """Features of image ``idx`` (K,) and their tracks (K,) whose points image ``idx`` may be registered on: the
    triangulated ones, and model points (BIM depth) that no second view has confirmed only for a photo of the
    camera that looked them up (a fence or crane in front of the model gives its features the wrong depth; from
    the same centre the depth does not matter) or with ``cfg.trust_model_points``."""
    ft = recon.feature_track[idx]
    feats = np.nonzero(ft >= 0)[0]
    tr = ft[feats]
    ok = np.all(np.isfinite(recon.points[tr]), axis=1)
    doubtful = ok & recon.point_from_model[tr] & ~recon.point_confirmed[tr]
    if doubtful.any() and not cfg.trust_model_points:
        cam_id = recon.images[idx].camera_id
        for k in np.nonzero(doubtful)[0]:
            others = [i for i in recon.track_obs[tr[k]] if i != idx and recon.images[i].registered]
            ok[k] = cam_id is not None and bool(others) and all(recon.images[i].camera_id == cam_id for i in others)
    return feats[ok], tr[ok]


def register_image_pnp(recon: Reconstruction, idx: int, cfg: MapperConfig, check: PoseCheck | None = None) -> bool:
    """Register image ``idx`` from its matches to triangulated tracks: PnP-RANSAC (inliers within
    ``pnp_inlier_frac`` of the width) then the epipolar-constrained refinement; ``check`` has the last word. Returns
    True on success."""
    im = recon.images[idx]
    feats, tr = usable_track_matches(recon, idx, cfg)
    im.num_matched_tracks = len(feats)
    if len(feats) < max(cfg.min_pnp_inliers, 6):
        im.message = f"only {len(feats)} matches to triangulated tracks"
        return False
    obj = recon.points[tr].astype(np.float64)
    img = im.features.keypoints_px[feats].astype(np.float64)
    f0 = focal_prior(im, cfg)
    lens = camera_lens(recon, idx, cfg)
    intr = with_focal(lens, f0)
    K = cam.K_matrix(intr)
    dist = np.array([intr.k1, intr.k2, 0.0, 0.0])  # OpenCV's k1, k2 = the project's radial model
    thr = cfg.pnp_inlier_frac * im.width_px
    best = None
    # Try the prior focal and, if that registers poorly, a few alternatives (a wrong prior breaks RANSAC).
    for f_try in (f0, f0 * 0.7, f0 * 1.4, f0 * 2.0, f0 * 0.5):
        Kt = K.copy()
        Kt[0, 0], Kt[1, 1] = f_try, f_try * intr.fy_over_fx
        try:
            ok_r, rvec, tvec, inl = cv2.solvePnPRansac(
                obj,
                img,
                Kt,
                dist,
                iterationsCount=2000,
                reprojectionError=thr,
                confidence=0.999,
                flags=cv2.SOLVEPNP_SQPNP,
            )
        except cv2.error:  # degenerate points (all nearly on one spot)
            ok_r, rvec, tvec, inl = False, None, None, None
        n_inl = 0 if (not ok_r or inl is None) else len(inl)
        if best is None or n_inl > best[0]:
            best = (n_inl, f_try, rvec, tvec, inl)
        if n_inl >= 0.5 * len(obj):
            break
    assert best is not None
    n_inl, f_try, rvec, tvec, inl = best
    if n_inl < cfg.min_pnp_inliers or rvec is None or tvec is None or inl is None:
        im.message = f"PnP found {n_inl} inliers among {len(obj)} track matches (< {cfg.min_pnp_inliers})"
        return False
    inl = inl.ravel()
    intr = with_focal(lens, f_try)
    cpts, clines = epipolar_constraints(recon, idx)
    rv, tv, f = solve_pose_epipolar(
        intr,
        rvec.ravel(),
        tvec.ravel(),
        obj[inl],
        img[inl],
        cpts,
        clines,
        cfg.epipolar_weight,
        solve_focal=n_inl >= 50 and not np.isfinite(focal_sigma_frac(im, cfg)),
        loss_scale_px=cfg.loss_scale_px,
    )
    intr = with_focal(lens, f)
    proj = project_pose(intr, rv, tv, f, obj)
    err = np.linalg.norm(proj - img, axis=1)
    R = cam.rodrigues_to_matrix(rv)
    z = obj @ R.T[:, 2] + tv[2]
    inliers = (err < thr) & (z > 0)
    if inliers.sum() < max(cfg.min_pnp_inliers, cfg.min_pnp_inlier_fraction * len(obj)):
        im.message = f"refined pose keeps {int(inliers.sum())} of {len(obj)} track matches as inliers"
        return False
    if np.isfinite(focal_sigma_frac(im, cfg)) and abs(f / f0 - 1) > cfg.max_focal_change:
        im.message = f"PnP pose needs a focal of {f:.0f} px, {abs(f / f0 - 1):.0%} off its prior {f0:.0f} px"
        return False
    if cfg.max_tilt_from_upright_deg is not None:
        tilt = tilt_deg(cam.invert_rigid(cam.rigid(R, tv)))
        if tilt > cfg.max_tilt_from_upright_deg:
            im.message = f"PnP pose tilted {tilt:.0f} deg from upright (> {cfg.max_tilt_from_upright_deg:g})"
            return False
    agree = pose_pair_agreement(
        recon, idx, intr, cam.invert_rigid(cam.rigid(R, tv)), 2 * thr, cfg.agreement_max_gps_apart_m
    )
    if agree < cfg.min_pose_pair_agreement:
        im.message = (
            f"PnP pose explains only {agree:.0%} of the verified matches to registered images "
            f"(< {cfg.min_pose_pair_agreement:.0%}; repeated texture?)"
        )
        return False
    world_from_camera = cam.invert_rigid(cam.rigid(R, tv))
    why = rotation_refusal(recon, idx, intr, world_from_camera, cfg) or gps_check(recon, idx, world_from_camera, cfg)
    why = why or (check(idx, intr, world_from_camera) if check is not None else "")
    if why:
        im.message = f"PnP pose ({int(inliers.sum())}/{len(obj)} inliers) refused: {why}"
        return False
    im.intrinsics = intr
    im.world_from_camera = world_from_camera
    im.status, im.method = "auto", "pnp"
    im.num_inliers = int(inliers.sum())
    im.rms_px = float(np.sqrt(np.mean(err[inliers] ** 2)))
    im.message = f"PnP {int(inliers.sum())}/{len(obj)} inliers, {len(clines)} epipolar click constraints"
    # Drop this image's outlier observations from their tracks.
    for fi, t in zip(feats[~inliers], tr[~inliers], strict=True):
        recon.track_obs[t].pop(idx, None)
        recon.feature_track[idx][fi] = -1
    return True


def rotation_refusal(
    recon: Reconstruction, idx: int, intr: Intrinsics, world_from_camera: np.ndarray, cfg: MapperConfig
) -> str:
    """Why a candidate automatic pose of image ``idx`` contradicts the rotations of its strong pairs
    (:func:`pair_rotation_agreement`; "" when it does not or the test is off)."""
    if cfg.min_pair_rotation_agreement is None:
        return ""
    frac, n = pair_rotation_agreement(recon, idx, intr, world_from_camera, cfg)
    if n and frac < cfg.min_pair_rotation_agreement:
        return (
            f"its rotation agrees with only {frac:.0%} (match-weighted) of its {n} strong pairs' own rotations "
            f"(within {cfg.rotation_check_max_deg:g} deg; < {cfg.min_pair_rotation_agreement:.0%}; repeated texture?)"
        )
    return ""


def click_disagreement_px(im: ImageState, clicks: Clicks) -> float:
    """Median distance (px) between clicked pixels and their model points projected under image ``im``'s current
    pose and intrinsics (points behind the camera count as infinitely far)."""
    return cam.median_click_error_px(im.camera, im.pose, clicks[0], clicks[1])


def frame_anchor_order(recon: Reconstruction, anchored: list[int]) -> list[int]:
    """Registered images without clicks, best first as the next anchor for the model frame: the most verified
    matches to an anchor times sin^2 of the angle between their viewing directions (two anchors far apart in
    direction fix the frame's rotation and scale best); images without a pair with an anchor last."""

    def strength(i: int) -> float:
        best = 0.0
        for a in anchored:
            p = recon.pair(a, i)
            if p is not None:
                ang = cam.viewing_angle_deg(recon.images[a].pose, recon.images[i].pose)
                best = max(best, len(p[0]) * np.sin(np.radians(min(ang, 90.0))) ** 2)
        return best

    cands = [i for i in recon.registered_indices() if recon.images[i].status != "anchor"]
    return sorted(cands, key=lambda i: -strength(i))


def bootstrap_next(recon: Reconstruction, unreg: list[int], cfg: MapperConfig, check: PoseCheck | None = None) -> int:
    """Try :func:`try_relative_pose` on (registered, unregistered) pairs, most verified matches first; returns the
    image registered, or -1."""
    reg = recon.registered_indices()
    cands = []
    for u in unreg:
        for r in reg:
            p = recon.pair(r, u)
            if p is not None and len(p[0]) >= cfg.bootstrap_min_matches:
                cands.append((len(p[0]), r, u))
    tried: set[int] = set()
    for _, r, u in sorted(cands, reverse=True):
        if u in tried and len(tried) > 3:
            continue
        tried.add(u)
        if try_relative_pose(recon, r, u, cfg, check):
            return u
    return -1


def add_model_points(recon: Reconstruction, idx: int, points_in_world: np.ndarray) -> int:
    """Give the features (N,) of registered image ``idx`` model points (N, 3) world, NaN rows for none (BIM depth
    at its pose: :func:`nodes.register.bimdepth.points_from_depth`): features without a triangulated track get
    them, on a new one-view track or on their untriangulated one, flagged ``point_from_model`` (held fixed in the
    adjustments, serving other photos once confirmed). Returns how many were added."""
    im = recon.images[idx]
    pts = np.asarray(points_in_world, np.float64).reshape(-1, 3)
    ft = recon.feature_track[idx]
    has = ft >= 0
    has[has] = np.all(np.isfinite(recon.points[ft[has]]), axis=1)
    todo = np.nonzero(~has & np.all(np.isfinite(pts), axis=1))[0]
    if len(todo) == 0:
        return 0
    fresh = todo[ft[todo] < 0]
    first = len(recon.track_obs)
    recon._add_tracks(len(fresh))
    for k, f in enumerate(fresh.tolist()):
        recon.track_obs.append({idx: f})
        ft[f] = first + k
    tr = ft[todo]
    recon.points[tr] = pts[todo]
    recon.point_from_model[tr] = True
    recon.point_confirmed[tr] = False
    if im.colors_rgb_u8 is not None:
        recon.colors[tr] = im.colors_rgb_u8[todo]
    return len(todo)


def implausible(im: ImageState, cfg: MapperConfig) -> str:
    """Why a registered image's camera is implausible ("" when it is not): lens distortion beyond
    ``cfg.max_abs_distortion``, a focal further than ``cfg.max_focal_deviation`` from a trusted prior (EXIF or
    user; not when the image's own clicks contradicted it) or a reprojection RMS above ``cfg.max_rms_frac`` of the
    width."""
    i = im.intrinsics
    if i is None or im.world_from_camera is None:
        return "no camera"
    if not (abs(i.k1) <= cfg.max_abs_distortion and abs(i.k2) <= cfg.max_abs_distortion):
        return f"lens distortion k1 = {i.k1:.3g}, k2 = {i.k2:.3g} (|k| > {cfg.max_abs_distortion:g})"
    if np.isfinite(focal_sigma_frac(im, cfg)):
        f0 = focal_prior(im, cfg)
        if not abs(i.f_px / f0 - 1) <= cfg.max_focal_deviation:
            return f"focal {i.f_px:.0f} px is {abs(i.f_px / f0 - 1):.0%} off its prior {f0:.0f} px"
    if np.isfinite(im.rms_px) and im.rms_px > cfg.max_rms_frac * im.width_px:
        return f"reprojection RMS {im.rms_px:.1f} px (> {cfg.max_rms_frac:.1%} of the width)"
    return ""


def prune_observations(recon: Reconstruction, idx: int, cfg: MapperConfig) -> int:
    """Detach registered image ``idx`` from the triangulated tracks (and model points) its camera does not see
    where they are: behind it, or reprojecting further than the observation threshold from its feature (matches
    on repeated texture chain a photo's features into other places' tracks). Returns how many were detached."""
    im = recon.images[idx]
    ft = recon.feature_track[idx]
    feats = np.nonzero(ft >= 0)[0]
    tr = ft[feats]
    fin = np.all(np.isfinite(recon.points[tr]), axis=1)
    feats, tr = feats[fin], tr[fin]
    if len(feats) == 0:
        return 0
    proj, z = cam.project_points(im.camera, cam.invert_rigid(im.pose), recon.points[tr])
    err = np.linalg.norm(proj - im.features.keypoints_px[feats], axis=1)
    bad = ~(np.isfinite(err) & (err < obs_threshold_px(im, cfg)) & (z > 0))
    for f, t in zip(feats[bad].tolist(), tr[bad].tolist(), strict=True):
        recon.track_obs[t].pop(idx, None)
        ft[f] = -1
    return int(bad.sum())
